"""From a dataset on disk to a calibrated robot: `jaxcal.calibrate(dataset)`.

detect (OpenCV) -> PnP with covariance -> clock sync (encoder angles at the
frame times; the offset estimated when unknown) -> frames assigned to joint
sweeps -> arc fits of every joint at once (vmapped) -> axis fit -> the
calibrated model, $T_{cam,base}$ and the marker mount, with standard
deviations, an identifiability report and, for synthetic datasets, a
validation against the truth.

This module is an impure edge (files, OpenCV through `jaxcal.vision`); the
maths it calls (`fit_arc`, `fit_axes`, `fit_clock_offset`) is pure and jitted.
The command line (`jaxcal calibrate`, `jaxcal demo`) and the Python API share
this one code path.
"""

import dataclasses
import functools
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ._links import arm_targets, average_pose, link_poses, sequential_sweeps, start_mounts
from .errors import CalibrationError

_DEG = np.pi / 180.0
#: A joint counts as "at zero" (not the one sweeping) within this angle.
AT_ZERO_DEG = 0.05
#: The sweeping joint must be at least this far from zero for encoder-based assignment.
MOVING_DEG = 0.5
#: Independence threshold of the refinement's identifiability search without encoders.
NO_ENCODER_TOL = 1e-3


@dataclass(frozen=True, eq=False)
class Sweeps:
    """The marker poses of every joint sweep, ready for the arc fits (NumPy).

    - `rows`: per joint, the dataset's frame-table rows used, `(joints, frames)`
      padded with -1.
    - `positions` (m), `orientations`, `covariances` (of position and camera-frame
      rotation vector), `mask` `(joints, markers, frames, ...)`.
    - `t_cam`: camera-clock stamps `(joints, frames)`; `encoder`: commanded joint
      positions interpolated at them (rad) or None.
    """

    rows: np.ndarray
    positions: np.ndarray
    orientations: np.ndarray
    covariances: np.ndarray
    mask: np.ndarray
    t_cam: np.ndarray
    encoder: np.ndarray | None

    def arc_data(self):
        """Stacked `ArcData` (joints leading) for `jax.vmap(fit_arc)`."""
        import jax

        from ._arcfit import make_arc_data

        enc = self.encoder
        return jax.vmap(
            lambda P, O, C, m, e: make_arc_data(P, O, e, m, covariances=C),
            in_axes=(0, 0, 0, 0, None if enc is None else 0),
        )(self.positions, self.orientations, self.covariances, self.mask, enc)


@dataclass(eq=False)
class CalibrationResult:
    """Everything `calibrate` found (NumPy arrays and the calibrated `KinematicModel`).

    - `model`, `nominal`: calibrated and nominal models; `T_cam_base` (4, 4);
      `T_flange_target`: calibrated marker mounts `(markers, 4, 4)`.
    - `parameters`: one row per physical parameter (`name`, `unit`,
      `nominal`, `estimate`, `std`, `free`).
    - `frozen`: parameters the data cannot see, held at nominal.
    - `arcs`: per-joint arc-fit summaries; `sweeps`: the measurements.
    - `clock`: offset (s), its std, and whether it was estimated.
    - `frames`: counts of used / dropped frames with reasons.
    - `validation`: errors against the truth (synthetic datasets), else None.
    - `refinement`: the reprojection refinement's summary (`None` when it did
      not run); `refine_fit`: its `RefineResult`. When it ran, `model`,
      `T_cam_base`, `T_flange_target`, `parameters`, the ratios and the clock
      are the refined ones and the two-stage figures sit beside them.
    - `other_cameras`: further fixed cameras, each `{"camera", "T_cam_base",
      "std_cam", "views", ...}`: the refinement estimates their poses along
      with the robot (one model, one `T_cam_base` per camera).
    - `eye_in_hand`: the camera rides on the flange and films `board`, fixed
      in the world. The fields keep their eye-to-hand names with the roles
      swapped: `T_cam_base` holds $T_{board,base}$ and `T_flange_target[0]`
      holds $T_{flange,cam}$ (`result.json` names them so).
    """

    dataset: Path
    robot_urdf: Path
    camera: str
    targets: list
    nominal: object
    model: object
    T_cam_base: np.ndarray
    std_cam: np.ndarray
    T_flange_target: np.ndarray
    parameters: list
    frozen: list
    arcs: list
    sweeps: Sweeps
    arc_fit: object
    axis_fit: object
    clock: dict
    frames: dict
    intrinsics: dict
    solver: dict
    timings: dict = field(default_factory=dict)
    validation: dict | None = None
    warnings: list = field(default_factory=list)
    ee_errors: dict | None = None
    refinement: dict | None = None
    refine_fit: object = None
    other_cameras: list = field(default_factory=list)
    eye_in_hand: bool = False
    board: str | None = None

    @property
    def ok(self) -> bool:
        """Every solver reported success and the estimate is finite."""
        return bool(self.solver["success"]) and bool(np.all(np.isfinite(self.T_cam_base)))

    def to_json(self) -> dict:
        """The `result.json` payload (plain Python types)."""
        from .sim.simulate import model_to_json

        T = self.T_cam_base
        fixed = {
            "matrix": T.tolist(),
            "xyz_m": T[:3, 3].tolist(),
            "quaternion_xyzw": _quaternion_xyzw(T[:3, :3]).tolist(),
            "std_xyz_mm": (1e3 * self.std_cam[:3]).tolist(),
            "std_rot_deg": np.degrees(self.std_cam[3:]).tolist(),
        }
        if self.eye_in_hand:
            poses = {
                "board": self.board,
                "T_board_base": fixed,
                "T_flange_cam": self.T_flange_target[0].tolist(),
            }
        else:
            poses = {"T_cam_base": fixed, "T_flange_target": self.T_flange_target.tolist()}
        return {
            "schema": "jaxcal.result",
            "schema_version": 1,
            "dataset": str(self.dataset),
            "setup": "eye_in_hand" if self.eye_in_hand else "eye_to_hand",
            "camera": self.camera,
            "targets": self.targets,
            "ok": self.ok,
            **poses,
            "reduction_ratios": {
                a["joint"]: {
                    "nominal": a["ratio_nominal"],
                    "estimate": a["ratio"],
                    "std": a["ratio_std"],
                    "identifiable": a["ratio_identifiable"],
                }
                for a in self.arcs
            },
            "parameters": self.parameters,
            "identifiability": {
                "estimated": sum(bool(p["free"]) for p in self.parameters if p["group"] == "correction"),
                "frozen": self.frozen,
                "note": "frozen parameters cannot be seen by a camera watching joint axes "
                "(they trade off against others or against T_cam_base); they are held at nominal",
            },
            "arcs": self.arcs,
            "frames": self.frames,
            "clock": self.clock,
            "intrinsics": self.intrinsics,
            "solver": self.solver,
            "timings_s": self.timings,
            "refinement": self.refinement,
            "other_cameras": [
                {
                    "camera": c["camera"],
                    "views": c["views"],
                    "T_cam_base": {
                        "matrix": np.asarray(c["T_cam_base"]).tolist(),
                        "xyz_m": np.asarray(c["T_cam_base"])[:3, 3].tolist(),
                        "quaternion_xyzw": _quaternion_xyzw(np.asarray(c["T_cam_base"])[:3, :3]).tolist(),
                        "std_xyz_mm": (1e3 * np.asarray(c["std_cam"][:3])).tolist(),
                        "std_rot_deg": np.degrees(np.asarray(c["std_cam"][3:])).tolist(),
                    },
                    "T_cam_base_start": np.asarray(c["T_cam_base_start"]).tolist(),
                }
                for c in self.other_cameras
            ],
            "validation": self.validation,
            "warnings": self.warnings,
            "model": model_to_json(self.model),
        }


# --------------------------------------------------------------------------- small helpers


