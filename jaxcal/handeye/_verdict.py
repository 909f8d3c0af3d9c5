"""Hand-eye's verdict step: `assess_hand_eye` on the solve, then what the input itself explains
(robot poses noisier than given, a misreading of the poses that fits, intrinsics self-calibrated)."""

import time
from collections.abc import Callable
from dataclasses import replace

import jax
import numpy as np

from .._distributions import chi2_sf, normal_isf
from .._handeye import (
    ROBOT_SIGMA_OPTIONS,
    HandEyeVerdict,
    assess_hand_eye,
    describe_robot_noise,
    implausible_robot_noise,
    noise_explains_fit,
    robot_correction_rms,
    robot_noise,
)
from .._npgeom import matrix_to_quaternion, quaternion_to_matrix
from ..errors import HandEyeInputError
from ..io.handeye import HandEyeCapture
from ._noise import NoiseChoice, model_data
from ._observe import Observed
from ._solve import Solved

#: Whitened residual RMS above which the poses and images are taken not to fit (`assess_hand_eye`'s
#: `max_residual_ratio`) and `diagnose_misfit` tries the common misreadings of the input.
MISFIT_RATIO = 3.0


def misreadings(capture: HandEyeCapture) -> list[tuple[str, np.ndarray, bool]]:
    """The input mistakes that keep every relative rotation angle, so that the input check
    passes and only the fit can see them: `(what to fix, T_base_ee, eye_in_hand)` each (an
    arrangement swapped or the poses inverted; a matrix's rotation transposed; a quaternion's
    components in another order)."""
    T = np.asarray(capture.T_base_ee, np.float64)
    other = "eye_to_hand" if capture.eye_in_hand else "eye_in_hand"
    out = [
        (
            f"handeye.json field 'arrangement' is {other!r} (or the poses are inverted: poses.csv must hold "
            "the flange in the base frame, T_base_ee, not T_ee_base)",
            T,
            not capture.eye_in_hand,
        )
    ]
    if capture.pose_format == "matrix":
        Tt = T.copy()
        Tt[:, :3, :3] = np.swapaxes(T[:, :3, :3], -1, -2)
        out.append(
            (
                "poses.csv's rotation blocks are transposed (m01 holds what belongs in m10: the matrices' "
                "rotations written by columns; write row by row, m00 m01 m02 m03 m10 ...)",
                Tt,
                capture.eye_in_hand,
            )
        )
    if capture.pose_format == "xyz_quat":
        q = np.stack([matrix_to_quaternion(R) for R in T[:, :3, :3]])  # as read: x, y, z, w
        for shift, holds in ((-1, "w, x, y, z"), (1, "y, z, w, x")):
            R = quaternion_to_matrix(np.roll(q, shift, axis=-1))
            Ta = T.copy()
            Ta[:, :3, :3] = R
            out.append(
                (
                    f"the columns that poses.csv's header names qx, qy, qz, qw hold {holds} (label the "
                    "columns in the order the values are written)",
                    Ta,
                    capture.eye_in_hand,
                )
            )
    return out


def misfit(result) -> bool:
    """The poses and images do not fit: the reprojection RMS is over `MISFIT_RATIO` times the
    detector's noise, the robot noise estimated to absorb it is beyond any robot's, or (robot
    noise given) the robot corrections are over `MISFIT_RATIO` times it."""
    given = result.robot_sigma is not None and not bool(np.all(np.asarray(result.robot_sigma_estimated)))
    return (
        float(result.residual_rms) > MISFIT_RATIO
        or implausible_robot_noise(result)
        or (given and robot_correction_rms(result) > MISFIT_RATIO)
    )


def fits(result) -> bool:
    """The whitened residual RMS is finite and at most `MISFIT_RATIO`, with a plausible robot noise."""
    ratio = float(result.residual_rms)
    return np.isfinite(ratio) and ratio <= MISFIT_RATIO and not implausible_robot_noise(result)


