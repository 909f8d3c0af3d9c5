"""Stop-and-shoot calibration from measured points: the residual model of point samples.

A measuring device (laser tracker, motion capture, a camera's PnP, the
controller) reports a point on the flange, in its own frame, at poses where
every joint stands still at known commanded positions $q_i$. The model of
sample $i$ is

$$ y_i = T_{dev,base}\\, T_{base,flange}(q_i + \\delta q_i;\\ \\text{model})\\, p, \\qquad
   T_{dev,base} = T_0 \\exp(\\xi_{cam}),\\ p = T_{flange,point,0} \\exp(\\xi_{tool})\\, \\mathbf{0}, $$

with the model corrected by `jaxcal._correction` (a twist on every joint
origin, zero offsets), so the unknowns are exactly the axis fit's vector
(`ParameterLayout.axis_size`: `cam`, `origin`, `zero`, `tool`), and the
tables, covariance and outputs of the two-stage fit apply unchanged.

**Non-geometric terms.** $\\delta q_{i,j} = \\sum_k e_{j,k}\\, b_{j,k}(q_i)$: joint
angle errors linear in a few coefficients per joint over a basis of the
pose. Families (`TERMS`):

- `compliance`: $b_j = \\tau_j(q)$ / (1 kN m), the gravity torque about joint
  $j$'s axis from the link masses and centres of mass (the joint yields by
  $c_j \\tau_j$; $e_j$ is then the compliance in rad per kN m).
- `harmonic1`, `harmonic2`: $\\sin(k q_j), \\cos(k q_j)$, a transmission's
  once- and twice-per-turn error.

Their coefficients follow the axis-fit vector in the flattened parameters
(`PointLayout`); the identifiability search visits them last, so a term is
freed only where the geometry cannot already explain it.

Everything here is pure and jittable; `fit_points` is one compiled program
for any mask of free parameters and any mask of samples, so K-fold
cross-validation is a vmap over sample masks (`cross_validate`).
"""

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from . import _lsq
from ._axisfit import AxisFitParams
from ._correction import ParameterLayout
from ._geometry import matmul_unrolled as mm
from ._geometry import matvec_unrolled as mv
from ._geometry import se3_exp, skew, so3_log
from ._kinematics import KinematicModel, forward_kinematics
from ._schur import NormalEquations, normal_least_squares

#: Non-geometric term families and their number of coefficients per joint.
TERMS = {"compliance": 1, "harmonic1": 2, "harmonic2": 2}
#: Standard gravity (m/s^2), along the base frame's -z.
GRAVITY = 9.80665
#: The point fit's Levenberg-Marquardt settings: it stops at steps below a thousandth of a
#: standard deviation (whitened residuals), far inside the answer's own uncertainty.
LM_OPTIONS = _lsq.LMOptions(rtol=1e-8, atol=1e-3)


@dataclass(frozen=True)
class PointLayout:
    """The point fit's flattened vector: the axis fit's (`ParameterLayout`)
    followed by the coefficients of the non-geometric `terms`, joint-major
    within each family. `orientation`: the samples also measure the point
    frame's orientation (a 6-DoF probe, a motion-capture body, a PnP pose)."""

    base: ParameterLayout
    terms: tuple[str, ...] = ()
    orientation: bool = False

    def __post_init__(self):
        unknown = [t for t in self.terms if t not in TERMS]
        if unknown:
            raise ValueError(f"unknown non-geometric terms {unknown}; known terms are {sorted(TERMS)}")

    @property
    def num_terms(self) -> int:
        """Coefficients per joint."""
        return sum(TERMS[t] for t in self.terms)

    @property
    def size(self) -> int:
        return self.base.axis_size + len(self.base.joints) * self.num_terms

    def term_names(self) -> list[str]:
        suffix = {
            "compliance": ("rad_per_kNm",),
            "harmonic1": ("sin1", "cos1"),
            "harmonic2": ("sin2", "cos2"),
        }
        return [f"{j}.{t}.{s}" for t in self.terms for j in self.base.joints for s in suffix[t]]

    def names(self) -> list[str]:
        return self.base.names(refine=False) + self.term_names()

    def split(self, x: Float[Array, " n"]) -> tuple[AxisFitParams, Float[Array, "joints k"]]:
        """The axis-fit parameters and the per-joint term coefficients `(joints, num_terms)`."""
        k = self.base.axis_size
        cam, corr, _ = self.base.split(x[:k])
        n = len(self.base.joints)
        blocks, start = [], k
        for t in self.terms:
            m = TERMS[t]
            blocks.append(x[start : start + n * m].reshape(n, m))
            start += n * m
        e = jnp.concatenate(blocks, axis=1) if blocks else jnp.zeros((n, 0), x.dtype)
        return AxisFitParams(cam=cam, correction=corr), e

    def priority(self) -> np.ndarray:
        """Column order of the identifiability search: the axis fit's, then the terms."""
        return np.concatenate([self.base.priority(refine=False), np.arange(self.base.axis_size, self.size)])


