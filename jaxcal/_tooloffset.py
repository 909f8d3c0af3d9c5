"""Tool offset by arc fitting (seed method 2), with the iterative axis correction.

A stylus on the tool is rotated about a preset axis (the flange's $z$ axis
through the current estimate of the tool centre). Its tip moves on a circle
whose radius is the distance of the tip from the axis, i.e. the error of the
estimate. A camera looking along the axis sees that circle; fitting it gives
the radius and, from the tip's angle on the circle at rotation 0, the
direction of the error. Because the camera is not calibrated to the robot,
that direction is known only up to the camera's roll about the axis: the
correction is applied with a nominal roll, the axis moved, and the rotation
repeated until the radius is below a threshold or stops changing. With a
roll error $\\epsilon$ each step alone would shrink the error by $2\\sin(\\epsilon/2)$
(and diverge beyond $60^\\circ$); but the second arc shows what the first move did, and
the loop learns from it: written as complex numbers, the measured offset is $m$ times the
true one ($m$ turns by the roll's error and scales by the image scale's), so a move $a$
between offsets $o_1$ and $o_2$ gives $m = (o_1 - o_2)/a$ exactly, and every later move is
$o/m$ (`_learned`). A roll off by any angle, or an image scale off by up to 5x, then costs one
rotation more than the right one; the result reports the roll and scale found.

The second offset (stylus axis to the camera's principal point) is iterated
the same way: the vector from the principal point to the stylus's image is
converted to metres and the stylus moved by it until the two coincide.

Pure, jittable pieces: `fit_circle` (closed-form Kasa start, then
Levenberg-Marquardt on the geometric distances, for 2D pixels or 3D points)
and `estimate_offset`. The loops (`calibrate_tool_offset`,
`align_to_principal_point`) call a user `measure` function (the robot and
camera, or a simulation: `jaxcal.sim.tool`) and run outside jit.
"""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from . import _lsq
from ._geometry import normalize, orthonormal_basis, safe_norm
from ._lsq import LMOptions
from .errors import ToolOffsetInputError

MIN_POINTS = 3
MIN_SPAN_DEG = 30.0
#: The loops learn the image's turn and scale (`_learned`) from a move this many times `tol` or
#: longer: shorter ones are within the arcs' noise.
LEARN_MOVE = 20.0


class CircleFit(eqx.Module):
    """A circle fitted to points (pixels, or 3D points in m).

    **Fields:**
    - `centre` `(d,)`, `radius` `()` in the points' units; `normal` `(3,)` the
      plane's unit normal (the image $z$ for 2D points).
    - `rms`: RMS geometric residual; `result`, `num_steps`: optimistix's.
    """

    centre: Float[Array, " d"]
    normal: Float[Array, "3"]
    radius: Float[Array, ""]
    rms: Float[Array, ""]
    result: optx.RESULTS
    num_steps: Int[Array, ""]


class _CircleParams(eqx.Module):
    centre: Float[Array, "3"]
    tilt: Float[Array, "2"]
    radius: Float[Array, ""]


def _as_3d(points: Float[Array, "n d"]) -> Float[Array, "n 3"]:
    if points.shape[-1] == 2:
        return jnp.concatenate([points, jnp.zeros_like(points[:, :1])], axis=1)
    return points


def _kasa(points: Float[Array, "n 3"], w: Float[Array, " n"], planar: bool):
    """Closed-form start: plane by PCA (or $z$ if `planar`), circle by Kasa's linear fit in it.

    In plane coordinates $(x, y)$: $x^2 + y^2 = 2ax + 2by + c$ is linear in
    $(a, b, c)$; centre $(a, b)$, radius $\\sqrt{c + a^2 + b^2}$.
    """
    m = jnp.sum(points * w[:, None], 0) / jnp.maximum(jnp.sum(w), 1.0)
    d = points - m
    if planar:
        n = jnp.array([0.0, 0.0, 1.0])
        B = jnp.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])
    else:
        _, V = jnp.linalg.eigh((d * w[:, None]).T @ d)
        n = V[:, 0]
        B = orthonormal_basis(n)
    xy = d @ B
    A = jnp.concatenate([2.0 * xy, jnp.ones_like(xy[:, :1])], axis=1) * w[:, None]
    z = jnp.linalg.lstsq(A, jnp.sum(xy**2, axis=1) * w)[0]
    centre = m + B @ z[:2]
    radius = jnp.sqrt(jnp.maximum(z[2] + z[0] ** 2 + z[1] ** 2, 0.0))
    return centre, n, radius