def diagnose_misfit(observed: Observed, result, solve: Callable, model: str) -> str | None:
    """When the poses and images do not fit one hand-eye transform, re-solve under each common
    misreading of the input (`misreadings`; `Observed.reobserve` builds the data) and name the
    one that fits, if one does: an arrangement swapped or poses inverted, a quaternion's
    components in another order. Each with the robot-noise `model` of `result` (`_noise.MODELS`).
    Same compiled solver: the arrangement is data and the shapes are the bucket's."""
    given = float(result.residual_rms)
    estimate = model == "estimate"
    sigma = None if model != "given" else tuple(np.asarray(result.robot_sigma)[[0, 3]])
    for fix, T, eye_in_hand in misreadings(observed.capture):
        try:
            alt = observed.reobserve(T, eye_in_hand)
        except HandEyeInputError:
            continue
        r = jax.tree.map(np.asarray, solve(model_data(alt.data, model, sigma)[0], True, estimate))
        if fits(r) and (float(r.residual_rms) < 0.1 * given or implausible_robot_noise(result)):
            noise = (
                f"; {describe_robot_noise(r)} that way against {describe_robot_noise(result)}"
                if estimate
                else ""
            )
            return (
                f"the data fit if {fix}: reprojection RMS {float(r.pixel_rms):.3g} px that way against "
                f"{float(result.pixel_rms):.3g} px as given{noise}"
            )
    return None


def robot_noise_hint(verdict, data, result, solve, log) -> HandEyeVerdict:
    """With the robot noise given and a poor fit (a misfit, or frames rejected): re-solve with the
    noise estimated (the same compiled program) and, when that fits, say that the robot poses are
    noisier than given, by how much, and which options set it."""
    if result.robot_sigma is None or bool(np.all(np.asarray(result.robot_sigma_estimated))):
        return verdict
    rejected = int(np.asarray(result.rejected).any(0).sum())
    if not (misfit(result) or rejected):
        return verdict
    r = jax.tree.map(np.asarray, solve(model_data(data, "estimate", None)[0], True, True))
    kept = int(np.asarray(r.rejected).any(0).sum())
    if not fits(r) or (kept >= max(rejected, 1) and not misfit(result)):
        return verdict
    given, est = robot_noise(result), robot_noise(r)
    if est[0] <= given[0] and est[1] <= given[1]:
        return verdict
    text = (
        f"the robot poses are noisier than given ({given[0]:.3g} mm / {given[1]:.3g} deg per axis): "
        f"estimated from the data, {est[0]:.3g} mm / {est[1]:.3g} deg, with which the reprojection RMS is "
        f"{float(r.pixel_rms):.3g} px ({float(result.pixel_rms):.3g} px as given) and {kept} frame(s) are "
        f"rejected ({rejected} as given); `--robot-noise estimate` uses the estimate ({ROBOT_SIGMA_OPTIONS})"
    )
    log(text)
    if misfit(result):
        return replace(verdict, reasons=verdict.reasons + (text,))
    return replace(verdict, notes=verdict.notes + (text,))


