"""A fleet: many units of one robot model calibrated in one run (`jaxcal.fleet`), and what the
fleet's summary says: the population's spread, and the units that stand out."""

import hashlib
import json

import numpy as np
import pytest

import jaxcal
from jaxcal.cli import main
from jaxcal.fleet import FleetUnit, fleet_datasets, outlier_threshold, summarize
from jaxcal.records import ParameterRow
from jaxcal.sim.tracker import TrackerSimConfig, simulate_tracker

# test_certify.py's tracker capture (its compiled programs serve both files).
KW = dict(robot="ur5e", noise_um=10.0, bad_fraction=0.0, home_deg=None, pose_range_deg=120.0, poses=48)


def _fleet(values: np.ndarray, stds: np.ndarray) -> tuple[list[FleetUnit], dict]:
    """Units `u0...` whose parameters `p0...` take `values[unit, parameter]` with `stds`."""
    units, params = [], {}
    for i, (row, sd) in enumerate(zip(values, stds, strict=True)):
        name = f"u{i}"
        units.append(FleetUnit(name, f"/data/{name}", "ok", "", 0.01 * (1 + 0.05 * np.sin(i)), "mm", 1.0))
        params[name] = tuple(
            ParameterRow(
                name=f"p{j}", unit="m", group="correction", nominal=0.0, estimate=v, std=s, free=True
            )
            for j, (v, s) in enumerate(zip(row, sd, strict=True))
        )
    return units, params


def test_ordinary_fleets_name_no_unit_at_the_stated_rate():
    """400 fleets of 20 ordinary units (10 parameters, normal): about 1 % name a unit
    (`FALSE_ALARM`); 4 expected, at most 12 allowed (binomial, p < 1e-3 beyond)."""
    rng = np.random.default_rng(1)
    named = 0
    for _ in range(400):
        units, params = _fleet(rng.normal(0.0, 1e-3, (20, 10)), np.full((20, 10), 1e-5))
        named += bool(summarize(units, params).outliers)
    assert named <= 12


def test_a_unit_off_the_fleet_is_named_alone():
    rng = np.random.default_rng(2)
    values = rng.normal(0.0, 1e-3, (30, 8))
    limit = outlier_threshold(30, 8)
    values[7, 3] += 2.0 * limit * 1e-3  # unit u7's parameter p3: twice the threshold off
    summary = summarize(*_fleet(values, np.full(values.shape, 1e-5)))
    assert [(o.unit, o.parameter) for o in summary.outliers] == [("u7", "p3")]
    assert summary.outliers[0].z > limit and summary.limit == pytest.approx(limit)


def test_round_off_is_not_a_difference_between_robots():
    """A parameter the capture barely moves scatters by nanometres across units (a spread of
    round-off, its MAD tinier still): no unit stands out by it."""
    rng = np.random.default_rng(4)
    values = np.c_[rng.normal(0.0, 1e-3, 20), rng.standard_t(1, 20) * 1e-10]
    assert not summarize(*_fleet(values, np.full(values.shape, 1e-11))).outliers


def test_the_population_spread_is_the_robots_not_their_measurement():
    """300 units whose parameter differs by 2 mm (the robots) and is measured to 1 mm: the
    population's spread 2 mm (within 10 %), the measurement's 1 mm."""
    rng = np.random.default_rng(3)
    truth = rng.normal(0.0, 2e-3, (300, 1))
    measured = truth + rng.normal(0.0, 1e-3, truth.shape)
    p = summarize(*_fleet(measured, np.full(truth.shape, 1e-3))).parameters[0]
    assert p.population_std == pytest.approx(2e-3, rel=0.1)
    assert p.measurement_std == pytest.approx(1e-3) and p.std == pytest.approx(np.sqrt(5) * 1e-3, rel=0.1)


def test_a_few_units_are_not_judged():
    units, params = _fleet(np.arange(12.0).reshape(4, 3), np.ones((4, 3)))
    s = summarize(units, params)
    assert s.limit is None and not s.outliers and "4 calibrated units" in s.note


def test_the_datasets_a_fleet_reads(tmp_path):
    for name in ("b", "a"):
        (tmp_path / "f" / name).mkdir(parents=True)
        (tmp_path / "f" / name / "metadata.json").write_text("{}")
    (tmp_path / "f" / "notes").mkdir()  # not a dataset: left out
    assert [d.name for d in fleet_datasets([tmp_path / "f"])] == ["a", "b"]
    (tmp_path / "g" / "a").mkdir(parents=True)
    (tmp_path / "g" / "a" / "metadata.json").write_text("{}")
    with pytest.raises(jaxcal.errors.DatasetError, match=r"units named alike \['a'\]"):
        fleet_datasets([tmp_path / "f", tmp_path / "g"])
    with pytest.raises(jaxcal.errors.DatasetError, match="neither a dataset"):
        fleet_datasets([tmp_path / "f" / "notes"])


def _digest(root) -> str:
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h.update(p.name.encode() + p.read_bytes())
    return h.hexdigest()


@pytest.mark.slow
def test_a_fleet_calibrates_each_unit_as_alone_and_names_the_odd_one(tmp_path):
    """12 simulated UR5e units (48 tracker poses each), one whose joint origins are 20x the
    others' spread off, and one whose robot file is missing: `jaxcal calibrate FOLDER` writes the
    11 results, each as a calibration of that unit alone writes it, names the refused unit and
    the odd one (which its own calibration calls suspect too), and nothing else (exit 3)."""
    fleet = tmp_path / "fleet"
    for seed in range(10):
        simulate_tracker(TrackerSimConfig(seed=40 + seed, **KW), fleet / f"unit{seed:02d}")
    simulate_tracker(TrackerSimConfig(seed=60, **(KW | {"origin_mm": 20.0})), fleet / "odd")
    (fleet / "broken").mkdir()
    (fleet / "broken" / "metadata.json").write_text((fleet / "unit00" / "metadata.json").read_text())
    before = _digest(fleet)
    out = tmp_path / "out"
    assert main(["calibrate", str(fleet), "--out", str(out), "--config", "cv-folds=0", "--quiet"]) == 3
    assert _digest(fleet) == before  # input files are never modified
    s = json.loads((out / "fleet.json").read_text())
    status = {u["name"]: u["status"] for u in s["units"]}
    assert status == {**{f"unit{k:02d}": "ok" for k in range(10)}, "odd": "suspect", "broken": "refused"}
    assert "mm from nominal" in next(u for u in s["units"] if u["name"] == "odd")["reason"]
    broken = next(u for u in s["units"] if u["name"] == "broken")
    assert "robot file missing" in broken["reason"] and "broken/metadata.json" in broken["reason"]
    assert {o["unit"] for o in s["outliers"]} == {"odd"}
    assert {"fleet.md", "fleet.png", "odd", "unit00"} <= {p.name for p in out.iterdir()}
    assert not (out / "broken").exists()
    assert "| odd |" in (out / "fleet.md").read_text()
    # A unit's result is its calibration alone: the same parameters to round-off.
    alone = jaxcal.calibrate(fleet / "unit03", cv_folds=0, progress=False)
    mine = json.loads((out / "unit03" / "result.json").read_text())
    np.testing.assert_allclose(
        [p["estimate"] for p in mine["parameters"]],
        [p.estimate for p in alone.parameters],
        rtol=1e-9,
        atol=1e-12,
    )
    assert mine["run"]["command"].startswith(f"jaxcal calibrate {fleet} --out {out}")
    p = {q["name"]: q for q in s["parameters"]}["elbow_joint.origin.x"]
    assert len(p["values"]) == 11 and p["units"] == 11