def _circle_residuals(params: _CircleParams, args):
    points, w, n0, planar = args
    B0 = orthonormal_basis(n0)
    n = n0 if planar else normalize(n0 + B0 @ params.tilt)
    d = points - params.centre
    height = d @ n
    in_plane = safe_norm(d - height[:, None] * n)
    res = jnp.stack([jnp.zeros_like(height) if planar else height, in_plane - params.radius], axis=1)
    return res * w[:, None]


#: `fit_circle`'s solver settings (residuals in the points' unit).
CIRCLE_OPTIONS = LMOptions(rtol=1e-10, atol=1e-10, max_steps=50)


def fit_circle(
    points: Float[Array, "n d"],
    mask: Bool[Array, " n"] | None = None,
    *,
    options: LMOptions = CIRCLE_OPTIONS,
) -> CircleFit:
    """Fit a circle to 2D points (pixels, in the image plane) or 3D points (a circle in space).

    Minimises $\\sum_k h_k^2 + (\\|p_k - c\\|_\\perp - r)^2$ ($h_k$ the height of
    point $k$ above the circle's plane, zero for 2D points) by
    Levenberg-Marquardt from Kasa's algebraic fit. Exact on noise-free points
    of any arc; pure and jittable (`d` is static).

    **Arguments:**
    - `points`: `(n, 2)` or `(n, 3)`; rows where `mask` is False are ignored.
    - `options`: the solver's `LMOptions` (the residuals are in the points'
      unit, not whitened: tight tolerances).

    **Returns:** a `CircleFit` (centre in the points' dimension); its `result` is `singular`
    with fewer than `MIN_POINTS` points.
    """
    planar = points.shape[-1] == 2
    w = jnp.ones(points.shape[0]) if mask is None else mask.astype(points.dtype)
    P = _as_3d(jnp.where(w[:, None] > 0, points, 0.0))
    c0, n0, r0 = _kasa(P, w, planar)
    params0 = _CircleParams(centre=c0, tilt=jnp.zeros(2), radius=r0)
    sol = _lsq.solve(_circle_residuals, params0, (P, w, n0, planar), options)
    p = sol.value
    n = n0 if planar else normalize(n0 + orthonormal_basis(n0) @ p.tilt)
    r = _circle_residuals(p, (P, w, n0, planar))
    rms = jnp.sqrt(jnp.sum(r**2) / jnp.maximum(jnp.sum(w), 1.0))
    centre = p.centre[:2] if planar else p.centre
    # Fewer than three points fit circles without end: no solver's success makes one of them the answer.
    result = optx.RESULTS.where(jnp.sum(w) >= MIN_POINTS, sol.result, optx.RESULTS.singular)
    return CircleFit(
        centre=centre,
        normal=n,
        radius=p.radius,
        rms=rms,
        result=result,
        num_steps=sol.stats["num_steps"],
    )


class OffsetEstimate(eqx.Module):
    """One arc measurement turned into a correction of the tool centre.

    **Fields:**
    - `offset`: the tip's offset from the rotation axis, in the axis frame's
      $xy$ plane (m), as seen through the nominal camera roll.
    - `radius`: the arc's radius (m); `radius_px`: in the measurement's units.
    - `handedness`: +1 if the image angle grows with the rotation angle, else -1.
    - `circle`: the `CircleFit`.
    """

    offset: Float[Array, "2"]
    radius: Float[Array, ""]
    radius_px: Float[Array, ""]
    handedness: Float[Array, ""]
    circle: CircleFit