def input_hints(verdict, observed: Observed, solved: Solved, log) -> tuple[HandEyeVerdict, dict]:
    """The verdict with what the input itself explains: robot poses noisier than given
    (`robot_noise_hint`), the misreading that fits when the poses and images do not
    (`diagnose_misfit`), the images' scale against the robot's (`image_scale`), a lens beyond
    the given one (`lens_tests`), and intrinsics self-calibrated from the capture, which make any
    result suspect; and per camera name the scale's and the lens test's figures (`result.json`)."""
    result, solve = solved.result, solved.solver
    verdict = robot_noise_hint(verdict, observed.observations.data, result, solve, log)
    # An exact-pose fit whose frames left out are predicted as a robot's noise allows is no misfit.
    misread = None
    if misfit(result) and not (result.robot_sigma is None and noise_explains_fit(solved.noise.fit.held_out)):
        misread = diagnose_misfit(observed, result, solve, solved.noise.fit.model)
        if misread:
            log(f"the poses fit the images once read differently: {misread}")
            verdict = replace(verdict, reasons=(misread, *verdict.reasons))  # the cause, before its symptoms
    scales, lenses = image_scale(observed, solved), lens_tests(observed)
    std_mm = 1e3 * np.linalg.norm(np.asarray(solved.result.std_robot_cam)[:, :3], axis=1)
    claimed = {c.name: float(std_mm[i]) for i, c in enumerate(observed.capture.cameras)}
    # A scale read off poses that are misread says nothing of the target or the lens.
    found = () if misread else scale_reasons(scales, claimed)
    if found:
        log(found[0])
        verdict = replace(verdict, status="suspect", reasons=verdict.reasons + found)
    checks = {
        name: {"image_scale": {"factor": k, "std": std, "target_distance_m": d}} for name, k, std, d in scales
    }
    for name, k1, k2, shift, sigmas in lenses:
        checks.setdefault(name, {})["lens_test"] = {"k1": k1, "k2": k2, "shift_px": shift, "sigmas": sigmas}
    found = lens_reasons(lenses)
    if found:
        log(found[0])
        verdict = replace(verdict, status="suspect", reasons=verdict.reasons + found)
    cameras = observed.capture.cameras
    tested = {t[0] for t in lenses}
    untested = [
        c.name for c, k in zip(cameras, observed.intrinsics) if k.source == "given" and c.name not in tested
    ]
    if untested:
        note = (
            f"camera {', '.join(untested)}: the lens test did not run (it needs 3 views of {LENS_MIN_CORNERS} "
            "corners or more; a single tag shows 4): a lens beyond handeye.json's would go unnamed"
        )
        verdict = replace(verdict, notes=verdict.notes + (note,))
    guessed = [c.name for c, k in zip(cameras, observed.intrinsics) if k.source == "self-calibrated"]
    if guessed:
        # The solve, its standard deviations and the k-fold spread all hold K exact: a focal length
        # calibrated from the same few views moves the camera along its axis unseen. Not trustworthy as is.
        verdict = replace(
            verdict,
            status="suspect",
            reasons=verdict.reasons
            + (
                f"camera {', '.join(guessed)}: intrinsics self-calibrated from these images; the standard "
                "deviations and the k-fold spread hold K exact and leave out its error, which can dominate "
                "(a rendered 16-frame capture: 7 mm off against 0.1 mm std); give K from a separate intrinsics "
                "calibration",
            ),
        )
    return verdict, checks


#: The images' scale against the robot's (`image_scale`): off by more than this fraction and by
#: `SCALE_Z` standard errors, the target's size or the focal length is wrong. The solve cannot see
#: it (its standard deviations and k-fold spread hold both exact): the camera moves along its
#: axis by the fraction times the target's distance.
SCALE_TOLERANCE = 0.005
SCALE_Z = 5.0
#: ... or, below the tolerance, off by enough to move the camera this many times the translation's
#: claimed standard deviation (a square 0.4 % small: 1.7 mm against a claimed 0.2 mm).
SCALE_CLAIMS = 2.0
#: Frames a camera needs for its scale (7 unknowns, three equations per frame, and a jackknife).
SCALE_MIN_FRAMES = 6


