"""Verdicts on a hand-eye result: the k-fold spread of its transforms, and plausibility checks (NumPy).

Run outside jit on a `HandEyeResult`. `kfold_spread` re-solves with each
fold of frames left out through the caller's compiled solver (the mask is
data, so no new compilation) and turns the fold estimates into a
delete-a-group jackknife standard deviation, comparable to the covariance's
(`HandEyeResult.std_robot_cam`). `assess_hand_eye` says whether the result
can be trusted: `status` is `"ok"` or `"suspect"`, with the reasons, and
notes that do not change the status.
"""

from collections.abc import Callable
from dataclasses import dataclass

import equinox as eqx
import jax
import numpy as np

from .._device import result_is
from .._npgeom import rotation_angle
from ..records import Judgement
from .consistency import MotionConsistency
from .data import HandEyeData, HandEyePixels
from .heldout import HeldOut, reprojection_squares
from .noise import ROBOT_SIGMA_START
from .solve import HandEyeResult

#: Stage names, in `HandEyeResult.stage_result` order.
STAGES = ("robust", "plain")


def _log_rotation(R: np.ndarray) -> np.ndarray:
    angle = rotation_angle(R)
    s = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    n = np.linalg.norm(s, axis=-1, keepdims=True)
    return np.where(n > 1e-12, s / np.where(n > 1e-12, n, 1.0), 0.0) * angle[..., None]


def pose_difference(T: np.ndarray, T_ref: np.ndarray) -> np.ndarray:
    """`(..., 6)`: translation difference (m) and parent-frame rotation vector of $R R_{ref}^T$ (rad),
    the error convention of `HandEyeResult`'s standard deviations."""
    T, T_ref = np.asarray(T, np.float64), np.asarray(T_ref, np.float64)
    dR = T[..., :3, :3] @ np.swapaxes(T_ref[..., :3, :3], -1, -2)
    return np.concatenate([T[..., :3, 3] - T_ref[..., :3, 3], _log_rotation(dR)], axis=-1)


@dataclass(frozen=True)
class KFoldSpread:
    """The spread of the transforms over folds of frames (delete-a-group jackknife), and the
    held-out reprojection of the frames each fold left out.

    With $K$ folds and $\\theta_k$ the estimate without fold $k$,
    $\\mathrm{var} = \\frac{K-1}{K} \\sum_k (\\theta_k - \\bar\\theta)^2$ per
    component, which estimates the full-data estimator's variance.

    - `folds`: $K$; `fold_frames`: the frames each fold leaves out (consecutive blocks).
    - `std_robot_cam` `(cameras, 6)`, `std_robot_board` `(6,)`: translation (m)
      and rotation (rad), as `HandEyeResult.std_robot_cam`.
    - `converged` `(folds,)`: whether each fold's solve succeeded.
    - `held_out_squares`, `held_out_coordinates` `(cameras, frames)`: pixels only, each held-out
      frame's corners predicted from its reported robot pose by the fold that left it out
      (`heldout.reprojection_squares`: px^2 summed, and the coordinates summed); zeros for frames
      never held out, None for pose data.
    """

    folds: int
    fold_frames: tuple[tuple[int, ...], ...]
    std_robot_cam: np.ndarray
    std_robot_board: np.ndarray
    converged: np.ndarray
    held_out_squares: "np.ndarray | None" = None
    held_out_coordinates: "np.ndarray | None" = None

    @property
    def held_out_frames(self) -> np.ndarray:
        """Indices of the frames held out, in order."""
        return np.array(sorted(f for fold in self.fold_frames for f in fold), int)

    @property
    def held_out_rms_px(self) -> float:
        """RMS per pixel coordinate over every held-out corner (NaN for pose data)."""
        if self.held_out_squares is None:
            return float("nan")
        return float(np.sqrt(self.held_out_squares.sum() / max(self.held_out_coordinates.sum(), 1.0)))

    def frame_squares(self) -> np.ndarray:
        """Each held-out frame's squared pixel errors, summed over cameras and corners (px^2), in
        `held_out_frames` order: the per-sample losses of `jaxcal._selection`."""
        return self.held_out_squares.sum(0)[self.held_out_frames]