def estimate_offset(
    points: Float[Array, "n d"],
    angles: Float[Array, " n"],
    mask: Bool[Array, " n"] | None = None,
    *,
    metres_per_unit: float | Float[Array, ""] = 1.0,
    camera_roll: float | Float[Array, ""] = 0.0,
) -> OffsetEstimate:
    """The tip's offset from the rotation axis from its image positions during one rotation.

    The tip at rotation angle $\\theta_k$ sits at image angle
    $\\psi_k = \\psi_0 + s\\,\\theta_k$ about the fitted centre ($s = \\pm 1$, the
    handedness of the view, found from the data). With the camera rolled by
    $\\gamma$ about the axis, the tip's direction in the axis frame at
    $\\theta = 0$ is $\\phi_0 = s(\\psi_0 - \\gamma)$ and the offset is
    $r(\\cos\\phi_0, \\sin\\phi_0)$. Pure and jittable.

    3D points (the tip in the camera frame, m: stereo, or PnP of a marker on the
    tool) are fitted by a circle in space and expressed in the circle's plane
    with the axes $e_1$ = the camera's $x$ projected on the plane and
    $e_2 = n \\times e_1$, $n$ the plane normal pointing away from the camera;
    for a camera looking along the axis these are the image axes.

    **Arguments:**
    - `points`: `(n, 2)` tip positions in the image (px), or in any planar units;
      or `(n, 3)` positions in the camera frame (use `metres_per_unit=1`).
    - `angles`: `(n,)` commanded rotation angles (rad) about the axis.
    - `metres_per_unit`: the image scale at the tip (m/px, e.g. depth / focal length).
    - `camera_roll`: $\\gamma$ (rad), the image angle (from the image's $x$ towards its $y$) at which
      the axis frame's $+x$ direction appears: for a camera looking along the axis with its $x$ turned
      by $\\rho$ from the axis frame's (`jaxcal.sim.tool.ToolScene(camera_roll=rho)`), $\\gamma = -\\rho$
      (`ToolScene.image_roll`). It need not be right: the loops learn it from their moves (module docstring).
    """
    w = jnp.ones(points.shape[0]) if mask is None else mask.astype(points.dtype)
    circle = fit_circle(points, None if mask is None else mask)
    d = points - circle.centre
    if points.shape[-1] == 3:
        n = circle.normal * jnp.where(circle.normal[2] < 0.0, -1.0, 1.0)
        e1 = normalize(jnp.array([1.0, 0.0, 0.0]) - n[0] * n)
        d = d @ jnp.stack([e1, jnp.cross(n, e1)], axis=1)
    psi = jnp.arctan2(d[:, 1], d[:, 0])
    # Handedness: the sign of the correlation of psi with theta, through unit phasors.
    z = jnp.exp(1j * psi)
    dz = z[1:] * jnp.conj(z[:-1])
    dtheta = angles[1:] - angles[:-1]
    ww = w[1:] * w[:-1]
    s = jnp.where(jnp.sum(ww * jnp.angle(dz) * dtheta) >= 0.0, 1.0, -1.0)
    psi0 = jnp.angle(jnp.sum(w * jnp.exp(1j * (psi - s * angles))))
    phi0 = s * (psi0 - camera_roll)
    radius = circle.radius * metres_per_unit
    return OffsetEstimate(
        offset=radius * jnp.stack([jnp.cos(phi0), jnp.sin(phi0)]),
        radius=radius,
        radius_px=circle.radius,
        handedness=s,
        circle=circle,
    )


def validate_arc_points(points, angles, mask=None) -> None:
    """Raise a `ToolOffsetInputError` if `points`/`angles` cannot give an offset."""
    P = np.asarray(points, np.float64)
    a = np.asarray(angles, np.float64)
    if P.ndim != 2 or P.shape[1] not in (2, 3):
        raise ToolOffsetInputError(f"points must have shape (n, 2) or (n, 3), got {P.shape}")
    if a.shape != (P.shape[0],):
        raise ToolOffsetInputError(f"{P.shape[0]} points but angles has shape {a.shape} (lengths must match)")
    m = np.ones(P.shape[0], bool) if mask is None else np.asarray(mask, bool)
    if m.shape != (P.shape[0],):
        raise ToolOffsetInputError(f"mask has shape {m.shape}, expected {(P.shape[0],)}")
    bad = m & ~np.all(np.isfinite(P), axis=1)
    if bad.any():
        raise ToolOffsetInputError(f"points: non-finite point at index {int(np.flatnonzero(bad)[0])}")
    if not np.all(np.isfinite(a)):
        raise ToolOffsetInputError("angles: non-finite entries")
    if m.sum() < MIN_POINTS:
        raise ToolOffsetInputError(f"only {int(m.sum())} points, an arc needs at least {MIN_POINTS}")
    span = np.degrees(np.ptp(a[m]))
    if span < MIN_SPAN_DEG:
        raise ToolOffsetInputError(
            f"angles: the rotation spans {span:.1f} deg; rotate at least {MIN_SPAN_DEG:g} deg about the axis"
        )


_estimate = jax.jit(estimate_offset)