def image_scale(observed: Observed, solved: Solved) -> list[tuple[str, float, float, float]]:
    """Per camera `(name, k, std, distance)`: PnP's distances over those the robot's motion implies
    (1 when the target's size and the focal length are right; a target declared 2 % too small:
    0.98), its standard error, and the target's mean distance (m). PnP's translations scaled by $s = 1/k$ follow the robot: at the solve's
    camera rotation $R_x$ the hand-eye translations are linear in the camera's and the board's
    offsets and in $s$: per frame (robot pose $R_a, t_a$, PnP
    translation $t_p$) $R_a^T t_y - t_x - s R_x t_p = R_a^T t_a$ eye-in-hand, $R_a t_y - t_x -
    s R_x t_p = -t_a$ eye-to-hand; least squares over the frames the solve kept. The standard
    error is the larger of least squares' and the jackknife's over frames (a robot pose's error
    is shared by its frame's three equations). The mean distance goes into the camera's offset:
    $s$ rests on how the target's distance varies over the frames."""
    obs, capture = observed.observations, observed.capture
    T_be, rejected = np.asarray(obs.data.T_base_ee)[: obs.frames], set(solved.rejected)
    out = []
    for c, camera in enumerate(capture.cameras):
        frames = [f for f, pose in enumerate(obs.poses[c]) if pose is not None and f not in rejected]
        if len(frames) < SCALE_MIN_FRAMES:
            continue
        R_x = np.asarray(solved.result.T_robot_cam)[c, :3, :3]
        A, y = [], []
        for f in frames:
            R_a, t_a = T_be[f, :3, :3], T_be[f, :3, 3]
            M, b = (R_a.T, R_a.T @ t_a) if capture.eye_in_hand else (R_a, -t_a)
            A.append(np.hstack([-np.eye(3), M, -(R_x @ obs.poses[c][f].T_cam_target[:3, 3])[:, None]]))
            y.append(b)
        A, y = np.vstack(A), np.concatenate(y)
        scale = lambda rows: np.linalg.lstsq(A[rows], y[rows], rcond=None)[0]  # noqa: E731
        x, F = scale(slice(None)), len(frames)
        var = np.sum((A @ x - y) ** 2) / (len(y) - A.shape[1])
        left_out = np.array([scale(np.r_[0 : 3 * i, 3 * i + 3 : 3 * F])[6] for i in range(F)])
        jackknife = (F - 1) / F * np.sum((left_out - left_out.mean()) ** 2)
        std = np.sqrt(max(var * np.linalg.pinv(A.T @ A)[6, 6], jackknife))
        distance = np.mean([np.linalg.norm(obs.poses[c][f].T_cam_target[:3, 3]) for f in frames])
        out.append((camera.name, float(1.0 / x[6]), float(std / x[6] ** 2), float(distance)))
    return out


def scale_reasons(scales, claimed_mm: dict[str, float] | None = None) -> tuple[str, ...]:
    """What `image_scale` finds wrong: a scale off by `SCALE_Z` standard errors and either by
    `SCALE_TOLERANCE`, or by enough to move the camera (the fraction times the target's distance)
    `SCALE_CLAIMS` times the translation's claimed standard deviation (`claimed_mm`, per camera)."""
    out = []
    for name, s, std, distance in scales:
        if not s > 0:  # no scale: the motions the fit left do not correlate (a misfit named elsewhere)
            continue
        off, move = abs(s - 1.0), 1e3 * abs(s - 1.0) * distance
        claim = (claimed_mm or {}).get(name)
        big = off > SCALE_TOLERANCE or (claim is not None and move > SCALE_CLAIMS * claim)
        if off > SCALE_Z * std and big:
            against = "" if claim is None else f", against a claimed {claim:.2f} mm"
            d = 1 if 100 * std >= 0.1 or 100 * off >= 1.0 else 2  # a fine scale: two digits
            out.append(
                f"camera {name}: PnP's distances are {100 * (s - 1):+.{d}f} % (+/- {100 * std:.{d}f} %) off those the "
                "robot's motion implies: the target's size (handeye.json target.square_length / marker_length) or the "
                "camera's focal length (K) is wrong, or the robot's own kinematics are; the camera's position is then "
                f"off along its axis by about that fraction of the target's distance ({move:.1f} mm at "
                f"{distance:.2f} m{against}), which neither the standard deviations nor the k-fold spread show"
                + _unit_factor(s)
            )
    return tuple(out)