def _quaternion_xyzw(R: np.ndarray) -> np.ndarray:
    import cv2

    rvec = cv2.Rodrigues(np.asarray(R, np.float64))[0].ravel()
    angle = np.linalg.norm(rvec)
    axis = rvec / angle if angle > 0 else np.array([1.0, 0.0, 0.0])
    return np.r_[np.sin(angle / 2) * axis, np.cos(angle / 2)]


def _rpy(R):
    import jax.numpy as jnp

    return jnp.stack(
        [
            jnp.arctan2(R[2, 1], R[2, 2]),
            jnp.arctan2(-R[2, 0], jnp.sqrt(R[0, 0] ** 2 + R[1, 0] ** 2)),
            jnp.arctan2(R[1, 0], R[0, 0]),
        ]
    )


def _progress(enabled: bool, description: str, total: int):
    from .sim.simulate import _progress as bar

    return bar(enabled, total, description)


# --------------------------------------------------------------------------- stages


def _camera_rows(ds, camera: str) -> np.ndarray:
    rows = np.flatnonzero(ds.frames["camera"] == camera)
    if rows.size == 0:
        raise CalibrationError(f"{ds.root / 'frames.csv'}: no frames for camera {camera!r}")
    return rows


def _flange_targets(ds, flange: str):
    targets = [t for t in ds.targets if t.link == flange]
    if not targets:
        links = sorted({t.link for t in ds.targets})
        raise CalibrationError(
            f"{ds.root / 'metadata.json'}: no target rides on the flange link {flange!r} (targets are on "
            f"{links}); the joint-sweep method films a target on the flange"
        )
    return targets


def _eye_in_hand_target(ds, camera, flange: str):
    """The fixed board an eye-in-hand `camera` films, and the pseudo-target of
    the fits: the board's pattern, named after the camera, riding on the
    flange (its "mount" is $T_{flange,cam}$, found by the fits)."""
    from .io.dataset import TargetInfo

    boards = [t for t in ds.targets if t.link == "world"]
    if not boards:
        raise CalibrationError(
            f"{ds.root / 'metadata.json'}: camera {camera.name!r} rides on the flange {flange!r} but no target is "
            f"fixed in the world (link 'world'); targets are on {sorted({t.link for t in ds.targets})}"
        )
    board = boards[0]
    spec = dataclasses.replace(board.spec, name=camera.name)
    return board, [TargetInfo(spec, flange, None)]


def _names(names: list, eye_in_hand: bool) -> list:
    """Parameter names in an eye-in-hand setup's words: the fixed frame is the
    board's, the mount is the camera's."""
    if not eye_in_hand:
        return names
    return [
        n.replace("T_cam_base.", "T_board_base.").replace("marker.mount.", "camera.mount.") for n in names
    ]


def detect_poses(ds, camera, targets, K, dist, *, workers=None, progress=True):
    """Detections and PnP poses of `targets` in every frame of `camera`.

    **Returns:** `(rows, detections, poses)`: the frame-table rows, per row a
    dict target name -> `Detection`, and per row a dict target name ->
    `PoseEstimate` (targets not found or without a pose are absent).
    """
    from .vision import detect_frames, estimate_pose

    rows = _camera_rows(ds, camera.name)
    paths = [ds.image_path(int(i)) for i in rows]
    dets = detect_frames(paths, [t.spec for t in targets], K=K, dist=dist, workers=workers, progress=progress)
    poses = []
    for det in dets:
        p = {}
        for t in targets:
            d = det.get(t.name)
            if d is not None:
                est = estimate_pose(d, t.spec, K, dist)
                if est is not None:
                    p[t.name] = est
        poses.append(p)
    return rows, dets, poses


def self_calibrate(ds, camera, targets, rows, *, workers=None, progress=True):
    """Intrinsics from the ChArUco frames themselves (the seed's variant); `(K, dist, rms_px)`."""
    from .vision import calibrate_intrinsics, detect_frames

    charuco = [t for t in targets if t.spec.kind == "charuco"]
    if not charuco:
        raise CalibrationError(
            f"{ds.root / 'metadata.json'}: camera {camera.name!r} has no intrinsics (K is null) and no "
            "ChArUco target to self-calibrate them from"
        )
    t = charuco[0]
    paths = [ds.image_path(int(i)) for i in rows]
    dets = detect_frames(paths, [t.spec], workers=workers, progress=progress)
    found = [d[t.name] for d in dets if t.name in d]
    return calibrate_intrinsics(found, t.spec, (camera.width, camera.height))


def commanded_positions(ds, nominal) -> tuple[np.ndarray, np.ndarray] | None:
    """The encoder log as commanded joint positions `motor / nominal ratio`: `(t (T,), q (T, joints))`."""
    if ds.encoder_t is None:
        return None
    ratio = np.asarray(nominal.reduction_ratio, np.float64)
    return ds.encoder_t, ds.encoder_motor / ratio


def assign_frames(ds, t_ctrl: np.ndarray, q: np.ndarray | None, num_joints: int) -> np.ndarray:
    """Which joint sweeps in each frame (index, or -1 for none).

    From the metadata's motion segments when present; otherwise from the
    encoder log: the one joint more than `MOVING_DEG` from zero while every
    other stays within `AT_ZERO_DEG`.
    """
    index = {name: j for j, name in enumerate(ds.joint_names)}
    joint = np.full(len(t_ctrl), -1)
    if ds.segments:
        for name, start, end in ds.segments:
            if name is None:
                continue
            joint[(t_ctrl >= start) & (t_ctrl <= end)] = index[name]
        return joint
    if q is None:
        raise CalibrationError(
            f"{ds.root / 'metadata.json'}: cannot tell which joint moves in which frame: the metadata has "
            "no 'motion' segments and there is no encoder log"
        )
    away = np.abs(q) > MOVING_DEG * _DEG
    still = np.abs(q) < AT_ZERO_DEG * _DEG
    for j in range(num_joints):
        others = np.delete(np.arange(num_joints), j)
        joint[away[:, j] & np.all(still[:, others], axis=1)] = j
    return joint


def _interp(t, enc_t, enc_q) -> np.ndarray:
    return np.stack([np.interp(t, enc_t, enc_q[:, j]) for j in range(enc_q.shape[1])], axis=-1)


def build_sweeps(ds, rows, poses, targets, joint_of_row, q_at_row, t_cam, num_joints) -> tuple[Sweeps, dict]:
    """Group the per-frame poses into padded per-joint sweeps; also the per-joint frame counts."""
    M = len(targets)
    per_joint = [
        np.flatnonzero((joint_of_row == j) & np.array([bool(p) for p in poses])) for j in range(num_joints)
    ]
    F = max(1, max(len(k) for k in per_joint))
    J = num_joints
    R = np.full((J, F), -1)
    P = np.zeros((J, M, F, 3))
    O = np.broadcast_to(np.eye(3), (J, M, F, 3, 3)).copy()
    C = np.broadcast_to(np.eye(6), (J, M, F, 6, 6)).copy()
    mask = np.zeros((J, M, F), bool)
    T = np.zeros((J, F))
    E = None if q_at_row is None else np.zeros((J, F))
    for j, idx in enumerate(per_joint):
        R[j, : len(idx)] = rows[idx]
        T[j, : len(idx)] = t_cam[idx]
        T[j, len(idx) :] = t_cam[idx[-1]] if len(idx) else 0.0
        if E is not None:
            E[j, : len(idx)] = q_at_row[idx, j]
        for f, i in enumerate(idx):
            for m, t in enumerate(targets):
                est = poses[i].get(t.name)
                if est is None:
                    continue
                P[j, m, f] = est.T_cam_target[:3, 3]
                O[j, m, f] = est.T_cam_target[:3, :3]
                C[j, m, f] = est.cov
                mask[j, m, f] = True
    counts = {ds.joint_names[j]: int(len(idx)) for j, idx in enumerate(per_joint)}
    return Sweeps(R, P, O, C, mask, T, E), counts


# --------------------------------------------------------------------------- jitted solves


@functools.cache
def _jit_arcs():
    import jax

    from ._arcfit import fit_arc

    return jax.jit(jax.vmap(lambda d: fit_arc(d, max_steps=100)))


