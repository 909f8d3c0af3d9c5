"""Parameter tables a user reads, with covariance, from a calibration's estimate.

A table is a function $v(x)$ of the estimate's parameter vector: the URDF
joint origins (`physical_values`), or the DH / MDH table of the calibrated
model (`jaxcal._dh`). Its covariance is the estimate's propagated through the
Jacobian at the solution, $\\Sigma_v = G\\,\\Sigma_x\\,G^T$ with
$G = \\partial v / \\partial x$ (`jax.jacfwd`; the model depends only on the
axis-fit part of the vector, so $G$ is taken there and the rest of a
refinement's vector, rates, clock, intrinsics and per-view angles, does not
enter). A row is `free` when an estimated parameter moves it.
"""

import functools
from dataclasses import dataclass, replace

import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array, Float

from ._correction import Estimate, parameters_to_model, physical_jacobian, physical_names
from ._device import to_device
from ._dh import COLUMNS, DHTable, dh_table, parallel_pairs, table_value_names, table_values, to_mdh
from ._exported import stored_jit

#: Conventions of `physical_table`.
TABLE_CONVENTIONS = ("urdf", "dh", "mdh")


@dataclass(frozen=True, eq=False)
class PhysicalTable:
    """Physical parameters with their covariance (NumPy).

    - `names`, `units`, `groups`: one per row (`groups`: `correction`,
      `camera`, `mount` for URDF rows; `dh`, `base`, `flange` for table rows).
    - `nominal`, `estimate`, `std`: per row; `covariance`: rows x rows.
    - `free`: an estimated parameter moves the row.
    - `convention`: `"urdf"`, `"dh"` or `"mdh"`; `table`, `nominal_table`,
      `std_table`: for DH / MDH, the calibrated and nominal `DHTable` and the
      one whose entries are the standard deviations (None for URDF).
    """

    names: tuple[str, ...]
    units: tuple[str, ...]
    groups: tuple[str, ...]
    nominal: np.ndarray
    estimate: np.ndarray
    std: np.ndarray
    covariance: np.ndarray
    free: np.ndarray
    convention: str
    table: DHTable | None = None
    nominal_table: DHTable | None = None
    std_table: DHTable | None = None

    def rows(self) -> list[dict]:
        """One dict per row (`name`, `unit`, `group`, `nominal`, `estimate`, `std`, `free`)."""
        return [
            {
                "name": n,
                "unit": u,
                "group": g,
                "nominal": float(self.nominal[i]),
                "estimate": float(self.estimate[i]),
                "std": float(self.std[i]),
                "free": bool(self.free[i]),
            }
            for i, (n, u, g) in enumerate(zip(self.names, self.units, self.groups))
        ]


def estimate_prefix(estimate: Estimate) -> Estimate:
    """`estimate` cut to its axis-fit part (the vector the model depends on;
    a refinement's ratios are kept as constants)."""
    layout = estimate.layout
    n = layout.axis_size
    x = np.asarray(estimate.x)  # the ratios on the host: no eager JAX program per call
    ratio = (
        np.asarray(estimate.nominal.reduction_ratio) / x[layout.index("rate")]
        if x.shape[0] == layout.size
        else np.asarray(estimate.reduction_ratio)
    )
    return Estimate(  # cut on the host: no eager JAX program per slice
        x=to_device(np.asarray(estimate.x)[:n]),
        cov=to_device(np.asarray(estimate.cov)[:n, :n]),
        free=to_device(np.asarray(estimate.free)[:n]),
        nominal=estimate.nominal,
        T_flange_marker0=estimate.T_flange_marker0,
        T_cam_base0=estimate.T_cam_base0,
        reduction_ratio=to_device(ratio),
        layout=layout,
        mount_names=estimate.mount_names,
    )


def dh_values(estimate: Estimate, reference: DHTable, x: Float[Array, " n"]) -> Float[Array, " values"]:
    """`table_values` of the calibrated model's DH table at axis-fit vector `x`
    (the form and signs of `reference`)."""
    return table_values(dh_table(parameters_to_model(estimate, x).model, "dh", reference=reference))


def dh_jacobian(estimate: Estimate, parallel: tuple[bool, ...]):
    """The nominal and calibrated DH tables, the Jacobian of `dh_values` at the estimate,
    and both tables' `table_values` (nominal, calibrated), as one compiled call (MDH
    follows by `mdh_from_dh_values`)."""
    return _dh_program(tuple(bool(p) for p in parallel))(estimate)


# Runs once per exported result: compiled without XLA's optimisation passes (the CLI's
# DH export compiles in half the time), its traced program stored (`jaxcal._exported`).
@functools.cache
def _dh_program(parallel: tuple[bool, ...]):
    def dh_jacobian(estimate: Estimate):
        reference = dh_table(estimate.nominal, "dh", parallel=parallel)
        table = dh_table(parameters_to_model(estimate).model, "dh", reference=reference)
        G = jax.jacfwd(lambda x: dh_values(estimate, reference, x))(estimate.x)
        return reference, table, G, table_values(reference), table_values(table)

    return stored_jit(dh_jacobian, "dh_jacobian", (parallel,))


