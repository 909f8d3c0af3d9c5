"""Dense linear algebra that is safe to batch on the CPU backend.

Why this module exists: jaxlib's CPU LAPACK kernels (SVD, eigh, Cholesky, LU,
QR, triangular solves) split a large enough batch into chunks, schedule the
chunks on XLA's intra-op thread pool and then *block* the pool thread they run
on until the chunks are done. XLA runs independent operations of one program
concurrently on that same pool. When as many chunked kernels run at once as
the pool has threads (two, on a two-core machine), every pool thread waits for
chunks that no thread is free to run: the process hangs with no CPU use. That
is what stalled `vmap`-ed refinements in CI (an SVD and a pseudo-inverse's
eigh side by side).

There is no runtime switch for it (the pool size and the executor's
sequential mode are compile-time constants in jaxlib 0.10), so jaxcal keeps
the decompositions of each program totally ordered by data dependence:

- one decomposition where two were taken (`gauss_newton_covariance` gives the
  covariance, the singular values and the right singular vectors from a
  single SVD; several small matrices go through one batched call);
- `after` where two must stay separate (an arithmetic dependence: XLA drops
  `optimization_barrier` from the compiled program, so it orders nothing at
  run time);
- `concurrent_decompositions` checks a function's jaxpr for any pair left
  unordered, and the tests run it on every batched entry point.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import core as jex
from jaxtyping import Array, Float

#: Primitives lowered to LAPACK kernels that may block a pool thread on CPU.
DECOMPOSITIONS = frozenset(
    {
        "cholesky",
        "eig",
        "eigh",
        "geqp3",
        "geqrf",
        "hessenberg",
        "householder_product",
        "lu",
        "ormqr",
        "qr",
        "schur",
        "svd",
        "triangular_solve",
        "tridiagonal",
        "tridiagonal_solve",
    }
)


def after(x: Any, *deps: Any) -> Any:
    """`x`, made to depend on `deps`: whatever consumes the result runs after
    every inexact array in `deps` is computed.

    The dependency is arithmetic, `x + 0 * nan_to_num(d[0])` for the first
    element of every floating leaf `d` of `deps`, which leaves `x` unchanged
    (to the sign of a zero) and which XLA keeps: it does not fold a float
    product with zero. `lax.optimization_barrier` does *not* do this at run
    time: XLA removes the barrier from the optimised program, and the CPU
    runtime then schedules by data dependence only (`tests/test_linalg.py`
    checks the compiled program).
    """
    firsts = [
        jnp.nan_to_num(jnp.ravel(d)[0])
        for d in jax.tree.leaves(deps)
        if jnp.issubdtype(jnp.result_type(d), jnp.inexact) and jnp.size(d) > 0
    ]
    if not firsts:
        return x
    zero = 0.0 * sum(jnp.real(f) for f in firsts)
    return jax.tree.map(
        lambda a: (
            a + zero.astype(jnp.result_type(a)) if jnp.issubdtype(jnp.result_type(a), jnp.inexact) else a
        ),
        x,
    )


def nearest_rotation(M: Float[Array, "... 3 3"]) -> Float[Array, "... 3 3"]:
    """The rotation closest to `M` in Frobenius norm (polar factor, det +1).
    Batched over leading axes in one SVD call."""
    U, _, Vt = jnp.linalg.svd(M)
    R = U @ Vt
    flip = jnp.sign(jnp.linalg.det(R))
    Vt = Vt.at[..., 2, :].multiply(flip[..., None])
    return U @ Vt


def gauss_newton_covariance(
    J: Float[Array, "m n"], rtol: float | None = None
) -> tuple[Float[Array, "n n"], Float[Array, " n"], Float[Array, "n n"]]:
    """`(J^T J)^+` with `J`'s columns scaled to unit norm first (Jacobi), the
    singular values and right singular vectors of the scaled `J`, from one SVD.

    Zero columns (frozen or unobserved parameters) get zero variance. Directions
    whose scaled singular value is under `rtol` times the largest are treated
    as unidentifiable and left out of the inverse (default
    $\\sqrt{10\\,n\\,\\epsilon}$: NumPy's `pinv` cut on the eigenvalues of
    $J^T J$, taken on its square roots). For a full-rank `J` this equals
    `pinv(J.T @ J)`; for a rank-deficient one it is the minimum-norm inverse in
    the scaled parameters, which does not depend on the parameters' units.
    """
    m, n = J.shape
    rtol = float(np.sqrt(10 * n * np.finfo(np.dtype(J.dtype)).eps)) if rtol is None else rtol
    norms = jnp.linalg.norm(J, axis=0)
    scale = jnp.where(norms > 0, 1.0 / jnp.where(norms > 0, norms, 1.0), 0.0)
    _, sv, Vt = jnp.linalg.svd(J * scale, full_matrices=False)
    keep = sv > rtol * sv[0]
    inv_s2 = jnp.where(keep, 1.0 / jnp.where(keep, sv, 1.0) ** 2, 0.0)
    A = Vt * scale[None, :]  # rows: V^T D^-1
    return A.T @ (inv_s2[:, None] * A), sv, Vt


# --------------------------------------------------------------------------- checking


#: Primitives that hide a LAPACK call from the jaxpr: lineax's `linear_solve`
#: (the QR / Cholesky / LU inside every optimistix Levenberg-Marquardt step)
#: keeps its operator and solver as Python objects, not as a sub-jaxpr.
OPAQUE_SOLVES = frozenset({"linear_solve"})


def _subjaxprs(params: dict) -> list:
    return list(jex.jaxprs_in_params(params))


def _primitive_name(e) -> str:
    """The equation's primitive, seen through equinox's batching wrapper (`vprim`)."""
    name = e.primitive.name
    if name == "vprim":
        inner = dict(e.params.get("params", ())).get("prim")
        if inner is not None:
            return getattr(inner, "name", name)
    return name


def _is_decomposition(e) -> bool:
    name = _primitive_name(e)
    return name in DECOMPOSITIONS or name in OPAQUE_SOLVES


def _decompositions_in(jaxpr) -> set[str]:
    out: set[str] = set()
    for e in jaxpr.eqns:
        if _is_decomposition(e):
            out.add(_primitive_name(e))
        for s in _subjaxprs(e.params):
            out |= _decompositions_in(s)
    return out


def _label(e, i: int) -> str:
    from jax._src import source_info_util

    inner = sorted(set().union(*(_decompositions_in(s) for s in _subjaxprs(e.params))))
    name = _primitive_name(e) + (f"({','.join(inner)})" if inner else "")
    return f"{name}[{i}] at {source_info_util.summarize(e.source_info)}"


def _unordered_pairs(jaxpr, where: str, found: list[str]) -> None:
    # Per variable: the decomposition-bearing equations it depends on.
    deps: dict = {}
    nodes: list[tuple[int, str, frozenset]] = []
    for i, e in enumerate(jaxpr.eqns):
        subs = _subjaxprs(e.params)
        for k, s in enumerate(subs):
            _unordered_pairs(s, f"{where}/{e.primitive.name}[{i}.{k}]", found)
        d = frozenset().union(*(deps.get(v, frozenset()) for v in e.invars if isinstance(v, jex.Var)))
        heavy = _is_decomposition(e) or any(_decompositions_in(s) for s in subs)
        if heavy:
            nodes.append((i, _label(e, i), d))
            d = d | {i}
        for v in e.outvars:
            deps[v] = d
    for a in range(len(nodes)):
        for b in range(a + 1, len(nodes)):
            (i, pi, _), (_, pj, dj) = nodes[a], nodes[b]
            if i not in dj:
                found.append(f"{where or '/'}: {pi} and {pj}")


def concurrent_decompositions(fn: Callable, *args, **kwargs) -> list[str]:
    """Pairs of LAPACK-backed operations in `fn(*args, **kwargs)`'s program
    that no data dependence orders (each as 'path: prim[i] and prim[j]').
    Higher-order operations (loops, calls, conditionals) that contain one count
    as one. Empty means XLA can never run two of them at once."""
    found: list[str] = []
    _unordered_pairs(jax.make_jaxpr(fn)(*args, **kwargs).jaxpr, "", found)
    return found
