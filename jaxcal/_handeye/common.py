"""Helpers shared by the hand-eye and TCP-touch solvers: the pose error and the LM call."""

import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float

from .._geometry import so3_log


def pose_error(T: Float[Array, "4 4"], T_hat: Float[Array, "4 4"]) -> Float[Array, "6"]:
    """$(t - \\hat t, \\log(R \\hat R^T))$: translation (m) and parent-frame rotation vector (rad)."""
    return jnp.concatenate([T[:3, 3] - T_hat[:3, 3], so3_log(T[:3, :3] @ T_hat[:3, :3].T)])


def least_squares(fn, params0, args, rtol, atol, max_steps, throw):
    """`optx.least_squares` with Levenberg-Marquardt at `(rtol, atol)`."""
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    return optx.least_squares(fn, solver, params0, args, max_steps=max_steps, throw=throw)
