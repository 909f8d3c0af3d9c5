"""`jaxcal.plan` and `jaxcal.evaluate_plan`: a capture planned, checked and pre-evaluated.

`plan` follows seed 002 and goes past it: generate poses about a taught pose,
check each (named reasons) and move the failing ones toward the taught pose or
drop them, then choose the frames by gradient descent on the predicted
end-effector error of the refinement that will solve them, from several starts
(`method="greedy"`: FIGAROH's greedy D-optimal selection from the same
candidates instead), order them into a short tour, check the moves, and
pre-evaluate the result; with `goal_mm`, regenerate with wider candidates while
the prediction falls short.
"""

import time
from collections import Counter
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .._correction import zero_correction
from .._progress import working
from .._terms import approach, approach_at, check_terms
from .._uncertainty import random_configurations, tool_points
from ..errors import BudgetTooSmallError, CameraViewError, PlanError, PlanFileError, UnreachableRegionError
from ..io.plan import CapturePlan, Correction, PlanCamera, PlanTarget, PoseSet, Sweep
from ..io.urdf import load_urdf, urdf_outline
from ..records_capture import ArmFigures, CameraNoise
from ..robots import link_inertials, robot_path, shipped
from ._evaluate import (
    PlanEvaluation,
    TermInputs,
    design,
    ee_gram,
    ee_jacobians,
    evaluate_views,
    sigma_for,
)
from ._layout import default_layout
from ._optimise import (
    TermModel,
    candidate_poses,
    correct_toward,
    descend,
    greedy_d_optimal,
    order_poses,
    path_clear,
    view_blocks,
)
from ._plan import load_plan
from ._realism import capture_terms
from ._scene import CHECKS, FeasibilityLimits, PlanScene, explain, make_scene, plate_box

#: Workspace configurations of the EE prediction (the validation's sample: 1000, seed 0).
WORKSPACE = 1000
#: Fewest frames of a pose plan: the hand-eye start needs three.
MIN_POSES = 3


@dataclass(frozen=True)
class Robot:
    """A robot for planning: its name or URDF path, the nominal model and commanded joint limits."""

    source: str
    model: object
    lower: np.ndarray
    upper: np.ndarray

    @classmethod
    def load(cls, robot: str) -> "Robot":
        path = robot_path(robot) if robot in shipped() else Path(robot)
        if not path.is_file():
            raise PlanError(f"robot {robot!r} is neither a shipped robot ({shipped()}) nor a URDF file")
        model = load_urdf(path)
        prismatic = [j for j, kind in zip(model.joint_names, model.joint_types) if kind != "revolute"]
        if prismatic:
            raise PlanError(
                f"robot {robot!r}: capture planning handles revolute joints only, and {prismatic} are "
                "prismatic; plan the sweeps by hand (jaxcal simulate --config sweep-mm=MM renders them)"
            )
        limits = urdf_outline(path, model.joint_names).limits
        lower = np.array([-np.inf if limits[j].lower is None else limits[j].lower for j in model.joint_names])
        upper = np.array([np.inf if limits[j].upper is None else limits[j].upper for j in model.joint_names])
        return cls(str(robot), model, lower, upper)


def scene_of(robot: Robot, camera: PlanCamera, target: PlanTarget, floor_z, where: str = "plan") -> PlanScene:
    """The planning scene of a camera and target on `robot` (checks the mounts name the flange or the world)."""
    flange = robot.model.link_names[-1]
    eye_in_hand = camera.mount != "world"
    if eye_in_hand and camera.mount != flange:
        raise PlanFileError(
            f"{where}: camera.mount must be 'world' or the flange {flange!r}, got {camera.mount!r}"
        )
    if not eye_in_hand and target.link != flange:
        raise PlanFileError(
            f"{where}: target.link must be the flange {flange!r} (a fixed camera films it), "
            f"got {target.link!r}"
        )
    spec = target.spec
    T_fixed = np.linalg.inv(target.T_link_target) if eye_in_hand else np.linalg.inv(camera.T_mount_cam)
    T_mount = camera.T_mount_cam if eye_in_hand else target.T_link_target
    return make_scene(
        robot.model,
        K=camera.K,
        dist=camera.distortion,
        image=(camera.width, camera.height),
        T_fixed=T_fixed,
        T_mount=T_mount,
        points=spec.points(),
        normal=spec.front_normal(),
        lower=robot.lower,
        upper=robot.upper,
        eye_in_hand=eye_in_hand,
        plate=plate_box(spec),
        floor_z=floor_z,
    )