class PointData(eqx.Module):
    """Point samples of one capture (padded: `mask` marks the real, used ones).

    - `q`: commanded joint positions `(samples, joints)` (rad, or m).
    - `y`: measured points in the device frame `(samples, 3)` (m).
    - `sigma`: per-axis 1-sigma of each point `(samples,)` (m).
    - `mask`: samples in the fit.
    - `masses`, `coms`: per joint's child link its mass (kg) and centre of mass
      in that link's frame (m); zeros when no compliance term is fitted.
    - `R`, `sigma_rad`: with orientations, the measured rotation of the point's
      frame in the device frame `(samples, 3, 3)` and its 1-sigma per axis (rad);
      identities and ones otherwise.
    """

    q: Float[Array, "samples joints"]
    y: Float[Array, "samples 3"]
    sigma: Float[Array, " samples"]
    mask: Bool[Array, " samples"]
    masses: Float[Array, " joints"]
    coms: Float[Array, "joints 3"]
    R: Float[Array, "samples 3 3"]
    sigma_rad: Float[Array, " samples"]


def gravity_torques(model: KinematicModel, q, masses, coms) -> Float[Array, " joints"]:
    """$\\tau_j = z_j \\cdot \\sum_{k \\ge j} (c_k - o_j) \\times m_k g$ (N m): the torque
    gravity (along the base's $-z$) exerts about each joint's axis at `q`."""
    T = forward_kinematics(model, q)
    links = T[1:-1]  # each joint's child link
    c = jnp.einsum("kab,kb->ka", links[:, :3, :3], coms) + links[:, :3, 3]
    z = jnp.einsum("jab,jb->ja", links[:, :3, :3], model.axis)
    o = links[:, :3, 3]
    f = masses[:, None] * jnp.array([0.0, 0.0, -GRAVITY])
    n = model.num_joints
    down = jnp.arange(n)[None, :] >= jnp.arange(n)[:, None]  # (j, k): link k rides on joint j
    moment = jnp.cross(c[None, :, :] - o[:, None, :], f[None, :, :])  # (j, k, 3)
    return jnp.einsum("ja,jka,jk->j", z, moment, down.astype(q.dtype))


def term_basis(
    terms: tuple[str, ...], model: KinematicModel, q, masses, coms
) -> Float[Array, "samples joints k"]:
    """The terms' basis at every sample's commanded pose `q` `(samples, joints)`, on the nominal model."""
    cols = []
    for t in terms:
        if t == "compliance":
            tau = jax.vmap(gravity_torques, in_axes=(None, 0, None, None))(model, q, masses, coms)
            cols.append(tau[..., None] / 1000.0)
        else:
            k = 1.0 if t == "harmonic1" else 2.0
            cols += [jnp.sin(k * q)[..., None], jnp.cos(k * q)[..., None]]
    return jnp.concatenate(cols, axis=-1) if cols else jnp.zeros((*q.shape, 0), q.dtype)