def fold_blocks(frames, folds: int) -> tuple[tuple[int, ...], ...]:
    """`frames` (in capture order) dealt into `folds` blocks of consecutive frames, as equal as can be."""
    frames = np.asarray(frames, int)
    return tuple(tuple(int(f) for f in block) for block in np.array_split(frames, min(folds, len(frames))))


def kfold_spread(
    solve: Callable[[HandEyeData], HandEyeResult],
    data: HandEyeData,
    result: HandEyeResult,
    *,
    folds: int = 10,
    min_frames: int = 8,
    frames=None,
) -> "KFoldSpread | None":
    """Re-solve `folds` times, each time without one block of consecutive frames, and predict
    the frames left out.

    The kept frames (or `frames`) are dealt into $K$ blocks in capture order (`fold_blocks`):
    consecutive frames share what changes slowly over a capture (the arm's configuration, its
    temperature), so a block held out is new to the fold, as a user's next frame is. Groups the
    full solve rejected stay out of every fold's solve; with pixels, every held-out frame's
    corners are predicted from its reported robot pose (`heldout.reprojection_squares`, the
    rejected views too: a model that rejects what the others fit pays for it here).

    **Arguments:** `solve` the (compiled) solver that gave `result` from
    `data`; `folds` $K$ (at most the number of frames); `min_frames`:
    below this many frames, return `None` (too few to leave any out); `frames`: the frames to
    deal (default: those the full solve kept; several models compared on one capture share them).

    **Returns:** a `KFoldSpread`, or `None`.
    """
    rejected = np.asarray(result.rejected)
    mask = np.asarray(data.mask)
    pixels = isinstance(data, HandEyePixels)
    per_group = mask.any(-1) if pixels else mask
    if frames is None:
        frames = np.flatnonzero((per_group & ~rejected).any(0))
    if len(frames) < max(min_frames, 2):
        return None
    base = mask & ~(rejected[..., None] if pixels else rejected)
    fold_frames = fold_blocks(frames, folds)
    K = len(fold_frames)
    X, Y, ok = [], [], []
    squares, coordinates = np.zeros(per_group.shape), np.zeros(per_group.shape)
    for block in fold_frames:
        m = base.copy()
        m[:, list(block)] = False
        r = solve(eqx.tree_at(lambda d: d.mask, data, np.asarray(m)))
        X.append(np.asarray(r.T_robot_cam))
        Y.append(np.asarray(r.T_robot_board))
        ok.append(bool(result_is(r.result)))
        if pixels:
            out = np.zeros(per_group.shape[1], bool)
            out[list(block)] = True
            s, n = reprojection_squares(np.asarray(r.T_cam_robot), np.asarray(r.T_robot_board), data, out)
            squares, coordinates = squares + s, coordinates + n
    X, Y = np.stack(X), np.stack(Y)
    eX = pose_difference(X, np.asarray(result.T_robot_cam)[None])  # (K, C, 6)
    eY = pose_difference(Y, np.asarray(result.T_robot_board)[None])  # (K, 6)

    def jackknife(e):
        return np.sqrt((K - 1) / K * np.sum((e - e.mean(0)) ** 2, axis=0))

    held = (squares, coordinates) if pixels else (None, None)
    return KFoldSpread(K, fold_frames, jackknife(eX), jackknife(eY), np.asarray(ok), *held)


@dataclass(frozen=True)
class HandEyeVerdict(Judgement):
    """Whether a hand-eye result can be trusted (the calibration's verdict's shape, `Judgement`).

    - `status`: `"ok"` or `"suspect"`.
    - `reasons`: why it is suspect (empty when ok).
    - `notes`: what a user should know that does not make it suspect
      (inconsistent or rejected frames, the k-fold spread against the std).
    """

    notes: tuple[str, ...]


def _message(code) -> str:
    if result_is(code, "nonlinear_max_steps_reached"):
        return "it stopped at its step cap"
    if result_is(code, "nonlinear_divergence"):
        return "it diverged"
    return "optimistix reported failure"


