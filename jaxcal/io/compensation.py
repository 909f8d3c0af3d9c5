"""`compensation.json`: the non-geometric terms a calibration kept, for the robot side to apply.

The calibrated URDF carries the rigid model; a joint's sag under gravity and
its lost motion it cannot. This file carries them (schema `jaxcal.compensation`,
version 1): the kept families and coefficients (`jaxcal._terms`), what their
basis is evaluated on (the nominal model, the links' masses and centres of mass
with the payload lumped in, gravity, the preload torque and the approach play)
and the rates. A controller (or `jaxcal.compensate`) commands $q_c = q_t -
\\Delta(q_c, a)/\\rho$ for a target $q_t$ of the rigid model.
"""

import json
from dataclasses import dataclass

import numpy as np

from .._kinematics import KinematicModel
from .._terms import APPROACH_WIDTH_RAD, GRAVITY, PRELOAD_NM, check_terms, names
from ..errors import DatasetError
from .model_json import model_from_json, model_to_json

SCHEMA = "jaxcal.compensation"
SCHEMA_VERSION = 1
#: The file `jaxcal.write_outputs` writes beside `result.json` when a term was kept.
COMPENSATION_FILE = "compensation.json"


@dataclass(frozen=True, eq=False)
class Compensation:
    """What `compensate` needs: the kept `terms`, their coefficients `x` and `std` (`names`
    order), the `nominal` model and the inertials (`masses`, `coms`) the basis is evaluated
    on, and each joint's `rate` (joint turn per commanded turn)."""

    terms: tuple[str, ...]
    x: np.ndarray
    std: np.ndarray
    nominal: KinematicModel
    masses: np.ndarray
    coms: np.ndarray
    rate: np.ndarray


def compensation_json(c: Compensation) -> dict:
    """The `compensation.json` payload of `c`."""
    joints = list(c.nominal.joint_names)
    coefficient_names = names(c.terms, joints)
    return {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "formula": "command q_c = q_t - Delta(q_c, a) / rate for a target q_t of calibrated.urdf, with "
        "Delta_j = sum_k e[j.family.k] b_k(q, a): compliance b = tau_j(q) / 1000 (the gravity torque about joint j, "
        "N m, from the masses below, gravity along the base's -z); backlash b = (a_j, tanh(tau_j / preload_nm)), "
        "a_j the flank joint j approaches from (+1 from smaller angles, -1 from larger, 0 unknown; a play of "
        "approach_width_rad); harmonic1/2 b = (sin(k q_j), cos(k q_j)); the basis on nominal_model at q",
        "joints": joints,
        "terms": list(c.terms),
        "coefficients": dict(zip(coefficient_names, np.asarray(c.x, np.float64).tolist())),
        "std": dict(zip(coefficient_names, np.asarray(c.std, np.float64).tolist())),
        "rate": np.asarray(c.rate, np.float64).tolist(),
        "gravity_m_s2": [0.0, 0.0, -GRAVITY],
        "preload_nm": PRELOAD_NM,
        "approach_width_rad": APPROACH_WIDTH_RAD,
        "masses_kg": np.asarray(c.masses, np.float64).tolist(),
        "coms_m": np.asarray(c.coms, np.float64).tolist(),
        "nominal_model": model_to_json(c.nominal),
    }


def read_compensation(path) -> Compensation:
    """The `Compensation` in `compensation.json` at `path` (a `DatasetError` naming the file
    and the field when it is not one jaxcal wrote)."""
    try:
        with open(path) as f:
            d = json.load(f)
    except FileNotFoundError:
        raise DatasetError(f"{path}: no such file") from None
    except (OSError, ValueError) as e:
        raise DatasetError(f"{path}: not JSON ({e})") from None
    try:
        if d.get("schema") != SCHEMA or d.get("schema_version") != SCHEMA_VERSION:
            raise ValueError(
                f"schema {d.get('schema')!r} version {d.get('schema_version')!r}, expected {SCHEMA!r} 1"
            )
        terms = check_terms(d["terms"])
        nominal = model_from_json(d["nominal_model"])
        wanted = names(terms, nominal.joint_names)
        missing = [n for n in wanted if n not in d["coefficients"]]
        if missing:
            raise ValueError(f"'coefficients' lacks {missing[:3]} (the terms {list(terms)} name them)")
        n = nominal.num_joints
        c = Compensation(
            terms=terms,
            x=np.array([float(d["coefficients"][k]) for k in wanted]),
            std=np.array([np.nan if d["std"].get(k) is None else float(d["std"][k]) for k in wanted]),
            nominal=nominal,
            masses=np.asarray(d["masses_kg"], np.float64).reshape(n),
            coms=np.asarray(d["coms_m"], np.float64).reshape(n, 3),
            rate=np.asarray(d["rate"], np.float64).reshape(n),
        )
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise DatasetError(f"{path}: not a compensation file jaxcal wrote ({e})") from None
    bad = [f"'coefficients' {k!r}" for k, v in zip(wanted, c.x, strict=True) if not np.isfinite(v)]
    bad += [
        f"'{k}'"
        for k, v in (("masses_kg", c.masses), ("coms_m", c.coms), ("rate", c.rate))
        if not np.isfinite(v).all()
    ]
    if bad or (c.rate <= 0).any() or (c.masses < 0).any():
        why = (
            f"{bad[0]} is not a finite number"
            if bad
            else "'rate' must be positive and 'masses_kg' not negative"
        )
        raise DatasetError(f"{path}: {why}")
    if d.get("preload_nm") != PRELOAD_NM or d.get("approach_width_rad") != APPROACH_WIDTH_RAD:
        raise DatasetError(
            f"{path}: written with preload_nm {d.get('preload_nm')} and approach_width_rad "
            f"{d.get('approach_width_rad')}; this jaxcal's basis uses {PRELOAD_NM} and {APPROACH_WIDTH_RAD}"
        )
    return c