class PointProblem(eqx.Module):
    """A point fit: the nominal model, the references the corrections are relative to, the data."""

    nominal: KinematicModel
    T_dev_base0: Float[Array, "4 4"]
    T_flange_point0: Float[Array, "4 4"]
    data: PointData
    layout: PointLayout = eqx.field(static=True)


def _rotations(axis: Float[Array, "3"], theta: Float[Array, " s"]) -> Float[Array, "s 3 3"]:
    """Rodrigues' rotations about one unit `axis` by many angles."""
    K = skew(axis)
    s, c = jnp.sin(theta)[:, None, None], jnp.cos(theta)[:, None, None]
    return jnp.eye(3) + s * K + (1.0 - c) * (K @ K)


def _chain(x, problem: "PointProblem"):
    """The forward pass of every sample at once: the fitted points `(s, 3)` and
    what their Jacobian needs: per joint the pose before its origin
    correction `A_j` and the point in its child link `s_j`, the joint's axis
    direction and a point on it (device frame), the device pose and the
    flange poses."""
    layout, d = problem.layout, problem.data
    params, e = layout.split(x)
    corr = params.correction
    nominal = problem.nominal
    E = jax.vmap(se3_exp)(corr.origin)
    T_db = problem.T_dev_base0 @ se3_exp(params.cam)
    mount = problem.T_flange_point0 @ se3_exp(corr.tool[0])
    theta = d.q + nominal.zero_offset + corr.zero_offset
    if layout.terms:
        theta = theta + jnp.sum(e[None] * term_basis(layout.terms, nominal, d.q, d.masses, d.coms), axis=2)
    S = theta.shape[0]
    R = jnp.broadcast_to(T_db[:3, :3], (S, 3, 3))
    t = jnp.broadcast_to(T_db[:3, 3], (S, 3))
    A_R, A_t, W_R, W_t, rot = [], [], [], [], []
    # Products of 3x3 blocks over the samples as unrolled multiply-adds: XLA's CPU backend
    # fuses them into elementwise loops, where batched `dot_general`s are several times slower.
    for j in range(nominal.num_joints):
        O = nominal.T_parent_joint[j]
        t = t + mv(R, O[:3, 3])
        R = mm(R, O[:3, :3])
        A_R.append(R)
        A_t.append(t)
        t = t + mv(R, E[j, :3, 3])
        rot.append(_rotations(nominal.axis[j], theta[:, j]))
        R = mm(mm(R, E[j, :3, :3]), rot[-1])
        W_R.append(R)
        W_t.append(t)
    F = nominal.T_last_flange
    t_f = t + mv(R, F[:3, 3])
    R_f = mm(R, F[:3, :3])
    y = t_f + mv(R_f, mount[:3, 3])
    W_R, W_t = jnp.stack(W_R, 1), jnp.stack(W_t, 1)  # (s, joints, ...)
    s_link = mv(jnp.swapaxes(W_R, -1, -2), y[:, None, :] - W_t)
    omega = mv(W_R, nominal.axis[None])
    return y, (jnp.stack(A_R, 1), jnp.stack(A_t, 1), s_link, omega, W_t, T_db, R_f, t_f, E, jnp.stack(rot, 1))


def predict(x: Float[Array, " n"], problem: "PointProblem") -> Float[Array, "samples 3"]:
    """The model's points in the device frame for every sample (m)."""
    return _chain(x, problem)[0]


def predict_rotation(x: Float[Array, " n"], problem: "PointProblem") -> Float[Array, "samples 3 3"]:
    """The model's rotation of the point's frame in the device frame for every sample."""
    params, _ = problem.layout.split(x)
    mount = problem.T_flange_point0 @ se3_exp(params.correction.tool[0])
    R_f = _chain(x, problem)[1][6]
    return R_f @ mount[:3, :3]


