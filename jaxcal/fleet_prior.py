"""A fleet's prior (`jaxcal.fleet`): what its usable units' point fits say of the next unit of
their model, as a Gaussian over the robot's own parameters (empirical Bayes, `fleet_prior`); its
reading from `fleet.json` (`read_prior`, every field checked) and its rows over a point fit's
vector (`prior_rows`, refused for another robot model or gauge)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._records_base import Record, from_plain
from .errors import DatasetError
from .io._schema import read_json

#: `fleet.json`'s schema version.
FLEET_SCHEMA_VERSION = 1
#: The fewest calibrated units that say what is usual.
MIN_UNITS = 5
#: The smallest difference between robots that counts (m, rad, or relative for unitless
#: parameters: 10 um, 10 urad), far below the spread of a model's robots (tenths of a
#: millimetre, tenths of a degree) and below what a calibration is used for: parameters a capture
#: barely moves (an offset along parallel axes, which the gauge fixes) scatter by nanometres to
#: micrometres across units, heavy-tailed, a difference no robot has.
RESOLUTION = 1e-5


@dataclass(frozen=True, eq=False)
class FleetPrior(Record):
    """A robot model's parameters across a fleet, as a Gaussian prior for the next unit: `names`
    (the point fit's, `jaxcal._pointfit.PointLayout.names`), their `mean` and the population's
    `covariance` (the units' own removed), from `units` units of the robot whose joints are `joints`
    and whose nominal model's digest is `nominal` (`model_digest`); `file`: where it was read."""

    units: int
    joints: tuple[str, ...]
    nominal: str
    names: tuple[str, ...]
    mean: np.ndarray
    covariance: np.ndarray
    #: The units' fixed frame was estimated (not `--device-is-base`): the parameters' gauge.
    frame_free: bool = True
    file: str = ""
    #: The units' data (`data_digest`): a unit of this fleet is not given its own fleet's prior.
    data: tuple[str, ...] = ()


#: The nominal model's fields a prior depends on: the robot's, not the tool the dataset mounts.
DIGESTED = ("T_parent_joint", "axis", "zero_offset", "reduction_ratio", "T_last_flange")


def model_digest(model) -> str:
    """A short digest of a nominal `KinematicModel`'s joints and geometry (to 1e-12): a prior is for
    the model it was learnt on."""
    h = hashlib.sha256(json.dumps([model.joint_names, model.joint_types]).encode())
    for name in DIGESTED:
        h.update(np.round(np.asarray(getattr(model, name), np.float64), 12).tobytes())
    return h.hexdigest()[:16]


#: A file larger than this is digested by its size, first and last `EDGE_BYTES` (a copied capture's
#: images are told without reading every byte of them).
WHOLE_BYTES, EDGE_BYTES = 1 << 20, 1 << 16


#: What is not a dataset's data: its metadata, a simulator's answer key, notes beside it, a
#: system's droppings. Two units differing only in these are one unit's data twice.
NOT_DATA = ("metadata.json", "truth.json")
NOTES = (".md", ".txt", ".rst", ".pdf", ".html")
#: Text whose line ends a copy may have changed (Windows' CRLF): compared line by line.
TEXT = (".csv", ".tsv", ".json", ".yaml", ".yml", ".urdf", ".xml")


def _is_data(path: Path) -> bool:
    return not (
        path.name in NOT_DATA
        or path.suffix.lower() in NOTES
        or path.name.lower().startswith("readme")
        or any(part.startswith(".") for part in path.parts)
    )


def data_digest(root) -> str:
    """A short digest of a dataset's data: every data file under `root` (not its metadata, a
    simulator's `truth.json`, notes or hidden files; `_is_data`), its name relative to `root` and
    its bytes, text with its line ends, trailing spaces and blank lines normalised. Two units of one digest
    are one unit's data twice."""
    root, h = Path(root), hashlib.sha256()
    files = sorted(p for p in root.rglob("*") if p.is_file() and _is_data(p.relative_to(root)))
    for path in files:
        h.update(path.relative_to(root).as_posix().encode() + b"\0")
        size = path.stat().st_size
        with open(path, "rb") as f:
            if path.suffix.lower() in TEXT and size <= WHOLE_BYTES:
                h.update(b"\n".join(line.rstrip() for line in f.read().splitlines() if line.strip()))
            elif size <= WHOLE_BYTES:
                h.update(f.read())
            else:
                h.update(str(size).encode() + f.read(EDGE_BYTES))
                f.seek(size - EDGE_BYTES)
                h.update(f.read())
    return h.hexdigest()[:16]


def check_not_a_unit(prior: FleetPrior | None, root) -> None:
    """Raises `DatasetError` when the dataset at `root` is one of the units `prior` was learnt on:
    its data would count twice (once in the prior, once as data)."""
    if prior is None or not prior.data or not Path(root).is_dir():
        return
    if data_digest(root) in prior.data:
        raise DatasetError(
            f"{root}: this dataset is one of the units the prior {prior.file} was learnt on (the same data): "
            "its data would count twice; calibrate it without --prior"
        )


def prior_parameter(name: str, fixed_frame: str) -> bool:
    """Whether a point-fit parameter is the robot's own (a prior carries it), not the frame the unit
    is measured in or its point's mount, which differ per unit."""
    return not name.startswith((f"{fixed_frame}.", "marker.mount.", "camera.mount."))


def fleet_prior(
    fits: dict, joints: Sequence[str], nominal: str, fixed_frame: str, frame_free: bool = True, data=()
) -> FleetPrior | None:
    """The fleet's prior from its usable units' point fits (`fits[unit] = (names, x, cov, free)`;
    `data`: their data's digests, `data_digest`):
    over the robot's parameters every unit estimated, the mean and the population's covariance:
    each parameter's variance $S_{ii} - \\overline{C_{ii}}$ (the sample's less the units' own), no
    smaller than $\\overline{C_{ii}}$ or `RESOLUTION`$^2$, and the sample's correlations shrunk
    towards none by parameters over units. None with fewer than `MIN_UNITS` units (or no such
    parameter)."""
    if len(fits) < MIN_UNITS:
        return None
    first = next(iter(fits.values()))[0]
    common = [
        n
        for n in first
        if prior_parameter(n, fixed_frame)
        and all(n in names and free[names.index(n)] for names, _, _, free in fits.values())
    ]
    if not common:
        return None
    X, C = [], []
    for names, x, cov, _ in fits.values():
        idx = [names.index(n) for n in common]
        X.append(np.asarray(x)[idx])
        C.append(np.asarray(cov)[np.ix_(idx, idx)])
    X, k, n = np.asarray(X), len(common), len(fits)
    S = np.cov(X, rowvar=False, ddof=1).reshape(k, k)
    meas = np.mean([np.diag(c) for c in C], axis=0)
    # Each parameter's population variance, no smaller than the units' own measurement variance
    # (a fleet cannot say its robots are closer than it measured them), nor RESOLUTION^2.
    var = np.maximum(np.diag(S) - meas, np.maximum(meas, RESOLUTION**2))
    # Their correlations, shrunk towards none by parameters / units: fewer units than parameters
    # leave most directions unseen, and a prior must not claim them known.
    d = np.sqrt(np.diag(S))
    R = S / np.outer(d, d) if np.all(d > 0) else np.eye(k)
    shrink = min(1.0, k / n)
    R = (1.0 - shrink) * R + shrink * np.eye(k)
    pop = R * np.sqrt(np.outer(var, var))
    return FleetPrior(
        units=len(fits),
        joints=tuple(joints),
        nominal=nominal,
        names=tuple(common),
        mean=X.mean(axis=0),
        covariance=pop,
        frame_free=frame_free,
        data=tuple(data),
    )


def read_prior(path) -> FleetPrior:
    """The `FleetPrior` of a `fleet.json` (or the folder `jaxcal calibrate` wrote it in); raises
    `DatasetError` naming the file and the field when it has none or is not one jaxcal wrote."""
    p = Path(path)
    file = p / "fleet.json" if p.is_dir() else p
    doc = read_json(file, "fleet summary (--prior takes the fleet.json a fleet's calibration wrote)")
    if not isinstance(doc, dict) or doc.get("schema") != "jaxcal.fleet":
        raise DatasetError(f"{file}: not a fleet.json jaxcal wrote (schema is not 'jaxcal.fleet')")
    if "prior" not in doc:
        raise DatasetError(f"{file}: no field 'prior' (not a fleet.json as jaxcal writes it, or edited)")
    if not doc.get("prior"):
        raise DatasetError(
            f"{file}: 'prior' is empty: the fleet had fewer than {MIN_UNITS} usable units calibrated "
            "from points (a tracker, motion capture or the controller's tool point)"
        )
    if doc.get("schema_version") != FLEET_SCHEMA_VERSION:
        raise DatasetError(
            f"{file}: schema_version {doc.get('schema_version')!r}, this jaxcal reads {FLEET_SCHEMA_VERSION}"
        )
    try:
        prior = from_plain(FleetPrior, doc["prior"])
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(
            f"{file}: field 'prior' is not one jaxcal wrote ({type(e).__name__}: {e})"
        ) from None
    k, C = len(prior.names), prior.covariance
    bad = {
        "prior.names": "names repeated" if len(set(prior.names)) < k else "",
        "prior.units": f"{prior.units} units, a prior is learnt on {MIN_UNITS} or more"
        if prior.units < MIN_UNITS
        else "",
        "prior.mean": f"shape {prior.mean.shape} for {k} names" if prior.mean.shape != (k,) else "",
        "prior.covariance": f"shape {C.shape} for {k} names" if C.shape != (k, k) else "",
    }
    if not any(bad.values()):
        finite = np.all(np.isfinite(prior.mean)) and np.all(np.isfinite(C))
        bad["prior.mean"] = "" if finite else "values that are not finite"
        if finite and not np.allclose(C, C.T, rtol=1e-9, atol=0.0):
            bad["prior.covariance"] = "not symmetric"
        elif finite and np.linalg.eigvalsh(C).min() <= 0:
            bad["prior.covariance"] = "not positive definite"
    for where, why in bad.items():
        if why:
            raise DatasetError(f"{file}: field '{where}' is not one jaxcal wrote ({why})")
    return dataclasses.replace(prior, file=str(file))


def as_prior(prior) -> FleetPrior | None:
    """`jaxcal.calibrate`'s `prior`: None, a `FleetPrior`, or the `fleet.json` to read (`read_prior`)."""
    if prior is None or isinstance(prior, FleetPrior):
        return prior
    if isinstance(prior, (str, os.PathLike)):
        return read_prior(prior)
    raise TypeError(f"prior: a fleet.json path or a jaxcal.fleet.FleetPrior, got {type(prior).__name__}")


def prior_rows(
    prior: FleetPrior, names: Sequence[str], joints: Sequence[str], nominal: str, frame_free: bool
):
    """The prior over a point fit's vector `names` (`jaxcal._pointfit.PointPrior`'s `root` and
    `mean`, full length, zero where the prior says nothing; `frame_free`: the unit's fixed frame is
    estimated). Raises `DatasetError` naming the file when it was learnt on another robot model, or
    with the fixed frame held where this unit estimates it (or the reverse)."""
    if tuple(joints) != prior.joints:
        raise DatasetError(
            f"{prior.file}: this prior was learnt on another robot (the fleet's joints {list(prior.joints)}, "
            f"this dataset's {list(joints)})"
        )
    if nominal != prior.nominal:
        raise DatasetError(
            f"{prior.file}: this prior was learnt on another robot model: the same joints, but the robot file's "
            f"joint origins, axes or zero offsets differ (digest {prior.nominal} against this dataset's {nominal})"
        )
    if frame_free != prior.frame_free:
        given = "with" if not prior.frame_free else "without"
        raise DatasetError(
            f"{prior.file}: the fleet was calibrated {given} --device-is-base and this unit is not: its "
            "parameters are in another gauge; calibrate the two alike"
        )
    missing = [n for n in prior.names if n not in names]
    if missing:
        raise DatasetError(f"{prior.file}: prior parameters {missing} are not in this calibration's model")
    return gaussian_rows(prior.names, prior.mean, prior.covariance, names)


def gaussian_rows(covered: Sequence[str], mean, covariance, names: Sequence[str]):
    """`jaxcal._pointfit.PointPrior`'s `root` and `mean` over the vector `names` of a Gaussian of
    `mean` and `covariance` over the parameters `covered` (each one of `names`)."""
    idx = np.array([list(names).index(n) for n in covered])
    w, V = np.linalg.eigh(np.asarray(covariance))
    root = np.zeros((len(idx), len(names)))
    root[:, idx] = (V / np.sqrt(w)).T  # root.T @ root = covariance^-1 on the prior's columns
    full = np.zeros(len(names))
    full[idx] = mean
    return root, full
