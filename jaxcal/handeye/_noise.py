"""The robot-noise model of a hand-eye solve: the one asked for, or the one that predicts frames it
did not see best.

Three models of the robot's reported poses:

- `exact`: the poses as reported, no corrections;
- `given`: a 6-DOF correction per pose with the Gaussian prior given (mm and deg per axis);
- `estimate`: the same, the prior's two scales estimated from the data (`jaxcal._handeye.noise`).

`auto` (the default) solves with each (the estimate first, then the given noise where sigmas
were given, then exact poses), runs each one's k-fold over the same blocks of consecutive
frames, predicting every frame left out from its reported robot pose with no correction
(`jaxcal._handeye.kfold_spread`), and keeps the estimate unless another model predicts those
frames better by jaxcal's rule for choosing a model (`jaxcal._selection`: by more than its
`CV_GAIN`, and by `MIN_Z` standard errors of the per-frame differences). The estimate is the
default because it is the efficient estimator where the robot's errors are independent per pose
(rendered captures at 0-3 mm, docs/handeye.md); exact poses win where the corrections absorb
what is no robot's noise (a real RealSense capture: 7.0 px held out with the noise estimated at
5.3 mm / 0.59 deg per axis, 2.0 px with exact poses). Without folds (`folds=0`) or with fewer
than 8 frames there is nothing to compare on, and `auto` takes the estimate and says so.
"""

import time
from collections.abc import Callable
from dataclasses import dataclass

import equinox as eqx
import jax
import numpy as np

from .._handeye import (
    ROBOT_SIGMA_START,
    HandEyePixels,
    HandEyeResult,
    HeldOut,
    KFoldSpread,
    describe_robot_noise,
    px_text,
    robot_noise,
    robot_pixel_scale,
)
from .._handeye.checks import check_sigma
from .._handeye.heldout import ABSURD_PX
from .._selection import CV_GAIN, MIN_Z, improves_on_samples, paired_z

#: `robot_noise` settings: `auto` chooses among the models by held-out reprojection.
MODES = ("auto", "exact", "estimate", "given")
#: The models `auto` compares, in the order it visits them (the default first).
MODELS = ("estimate", "given", "exact")
#: Fewest frames `auto` compares the models on (and the k-fold spread's `min_frames`).
MIN_FRAMES = 8


@dataclass(frozen=True)
class RobotNoiseSetting:
    """What was asked of the robot-noise model: `mode` (one of `MODES`) and, for `given` (and
    `auto`'s given candidate), `sigma` `(translation m, rotation rad)` per axis."""

    mode: str
    sigma: tuple[float, float] | None = None

    @property
    def models(self) -> tuple[str, ...]:
        """The models to solve with, in `MODELS` order."""
        if self.mode != "auto":
            return (self.mode,)
        return tuple(m for m in MODELS if m != "given" or self.sigma is not None)


def robot_noise_setting(
    robot_noise: str | None = None,
    translation: float | None = None,
    rotation: float | None = None,
    estimate_robot_noise: bool | None = None,
) -> RobotNoiseSetting:
    """The `RobotNoiseSetting` of `calibrate_hand_eye_capture`'s arguments.

    `robot_noise` None: `given` when the sigmas are given, else `auto`; `estimate_robot_noise`
    (the previous release's switch): True `estimate`, False `exact` (`given` with sigmas).

    **Raises:** `ValueError` naming the arguments that disagree or are missing;
    `NoiseLevelError` for a sigma that is not finite and positive.
    """
    if (translation is None) != (rotation is None):
        raise ValueError("robot_sigma_translation and robot_sigma_rotation must be given together")
    sigma = None if translation is None else (float(translation), float(rotation))
    if sigma is not None:
        check_sigma("robot_sigma_translation and robot_sigma_rotation", sigma)
    if estimate_robot_noise is not None:
        legacy = "given" if sigma is not None else ("estimate" if estimate_robot_noise else "exact")
        if robot_noise is not None and robot_noise != legacy:
            raise ValueError(
                f"robot_noise={robot_noise!r} and estimate_robot_noise={estimate_robot_noise!r} disagree; "
                "give robot_noise only"
            )
        robot_noise = legacy
    if robot_noise is None:
        robot_noise = "given" if sigma is not None else "auto"
    if robot_noise not in MODES:
        raise ValueError(f"robot_noise must be one of {list(MODES)}, got {robot_noise!r}")
    if robot_noise == "given" and sigma is None:
        raise ValueError("robot_noise='given' needs robot_sigma_translation and robot_sigma_rotation")
    if robot_noise in ("exact", "estimate") and sigma is not None:
        raise ValueError(
            f"robot_noise={robot_noise!r} takes no robot_sigma_translation / robot_sigma_rotation (they are "
            "the noise of 'given', and of auto's given candidate)"
        )
    return RobotNoiseSetting(robot_noise, sigma)


def model_data(data, model: str, sigma: tuple[float, float] | None):
    """`(data, estimate)`: `data` with the robot noise of `model` (exact: None; estimate: its start,
    `ROBOT_SIGMA_START`; given: `sigma`) and whether the solve estimates it."""
    if model == "exact":
        return eqx.tree_at(lambda d: d.robot_sigma, data, None, is_leaf=lambda x: x is None), False
    value = ROBOT_SIGMA_START if model == "estimate" else sigma
    s = np.repeat(np.asarray(value, np.asarray(data.T_base_ee).dtype), 3)  # `robot_sigma6`'s, on the host
    return eqx.tree_at(lambda d: d.robot_sigma, data, s, is_leaf=lambda x: x is None), model == "estimate"


