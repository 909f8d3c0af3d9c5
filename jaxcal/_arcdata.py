"""Sweep data for the arc fit: one joint's marker poses per frame, their
whitening and encoder angles (`ArcData`, `make_arc_data`), and several sweeps
stacked into one batch for `jax.vmap(fit_arc)` (`stack_sweeps`)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

_DEG = np.pi / 180.0
MIN_FRAMES = 5
MIN_SWEEP_DEG = 5.0


class ArcData(eqx.Module):
    """Measurements of one joint sweep, padded to a fixed number of frames.

    **Fields:**
    - `positions`: marker positions in the camera frame (m), `(markers, frames, 3)`.
    - `orientations`: marker orientations `O_cam_marker`, `(markers, frames, 3, 3)`, or None.
    - `encoder`: encoder angles (rad), `(frames,)`, or None (no encoders).
    - `mask`: which entries were observed, `(markers, frames)`; padding is False
      and may hold any value, NaN included.
    - `sqrt_info`: whitening matrices $W$ with $W^T W = \\Sigma^{-1}$ of the
      per-frame error `(position, rotation vector)`, `(markers, frames, 6, 6)`
      (`3, 3` without orientations).
    """

    positions: Float[Array, "markers frames 3"]
    orientations: Float[Array, "markers frames 3 3"] | None
    encoder: Float[Array, " frames"] | None
    mask: Bool[Array, "markers frames"]
    sqrt_info: Float[Array, "markers frames k k"]


def make_arc_data(
    positions,
    orientations=None,
    encoder=None,
    mask=None,
    *,
    sigma_position: float = 1e-4,
    sigma_rotation: float = 1e-3,
    covariances=None,
) -> ArcData:
    """Build `ArcData`, adding a marker axis if absent and filling defaults.

    **Arguments:**
    - `positions`: `(frames, 3)` or `(markers, frames, 3)` (m).
    - `orientations`: matching `(..., 3, 3)` or None.
    - `encoder`: `(frames,)` encoder angles (rad) or None.
    - `mask`: `(frames,)` / `(markers, frames)` bools, default all observed.
    - `sigma_position` (m), `sigma_rotation` (rad): isotropic noise used when no
      `covariances` are given.
    - `covariances`: per-frame covariance of the measurement error
      (position, camera-frame rotation vector $w$ with $O = \\exp([w]_\\times) O_{true}$),
      `(..., frames, 6, 6)` (or `3, 3` without orientations), as
      `jaxcal.vision.estimate_pose` reports it.
    """
    P = jnp.asarray(positions, jnp.float64)
    if P.ndim == 2:
        P = P[None]
        orientations = None if orientations is None else jnp.asarray(orientations, jnp.float64)[None]
        mask = None if mask is None else jnp.asarray(mask)[None]
        covariances = None if covariances is None else jnp.asarray(covariances, jnp.float64)[None]
    M, F = P.shape[:2]
    O = None if orientations is None else jnp.asarray(orientations, jnp.float64)
    k = 3 if O is None else 6
    mask = jnp.ones((M, F), bool) if mask is None else jnp.asarray(mask, bool)
    if covariances is None:
        diag = jnp.array([1.0 / sigma_position] * 3 + [1.0 / sigma_rotation] * 3)[:k]
        W = jnp.broadcast_to(jnp.diag(diag), (M, F, k, k))
    else:
        C = jnp.asarray(covariances, jnp.float64)
        C = jnp.where(mask[..., None, None], C, jnp.eye(k))
        # The residual is (predicted - measured position, log(measured predicted^T)):
        # the position error enters with the opposite sign of the rotation error,
        # so its cross-covariance with the rotation flips (C -> S C S,
        # S = diag(-1, -1, -1, 1, 1, 1)). This matters for PnP poses, whose
        # lateral position and rotation errors are strongly correlated.
        s = jnp.array([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0])[:k]
        C = C * s[:, None] * s[None, :]
        # Sigma^{-1} = L^{-T} L^{-1} with Sigma = L L^T, so W = L^{-1}.
        L = jnp.linalg.cholesky(C)
        W = jax.vmap(jax.vmap(lambda Li: jax.scipy.linalg.solve_triangular(Li, jnp.eye(k), lower=True)))(L)
    enc = None if encoder is None else jnp.asarray(encoder, jnp.float64)
    return ArcData(positions=P, orientations=O, encoder=enc, mask=mask, sqrt_info=W)


# --------------------------------------------------------------------------- several sweeps


def _bucket_size(n: int, bucket: int | str) -> int:
    if bucket == "pow2":
        return 1 << max(n - 1, 0).bit_length()
    if isinstance(bucket, str) or int(bucket) < 1:
        raise ValueError(f"stack_sweeps: bucket must be a positive int or 'pow2', got {bucket!r}")
    return -(-n // int(bucket)) * int(bucket)


def stack_sweeps(
    sweeps,
    orientations=None,
    encoders=None,
    masks=None,
    *,
    covariances=None,
    sigma_position: float = 1e-4,
    sigma_rotation: float = 1e-3,
    bucket: int | str = 64,
) -> ArcData:
    """Stack sweeps of different lengths into one `ArcData` for `jax.vmap(fit_arc)`.

    Every sweep is padded (masked out) to one number of frames, rounded up to
    a bucket so that sweeps of similar length share a compiled program: a
    multiple of `bucket` (default 64) or, with `bucket="pow2"`, the next power
    of two. Markers are padded the same way (never observed) when the sweeps
    have different numbers. Padding holds zeros, identity rotations and
    identity whitening; `fit_arc` ignores it (its results equal those of the
    unpadded sweep to round-off). NumPy glue: call it outside `jit`.

    **Arguments:**
    - `sweeps`: one `ArcData` per joint (from `make_arc_data`), or one
      positions array per joint, `(frames_j, 3)` or `(markers, frames_j, 3)` (m),
      with `orientations`, `encoders`, `masks`, `covariances`: matching lists
      (or None) and the noise levels, as `make_arc_data` takes them.
    - `bucket`: the padding rule (above).

    **Returns:** an `ArcData` with a leading joints axis,
    `(joints, markers, frames, ...)`.
    """
    sweeps = list(sweeps)
    if not sweeps:
        raise ValueError("stack_sweeps: no sweeps")
    if isinstance(sweeps[0], ArcData):
        if any(x is not None for x in (orientations, encoders, masks, covariances)):
            raise ValueError("stack_sweeps: give ArcData sweeps alone, or positions with matching lists")
        if not all(isinstance(d, ArcData) for d in sweeps):
            raise ValueError("stack_sweeps: mix of ArcData and arrays")
        datas = sweeps
    else:
        n = len(sweeps)

        def each(x, name):
            if x is None:
                return [None] * n
            if len(x) != n:
                raise ValueError(f"stack_sweeps: {n} position arrays but {len(x)} {name}")
            return list(x)

        datas = [
            make_arc_data(
                P,
                O,
                e,
                m,
                sigma_position=sigma_position,
                sigma_rotation=sigma_rotation,
                covariances=C,
            )
            for P, O, e, m, C in zip(
                sweeps,
                each(orientations, "orientation arrays"),
                each(encoders, "encoder arrays"),
                each(masks, "masks"),
                each(covariances, "covariance arrays"),
            )
        ]
    has_rot = {d.orientations is not None for d in datas}
    has_enc = {d.encoder is not None for d in datas}
    if len(has_rot) > 1 or len(has_enc) > 1:
        raise ValueError(
            "stack_sweeps: every sweep needs the same inputs (orientations: "
            f"{[d.orientations is not None for d in datas]}, encoders: {[d.encoder is not None for d in datas]})"
        )
    M = max(d.mask.shape[0] for d in datas)
    F = _bucket_size(max(d.mask.shape[1] for d in datas), bucket)
    k = datas[0].sqrt_info.shape[-1]

    def pad(x, fill):
        x = np.asarray(x)
        out = np.broadcast_to(np.asarray(fill, x.dtype), (M, F) + x.shape[2:]).copy()
        out[: x.shape[0], : x.shape[1]] = x
        return out

    return ArcData(
        positions=jnp.asarray(np.stack([pad(d.positions, 0.0) for d in datas])),
        orientations=(
            jnp.asarray(np.stack([pad(d.orientations, np.eye(3)) for d in datas]))
            if has_rot == {True}
            else None
        ),
        encoder=(
            jnp.asarray(np.stack([np.pad(np.asarray(d.encoder), (0, F - d.encoder.shape[0])) for d in datas]))
            if has_enc == {True}
            else None
        ),
        mask=jnp.asarray(np.stack([pad(d.mask, False) for d in datas])),
        sqrt_info=jnp.asarray(np.stack([pad(d.sqrt_info, np.eye(k)) for d in datas])),
    )
