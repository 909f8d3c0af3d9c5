"""Choosing the frames: feasible candidates, seed 002's correction, greedy D-optimal selection and
gradient descent on the predicted end-effector error.

- `candidate_poses`: random configurations about the taught pose $q_0$, each
  checked and, when it fails, moved toward $q_0$ until it passes (the largest
  $s \\in \\{1, 0.9, ..., 0.1\\}$ with $q_0 + s (q - q_0)$ feasible) or dropped
  (`correct_toward`), with the first failing check named.
- `greedy_d_optimal`: the baseline (FIGAROH's selection): from the candidates,
  add one frame at a time, the one that most increases $\\log\\det$ of the
  Fisher information, $\\log\\det(I + B_v F^{-1} B_v^T)$ with $B_v$ the frame's
  Jacobian block (Woodbury updates of $F^{-1}$).
- `descend`: Adam on $\\log e^2(q) + w\\,\\overline{\\mathrm{pen}}(q)$ over every
  frame's joint values at once, $e^2$ the predicted mean-square EE error
  (`jaxcal.planning._evaluate.ee_mean_square`, autodiff through the Fisher
  information) and $\\mathrm{pen}$ the feasibility penalty of each frame
  (`jaxcal.planning._scene.penalty`); several starts vmapped.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray

from .._buckets import bucket
from ._evaluate import corner_problem, ee_mean_square, free_jacobian, term_columns
from ._scene import CHECKS, FeasibilityLimits, PlanScene, margins, penalty

#: Fractions of the way from the taught pose a failing frame is tried at, largest first.
FRACTIONS = (1.0, 0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3, 0.2, 0.1)


@eqx.filter_jit
def all_margins(
    scene: PlanScene, limits: FeasibilityLimits, q: Float[Array, "V joints"]
) -> Float[Array, "V k"]:
    """Every frame's margins, `(V, len(CHECKS))` in `CHECKS` order."""
    m = jax.vmap(lambda qq: margins(scene, limits, qq))(q)
    return jnp.stack([m[k] for k in CHECKS], axis=-1)


def correct_toward(
    scene: PlanScene, limits: FeasibilityLimits, q0, q, extra=None
) -> tuple[np.ndarray, np.ndarray, list]:
    """Seed 002's correction: each frame that fails moves toward the taught pose `q0`.

    **Arguments:** the scene and limits; `q0 (joints,)`; `q (V, joints)`; `extra`:
    an optional further check, `q (V, joints) -> list of None or a reason`
    (e.g. the MuJoCo contacts of `jaxcal.sim.plan`).

    **Returns:** `(q_new (V, joints), fraction (V,), reason per frame)`: fraction 1
    for a frame that passed as it was, 0 for one dropped; `reason` the first
    check the original frame failed (`None` when it passed).
    """
    q0 = np.asarray(q0, np.float64)
    q = np.asarray(q, np.float64).reshape(-1, q0.size)
    V = len(q)
    frac = np.zeros(V)
    out = q.copy()
    reason: list = [None] * V
    todo = np.ones(V, bool)
    size = bucket(V)  # every fraction's frames padded to one size: one compiled check, not one per count
    for s in FRACTIONS:
        if not todo.any():
            break
        idx = np.flatnonzero(todo)
        qs = q0 + s * (q[idx] - q0)
        padded = np.concatenate([qs, np.broadcast_to(q0, (size - len(qs), q0.size))])
        m = np.asarray(all_margins(scene, limits, jnp.asarray(padded)))[: len(qs)]
        ok = np.all(m > 0, axis=1)
        why = [CHECKS[int(np.argmax(row <= 0))] if not k else None for row, k in zip(m, ok)]
        if extra is not None and ok.any():
            ext = extra(qs[ok])
            for i, r in zip(np.flatnonzero(ok), ext):
                if r is not None:
                    ok[i], why[i] = False, r
        if s == FRACTIONS[0]:
            for i, w in zip(idx, why):
                reason[i] = w
        good = idx[ok]
        out[good], frac[good] = qs[ok], s
        todo[good] = False
    return out, frac, reason