def _rotation_residuals(x, problem) -> Float[Array, " m"]:
    """Whitened rotation residuals $\\log(R_i^T \\hat R_i) / \\sigma_{rad,i}$, zero for masked samples."""
    d = problem.data
    e = jax.vmap(so3_log)(jnp.einsum("sba,sbc->sac", d.R, predict_rotation(x, problem)))
    w = jnp.where(d.mask, 1.0 / d.sigma_rad, 0.0)
    return (e * w[:, None]).reshape(-1)


def _dexp(xi: Float[Array, "6"]) -> Float[Array, "4 4 6"]:
    return jax.jacfwd(se3_exp)(xi)


def point_jacobian(x: Float[Array, " n"], problem: "PointProblem", chain=None) -> Float[Array, "samples 3 n"]:
    """$\\partial \\hat y_i / \\partial x$ in closed form (tested against autodiff):

    - joint $j$'s origin twist: $A_j\\, \\partial\\exp(\\xi_j) \\, R_j(\\theta_j) s_j$, with $A_j$
      the pose up to its nominal origin and $s_j$ the point in joint $j$'s child link;
    - zero offset and every joint-angle term: $\\omega_j \\times (\\hat y - o_j)$ (times the term's basis);
    - the fixed frame: $T_0\\, \\partial\\exp(\\xi_{cam})\\, T_{dev,base}^{-1} \\hat y$;
    - the mount: $R_{flange}\\, \\partial \\exp(\\xi_{tool}) \\mathbf{0}$ on the nominal mount.

    `chain`: `_chain(x, problem)` when the caller has it already.
    """
    layout, d = problem.layout, problem.data
    params, _ = layout.split(x)
    corr = params.correction
    y, (A_R, _A_t, s_link, omega, W_t, T_db, R_f, _t_f, _E, rot) = (
        _chain(x, problem) if chain is None else chain
    )
    n = problem.nominal.num_joints
    S = y.shape[0]
    c_link = mv(rot, s_link)  # R_j s_j, in the corrected origin frame
    dE = jax.vmap(_dexp)(corr.origin)  # (joints, 4, 4, 6)
    # g[s, j, :, k] = dE_j[:3, :3, k] c_link[s, j] + dE_j[:3, 3, k], as multiply-adds over b
    g = dE[None, :, :3, 3, :] + sum(dE[None, :, :3, b, :] * c_link[:, :, None, b, None] for b in range(3))
    J_origin = jnp.swapaxes(mm(A_R, g), 1, 2).reshape(S, 3, 6 * n)
    J_angle = jnp.cross(omega, y[:, None, :] - W_t)  # (s, joints, 3): d y / d theta_j
    J_zero = jnp.swapaxes(J_angle, 1, 2)
    dC = _dexp(params.cam)
    base_pt = mv(T_db[:3, :3].T, y - T_db[:3, 3])  # T_db^-1 y
    gc = dC[None, :3, 3, :] + sum(dC[None, :3, b, :] * base_pt[:, None, b, None] for b in range(3))
    J_cam = mm(problem.T_dev_base0[:3, :3], gc)
    dT = _dexp(corr.tool[0])
    J_tool = mm(R_f, (problem.T_flange_point0[:3, :3] @ dT[:3, 3, :])[None])
    blocks = [J_cam, J_origin, J_zero, J_tool]
    if layout.terms:
        b = term_basis(layout.terms, problem.nominal, d.q, d.masses, d.coms)  # (s, joints, k)
        start = 0
        for t in layout.terms:
            m = TERMS[t]
            blocks.append(
                jnp.einsum("sja,sjk->sajk", J_angle, b[:, :, start : start + m]).reshape(S, 3, n * m)
            )
            start += m
    return jnp.concatenate(blocks, axis=2)


def _weights(problem) -> Float[Array, " samples"]:
    d = problem.data
    return jnp.where(d.mask, 1.0 / d.sigma, 0.0)


def _residuals_primal(x, problem):
    r = ((predict(x, problem) - problem.data.y) * _weights(problem)[:, None]).reshape(-1)
    if problem.layout.orientation:
        r = jnp.concatenate([r, _rotation_residuals(x, problem)])
    return r


