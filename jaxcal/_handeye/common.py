"""Helpers shared by the hand-eye and TCP-touch solvers: the pose error and the LM call."""

import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float

from .. import _lsq
from .._geometry import so3_log


def pose_error(T: Float[Array, "4 4"], T_hat: Float[Array, "4 4"]) -> Float[Array, "6"]:
    """$(t - \\hat t, \\log(R \\hat R^T))$: translation (m) and parent-frame rotation vector (rad)."""
    return jnp.concatenate([T[:3, 3] - T_hat[:3, 3], so3_log(T[:3, :3] @ T_hat[:3, :3].T)])


def least_squares(fn, params0, args, options: _lsq.LMOptions) -> optx.Solution:
    """Levenberg-Marquardt with `options` on the normal equations (`jaxcal._lsq.solve_normal`):
    the Jacobians are tall (thousands of corner rows, a dozen unknowns) and whitened, and
    lineax's default QR forms the thin Q every step, which the Cholesky of $J^T J$ avoids for
    the same answer to round-off."""
    return _lsq.solve_normal(fn, params0, args, options)