def mdh_from_dh_values(num_joints: int) -> np.ndarray:
    """The 0/1 matrix mapping `table_values` of a DH table to those of its MDH
    form (`to_mdh`: $a$, $\\alpha$, $\\beta$ one row later, row 1's zero)."""
    n = num_joints
    size = 5 * n + 12
    P = np.zeros((size, size))
    shifted = {COLUMNS.index(c) for c in ("a", "alpha", "beta")}
    for i in range(n):
        for c in range(5):
            if c not in shifted:
                P[5 * i + c, 5 * i + c] = 1.0
            elif i > 0:
                P[5 * i + c, 5 * (i - 1) + c] = 1.0
    P[5 * n :, 5 * n :] = np.eye(12)
    return P


def as_estimate(source) -> Estimate:
    """An `Estimate`, or the `estimate` of a `CalibrationResult`."""
    est = source if isinstance(source, Estimate) else getattr(source, "estimate", None)
    if not isinstance(est, Estimate):
        raise TypeError(f"expected an Estimate or a CalibrationResult with one, got {type(source).__name__}")
    return est


def physical_table(source, convention: str = "urdf") -> PhysicalTable:
    """The calibrated parameters in `convention` with their covariance.

    **Arguments:**
    - `source`: a `CalibrationResult` or its `Estimate`.
    - `convention`: `"urdf"` (joint origins as xyz/rpy, zero offsets, the
      fixed frame, the mounts: the `parameters` of `result.json`), `"dh"` or
      `"mdh"` (per joint $\\theta, d, a, \\alpha, \\beta$ and the base and flange
      transforms as xyz/rpy; see `jaxcal._dh` for the frames and the
      parallel-axis rule; the nominal model's table fixes the form and the signs).

    **Returns:** a `PhysicalTable`; its `covariance` is $G\\Sigma_x G^T$.
    """
    if convention not in TABLE_CONVENTIONS:
        raise ValueError(f"convention must be one of {TABLE_CONVENTIONS}, got {convention!r}")
    est = estimate_prefix(as_estimate(source))
    if convention == "urdf":
        cam, corr, _ = est.layout.split(est.x)
        value, nom, G = (
            np.asarray(a)
            for a in physical_jacobian(est.nominal, est.T_flange_marker0, est.T_cam_base0, cam, corr)
        )
        names, units, groups = zip(
            *physical_names(est.layout, list(est.mount_names), est.nominal.joint_types)
        )
        return _table(names, units, groups, nom, value, G, est, convention)
    reference, table, G, nom, value = dh_jacobian(est, parallel_pairs(est.nominal))
    nom, value, G = np.asarray(nom), np.asarray(value), np.asarray(G)
    if convention == "mdh":
        P = mdh_from_dh_values(est.nominal.num_joints)
        reference, table, nom, value, G = to_mdh(reference), to_mdh(table), P @ nom, P @ value, P @ G
    names, units = zip(*table_value_names(reference))
    n = est.nominal.num_joints
    groups = (convention,) * (5 * n) + ("base",) * 6 + ("flange",) * 6
    out = _table(names, units, groups, nom, value, G, est, convention)
    return replace(out, table=table, nominal_table=reference, std_table=_std_table(reference, out.std))


def _table(names, units, groups, nom, value, G, est: Estimate, convention: str) -> PhysicalTable:
    """The covariance $G\\Sigma G^T$, the std and the free rows, into a `PhysicalTable`."""
    cov = G @ np.asarray(est.cov) @ G.T
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    free = np.abs(G[:, np.asarray(est.free)]).sum(axis=1) > 1e-12
    return PhysicalTable(tuple(names), tuple(units), tuple(groups), nom, value, std, cov, free, convention)


def _std_table(reference: DHTable, std: np.ndarray) -> DHTable:
    """A `DHTable` whose columns hold the standard deviations (base/flange left as identity)."""
    n = len(reference.joint_names)
    cols = np.asarray(std[: 5 * n].reshape(n, 5).T)
    return eqx.tree_at(
        lambda t: (t.theta, t.d, t.a, t.alpha, t.beta), reference, tuple(to_device(cols[k]) for k in range(5))
    )


def base_flange_std(table: PhysicalTable) -> dict[str, np.ndarray]:
    """Standard deviations of the base and flange transforms (xyz m, rpy rad) of a DH / MDH table."""
    n = len(table.table.joint_names)
    return {"base": table.std[5 * n : 5 * n + 6], "flange": table.std[5 * n + 6 : 5 * n + 12]}