@functools.cache
def _jit_axes(use_poses: bool):
    import jax

    from ._axisfit import fit_axes

    def fit(nominal, arcs, mount, free=None):
        return fit_axes(nominal, arcs, T_flange_marker=mount, use_poses=use_poses, free=free)

    return jax.jit(fit)


def _physical(nominal, mounts0, T_cam_base0, unravel):
    """Map flattened axis-fit parameters to the physical ones reported (xyz, rpy, offsets, camera, mount)."""
    import jax
    import jax.numpy as jnp

    from ._axisfit import apply_correction
    from ._geometry import se3_exp, so3_log

    def f(x):
        params = unravel(x)
        model, mounts = apply_correction(nominal, mounts0, params.correction)
        T_cb = T_cam_base0 @ se3_exp(params.cam)
        origins = jax.vmap(lambda T: jnp.concatenate([T[:3, 3], _rpy(T[:3, :3])]))(model.T_parent_joint)
        mount = jax.vmap(lambda T: jnp.concatenate([T[:3, 3], _rpy(T[:3, :3])]))(mounts)
        dR = so3_log(T_cam_base0[:3, :3].T @ T_cb[:3, :3])
        return jnp.concatenate([origins.reshape(-1), model.zero_offset, T_cb[:3, 3], dR, mount.reshape(-1)])

    return f


@functools.cache
def _jit_physical():
    """`_physical` at the estimate and at zero, and its Jacobian, as one compiled call."""
    import jax
    import jax.numpy as jnp
    from jax.flatten_util import ravel_pytree

    @jax.jit
    def run(nominal, mounts0, T_cam_base0, params):
        flat, unravel = ravel_pytree(params)
        f = _physical(nominal, mounts0, T_cam_base0, unravel)
        return f(flat), f(jnp.zeros_like(flat)), jax.jacfwd(f)(flat)

    return run


def _parameter_table(nominal, fit, mounts0, T_cam_base0, targets, eye_in_hand=False) -> list:
    import jax.numpy as jnp

    est, nom, G = (
        np.asarray(a)
        for a in _jit_physical()(nominal, jnp.asarray(mounts0), jnp.asarray(T_cam_base0), fit.params)
    )
    std = np.sqrt(np.maximum(np.einsum("ia,ab,ib->i", G, np.asarray(fit.cov), G), 0.0))
    free_cols = np.asarray(fit.free)
    moves = np.abs(G[:, free_cols]).sum(axis=1) > 1e-12
    rows = []
    pose = [("x", "m"), ("y", "m"), ("z", "m"), ("roll", "rad"), ("pitch", "rad"), ("yaw", "rad")]
    for j in nominal.joint_names:
        rows += [(f"{j}.origin.{a}", u, "correction") for a, u in pose]
    rows += [(f"{j}.zero_offset", "rad", "correction") for j in nominal.joint_names]
    fixed = "T_board_base" if eye_in_hand else "T_cam_base"
    rows += [(f"{fixed}.{a}", "m", "camera") for a in "xyz"]
    rows += [(f"{fixed}.rot_{a}", "rad", "camera") for a in "xyz"]
    for t in targets:
        rows += [(f"{t.name}.mount.{a}", u, "mount") for a, u in pose]
    return [
        {
            "name": n,
            "unit": u,
            "group": g,
            "nominal": float(nom[i]),
            "estimate": float(est[i]),
            "std": float(std[i]),
            "free": bool(moves[i]),
        }
        for i, (n, u, g) in enumerate(rows)
    ]


# --------------------------------------------------------------------------- validation