def _unit_factor(s: float) -> str:
    """A hint where the scale `s` is a unit's factor (10, 100, 1000, 25.4) to within 10 %: a unit
    misdeclared, not a target or a lens a few percent off."""
    ratio = max(s, 1.0 / s)
    factor = next((f for f in (10.0, 100.0, 1000.0, 25.4) if abs(ratio / f - 1.0) < 0.1), None)
    if factor is None:
        return ""
    return (
        f"; that is a factor of {factor:g}: a unit, not a size, is wrong (the robot poses' translations in "
        "another unit than handeye.json's poses.translation_unit, or the target's size not in metres)"
    )


#: A lens beyond the given one (`lens_tests`) is named past this many standard deviations and this
#: shift (px) at the farthest corner seen: a hand-eye result claims tens of micrometres, and a lens
#: 0.01 off in k1 (0.15 px there, 10-11 sigmas on a 16-frame capture) moves the camera 0.11 mm
#: against a claimed 0.025 (`jaxcal calibrate`'s limits, 10 sigmas and 0.5 px, are a robot's).
LENS_SIGMAS = 5.0
LENS_PX = 0.1
#: Corners a view needs for the lens test: a single tag's four leave two residuals beside its pose,
#: and a radial pattern over a tag's few pixels is nearly a pose change (ViSP's tag capture: k1 +0.12,
#: k2 -0.26 at 5.1 sigmas, coefficients the chessboard's 8 views of the same camera put at +0.02, +0.23).
LENS_MIN_CORNERS = 6


def lens_tests(observed: Observed) -> list[tuple[str, float, float, float, float]]:
    """Per camera with a given K: `(name, k1, k2, shift_px, sigmas)`, the score test of a radial
    distortion beyond handeye.json's. The pixels the solve fits are undistorted with the given lens;
    a lens left out leaves residuals that grow with the distance from the image's centre, which
    each view's PnP pose takes up only in part. Per view (its pose free, pinhole model at PnP's
    pose): residuals $r$, their derivatives $J_p$ along the pose's six increments and $J_d$ along
    $(k_1, k_2)$, $x_d = x(1 + k_1\\rho^2 + k_2\\rho^4)$. Summed over views, $D = \\sum J_d^TJ_d -
    J_d^TJ_p(J_p^TJ_p)^{-1}J_p^TJ_d$ and $g = \\sum J_d^T(I - P_p)r$; the step $\\hat d = D^{-1}g$,
    $S = g^TD^{-1}g/\\hat\\sigma^2 \\sim \\chi^2_2$ under a right lens (stated as a normal's
    quantile, `sigmas`); `shift_px` is the step's move at the farthest corner seen."""
    obs, capture = observed.observations, observed.capture
    data, out = obs.data, []
    pixels, mask, points = np.asarray(data.pixels), np.asarray(data.mask), np.asarray(data.board_points)
    for c, (camera, intr) in enumerate(zip(capture.cameras, observed.intrinsics)):
        if intr.source != "given":
            continue
        K = np.asarray(data.K[c], np.float64)
        D, g, rr, n, views, reach = np.zeros((2, 2)), np.zeros(2), 0.0, 0, 0, 0.0
        for f, pose in enumerate(obs.poses[c]):
            if pose is None or mask[c, f].sum() < LENS_MIN_CORNERS:
                continue
            T = np.asarray(pose.T_cam_target, np.float64)
            P = points[mask[c, f]] @ T[:3, :3].T + T[:3, 3]
            x, y, z = P[:, 0] / P[:, 2], P[:, 1] / P[:, 2], P[:, 2]
            fx, fy = K[0, 0], K[1, 1]
            r = (pixels[c, f][mask[c, f]] - np.stack([fx * x + K[0, 2], fy * y + K[1, 2]], -1)).reshape(-1)
            # d(u, v)/dP (pinhole), then along the pose's increments: dP = dt - [P]x dtheta.
            dudP = np.zeros((len(P), 2, 3))
            dudP[:, 0, 0], dudP[:, 0, 2] = fx / z, -fx * x / z
            dudP[:, 1, 1], dudP[:, 1, 2] = fy / z, -fy * y / z
            skew = np.zeros((len(P), 3, 3))
            skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -P[:, 2], P[:, 1], -P[:, 0]
            skew -= skew.transpose(0, 2, 1)
            Jp = np.concatenate([dudP, -dudP @ skew], axis=2).reshape(-1, 6)
            rho2 = x * x + y * y
            reach = max(reach, float(rho2.max()))
            Jd = np.stack([np.stack([fx * x, fy * y], -1) * rho2[:, None] ** k for k in (1, 2)], -1).reshape(
                -1, 2
            )
            A_inv = np.linalg.pinv(Jp.T @ Jp)
            B = Jp.T @ Jd
            D += Jd.T @ Jd - B.T @ A_inv @ B
            g += Jd.T @ r - B.T @ A_inv @ (Jp.T @ r)
            rr += float(r @ r - (Jp.T @ r) @ A_inv @ (Jp.T @ r))
            n, views = n + len(r), views + 1
        if views < 3 or n <= 6 * views + 2:
            continue
        step = np.linalg.solve(D, g)
        score = float(g @ step)
        sigma2 = max(rr - score, 1e-300) / (n - 6 * views - 2)
        k1, k2 = float(step[0]), float(step[1])
        # At the farthest corner seen: beyond it the fitted k2 extrapolates (a right lens's step of
        # noise would read as pixels there).
        shift = float(np.sqrt(reach) * np.mean(np.diag(K)[:2]) * abs(k1 * reach + k2 * reach**2))
        sigmas = float(normal_isf(chi2_sf(score / sigma2, 2)))
        out.append((camera.name, k1, k2, shift, sigmas))
    return out