def _labels(frames, frame_names) -> str:
    names = [str(frame_names[f]) if frame_names is not None else str(f) for f in frames]
    return ", ".join(names[:20]) + (f" and {len(names) - 20} more" if len(names) > 20 else "")


def std_ratio(kfold: KFoldSpread, result: HandEyeResult) -> np.ndarray:
    """`(cameras, 2)`: k-fold spread over reported std, for translation and rotation (norms of 3)."""
    std = np.asarray(result.std_robot_cam)
    spread = kfold.std_robot_cam
    return np.stack(
        [
            np.linalg.norm(spread[:, :3], axis=1) / np.maximum(np.linalg.norm(std[:, :3], axis=1), 1e-300),
            np.linalg.norm(spread[:, 3:], axis=1) / np.maximum(np.linalg.norm(std[:, 3:], axis=1), 1e-300),
        ],
        axis=1,
    )


#: Estimated robot pose noise (per axis) beyond which the poses are taken not to be these images'
#: poses as read: a robot, even uncalibrated, is not this far off (m, deg).
MAX_ROBOT_SIGMA_M = 5e-3
MAX_ROBOT_SIGMA_DEG = 0.5
#: The option of `jaxcal handeye` that sets the robot pose noise model, for messages.
ROBOT_SIGMA_OPTIONS = (
    "--robot-noise exact|estimate|given (given: --config robot-sigma-mm=MM, robot-sigma-deg=DEG)"
)


def robot_noise(result: HandEyeResult) -> "tuple[float, float] | None":
    """`(translation mm, rotation deg)` per axis of the robot pose noise `result` used, or None (exact poses)."""
    if result.robot_sigma is None:
        return None
    s = np.asarray(result.robot_sigma)
    return float(1e3 * s[0]), float(np.degrees(s[3]))


def describe_robot_noise(result: HandEyeResult) -> str:
    """One phrase: the robot pose noise and where it came from (for messages and the console)."""
    noise = robot_noise(result)
    if noise is None:
        return "robot poses taken as exact"
    how = "estimated from the data" if bool(np.all(np.asarray(result.robot_sigma_estimated))) else "as given"
    return f"robot pose noise {noise[0]:.3g} mm / {noise[1]:.3g} deg per axis ({how})"


def implausible_robot_noise(
    result: HandEyeResult,
    max_translation_m: float = MAX_ROBOT_SIGMA_M,
    max_rotation_deg: float = MAX_ROBOT_SIGMA_DEG,
) -> bool:
    """Whether the robot noise was estimated and came out beyond any robot's (`MAX_ROBOT_SIGMA_*`):
    the corrections then absorb a misfit that is not noise (poses misread, not these images')."""
    noise = robot_noise(result)
    if noise is None or not bool(np.all(np.asarray(result.robot_sigma_estimated))):
        return False
    return noise[0] > 1e3 * max_translation_m or noise[1] > max_rotation_deg


def robot_correction_rms(result: HandEyeResult) -> float:
    """RMS over the kept frames of the robot corrections in units of the robot noise
    (`HandEyeResult.robot_rms`; at most about 1 when the noise is right), NaN for exact poses."""
    p = np.asarray(result.robot_rms, float)
    p = p[np.isfinite(p)]
    return float(np.sqrt(np.mean(p**2))) if p.size else float("nan")