class ToolOffsetResult(eqx.Module):
    """The outcome of the iterative tool-offset calibration (NumPy; from the loop outside jit).

    **Fields:**
    - `tcp`: the final tool-centre estimate in the axis frame's $xy$ plane (m).
    - `radii`: the measured radius (m) at every iteration (the error of the
      estimate used for that rotation); `tcps`: the estimate at every iteration.
    - `converged`: the last radius is below `tol` or changed by less than `tol_change`.
    - `iterations`: how many rotations were measured.
    - `camera_roll_found`, `metres_per_unit_found`: the roll and image scale the moves showed
      (`_learned`; the ones given where no move was long enough to tell): give them next time.
    """

    tcp: np.ndarray
    tcps: np.ndarray
    radii: np.ndarray
    converged: bool
    iterations: int
    camera_roll_found: float
    metres_per_unit_found: float


def _learned(m: complex, before: complex, after: complex, move: complex) -> complex:
    """The measured offsets' turn and scale against the true ones, `m` (measured = m x true, as
    x + iy), from the offsets `before` and `after` one `move`: `after = before - m move`. A pair
    whose `m` is beyond 0.2-5 in size (the noise of a short move, a tip found elsewhere) keeps the
    last `m`."""
    new = (before - after) / move
    return new if 0.2 < abs(new) < 5.0 else m


def _check_roll(camera_roll) -> None:
    """`camera_roll` is an angle in radians: finite, within one turn (a larger one is degrees)."""
    if not (np.isfinite(camera_roll) and abs(camera_roll) <= 2 * np.pi):
        raise ToolOffsetInputError(
            f"camera_roll: the image angle of the axis frame's +x, in radians within one turn, got {camera_roll!r}"
            + (f" (degrees? {np.radians(camera_roll):.4g} rad)" if np.isfinite(camera_roll) else "")
        )


def calibrate_tool_offset(
    measure: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray | None]],
    tcp0,
    *,
    metres_per_unit: float,
    camera_roll: float = 0.0,
    tol: float = 5e-5,
    tol_change: float = 1e-6,
    max_iter: int = 10,
) -> ToolOffsetResult:
    """Seed 2: rotate about the axis through the estimate, fit the arc, move the axis, repeat.

    **Arguments:**
    - `measure(tcp)`: rotates the tool about the axis through `tcp` (m, the
      axis frame's $xy$) and returns `(points (n, 2) or (n, 3), angles (n,), mask
      or None)`: the tip's image positions (px) or camera-frame positions (m)
      at the commanded angles.
    - `tcp0`: the starting estimate (m), e.g. the design value.
    - `metres_per_unit`, `camera_roll`: see `estimate_offset`.
    - `tol` (m): stop when the radius is below it; `tol_change` (m): or when
      two consecutive radii differ by less; `max_iter`: at most this many rotations.

    **Returns:** a `ToolOffsetResult`. Raises `ToolOffsetInputError` on a bad measurement.
    """
    _check_roll(camera_roll)
    tcp = np.asarray(tcp0, np.float64).copy()
    if tcp.shape != (2,) or not np.all(np.isfinite(tcp)):
        raise ToolOffsetInputError(
            f"tcp0: the start's x, y in the axis frame (m), 2 finite numbers, got {tcp0!r}"
        )
    if not (np.isfinite(metres_per_unit) and metres_per_unit > 0):
        raise ToolOffsetInputError(
            f"metres_per_unit: the length of one unit of the measured points (m per px at the tool; 1.0 for points "
            f"in metres), a positive number, got {metres_per_unit!r}"
        )
    if not (tol >= 0 and tol_change >= 0 and max_iter >= 1):
        raise ToolOffsetInputError(
            f"tol, tol_change must not be negative and max_iter at least 1: {tol}, {tol_change}, {max_iter}"
        )
    tcps, radii = [tcp.copy()], []
    converged, m, last, hand = False, 1.0 + 0.0j, None, 1.0
    for k in range(max_iter):
        points, angles, mask = measure(tcp)
        try:
            validate_arc_points(points, angles, mask)
        except ToolOffsetInputError as e:
            if not k:
                raise
            step = 1e3 * np.linalg.norm(tcps[-1] - tcps[-2])
            raise ToolOffsetInputError(
                f"rotation {k + 1}, after the axis moved {step:.3g} mm to {tcp.tolist()} m (the last arc's radius "
                f"{1e3 * radii[-1]:.3g} mm): {e}; a move this large for that arc: is metres_per_unit right?"
            ) from None
        est = _estimate(
            jnp.asarray(points, jnp.float64),
            jnp.asarray(angles, jnp.float64),
            None if mask is None else jnp.asarray(mask),
            metres_per_unit=metres_per_unit,
            camera_roll=camera_roll,
        )
        r = float(est.radius)
        if not (np.isfinite(r) and np.all(np.isfinite(np.asarray(est.offset)))):
            raise ToolOffsetInputError(
                f"rotation {k + 1}: the tip's arc gives no circle (its points on a line?)"
            )
        o = complex(*np.asarray(est.offset))
        hand = float(est.handedness) if not k else hand  # the first, widest arc's
        if last is not None and abs(last[1]) >= LEARN_MOVE * tol:
            m = _learned(m, last[0], o, last[1])
        if len(radii) > 1 and r > radii[-1] > radii[-2]:
            raise ToolOffsetInputError(
                f"rotation {k + 1}: the arc's radius grew from {1e3 * radii[-2]:.3g} to {1e3 * radii[-1]:.3g} to "
                f"{1e3 * r:.3g} mm as the axis moved toward each estimate, each move turned and scaled by what the "
                f"one before showed: metres_per_unit ({metres_per_unit:.4g}) is off by over 5x, or the tip is not "
                "where the moves put it (a tool that slips, another tip found, an axis other than the one moved)"
            )
        radii.append(r)
        if r < tol or (len(radii) > 1 and abs(radii[-2] - r) < tol_change):
            converged = True
            break
        move = o / m
        tcp = tcp + np.array([move.real, move.imag])
        tcps.append(tcp.copy())
        last = (o, move)
    return ToolOffsetResult(
        tcp=tcp,
        tcps=np.stack(tcps),
        radii=np.asarray(radii),
        converged=converged,
        iterations=len(radii),
        camera_roll_found=float(np.angle(np.exp(1j * (camera_roll + hand * np.angle(m))))),
        metres_per_unit_found=float(metres_per_unit / abs(m)),
    )