def lens_reasons(tests) -> tuple[str, ...]:
    """What `lens_tests` finds wrong: a lens beyond the given one past `LENS_SIGMAS` and `LENS_PX`."""
    return tuple(
        f"camera {name}: the residuals grow with the distance from the image's centre, as a lens's radial "
        f"distortion does ({sigmas:.0f} sigmas): a distortion of k1 {k1:+.3g}, k2 {k2:+.3g} beyond handeye.json's "
        f"would shift the farthest corners seen by {shift:.2f} px, and the solve fits the camera's pose to them, which "
        "neither the standard deviations nor the k-fold spread show; give handeye.json cameras[].distortion from "
        "the camera's own calibration"
        for name, k1, k2, shift, sigmas in tests
        if sigmas > LENS_SIGMAS and shift >= LENS_PX
    )


def noise_model_note(choice: NoiseChoice) -> str:
    """What the robot-noise model is and why: asked, chosen by held-out reprojection, or the default."""
    fit = choice.fit
    return f"robot-noise model {fit.model!r}, {choice.basis}: {describe_robot_noise(fit.result)}"


def judge(
    observed: Observed, solved: Solved, *, max_steps: int, log
) -> tuple[HandEyeVerdict, dict[str, float], dict]:
    """`assess_hand_eye` of the solve (residuals, convergence, k-fold against std, the rotation-angle
    check), then `input_hints`; returns the verdict, `{"hints": seconds}` and `input_hints`' checks."""
    capture = observed.capture
    verdict = assess_hand_eye(
        solved.result,
        kfold=solved.kfold,
        consistency=observed.observations.consistency,
        frame_names=capture.frames,
        camera_names=[f"camera {c.name}" for c in capture.cameras],
        max_steps=max_steps,
        held_out=solved.noise.fit.held_out,
    )
    verdict = replace(verdict, notes=capture.notes + verdict.notes + (noise_model_note(solved.noise),))
    t0 = time.perf_counter()
    verdict, checks = input_hints(verdict, observed, solved, log)
    return verdict, {"hints": time.perf_counter() - t0}, checks