def _misfit_reason(result: HandEyeResult, ratio: float) -> str:
    """Why the reprojection RMS is `ratio` times the detector's noise, by how the robot noise was set."""
    sigma = float(result.pixel_rms) / max(ratio, 1e-300)
    head = (
        f"the reprojection RMS, {float(result.pixel_rms):.3g} px, is {ratio:.1f} times the detector's "
        f"noise ({sigma:.3g} px) with the {describe_robot_noise(result)}: "
    )
    misreadings = (
        "check the poses' frames and units and, for quaternions, the component order, xyzw or wxyz: "
        "a reordered quaternion keeps every relative rotation angle, so the input check cannot see it"
    )
    if result.robot_sigma is None:
        return head + (
            "real robots' poses are noisy; estimate their noise from the data (`jaxcal handeye --robot-noise "
            "estimate`, `calibrate_hand_eye(..., estimate_robot_noise=True)`) or give it "
            f"({ROBOT_SIGMA_OPTIONS}); "
            "else the robot poses and the images do not fit one hand-eye transform (" + misreadings + ")"
        )
    if bool(np.all(np.asarray(result.robot_sigma_estimated))):
        return head + (
            "robot pose noise, estimated, does not explain it: the images do not fit one hand-eye "
            "transform and one rigid target (check the intrinsics, the target's dimensions and "
            "flatness, the camera's mount) or the poses are misread (" + misreadings + ")"
        )
    return head + (
        "the robot poses may be noisier than given: estimate it from the data (`--robot-noise estimate`); "
        "else the robot poses and the images do not fit one hand-eye transform (" + misreadings + ")"
    )


def assess_hand_eye(
    result: HandEyeResult,
    *,
    kfold: "KFoldSpread | None" = None,
    consistency: "MotionConsistency | None" = None,
    frame_names=None,
    camera_names=None,
    max_steps: int | None = None,
    max_residual_ratio: float = 3.0,
    max_start_rotation_deg: float = 5.0,
    max_start_translation_m: float = 0.05,
    max_rejected_fraction: float = 0.3,
    max_robot_sigma_m: float = MAX_ROBOT_SIGMA_M,
    max_robot_sigma_deg: float = MAX_ROBOT_SIGMA_DEG,
    held_out: "HeldOut | None" = None,
) -> HandEyeVerdict:
    """Plausibility checks of a hand-eye result (call outside jit).

    Suspect when: a Levenberg-Marquardt stage did not converge (its own
    result code and step count); the whitened residual RMS exceeds
    `max_residual_ratio` (pixels: the reprojection RMS is that many times the
    stated detector noise); a camera ends further than
    `max_start_rotation_deg` / `max_start_translation_m` from the closed-form
    start (the solve went where the data's closed form does not lead); or more
    than `max_rejected_fraction` of the observed frames were rejected; or the
    robot pose noise was estimated beyond `max_robot_sigma_m` /
    `max_robot_sigma_deg` per axis (the corrections absorbed a misfit that is no
    robot's error); or, with the robot noise given, the robot corrections'
    RMS in its units (`robot_correction_rms`) exceeds `max_residual_ratio`
    (the poses are noisier than given). The reason for a poor fit says how the robot noise was set:
    taken exact or given (then it may be the robot's noise, and the way to
    estimate it is named) or estimated (then it is not).

    With `held_out` (`heldout.HeldOut`: frames left out, predicted from their reported robot
    poses) the robot poses' noise is read off the held-out error (`HeldOut.level`), which tells
    the two apart: beyond `max_robot_sigma_m` / `max_robot_sigma_deg` per axis the poses do not
    belong to these images as read (suspect); within them the robot's poses are noisy at that
    level (a note, with the held-out error beside the in-sample one), and an exact-pose fit's
    residuals above the detector's noise are that noise, not a misfit.
    Notes: frames the rotation-angle pre-check found inconsistent, rejected
    frames, and a k-fold spread that differs from the reported std by more
    than 2x (either way).
    """
    cams = camera_names or [f"camera {c}" for c in range(np.shape(result.T_robot_cam)[0])]
    reasons = _solver_reasons(result, max_steps)
    limits = (max_robot_sigma_m, max_robot_sigma_deg)
    reasons += _fit_reasons(
        result, max_residual_ratio, *limits, explained=noise_explains_fit(held_out, *limits)
    )
    reasons += _start_reasons(result, cams, max_start_rotation_deg, max_start_translation_m)
    rejection, notes = _rejection(result, max_rejected_fraction, frame_names)
    reasons += rejection
    if held_out is not None:
        held_reasons, held_notes = _held_out_verdict(held_out, *limits)
        reasons, notes = reasons + held_reasons, notes + held_notes
    if consistency is not None and consistency.inconsistent.any():
        notes.append(
            f"frames {_labels(consistency.inconsistent_frames(), frame_names)}: the robot's rotation between "
            f"them and most other frames differs from the camera's by more than {consistency.tolerance_deg:g} deg"
        )
    if kfold is not None:
        notes += _kfold_notes(kfold, result, cams)
    return HandEyeVerdict("suspect" if reasons else "ok", tuple(reasons), tuple(notes))


