"""The refinement's residuals tested at its solution: the score tests of a rolling shutter
and of a lens and intrinsics beyond the given ones, and the test of errors that repeat along the capture or
between the views of one pose, with the covariance that then accounts for them
(`jaxcal.stages.refine` runs them; the verdict names what they find).

`corners`: the refinement's views (`stages._refine._Corners`: per view its camera, target,
capture index `pose`, camera time `t_cam` and corner `ids`, in the refinement's view order).
"""

import dataclasses

import jax
import numpy as np

from .._correction import INTRINSIC_NAMES, ParameterLayout
from .._diagnostics import residual_correlation
from .._distributions import chi2_sf, normal_isf
from .._lsq import larger_covariance_np, newey_west_lags
from .._refine import RefineProblem
from ..records import ErrorCorrelation, IntrinsicsTest, LensTest, ShutterTest
from . import _programs
from ._setup import Setup

#: A lag whose own correlation is this many sigmas is one the kernel sandwich spans.
SIGNIFICANT_LAG_Z = 3.0


def score_tests(
    setup: Setup, corners, problem: RefineProblem, res, layout: ParameterLayout, free
) -> tuple[tuple[ShutterTest, ...] | None, LensTest | None, IntrinsicsTest | None, np.ndarray | None]:
    """The score tests of a global-shutter refinement (one program, `_programs.score_tests`).

    Per camera, the rolling shutter its residuals point to (`jaxcal._diagnostics.line_delay_test`):
    the line delay (s per row), the readout it implies (times the image height, s) and its
    size in standard deviations. For the first camera, when its radial distortion was held
    (the metadata's lens), the radial distortion they point to (`jaxcal._diagnostics.lens_test`):
    $k_1, k_2$, the shift they imply at the image's corner (px) and their size in sigmas; when its
    focal lengths and principal point were held, the ones they point to
    (`jaxcal._diagnostics.intrinsics_test`), likewise. All `None` when a line delay was
    modelled, or without an encoder log (each view's angle is then an unknown of its own).
    Fourth: with the intrinsics tested, how the solution (its flattened parameters) moves per px of
    the held fx, fy, cx, cy (`jaxcal._diagnostics.IntrinsicsTest.sensitivity`, `(n, 4)`), else None."""
    if problem.line_delay0_s is not None or setup.kind.per_view_angles:
        return None, None, None, None
    shutter, radial, pinhole = jax.device_get(_programs.score_tests()(problem, res))
    tests = tuple(
        ShutterTest(
            camera=v.camera.name,
            line_delay_s=float(shutter.line_delay_s[c]),
            readout_s=float(shutter.line_delay_s[c]) * v.camera.height,
            sigmas=float(shutter.sigmas[c]),
        )
        for c, v in enumerate(corners.used)
    )
    intr = layout.index("intr")
    held = [not free[intr[INTRINSIC_NAMES.index(k)]] for k in INTRINSIC_NAMES]
    cam = corners.used[0].camera
    K = np.asarray(problem.K0, np.float64)
    # The image's corners, normalised: the farthest a corner can be from the principal point.
    edges = np.array(
        [
            ((x - K[0, 2]) / K[0, 0], (y - K[1, 2]) / K[1, 1])
            for x in (0.0, cam.width - 1.0)
            for y in (0.0, cam.height - 1.0)
        ]
    )
    lens = None
    if all(held[INTRINSIC_NAMES.index(k)] for k in ("k1", "k2")):
        k1, k2 = (float(x) for x in radial.distortion)
        rho2 = float(np.max(np.sum(edges**2, axis=1)))
        shift = float(np.sqrt(rho2) * K[0, 0] * abs(k1 * rho2 + k2 * rho2**2))
        lens = LensTest(camera=cam.name, k1=k1, k2=k2, shift_px=shift, sigmas=float(radial.sigmas))
    intrinsics = sensitivity = None
    if all(held[INTRINSIC_NAMES.index(k)] for k in ("fx", "fy", "cx", "cy")):
        sensitivity = np.asarray(pinhole.sensitivity, np.float64)
        dfx, dfy, dcx, dcy = (float(x) for x in pinhole.step)
        moved = np.stack([dfx * edges[:, 0] + dcx, dfy * edges[:, 1] + dcy], axis=1)
        intrinsics = IntrinsicsTest(
            camera=cam.name,
            fx_px=dfx,
            fy_px=dfy,
            cx_px=dcx,
            cy_px=dcy,
            shift_px=float(np.max(np.linalg.norm(moved, axis=1))),
            sigmas=float(normal_isf(chi2_sf(float(pinhole.chi2), 4))),
        )
    return tests, lens, intrinsics, sensitivity


#: The correlation test's lags along the capture (frames).
CORRELATION_LAGS = 8


def corner_pairs(corners, lags: int = CORRELATION_LAGS) -> tuple[np.ndarray, ...]:
    """Per lag $k = 1..$`lags`, the same corner of one target and camera in views $k$ frames
    apart (capture indices) within one run of the capture (at most $k + 1/2$ typical frame
    intervals apart in time: a sweep, not the next one): rows `(view_a, corner_a, view_b,
    corner_b)` into the refinement's views and their corner slots."""
    cam, tgt, pose = (np.asarray(a, int) for a in (corners.camera, corners.target, corners.pose))
    t = np.asarray(corners.t_cam, np.float64)
    at = {(c, m, f): v for v, (c, m, f) in enumerate(zip(cam, tgt, pose))}
    steps = [
        (t[w] - t[v])
        for v, (c, m, f) in enumerate(zip(cam, tgt, pose))
        if (w := at.get((c, m, f + 1))) is not None
    ]
    frame_s = float(np.median(steps)) if steps else 0.0
    out = [[] for _ in range(lags)]
    for v, (c, m, f) in enumerate(zip(cam, tgt, pose)):
        for k in range(1, lags + 1):
            w = at.get((c, m, f + k))
            if w is None or not abs(t[w] - t[v]) <= (k + 0.5) * frame_s:
                continue
            _, a, b = np.intersect1d(corners.ids[v], corners.ids[w], assume_unique=True, return_indices=True)
            out[k - 1].append(np.stack([np.full(a.size, v), a, np.full(b.size, w), b], axis=1))
    return tuple(np.concatenate(rows) if rows else np.zeros((0, 4), int) for rows in out)


