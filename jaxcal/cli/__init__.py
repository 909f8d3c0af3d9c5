"""Command line: `jaxcal demo | calibrate | import-bag | inspect | simulate[-tracker|-plan] | plan | handeye | ...`.

- `demo`: render a perturbed UR5e filming a ChArUco plate (MuJoCo), calibrate
  it from the images, print a before/after table, write the report.
- `calibrate DATASET --out DIR`: images -> calibrated robot, camera pose, report (DATASET may be a ROS bag).
- `import-bag BAG --out DIR`: a ROS 1 / ROS 2 bag -> a dataset directory.
- `import-csv CSV --out DIR`: a table of joint positions and measured points -> a tracker dataset.
- `inspect DATASET|BAG`: what a capture holds (cameras, sweeps, clocks, detections, capture kind).
- `verify RESULT DATASET`: a stop-and-shoot calibration against samples it was not fitted on.
- `certify RESULT`: the tool-point accuracy a calibration supports over a task region.
- `check RESULT CAPTURE`: a short later capture against a calibration: drift detected or not (exit 3).
- `simulate`: render a synthetic camera dataset (see docs/dataset.md); `simulate-tracker`:
  laser-tracker sweeps; `simulate-plan PLAN`: render exactly a capture plan.
- `montecarlo`: vmapped sensitivity study on analytic marker poses.
- `handeye CAPTURE --out DIR`: classic hand-eye from a folder of images and robot poses.
- `simulate-handeye`: render a hand-eye capture (see docs/handeye.md).
"""

import argparse
import importlib
import logging
import os
import re
import shlex
import sys
from pathlib import Path

from .. import _configkeys as _config
from .. import _interrupt, distributed
from .._cache import enable_compilation_cache
from .._configkeys import knob
from ..fleet import is_fleet
from ._common import (
    EYE_IN_HAND_SWEEP,
    MAX_CAMERAS,
    MAX_FRAMES_PER_JOINT,
    MAX_MOTION_S,
    MAX_SAMPLES_PER_JOINT,
    count,
    degrees,
    finite,
    fmt_degrees,
    home,
    resolution,
    seconds,
    seed,
)


class DefaultsFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """argparse's defaults formatter, except where the help already says its default in words;
    the epilog (the configuration keys, `_config.epilog`) keeps its lines."""

    def _fill_text(self, text, width, indent):
        return "\n".join(indent + line for line in text.splitlines())

    def _get_help_string(self, action):
        text = action.help or ""
        if "default" in text.lower() or action.default is argparse.SUPPRESS or action.required:
            return text
        return super()._get_help_string(action)


def show_defaults(parser: argparse.ArgumentParser) -> None:
    """Every subcommand's `--help` shows every option's default (`DefaultsFormatter`)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                sub.formatter_class = DefaultsFormatter
                sub.epilog = _config.epilog(sub)
                for a in sub._actions:
                    if a.help is None and a.option_strings:  # an option nobody described: its name shows
                        a.help = a.dest.replace("_", " ")
                show_defaults(sub)


#: `jaxcal simulate --camera-model` (the names of `jaxcal.sim.camera.PRESETS`, which the CLI imports only to render).
CAMERAS = ("ideal", "global-shutter", "rolling-shutter")
#: `jaxcal simulate --arm` (the names of `jaxcal.sim.arm.ARM_PRESETS`).
ARMS = ("ideal", "realistic", "physics")


def _module(name: str):
    """A subcommand's module (`._calibrate`), imported when its parser is built: a command
    imports only what it runs (`build_parser`), not every other command's libraries."""
    return importlib.import_module(name, __package__)


def _add_simulate_common(p, *, robot_help: str | None) -> None:
    """The options every `jaxcal simulate*` command takes."""
    if robot_help is not None:
        p.add_argument("--robot", default=None, help=robot_help)
    p.add_argument("--out", required=True, help="dataset directory (must be empty or absent)")
    p.add_argument("--overwrite", action="store_true", help="replace a dataset jaxcal wrote")
    p.add_argument("--seed", type=seed, default=0)


