"""The verdict's check for an arm that is not rigid: the joint axes move with the gravity torques.

The camera calibration models a rigid arm whose joints stand where the
encoders say. A real one sags under gravity (each joint yields by its
compliance $c_k$ times the gravity torque $\\tau_k$ of the links it carries)
and has lost motion. Between single-joint sweeps both move the joint axes
the camera measures: during the sweep of joint $j$ the resting joint $k$
stands $10^{-3} c_k \\bar\\tau_{jk}$ off, $\\bar\\tau_{jk}$ its mean gravity torque
(N m) over that sweep's frames (`jaxcal._pointfit.gravity_torques` at the
frames' commanded positions, from the robot file's masses). The part of that
which is the same in every sweep is a zero offset; the rest makes the
sweeps' axes disagree with any rigid arm.

`arm_check` is a score test of those compliances in the axis fit: the
whitened axis residuals $r$ at the fit, their Jacobian $J_p$ in the free
parameters and $J_c$ in the compliances (the derivative with respect to each
sweep's home configuration times $10^{-3}\\bar\\tau$); with $P$ the projection
off the span of $J_p$ and $A = P J_c$ (its directions below `1e-2` of the
largest singular value dropped, rank $m$), the compliances that best explain
the residuals are $\\hat c = -A^+ r$, and
$F = (\\|A \\hat c\\|^2 / m) / (\\|P r + A\\hat c\\|^2 / (N - p - m))$ is
F-distributed with $(m, N - p - m)$ degrees of freedom for a rigid arm. Above
`Limits.arm_gravity_F`, where $\\hat c$ at the joint whose sag it moves the most
is one of a real arm (a sag, at least `Limits.arm_compliance_rad_per_kNm`; a
rigid arm's axis misfit can correlate with the torques too, with no sign or
size of its own), the capture is flagged, the reason naming gravity sag with
$\\hat c$, backlash (which also shifts resting joints between sweeps) and what
to change.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._axisfit import AxisFitProblem, axis_jacobian, axis_problem, home_jacobian
from .._pointfit import gravity_torques
from ..robots import link_inertials


def sweep_torques(setup, sync) -> np.ndarray | None:
    """`(joints, joints)`: row `j`, each joint's mean gravity torque (N m) over the frames
    of joint `j`'s sweep; None without the frames' positions, a sweep or the robot's masses."""
    if sync.q is None or sync.sweeps is None:
        return None
    try:
        masses, coms = link_inertials(setup.dataset.robot_urdf)
    except (ValueError, KeyError, OSError):
        return None
    q, joint = np.asarray(sync.q, np.float64), np.asarray(sync.joint)
    inside = np.asarray(sync.inside, bool) & np.all(np.isfinite(q), axis=1)
    n = setup.nominal.num_joints
    if any(not np.any(inside & (joint == j)) for j in range(n)):
        return None
    tau = np.asarray(
        jax.vmap(gravity_torques, in_axes=(None, 0, None, None))(
            setup.nominal, jnp.asarray(q[inside]), jnp.asarray(masses), jnp.asarray(coms)
        )
    )
    return np.stack([tau[joint[inside] == j].mean(axis=0) for j in range(n)])


@eqx.filter_jit
def _score_terms(params, problem: AxisFitProblem, D):
    """The axis fit's whitened residuals, their Jacobian in the parameters and in the compliances."""
    r, J = axis_jacobian(params, problem)
    return r.ravel(), J, jnp.einsum("rjk,jk->rk", home_jacobian(params, problem), D)


def gravity_score(setup, sync, two) -> tuple[float, int, int, np.ndarray] | None:
    """`(F, m, dof, c_hat)` of the module docstring's test (c_hat in rad per kN m), or None
    where it does not apply (no sweeps with encoders, no masses, no gravity torque that varies)."""
    tau = sweep_torques(setup, sync)
    arcs, fit = two.arcs, two.fit
    if tau is None or not bool(arcs.has_encoder):
        return None
    problem = axis_problem(setup.nominal, arcs, fit.T_flange_marker0, fit.T_cam_base0, sync.homes)
    r, J, Jc = (np.asarray(a) for a in _score_terms(fit.params, problem, jnp.asarray(1e-3 * tau)))
    J = J[:, np.asarray(fit.free)]
    Q = np.linalg.qr(J)[0]
    A, rp = Jc - Q @ (Q.T @ Jc), r - Q @ (Q.T @ r)
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    keep = s > 1e-2 * s.max() if s.size and s.max() > 0 else np.zeros(len(s), bool)
    m, dof = int(keep.sum()), len(r) - J.shape[1] - int(keep.sum())
    if m == 0 or dof <= 0:
        return None
    proj = U[:, keep].T @ rp
    drop = float(proj @ proj)
    F = (drop / m) / max(float(rp @ rp) - drop, 1e-300) * dof
    return F, m, dof, -(Vt[keep].T @ (proj / s[keep]))


def arm_check(c, setup, sync, two, limits) -> None:
    """Add the `arm_gravity_F` check to the verdict's checks `c` (see the module docstring)."""
    got = gravity_score(setup, sync, two)
    if got is None:
        return
    F, m, dof, c_hat = got
    tau = sweep_torques(setup, sync)
    span = tau.max(axis=0) - tau.min(axis=0)
    j = int(np.argmax(np.abs(c_hat) * span))
    joint = setup.nominal.joint_names[j]
    physical = c_hat[j] >= limits.arm_compliance_rad_per_kNm
    c.add(
        "arm_gravity_F",
        F,
        limits.arm_gravity_F if physical else float("inf"),
        f"the joint axes moved between the sweeps as the gravity torques did (F = {F:.3g} on ({m}, {dof}) degrees "
        f"of freedom, limit {limits.arm_gravity_F:g}; axis fit residual RMS {float(two.fit.residual_rms):.3g}): "
        f"the arm is not rigid. Gravity sag moves them so: {joint}'s torque changes by {span[j]:.0f} N m between "
        f"sweeps (from {setup.dataset.robot_urdf.name}'s masses) and the axes fit an apparent compliance of "
        f"{c_hat[j]:.3g} rad/kN m there (a UR5's shoulder: 0.031); backlash does too (a resting joint stands "
        "where its last move left it within its lost motion). The camera calibration models neither. To change: "
        "calibrate the compliance with stop-and-shoot poses (a laser tracker's point fit with `compliance` "
        "terms), sweep about a home pose where the gravity torques change less, approach every sweep and home "
        "pose from the same side, or trust the result only near the capture's poses",
    )