def _by_pose(corners, values: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """`values` (per view, first axis) summed over the views of each pose, in capture order,
    and each pose's views."""
    pose = np.asarray(corners.pose, int)
    keys = np.unique(pose)
    groups = [np.flatnonzero(pose == k) for k in keys]
    return np.stack([values[g].sum(axis=0) for g in groups]), groups


def error_correlation(corners, res, limits, information):
    """The refinement's residuals tested for errors that repeat along the capture and between
    the views of one pose, and, where either test passes `limits.correlation_sigmas`, the
    covariance that accounts for them: `(ErrorCorrelation | None, cov | None, cov_views | None)`,
    the free parameters' covariance to take and the one it replaces (`None`, `None`: keep
    `res.cov`). `res`: the `RefineResult` (read only); `information()`: its views' information
    (`jaxcal._diagnostics.view_information`), asked for only where a test passes.

    Along the capture, `jaxcal._diagnostics.residual_correlation` on the pairs of `corner_pairs` (up to
    `CORRELATION_LAGS`): Ljung-Box's $Q$ over them, and the one-sided test of errors that repeat,
    $\\sum_{k \\le L} z_k / \\sqrt L$ over Newey-West's $L$ lags for the capture's poses (4 for 100 to
    420; a correlation that fades beyond them adds only noise to the sum). Between the views of one pose
    (several cameras or targets at one capture index), the score test of their shared error:
    $c_{uv} = s_u^T B s_v$ for the views' gradients $s$ and the bread $B = (J^TJ)^+$, summed over
    the poses' pairs of views over $\\sqrt{\\sum c_{uv}^2}$. The covariance is then the views'
    (`RefineResult.cov`), or the kernel (HAC) sandwich of the poses along the capture
    (`jaxcal._lsq.hac_covariance`: one cluster per pose, Newey-West's lags or twice the
    test's longest lag of $z_k \\ge 3$, whichever is longer) along the directions where that is larger by
    more than its sampling spread $2\\sqrt{2 / G_{eff}}$ (`jaxcal._lsq.larger_covariance_np`).
    None without per-view gradients (per-view angles) or pairs."""
    if res.view_scores is None or not corners.ids:
        return None, None, None
    pairs = corner_pairs(corners)
    if not sum(len(p) for p in pairs):
        return None, None, None
    used = np.asarray(res.inlier) & (np.asarray(res.weights) > 0.0)
    rho, z, count = residual_correlation(np.asarray(res.residuals), used, pairs)
    lags = len(z)
    q = float(np.sum(z**2))
    free = np.flatnonzero(np.asarray(res.free))
    V = len(corners.pose)
    scores = np.asarray(res.view_scores, np.float64)[:V]
    sigma2 = float(res.sigma_px) ** 2
    bread = np.asarray(res.cov_model, np.float64)[np.ix_(free, free)] / max(sigma2, 1e-300)
    _, groups = _by_pose(corners, scores)
    tested = min(lags, newey_west_lags(len(groups)))  # the one-sided test spans Newey-West's lags
    sigmas = float(np.sum(z[:tested]) / np.sqrt(tested))
    cross = [scores[u] @ bread @ scores[v] for g in groups for i, u in enumerate(g) for v in g[i + 1 :]]
    pose_sigmas = (
        float(np.sum(cross) / np.sqrt(np.sum(np.square(cross)))) if cross and np.any(cross) else None
    )
    record = ErrorCorrelation(
        autocorrelation=tuple(float(x) for x in rho),
        z=tuple(float(x) for x in z),
        pairs=tuple(int(x) for x in count),
        q_statistic=q,
        dof=lags,
        p_value=float(chi2_sf(q, lags)),
        sigmas=sigmas,
        pose_sigmas=pose_sigmas,
    )
    if max(sigmas, pose_sigmas or 0.0) < limits.correlation_sigmas:
        return record, None, None
    significant = [k + 1 for k in range(lags) if z[k] >= SIGNIFICANT_LAG_Z]
    pose_scores, _ = _by_pose(corners, scores)
    info, _ = _by_pose(corners, np.asarray(information(), np.float64)[:V])
    # Bartlett's weights fall linearly to zero at lags + 1: twice the longest lag still
    # correlated keeps half its weight there (at most a quarter of the poses).
    reach = min(2 * max(significant, default=0), len(groups) // 4)
    kernel_lags = max(newey_west_lags(len(groups)), reach)
    hac, g_eff = _programs.hac_covariance()(bread, pose_scores, info, kernel_lags)
    before = np.asarray(res.cov, np.float64)[np.ix_(free, free)]
    larger = larger_covariance_np(before, np.asarray(hac), 2.0 * np.sqrt(2.0 / max(float(g_eff), 2.0)))
    return dataclasses.replace(record, kernel_lags=kernel_lags), larger, before