def _residuals_terms(x, problem):
    """The whitened residuals and their Jacobian: the positions' in closed form, the
    orientations' (when measured) by forward-mode autodiff."""
    w = _weights(problem)
    chain = _chain(x, problem)
    r = ((chain[0] - problem.data.y) * w[:, None]).reshape(-1)
    J = (point_jacobian(x, problem, chain) * w[:, None, None]).reshape(-1, x.shape[0])
    if problem.layout.orientation:
        r = jnp.concatenate([r, _rotation_residuals(x, problem)])
        J = jnp.concatenate([J, jax.jacfwd(_rotation_residuals)(x, problem)])
    return r, J


def _residuals_autodiff(x, problem):
    d = problem.data
    r = (predict(x, problem) - d.y) / d.sigma[:, None]
    r = jnp.where(d.mask[:, None], r, 0.0).reshape(-1)
    if problem.layout.orientation:
        r = jnp.concatenate([r, _rotation_residuals(x, problem)])
    return r


#: Whitened residuals $(\\hat y_i - y_i) / \\sigma_i$, zero for masked samples, flattened,
#: with the closed-form Jacobian (`point_jacobian`).
point_residuals = _lsq.closed_form_jvp(_residuals_primal, _residuals_terms, _residuals_autodiff)


class PointFitResult(eqx.Module):
    """A point fit's answer.

    - `x`, `std`, `cov`: the flattened parameters (`PointLayout` order), their
      1-sigma and covariance (scaled by the residual variance when `scale`).
    - `free`: estimated parameters; the others are held at nominal.
    - `independence`: each column's distance from the span kept before it.
    - `sigma2`: the residual variance factor $\\hat\\sigma^2$ (1 when the noise
      model is exact).
    - `rms_m`: RMS distance between measured and fitted points of the fitted samples (m).
    - `result`, `num_steps`: optimistix's.
    """

    x: Float[Array, " n"]
    std: Float[Array, " n"]
    cov: Float[Array, "n n"]
    free: Bool[Array, " n"]
    independence: Float[Array, " n"]
    sigma2: Float[Array, ""]
    rms_m: Float[Array, ""]
    result: optx.RESULTS
    num_steps: Int[Array, ""]


def fit_points(
    problem: PointProblem,
    candidates: Bool[Array, " n"],
    *,
    tol: float,
    free: Bool[Array, " n"] | None = None,
    options: _lsq.LMOptions | None = None,
) -> PointFitResult:
    """Solve the point fit; pure, jittable and vmappable (over `problem.data.mask` for folds).

    **Arguments:**
    - `problem`: the `PointProblem`.
    - `candidates`: the parameters that may be freed (e.g. the fixed frame held
      when it is the base; the point mount's rotation never shows in a point).
    - `tol`: independence threshold of the identifiability search (each
      column's distance from the span of those kept before it, columns
      normalised; see `_lsq.independent_columns`).
    - `free`: a given mask instead of the search.
    - `options`: the Levenberg-Marquardt settings (default `LM_OPTIONS`).

    **Returns:** a `PointFitResult`; the covariance is
    $\\hat\\sigma^2 (J^TJ)^{-1}$ over the free columns.
    """
    layout = problem.layout
    options = LM_OPTIONS if options is None else options
    x0 = jnp.zeros(layout.size)
    if free is None:
        _, J0 = _residuals_terms(x0, problem)
        keep, indep = _lsq.independent_columns_normal(
            J0.T @ J0, layout.priority(), tol=tol, candidates=candidates
        )
    else:
        keep, indep = jnp.asarray(free, bool), jnp.full(layout.size, jnp.nan)
    kf = keep.astype(x0.dtype)

    def normal(x, p):
        r, J = _residuals_terms(x * kf, p)
        J = J * kf[None, :]
        return r, NormalEquations(H=J.T @ J, e=J.T @ r)

    sol = normal_least_squares(
        normal, x0, problem, rtol=options.rtol, atol=options.atol, max_steps=options.max_steps
    )
    x = sol.x * kf
    r = sol.residuals  # and `sol.normal`: the normal equations at `x`, frozen columns zero
    n_obs = (6 if problem.layout.orientation else 3) * jnp.sum(problem.data.mask)
    sigma2 = _lsq.residual_variance(r, n_obs, jnp.sum(keep))
    cov = _lsq.covariance_normal(sol.normal.H, keep, sigma2)
    sigma = problem.data.sigma
    dist2 = jnp.sum((r[: 3 * sigma.shape[0]].reshape(-1, 3) * sigma[:, None]) ** 2, axis=1)
    rms = jnp.sqrt(jnp.sum(jnp.where(problem.data.mask, dist2, 0.0)) / jnp.sum(problem.data.mask))
    return PointFitResult(
        x=x,
        std=jnp.sqrt(jnp.maximum(jnp.diag(cov), 0.0)),
        cov=cov,
        free=keep,
        independence=indep,
        sigma2=sigma2,
        rms_m=rms,
        result=sol.result,
        num_steps=sol.num_steps,
    )