def _validation(
    ds,
    nominal,
    fit,
    camera,
    targets,
    sweeps,
    mounts0,
    use_poses,
    fit_arcs_have_encoder,
    q_val_seed=0,
    n=1000,
    refined=None,
    board=None,
):
    """Errors against `truth.json`: EE (target origin) in the camera frame over random configurations,
    axis lines, ratios, T_cam_base (raw and in the estimator's gauge).

    With `refined` (a `RefineResult`), the `*_after` figures and the parameter
    errors are the refined ones and `*_two_stage` the axis fit's. With `board`
    (eye-in-hand), the fixed frame is the board's and the mount the camera's:
    the EE point is the camera's origin in the board frame."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from . import _montecarlo as mc
    from ._geometry import pose_inverse, so3_log
    from ._kinematics import forward_kinematics
    from .sim.simulate import model_from_json

    truth = ds.truth
    true = model_from_json(truth["model"])
    cam_truth = truth["cameras"].get(camera, {})
    if board is not None:
        if "T_mount_cam" not in cam_truth or board not in truth["targets"]:
            return None, None
        T_world_board = np.asarray(truth["targets"][board]["T_link_target"])
        T_cb_true = jnp.asarray(
            np.linalg.inv(T_world_board) @ np.asarray(truth.get("T_world_base", np.eye(4)))
        )
        mounts_true = jnp.asarray(cam_truth["T_mount_cam"])[None]
    elif "T_cam_base" not in cam_truth:
        return None, None
    else:
        T_cb_true = jnp.asarray(cam_truth["T_cam_base"])
        mounts_true = jnp.stack([jnp.asarray(truth["targets"][t.name]["T_link_target"]) for t in targets])
    q_val = jax.random.uniform(
        jax.random.key(q_val_seed), (n, nominal.num_joints), minval=-np.pi, maxval=np.pi
    )
    two_stage = fit
    if refined is not None:
        fit = refined
    s = jax.jit(mc.score)(fit, true, T_cb_true, mounts_true, nominal, q_val)

    # Per-configuration errors (for the plot).
    def marker(model, T_cb, mount, q):
        return (T_cb @ jax.vmap(lambda qq: forward_kinematics(model, qq)[-1])(q) @ mount)[:, :3, 3]

    tru = marker(true, T_cb_true, mounts_true[0], q_val)
    est = marker(fit.model, fit.T_cam_base, fit.T_flange_marker[0], q_val)
    nom = marker(nominal, fit.T_cam_base, fit.T_flange_marker[0], q_val)
    err_after = np.asarray(jnp.linalg.norm(est - tru, axis=-1)) * 1e3
    err_before = np.asarray(jnp.linalg.norm(nom - tru, axis=-1)) * 1e3
    est2 = marker(two_stage.model, two_stage.T_cam_base, two_stage.T_flange_marker[0], q_val)
    err_two = np.asarray(jnp.linalg.norm(est2 - tru, axis=-1)) * 1e3

    # The estimator's gauge for T_cam_base: the same axis fit on (nearly) exact
    # sweeps of the truth, with the same parameters frozen. The sweeps have the
    # dataset's shapes, so the arc and axis fits reuse their compiled code.
    F = sweeps.mask.shape[-1]
    plan = mc.SweepPlan(range_deg=40.0, frames=F)
    tiny = mc.NoiseModel(position_mm=1e-3, orientation_deg=1e-4, encoder_deg=0.0)
    exact = eqx.filter_jit(mc.synthesize_sweeps)(
        true,
        T_cb_true,
        mounts_true[: mounts0.shape[0]],  # the axis fit's markers (the flange's, first)
        plan,
        tiny,
        jax.random.key(1),
        nominal_ratio=nominal.reduction_ratio,
        use_encoders=bool(fit_arcs_have_encoder),
    )
    arcs_exact = _jit_arcs()(exact)
    T_gauge = _jit_axes(bool(use_poses))(nominal, arcs_exact, mounts0, two_stage.free).T_cam_base
    dT = np.asarray(pose_inverse(T_gauge) @ fit.T_cam_base)
    dT_raw = np.asarray(pose_inverse(T_cb_true) @ fit.T_cam_base)
    ratio_err = np.asarray(s["ratio_err_percent"])
    out = {
        "configurations": n,
        "ee_point": "camera origin, board frame" if board is not None else "target origin, camera frame",
        "ee_rms_mm_before": float(np.sqrt(np.mean(err_before**2))),
        "ee_max_mm_before": float(err_before.max()),
        "ee_rms_mm_after": float(np.sqrt(np.mean(err_after**2))),
        "ee_max_mm_after": float(err_after.max()),
        "ee_rms_mm_two_stage": float(np.sqrt(np.mean(err_two**2))),
        "ee_max_mm_two_stage": float(err_two.max()),
        "refined": refined is not None,
        "T_cam_base_error": {
            "trans_mm": float(np.linalg.norm(dT[:3, 3]) * 1e3),
            "rot_deg": float(np.degrees(np.linalg.norm(np.asarray(so3_log(jnp.asarray(dT[:3, :3])))))),
            "gauge": "the truth seen through the same frozen parameters (the same fit on exact sweeps)",
            "raw_trans_mm": float(np.linalg.norm(dT_raw[:3, 3]) * 1e3),
            "raw_rot_deg": float(
                np.degrees(np.linalg.norm(np.asarray(so3_log(jnp.asarray(dT_raw[:3, :3])))))
            ),
        },
        "parameter_errors": {
            j: {
                "axis_direction_deg": float(s["axis_dir_deg"][k]),
                "axis_position_mm": float(s["axis_pos_mm"][k]),
                "ratio_percent": None if not np.isfinite(ratio_err[k]) else float(ratio_err[k]),
                "zero_offset_deg": float(np.degrees(fit.model.zero_offset[k] - true.zero_offset[k])),
            }
            for k, j in enumerate(nominal.joint_names)
        },
        "true_ratios": np.asarray(true.reduction_ratio).tolist(),
        "true_clock_offset_s": truth.get("clock", {}).get("offset_s"),
    }
    if refined is not None:
        d2 = np.asarray(pose_inverse(T_gauge) @ two_stage.T_cam_base)
        out["T_cam_base_error_two_stage"] = {
            "trans_mm": float(np.linalg.norm(d2[:3, 3]) * 1e3),
            "rot_deg": float(np.degrees(np.linalg.norm(np.asarray(so3_log(jnp.asarray(d2[:3, :3])))))),
        }
    return out, {"before": err_before, "two_stage": err_two, "after": err_after}


# --------------------------------------------------------------------------- the pipeline


def calibrate(
    dataset,
    *,
    camera: str | None = None,
    workers: int | None = None,
    progress: bool = True,
    estimate_clock: bool | None = None,
    validate: bool = True,
    refine: bool = True,
    other_cameras: bool = True,
    log=None,
) -> CalibrationResult:
    """Calibrate the robot and camera of `dataset` (a path or a loaded `Dataset`).

    **Arguments:**
    - `camera`: which fixed camera the two-stage fit uses (default the first
      one mounted in the world). The refinement adds every other fixed camera
      (`other_cameras=False`: only this one): one robot model, one
      `T_cam_base` per camera, all cameras on the dataset's one clock.
    - `workers`: processes for detection (default all cores).
    - `estimate_clock`: estimate the camera-controller clock offset (default:
      when the metadata leaves it null).
    - `validate`: with a synthetic dataset's `truth.json`, add the validation block.
    - `refine`: after the two-stage fit, minimise the reprojection error of
      every detected corner over all parameters (`jaxcal._refine`); needs the
      encoder log. `False` stops at the two-stage result.
    - `log`: a callable taking one line of progress text (default silent).

    Compiled solvers are kept in JAX's persistent cache (see `jaxcal._cache`),
    so a second call on data of the same shapes skips compilation.

    **Returns:** a `CalibrationResult`. Raises `CalibrationError` /
    `DatasetError` / `VisionError` (all `ValueError`) naming the problem.
    """
    import jax
    import jax.numpy as jnp
    import optimistix as optx

    from ._arcfit import validate_arc_data
    from ._axisfit import parameter_names, register_lines
    from ._cache import enable_compilation_cache
    from ._clocksync import fit_clock_offset
    from ._geometry import pose_inverse, se3_exp
    from ._kinematics import forward_kinematics
    from .io.dataset import Dataset, load_dataset

    enable_compilation_cache()
    say = log or (lambda text: None)
    timings = {}
    t_start = time.perf_counter()
    ds = dataset if isinstance(dataset, Dataset) else load_dataset(dataset)
    nominal = ds.load_model()
    if tuple(nominal.joint_names) != tuple(ds.joint_names):
        raise CalibrationError(
            f"{ds.root / 'metadata.json'}: robot.joints {list(ds.joint_names)} differ from the chain in "
            f"{ds.robot_urdf} ({list(nominal.joint_names)})"
        )
    flange = nominal.link_names[-1]
    fixed = [c for c in ds.cameras if c.mount == "world"]
    if camera is None:
        on_hand = [c for c in ds.cameras if c.mount == flange]
        if not fixed and not on_hand:
            raise CalibrationError(
                f"{ds.root / 'metadata.json'}: no camera is fixed (mount 'world') or on the flange link "
                f"{flange!r} (mounts: {sorted({c.mount for c in ds.cameras})})"
            )
        cam = fixed[0] if fixed else on_hand[0]
    else:
        try:
            cam = ds.camera(camera)
        except KeyError:
            raise CalibrationError(
                f"camera {camera!r} is not in {ds.root / 'metadata.json'} (cameras: {[c.name for c in ds.cameras]})"
            ) from None
        if cam.mount not in ("world", flange):
            raise CalibrationError(
                f"camera {camera!r} rides on {cam.mount!r}; the joint-sweep method needs a fixed camera or "
                f"one on the flange link {flange!r}"
            )
    eye_in_hand = cam.mount == flange
    links_mode = not eye_in_hand and bool(ds.segments) and all(j is None for j, _, _ in ds.segments)
    notes = []
    if eye_in_hand:
        # The camera moves and a board stands still: the camera's pose in the board
        # frame follows exactly the arcs a flange target traces in a fixed camera's
        # frame, so the same fits run on the inverted PnP poses, with the board in
        # the role of the camera and the camera in that of the flange target.
        board, targets = _eye_in_hand_target(ds, cam, flange)
        extra = []
        others = [t.name for t in ds.targets if t.name != board.name]
        if others:
            notes.append(f"eye-in-hand: board {board.name!r} is the reference; not used: {others}")
    else:
        board = None
        targets = _flange_targets(ds, flange) if not links_mode else None
        extra = [c for c in fixed if c.name != cam.name] if (refine and other_cameras) else []
    target_link = None
    if links_mode:
        # Every joint moves at once: the seed's sequential procedure on markers on every link.
        try:
            targets, target_link, per_joint = arm_targets(ds, nominal)
        except ValueError as e:
            raise CalibrationError(f"{ds.root / 'metadata.json'}: {e}") from None
        if ds.encoder_t is None:
            raise CalibrationError(
                f"{ds.root}: arbitrary motion (no single-joint 'motion' segment) needs the encoder log: the "
                "sequential method undoes each joint's rotation with its encoder angle"
            )
        extra = []
        notes.append(
            "arbitrary motion, markers on every link: sequential initialisation (each joint's axis from its child "
            "link's marker, the earlier joints undone with their encoders), then the refinement over all markers"
        )
    if len(ds.cameras) > 1:
        notes.append(
            f"two-stage fit from camera {cam.name!r}; "
            + (
                f"the refinement adds {[c.name for c in extra]}"
                if extra
                else "the other cameras are not used (other_cameras=False, or none is fixed)"
            )
        )
    ignored = [t.name for t in ds.targets if t.link != flange]
    if ignored and not eye_in_hand and not links_mode:
        notes.append(f"targets not on the flange are not used by the two-stage method: {ignored}")
    timings["load_s"] = time.perf_counter() - t_start

    # Intrinsics.
    t0 = time.perf_counter()
    rows = _camera_rows(ds, cam.name)
    K, dist = cam.K, cam.dist
    intrinsics = {"source": "metadata"}
    if K is None:
        say(f"camera {cam.name}: no intrinsics in the metadata, self-calibrating from the ChArUco frames")
        K, dist, rms = self_calibrate(ds, cam, targets, rows, workers=workers, progress=progress)
        intrinsics = {"source": "self-calibrated (ChArUco)", "rms_px": float(rms)}
    intrinsics.update({"K": np.asarray(K).tolist(), "distortion": np.asarray(dist).tolist()})

    # Detection and PnP.
    say(f"detecting {', '.join(t.name for t in targets)} in {len(rows)} frames of camera {cam.name}")
    rows, dets, poses = detect_poses(ds, cam, targets, K, dist, workers=workers, progress=progress)
    if eye_in_hand:  # the camera's pose in the board frame (see above)
        poses = [{k: p.inverse() for k, p in d.items()} for d in poses]
    found = np.array([bool(p) for p in poses])
    if not found.any():
        raise CalibrationError(
            f"{ds.root}: no target was found in any of the {len(rows)} images of camera {cam.name!r}; check the "
            f"targets' dictionary ({', '.join(sorted({t.spec.dictionary for t in targets}))}), ids and sizes "
            "in metadata.json"
        )
    timings["detect_s"] = time.perf_counter() - t0

    # Clock and joint assignment.
    t0 = time.perf_counter()
    t_cam = ds.frames["timestamp"][rows]
    log_q = commanded_positions(ds, nominal)
    offset = ds.clock_offset_s
    if estimate_clock is None:
        estimate_clock = offset is None and log_q is not None
    if estimate_clock and log_q is None:
        raise CalibrationError(f"{ds.root}: the clock offset cannot be estimated without an encoder log")
    offset0 = 0.0 if offset is None else offset
    clock = {"offset_s": offset0, "std_s": None, "estimated": False, "drift_ppm": ds.clock_drift_ppm}
    if offset is None and not estimate_clock:
        notes.append("clock offset unknown and not estimated: 0 assumed")

    def sync(offset_s):
        t_ctrl = (t_cam - offset_s) / (1.0 + 1e-6 * ds.clock_drift_ppm)
        if log_q is None:
            return t_ctrl, None, np.ones(len(t_ctrl), bool)
        enc_t, enc_q = log_q
        inside = (t_ctrl >= enc_t[0]) & (t_ctrl <= enc_t[-1])
        if not inside.any():
            raise CalibrationError(
                f"{ds.root}: no overlap between the image timestamps of camera {cam.name!r} "
                f"([{t_cam.min():.3f}, {t_cam.max():.3f}] s camera clock, offset {offset_s * 1e3:.1f} ms) and "
                f"the encoder log ([{enc_t[0]:.3f}, {enc_t[-1]:.3f}] s, {ds.root / 'encoders.csv'})"
            )
        return t_ctrl, _interp(t_ctrl, enc_t, enc_q), inside

    def sweeps_at(offset_s):
        t_ctrl, q, inside = sync(offset_s)
        joint = np.where(inside, assign_frames(ds, t_ctrl, q, nominal.num_joints), -1)
        sw, counts = build_sweeps(ds, rows, poses, targets, joint, q, t_cam, nominal.num_joints)
        return sw, counts, joint, inside

    if links_mode:
        t_ctrl, q_rows, inside = sync(offset0)
        sel = np.flatnonzero(inside & found)
        if estimate_clock:
            # The first joint's child-link plate moves with that joint alone: its arc,
            # against the encoder log, gives the offset (before anything is undone).
            say("estimating the camera-controller clock offset (the first joint's arc, its link's plate)")
            from ._arcfit import make_arc_data

            try:
                P1, O1, C1, k1 = link_poses([poses[i] for i in sel], targets, per_joint[0])
            except ValueError as e:
                raise CalibrationError(f"{ds.root}: joint {ds.joint_names[0]!r}: {e}") from None
            d1 = jax.tree.map(lambda x: x[None], make_arc_data(P1, O1, None, covariances=C1))
            cf = jax.jit(partial(fit_clock_offset, offset0_s=offset0, drift_ppm=ds.clock_drift_ppm))(
                d1, jnp.asarray(t_cam[sel][k1])[None], jnp.asarray(log_q[0]), jnp.asarray(log_q[1][:, :1])
            )
            if not bool(cf.result == optx.RESULTS.successful) or not np.isfinite(float(cf.offset_s)):
                raise CalibrationError(f"{ds.root}: the clock-offset fit failed ({cf.result})")
            clock.update(offset_s=float(cf.offset_s), std_s=float(cf.std_s), estimated=True)
            t_ctrl, q_rows, inside = sync(float(cf.offset_s))
            sel = np.flatnonzero(inside & found)
        say(
            f"sequential arc fits of {nominal.num_joints} joints (markers on every link, earlier joints undone)"
        )
        Ps, Os, Cs, mk, arc_list = sequential_sweeps(
            rows[sel], [poses[i] for i in sel], targets, per_joint, q_rows[sel], t_cam[sel], _jit_arc_one()
        )
        n_j = nominal.num_joints
        sweeps = Sweeps(
            np.where(mk[:, 0], rows[sel][None], -1),
            Ps,
            Os,
            Cs,
            mk,
            np.broadcast_to(t_cam[sel], (n_j, sel.size)).copy(),
            q_rows[sel].T.copy(),
        )
        counts = {name: int(mk[j, 0].sum()) for j, name in enumerate(ds.joint_names)}
        joint = np.full(len(rows), -1)
    else:
        sweeps, counts, joint, inside = sweeps_at(offset0)
    if estimate_clock and not links_mode:
        say("estimating the camera-controller clock offset (arc fits of all joints with a shared offset)")
        cf = jax.jit(partial(fit_clock_offset, offset0_s=offset0, drift_ppm=ds.clock_drift_ppm))(
            sweeps.arc_data(), jnp.asarray(sweeps.t_cam), jnp.asarray(log_q[0]), jnp.asarray(log_q[1])
        )
        if not bool(cf.result == optx.RESULTS.successful) or not np.isfinite(float(cf.offset_s)):
            raise CalibrationError(f"{ds.root}: the clock-offset fit failed ({cf.result})")
        clock.update(offset_s=float(cf.offset_s), std_s=float(cf.std_s), estimated=True)
        sweeps, counts, joint, inside = sweeps_at(float(cf.offset_s))
    timings["sync_s"] = time.perf_counter() - t0

    data = sweeps.arc_data()
    for j, name in enumerate(ds.joint_names):
        if counts[name] == 0:
            raise CalibrationError(
                f"{ds.root}: joint {name!r}: no frame of camera {cam.name!r} shows a target while this joint "
                "sweeps alone"
            )
        try:
            validate_arc_data(jax.tree.map(lambda x, j=j: x[j], data), name)
        except ValueError as e:
            raise CalibrationError(f"{ds.root}: {e}") from None

    # Arc fits, then the axis fit.
    t0 = time.perf_counter()
    if links_mode:
        arcs = jax.tree.map(lambda *a: jnp.stack(a), *arc_list)
    else:
        say(f"arc fits of {nominal.num_joints} joints (one vmapped solve)")
        arcs = _jit_arcs()(data)
    jax.block_until_ready(arcs)
    timings["arc_fit_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    say("axis fit: kinematic parameters and camera-to-base")
    # With markers on every link each arc has its own marker: the axis fit uses
    # the lines only and the flange marker's mount; the refinement sees them all.
    fit_targets = targets[:1] if links_mode else targets
    mounts0 = [t.T_link_target for t in fit_targets]
    if all(m is not None for m in mounts0):
        mounts0 = jnp.asarray(np.stack(mounts0))
    else:
        mounts0 = None
    use_poses = bool(arcs.has_encoder) and not links_mode
    if mounts0 is None:
        T0 = register_lines(nominal, arcs)
        T_cf = T0 @ forward_kinematics(nominal, jnp.zeros(nominal.num_joints))[-1]
        mounts0 = jnp.einsum("ab,mbc->mac", pose_inverse(T_cf), arcs.T_cam_marker0[0])
    fit = _jit_axes(use_poses)(nominal, arcs, mounts0)
    jax.block_until_ready(fit)
    timings["axis_fit_s"] = time.perf_counter() - t0

    # Summaries.
    ok_arc = np.asarray(arcs.result == optx.RESULTS.successful)
    ok_axis = bool(fit.result == optx.RESULTS.successful)
    names = _names(parameter_names(nominal, len(fit_targets)), eye_in_hand)
    frozen = [n for n, f in zip(names, np.asarray(fit.free)) if not f]
    T_cam_base0 = np.asarray(fit.T_cam_base) @ np.linalg.inv(np.asarray(se3_exp(fit.params.cam)))
    parameters = _parameter_table(nominal, fit, mounts0, T_cam_base0, fit_targets, eye_in_hand)
    nominal_ratio = np.asarray(nominal.reduction_ratio)
    arc_rows = []
    for j, name in enumerate(ds.joint_names):
        rate = float(arcs.rate[j])
        has = bool(arcs.has_encoder)
        arc_rows.append(
            {
                "joint": name,
                "frames": int(arcs.num_frames[j]),
                "position_rms_mm": float(arcs.position_rms[j]) * 1e3,
                "rotation_rms_deg": float(np.degrees(arcs.rotation_rms[j])),
                "residual_rms": float(arcs.residual_rms[j]),
                "direction_cam": np.asarray(arcs.direction[j]).tolist(),
                "point_cam_m": np.asarray(arcs.point[j]).tolist(),
                "ratio_nominal": float(nominal_ratio[j]),
                "ratio": float(nominal_ratio[j] / rate) if has else None,
                "ratio_std": float(nominal_ratio[j] * np.sqrt(max(float(arcs.rate_var[j]), 0.0)) / rate**2)
                if has
                else None,
                "ratio_identifiable": has,
                "solver": {
                    "result": "successful" if ok_arc[j] else "failed",
                    "steps": int(arcs.num_steps[j]),
                },
            }
        )
    if not arcs.has_encoder:
        notes.append("no encoder log: reduction ratios are not identifiable (images alone give the axes)")
    n_rows = len(rows)
    frames = {
        "images": int(n_rows),
        "target_found": int(found.sum()),
        "no_target": int((~found).sum()),
        "outside_encoder_log": int((~inside).sum()),
        "not_in_a_sweep": 0 if links_mode else int(((joint < 0) & inside & found).sum()),
        "used_per_joint": counts,
        "dropped_capture_indices": _dropped(ds, cam.name),
    }
    std_cam = np.asarray(fit.std[:6])
    result = CalibrationResult(
        dataset=ds.root,
        robot_urdf=ds.robot_urdf,
        camera=cam.name,
        targets=[t.name for t in targets],
        nominal=nominal,
        model=jax.device_get(fit.model),
        T_cam_base=np.asarray(fit.T_cam_base),
        std_cam=std_cam,
        T_flange_target=np.asarray(fit.T_flange_marker),
        parameters=parameters,
        frozen=frozen,
        arcs=arc_rows,
        sweeps=sweeps,
        arc_fit=jax.device_get(arcs),
        axis_fit=jax.device_get(fit),
        clock=clock,
        frames=frames,
        intrinsics=intrinsics,
        solver={
            "success": bool(ok_arc.all() and ok_axis),
            "arc_fits_ok": ok_arc.tolist(),
            "axis_fit": _result_name(fit.result),
            "axis_fit_steps": int(fit.num_steps),
            "axis_fit_residual_rms": float(fit.residual_rms),
        },
        timings=timings,
        warnings=notes,
        eye_in_hand=eye_in_hand,
        board=None if board is None else board.name,
    )
    if refine and log_q is None and extra:
        notes.append(
            f"no encoder log: the refinement uses camera {cam.name!r} only (not {[c.name for c in extra]})"
        )
        extra = []
    if refine:
        t0 = time.perf_counter()
        views = [_CameraViews(cam, rows, dets, poses, t_cam, K, dist)]
        for c in extra:
            say(f"camera {c.name}: detecting {', '.join(t.name for t in targets)} for the refinement")
            views.append(_camera_views(ds, c, targets, workers=workers, progress=progress))
        timings["detect_other_cameras_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        say(
            "refinement: reprojection error of every corner over all parameters (robust, Cauchy)"
            + (f", {len(views)} cameras" if len(views) > 1 else "")
        )
        links = None
        if links_mode:
            links = (
                target_link,
                _link_mounts(fit, q_rows[sel], [poses[i] for i in sel], targets, target_link),
            )
        _refine_stage(result, ds, views, targets, log_q, fit, arcs, mounts0, T_cam_base0, joint, links)
        timings["refine_s"] = time.perf_counter() - t0
    if validate and ds.truth is not None:
        t0 = time.perf_counter()
        say("validating against truth.json (1000 random configurations)")
        result.validation, result.ee_errors = _validation(
            ds,
            nominal,
            fit,
            cam.name,
            targets,
            sweeps,
            mounts0,
            use_poses,
            arcs.has_encoder,
            refined=result.refine_fit,
            board=result.board,
        )
        if result.validation is not None:
            result.validation["clock_offset_error_ms"] = (
                None
                if result.validation["true_clock_offset_s"] is None
                else 1e3 * (clock["offset_s"] - result.validation["true_clock_offset_s"])
            )
        if result.validation is not None and result.other_cameras:
            result.validation["other_cameras"] = _other_camera_errors(ds.truth, result)
        timings["validation_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start
    return result


def _other_camera_errors(truth: dict, result) -> dict:
    """Each further camera's pose relative to the first, against the truth
    (gauge-free: the base frame cancels), at the start and refined."""
    cams = truth.get("cameras", {})
    if "T_cam_base" not in cams.get(result.camera, {}):
        return {}
    T0_true = np.asarray(cams[result.camera]["T_cam_base"])
    out = {}
    for c in result.other_cameras:
        if "T_cam_base" not in cams.get(c["camera"], {}):
            continue
        rel_true = np.asarray(cams[c["camera"]]["T_cam_base"]) @ np.linalg.inv(T0_true)
        row = {}
        # The start is relative to the two-stage first camera (the gauge it was computed in).
        T0_two = np.asarray(result.refinement["two_stage"]["T_cam_base"])
        for key, T, T0 in (
            ("start", c["T_cam_base_start"], T0_two),
            ("refined", c["T_cam_base"], result.T_cam_base),
        ):
            D = np.linalg.inv(rel_true) @ (np.asarray(T) @ np.linalg.inv(T0))
            cos = np.clip((np.trace(D[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
            row[key] = {
                "trans_mm": float(1e3 * np.linalg.norm(D[:3, 3])),
                "rot_deg": float(np.degrees(np.arccos(cos))),
            }
        out[c["camera"]] = row
    return out


def _result_name(result) -> str:
    import optimistix as optx

    return "successful" if bool(result == optx.RESULTS.successful) else "failed"


def _dropped(ds, camera: str) -> list:
    idx = np.sort(ds.frames["frame"][ds.frames["camera"] == camera])
    if idx.size == 0:
        return []
    return sorted(set(range(int(idx[0]), int(idx[-1]) + 1)) - set(int(i) for i in idx))


# --------------------------------------------------------------------------- refinement


@functools.cache
def _jit_refine(free: tuple):
    import jax

    from ._refine import refine

    return jax.jit(lambda problem, params0: refine(problem, params0, np.asarray(free)))


@functools.cache
def _jit_identifiable():
    import jax

    from ._refine import identifiable_mask

    return jax.jit(identifiable_mask)


class _CameraViews(NamedTuple):
    """One fixed camera's frames for the refinement: dataset rows, detections,
    PnP poses, camera-clock stamps and intrinsics."""

    camera: object
    rows: np.ndarray
    dets: list
    poses: list
    t_cam: np.ndarray
    K: np.ndarray
    dist: np.ndarray | None


def _camera_views(ds, camera, targets, *, workers=None, progress=True) -> _CameraViews:
    """Detect `targets` in every frame of a further fixed camera (its intrinsics
    from the metadata, or self-calibrated from its ChArUco frames)."""
    rows = _camera_rows(ds, camera.name)
    K, dist = camera.K, camera.dist
    if K is None:
        K, dist, _ = self_calibrate(ds, camera, targets, rows, workers=workers, progress=progress)
    rows, dets, poses = detect_poses(ds, camera, targets, K, dist, workers=workers, progress=progress)
    return _CameraViews(camera, rows, dets, poses, ds.frames["timestamp"][rows], np.asarray(K), dist)


def _dist5(dist) -> np.ndarray | None:
    """OpenCV's first five distortion coefficients; `None` if more are non-zero."""
    d = np.zeros(5) if dist is None else np.asarray(dist, np.float64).ravel()
    if d.size > 5 and np.any(d[5:] != 0):
        return None
    out = np.zeros(5)
    out[: min(5, d.size)] = d[:5]
    return out


