"""A fleet: many units of one robot model calibrated in one run (`jaxcal.fleet`), and what the
fleet's summary says: the population's spread, and the units that stand out."""

import hashlib
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

import jaxcal
from jaxcal._distributions import chi2_ppf
from jaxcal._records_base import plain
from jaxcal.cli import main
from jaxcal.errors import CalibrationError, DatasetError
from jaxcal.fleet import (
    FleetUnit,
    fleet_datasets,
    fleet_prior,
    is_fleet,
    outlier_threshold,
    prior_rows,
    read_prior,
    summarize,
)
from jaxcal.io.dataset import load_dataset
from jaxcal.records import ParameterRow
from jaxcal.sim.tracker import TrackerSimConfig, simulate_tracker
from jaxcal.verification import verify

# test_certify.py's tracker capture (its compiled programs serve both files).
ROOT = Path(__file__).resolve().parents[1]
KW = dict(robot="ur5e", noise_um=10.0, bad_fraction=0.0, home_deg=None, pose_range_deg=120.0, poses=48)


def _fleet(values: np.ndarray, stds: np.ndarray, unit: str = "m") -> tuple[list[FleetUnit], dict]:
    """Units `u0...` whose parameters `p0...` (in `unit`) take `values[unit, parameter]` with `stds`."""
    units, params = [], {}
    for i, (row, sd) in enumerate(zip(values, stds, strict=True)):
        name = f"u{i}"
        units.append(FleetUnit(name, f"/data/{name}", "ok", "", 0.01 * (1 + 0.05 * np.sin(i)), "mm", 1.0))
        params[name] = tuple(
            ParameterRow(
                name=f"p{j}", unit=unit, group="correction", nominal=0.0, estimate=v, std=s, free=True
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


def test_angles_that_straddle_half_a_turn_are_one_cluster():
    """A plate mounted upside down: its roll about +-180 deg, one unit's just past +180 (found by a
    new user as "+795 robust spreads" and a population spread of 160 deg). Angles are compared
    within half a turn of their circular mean: no unit stands out, the spread is the units' own;
    a unit 10 deg off is still named."""
    rng = np.random.default_rng(6)
    roll = np.pi - 0.01 + rng.normal(0.0, 0.005, (12, 1))
    roll[4] = -np.pi + 0.005  # 179.4 deg against the others' -179.x: 1 deg apart, not 359
    summary = summarize(*_fleet(np.angle(np.exp(1j * roll)), np.full(roll.shape, 1e-4), unit="rad"))
    (p,) = summary.parameters
    assert not summary.outliers and np.degrees(p.std) < 1.0, (summary.outliers, np.degrees(p.std))
    roll[4] = np.pi - 0.01 + np.radians(10.0)
    summary = summarize(*_fleet(np.angle(np.exp(1j * roll)), np.full(roll.shape, 1e-4), unit="rad"))
    assert [o.unit for o in summary.outliers] == ["u4"]


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


def test_the_datasets_a_fleet_reads(tmp_path, capsys):
    for name in ("b", "a"):
        (tmp_path / "f" / name).mkdir(parents=True)
        (tmp_path / "f" / name / "metadata.json").write_text("{}")
    (tmp_path / "f" / "notes").mkdir()  # not a dataset: a unit the reader refuses by name, not left out
    (tmp_path / "f" / ".cache").mkdir()  # hidden: no unit
    assert [d.name for d in fleet_datasets([tmp_path / "f"])] == ["a", "b", "notes"]
    (tmp_path / "g" / "a").mkdir(parents=True)
    (tmp_path / "g" / "a" / "metadata.json").write_text("{}")
    with pytest.raises(jaxcal.errors.DatasetError, match=r"units named alike \['a'\]"):
        fleet_datasets([tmp_path / "f", tmp_path / "g"])
    with pytest.raises(jaxcal.errors.DatasetError, match="neither a dataset"):
        fleet_datasets([tmp_path / "f" / "notes"])
    assert main(["inspect", str(tmp_path / "f")]) == 2  # a fleet is inspected unit by unit
    assert f"{tmp_path / 'f'}: a folder of datasets" in capsys.readouterr().err


def _digest(root) -> str:
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h.update(p.name.encode() + p.read_bytes())
    return h.hexdigest()


def _prior_fits(units: int, cov: np.ndarray, meas: float, seed: int = 0) -> dict:
    """Point fits of `units` units whose robot parameters `j.origin.tx...` are drawn from a population
    of covariance `cov`, each measured with standard deviation `meas`; a device frame beside them."""
    rng = np.random.default_rng(seed)
    k = len(cov)
    names = ["T_device_base.tx", *(f"j{i}.origin.tx" for i in range(k)), "marker.mount.tx"]
    fits = {}
    for u in range(units):
        x = np.concatenate([[rng.normal()], rng.multivariate_normal(np.zeros(k), cov), [rng.normal()]])
        x[1:-1] += meas * rng.standard_normal(k)
        fits[f"u{u}"] = (names, x, meas**2 * np.eye(k + 2), np.ones(k + 2, bool))
    return fits


def test_the_fleet_prior_is_the_population_not_the_measurement():
    """`fleet_prior` (empirical Bayes): 400 units of a correlated population measured with a third of
    its spread give its covariance back, the measurement removed, within the sampling error;
    the frame each unit is measured in and its point's mount carry no prior."""
    A = np.array([[1.0, 0.6, 0.0], [0.6, 1.0, -0.3], [0.0, -0.3, 1.0]]) * 1e-6  # (1 mm)^2, correlated
    prior = fleet_prior(_prior_fits(400, A, 3.3e-4), ("j0", "j1", "j2"), "abc", "T_device_base")
    assert prior.names == ("j0.origin.tx", "j1.origin.tx", "j2.origin.tx") and prior.units == 400
    # Sampling error of a variance over 400 units: sqrt(2/400) = 7 %; the shrinkage 3/400 of the correlations.
    np.testing.assert_allclose(np.diag(prior.covariance), np.diag(A), rtol=0.25)
    np.testing.assert_allclose(prior.covariance, A, atol=0.25e-6)
    assert np.all(np.abs(prior.mean) < 4 * 1e-3 / np.sqrt(400))


def test_a_small_fleet_claims_no_direction_it_has_not_seen():
    """Six units of eighteen parameters span five directions: the prior keeps each parameter's
    variance but not their correlations (shrunk by parameters over units), and no variance under
    the units' own measurement's, so that no combination is claimed known to a micrometre."""
    A = 1e-6 * np.eye(18)
    fits = _prior_fits(6, A, 2e-4, seed=1)
    for k, (_, x, _, _) in enumerate(fits.values()):  # robots alike in one parameter: measurement alone
        x[1] = 2e-4 * np.random.default_rng(k).standard_normal()
    prior = fleet_prior(fits, tuple(f"j{i}" for i in range(18)), "abc", "T_device_base")
    np.testing.assert_allclose(prior.covariance, np.diag(np.diag(prior.covariance)), atol=0)
    assert np.min(np.diag(prior.covariance)) >= (1 - 1e-9) * (2e-4) ** 2
    assert np.linalg.eigvalsh(prior.covariance).min() >= (1 - 1e-9) * (2e-4) ** 2
    assert (
        fleet_prior(dict(list(fits.items())[:4]), ("j0",), "abc", "T_device_base") is None
    )  # under MIN_UNITS


def test_a_prior_is_refused_by_name_for_another_robot_or_file(tmp_path):
    prior = fleet_prior(_prior_fits(8, 1e-6 * np.eye(2), 1e-5), ("j0", "j1"), "abc", "T_device_base")
    doc = {"schema": "jaxcal.fleet", "schema_version": 1, "prior": plain(prior)}
    (tmp_path / "fleet.json").write_text(json.dumps(doc))
    got = read_prior(tmp_path)  # the folder or the file
    assert got.file == str(tmp_path / "fleet.json") and got.names == prior.names
    names = ["T_device_base.tx", "j1.origin.tx", "j0.origin.tx", "j0.zero_offset"]
    root, mean = prior_rows(got, names, ("j0", "j1"), "abc", True)
    P = root.T @ root
    np.testing.assert_allclose(P[np.ix_([2, 1], [2, 1])], np.linalg.inv(prior.covariance), rtol=1e-9)
    assert not P[0].any() and not P[3].any() and mean[[2, 1]].tolist() == prior.mean.tolist()
    with pytest.raises(
        DatasetError, match=r"fleet\.json: this prior was learnt on another robot model: the same"
    ):
        prior_rows(got, names, ("j0", "j1"), "other", True)
    with pytest.raises(
        DatasetError, match=r"another robot \(the fleet's joints \['j0', 'j1'\], this dataset's"
    ):
        prior_rows(got, names, ("a", "b"), "abc", True)
    with pytest.raises(DatasetError, match=r"calibrated without --device-is-base and this unit is not"):
        prior_rows(got, names, ("j0", "j1"), "abc", False)
    edits = {
        "prior.names": ({"names": [prior.names[0]] * 2}, "names repeated"),
        "prior.units": ({"units": 3}, "3 units, a prior is learnt on 5 or more"),
        "prior.covariance": ({"covariance": [[1e-6, 1e-7], [0.0, 1e-6]]}, "not symmetric"),
    }
    for field, (change, why) in edits.items():
        doc["prior"] = plain(prior) | change
        (tmp_path / "fleet.json").write_text(json.dumps(doc))
        with pytest.raises(DatasetError, match=rf"field '{field}' is not one jaxcal wrote \({why}"):
            read_prior(tmp_path)
    (tmp_path / "fleet.json").write_text(json.dumps(doc | {"schema_version": 99}))
    with pytest.raises(DatasetError, match="schema_version 99, this jaxcal reads 1"):
        read_prior(tmp_path)
    doc["prior"] = None
    (tmp_path / "fleet.json").write_text(json.dumps(doc))
    with pytest.raises(DatasetError, match=r"fleet\.json: 'prior' is empty"):
        read_prior(tmp_path / "fleet.json")
    (tmp_path / "fleet.json").write_text(json.dumps({k: v for k, v in doc.items() if k != "prior"}))
    with pytest.raises(DatasetError, match=r"fleet\.json: no field 'prior' \(not a fleet\.json as jaxcal"):
        read_prior(tmp_path / "fleet.json")
    doc["prior"] = plain(prior) | {"covariance": [[1.0, 2.0], [2.0, 1.0]]}
    (tmp_path / "fleet.json").write_text(json.dumps(doc))
    with pytest.raises(
        DatasetError, match=r"field 'prior.covariance' is not one jaxcal wrote \(not positive"
    ):
        read_prior(tmp_path / "fleet.json")
    with pytest.raises(DatasetError, match=r"none\.json: fleet summary \(--prior takes the fleet\.json"):
        read_prior(tmp_path / "none.json")
    (tmp_path / "x.json").write_text(json.dumps({"schema": "jaxcal.result"}))
    with pytest.raises(DatasetError, match=r"x\.json: not a fleet\.json"):
        read_prior(tmp_path / "x.json")


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
    # The fleet's spread is its usable units' (the suspect one is named and not the population).
    assert len(p["values"]) == 10 and p["units"] == 10
    assert "left out: odd" in s["note"]
    # The fleet as prior (issue 52 item 2): the 10 ok units' (the suspect one is not the population).
    prior = s["prior"]
    assert prior["units"] == 10 and prior["joints"] == list(alone.nominal.joint_names)
    assert prior["names"] and not any(n.startswith(("T_device_base", "marker.mount")) for n in prior["names"])
    new = simulate_tracker(TrackerSimConfig(seed=80, **KW), tmp_path / "new")
    with_prior = tmp_path / "with_prior"
    assert (
        main(["calibrate", str(new), "--out", str(with_prior), "--prior", str(out / "fleet.json"), "--quiet"])
        == 0
    )
    used = json.loads((with_prior / "result.json").read_text())
    share = np.array(used["point_fit"]["prior"]["share"])
    assert used["point_fit"]["prior"]["names"] == prior["names"] and len(share) == len(prior["names"])
    assert np.all((share > -1e-9) & (share < 1 + 1e-9))
    # 48 poses at 10 um see the robot far better than a population 1 mm wide: the data's answer, mostly.
    assert share.mean() < 0.5
    plain_fit = jaxcal.calibrate(new, progress=False)
    assert used["validation"]["ee_rms_mm_after"] < 1.05 * plain_fit.validation.ee_rms_mm_after
    # The data's gauge is kept: the prior frees only parameters it covers (a parameter collinear
    # with a covered one, held by the fleet, stays held).
    pf = used["point_fit"]
    freed = {n for n, f in zip(pf["names"], pf["free"]) if f}
    alone_free = {n for n, f in zip(plain_fit.point_fit.layout.names(), plain_fit.point_fit.fit.free) if f}
    assert freed - alone_free <= set(prior["names"]) and alone_free <= freed
    assert used["status"] == "ok"
    # A prior the data contradict (one mean moved by 50 of its standard deviations) is a reason.
    moved = json.loads((out / "fleet.json").read_text())
    moved["prior"]["mean"][0] += 50 * np.sqrt(moved["prior"]["covariance"][0][0])
    (tmp_path / "moved.json").write_text(json.dumps(moved))
    wrong = jaxcal.calibrate(new, prior=tmp_path / "moved.json", progress=False)
    assert wrong.status == "suspect"
    said = next(r for r in wrong.reasons if r.startswith("the data contradict the fleet's prior"))
    assert (
        f"({tmp_path / 'moved.json'}): over the " in said and f"farthest {prior['names'][0]} at " in said
    ), said
    # ... read from the data alone: the prior's 50 standard deviations less what the unit's own add.
    z = float(re.search(r"farthest \S+ at ([\d.]+) standard deviations", said).group(1))
    assert 20 < z < 50, said
    # ... and so is a prior that claims too much (the fleet's covariance shrunk 10^8 times: 0.1 um).
    tight = json.loads((out / "fleet.json").read_text())
    tight["prior"]["covariance"] = (1e-8 * np.asarray(tight["prior"]["covariance"])).tolist()
    (tmp_path / "tight.json").write_text(json.dumps(tight))
    pinned = jaxcal.calibrate(new, prior=tmp_path / "tight.json", progress=False)
    assert pinned.status == "suspect" and any(
        "the data contradict the fleet's prior" in r for r in pinned.reasons
    )
    assert main(["calibrate", str(fleet), "--out", str(tmp_path / "o2"), "--prior", str(out), "--quiet"]) == 2
    assert "A fleet's prior" in (with_prior / "report.md").read_text()
    # `verify --cv` refits the folds as the calibration did, with the prior its result.json carries.
    v = tmp_path / "v.json"
    assert main(["verify", str(with_prior), str(new), "--cv", "5", "--json", str(v)]) == 0
    kept = next(m for m in used["point_fit"]["models"] if m["kept"])
    assert json.loads(v.read_text())["cv"]["mean"] == pytest.approx(kept["cv_mean_mm"], rel=1e-9)
    # Sweeps are the arc fits', not a point fit's: refused before any work.
    sweeps = simulate_tracker(
        TrackerSimConfig(robot="ur5e", seed=1, samples_per_joint=12, bad_fraction=0.0), tmp_path / "sweeps"
    )
    with pytest.raises(
        CalibrationError, match="applies to stop-and-shoot poses; these samples are joint sweeps"
    ):
        jaxcal.calibrate(sweeps, prior=out / "fleet.json", progress=False)


def _split(source: Path, rows: list[str], folder: Path) -> Path:
    """A dataset of `source`'s metadata and robot file with the samples `rows` (header first)."""
    folder.mkdir(parents=True)
    for name in ("metadata.json", "robot_dh.json"):
        shutil.copyfile(source / name, folder / name)
    (folder / "samples.csv").write_text("\n".join(rows) + "\n")
    return folder


@pytest.mark.slow
def test_a_real_robots_prior_lends_to_its_short_captures_without_false_alarms(tmp_path):
    """The real UR5's grid as a fleet of 6 units (its rows dealt out; one robot, so they agree to
    their measurement, and the fleet's spread is its floor) and 3 new 30-pose captures of rows the
    fleet never saw: each new capture is `ok` with the prior (the data alone within the fleet's
    spread plus their own: a real arm's model error in a short capture must not read as a unit
    unlike the fleet), and no worse on the held-out test set than without it."""
    grid = ROOT / "data" / "ur5_tracker" / "grid"
    header, *body = (grid / "samples.csv").read_text().splitlines()
    held, rest = body[::10], [r for i, r in enumerate(body) if i % 10]
    for k in range(6):
        _split(grid, [header, *rest[k::6]], tmp_path / "units" / f"ur5_{k}")
    out = tmp_path / "fleet"
    assert main(["calibrate", str(tmp_path / "units"), "--device-is-base", "--out", str(out), "--quiet"]) == 0
    test = load_dataset(ROOT / "data" / "ur5_tracker" / "test")
    for k in range(3):
        new = _split(grid, [header, *held[k::3][:30]], tmp_path / f"new{k}")
        args = ["calibrate", str(new), "--device-is-base", "--quiet", "--out"]
        assert main([*args, str(tmp_path / f"prior{k}"), "--prior", str(out / "fleet.json")]) == 0
        assert main([*args, str(tmp_path / f"alone{k}")]) == 0
        use = json.loads((tmp_path / f"prior{k}" / "result.json").read_text())["point_fit"]["prior"]
        assert use["dof"] >= 15 and use["chi2"] < chi2_ppf(0.99, use["dof"]), use
        errs = [float(np.mean(verify(tmp_path / f"{w}{k}", test).errors_mm)) for w in ("prior", "alone")]
        assert errs[0] < 1.02 * errs[1], errs


def _copied(unit: Path, to: Path) -> None:
    """A copy of `unit` as a user's might differ: Windows' line ends, a note beside the data, the
    simulator's answer key left behind."""
    shutil.copytree(unit, to)
    for csv in to.glob("*.csv"):
        csv.write_bytes(csv.read_bytes().replace(b"\n", b"\r\n"))
    (to / "README.txt").write_text("unit copied from the line's test bench\n")
    (to / "truth.json").unlink(missing_ok=True)


@pytest.mark.slow
def test_a_fleet_refuses_by_name_what_is_not_one_of_its_units(tmp_path):
    """In a folder of five UR5e units: a UR3 (the same joints, another robot file), a copy of a
    unit under another name (its line ends Windows', a note added, the simulator's truth
    dropped), a subfolder without metadata.json and an empty one. Each is refused in the summary with its reason (not left out unsaid, nor counted in the fleet's
    spread), the UR3's folder is not written, the others' results are; and the fleet's prior
    refuses one of its own units calibrated alone (its data would count twice)."""
    fleet = tmp_path / "fleet"
    for seed in range(5):
        simulate_tracker(TrackerSimConfig(seed=90 + seed, **KW), fleet / f"unit{seed}")
    simulate_tracker(TrackerSimConfig(seed=95, **(KW | {"robot": "ur3"})), fleet / "ur3")
    _copied(fleet / "unit2", fleet / "unit2 copy")
    (fleet / "empty").mkdir()
    (fleet / "no_metadata").mkdir()
    shutil.copyfile(fleet / "unit0" / "samples.csv", fleet / "no_metadata" / "samples.csv")
    (fleet / ".hidden").mkdir()  # hidden folders are no units
    before = _digest(fleet)
    out = tmp_path / "out"
    assert main(["calibrate", str(fleet), "--out", str(out), "--config", "cv-folds=0", "--quiet"]) == 3
    assert _digest(fleet) == before
    s = json.loads((out / "fleet.json").read_text())
    units = {u["name"]: u for u in s["units"]}
    assert set(units) == {f"unit{k}" for k in range(5)} | {"ur3", "unit2 copy", "empty", "no_metadata"}
    assert {n for n, u in units.items() if u["status"] == "ok"} == {f"unit{k}" for k in range(5)}
    why = {n: u["reason"] for n, u in units.items() if u["status"] == "refused"}
    assert set(why) == {"ur3", "unit2 copy", "empty", "no_metadata"}
    assert "not this fleet's robot model: the same joints, but its robot file's" in why["ur3"]
    assert "against the 5 unit(s) of the fleet's" in why["ur3"]
    assert "the same data as unit unit2 (" in why["unit2 copy"]
    assert "metadata.json" in why["empty"] and "metadata.json" in why["no_metadata"]
    assert not (out / "ur3").exists() and not (out / "unit2 copy").exists() and (out / "unit4").is_dir()
    assert all(len(p["values"]) == 5 for p in s["parameters"])  # the fleet's spread: its five units
    assert s["prior"]["units"] == 5 and len(s["prior"]["data"]) == 5
    with pytest.raises(
        DatasetError, match=r"unit3: this dataset is one of the units the prior .* count twice"
    ):
        jaxcal.calibrate(fleet / "unit3", prior=out / "fleet.json", progress=False)
    _copied(fleet / "unit3", tmp_path / "unit3 again")
    with pytest.raises(DatasetError, match=r"unit3 again: this dataset is one of the units the prior"):
        jaxcal.calibrate(tmp_path / "unit3 again", prior=out / "fleet.json", progress=False)

    # A folder none of whose subfolders is a dataset is named as such, not read as one dataset.
    (tmp_path / "none" / "a").mkdir(parents=True)
    with pytest.raises(
        DatasetError, match=r"none: neither a dataset .* \(none of its 1 subfolders \(a\) holds"
    ):
        fleet_datasets([tmp_path / "none"])
    assert is_fleet([tmp_path / "none"]) and not is_fleet([fleet / "unit0"])
