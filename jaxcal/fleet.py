"""A fleet: many robots of one model calibrated in one run, and what their results say together.

`calibrate_fleet(datasets, out)` (`jaxcal calibrate DS1 DS2 ...`, or a folder of datasets)
calibrates every unit in one process (the compiled programs one unit loads serve the next), or
shares them out over the processes of a distributed run (`jaxcal.distributed`), writes each
unit's result as `jaxcal calibrate` would (`OUT/<unit>/`), then the fleet's summary (`fleet.json`,
`fleet.md`, `fleet.png`). A unit whose data are refused, or whose calibration fails, does not stop
the others: its reason is in the summary.

The summary, per parameter that every calibrated unit estimated:

- the fleet's median and its robust spread ($1.4826\\,\\mathrm{MAD}$), the mean and the sample
  standard deviation, the units' own uncertainty (the RMS of their standard deviations) and
  the population's spread with that uncertainty removed,
  $\\sqrt{\\max(s^2 - \\overline{\\sigma_i^2}, 0)}$: how much the robots differ, not how well
  each was measured;
- the units that stand out: $|x_i - \\mathrm{median}| / \\max(\\text{robust spread}, \\sigma_i,
  10^{-5})$ (`RESOLUTION`: 10 micrometres, 10 microradians) above `outlier_threshold` (set so
  that a fleet of ordinary units has one named with chance `FALSE_ALARM`), named with the
  parameter, the value and how far; and units whose residual stands out from the fleet's the
  same way (a unit measured badly, or not of this model).

Outliers are judged only with at least `MIN_UNITS` calibrated units: fewer cannot say what is usual.

**The fleet as prior.** A fleet of point-fit units (tracker, motion capture, the controller's
tool point) also writes `prior` into `fleet.json`: over the robot's own parameters (joint
origins, zero offsets, terms) that every usable unit (ok, not named) estimated, their mean and
the population's covariance, the units' own covariance removed (empirical Bayes, `fleet_prior`).
`jaxcal calibrate --prior fleet.json` (`read_prior`) then fits a new unit of the same model with
it as a Gaussian prior (`jaxcal._pointfit.PointPrior`): a short capture borrows what the fleet
knows. The frame the unit is measured in and its point's mount differ per unit: no prior on them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import shutil
import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ._processes import ONE, Processes
from ._records_base import Record, plain
from .errors import DatasetError, OutputError
from .fleet_prior import FLEET_SCHEMA_VERSION as FLEET_SCHEMA_VERSION
from .fleet_prior import MIN_UNITS as MIN_UNITS
from .fleet_prior import RESOLUTION as RESOLUTION
from .fleet_prior import FleetPrior as FleetPrior
from .fleet_prior import data_digest as data_digest
from .fleet_prior import fleet_prior as fleet_prior
from .fleet_prior import model_digest as model_digest
from .fleet_prior import prior_rows as prior_rows
from .fleet_prior import read_prior as read_prior
from .io._files import atomic_directory, write_text_atomic

#: The chance that a fleet of normal units, none out of the ordinary, has a unit named anyway
#: (per family: the parameters together, the residuals apart).
FALSE_ALARM = 0.01
#: Normal consistency of the median absolute deviation.
MAD_SIGMA = 1.4826


@dataclass(frozen=True, eq=False)
class FleetUnit(Record):
    """One unit of the fleet: where its data are, what became of it."""

    name: str
    dataset: str
    #: `ok`, `suspect` or `failed` (the calibration's status), or `refused` (its data).
    status: str
    #: The calibration's first reason, or why the data were refused ("" when ok).
    reason: str
    #: The fit's residual RMS (`residual_unit`), or None when not calibrated.
    residual: float | None
    residual_unit: str
    seconds: float
    #: The calibration's verdict notes (samples the robust fit rejected, parameters held, ...).
    notes: tuple[str, ...] = ()


@dataclass(frozen=True, eq=False)
class FleetParameter(Record):
    """One parameter across the calibrated units that estimated it (SI units: `unit`)."""

    name: str
    unit: str
    units: int
    nominal: float
    median: float
    robust_spread: float
    mean: float
    std: float
    #: The RMS of the units' own standard deviations.
    measurement_std: float
    #: The spread of the robots themselves: the sample variance less the measurement variance.
    population_std: float
    #: Each calibrated unit's estimate, in `FleetSummary.calibrated`'s order.
    values: tuple[float, ...] = ()


@dataclass(frozen=True, eq=False)
class FleetOutlier(Record):
    """A unit that stands out: its `parameter` (or `residual`) `z` robust spreads from the median."""

    unit: str
    parameter: str
    value: float
    median: float
    z: float


@dataclass(frozen=True, eq=False)
class FleetSummary(Record):
    units: tuple[FleetUnit, ...]
    parameters: tuple[FleetParameter, ...]
    outliers: tuple[FleetOutlier, ...]
    #: How far (robust spreads) a parameter lies from the median to be named (`outlier_threshold`;
    #: None: not judged).
    limit: float | None
    #: Why outliers were not judged (too few units), else "".
    note: str = ""
    timings_s: dict = field(default_factory=dict)
    #: The fleet's prior (`FleetPrior`; None: too few usable point-fit units).
    prior: "FleetPrior | None" = None

    @property
    def calibrated(self) -> tuple[FleetUnit, ...]:
        return tuple(u for u in self.units if u.residual is not None)

    @property
    def exit_code(self) -> int:
        """0 when every unit is ok and none stands out, else 3 (as a suspect calibration)."""
        return 0 if all(u.status == "ok" for u in self.units) and not self.outliers else 3


def _subfolders(p: Path) -> list[Path]:
    """`p`'s subfolders in name order, hidden ones (`.name`) left out."""
    return sorted(d for d in p.iterdir() if d.is_dir() and not d.name.startswith("."))