def _add_simulate_parser(sub) -> None:
    """`jaxcal simulate`: a rendered camera dataset (MuJoCo)."""
    p = sub.add_parser(
        "simulate", help="render a perturbed arm's calibration dataset (MuJoCo) into a directory"
    )
    _add_simulate_common(
        p,
        robot_help="shipped robot (ur5e, ur3, panda, scara) or a URDF file (default ur5e); upper_body: the "
        "synthetic humanoid's head camera filming plates on both hands (a tree dataset)",
    )
    # The defaults film the demo's capture (EE RMS 0.19 mm refined; the former 640x480, 30 frames per
    # 40-degree sweep gave 1.2 mm): see docs/plan.md, and `simulate-plan` for a planned capture (0.04 mm).
    p.add_argument("--resolution", type=resolution, default=(1280, 960), help="WxH pixels")
    p.add_argument(
        "--frames-per-joint",
        type=count(2, MAX_FRAMES_PER_JOINT),
        default=40,
        help=f"frames per joint sweep, at most {MAX_FRAMES_PER_JOINT}",
    )
    p.add_argument(
        "--sweep-deg", type=degrees, default=80.0, help="angle each joint sweeps (deg), one or one per joint"
    )
    knob(p, "--sweep-mm", type=finite, default=100.0, help="travel each prismatic joint sweeps (mm)")
    knob(
        p,
        "--home-deg",
        type=home,
        default=None,
        help="the configuration every sweep starts from and the others hold, one angle per joint "
        "(deg, e.g. 0,-20,30,-15,20,0; default zero)",
    )
    knob(p, "--markers", choices=("charuco", "aruco"), default="charuco")
    knob(p, "--dictionary", default="DICT_4X4_50", help="OpenCV ArUco dictionary")
    p.add_argument(
        "--cameras",
        type=count(1, MAX_CAMERAS),
        default=1,
        help=f"fixed cameras (eye-to-hand), at most {MAX_CAMERAS}",
    )
    p.add_argument("--eye-in-hand", action="store_true", help="camera on the flange, board in the world")
    p.add_argument("--markers-on-links", action="store_true", help="a plate on every link too")
    p.add_argument(
        "--random-motion",
        type=seconds(MAX_MOTION_S),
        metavar="SECONDS",
        help="move every joint at once through random waypoints for this long, filmed throughout "
        f"(at most {MAX_MOTION_S:g} s; default: joint-by-joint sweeps); calibrated with --markers-on-links",
    )
    knob(p, "--motion-amplitude-deg", type=finite, default=25.0, help="random motion range, +- about zero")
    knob(p, "--clock-offset-ms", type=finite, default=0.0, help="camera clock minus controller clock")
    knob(p, "--clock-drift-ppm", type=finite, default=0.0)
    knob(p, "--clock-jitter-ms", type=finite, default=0.0)
    knob(p, "--unknown-clock-offset", action="store_true", help="leave the offset out of the metadata")
    knob(p, "--drop-rate", type=finite, default=0.0, help="probability that a frame is lost")
    knob(p, "--no-encoders", action="store_true", help="write no encoder log")
    knob(p, "--distortion", type=finite, nargs=5, default=[0.0] * 5, metavar=("K1", "K2", "P1", "P2", "K3"))
    _add_capture_models(p)
    p.set_defaults(func=_module("._simulate").cmd_simulate)