def workspace(robot: Robot, scene: PlanScene, region=None, key=None) -> np.ndarray:
    """The configurations the EE prediction averages over: the validation's 1000
    (uniform in $[-\\pi, \\pi]$ per joint, seed 0), or with `region = (lo, hi)`
    (base frame, m) up to 1000 configurations within the joint limits whose EE
    point lies in that box (`UnreachableRegionError` when none does)."""
    n = robot.model.num_joints
    if region is None:
        return np.asarray(random_configurations(jax.random.key(0), WORKSPACE, n))
    lo, hi = (np.asarray(v, np.float64).reshape(3) for v in region)
    if not np.all(hi > lo):
        raise UnreachableRegionError(
            f"region: the box's upper corner {hi.tolist()} must exceed its lower {lo.tolist()}"
        )
    box = f"region [{', '.join(f'{v:g}' for v in lo)}] .. [{', '.join(f'{v:g}' for v in hi)}] (m, base frame)"
    floor = float(scene.floor_z)
    if hi[2] <= floor:
        raise UnreachableRegionError(
            f"{box}: it lies wholly below the floor at z = {floor:g} m; give a region above it"
        )
    a, b = np.maximum(robot.lower, -np.pi), np.minimum(robot.upper, np.pi)
    key = jax.random.key(0) if key is None else key
    q = np.asarray(jax.random.uniform(key, (200_000, n), minval=a, maxval=b))
    corr = zero_correction(n, 1)
    T_base = np.eye(4)
    p = np.asarray(_points(scene, T_base, corr, jnp.asarray(q)))
    inside = np.all((p >= lo) & (p <= hi), axis=1)
    if inside.sum() < 10:
        raise UnreachableRegionError(
            f"{box}: the {'camera' if scene.eye_in_hand else 'target'} reaches it in {int(inside.sum())} of {len(q)} "
            "random configurations within the joint limits; give a region the arm can reach"
        )
    return q[inside][:WORKSPACE]


@jax.jit
def _points(scene, T_base, corr, q):
    return tool_points(scene.nominal, T_base, scene.T_mount[None], jnp.zeros(6), corr, q)


def plan_robot(plan: CapturePlan, where: str = "plan") -> Robot:
    """The plan's robot, checked against the plan: the same joints, and every commanded
    configuration (the taught pose and every frame) inside the robot's joint limits
    (`PlanFileError` naming the segment, frame and joint)."""
    robot = Robot.load(plan.robot)
    if tuple(robot.model.joint_names) != tuple(plan.joints):
        raise PlanFileError(
            f"{where}: joints {list(plan.joints)} are not robot {plan.robot!r}'s {list(robot.model.joint_names)}"
        )
    q, _, segment = plan.views()
    q = np.concatenate([np.asarray(plan.taught, np.float64)[None], q])
    outside = (q < robot.lower - 1e-9) | (q > robot.upper + 1e-9)
    if outside.any():
        i, j = (int(k[0]) for k in np.nonzero(outside))
        s = int(segment[i - 1]) if i else -1
        what = "taught" if i == 0 else f"segments[{s}] frame {int(np.sum(segment[: i - 1] == s))}"
        raise PlanFileError(
            f"{where}: {what}: joint {plan.joints[j]} = {q[i, j]:.4f} rad is outside its limits "
            f"[{robot.lower[j]:.4f}, {robot.upper[j]:.4f}] (robot {plan.robot!r})"
        )
    return robot


def views(plan: CapturePlan) -> tuple[np.ndarray, np.ndarray, bool]:
    """The frames of `plan`: configurations, times and whether it is a plan of sweeps."""
    q, t, _ = plan.views()
    sweeps = any(isinstance(s, Sweep) for s in plan.segments)
    return q, t, sweeps