def fleet_datasets(paths: Sequence) -> list[Path]:
    """The datasets named: each path a dataset (its `metadata.json`) or a folder of datasets (every
    subfolder, in name order: one without `metadata.json` is a unit the reader refuses by name,
    not one left out unsaid). Raises `DatasetError` for a folder none of whose subfolders is a
    dataset, or for two units of one name (their results would share a folder)."""
    found = []
    for p in map(Path, paths):
        if (p / "metadata.json").is_file() or not p.is_dir():
            found.append(p)  # a dataset, or what the reader will refuse by name
            continue
        inside = _subfolders(p)
        if not any((d / "metadata.json").is_file() for d in inside):
            some = ", ".join(d.name for d in inside[:5]) + (" ..." if len(inside) > 5 else "")
            raise DatasetError(
                f"{p}: neither a dataset (no metadata.json) nor a folder of datasets (none of its "
                f"{len(inside)} subfolders{' (' + some + ')' if some else ''} holds a metadata.json)"
            )
        found += inside
    names = [d.name for d in found]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise DatasetError(
            f"units named alike {twice}: each unit's result is OUT/<its folder's name>; rename them"
        )
    return found


def is_fleet(paths: Sequence) -> bool:
    """Several datasets, or one folder of datasets (`fleet_datasets`): a folder with no
    `metadata.json` (nor a hand-eye capture's `handeye.json`, a tree dataset's `tree.json`) and subfolders."""
    if len(paths) > 1:
        return True
    p = Path(paths[0])
    if not p.is_dir() or any((p / f).exists() for f in ("metadata.json", "handeye.json", "tree.json")):
        return False
    return bool(_subfolders(p))


def copies(digests: Sequence[str | None]) -> dict[int, int]:
    """`{k: j}` for each dataset `k` whose data's digest (`data_digest`; None: not read) is an
    earlier dataset `j`'s."""
    first, out = {}, {}
    for k, digest in enumerate(digests):
        if digest is not None and digest in first:
            out[k] = first[digest]
        elif digest is not None:
            first[digest] = k
    return out