def _add_capture_models(p) -> None:
    """The camera and arm models and the image options a rendered capture takes (`simulate`,
    `simulate-plan`)."""
    knob(p, "--grayscale", action="store_true", help="write single-channel PNGs")
    p.add_argument(
        "--camera-model",
        choices=CAMERAS,
        default="ideal",
        help="the camera model (jaxcal.sim.camera): exposure, rolling shutter, sensor noise, JPEG; "
        "'ideal' takes each frame at one instant, noise-free",
    )
    p.add_argument(
        "--arm",
        choices=ARMS,
        default="ideal",
        help="the arm model (jaxcal.sim.arm): gravity compliance, backlash, encoder counts and latency; "
        "'ideal' is rigid with fine, prompt encoders; 'physics' moves the realistic arm with MuJoCo's dynamics "
        "(servos, compliant geared joints, the links' inertias, gravity; the encoders on the motors)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _add_simulate_tracker_parser(sub) -> None:
    """`jaxcal simulate-tracker`: laser-tracker sweeps of a point on the flange (no rendering)."""
    p = sub.add_parser(
        "simulate-tracker",
        help="laser-tracker samples of a perturbed arm's flange point, joint by joint (docs/dataset.md; "
        "no rendering)",
    )
    _add_simulate_common(
        p,
        robot_help="shipped robot (ur5e, ur3, panda, scara) or a URDF file (default ur3); upper_body: the "
        "synthetic humanoid, a tree whose two hands are measured at once (random-poses, default 500)",
    )
    p.add_argument(
        "--sweep-deg", type=degrees, default=None, help="angle each joint sweeps (deg; default 120)"
    )
    knob(
        p,
        "--home-deg",
        type=home,
        default=None,
        help="the configuration every sweep starts from (deg, one per joint; default 0,0,-90,0,90,0)",
    )
    knob(
        p,
        "--samples-per-joint",
        type=count(2, MAX_SAMPLES_PER_JOINT),
        default=300,
        help=f"samples per joint sweep, at most {MAX_SAMPLES_PER_JOINT:,}",
    )
    knob(
        p,
        "--random-poses",
        type=count(0, MAX_SAMPLES_PER_JOINT),
        default=0,
        help="stop-and-shoot poses drawn within the joint limits instead of the sweeps (0, the default: sweeps; "
        f"at most {MAX_SAMPLES_PER_JOINT:,})",
    )
    p.add_argument("--noise-um", type=finite, default=10.0, help="position noise, 1-sigma per axis (um)")
    knob(
        p, "--bad-fraction", type=finite, default=0.02, help="bad samples (0.3-0.5 mm off) at the sweep ends"
    )
    p.add_argument("--device-is-base", action="store_true", help="the device frame is the robot's base frame")
    p.add_argument("--orientation", action="store_true", help="also measure an orientation (6-DoF probe)")
    p.add_argument(
        "--quiet", action="store_true", help="print only the summary line (there is no progress bar)"
    )
    p.set_defaults(
        func=_module("._simulate").cmd_simulate_tracker,
        foreign="{options}: not options of tracker data, which have no images or cameras (jaxcal simulate "
        "renders those)",
    )


def _add_simulate_plan_parser(sub) -> None:
    """`jaxcal simulate-plan PLAN`: render exactly a capture plan."""
    p = sub.add_parser(
        "simulate-plan", help="render exactly a capture plan (docs/plan.md): its camera, target and motion"
    )
    p.add_argument("plan", help="the plan file (`jaxcal plan --out`)")
    _add_simulate_common(p, robot_help=None)
    _add_capture_models(p)
    p.set_defaults(
        func=_module("._simulate").cmd_simulate_plan,
        foreign="{options} cannot change a plan (its robot, camera, target and motion are the plan's); drop "
        "them or edit the plan",
    )


def _add_calibration_parsers(sub) -> None:
    """`jaxcal demo` and `jaxcal calibrate`."""
    calibrate, rosbag = _module("._calibrate"), _module("._rosbag")
    p = sub.add_parser(
        "demo", help="render a perturbed UR5e, calibrate it from the images, show before/after"
    )
    p.add_argument("--out", default="jaxcal-demo", help="where the dataset and the results go")
    p.add_argument("--seed", type=seed, default=0)
    knob(p, "--resolution", type=resolution, default=(1280, 960), help="WxH pixels")
    knob(
        p,
        "--frames-per-joint",
        type=count(2, MAX_FRAMES_PER_JOINT),
        default=40,
        help=f"frames per joint sweep, at most {MAX_FRAMES_PER_JOINT}",
    )
    knob(
        p,
        "--sweep-deg",
        type=degrees,
        default=None,
        help="angle each joint sweeps (deg), one or one per joint (default 80; eye-in-hand "
        + fmt_degrees(EYE_IN_HAND_SWEEP)
        + ")",
    )
    p.add_argument(
        "--cameras",
        type=count(1, MAX_CAMERAS),
        default=1,
        help=f"fixed cameras filming the arm, at most {MAX_CAMERAS}",
    )
    p.add_argument(
        "--eye-in-hand", action="store_true", help="the camera on the flange, a ChArUco board in the world"
    )
    p.add_argument(
        "--markers-on-links",
        action="store_true",
        help="a plate on every link, every joint moving at once (random waypoints, as many frames as the "
        "sweeps would take); sequential initialisation, then the refinement",
    )
    p.add_argument(
        "--camera-model",
        choices=CAMERAS,
        default="ideal",
        help="the camera model, as `jaxcal simulate --camera-model` (e.g. global-shutter: 2 ms exposure, sensor noise)",
    )
    p.add_argument(
        "--arm",
        choices=ARMS,
        default="ideal",
        help="the arm model, as `jaxcal simulate --arm` (realistic: gravity compliance, backlash, encoder counts; "
        "physics: the same arm under MuJoCo's dynamics)",
    )
    calibrate.add_calibrate_args(p, demo=True)
    p.set_defaults(func=calibrate.cmd_demo)
    p = sub.add_parser("calibrate", help="calibrate robot and camera from a dataset (docs/dataset.md)")
    p.add_argument(
        "dataset",
        help="dataset directory, or a ROS bag (with --images, --joints, --robot, --target), or a folder of "
        "datasets (a fleet: one result per unit and the fleet's summary, docs/fleet.md)",
    )
    p.add_argument(
        "more", nargs="*", metavar="DATASET", help="more datasets: a fleet of units of one robot model"
    )
    p.add_argument(
        "--out",
        required=True,
        help="result directory: absent or empty, never the dataset, inside it or around it",
    )
    p.add_argument("--overwrite", action="store_true", help="replace a result directory jaxcal wrote")
    p.add_argument(
        "--device-is-base",
        action="store_true",
        help="tracker data: the measuring device's frame is the robot's base frame (T_device_base = identity, "
        "not estimated; makes the base height d1 identifiable)",
    )
    calibrate.add_calibrate_args(p)
    rosbag.add_bag_args(p, required=False)
    p.set_defaults(func=calibrate.cmd_calibrate)


def _add_import_bag_parser(sub) -> None:
    rosbag = _module("._rosbag")
    p = sub.add_parser(
        "import-bag", help="convert a ROS 1 / ROS 2 bag into a dataset directory (docs/dataset.md)"
    )
    p.add_argument("bag", help="ROS 1 .bag file, or ROS 2 bag directory (sqlite3 or MCAP)")
    p.add_argument("--out", required=True, help="dataset directory (absent or empty)")
    p.add_argument("--overwrite", action="store_true", help="replace a dataset jaxcal wrote")
    rosbag.add_bag_args(p, required=True)
    p.set_defaults(func=rosbag.cmd_import_bag)


def _add_montecarlo_parser(sub) -> None:
    p = sub.add_parser("montecarlo", help="vmapped Monte Carlo sensitivity study (analytic marker poses)")
    study = _module("._study")
    study.add_study_args(p, trials=1000)
    p.add_argument("--json", help="write the summary here (atomically)")
    knob(p, "--detail", action="store_true", help="first show one trial in detail")
    p.set_defaults(func=study.cmd_montecarlo)


#: The subcommands in `--help`'s order, by the function adding their parsers.
GROUPS = (
    (("demo", "calibrate"), _add_calibration_parsers),
    (("import-bag",), _add_import_bag_parser),
    (("montecarlo",), _add_montecarlo_parser),
    (("simulate",), _add_simulate_parser),
    (("simulate-tracker",), _add_simulate_tracker_parser),
    (("simulate-plan",), _add_simulate_plan_parser),
    (("inspect",), lambda sub: _module("._inspect").add_inspect_parser(sub)),
    (("import-csv",), lambda sub: _module("._import_csv").add_import_csv_parser(sub)),
    (("verify",), lambda sub: _module("._verify").add_verify_parser(sub)),
    (("certify", "check"), lambda sub: _module("._certify").add_certify_parsers(sub)),
    (("handeye", "simulate-handeye"), lambda sub: _module("._handeye").add_handeye_parsers(sub)),
    (
        ("plan",),
        lambda sub: _module("._plan").add_plan_parser(sub, _module("._simulate").cmd_plan, CAMERAS, ARMS),
    ),
)


class _Parser(argparse.ArgumentParser):
    """argparse, whose errors in a subcommand name first the options it does not take, each with
    the closest one it does (a misspelt `--ouput` is not reported as a missing `--out`)."""

    #: The words this parser was last given (a subcommand's parser gets the words after its
    #: name): argparse's `error` is not given them.
    argv: tuple[str, ...] = ()

    def parse_known_args(self, args=None, namespace=None):
        self.argv = tuple(sys.argv[1:] if args is None else args)
        return super().parse_known_args(args, namespace)

    def unknown_options(self) -> list[str]:
        words = self.argv[: self.argv.index("--")] if "--" in self.argv else self.argv
        options = [w.split("=")[0] for w in words if w.startswith("-") and not _NUMBER.match(w)]
        return [o for o in dict.fromkeys(options) if o not in self._option_string_actions]

    def error(self, message):
        unknown = self.unknown_options() if " " in self.prog else []  # a subcommand's parser
        if unknown:
            import difflib

            known = [o for o in self._option_string_actions if o.startswith("--")]
            keys = ["--" + k for k in _config.keys(self)]
            named = []
            for o in unknown:
                close = difflib.get_close_matches(o, known + keys, n=1, cutoff=0.6)
                if close and close[0] in keys:
                    key = close[0][2:]
                    named.append(f"{o} (did you mean the configuration key {key}: --config {key}=VALUE?)")
                else:
                    named.append(o + (f" (did you mean {close[0]}?)" if close else ""))
            first = f"{self.prog} takes no option {', '.join(named)}; see {self.prog} --help"
            message = first if message.startswith("unrecognized arguments") else f"{first}. Also: {message}"
        super().error(message)


_NUMBER = re.compile(r"^-\d+$|^-\d*\.\d+(e[-+]?\d+)?$", re.IGNORECASE)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The `jaxcal` argument parser: with every subcommand, or with only `command`'s
    (and those sharing its module, `GROUPS`), so that a run imports only the
    modules of the command it runs."""
    parser = _Parser(prog="jaxcal", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    known = any(command in names for names, _ in GROUPS)
    for names, add in GROUPS:
        if not known or command in names:
            add(sub)
    show_defaults(parser)
    return parser


#: Converters of one vocabulary that differ in what a command can use: `plan --terms` takes the
#: term families `calibrate --terms` takes, but not `auto` (which chooses from a capture's data, and
#: a plan comes before any capture).
SAME_VOCABULARY = {"_terms_arg": "terms_arg"}


def subcommands() -> dict[str, argparse.ArgumentParser]:
    """Every subcommand's parser, by name."""
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def option_meanings(*, keys: bool = True) -> dict[str, dict[str, tuple]]:
    """Per long option name, per subcommand taking it, what the option is apart from its help
    text and default: the kind of action, the type converting its value (by its qualified name:
    `count(1, N)` and `count(3, M)` are one type with other bounds), its choices and how many
    values it takes; with `keys`, the configuration keys too, by their flag's spelling
    (`_config`: a key is converted as the flag it replaced). One name, one meaning:
    `tests/test_cli_vocabulary.py`."""
    out: dict[str, dict[str, tuple]] = {}
    for command, parser in subcommands().items():
        knobs = _config.knobs_of(parser)
        actions = parser._actions + (knobs._actions if keys and knobs is not None else [])
        for action in actions:
            kind = getattr(action.type, "__qualname__", action.type)
            meaning = (
                type(action).__name__,
                SAME_VOCABULARY.get(kind, kind),
                tuple(action.choices or ()),
                action.nargs,
            )
            for name in action.option_strings:
                if name.startswith("--") and name != "--help":
                    out.setdefault(name, {})[command] = meaning
    return out


def _command(argv: list[str]) -> str | None:
    """The subcommand `argv` names: its first word that is not an option."""
    return next((a for a in argv if not a.startswith("-")), None)


#: Options whose value is a comma-separated list of numbers that may start with a minus.
NUMBER_LISTS = (
    "--region",
    "--taught",
    "--home-deg",
    "--sweep-deg",
    "--point-mm",
    "--point-rotvec-deg",
    "--joint-box",
)
_NEGATIVE_LIST = re.compile(r"^-\.?\d[\d.eE+:-]*(,[-+]?[\d.eE+:-]+)*$")


def _join_negative_lists(argv: list[str]) -> list[str]:
    """`--region -0.5,...` as `--region=-0.5,...`: argparse takes a value that starts
    with a minus for an option of its own."""
    out, i = [], 0
    while i < len(argv):
        if argv[i] in NUMBER_LISTS and i + 1 < len(argv) and _NEGATIVE_LIST.match(argv[i + 1]):
            out.append(f"{argv[i]}={argv[i + 1]}")
            i += 2
        else:
            out.append(argv[i])
            i += 1
    return out


#: Option spellings that meant something else in another subcommand, renamed so that one option
#: name has one meaning everywhere (`tests/test_cli_vocabulary.py`); the old spelling still works
#: for one release, with a warning. `(command, old): new`.
RENAMED = {
    ("simulate", "--camera"): "--camera-model",
    ("simulate-plan", "--camera"): "--camera-model",
    ("plan", "--camera"): "--camera-file",
    ("montecarlo", "--frames"): "--frames-per-joint",
    ("import-csv", "--joints"): "--joint-columns",
    ("import-csv", "--orientation"): "--orientation-columns",
    ("simulate-handeye", "--target"): "--target-kind",
}


def _renamed(argv: list[str]) -> list[str]:
    """`argv` with the old spellings of `RENAMED` (and `inspect`'s bare `--json`, now
    `--json -`) written the new way, each named in a warning on stderr."""
    command = _command(argv)
    out = []
    for k, a in enumerate(argv):
        name, eq, value = a.partition("=")
        new = RENAMED.get((command, name))
        if new is not None:
            note = f"`jaxcal {command} {name}` is now `{new}`; {name} goes in the next release"
            print(f"jaxcal: warning: {note}", file=sys.stderr)
            a = new + eq + value
        elif command == "inspect" and a == "--json" and _bare(argv[k + 1 :]):
            print(
                "jaxcal: warning: `jaxcal inspect --json` is now `--json -` (or `--json FILE`)",
                file=sys.stderr,
            )
            out.append("--json=-")
            continue
        out.append(a)
    return out


def _bare(rest: list[str]) -> bool:
    """Whether `inspect --json` followed by `rest` is the old flag: nothing or another option
    follows, or the dataset (a folder, never a JSON file to write)."""
    return not rest or (rest[0].startswith("-") and rest[0] != "-") or Path(rest[0]).is_dir()


#: Every subcommand's name (`GROUPS`): a `--config` file's tables.
COMMANDS = tuple(name for names, _ in GROUPS for name in names)


def _subparser(parser: argparse.ArgumentParser, command: str | None) -> argparse.ArgumentParser | None:
    """`command`'s parser within `parser`, or None (no such subcommand: argparse says so)."""
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices.get(command)


def _refusal(parser: argparse.ArgumentParser, args, unknown: list[str]) -> str | None:
    """The one policy for options another command takes: named and refused (exit 2), with the
    command's reason (its `foreign` default, a template of `{options}`) where it has one."""
    if not unknown:
        return None
    options = [a.split("=")[0] for a in unknown if a.startswith("-")]
    reason = getattr(args, "foreign", None)
    if reason is None or not options:
        subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        subparsers.choices[args.command].error("unrecognized arguments: " + " ".join(unknown))
    what = f"jaxcal {args.command}" + (f" {args.plan}" if getattr(args, "plan", None) else "")
    return f"{what}: " + reason.format(options=", ".join(options))


class Refused(ValueError):
    """A command line refused before any work: the message says why (exit 2)."""


def parse(argv: list[str]) -> argparse.Namespace:
    """The namespace `argv`'s command runs on: the old spellings rewritten (with a warning),
    the subcommand's options parsed, then its configuration (`--config`, and the flags the keys
    replaced) applied (`_config`). `Refused` names what cannot be used; argparse's own errors
    exit as argparse does. The namespace keeps `argv` as given (`_argv`: `run_record`)."""
    given = list(argv)
    argv = _renamed(_join_negative_lists(given))
    command = _command(argv)
    parser = build_parser(command)
    chosen = _subparser(parser, command)
    argv, moved = _config.extract_moved(chosen, command, argv) if chosen is not None else (argv, [])
    args, unknown = parser.parse_known_args(argv)
    refusal = _refusal(parser, args, unknown)
    if refusal is not None:
        raise Refused(refusal)
    try:
        _config.apply(chosen, args, COMMANDS, moved)
    except _config.ConfigError as e:
        raise Refused(f"jaxcal: error: {e}") from None
    args._argv = given
    return args


def main(argv: list[str] | None = None) -> int:
    try:
        args = parse(sys.argv[1:] if argv is None else argv)
    except Refused as e:
        print(e, file=sys.stderr)
        return 2
    enable_compilation_cache()
    try:
        _join(args, sys.argv[1:] if argv is None else argv)
        return args.func(args)
    except (ValueError, OSError) as e:
        _stopped(str(e))
        print(f"jaxcal: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # what was being written is gone (`jaxcal.io._files`)
        _stopped("interrupted")
        if not _interrupt.interrupted():  # not the command line's own handling (`run`): as Python does
            raise
        return _interrupt.report()
    except BaseException as e:
        _stopped(f"{type(e).__name__}: {e}")
        raise


#: The commands that share their work over the processes of a distributed run (`jaxcal.distributed`).
DISTRIBUTED = ("montecarlo", "calibrate")


def _join(args, argv: list[str]) -> None:
    """Join the distributed run the environment asks for (`jaxcal.distributed`), before any work;
    refused by the commands that run in one process, and where the processes were not all given
    the same command line."""
    count = distributed.requested()
    if count == 1:
        return
    if args.command not in DISTRIBUTED or (
        args.command == "calibrate" and not is_fleet([args.dataset, *args.more])
    ):
        what = (
            f"jaxcal {args.command}"
            if args.command != "calibrate"
            else f"calibrating one dataset ({args.dataset})"
        )
        raise ValueError(
            f"{what} runs in one process, and the environment asks for {count} "
            f"({distributed.PROCESSES} or SLURM's {distributed.SLURM_TASKS}): start one, or run "
            f"{' or '.join(DISTRIBUTED)} (a fleet: several datasets, or a folder of them) over several"
        )
    processes = distributed.join()
    lines = processes.gather(argv)
    other = next((i for i, line in enumerate(lines) if line != argv), None)
    if other is not None:
        raise ValueError(
            f"the processes of a distributed run must run one command line; process {processes.index} of "
            f"{processes.count} has `jaxcal {shlex.join(argv)}`, process {other} `jaxcal {shlex.join(lines[other])}`"
        )


def _stopped(why: str) -> None:
    """In a distributed run, tell the other processes that this one stopped (they stop too)."""
    distributed.current().fail(why)


def run() -> None:
    """The `jaxcal` command (and `python -m jaxcal`): `main()`, then the process ends as soon
    as its outputs are out. A command writes and closes everything it writes (atomically)
    before `main` returns; what Python's shutdown would do next, tearing down JAX's backend
    and its compiled programs, costs most of a second of a warm `jaxcal calibrate` and saves
    nothing. A program still compiling ahead (a run that stopped early) is waited for, and
    JAX's pending effects; an exception (argparse's exit included) ends the process as usual.
    Ctrl-C (SIGINT) ends it within `jaxcal._interrupt.STOP_S` seconds, exit 130, leaving nothing
    behind (`jaxcal._interrupt`): nothing is waited for then."""
    _interrupt.install()
    code = main()
    if not _interrupt.interrupted():
        programs = sys.modules.get("jaxcal.stages._programs")
        if programs is not None:
            programs.wait_ahead()
        if "jax" in sys.modules:
            sys.modules["jax"].effects_barrier()
    distributed.leave()  # a distributed run's processes end together
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    run()