def _start_pose(views: _CameraViews, t_ctrl, inside, enc_t, enc_q, rate, model, mounts, targets):
    """A further camera's `T_cam_base` from its PnP poses and the two-stage
    robot: per view $T_{cam,target} (T_{base,flange}(q) T_{flange,target})^{-1}$,
    the rotations averaged (nearest rotation to their sum), the median translation."""
    import jax

    from ._kinematics import forward_kinematics

    idx = [i for i in range(len(views.rows)) if inside[i] and views.poses[i]]
    if not idx:
        return None
    q = _interp(t_ctrl[idx], enc_t, enc_q) * np.asarray(rate)
    T_bf = np.asarray(jax.jit(jax.vmap(lambda qq: forward_kinematics(model, qq)[-1]))(q))
    est = []
    for k, i in enumerate(idx):
        for m, t in enumerate(targets):
            pose = views.poses[i].get(t.name)
            if pose is not None:
                est.append(pose.T_cam_target @ np.linalg.inv(T_bf[k] @ np.asarray(mounts[m])))
    return average_pose(np.stack(est))


def _sweep_angles(R_pnp, target, joint, model, T_cam_base, mounts) -> np.ndarray:
    """Start angles of the sweeping joint in every view without encoders, from
    its PnP orientation and the two-stage model: with the others at zero the
    joint turns the target about its axis $w_j$ (camera frame), $R(a) =
    \\exp(a[w_j]_\\times) R(0)$, so $a$ is the rotation of $R_{PnP} R(0)^T$
    about $w_j$.

    **Arguments:** per view the PnP rotation `R_pnp` `(V, 3, 3)`, the target
    index and the sweeping joint `(V,)`; the two-stage model, `T_cam_base` and
    mounts `(targets, 4, 4)`.
    """
    import jax
    import jax.numpy as jnp

    from ._geometry import so3_log
    from ._kinematics import forward_kinematics

    n = model.num_joints
    q = jnp.concatenate([jnp.zeros((1, n)), jnp.eye(n)])  # home, then each joint at 1 rad
    T = np.asarray(jax.jit(jax.vmap(lambda qq: T_cam_base @ forward_kinematics(model, qq)[-1]))(q))
    R0 = np.einsum("ab,mbc->mac", T[0, :3, :3], np.asarray(mounts)[:, :3, :3])  # (targets, 3, 3)
    w = np.asarray(jax.vmap(lambda R: so3_log(R @ jnp.asarray(T[0, :3, :3]).T))(jnp.asarray(T[1:, :3, :3])))
    M = np.einsum("vab,vcb->vac", np.asarray(R_pnp), R0[np.asarray(target)])
    vee = 0.5 * np.stack([M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0], M[:, 1, 0] - M[:, 0, 1]], -1)
    cos = 0.5 * (np.trace(M, axis1=1, axis2=2) - 1.0)
    return np.arctan2(np.einsum("va,va->v", w[np.asarray(joint)], vee), cos)