def _solver_reasons(result: HandEyeResult, max_steps: int | None) -> list[str]:
    """A reason per Levenberg-Marquardt stage that did not converge (its code and steps)."""
    reasons = []
    steps = np.asarray(result.stage_steps)
    for i, name in enumerate(STAGES):
        code_i = jax.tree.map(lambda x, i=i: x[i], result.stage_result)
        if not result_is(code_i):
            cap = f" (max_steps={max_steps})" if max_steps is not None else ""
            reasons.append(
                f"the {name} solve did not converge: {_message(code_i)} after {int(steps[i])} steps{cap}"
            )
    return reasons


#: A held-out robot noise level (`HeldOut.level`, units of 1 mm / 0.1 deg) below which the poses read as exact.
EXACT_LEVEL = 0.1


def max_noise_level(
    max_sigma_m: float = MAX_ROBOT_SIGMA_M, max_sigma_deg: float = MAX_ROBOT_SIGMA_DEG
) -> float:
    """The limits of a robot's pose error in `HeldOut.level`'s units (1 mm and 0.1 deg per axis)."""
    return min(max_sigma_m / ROBOT_SIGMA_START[0], np.radians(max_sigma_deg) / ROBOT_SIGMA_START[1])


def noise_explains_fit(
    held_out: "HeldOut | None",
    max_sigma_m: float = MAX_ROBOT_SIGMA_M,
    max_sigma_deg: float = MAX_ROBOT_SIGMA_DEG,
) -> bool:
    """Whether frames left out are predicted as well as a robot's pose noise allows (`HeldOut.level`
    within the limits): then an exact-pose fit's residuals above the detector's noise are that noise."""
    return held_out is not None and held_out.level <= max_noise_level(max_sigma_m, max_sigma_deg)


def _held_out_verdict(
    held_out: "HeldOut", max_sigma_m: float, max_sigma_deg: float
) -> tuple[list[str], list[str]]:
    """`(reasons, notes)` of the held-out reprojection: the poses do not belong to these images (a
    reason), or the robot's poses are noisy at the level it reads as (a note)."""
    if not noise_explains_fit(held_out, max_sigma_m, max_sigma_deg):
        return [
            f"the robot poses do not belong to these images as read: {held_out.figures()}, which robot pose "
            f"errors of {held_out.noise_text()} would explain, more than any robot's (limits "
            f"{1e3 * max_sigma_m:g} mm, {max_sigma_deg:g} deg): check the arrangement, that the poses are the "
            "flange in the base frame and not inverted, the quaternion component order, the rotation unit"
        ], []
    if held_out.level < EXACT_LEVEL:
        return [], [
            f"{held_out.figures()}: the reported robot poses are as exact as these views resolve (their noise "
            f"reads as {held_out.noise_text()})"
        ]
    return [], [
        f"{held_out.figures()}: the robot's poses are noisy at this level, {held_out.noise_text()} (at most: "
        "the held-out error also holds the fit's own), within a robot's pose error; a result applied to "
        "new robot poses is off by about the held-out error"
    ]


