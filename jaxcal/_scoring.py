"""Scoring a calibration against a known truth (Monte Carlo trials, synthetic datasets).

The camera sees the robot's base frame only up to a gauge (the estimator
holds joint 1's frame at nominal, see `jaxcal._kinematics.anchor_base`), so
camera-pose errors are measured against the truth seen through the same
gauge when one is given.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._axisfit import AxisFitResult
from ._geometry import matmul, pose_inverse, so3_log
from ._kinematics import KinematicModel, forward_kinematics, joint_axes

_MM = 1e-3
_DEG = jnp.pi / 180.0


class Score(NamedTuple):
    """Errors of a calibration against the truth (`score`; the figures of
    `jaxcal._montecarlo.TrialResult`, which documents them). A pytree: `score` runs
    under `jit` and `vmap`, batched fields get a leading axis."""

    ee_rms_mm: Float[Array, ""]
    ee_max_mm: Float[Array, ""]
    ee_rms_mm_nominal: Float[Array, ""]
    cam_rot_deg: Float[Array, ""]
    cam_trans_mm: Float[Array, ""]
    axis_dir_deg: Float[Array, " joints"]
    axis_pos_mm: Float[Array, " joints"]
    ratio_err_percent: Float[Array, " joints"]


def score(
    fit: AxisFitResult,
    true: KinematicModel,
    T_cam_base: Float[Array, "4 4"],
    T_flange_marker: Float[Array, "markers 4 4"],
    nominal: KinematicModel,
    q_val: Float[Array, "n joints"],
    T_cam_base_gauge: Float[Array, "4 4"] | None = None,
) -> Score:
    """Errors of a calibration against the truth (see `jaxcal._montecarlo.TrialResult`)."""

    def marker_in_cam(model, T_cb, mount, q):
        return matmul(matmul(T_cb, forward_kinematics(model, q)[-1]), mount)[:3, 3]

    est = jax.vmap(lambda q: marker_in_cam(fit.model, fit.T_cam_base, fit.T_flange_marker[0], q))(q_val)
    tru = jax.vmap(lambda q: marker_in_cam(true, T_cam_base, T_flange_marker[0], q))(q_val)
    nom = jax.vmap(lambda q: marker_in_cam(nominal, fit.T_cam_base, fit.T_flange_marker[0], q))(q_val)
    err = jnp.linalg.norm(est - tru, axis=-1) / _MM
    err_nom = jnp.linalg.norm(nom - tru, axis=-1) / _MM
    # The camera sees the base frame only up to the gauge (see module
    # docstring): compare with the truth in the estimator's gauge when given.
    T_ref = T_cam_base if T_cam_base_gauge is None else T_cam_base_gauge
    dT = pose_inverse(T_ref) @ fit.T_cam_base
    q0 = jnp.zeros(true.num_joints)
    p_e, d_e = joint_axes(fit.model, q0)
    p_t, d_t = joint_axes(true, q0)
    # Both in the camera frame.
    p_e = p_e @ fit.T_cam_base[:3, :3].T + fit.T_cam_base[:3, 3]
    d_e = d_e @ fit.T_cam_base[:3, :3].T
    p_t = p_t @ T_cam_base[:3, :3].T + T_cam_base[:3, 3]
    d_t = d_t @ T_cam_base[:3, :3].T
    cosang = jnp.clip(jnp.sum(d_e * d_t, -1), -1.0, 1.0)
    sinang = jnp.linalg.norm(jnp.cross(d_e, d_t), axis=-1)
    dp = p_e - p_t
    # Distance of the true axis point from the estimated line (lines nearly parallel).
    pos = jnp.linalg.norm(dp - jnp.sum(dp * d_e, -1, keepdims=True) * d_e, axis=-1)
    return Score(
        ee_rms_mm=jnp.sqrt(jnp.mean(err**2)),
        ee_max_mm=jnp.max(err),
        ee_rms_mm_nominal=jnp.sqrt(jnp.mean(err_nom**2)),
        cam_rot_deg=jnp.linalg.norm(so3_log(dT[:3, :3])) / _DEG,
        cam_trans_mm=jnp.linalg.norm(dT[:3, 3]) / _MM,
        axis_dir_deg=jnp.arctan2(sinang, cosang) / _DEG,
        axis_pos_mm=pos / _MM,
        ratio_err_percent=100.0 * (fit.model.reduction_ratio - true.reduction_ratio) / true.reduction_ratio,
    )