def candidate_poses(
    scene: PlanScene,
    limits: FeasibilityLimits,
    q0,
    count: int,
    amplitude: float | np.ndarray,
    key: PRNGKeyArray,
    extra=None,
) -> tuple[np.ndarray, dict]:
    """`count` random configurations uniform within `amplitude` (rad, one or per
    joint) of the taught pose, clipped to the joint limits, corrected toward it
    (`correct_toward`); the dropped ones removed.

    **Returns:** `(feasible (M, joints), counts)`: `counts` of the first failing
    check over all draws, and of `moved` / `dropped` / `passed`.
    """
    q0 = np.asarray(q0, np.float64)
    u = np.asarray(jax.random.uniform(key, (count, q0.size), minval=-1.0, maxval=1.0))
    lo, hi = np.asarray(scene.lower), np.asarray(scene.upper)
    q = np.clip(q0 + u * np.asarray(amplitude), lo + limits.joint_margin, hi - limits.joint_margin)
    qn, frac, reason = correct_toward(scene, limits, q0, q, extra)
    counts = {k: sum(r == k for r in reason) for k in sorted({r for r in reason if r is not None})}
    counts |= {
        "passed": int(np.sum(frac == 1.0)),
        "moved": int(np.sum((frac > 0) & (frac < 1))),
        "dropped": int(np.sum(frac == 0)),
    }
    return qn[frac > 0], counts


def view_blocks(scene: PlanScene, q: Float[Array, "V joints"], free_idx: np.ndarray) -> Float[Array, "V r f"]:
    """Each frame's block of the refinement's Jacobian over the free parameters, `(V, 2N, f)`."""
    V = q.shape[0]
    J = free_jacobian(corner_problem(scene, q, jnp.arange(V, dtype=q.dtype)), free_idx)
    return J.reshape(V, -1, J.shape[-1])


@eqx.filter_jit
def greedy_d_optimal(B: Float[Array, "M r f"], count: int, prior: float = 1e-6) -> Int[Array, " count"]:
    """Greedy D-optimal selection of `count` of the `M` candidate frames (Jacobian
    blocks `B`), from a weak prior $F_0 = \\epsilon\\,\\mathrm{tr}(\\bar F)/f\\,I$ on
    Jacobi-scaled parameters. Pure; one `fori_loop`.

    **Returns:** the chosen candidates' indices, in the order chosen.
    """
    M, r, f = B.shape
    scale = jnp.sqrt(jnp.maximum(jnp.einsum("mrf,mrf->f", B, B) / M, 1e-300))
    Bs = B / scale
    Finv = jnp.eye(f) / (prior * r)

    def body(i, carry):
        Finv, taken, order = carry
        S = jnp.eye(r) + jnp.einsum("mrf,fg,msg->mrs", Bs, Finv, Bs)
        gain = 2.0 * jnp.sum(jnp.log(jnp.diagonal(jnp.linalg.cholesky(S), axis1=-2, axis2=-1)), axis=-1)
        v = jnp.argmax(jnp.where(taken, -jnp.inf, gain))
        b = Bs[v]
        W = Finv @ b.T
        Finv = Finv - W @ jnp.linalg.solve(S[v], W.T)
        return Finv, taken.at[v].set(True), order.at[i].set(v)

    init = (Finv, jnp.zeros(M, bool), jnp.zeros(count, int))
    return jax.lax.fori_loop(0, count, body, init)[2]


class TermModel(eqx.Module):
    """Non-geometric terms the planner counts as nuisance parameters (`jaxcal._terms`): the
    families and the links' masses and centres of mass of their basis."""

    masses: Float[Array, " joints"]
    coms: Float[Array, "joints 3"]
    terms: tuple[str, ...] = eqx.field(static=True)
    #: The zero offsets' indices in the flattened `RefineParams` (the joints' angle columns).
    zero_idx: tuple[int, ...] = eqx.field(static=True, default=())


def path_approach(q0, q):
    """Every frame's approach flank along a path from `q0` through the frames `q` in order
    (the sign of each joint's last move; no gradient)."""
    prev = jnp.concatenate([q0[None], q[:-1]])
    return jax.lax.stop_gradient(jnp.sign(q - prev))