def evaluate_plan(
    plan: "CapturePlan | str | Path",
    *,
    region=None,
    sigma_px: float | None = None,
    limits: FeasibilityLimits | None = None,
    camera_model: CameraNoise | None = None,
    arm: ArmFigures | None = None,
    terms: tuple[str, ...] = (),
) -> PlanEvaluation:
    """Predict, before any capture, what the refinement will make of `plan`.

    **Arguments:**
    - `plan`: a `CapturePlan` or a plan file.
    - `region`: `(lo, hi)` corners of a box in the base frame (m) where the EE
      accuracy matters (default: the validation's 1000 random configurations).
    - `sigma_px`: the detector's corner noise (px per coordinate; default: rendered captures' at the
      plan camera's image width, `sigma_for`).
    - `limits`: the feasibility limits (default the plan's own `checks`): frames
      that fail them are left out, as the detector would miss them.
    - `camera_model`, `arm`: the capture's camera and arm (`jaxcal.records_capture`;
      `jaxcal.sim.camera.PRESETS[name].noise_record()`,
      `jaxcal.sim.arm.ARM_PRESETS[name].figures()`): the camera's corner noise is
      added to `sigma_px`, frames it would blur are left out, and the arm's sag,
      backlash and latency give the EE bias (`jaxcal.planning._realism`).
    - `terms`: non-geometric terms the refinement fits beside the geometry
      (`jaxcal._terms`; the calibration's `terms`): the prediction counts what telling
      them from the geometry costs, and the arm's bias is what they leave (the bias
      without them beside: `PlanEvaluation.ee_bias_rigid`).

    **Returns:** a `PlanEvaluation` (per-parameter standard deviations, what is
    left unidentifiable, the EE 1-sigma at every workspace configuration, its
    RMS and 95th percentile). Raises `PlanFileError`, `UnreachableRegionError`,
    `BudgetTooSmallError`.
    """
    where = str(plan) if isinstance(plan, (str, Path)) else "plan"
    plan = load_plan(plan) if isinstance(plan, (str, Path)) else plan
    robot = plan_robot(plan, where)
    scene = scene_of(robot, plan.camera, plan.target, plan.floor_z, where)
    sigma_px = sigma_for(plan.camera.width, sigma_px)
    limits = FeasibilityLimits(**plan.checks) if limits is None else limits
    q, t, sweeps = views(plan)
    _, fraction, reasons = correct_toward(scene, limits, plan.taught, q)
    m = fraction == 1.0
    failing = "" if m.all() else _infeasible(scene, limits, q, reasons, plan.robot)
    if m.sum() < MIN_POSES:
        raise BudgetTooSmallError(f"plan: {failing}; at least {MIN_POSES} frames are needed")
    lost = {"frames_infeasible": int(np.sum(~m)), "infeasible_note": failing}
    if camera_model is None and arm is None:
        ev = evaluate_views(
            scene,
            q[m],
            t[m],
            workspace(robot, scene, region),
            sweeps=sweeps,
            sigma_px=sigma_px,
            terms=term_inputs(plan, robot, t[m], terms),
        )
        return replace(ev, **lost)
    q, t = q[m], t[m]
    kept, offsets, joint_std, note = capture_terms(
        plan, robot.source, scene, q, t, camera_model, arm, design(scene, sweeps).kind.single_joint_sweeps
    )
    if kept.sum() < MIN_POSES:
        raise BudgetTooSmallError(f"plan: {note}; fewer than {MIN_POSES} frames are left")
    added = 0.0 if camera_model is None else float(camera_model.added_sigma_px)
    ev = evaluate_views(
        scene,
        q[kept],
        t[kept],
        workspace(robot, scene, region),
        sweeps=sweeps,
        sigma_px=float(np.hypot(sigma_px, added)),
        offsets=offsets,
        joint_std=joint_std,
        terms=term_inputs(plan, robot, t[kept], terms),
    )
    return replace(
        ev,
        camera_model=None if camera_model is None else camera_model.name,
        arm_model=None if arm is None else arm.name,
        added_sigma_px=added,
        camera_note=note,
        frames_lost_to_blur=int(np.sum(~kept)),
        **lost,
    )