def _fit_reasons(
    result: HandEyeResult, max_ratio: float, max_sigma_m: float, max_sigma_deg: float, explained: bool = False
) -> list[str]:
    """Reasons the data do not fit the model: a robot noise estimate beyond any robot's,
    robot corrections beyond the noise given, residuals beyond `max_ratio` times the noise
    (not for exact robot poses when the held-out error reads as a robot's noise: `explained`)."""
    reasons = []
    ratio = float(result.residual_rms)
    if implausible_robot_noise(result, max_sigma_m, max_sigma_deg) and explained:
        reasons.append(
            f"the robot noise estimated, {describe_robot_noise(result)}, is beyond any robot's pose error "
            f"(limits {1e3 * max_sigma_m:g} mm, {max_sigma_deg:g} deg) although frames left out read as a "
            "robot's noise (see the notes): the corrections absorb what the model leaves out (intrinsics, "
            "lens distortion, the target's flatness) and move the camera with it; exact poses or a given "
            "noise may predict new frames better (`--robot-noise auto` lists each model's held-out error; "
            "`exact` or `given` takes one)"
        )
    elif implausible_robot_noise(result, max_sigma_m, max_sigma_deg):
        reasons.append(
            f"the robot poses are off the images' by {describe_robot_noise(result)}, more than any robot's "
            f"pose error (limits {1e3 * max_sigma_m:g} mm, {max_sigma_deg:g} deg): the poses are "
            "not these images' as read (check the arrangement, that the poses are the flange in the base "
            "frame and not inverted, the quaternion component order, the rotation unit)"
        )
    estimated = bool(np.all(np.asarray(result.robot_sigma_estimated)))
    if not estimated and robot_correction_rms(result) > max_ratio:
        reasons.append(
            f"the robot poses needed corrections of {robot_correction_rms(result):.1f} times the "
            f"{describe_robot_noise(result)} (RMS over the frames; about 1 expected): their noise is larger "
            f"than that; estimate it from the data ({ROBOT_SIGMA_OPTIONS}: estimate)"
        )
    if ratio > max_ratio and not (explained and result.robot_sigma is None):
        if np.isfinite(float(result.pixel_rms)):
            reasons.append(_misfit_reason(result, ratio))
        else:
            reasons.append(
                f"the whitened pose-error RMS is {ratio:.1f} (about 1 expected): the robot poses and the "
                "board poses do not fit one hand-eye transform"
            )
    return reasons


def _start_reasons(
    result: HandEyeResult, cams, max_rotation_deg: float, max_translation_m: float
) -> list[str]:
    """A reason per camera whose pose ended beyond the limits from the closed-form start."""
    reasons = []
    X, X0 = np.asarray(result.T_robot_cam), np.linalg.inv(np.asarray(result.T_cam_robot_start))
    for c, name in enumerate(cams):
        rot = np.degrees(rotation_angle(X[c, :3, :3] @ X0[c, :3, :3].T))
        trans = np.linalg.norm(X[c, :3, 3] - X0[c, :3, 3])
        if rot > max_rotation_deg or trans > max_translation_m:
            reasons.append(
                f"{name}'s pose ended {rot:.1f} deg and {1e3 * trans:.0f} mm from the closed-form start "
                f"(limits {max_rotation_deg:g} deg, {1e3 * max_translation_m:.0f} mm)"
            )
    return reasons


def _rejection(result: HandEyeResult, max_fraction: float, frame_names) -> tuple[list[str], list[str]]:
    """`(reasons, notes)` of the frames rejected as outliers: a reason beyond `max_fraction`
    of the observed frames, else a note naming them."""
    rejected = np.asarray(result.rejected).any(0)
    observed = rejected | np.isfinite(np.asarray(result.group_rms)).any(0)
    n_obs = max(int(observed.sum()), 1)
    if rejected.sum() > max_fraction * n_obs:
        return [
            f"{int(rejected.sum())} of {n_obs} frames were rejected as outliers "
            f"(more than {100 * max_fraction:.0f}%)"
        ], []
    if rejected.any():
        return [], [f"rejected as outliers: frames {_labels(np.flatnonzero(rejected), frame_names)}"]
    return [], []


def _kfold_notes(kfold: "KFoldSpread", result: HandEyeResult, cams) -> list[str]:
    """A note per camera and component whose k-fold spread is off the reported std by over 2x."""
    notes = []
    r = std_ratio(kfold, result)
    for c, name in enumerate(cams):
        for k, what in enumerate(("translation", "rotation")):
            if not 0.5 <= r[c, k] <= 2.0:
                notes.append(
                    f"{name} {what}: the {kfold.folds}-fold spread is {r[c, k]:.2f} times the reported std; "
                    + (
                        "the std is optimistic (unmodelled errors): trust the k-fold spread"
                        if r[c, k] > 2.0
                        else "the std is conservative"
                    )
                )
    return notes
