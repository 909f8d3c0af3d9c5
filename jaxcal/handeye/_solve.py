"""Hand-eye's solve step: the compiled solver of `calibrate_hand_eye`, its solve of the observed
data, the k-fold spread and the rejected frames with their reasons."""

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import lru_cache, partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._exported import stored_jit
from .._handeye import (
    HandEyePixels,
    HandEyeResult,
    KFoldSpread,
    calibrate_hand_eye,
    describe_robot_noise,
    initialise_hand_eye,
    kfold_spread,
    px_text,
)
from .._handeye.solve import HAND_EYE_OPTIONS
from ..io.handeye import repeated_poses
from ._noise import MIN_FRAMES, NoiseChoice, solve_models
from ._observe import Observed

#: Outlier threshold of `calibrate_hand_eye` (times the median group RMS); reported with rejections.
OUTLIER_THRESHOLD = 3.0
#: The least median the threshold multiplies (px): a view is rejected only above `OUTLIER_THRESHOLD`
#: times this too. Corners refined to a few hundredths of a pixel make the median small enough that a
#: clean but steep view (0.09 px against a median of 0.028 px, docs/performance.md, "Chessboard
#: corners") would pass 3x it; a robot pose off by a millimetre moves the corners by pixels.
MIN_OUTLIER_PX = 0.1


@lru_cache(maxsize=4)
def hand_eye_solver(max_steps: int = 200) -> Callable:
    """`jax.jit(calibrate_hand_eye)` at `max_steps` as `solve(data, reject_outliers, estimate_robot_noise,
    start=None)`, one per value (shapes are bucketed by the caller; the flags and the start are traced,
    so every setting shares the program of its data: with noisy robot poses, estimated or given, one
    program). `start`: `calibrate_hand_eye`'s, `(T_cam_robot, T_robot_board)` or None (the closed form)."""

    def hand_eye(data, reject, estimate, start, use_start):
        # The closed form runs only where no start is given (a branch, not a second program).
        start = jax.lax.cond(use_start, lambda: start, lambda: initialise_hand_eye(data))
        return calibrate_hand_eye(
            data,
            reject_outliers=reject,
            # Exact robot poses are their own program (no corrections): nothing to estimate there.
            estimate_robot_noise=estimate if data.robot_sigma is not None else False,
            options=replace(HAND_EYE_OPTIONS, max_steps=max_steps),
            outlier_threshold=OUTLIER_THRESHOLD,
            min_outlier_scale=min_outlier_scale(data),
            start=start,
        )

    # Runs many times per process (k-fold, bootstrap): XLA's optimisations pay for themselves.
    key = (max_steps, OUTLIER_THRESHOLD, MIN_OUTLIER_PX)
    program = stored_jit(hand_eye, "hand_eye", key, compiler_options=None)

    def solve(data, reject, estimate, start=None):
        if start is None:
            X = np.broadcast_to(np.eye(4), (data.mask.shape[0], 4, 4))
            return program(data, reject, estimate, (X, np.eye(4)), np.asarray(False))
        return program(
            data, reject, estimate, tuple(np.asarray(T, np.float64) for T in start), np.asarray(True)
        )

    return solve


def min_outlier_scale(data):
    """`calibrate_hand_eye`'s `min_outlier_scale` (whitened): `MIN_OUTLIER_PX` over the pixel noise
    (pixels), at least the solver's own 0.1; pose data keep 0.1."""
    if not isinstance(data, HandEyePixels):
        return 0.1
    return jnp.maximum(MIN_OUTLIER_PX / data.sigma_px, 0.1)


def rejection_reasons(result, observations, threshold: float) -> dict[int, str]:
    """`{frame: reason}` for every rejected frame, from the final per-view RMS."""
    rejected = np.asarray(result.rejected)
    rms = np.asarray(result.group_rms) * observations.sigma_px
    kept = np.where(rejected, np.nan, rms)
    median = float(np.nanmedian(kept)) if np.isfinite(kept).any() else float("nan")
    out = {}
    for f in np.flatnonzero(rejected.any(0)):
        cams = np.flatnonzero(rejected[:, f])
        worst = float(np.nanmax(rms[cams, f]))
        out[int(f)] = (
            f"reprojection RMS {px_text(worst)} against a median of {median:.3g} px over the kept views "
            f"(rejected above {threshold:g}x the median, and above {threshold * MIN_OUTLIER_PX:g} px); "
            "its robot pose does not fit the others"
        )
    return out


def kfold_from_optimum(
    solver: Callable, data, result: HandEyeResult, estimate, folds: int, frames=None
) -> KFoldSpread | None:
    """`kfold_spread` of `solver`'s `result` on `data`, each fold starting from the full data's optimum
    (and its robot noise estimate): a fold is a small step away, a few Levenberg-Marquardt steps
    instead of a solve from the closed form, to the same optimum within the solver's tolerance.
    The folds leave the rejected groups out already: plain solves (the robot noise estimated again
    in each when `estimate`, as the whole estimator is being replicated), same compiled program.
    `frames`: the frames to deal into folds (`kfold_spread`'s; default: those `result` kept)."""
    start = (result.T_cam_robot, result.T_robot_board)
    if estimate:
        data = eqx.tree_at(lambda d: d.robot_sigma, data, result.robot_sigma)
    return kfold_spread(
        lambda d: solver(d, False, estimate, start),
        data,
        result,
        folds=folds,
        min_frames=MIN_FRAMES,
        frames=frames,
    )


@dataclass(frozen=True, eq=False)
class Solved:
    """The solve of the observed data.

    - `result`: the `HandEyeResult` of the robot-noise model kept (NumPy leaves; padded frames
      beyond the observed frames).
    - `kfold`: its k-fold spread (with the held-out reprojection), or None when no folds were asked for.
    - `rejected`: `{frame index: reason}` of the frames the solve rejected.
    - `solver`: the compiled solver (`hand_eye_solver`), for the verdict's re-solves.
    - `seconds`: `solve` (every model's solve), `kfold` (every model's k-fold).
    - `noise`: the robot-noise models solved and the one kept (`NoiseChoice`).
    """

    result: HandEyeResult
    kfold: KFoldSpread | None
    rejected: dict[int, str]
    solver: Callable
    seconds: dict[str, float]
    noise: NoiseChoice


def solve(observed: Observed, *, folds: int, max_steps: int, log: Callable[[str], None]) -> Solved:
    """`calibrate_hand_eye` on the observed data (outliers rejected) with each robot-noise model
    `observed.noise` asks for, each one's spread over `folds` folds of frames (0: none), and the
    model kept (`_noise.solve_models`)."""
    solver = hand_eye_solver(max_steps)
    obs = observed.observations
    seconds = {}
    choice = solve_models(
        solver, obs.data, observed.noise, folds, obs.sigma_px, partial(kfold_from_optimum, solver), seconds
    )
    fit = choice.fit
    log(describe_robot_noise(fit.result))  # the model kept and why: the verdict's note
    rejected = rejection_reasons(fit.result, obs, OUTLIER_THRESHOLD)
    capture = observed.capture
    for f, earlier in repeated_poses(capture.T_base_ee).items():
        if f in rejected:
            rejected[f] += (
                f"; it repeats frame {capture.frames[earlier]}'s pose exactly (a pose logged twice?)"
            )
    return Solved(fit.result, fit.kfold, rejected, solver, seconds, choice)