def prediction_std(x, cov, problem: PointProblem) -> Float[Array, " samples"]:
    """Per sample, the RMS over the three axes of the fitted point's standard
    deviation from the parameters' covariance (m): $\\sqrt{\\mathrm{tr}(J_i C J_i^T)/3}$."""
    J = point_jacobian(x, problem)
    var = jnp.einsum("sai,ij,saj->s", J, cov, J)
    return jnp.sqrt(jnp.maximum(var, 0.0) / 3.0)


def fold_masks(num: int, folds: int, seed: int = 0) -> np.ndarray:
    """`(folds, num)` training masks of a shuffled K-fold split (each sample held out once)."""
    if not 2 <= folds <= num:
        raise ValueError(f"cross-validation needs 2 <= folds <= samples ({num}), got {folds}")
    order = np.random.default_rng(seed).permutation(num)
    test = np.zeros((folds, num), bool)
    for k, chunk in enumerate(np.array_split(order, folds)):
        test[k, chunk] = True
    return ~test


def cross_validate(
    problem: PointProblem, candidates, free, train: Bool[Array, "folds samples"], options=None
):
    """K-fold cross-validation: per fold, the fit on the training samples with
    the mask of free parameters `free` (fixed, so folds are comparable), and
    the distances of the held-out samples from their prediction (m).

    **Returns:** `(distances (folds, samples), test mask (folds, samples))`.
    """
    base = problem.data.mask

    def one(tr):
        p = eqx.tree_at(lambda q: q.data.mask, problem, base & tr)
        res = fit_points(p, candidates, tol=0.0, free=free, options=options)
        d = jnp.linalg.norm(predict(res.x, problem) - problem.data.y, axis=1)
        return d

    dist = jax.vmap(one)(jnp.asarray(train))
    return dist, base[None, :] & ~jnp.asarray(train)


def kabsch(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """The rigid transform $T$ minimising $\\sum \\|T a_i - b_i\\|^2$ (NumPy; points `(n, 3)`)."""
    ca, cb = A.mean(0), B.mean(0)
    U, _, Vt = np.linalg.svd((A - ca).T @ (B - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, cb - R @ ca
    return T


def start_frame(
    nominal: KinematicModel, q: np.ndarray, y: np.ndarray, T_flange_point0: np.ndarray
) -> np.ndarray:
    """A start for $T_{dev,base}$: the rigid registration of the nominal model's
    points onto the measured ones (Kabsch)."""
    T = np.asarray(jax.vmap(lambda qq: forward_kinematics(nominal, qq)[-1])(jnp.asarray(q)))
    p = np.einsum("nab,b->na", T, np.asarray(T_flange_point0)[:, 3])[:, :3]
    return kabsch(p, y)