@dataclass(frozen=True, eq=False)
class NoiseModelFit:
    """One robot-noise model's solve: `model` (one of `MODELS`), its `result` (NumPy leaves),
    its k-fold (`kfold`, with the held-out reprojection) and `held_out` (None without folds)."""

    model: str
    result: HandEyeResult
    kfold: KFoldSpread | None
    held_out: HeldOut | None

    @property
    def noise(self) -> "tuple[float, float] | None":
        """`(mm, deg)` per axis of the noise the solve used, None for exact poses."""
        return robot_noise(self.result)

    def describe(self) -> str:
        """`model: held-out X px (in-sample Y px), noise` for messages."""
        held = "" if self.held_out is None else f"held out {px_text(self.held_out.rms_px)}, "
        return (
            f"{self.model}: {held}in-sample {px_text(float(self.result.pixel_rms))}, "
            f"{describe_robot_noise(self.result)}"
        )


@dataclass(frozen=True, eq=False)
class NoiseChoice:
    """The robot-noise models solved and the one kept: `fits` (in `MODELS` order), `chosen` (its
    index), `setting` (what was asked) and `basis`, why it was kept, in words."""

    fits: tuple[NoiseModelFit, ...]
    chosen: int
    setting: RobotNoiseSetting
    basis: str

    @property
    def fit(self) -> NoiseModelFit:
        return self.fits[self.chosen]


def held_out(
    result: HandEyeResult, kfold: KFoldSpread | None, data: HandEyePixels, sigma_px: float
) -> HeldOut | None:
    """The `HeldOut` of a solve and its k-fold (None without one)."""
    if kfold is None or kfold.held_out_squares is None:
        return None
    frames = np.zeros(np.shape(data.mask)[1], bool)
    frames[kfold.held_out_frames] = True
    scale = robot_pixel_scale(result.T_cam_robot, result.T_robot_board, data, frames)
    return HeldOut(
        float(kfold.held_out_rms_px),
        float(result.pixel_rms),
        float(sigma_px),
        scale,
        kfold.folds,
        int(frames.sum()),
    )


def choose(fits: tuple[NoiseModelFit, ...], setting: RobotNoiseSetting, folds: int) -> tuple[int, str]:
    """`(index, basis)` of the model kept: the one asked, or (`auto`) the estimate unless another
    predicts the frames left out better by `jaxcal._selection.improves_on_samples`."""
    if setting.mode != "auto":
        return 0, f"as asked (robot_noise={setting.mode!r})"
    if any(f.held_out is None for f in fits):
        why = "no folds (folds=0)" if folds < 2 else f"fewer than {MIN_FRAMES} frames kept"
        return 0, f"the default, with nothing to compare the models on ({why})"
    best, words = 0, [f"{fits[0].model} {px_text(fits[0].held_out.rms_px)}"]
    for k in range(1, len(fits)):
        a, b = fits[best], fits[k]
        z = paired_z(a.kfold.frame_squares(), b.kfold.frame_squares())
        kept = improves_on_samples(
            a.kfold.frame_squares(), b.kfold.frame_squares(), a.held_out.rms_px, b.held_out.rms_px
        )
        if (
            a.held_out.rms_px >= ABSURD_PX > b.held_out.rms_px
        ):  # a's frames far off the image: no test weighs it
            kept, why = True, f"{a.model} predicts the frames left out far off the image"
        elif b.held_out.rms_px >= a.held_out.rms_px:  # worse on the frames left out: no gain to weigh
            why = f"worse than {a.model} on the frames left out"
        else:
            why = (
                f"better than {a.model} by {z:.2g} standard errors of the per-frame differences ({MIN_Z:g} "
                f"needed, with a gain over {100 * CV_GAIN:g} %)"
            )
        words.append(
            f"{b.model} {px_text(b.held_out.rms_px)}, " + ("kept" if kept else "not kept") + f": {why}"
        )
        best = k if kept else best
    return best, f"chosen by held-out reprojection ({'; '.join(words)})"


def solve_models(
    solver: Callable,
    data: HandEyePixels,
    setting: RobotNoiseSetting,
    folds: int,
    sigma_px: float,
    kfold_of: Callable,
    seconds: dict | None = None,
) -> NoiseChoice:
    """Solve with each of `setting.models`, run each one's k-fold over the same frames (those any
    model kept) with `kfold_of(data, result, estimate, folds, frames)`, and choose (`choose`).
    `seconds`: filled with the wall time of the solves (`solve`) and of the folds (`kfold`)."""
    seconds = {} if seconds is None else seconds
    t0 = time.perf_counter()
    solved = []
    for model in setting.models:
        d, estimate = model_data(data, model, setting.sigma)
        solved.append((model, d, estimate, jax.tree.map(np.asarray, solver(d, True, estimate))))
    observed = np.asarray(data.mask).any(-1)
    kept = np.any([(observed & ~np.asarray(r.rejected)).any(0) for *_, r in solved], axis=0)
    frames = np.flatnonzero(kept)
    seconds["solve"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    fits = []
    for model, d, estimate, r in solved:
        kf = kfold_of(d, r, estimate, folds, frames) if folds >= 2 and len(frames) >= MIN_FRAMES else None
        fits.append(NoiseModelFit(model, r, kf, held_out(r, kf, d, sigma_px)))
    fits = tuple(fits)
    seconds["kfold"] = time.perf_counter() - t0
    chosen, basis = choose(fits, setting, folds)
    return NoiseChoice(fits, chosen, setting, basis)