class AlignmentResult(eqx.Module):
    """The second offset: where the stylus axis meets the principal point (NumPy).

    **Fields:** `position` (m, the stylus's final $xy$), `offset` = `position`
    minus the start, `errors_px` (distance of the stylus image from the
    principal point at every iteration), `converged`, `iterations`.
    """

    position: np.ndarray
    offset: np.ndarray
    errors_px: np.ndarray
    converged: bool
    iterations: int


def align_to_principal_point(
    measure: Callable[[np.ndarray], np.ndarray],
    position0,
    principal_point,
    *,
    metres_per_px: float,
    camera_roll: float = 0.0,
    handedness: float = 1.0,
    tol_px: float = 0.05,
    max_iter: int = 10,
) -> AlignmentResult:
    """Seed 2's second offset: move the stylus until its axis images onto the principal point.

    The image vector $q - c$ (stylus image minus principal point, px) becomes
    the robot move $-m\\,R(\\gamma)^{-1} \\mathrm{diag}(1, s)(q - c)$ with the
    image scale $m$, the nominal roll $\\gamma$ and handedness $s$ (from
    `estimate_offset`), iterated while $\\|q - c\\| >$ `tol_px`; from the second move on, turned and
    scaled by what the first showed (`_learned`), so a wrong roll or scale costs one move.

    **Arguments:**
    - `measure(position)`: moves the stylus to `position` (m, $xy$) and returns
      the stylus axis's image point (px, `(2,)`).
    - `position0` (m), `principal_point` (px): start and target.
    """
    _check_roll(camera_roll)
    c = np.asarray(principal_point, np.float64)
    pos = np.asarray(position0, np.float64).copy()
    start = pos.copy()
    cr, sr = np.cos(camera_roll), np.sin(camera_roll)
    R = np.array([[cr, -sr], [sr, cr]])  # axis frame -> image axes
    errors, converged, m, last = [], False, 1.0 + 0.0j, None
    for _ in range(max_iter):
        q = np.asarray(measure(pos), np.float64)
        if q.shape != (2,) or not np.all(np.isfinite(q)):
            raise ToolOffsetInputError(f"measure returned {q!r}; expected a finite image point (2,)")
        e = q - c
        errors.append(float(np.linalg.norm(e)))
        if errors[-1] < tol_px:
            converged = True
            break
        # Image offset -> axis frame: undo the roll, then the handedness flip; turned and scaled by
        # what the moves so far showed (`_learned`).
        o = complex(*(-metres_per_px * np.diag([1.0, handedness]) @ (R.T @ e)))
        if last is not None and abs(last[1]) >= LEARN_MOVE * tol_px * metres_per_px:
            m = _learned(m, last[0], o, last[1])
        move = o / m
        pos = pos + np.array([move.real, move.imag])
        last = (o, move)
    return AlignmentResult(
        position=pos,
        offset=pos - start,
        errors_px=np.asarray(errors),
        converged=converged,
        iterations=len(errors),
    )