def objective(scene, limits, M, free_idx, sigma_px, weight, q, terms: TermModel | None = None):
    """$\\log e^2(q) + w \\cdot$ mean feasibility penalty (see the module docstring); with
    `terms`, their columns join the information as nuisance parameters (`M` zero there)."""
    V = q.shape[0]
    problem = corner_problem(scene, q, jnp.arange(V, dtype=q.dtype))
    if terms is None:
        J = free_jacobian(problem, free_idx)
    else:
        # The joints' angle columns are the zero offsets': one Jacobian for both.
        f = len(free_idx)
        J = free_jacobian(problem, jnp.concatenate([jnp.asarray(free_idx), jnp.asarray(terms.zero_idx, int)]))
        T = term_columns(scene, q, path_approach(q[0], q), terms.masses, terms.coms, terms.terms, J[:, f:])
        J = jnp.concatenate([J[:, :f], T], axis=1)
        M = jnp.zeros((J.shape[1],) * 2).at[: M.shape[0], : M.shape[1]].set(M)
    pen = jnp.mean(jax.vmap(lambda qq: penalty(scene, limits, qq))(q))
    return jnp.log(ee_mean_square(J, M, sigma_px)) + weight * pen


@eqx.filter_jit
def descend(
    scene: PlanScene,
    limits: FeasibilityLimits,
    M: Float[Array, "f f"],
    free_idx: np.ndarray,
    q_init: Float[Array, "S V joints"],
    *,
    sigma_px: float,
    steps: int,
    lr: float = 0.02,
    weight: float = 10.0,
    terms: TermModel | None = None,
) -> tuple[Float[Array, "S V joints"], Float[Array, "S steps"]]:
    """Adam ($\\beta = 0.9, 0.999$) on `objective` from every start in `q_init`
    (vmapped), `steps` steps of at most `lr` rad per joint; joint values kept
    inside the limits. Pure.

    **Returns:** the final joint values and each start's objective per step.
    """
    lo, hi = scene.lower + limits.joint_margin, scene.upper - limits.joint_margin
    vg = jax.value_and_grad(lambda q: objective(scene, limits, M, free_idx, sigma_px, weight, q, terms))

    def one(q0):
        def step(carry, k):
            q, m, v = carry
            val, g = vg(q)
            g = jnp.where(jnp.isfinite(g), g, 0.0)
            m = 0.9 * m + 0.1 * g
            v = 0.999 * v + 0.001 * g * g
            mh, vh = m / (1 - 0.9 ** (k + 1)), v / (1 - 0.999 ** (k + 1))
            q = jnp.clip(q - lr * mh / (jnp.sqrt(vh) + 1e-12), lo, hi)
            return (q, m, v), val

        zeros = jnp.zeros_like(q0)
        (q, _, _), hist = jax.lax.scan(step, (q0, zeros, zeros), jnp.arange(steps))
        return q, hist

    return jax.vmap(one)(q_init)


def order_poses(q0, q) -> np.ndarray:
    """A short tour: nearest neighbour (largest joint move) from the taught pose."""
    q = np.asarray(q, np.float64)
    left = list(range(len(q)))
    here, out = np.asarray(q0, np.float64), []
    while left:
        d = [np.max(np.abs(q[i] - here)) for i in left]
        k = left.pop(int(np.argmin(d)))
        out.append(k)
        here = q[k]
    return np.array(out, dtype=int)


def path_clear(scene: PlanScene, limits: FeasibilityLimits, a, b, samples: int = 8) -> bool:
    """Whether the straight joint-space move from `a` to `b` (the plan's smooth
    step follows it) keeps clear of the arm itself and the floor."""
    s = np.linspace(0.0, 1.0, samples + 2)[1:-1, None]
    m = np.asarray(all_margins(scene, limits, jnp.asarray(a + s * (b - a))))
    cols = [CHECKS.index("self_collision"), CHECKS.index("scene_collision")]
    return bool(np.all(m[:, cols] > 0))