def _infeasible(scene: PlanScene, limits: FeasibilityLimits, q: np.ndarray, reasons: list, robot: str) -> str:
    """How many of a plan's frames `q` fail the feasibility checks (`reasons`: each frame's first
    failing check, None where it passes), how many fail each check, and why the first does
    (`explain`): a plan made for another robot or scene fails many."""
    failed = [i for i, r in enumerate(reasons) if r is not None]
    counts = Counter(reasons[i] for i in failed)
    per_check = ", ".join(f"{k} {n}" for k, n in counts.most_common())
    return (
        f"{len(failed)} of its {len(q)} frames fail the feasibility checks on robot {robot!r} and are left "
        f"out ({per_check}; frame {failed[0]}: {explain(scene, limits, q[failed[0]])}); were they planned for "
        "this robot and layout?"
    )


def term_inputs(plan: CapturePlan, robot: Robot, t: np.ndarray, terms) -> TermInputs | None:
    """The `TermInputs` of frames at controller times `t` of `plan` (None without `terms`): the
    robot file's masses and every frame's approach flank along the plan's commanded motion."""
    terms = check_terms(terms)
    if not terms:
        return None
    masses, coms = link_inertials(robot.source) if {"compliance", "backlash"} & set(terms) else (None, None)
    n = robot.model.num_joints
    m = plan.motion()
    return TermInputs(
        terms,
        np.zeros(n) if masses is None else masses,
        np.zeros((n, 3)) if coms is None else coms,
        approach_at(m.times, m.q, np.asarray(t, np.float64)),
    )


@dataclass(frozen=True, eq=False)
class PlanResult:
    """What `plan` made: the `plan`, its `evaluation`, the `greedy` baseline's
    evaluation at the same budget (when run), the candidate `counts` (first
    failing check per draw), and `timings` (s)."""

    plan: CapturePlan
    evaluation: PlanEvaluation
    greedy: PlanEvaluation | None = None
    counts: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)


