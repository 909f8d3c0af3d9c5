"""What a calibration's covariance means at the end effector.

The solvers report the covariance $\\Sigma$ of the correction vector
(`jaxcal._correction`). A user asks a different question: how far off can
the tool point be? With $p(q; x)$ the target origin in the fixed frame at
configuration $q$ (the camera origin in the board frame, eye-in-hand) and
$G_q = \\partial p / \\partial x$, its covariance is $G_q \\Sigma G_q^T$; over a
sample of configurations the RMS of $\\sqrt{\\mathrm{tr}}$ is the 1-sigma
end-effector uncertainty the data support (to first order).
"""

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float, PRNGKeyArray

from ._correction import KinematicCorrection, apply_correction
from ._geometry import se3_exp
from ._kinematics import REVOLUTE, KinematicModel, forward_kinematics

#: A prismatic joint's travel either side of zero in the random configurations
#: when its URDF gives no limits (m).
PRISMATIC_TRAVEL_M = 0.1


def tool_points(
    nominal: KinematicModel,
    T_cam_base0: Float[Array, "4 4"],
    T_flange_marker0: Float[Array, "markers 4 4"],
    cam: Float[Array, "6"],
    correction: KinematicCorrection,
    q: Float[Array, "n joints"],
) -> Float[Array, "n 3"]:
    """The first target's origin in the fixed frame at every configuration `q` (m)."""
    model, mounts = apply_correction(nominal, T_flange_marker0, correction)
    T_cb = T_cam_base0 @ se3_exp(cam)
    return jax.vmap(lambda qq: (T_cb @ forward_kinematics(model, qq)[-1] @ mounts[0])[:3, 3])(q)


def ee_sigma(
    nominal: KinematicModel,
    T_cam_base0,
    T_flange_marker0,
    cam,
    correction: KinematicCorrection,
    cov: Float[Array, "n n"],
    q: Float[Array, "c joints"],
    term_joint=None,
    term_basis: Float[Array, "c k"] | None = None,
) -> Float[Array, " c"]:
    """Per configuration, the 1-sigma end-effector position uncertainty
    $\\sqrt{\\mathrm{tr}(G_q \\Sigma G_q^T)}$ (m), `cov` over the flattened
    `(cam, correction)` (the axis-fit prefix of the layout), followed, with non-geometric
    terms (`jaxcal._terms`), by their coefficients: coefficient $k$ turns joint
    `term_joint[k]` by `term_basis[:, k]` per unit at each configuration, so its column is
    that joint's angle column (its zero offset's) times its basis."""
    flat, unravel = ravel_pytree((cam, correction))

    def points(x):
        c, corr = unravel(x)
        return tool_points(nominal, T_cam_base0, T_flange_marker0, c, corr, q)

    G = jax.jacfwd(points)(flat)  # (c, 3, n)
    if term_basis is not None:
        zero = 6 + 6 * nominal.num_joints  # the zero offsets' columns in the flattened (cam, correction)
        G = jnp.concatenate([G, G[:, :, zero + np.asarray(term_joint)] * term_basis[:, None, :]], axis=-1)
    return jnp.sqrt(jnp.maximum(jnp.einsum("cia,ab,cib->c", G, cov, G), 0.0))


def random_configurations(key: PRNGKeyArray, n: int, joints: int) -> Float[Array, "n joints"]:
    """`n` configurations uniform in $[-\\pi, \\pi]$ per joint (the validation's sample)."""
    return jax.random.uniform(key, (n, joints), minval=-jnp.pi, maxval=jnp.pi)


def joint_travel(model: KinematicModel, limits: dict | None = None) -> np.ndarray:
    """Every joint's range in the random configurations, `(joints, 2)`: $[-\\pi, \\pi]$
    for a revolute joint; a prismatic joint's URDF limits (`limits`: joint name
    -> `jaxcal.io.urdf.JointLimits`), else $\\pm$`PRISMATIC_TRAVEL_M` (m)."""
    travel = np.tile([-np.pi, np.pi], (model.num_joints, 1))
    for j, (name, kind) in enumerate(zip(model.joint_names, model.joint_types)):
        if kind != REVOLUTE:
            lim = (limits or {}).get(name)
            lo, hi = (None, None) if lim is None else (lim.lower, lim.upper)
            travel[j] = (-PRISMATIC_TRAVEL_M if lo is None else lo, PRISMATIC_TRAVEL_M if hi is None else hi)
    return travel


def on_travel(model: KinematicModel, q: Float[Array, "n joints"], travel) -> Float[Array, "n joints"]:
    """`random_configurations`' sample with each prismatic joint's column mapped
    from $[-\\pi, \\pi]$ onto its `travel` (`joint_travel`): metres, not metres as
    if they were radians. Revolute columns are returned as they are."""
    prismatic = np.asarray([k != REVOLUTE for k in model.joint_types])
    if not prismatic.any():
        return q
    lo, hi = travel[:, 0], travel[:, 1]
    return jnp.where(prismatic, lo + (q + jnp.pi) / (2.0 * jnp.pi) * (hi - lo), q)
