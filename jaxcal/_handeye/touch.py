"""TCP-touch hand-eye calibration (seed 5): camera-measured points touched by the tool centre point."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float, Int

from .._geometry import make_pose, se3_exp
from .._linalg import nearest_rotation
from .._lsq import LMOptions, normal_pinv, residual_variance
from ..errors import DegenerateMotionError, LengthMismatchError, NonFiniteError, ShapeError, TooFewPosesError
from .checks import check_motion_diversity, check_rotations
from .common import least_squares, pose_error


class TouchData(eqx.Module):
    """Board points measured by the camera and touched by the robot's tool centre point.

    For point $k$: the camera measures $p_k$ (camera frame, m) while the end
    effector is at $C_k$ (eye-in-hand; identity for a fixed camera), and the
    TCP touches it with the end effector at $D_k$. Both expressions of the
    point in the base frame agree:

    $$C_k X p_k = D_k\\, t_{tcp},$$

    $X = T_{base\\_cam}$ (eye-to-hand) or $T_{ee\\_cam}$ (eye-in-hand).

    **Fields:**
    - `points_cam` `(points, 3)` (m); `T_base_ee_touch` `(points, 4, 4)`.
    - `T_base_ee_camera` `(points, 4, 4)` for eye-in-hand, None for eye-to-hand.
    - `tcp`: the TCP offset in the end-effector frame (m) if known, else None (solved).
    - `mask` `(points,)`; `sigma`: the 3D point noise (m), touch and camera together.
    """

    points_cam: Float[Array, "points 3"]
    T_base_ee_touch: Float[Array, "points 4 4"]
    T_base_ee_camera: Float[Array, "points 4 4"] | None
    tcp: Float[Array, "3"] | None
    mask: Bool[Array, " points"]
    sigma: Float[Array, ""]


def make_touch_data(
    points_cam,
    T_base_ee_touch,
    T_base_ee_camera=None,
    tcp=None,
    mask=None,
    *,
    sigma: float = 1e-4,
    validate: bool = True,
) -> TouchData:
    """Build `TouchData` (see its fields); a single 4x4 `T_base_ee_camera` is used for every point."""
    P = np.asarray(points_cam, dtype=np.float64)
    D = np.asarray(T_base_ee_touch, dtype=np.float64)
    Cm = None
    if T_base_ee_camera is not None:
        Cm = np.asarray(T_base_ee_camera, dtype=np.float64)
        if Cm.ndim == 2:
            Cm = np.broadcast_to(Cm, (P.shape[0], 4, 4))
    mask = np.ones(P.shape[0], bool) if mask is None else np.asarray(mask, bool)
    data = TouchData(
        points_cam=jnp.asarray(P),
        T_base_ee_touch=jnp.asarray(D),
        T_base_ee_camera=None if Cm is None else jnp.asarray(Cm),
        tcp=None if tcp is None else jnp.asarray(np.asarray(tcp, dtype=np.float64)),
        mask=jnp.asarray(mask),
        sigma=jnp.asarray(sigma, jnp.float64),
    )
    if validate:
        validate_touch(data)
    return data


def validate_touch(data: TouchData) -> None:
    """Raise a `ValueError` naming the problem if `data` cannot give a TCP-touch calibration.

    Shapes and lengths, finite values, rotations, at least 3 non-collinear
    points (5 when the TCP offset is unknown), and, when it is unknown, touch
    orientations about two non-parallel axes (else the offset is confounded
    with the camera translation).
    """
    P, D, mask = np.asarray(data.points_cam), np.asarray(data.T_base_ee_touch), np.asarray(data.mask)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ShapeError(f"points_cam must have shape (points, 3), got {P.shape}")
    N = P.shape[0]
    if D.shape != (N, 4, 4):
        raise LengthMismatchError(
            f"{N} camera points but T_base_ee_touch has shape {D.shape} (lengths must match)"
        )
    if data.T_base_ee_camera is not None and np.shape(data.T_base_ee_camera) != (N, 4, 4):
        raise LengthMismatchError(
            f"{N} camera points but T_base_ee_camera has shape {np.shape(data.T_base_ee_camera)} (lengths must match)"
        )
    if mask.shape != (N,):
        raise ShapeError(f"mask has shape {mask.shape}, expected {(N,)}")
    if data.tcp is not None and np.shape(data.tcp) != (3,):
        raise ShapeError(f"tcp must have shape (3,), got {np.shape(data.tcp)}")
    bad = mask & ~np.all(np.isfinite(P), axis=-1)
    if bad.any():
        raise NonFiniteError(f"points_cam: non-finite point {np.flatnonzero(bad)[0]}")
    check_rotations(D[mask], "T_base_ee_touch")
    if data.T_base_ee_camera is not None:
        check_rotations(np.asarray(data.T_base_ee_camera)[mask], "T_base_ee_camera")
    need = 3 if data.tcp is not None else 5
    n = int(mask.sum())
    if n < need:
        raise TooFewPosesError(f"only {n} touched points, at least {need} are needed")
    Pm = P[mask] - P[mask].mean(0)
    sv = np.linalg.svd(Pm, compute_uv=False)
    if sv[1] < 1e-6 * max(sv[0], 1e-12):
        raise DegenerateMotionError(
            "points_cam: the touched points are collinear; the camera rotation is not identifiable"
        )
    if data.tcp is None:
        check_motion_diversity(
            D[mask], "T_base_ee_touch (an unknown TCP offset needs varied touch orientations)"
        )


class TouchParams(eqx.Module):
    robot_cam: Float[Array, "6"]
    tcp: Float[Array, "3"] | None


class TouchResult(eqx.Module):
    """A TCP-touch hand-eye calibration.

    **Fields:**
    - `T_robot_cam`: $T_{base\\_cam}$ (eye-to-hand) or $T_{ee\\_cam}$ (eye-in-hand).
    - `tcp`: the TCP offset in the end-effector frame (m), solved or as given.
    - `std_robot_cam` `(6,)` (translation m, rotation rad, parent frame as in
      `HandEyeResult`), `std_tcp` `(3,)` (zero when given).
    - `rms`: RMS distance between the two expressions of each point (m).
    - `result`, `num_steps`: optimistix's.
    """

    T_robot_cam: Float[Array, "4 4"]
    tcp: Float[Array, "3"]
    std_robot_cam: Float[Array, "6"]
    std_tcp: Float[Array, "3"]
    rms: Float[Array, ""]
    result: optx.RESULTS
    num_steps: Int[Array, ""]
    eye_in_hand: bool = eqx.field(static=True)

    @property
    def T_base_cam(self) -> Float[Array, "4 4"]:
        if self.eye_in_hand:
            raise AttributeError("T_base_cam is not defined for an eye-in-hand calibration")
        return self.T_robot_cam

    @property
    def T_ee_cam(self) -> Float[Array, "4 4"]:
        if not self.eye_in_hand:
            raise AttributeError("T_ee_cam is not defined for an eye-to-hand calibration")
        return self.T_robot_cam


def _touch_C(data: TouchData):
    if data.T_base_ee_camera is None:
        return jnp.broadcast_to(jnp.eye(4), data.T_base_ee_touch.shape)
    return data.T_base_ee_camera


def initialise_touch(data: TouchData) -> tuple[Float[Array, "4 4"], Float[Array, "3"]]:
    """Closed-form `(X, tcp)`: linear least squares in the plane frame of the points.

    With $p_k = c + U(a_k, b_k, d_k)$ ($U$ the points' principal axes), the
    unknowns $g_1, g_2 = R_X U e_{1,2}$, $s = R_X c + t_X$ and $t_{tcp}$ enter
    $R_{C_k}(a_k g_1 + b_k g_2 + s) - R_{D_k} t_{tcp} = t_{D_k} - t_{C_k}$
    linearly ($d_k$, zero for a planar board, is dropped). Then
    $R_X = \\mathrm{proj}[g_1, g_2, g_1 \\times g_2] U^T$, and $t_X$, $t_{tcp}$
    are re-solved at that rotation.
    """
    w = data.mask.astype(jnp.float64)
    P = jnp.where(data.mask[:, None], data.points_cam, 0.0)
    c = jnp.sum(P * w[:, None], 0) / jnp.maximum(jnp.sum(w), 1.0)
    _, V = jnp.linalg.eigh(((P - c) * w[:, None]).T @ (P - c))
    U = jnp.stack([V[:, 2], V[:, 1], jnp.cross(V[:, 2], V[:, 1])], axis=1)
    ab = (P - c) @ U[:, :2]
    Cm, D = _touch_C(data), data.T_base_ee_touch
    RC, RD = Cm[:, :3, :3], D[:, :3, :3]
    known = data.tcp is not None
    rhs = D[:, :3, 3] - Cm[:, :3, 3]
    blocks = [RC * ab[:, :1, None], RC * ab[:, 1:, None], RC]
    if known:
        rhs = rhs + jnp.einsum("kij,j->ki", RD, data.tcp)
    else:
        blocks.append(-RD)
    A = jnp.concatenate(blocks, axis=2) * jnp.sqrt(w)[:, None, None]
    n = A.shape[2]
    A, b = A.reshape(-1, n), (rhs * jnp.sqrt(w)[:, None]).reshape(-1)
    z = jnp.linalg.solve(A.T @ A + 1e-12 * jnp.eye(n), A.T @ b)
    g1, g2 = z[0:3], z[3:6]
    R = nearest_rotation(jnp.stack([g1, g2, jnp.cross(g1, g2)], axis=1)) @ U.T
    # Translation (and tcp) at that rotation: R_C (R p + t) - R_D tcp = t_D - t_C.
    rhs2 = rhs - jnp.einsum("kij,jl,kl->ki", RC, R, P)
    blocks2 = [RC] if known else [RC, -RD]
    A2 = jnp.concatenate(blocks2, axis=2) * jnp.sqrt(w)[:, None, None]
    n2 = A2.shape[2]
    A2, b2 = A2.reshape(-1, n2), (rhs2 * jnp.sqrt(w)[:, None]).reshape(-1)
    z2 = jnp.linalg.solve(A2.T @ A2 + 1e-12 * jnp.eye(n2), A2.T @ b2)
    tcp = data.tcp if known else z2[3:6]
    return make_pose(R, z2[:3]), tcp


def touch_residuals(params: TouchParams, args) -> Float[Array, "points 3"]:
    """$(C_k X p_k - D_k t_{tcp})/\\sigma$ in the base frame, zero where masked."""
    X0, data = args
    X = X0 @ se3_exp(params.robot_cam)
    tcp = data.tcp if params.tcp is None else params.tcp
    P = jnp.where(data.mask[:, None], data.points_cam, 0.0)
    q_cam = jnp.einsum(
        "kij,kj->ki",
        _touch_C(data),
        jnp.concatenate([P @ X[:3, :3].T + X[:3, 3], jnp.ones_like(P[:, :1])], 1),
    )
    D = data.T_base_ee_touch
    q_tcp = jnp.einsum("kij,j->ki", D[:, :3, :3], tcp) + D[:, :3, 3]
    return jnp.where(data.mask[:, None], (q_cam[:, :3] - q_tcp) / data.sigma, 0.0)


#: `calibrate_touch`'s solver settings.
TOUCH_OPTIONS = LMOptions(rtol=1e-8, atol=1e-6, max_steps=50)


def calibrate_touch(
    data: TouchData,
    *,
    options: LMOptions = TOUCH_OPTIONS,
    throw: bool = False,
    scale_covariance: bool = True,
) -> TouchResult:
    """TCP-touch hand-eye calibration (seed 5), eye-to-hand or eye-in-hand; pure and jittable.

    Closed-form start (`initialise_touch`), then Levenberg-Marquardt on
    `touch_residuals` over $X = X_0 \\exp(\\xi)$ and, when `data.tcp` is None,
    the TCP offset. Covariance from the Jacobian as in `calibrate_hand_eye`.
    `options`: the solver's `LMOptions`; `throw`: optimistix's.
    """
    X0, tcp0 = initialise_touch(data)
    params0 = TouchParams(robot_cam=jnp.zeros(6), tcp=None if data.tcp is not None else tcp0)
    options = dataclasses.replace(options, throw=throw or options.throw)
    sol = least_squares(touch_residuals, params0, (X0, data), options)
    params = sol.value
    flat, unravel = ravel_pytree(params)
    J = jax.jacfwd(lambda x: touch_residuals(unravel(x), (X0, data)).reshape(-1))(flat)
    r = touch_residuals(params, (X0, data))
    cov = normal_pinv(J.T @ J)
    if scale_covariance:
        cov = cov * residual_variance(r, 3.0 * jnp.sum(data.mask), flat.size)
    X = X0 @ se3_exp(params.robot_cam)

    def errors(x):
        p = unravel(x)
        e = pose_error(X0 @ se3_exp(p.robot_cam), X)
        return e if p.tcp is None else jnp.concatenate([e, p.tcp])

    G = jax.jacfwd(errors)(flat)
    std = jnp.sqrt(jnp.maximum(jnp.einsum("ia,ab,ib->i", G, cov, G), 0.0))
    return TouchResult(
        T_robot_cam=X,
        tcp=data.tcp if params.tcp is None else params.tcp,
        std_robot_cam=std[:6],
        std_tcp=jnp.zeros(3) if params.tcp is None else std[6:9],
        rms=jnp.sqrt(jnp.sum(r**2) / jnp.maximum(jnp.sum(data.mask), 1.0)) * data.sigma,
        result=sol.result,
        num_steps=sol.stats["num_steps"],
        eye_in_hand=data.T_base_ee_camera is not None,
    )