#: Taught poses of the shipped robots (commanded, rad): the UR5e's zero (the
#: demo's), a Panda pose inside its limits with the flange facing sideways.
TAUGHT = {
    "ur5e": (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    "panda": (0.0, -0.3, 0.0, -2.0, 0.0, 1.7, 0.785),
}


def _taught(robot: Robot, taught) -> np.ndarray:
    n = robot.model.num_joints
    if taught is None:
        taught = TAUGHT.get(
            Path(robot.source).stem if robot.source not in TAUGHT else robot.source, np.zeros(n)
        )
    q0 = np.asarray(taught, np.float64).reshape(-1)
    if q0.shape != (n,):
        raise PlanError(
            f"taught pose: expected {n} joint values ({list(robot.model.joint_names)}), got {q0.size}"
        )
    return q0


def _check_taught(scene, limits, q0, checker) -> None:
    _, frac, why = correct_toward(scene, limits, q0, q0[None], checker)
    if frac[0] != 1.0:
        detail = explain(scene, limits, q0) or f"fails the {why[0]!r} check"  # None: MuJoCo's verdict alone
        hint = (
            "the camera must see the target at the taught pose (move the camera, or teach another pose)"
            if why[0] in ("distance", "view_angle", "in_image", "corner_spacing", "occlusion")
            else "teach another pose"
            + (", or check the floor height, --config floor-z=M" if why[0] == "scene_collision" else "")
        )
        raise CameraViewError(f"taught pose {np.round(q0, 4).tolist()}: {detail}; {hint}")


def _budget(scene: PlanScene, frames: int, sweeps: bool) -> None:
    need = int(design(scene, sweeps).candidates.sum())
    rows = 2 * scene.points.shape[0] * frames
    if frames < MIN_POSES or rows < need:
        raise BudgetTooSmallError(
            f"--frames {frames}: too few to identify anything: a pose plan needs at least {MIN_POSES} frames, and "
            f"{frames} frames of {scene.points.shape[0]} corners give {rows} equations for up to {need} unknowns"
        )


def _pick(cands: np.ndarray, frames: int, rng: np.random.Generator) -> np.ndarray:
    idx = rng.choice(len(cands), frames, replace=len(cands) < frames)
    q = cands[idx]
    if len(cands) < frames:  # repeated candidates would move together: part them
        q = q + rng.normal(0.0, 0.01, q.shape)
    return q


def _finish(scene, limits, q0, q, checker) -> tuple[np.ndarray, list[Correction]]:
    """Correct toward the taught pose (or drop), order into a tour, drop poses whose move collides."""
    qn, frac, why = correct_toward(scene, limits, q0, q, checker)
    corrections = [
        Correction(0, i, "moved" if f > 0 else "dropped", why[i], float(f))
        for i, f in enumerate(frac)
        if f < 1.0
    ]
    keep = np.flatnonzero(frac > 0)
    order = keep[order_poses(q0, qn[keep])]
    out, here = [], np.asarray(q0, np.float64)
    for i in order:
        ok = path_clear(scene, limits, here, qn[i])
        if ok and checker is not None:
            s = np.linspace(0.0, 1.0, 10)[1:-1, None]
            ok = all(r is None for r in checker(here + s * (qn[i] - here), path=True))
        if not ok:
            corrections.append(Correction(0, int(i), "dropped", "path_collision", 0.0))
            continue
        out.append(qn[i])
        here = qn[i]
    return np.asarray(out).reshape(-1, q0.size), corrections


def _choose(
    scene,
    limits,
    q0,
    cands,
    frames,
    configs,
    *,
    method,
    starts,
    steps,
    sigma_px,
    seed,
    checker,
    timings,
    terms=None,
):
    """The frames by `method` from the feasible candidates; returns (poses, corrections, evaluation, greedy eval).
    `terms`: a `TermModel` the plan must tell from the geometry (nuisance parameters of the objective)."""
    rng = np.random.default_rng(seed)
    n = min(frames, len(cands))
    probe = evaluate_views(
        scene,
        _pick(cands, frames, rng),
        np.arange(frames, dtype=float),
        configs,
        sweeps=False,
        sigma_px=sigma_px,
    )
    idx = np.flatnonzero(probe.free)
    t0 = time.perf_counter()
    if method == "greedy":
        B = view_blocks(scene, jnp.asarray(cands), idx)
        sel = np.asarray(greedy_d_optimal(B, n))
        tries = [cands[sel] if n == frames else _pick(cands[sel], frames, rng)]
    else:
        M = ee_gram(ee_jacobians(scene, jnp.asarray(configs)), idx, design(scene, False).layout.size)
        q_init = np.stack([_pick(cands, frames, rng) for _ in range(starts)])
        qf, _ = descend(
            scene, limits, M, idx, jnp.asarray(q_init), sigma_px=sigma_px, steps=steps, terms=terms
        )
        tries = list(np.asarray(qf))
    timings[f"{method}_s"] = time.perf_counter() - t0
    best = None
    for q in tries:
        poses, corrections = _finish(scene, limits, q0, q, checker)
        if len(poses) < MIN_POSES:
            continue
        flank = None
        if terms is not None:
            flank = TermInputs(
                terms.terms,
                np.asarray(terms.masses),
                np.asarray(terms.coms),
                approach(np.vstack([q0, poses]))[1:],
            )
        ev = evaluate_views(
            scene,
            poses,
            np.arange(len(poses), dtype=float),
            configs,
            sweeps=False,
            sigma_px=sigma_px,
            terms=flank,
        )
        if best is None or ev.ee_rms_with_held < best[2].ee_rms_with_held:
            best = (poses, corrections, ev)
    if best is None:
        raise CameraViewError(
            "no start of the optimiser kept 3 feasible poses; widen the limits or move the camera"
        )
    return best


def plan(
    robot: str = "ur5e",
    *,
    camera: PlanCamera | None = None,
    target: PlanTarget | None = None,
    taught=None,
    frames: int = 240,
    eye_in_hand: bool = False,
    distance: float | None = None,
    resolution: tuple[int, int] = (1280, 960),
    floor_z: float | None = -0.6,
    region=None,
    limits: FeasibilityLimits | None = None,
    sigma_px: float | None = None,
    method: str = "gradient",
    starts: int = 3,
    steps: int = 150,
    candidates: int = 2000,
    amplitude_deg: float = 60.0,
    goal_mm: float | None = None,
    greedy_baseline: bool = False,
    seed: int = 0,
    checker=None,
    checker_factory=None,
    log=None,
    terms: tuple[str, ...] = (),
) -> PlanResult:
    """Plan a pose-based capture of `frames` stop-and-shoot frames (see the module docstring).

    **Arguments:**
    - `robot`: a shipped robot or a URDF file; `taught`: the taught pose
      (default `TAUGHT[robot]`, else zeros).
    - `camera`, `target`: given, or the demo's layout at the taught pose
      (`default_layout`: `resolution`, `distance` (0.9 m; 0.6 m eye-in-hand),
      `eye_in_hand`).
    - `floor_z`: the floor's height (m, base frame; `None`: no floor).
    - `region`: `(lo, hi)` box (m, base frame) where the EE accuracy matters.
    - `limits`: `FeasibilityLimits`; `sigma_px`: the detector's corner noise (default: rendered
      captures' at the camera's image width, `sigma_for`).
    - `method`: `"gradient"` (descent from `starts` random feasible subsets,
      `steps` Adam steps) or `"greedy"` (D-optimal selection); `candidates`
      random draws within `amplitude_deg` of the taught pose.
    - `goal_mm`: regenerate with wider candidates (x1.5, twice at most) while
      the predicted EE RMS is above it (seed 002's loop).
    - `greedy_baseline`: also run the greedy selection at the same budget.
    - `checker`: a further check of configurations, `checker(q (V, joints),
      path=False) -> [None or reason]`; or `checker_factory(draft plan) ->
      checker` (`jaxcal.sim.plan.MujocoChecker`: MuJoCo's contacts and lines of
      sight on the plan's own layout).
    - `log`: a callable taking a line of progress text.
    - `terms`: non-geometric terms (`jaxcal._terms`: `compliance`, `backlash`, ...) the
      capture must tell from the geometry: the objective counts them as nuisance parameters
      of the refinement, so the plan gains gravity-torque variety and approaches from both
      sides where the terms would otherwise cost the geometry its accuracy.

    **Returns:** a `PlanResult`. Raises `CameraViewError`, `BudgetTooSmallError`,
    `UnreachableRegionError`, `PlanError`.
    """
    say = log if log is not None else (lambda text: None)
    if method not in ("gradient", "greedy"):
        raise PlanError(f"method must be 'gradient' or 'greedy', got {method!r}")
    timings, t_start = {}, time.perf_counter()
    rob = Robot.load(robot)
    q0 = _taught(rob, taught)
    if camera is None or target is None:
        dist = distance if distance is not None else (0.6 if eye_in_hand else 0.9)
        c, t = default_layout(rob.model, q0, resolution=resolution, distance=dist, eye_in_hand=eye_in_hand)
        camera, target = camera or c, target or t
    scene = scene_of(rob, camera, target, floor_z, where="plan")
    sigma_px = sigma_for(camera.width, sigma_px)
    limits = FeasibilityLimits() if limits is None else limits
    # The plan's layout at the taught pose: what a checker of lines of sight is built on.
    draft = CapturePlan(
        robot, tuple(rob.model.joint_names), camera, target, q0, (PoseSet(q0[None]),), floor_z
    )
    if checker_factory is not None:
        checker = checker_factory(draft)
    _budget(scene, frames, sweeps=False)
    _check_taught(scene, limits, q0, checker)
    configs = workspace(rob, scene, region)
    amplitude = np.radians(amplitude_deg)
    terms = check_terms(terms)
    tm = _term_model(rob, scene, terms) if terms else None
    choose = partial(
        _choose, scene, limits, q0, configs=configs, sigma_px=sigma_px, checker=checker, timings=timings
    )
    best, greedy = None, None
    for attempt in range(3 if goal_mm is not None else 1):
        cands, counts = _feasible_candidates(
            scene, limits, q0, candidates, amplitude, seed + attempt, checker, say, timings
        )
        say(f"choosing {frames} of {len(cands)} poses ({method}; the first plan compiles its programs)")
        with working(log is not None, f"choosing {frames} poses", say=say):
            got = choose(
                cands, frames, method=method, starts=starts, steps=steps, seed=seed + attempt, terms=tm
            )
        if best is None or got[2].ee_rms_with_held < best[2].ee_rms_with_held:
            best = got
        if goal_mm is None or 1e3 * best[2].ee_rms_with_held <= goal_mm:
            break
        amplitude *= 1.5
        say(f"predicted EE RMS {1e3 * best[2].ee_rms:.3f} mm > goal {goal_mm} mm: regenerating wider")
    if greedy_baseline and method == "gradient":
        greedy = choose(cands, frames, method="greedy", starts=1, steps=0, seed=seed)[2]
    poses, corrections, ev = best
    timings["plan_s"] = time.perf_counter() - t_start
    result = replace(
        draft,
        segments=(PoseSet(poses),),
        checks=limits.to_dict(),
        corrections=tuple(corrections),
        prediction=ev.summary()
        | {"method": method, "workspace": "region" if region is not None else "random"}
        | ({"planned_for_terms": list(terms)} if terms else {}),
        description=f"{len(poses)} stop-and-shoot poses planned by jaxcal plan ({method})",
    )
    return PlanResult(result, ev, greedy, counts, timings)


def _term_model(rob: Robot, scene, terms: tuple[str, ...]) -> TermModel:
    """The non-geometric terms a plan is chosen for, with the robot file's link inertials."""
    masses, coms = link_inertials(rob.source)
    zero = tuple(int(i) for i in design(scene, False).layout.index("zero"))
    return TermModel(jnp.asarray(masses), jnp.asarray(coms), terms, zero)


def _feasible_candidates(
    scene, limits, q0, candidates: int, amplitude: float, seed: int, checker, say, timings: dict
):
    """`candidate_poses` about the taught pose (said and timed); `CameraViewError` when none is feasible."""
    t0 = time.perf_counter()
    say(f"candidates: {candidates} random poses within {np.degrees(amplitude):.0f} deg of the taught pose")
    cands, counts = candidate_poses(scene, limits, q0, candidates, amplitude, jax.random.key(seed), checker)
    timings["candidates_s"] = time.perf_counter() - t0
    if len(cands) == 0:
        raise CameraViewError(
            f"the camera sees the target in none of {candidates} poses about the taught pose (first failing "
            f"check: {', '.join(f'{k} {v}' for k, v in counts.items() if k in CHECKS)})"
        )
    say(
        f"{len(cands)} feasible ({counts['passed']} as drawn, {counts['moved']} moved toward the taught pose)"
    )
    return cands, counts


def with_prediction(plan_: CapturePlan, evaluation: PlanEvaluation) -> CapturePlan:
    """`plan_` with `evaluation`'s summary as its `prediction`."""
    return replace(plan_, prediction=evaluation.summary())


def sweep_plan(
    robot: str = "ur5e",
    *,
    frames_per_joint: int = 40,
    range_deg: float = 80.0,
    fps: float = 30.0,
    camera: PlanCamera | None = None,
    target: PlanTarget | None = None,
    resolution: tuple[int, int] = (1280, 960),
    distance: float = 0.9,
    eye_in_hand: bool = False,
    floor_z: float | None = -0.6,
) -> CapturePlan:
    """The seed method's capture as a plan: each joint in turn sweeps `range_deg`
    centred on zero in `frames_per_joint` frames over `frames_per_joint / fps`
    seconds, the others at zero (`jaxcal demo`: 40 frames, 80 deg, 1280x960;
    `jaxcal simulate`'s defaults: 30 frames, 40 deg, 640x480), filmed by the
    demo's camera unless `camera` / `target` are given."""
    rob = Robot.load(robot)
    n = rob.model.num_joints
    if camera is None or target is None:
        c, t = default_layout(
            rob.model, np.zeros(n), resolution=resolution, distance=distance, eye_in_hand=eye_in_hand
        )
        camera, target = camera or c, target or t
    half = 0.5 * np.radians(range_deg)
    speed = 2.0 * half * fps / frames_per_joint
    segments = tuple(
        Sweep(joint=j, home=np.zeros(n), start=-half, end=half, frames=frames_per_joint, speed=speed)
        for j in rob.model.joint_names
    )
    return CapturePlan(
        robot=robot,
        joints=tuple(rob.model.joint_names),
        camera=camera,
        target=target,
        taught=np.zeros(n),
        segments=segments,
        floor_z=floor_z,
        checks=FeasibilityLimits().to_dict(),
        description=f"{frames_per_joint} frames per {range_deg:g}-degree sweep of every joint from zero",
    )
