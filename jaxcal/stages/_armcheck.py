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

from concurrent.futures import Future

import numpy as np

from .._buckets import bucket
from ..robots import link_inertials
from . import _programs


def _sweep_weights(setup, sync) -> tuple[np.ndarray, np.ndarray] | None:
    """The frames' commanded positions `q` padded to a bucket, and `weights` whose column `j`
    averages over joint `j`'s sweep (`_programs.arm_score`); None without the frames'
    positions or with a sweep that has none."""
    if sync.q is None or sync.sweeps is None:
        return None
    q, joint = np.asarray(sync.q, np.float64), np.asarray(sync.joint)
    inside = np.asarray(sync.inside, bool) & np.all(np.isfinite(q), axis=1) & (joint >= 0)
    n = setup.nominal.num_joints
    counts = np.array([np.sum(inside & (joint == j)) for j in range(n)])
    if np.any(counts == 0):
        return None
    size = bucket(int(inside.sum()))
    padded, weights = np.zeros((size, n)), np.zeros((size, n))
    padded[: inside.sum()] = q[inside]
    weights[np.arange(inside.sum()), joint[inside]] = 1.0 / counts[joint[inside]]
    return padded, weights


def gravity_score(setup, sync, two) -> tuple[float, int, int, np.ndarray, np.ndarray] | None:
    """`(F, m, dof, c_hat, tau)` of the module docstring's test (c_hat in rad per kN m; `tau`
    row `j`, each joint's mean gravity torque (N m) over joint `j`'s sweep), or None where
    it does not apply (no sweeps with encoders, no masses, no gravity torque that varies)."""
    arcs, fit = two.arcs, two.fit
    sweeps = _sweep_weights(setup, sync)
    if sweeps is None or not bool(arcs.has_encoder):
        return None
    try:
        masses, coms = link_inertials(setup.dataset.robot_urdf)
    except (ValueError, KeyError, OSError):
        return None
    n = setup.nominal.num_joints
    home = np.zeros((n, n)) if sync.homes is None else np.asarray(sync.homes, np.float64)
    r, J, Jc, tau = (
        np.asarray(a)
        for a in _programs.arm_score(True)(
            setup.nominal,
            arcs,
            fit.T_flange_marker0,
            fit.T_cam_base0,
            home,
            fit.params,
            *sweeps,
            masses,
            coms,
        )
    )
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
    return F, m, dof, -(Vt[keep].T @ (proj / s[keep])), tau


def start_arm_score(setup, sync, two) -> Future:
    """`gravity_score(setup, sync, two)` on a thread of its own (`_programs.run_ahead`): it
    needs only the two-stage fit, so its program compiles (or loads) and runs while the
    refinement does; hand the `Future` to `verdict(..., arm_score=...)`."""
    return _programs.run_ahead("arm check", gravity_score, setup, sync, two)


def arm_check(c, setup, sync, two, limits, score: Future | None = None) -> None:
    """Add the `arm_gravity_F` check to the verdict's checks `c` (see the module docstring);
    `score`: `gravity_score(setup, sync, two)` started ahead (`_programs.run_ahead`), if it was."""
    got = gravity_score(setup, sync, two) if score is None else score.result()
    if got is None:
        return
    F, m, dof, c_hat, tau = got
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
