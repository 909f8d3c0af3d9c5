"""`jaxcal plan`'s arguments. Its parser imports nothing of the planner (seconds): `plan` says
what it does first (`jaxcal.planning._cli.run_plan`)."""

import argparse

from .._argtypes import count, finite, positive, resolution
from .._configkeys import knob
from ..io._images import MAX_PIXELS, MAX_SIDE
from ._calibrate import TERMS, terms_arg

#: `sigma-px`'s default in `--help`: `jaxcal.planning.DEFAULT_SIGMA_PX` at 1280 px wide, growing as the
#: image narrows (`jaxcal.planning.sigma_for`; a test keeps them equal).
SIGMA_PX_HELP = (
    "detector corner noise, px (default: rendered captures' at the camera's image width, 0.045 at 1280 px, "
    "0.058 at 640: jaxcal.planning.sigma_for)"
)

#: Bounds of the options that size a plan's work and memory (the candidates' and the frames'
#: Jacobians are held at once): ten to twenty times their defaults.
MAX_FRAMES, MAX_CANDIDATES, MAX_STARTS, MAX_STEPS, MAX_BUDGET = 5000, 50_000, 100, 100_000, 1000


#: `--resolution`: `WxH` pixels, as the dataset reader takes them (`jaxcal.cli`'s type).
_RESOLUTION = resolution(MAX_SIDE, MAX_PIXELS)


def add_plan_parser(sub, func, cameras=("ideal",), arms=("ideal",)) -> None:
    """The `plan` subcommand's arguments (`func` runs it; `cameras`, `arms`: the preset names)."""
    p = sub.add_parser(
        "plan",
        help="plan, check and pre-evaluate a calibration capture before any image is taken (docs/plan.md)",
        description="Plan a pose-based calibration capture, or pre-evaluate a plan (--evaluate). Exit codes: 0 done; "
        "2 refused input (unreachable region, a camera that sees nothing, too small a budget, a malformed plan).",
    )
    p.add_argument("--evaluate", metavar="PLAN", help="pre-evaluate this plan file instead of planning")
    p.add_argument(
        "--check",
        metavar="RESULT",
        help="propose the --budget poses that make jaxcal check of this camera result most sensitive "
        "(--out: a CSV of them; --json: the figures)",
    )
    p.add_argument(
        "--budget",
        type=count(1, MAX_BUDGET),
        default=10,
        help=f"--check: the check capture's poses (at most {MAX_BUDGET})",
    )
    p.add_argument(
        "--robot", default="ur5e", help="shipped robot (ur5e, panda; revolute joints only) or a URDF file"
    )
    p.add_argument(
        "--camera-file",
        help="camera YAML (camera_matrix, image size, T_base_cam or T_flange_cam); default: the demo's camera "
        "at the taught pose",
    )
    p.add_argument(
        "--target", help="target JSON (spec, link, T_link_target); default: the demo's plate (board)"
    )
    p.add_argument(
        "--eye-in-hand", action="store_true", help="default layout: camera on the flange, board in the world"
    )
    knob(p, "--resolution", type=_RESOLUTION, default=(1280, 960), help="WxH pixels of the default camera")
    knob(p, "--distance", type=positive, help="default camera to target distance, m (0.9; eye-in-hand 0.6)")
    knob(p, "--taught", help="taught pose q1,q2,... (rad; default the robot's)")
    p.add_argument(
        "--frames",
        type=count(1, MAX_FRAMES),
        default=240,
        help=f"frames (stop-and-shoot poses), at most {MAX_FRAMES:,}",
    )
    p.add_argument("--out", help="the plan file to write (refused if it exists, unless --overwrite)")
    p.add_argument(
        "--overwrite", action="store_true", help="replace --out, --plot and --json (never an input)"
    )
    p.add_argument("--region", help="x0,y0,z0,x1,y1,z1: box (m, base frame) where EE accuracy matters")
    knob(p, "--sigma-px", type=finite, default=None, help=SIGMA_PX_HELP)
    p.add_argument(
        "--camera-model",
        choices=cameras,
        help="the camera model, as `jaxcal simulate --camera-model`: its corner noise (sensor noise, JPEG) joins "
        "sigma-px, and frames it would blur are left out (default: sigma-px alone)",
    )
    p.add_argument(
        "--arm",
        choices=arms,
        help="the arm model, as `jaxcal simulate --arm`: the EE bias its gravity sag, backlash and latency "
        "leave in the calibration is predicted beside the noise (default: a rigid arm, no bias; 'physics' is "
        "predicted from its compliance and lost motion, as 'realistic')",
    )
    p.add_argument(
        "--terms",
        type=_terms_arg,
        default=(),
        help="non-geometric joint terms the calibration will fit (as `jaxcal calibrate --terms`: compliance, "
        "backlash, harmonic1, harmonic2; comma-separated): planning, the poses are chosen so that the terms can "
        "be told from the geometry (gravity-torque variety, approaches from both sides); --evaluate, the "
        "prediction counts them and the arm's bias is what they leave, the bias without them beside",
    )
    knob(p, "--method", choices=("gradient", "greedy"), default="gradient")
    knob(p, "--baseline", action="store_true", help="also run the greedy D-optimal baseline")
    knob(p, "--starts", type=count(1, MAX_STARTS), default=3, help=f"gradient starts, at most {MAX_STARTS}")
    knob(p, "--steps", type=count(1, MAX_STEPS), default=150, help=f"gradient steps, at most {MAX_STEPS:,}")
    knob(
        p,
        "--candidates",
        type=count(1, MAX_CANDIDATES),
        default=2000,
        help=f"random poses drawn about the taught pose, at most {MAX_CANDIDATES:,}",
    )
    knob(p, "--amplitude-deg", type=finite, default=60.0, help="candidates within this of the taught pose")
    p.add_argument("--goal-mm", type=finite, help="regenerate wider while the predicted EE RMS is above this")
    knob(p, "--floor-z", type=finite, default=-0.6, help="floor height, m (base frame)")
    knob(p, "--view-angle-deg", type=finite, default=60.0, help="largest plate view angle")
    knob(p, "--no-mujoco", action="store_true", help="skip MuJoCo's contact and line-of-sight checks")
    p.add_argument("--seed", type=count(0, 2**32 - 1), default=0)
    p.add_argument("--plot", help="write the plan's predicted EE sigma plot (PNG) here")
    p.add_argument("--json", help="write the plan's predicted figures (JSON) here")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=func)


def _terms_arg(text: str) -> tuple[str, ...]:
    """`--terms`: the families the calibration will fit, named as `jaxcal calibrate --terms` names
    them, `none` included; not `auto`, which chooses from a capture's data, and a plan comes first."""
    if text.strip() == "auto":
        raise argparse.ArgumentTypeError(
            "'auto' chooses terms from a capture's data, which a plan comes before: name the families the "
            f"calibration will fit ({', '.join(TERMS)}), or none"
        )
    return terms_arg(text)