@functools.cache
def _jit_arc_one():
    import jax

    from ._arcfit import fit_arc

    return jax.jit(lambda d: fit_arc(d, max_steps=100))


def _link_mounts(fit, q, poses, targets, link) -> np.ndarray:
    """Start mounts of every arm target on its link (`jaxcal._links.start_mounts`)
    from the two-stage robot at the rows' encoder positions `q`."""
    import jax
    import jax.numpy as jnp

    from ._kinematics import forward_kinematics

    T = jax.jit(jax.vmap(lambda qq: jnp.asarray(fit.T_cam_base) @ forward_kinematics(fit.model, qq)))(
        jnp.asarray(q)
    )
    return start_mounts(np.asarray(T), poses, targets, link)


def _refine_stage(
    result, ds, views, targets, log_q, fit, arcs, mounts0, T_cam_base0, joint_of_row, links=None
):
    """Reprojection refinement from the two-stage result; updates `result` in place.

    `views`: the two-stage camera's `_CameraViews` first, then any further
    fixed cameras (their start poses from their PnP poses and the two-stage
    robot). Every frame inside the encoder log with a detected target
    contributes all its corners (sweep or not). The axis fit's frozen
    parameters stay frozen; rates are free with encoders, the clock offset
    when it was estimated. The two-stage figures are kept beside the refined.

    Without an encoder log (`log_q` None; one camera), the sweep frames
    (`joint_of_row` >= 0) with a PnP pose contribute, each with its sweeping
    joint's angle as one more unknown (started from `_sweep_angles`); the
    other joints sit at their commanded zero, the reduction ratios and the
    clock offset are not identifiable.

    With markers on every link (`links`: each target's link index and its
    start mount on that link, `_link_mounts`), every target's corners go
    through its own link's chain; the corners decide what is identifiable.
    """
    from types import SimpleNamespace

    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import optimistix as optx

    from ._axisfit import AxisFitParams
    from ._refine import (
        OtherCameras,
        RefineParams,
        RefineProblem,
        default_free,
        make_corner_data,
        refine_parameter_names,
        summarize_refinement,
    )

    cam, K = views[0].camera, views[0].K
    dist5 = _dist5(views[0].dist)
    if dist5 is None:
        result.warnings.append(
            f"camera {cam.name!r}: distortion beyond (k1, k2, p1, p2, k3) is not modelled by the refinement; "
            "stopped at two-stage"
        )
        return
    no_encoders = log_q is None
    n = result.nominal.num_joints
    # Without encoders the log is not read (RefineParams.angles): a placeholder keeps the shapes.
    enc_t, enc_q = log_q if not no_encoders else (np.array([-np.inf, np.inf]), np.zeros((2, n)))
    offset = result.clock["offset_s"]
    has = bool(arcs.has_encoder)
    rate0 = jnp.asarray(arcs.rate) if has else jnp.ones(result.nominal.num_joints)
    pts = {t.name: np.asarray(t.spec.points(), np.float64) for t in targets}
    P, U, tgt, frame, tc, cams, sweep, pnp = [], [], [], [], [], [], [], []
    others, used = [], [views[0]]
    for v in views:
        t_ctrl = (v.t_cam - offset) / (1.0 + 1e-6 * ds.clock_drift_ppm)
        inside = (t_ctrl >= enc_t[0]) & (t_ctrl <= enc_t[-1])
        if no_encoders:
            inside = np.asarray(joint_of_row) >= 0
        if v is not views[0]:
            d5 = _dist5(v.dist)
            T0 = _start_pose(v, t_ctrl, inside, enc_t, enc_q, rate0, fit.model, fit.T_flange_marker, targets)
            if d5 is None or T0 is None:
                result.warnings.append(
                    f"camera {v.camera.name!r}: "
                    + ("unmodelled distortion" if d5 is None else "no target pose inside the encoder log")
                    + "; left out of the refinement"
                )
                continue
            others.append((T0, np.asarray(v.K, np.float64), d5))
            used.append(v)
        c = len(used) - 1
        for i, det in enumerate(v.dets):
            if not inside[i]:
                continue
            for m, t in enumerate(targets):
                dt = det.get(t.name)
                if dt is None or len(dt.ids) < 4:
                    continue
                if no_encoders:
                    pose = v.poses[i].get(t.name)
                    if pose is None:
                        continue
                    sweep.append(int(joint_of_row[i]))
                    pnp.append(pose.T_cam_target[:3, :3])
                P.append(pts[t.name][dt.ids])
                U.append(dt.pixels)
                tgt.append(m)
                frame.append(int(v.rows[i]))
                tc.append(float(v.t_cam[i]))
                cams.append(c)
    if not P:
        result.warnings.append("refinement: no detected corners inside the encoder log; stopped at two-stage")
        return
    data = make_corner_data(
        P,
        U,
        np.array(tgt),
        np.array(frame),
        np.array(tc),
        enc_t,
        enc_q,
        ds.clock_drift_ppm,
        camera=np.array(cams) if others else None,
        sweep_joint=np.array(sweep) if no_encoders else None,
    )
    nominal = result.nominal
    n, M = nominal.num_joints, len(targets)
    correction = fit.params.correction
    if links is not None:
        mounts0 = links[1]
        correction = eqx.tree_at(lambda c: c.tool, correction, jnp.zeros((M, 6)))
    problem = RefineProblem(
        nominal=nominal,
        T_flange_marker0=jnp.asarray(mounts0),
        T_cam_base0=jnp.asarray(T_cam_base0),
        K0=jnp.asarray(K, jnp.float64),
        dist0=jnp.asarray(dist5),
        offset0_s=jnp.asarray(offset),
        data=data,
        other_cameras=OtherCameras(*(jnp.asarray(np.stack(a)) for a in zip(*others))) if others else None,
        eye_in_hand=result.eye_in_hand,
        target_link=None if links is None else jnp.asarray(links[0]),
    )
    params0 = RefineParams(
        cam=fit.params.cam,
        correction=correction,
        rate=rate0,
        clock_ms=jnp.zeros(()),
        intrinsics=jnp.zeros(9),
        other_cams=jnp.zeros((len(others), 6)) if others else None,
        angles=None,
    )
    angle_names = []
    if no_encoders:
        a0 = _sweep_angles(
            np.stack(pnp), tgt, sweep, fit.model, jnp.asarray(fit.T_cam_base), fit.T_flange_marker
        )
        params0 = eqx.tree_at(lambda p: p.angles, params0, jnp.asarray(a0), is_leaf=lambda x: x is None)
        angle_names = [f"frame{f}.{nominal.joint_names[j]}" for f, j in zip(frame, sweep)]
    cand = default_free(
        n,
        M,
        rates=has,
        clock=bool(result.clock["estimated"]),
        other_cameras=len(others),
        angles=len(angle_names),
    )
    n_ax = 6 + 7 * n + 6 * M  # the axis-fit part of the layout
    if not no_encoders and links is None:
        cand[:n_ax] &= np.asarray(fit.free)  # the two-stage gauge
    # Without encoders the lines-only axis fit holds the mount at nominal, which
    # the corners do see: they decide, with a stricter independence threshold. A
    # zero offset then only shows through the home pose of the other joints'
    # sweeps, nearly degenerate with the link geometry (parallel axes: the
    # default threshold keeps directions with singular values ~1e-7 of the largest).
    strict = no_encoders or links is not None
    free, _ = _jit_identifiable()(problem, params0, cand, tol=NO_ENCODER_TOL if strict else 1e-6)
    free = np.asarray(free)
    res = _jit_refine(tuple(bool(f) for f in free))(problem, params0)
    jax.block_until_ready(res)
    names = _names(
        refine_parameter_names(nominal, M, [v.camera.name for v in used[1:]], angle_names), result.eye_in_hand
    )
    summary = summarize_refinement(res, names, data)
    ok = bool(res.result == optx.RESULTS.successful) and bool(np.all(np.isfinite(np.asarray(res.T_cam_base))))
    std = np.asarray(res.std)
    newly = [nm for nm, c, f in zip(names, cand, free) if c and not f]

    # The reported figures become the refined ones; the two-stage ones stay beside them.
    two = {
        "T_cam_base": np.asarray(result.T_cam_base).tolist(),
        "std_cam": np.asarray(result.std_cam).tolist(),
        "T_flange_target": np.asarray(result.T_flange_target).tolist(),
        "clock_offset_s": result.clock["offset_s"],
        "ratios": {a["joint"]: a["ratio"] for a in result.arcs},
    }
    shim = SimpleNamespace(
        params=AxisFitParams(cam=res.params.cam, correction=res.params.correction),
        cov=np.asarray(res.cov)[:n_ax, :n_ax],
        free=free[:n_ax],
    )
    result.model = jax.device_get(res.model)
    result.T_cam_base = np.asarray(res.T_cam_base)
    result.std_cam = std[:6]
    result.T_flange_target = np.asarray(res.T_flange_marker)
    result.parameters = _parameter_table(nominal, shim, mounts0, T_cam_base0, targets, result.eye_in_hand)
    result.frozen = [nm for nm, f in zip(names[:n_ax], free[:n_ax]) if not f]
    rate = np.asarray(res.params.rate)
    nominal_ratio = np.asarray(nominal.reduction_ratio)
    for j, a in enumerate(result.arcs):
        a["ratio_two_stage"], a["ratio_std_two_stage"] = a["ratio"], a["ratio_std"]
        if has:
            a["ratio"] = float(nominal_ratio[j] / rate[j])
            a["ratio_std"] = float(nominal_ratio[j] * std[names.index(f"{a['joint']}.rate")] / rate[j] ** 2)
    ic = names.index("clock_offset_ms")
    if result.clock["estimated"]:
        result.clock.update(
            offset_s_two_stage=result.clock["offset_s"],
            std_s_two_stage=result.clock["std_s"],
            offset_s=float(res.offset_s),
            std_s=float(1e-3 * std[ic]),
        )
    result.refine_fit = jax.device_get(res)
    result.solver.update(
        success=bool(result.solver["success"]) and ok,
        refinement=summary["solver"]["result"],
        refinement_steps=summary["solver"]["steps"],
        refinement_rounds_ok=bool(res.rounds_ok),
    )
    summary.update(
        views=int(data.mask.shape[0]),
        frames=len(set(frame)),
        free_parameters=int(free.sum()),
        held_at_start=[nm for nm, f in zip(names, free) if not f],
        frozen_beyond_two_stage=newly,
        std={nm: float(std[i]) for i, nm in enumerate(names) if free[i]},
        two_stage=two,
        loss="cauchy IRLS (3 rounds), then least squares on the inliers (3.7 robust sigmas)",
    )
    if no_encoders:
        g0 = len(names) - len(angle_names)
        a = np.asarray(res.params.angles)
        summary["joint_angles"] = {
            "note": "no encoder log: each sweep frame's joint angle was estimated from the images "
            "(commanded coordinates; the other joints at zero); reduction ratios are not identifiable",
            "views": [
                {
                    "frame": int(f),
                    "joint": nominal.joint_names[j],
                    "angle_deg": float(np.degrees(a[k])),
                    "std_deg": float(np.degrees(std[g0 + k])),
                }
                for k, (f, j) in enumerate(zip(frame, sweep))
            ],
        }
        summary["std"] = {nm: sd for nm, sd in summary["std"].items() if nm not in set(angle_names)}
    result.refinement = summary
    cams_v = np.zeros(len(frame), int) if not others else np.array(cams)
    summary["views_per_camera"] = {v.camera.name: int((cams_v == c).sum()) for c, v in enumerate(used)}
    T_all = np.asarray(res.T_cam_bases)
    for c, v in enumerate(used[1:], start=1):
        k = names.index(f"{v.camera.name}.T_cam_base.tx")
        result.other_cameras.append(
            {
                "camera": v.camera.name,
                "T_cam_base": T_all[c],
                "std_cam": std[k : k + 6],
                "views": summary["views_per_camera"][v.camera.name],
                "T_cam_base_start": np.asarray(others[c - 1][0]),
                "K": others[c - 1][1],
                "distortion": others[c - 1][2],
            }
        )
    if summary["outlier_frames"]:
        result.warnings.append(
            f"refinement: {len(summary['outlier_frames'])} frame(s) whose corners stay outliers: "
            f"{summary['outlier_frames'][:20]}"
        )