@functools.cache
def outlier_threshold(units: int, parameters: int, alpha: float = FALSE_ALARM) -> float:
    """How far (in robust spreads) from the median a value must lie to be named, so that a fleet of
    `units` normal units, compared over `parameters` parameters, has one named with chance `alpha`:
    the $1 - \\alpha$ quantile of the largest $|x_i - \\mathrm{median}| / (1.4826\\,\\mathrm{MAD})$,
    by simulation (fixed seed). The median and MAD of a few units are themselves uncertain, so
    the threshold is far above the normal one for small fleets (about 36 at 7 units and 30
    parameters, 8.5 at 20, 5.4 at 100)."""
    rng = np.random.default_rng(0)
    draws = int(min(2000, max(200, 2e7 // (units * parameters))))
    largest = []
    for start in range(0, draws, 100):
        x = rng.standard_normal((min(100, draws - start), parameters, units))
        med = np.median(x, axis=2, keepdims=True)
        spread = MAD_SIGMA * np.median(np.abs(x - med), axis=2, keepdims=True)
        largest.append(np.max(np.abs(x - med) / spread, axis=(1, 2)))
    return float(np.quantile(np.concatenate(largest), 1.0 - alpha))


def _unwrapped(x: np.ndarray) -> np.ndarray:
    """Angles (rad) within half a turn of their circular mean: a fleet whose values straddle +-pi
    (a plate mounted upside down: roll about 180 deg) is one cluster, not two a turn apart."""
    centre = float(np.angle(np.mean(np.exp(1j * x))))
    return centre + np.angle(np.exp(1j * (x - centre)))


def _robust(x: np.ndarray) -> tuple[float, float]:
    med = float(np.median(x))
    return med, MAD_SIGMA * float(np.median(np.abs(x - med)))


def summarize(units: Sequence[FleetUnit], parameters: dict[str, list]) -> FleetSummary:
    """The fleet's summary from its units and, per calibrated unit name, its `ParameterRow`s. Units
    whose residual stands out are named first; the parameters' statistics and outliers are then
    over the usable units (ok, their residual not named), as the prior's are: a unit measured
    badly (misaligned rows, another robot) would otherwise set the fleet's spread."""
    calibrated = [u.name for u in units if u.residual is not None]
    judge = len(calibrated) >= MIN_UNITS
    outliers = _residual_outliers(units) if judge else []
    named = {o.unit for o in outliers}
    usable = [u.name for u in units if u.residual is not None and u.status == "ok" and u.name not in named]
    counted = usable if len(usable) >= 2 else calibrated
    rows_by_name: dict[str, list] = {}
    for unit in calibrated:
        for r in parameters[unit]:
            if r.free:
                rows_by_name.setdefault(r.name, []).append((unit, r))
    stats = []
    common = [n for n, rows in rows_by_name.items() if {u for u, _ in rows} >= set(counted)]  # comparable
    limit = outlier_threshold(len(counted), max(len(common), 1)) if len(counted) >= MIN_UNITS else None
    for name in common:
        every = rows_by_name[name]  # the units left out are judged against the counted ones
        x_all = np.array([r.estimate for _, r in every])
        x_all = _unwrapped(x_all) if every[0][1].unit == "rad" else x_all
        mine = np.array([u in counted for u, _ in every])
        rows = [row for row, m in zip(every, mine, strict=True) if m]
        x, s = x_all[mine], np.array([r.std for _, r in rows])
        med, spread = _robust(x)
        std = float(np.std(x, ddof=1)) if len(x) > 1 else 0.0
        meas = float(np.sqrt(np.mean(s**2)))
        stats.append(
            FleetParameter(
                name=name,
                unit=rows[0][1].unit,
                units=len(rows),
                nominal=float(rows[0][1].nominal),
                median=med,
                robust_spread=spread,
                mean=float(np.mean(x)),
                std=std,
                measurement_std=meas,
                population_std=float(np.sqrt(max(std**2 - meas**2, 0.0))),
                values=tuple(float(v) for v in x),
            )
        )
        s_all = np.array([r.std for _, r in every])
        z = (x_all - med) / np.maximum(np.maximum(spread, s_all), RESOLUTION)
        outliers += [
            FleetOutlier(unit=u, parameter=name, value=float(v), median=med, z=float(zi))
            for (u, _), v, zi in zip(every, x_all, z, strict=True)
            if limit is not None and abs(zi) > limit and u not in named
        ]
    notes = [] if judge else [f"{len(calibrated)} calibrated units: outliers are judged from {MIN_UNITS} on"]
    left = [u for u in calibrated if u not in counted]
    if left:
        notes.append(
            f"the parameters' statistics are over the {len(counted)} usable units (ok, their residual not "
            f"named); left out: {', '.join(left)}"
        )
    outliers.sort(key=lambda o: -abs(o.z))
    return FleetSummary(
        units=tuple(units),
        parameters=tuple(stats),
        outliers=tuple(outliers),
        limit=limit,
        note="; ".join(notes),
    )


def _residual_outliers(units: Sequence[FleetUnit]) -> list[FleetOutlier]:
    """The units whose residual stands out from the fleet's (compared as ratios: residuals are
    positive and skewed)."""
    res = np.array([u.residual for u in units if u.residual is not None])
    med, spread = _robust(np.log(res))
    out = []
    for u in units:
        z = (np.log(u.residual) - med) / spread if u.residual is not None and spread > 0 else 0.0
        if z > outlier_threshold(len(res), 1):
            out.append(
                FleetOutlier(
                    unit=u.name, parameter="residual", value=u.residual, median=float(np.exp(med)), z=float(z)
                )
            )
    return out


def _unit_of(name: str, dataset: Path, result, seconds: float) -> FleetUnit:
    if result.point_fit is not None:
        residual, unit = float(result.point_fit.residual_mm.rms), "mm"
    elif result.refinement is not None:
        residual, unit = float(result.refinement.inlier_rms_px), "px"
    else:
        residual, unit = float("nan"), ""
    return FleetUnit(
        name=name,
        dataset=str(dataset),
        status=result.status,
        reason=result.reasons[0] if result.reasons else "",
        residual=residual,
        residual_unit=unit,
        seconds=seconds,
        notes=tuple(result.verdict.notes) if result.verdict is not None else (),
    )


def calibrate_fleet(
    datasets: Sequence,
    out,
    *,
    calibrate: Callable,
    write: Callable,
    overwrite: bool = False,
    checked=None,
    strict: bool = False,
    say: Callable[[str], None] = print,
    processes: Processes = ONE,
) -> FleetSummary:
    """Calibrate every dataset (`calibrate(path) -> CalibrationResult`) and write each result with
    `write(result, folder)` into `out/<unit>/`, then the fleet's summary, all atomically (`out`
    appears whole or not at all). `strict`: a unit that is not ok is not written (its reason is
    in the summary). `say`: one line per unit. `processes` (`jaxcal.distributed.join()`): this
    process's place in a distributed run; each process calibrates its share of the units
    (`Processes.share`), the first writes the summary, and every process returns it.
    **Returns:** the `FleetSummary`."""
    datasets = fleet_datasets(datasets)
    t0 = time.perf_counter()
    digests = [data_digest(d) if d.is_dir() else None for d in datasets]
    twice = copies(digests)
    with _shared_folder(
        out, processes, overwrite=overwrite, inputs=datasets, kind="result", what="--out", checked=checked
    ) as tmp:
        mine = []
        for k in processes.share(len(datasets)):
            processes.check()  # another process stopped: so does this one
            if k in twice:  # one unit's data twice would narrow the fleet's spread
                why = (
                    f"{datasets[k]}: the same data as unit {datasets[twice[k]].name} (its data files alike; metadata, "
                    "notes and line ends aside): one unit counted twice; remove the copy"
                )
                mine.append(_refused(k, datasets, why, 0.0, say))
                continue
            mine.append(_calibrate_unit(k, datasets, calibrate, write, tmp, strict=strict, say=say))
        done = sorted((d for share in processes.gather(mine) for d in share), key=lambda d: d[0])
        done = _one_model(done, tmp if processes.first else None, say)
        units = [d[1] for d in done]
        parameters = {d[1].name: d[2] for d in done if d[2] is not None}
        fits = {d[1].name: d[3] for d in done if d[3] is not None}
        robot = next((d[4] for d in reversed(done) if d[4] is not None), None)
        summary = summarize(units, parameters)
        named = {o.unit for o in summary.outliers}
        usable = {u: f for u, f in fits.items() if u not in named}
        data = [digests[d[0]] for d in done if d[1].name in usable]
        prior = None if robot is None else fleet_prior(usable, *robot, data=data)
        summary = dataclasses.replace(summary, prior=prior, timings_s={"total": time.perf_counter() - t0})
        if processes.first:
            write_text_atomic(tmp / "fleet.json", json.dumps(fleet_json(summary), indent=1))
            plotted = plot_fleet(summary, tmp / "fleet.png")
            (tmp / "fleet.md").write_text(fleet_markdown(summary, plotted))
    processes.meet("fleet written")
    return summary


def _refused(k: int, datasets: list[Path], why: str, seconds: float, say, status: str = "refused") -> tuple:
    """Unit `k` not calibrated, for `why` (`_calibrate_unit`'s tuple)."""
    path = datasets[k]
    say(f"unit {k + 1}/{len(datasets)} {path.name}: {status}: {why}")
    return k, FleetUnit(path.name, str(path), status, why, None, "", seconds), None, None, None, None


def _one_model(done: list, tmp: Path | None, say) -> list:
    """`done` (`_calibrate_unit`'s tuples) with each calibrated unit of a robot model other than
    most units' (its joints and `model_digest`; a tie goes to the first unit's) refused: its
    parameters are another robot's, and would widen the fleet's spread. Its folder is removed
    from `tmp` (None: not this process's to remove)."""
    models = [d[5] for d in done if d[5] is not None]
    if len(set(models)) < 2:
        return done
    fleet = max(dict.fromkeys(models), key=models.count)  # dict keeps the first unit's first
    out = []
    for d in done:
        if d[5] is None or d[5] == fleet:
            out.append(d)
            continue
        other = (
            f"its joints {list(d[5][0])}"
            if d[5][0] != fleet[0]
            else "the same joints, but its robot file's joint origins, axes or zero offsets differ"
        )
        why = (
            f"{d[1].dataset}: not this fleet's robot model: {other}, against the {models.count(fleet)} unit(s) of "
            f"the fleet's (joints {list(fleet[0])}); calibrate it apart"
        )
        if tmp is not None:
            shutil.rmtree(tmp / d[1].name, ignore_errors=True)
        say(f"{d[1].name}: refused: {why}")
        out.append(
            (
                d[0],
                dataclasses.replace(d[1], status="refused", reason=why, residual=None, residual_unit=""),
                None,
                None,
                None,
                None,
            )
        )
    return out


def _calibrate_unit(k: int, datasets: list[Path], calibrate, write, tmp: Path, *, strict: bool, say) -> tuple:
    """Unit `k` calibrated and written into `tmp/<unit>/`: `(k, FleetUnit, parameters or None,
    the point fit's (names, x, cov, free) or None, the robot's (joints, digest, fixed frame,
    frame free) or None, the robot model's (joints, digest) or None)`."""
    path = datasets[k]
    name, start, where = path.name, time.perf_counter(), f"unit {k + 1}/{len(datasets)} {path.name}"
    try:
        result = calibrate(path)
    except (ValueError, OSError) as e:  # jaxcal's errors name the file, field or frame
        status = "refused" if isinstance(e, (DatasetError, OSError)) else "failed"
        return _refused(k, datasets, str(e), time.perf_counter() - start, say, status)
    unit = _unit_of(name, path, result, time.perf_counter() - start)
    if not np.isfinite(unit.residual):
        unit = FleetUnit(name, str(path), result.status, unit.reason, None, "", unit.seconds)
    fit = robot = None
    if unit.status == "ok" and result.point_fit is not None:
        pf = result.point_fit
        fit = (pf.layout.names(), *(np.asarray(a) for a in (pf.fit.x, pf.fit.cov, pf.fit.free)))
        frame_free = bool(pf.candidates[pf.layout.base.index("cam")].any())
        robot = (
            pf.layout.base.joints,
            model_digest(pf.problem.nominal),
            pf.layout.base.fixed_frame,
            frame_free,
        )
    if not (strict and result.status != "ok"):
        write(result, tmp / name)
    residual = "" if unit.residual is None else f", residual {unit.residual:.4g} {unit.residual_unit} RMS"
    notes = f"; {len(unit.notes)} verdict note(s) in its result.json" if unit.notes else ""
    say(f"{where}: {result.status}{residual} ({unit.seconds:.1f} s){notes}")
    model = (tuple(result.nominal.joint_names), model_digest(result.nominal))
    return k, unit, (result.parameters if unit.residual is not None else None), fit, robot, model


@contextlib.contextmanager
def _shared_folder(out, processes: Processes, **check):
    """`atomic_directory(out, **check)` held by the first process, its temporary folder shared
    with the others (which raise the first's error where it refuses `out`, and all raise where one
    cannot see the folder: a folder local to one host)."""
    if processes.count == 1:
        with atomic_directory(out, **check) as tmp:
            yield tmp
        return
    with contextlib.ExitStack() as stack:
        tmp = error = None
        if processes.first:
            try:
                tmp = stack.enter_context(atomic_directory(out, **check))
            except (ValueError, OSError) as e:
                error = e
        shared = (None if tmp is None else str(tmp), None if error is None else str(error))
        folder, refused = processes.gather(shared)[0]
        if error is not None:
            raise error
        if refused is not None:
            raise OutputError(refused)
        seen = processes.gather((socket.gethostname(), Path(folder).is_dir()))
        if blind := [f"{i} (on {host})" for i, (host, sees) in enumerate(seen) if not sees]:
            raise OutputError(
                f"--out {out}: process {', '.join(blind)} of {processes.count} cannot see {folder}, which process "
                f"0 ({seen[0][0]}) made: the output must be on a file system every process shares"
            )
        try:
            yield Path(folder)
        except BaseException:
            if not processes.first:  # what it wrote after the first removed the folder goes too
                shutil.rmtree(folder, ignore_errors=True)
            raise


def without_timings(doc):
    """`doc` (a `fleet.json` or `result.json`, read) without its seconds: what two runs give alike."""
    if isinstance(doc, dict):
        return {k: without_timings(v) for k, v in doc.items() if k not in ("seconds", "timings_s")}
    if isinstance(doc, list):
        return [without_timings(v) for v in doc]
    return doc


def fleet_json(summary: FleetSummary) -> dict:
    return {"schema": "jaxcal.fleet", "schema_version": FLEET_SCHEMA_VERSION, **plain(summary)}


def _fmt(v: float, unit: str) -> str:
    scale, shown = {"m": (1e3, "mm"), "rad": (np.degrees(1.0), "deg")}.get(unit, (1.0, unit))
    return f"{v * scale:.4g} {shown}".strip()


def fleet_markdown(summary: FleetSummary, plotted: bool) -> str:
    s = summary
    counts = {k: sum(u.status == k for u in s.units) for k in ("ok", "suspect", "failed", "refused")}
    lines = [
        "# jaxcal fleet calibration",
        "",
        f"{len(s.units)} units: " + ", ".join(f"{v} {k}" for k, v in counts.items() if v) + ". Each unit's "
        "result is in its own folder, as `jaxcal calibrate` writes it.",
        "",
    ]
    if s.note:
        lines += [f"Note: {s.note}.", ""]
    lines += ["## Units that stand out", ""]
    if s.outliers:
        lines += [
            "| unit | parameter | value | fleet median | robust spreads off |",
            "| --- | --- | --- | --- | ---: |",
        ]
        units = {p.name: p.unit for p in s.parameters} | {"residual": ""}
        for o in s.outliers:
            u = units.get(o.parameter, "")
            lines.append(
                f"| {o.unit} | {o.parameter} | {_fmt(o.value, u)} | {_fmt(o.median, u)} | {o.z:+.1f} |"
            )
    else:
        lines.append("None." if s.limit is not None else "Not judged (too few units).")
    lines += [
        "",
        "## Units",
        "",
        "| unit | status | residual RMS | seconds | reason, or the verdict's notes |",
        "| --- | --- | --- | ---: | --- |",
    ]
    for u in s.units:
        res = "" if u.residual is None else f"{u.residual:.4g} {u.residual_unit}"
        why = u.reason or "; ".join(f"note: {n}" for n in u.notes)
        lines.append(f"| {u.name} | {u.status} | {res} | {u.seconds:.1f} | {why.replace('|', '/')} |")
    lines += [
        "",
        "## Parameters across the fleet",
        "",
        "Median, robust spread (1.4826 MAD), the units' own uncertainty (RMS of their standard "
        "deviations) and the spread of the robots themselves (the sample's, less that uncertainty).",
        "",
        "| parameter | nominal | median | robust spread | measurement std | population std |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for p in s.parameters:
        cells = (p.nominal, p.median, p.robust_spread, p.measurement_std, p.population_std)
        lines.append(f"| {p.name} | " + " | ".join(_fmt(v, p.unit) for v in cells) + " |")
    if s.prior is None:
        lines += [
            "",
            f"No prior for a new unit (fleet.json's `prior` is empty): it needs {MIN_UNITS} or more `ok` units "
            "calibrated from points (a tracker, motion capture, the controller's tool point) that do not stand out.",
        ]
    else:
        lines += [
            "",
            "## The fleet as prior",
            "",
            f"fleet.json's `prior`: {len(s.prior.names)} of the robot's parameters, their mean and the "
            f"population's covariance over {s.prior.units} units (ok, none named). A new unit of this model: "
            "`jaxcal calibrate NEW --prior fleet.json` (a short capture borrows what the fleet knows).",
        ]
    if plotted:
        lines += ["", "![each unit's parameters, in robust spreads from the fleet's median](fleet.png)", ""]
    return "\n".join(lines) + "\n"


def plot_fleet(summary: FleetSummary, path) -> bool:
    """Each parameter's units as dots, in robust spreads from the fleet's median (outliers red and
    named). **Returns:** whether a plot was written (none without parameters)."""
    params = [p for p in summary.parameters if p.robust_spread > 0]
    if not params:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    named = {(o.unit, o.parameter): o.z for o in summary.outliers}
    fig, ax = plt.subplots(figsize=(8, 0.28 * len(params) + 1.5))
    for i, p in enumerate(params):
        z = (np.asarray(p.values) - p.median) / p.robust_spread
        ax.scatter(z, np.full(len(z), i), color="0.45", s=8, alpha=0.6)
        for (u, q), zu in named.items():
            if q == p.name:
                ax.scatter([zu], [i], color="tab:red", s=18, zorder=3)
                ax.annotate(
                    u, (zu, i), xytext=(3, 3), textcoords="offset points", fontsize=7, color="tab:red"
                )
    if (lim := summary.limit) is not None:
        ax.axvspan(
            -lim, lim, color="tab:green", alpha=0.08, label=f"within {lim:.3g} robust spreads: not named"
        )
        ax.legend(loc="lower right", fontsize=7)
    ax.set_yticks(range(len(params)), [p.name for p in params], fontsize=7)
    ax.set_xlabel("robust spreads from the fleet's median (outliers named)")
    ax.set_title(f"{len(summary.calibrated)} calibrated units")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True
