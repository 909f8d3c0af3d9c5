"""The verdict's arm check (`jaxcal.stages._armcheck`) on analytic corners of `data/ur5e_sweeps`'
design (`jaxcal.sim.corners`, no rendering): a rigid arm passes at the false-alarm rate the limits
say, the statistics follow their laws, and a sagging arm is flagged, naming gravity sag and backlash."""

from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from jaxcal import stages
from jaxcal.io.dataset import load_dataset
from jaxcal.sim.arm import ArmModel
from jaxcal.sim.corners import analytic_detections, capture_truth
from jaxcal.stages._armcheck import f_quantile, f_survival, gravity_score
from jaxcal.vision import detect_frames

DESIGN = Path(__file__).resolve().parents[1] / "data" / "ur5e_sweeps"
#: The detector's noise on the design's images (px per axis, `benchmarks/realism.py`).
NOISE_PX = 0.054


@pytest.mark.parametrize("m, dof", [(1, 10), (2, 28), (3, 40), (6, 200)])
def test_the_f_law_without_scipy(m, dof):
    for x in (0.1, 1.0, 5.0, 40.0):
        assert f_survival(x, m, dof) == pytest.approx(stats.f.sf(x, m, dof), rel=1e-9, abs=1e-300)
    for alpha in (0.5, 0.01, 1e-3, 1e-6):
        assert f_quantile(alpha, m, dof) == pytest.approx(stats.f.isf(alpha, m, dof), rel=1e-9)


@pytest.fixture(scope="module")
def like():
    """The corners the detector finds in the design's images (the analytic corners are these:
    the calibration's programs then have the shapes `data/ur5e_sweeps`' calibrations compiled)."""
    ds = load_dataset(DESIGN)
    rows = np.flatnonzero(ds.frames.camera == "cam0")
    return detect_frames(
        [ds.image_path(int(r)) for r in rows], [ds.targets[0].spec], K=ds.cameras[0].K, progress=False
    )


def _runs(arm, seeds, like):
    """Per seed: the arm check's figures and the verdict of the design's sweeps, their corners
    where `arm` puts them plus independent noise, calibrated with the refinement."""
    ds = load_dataset(DESIGN)
    truth = capture_truth(ds, arm=arm)
    opt = stages.Options(progress=False)
    setup = stages.setup(DESIGN, opt)
    out = []
    for seed in seeds:
        dets = analytic_detections(
            truth, "cam0", like=like, noise_px=NOISE_PX, rng=np.random.default_rng(seed)
        )
        obs = stages.observe(setup, opt, {"cam0": dets})
        sync = stages.synchronise(setup, obs, opt)
        two = stages.two_stage(setup, obs, sync, opt)
        refined = stages.refine(setup, obs, sync, two, opt)
        verdict = stages.verdict(setup, obs, sync, two, refined, opt.limits)
        out.append((gravity_score(setup, sync, two, refined), verdict))
    return out


@pytest.mark.slow
def test_a_rigid_arm_is_not_flagged(like):
    """Ten seeds of a rigid arm: F against the arcs at the refinement's clock follows the F law
    and the two clocks' difference the normal law (each about half above its median, within
    binomial bounds: before the clock was accounted for, F's median was 11 against the law's
    0.7, and 20 of its former limit was exceeded by a quarter of the seeds), and the arm check
    flags at most what its false-alarm rate allows (0.01 per row: three or more of 20 rows has
    probability 0.001)."""
    runs = _runs(None, range(10), like)
    F = np.array([g.F for g, _ in runs])
    z = np.array([g.clock_z for g, _ in runs])
    m, dof = runs[0][0].m, runs[0][0].dof
    assert all(g.clock == "refined" for g, _ in runs)
    # binomial(10, 1/2): 1..9 above the median holds with probability 0.998
    assert 1 <= np.sum(F > stats.f.median(m, dof)) <= 9, F
    assert 1 <= np.sum(np.abs(z) > stats.norm.isf(0.25)) <= 9, z
    flagged = [c.check for _, v in runs for c in v.checks if c.check.startswith("arm_") and not c.passed]
    assert len(flagged) <= 2, flagged


@pytest.mark.slow
def test_a_sagging_arm_is_flagged(like):
    """Twice the `realistic` arm's compliance (a UR5's shoulder yields 1/32 rad per kN m; here
    1/16 at the base, shoulder and elbow): the joints yielding along their own sweeps put the
    arcs' clock tens of microseconds from the refinement's, beyond the limit in most seeds; the
    reason names gravity sag and backlash and what to change."""
    arm = ArmModel(name="sag", compliance=(1 / 16, 1 / 16, 1 / 16, 2 / 5))
    runs = _runs(arm, range(4), like)
    flagged = [v for _, v in runs if any(c.check == "arm_clock_z" and not c.passed for c in v.checks)]
    assert len(flagged) >= 3, [g.clock_z for g, _ in runs]
    reason = next(r for r in flagged[0].reasons if "clock" in r)
    assert "gravity sag" in reason and "backlash" in reason and "stop-and-shoot" in reason
    assert all(v.status == "suspect" for v in flagged)


def _late(like, tmp_path, seconds: float):
    """`(sync, truth offset)`: the design's analytic corners with every frame stamped `seconds`
    late, nothing in the metadata, synchronised."""
    import csv
    import shutil

    ds = load_dataset(DESIGN)
    truth = capture_truth(ds, arm=None)
    copy = tmp_path / f"late{seconds:g}"
    shutil.copytree(DESIGN, copy, ignore=shutil.ignore_patterns("images"))
    (copy / "images").symlink_to(DESIGN / "images")
    header, *rows = (copy / "frames.csv").read_text().splitlines()
    rows = [",".join([c, f, repr(float(t) + seconds), p]) for c, f, t, p in csv.reader(rows)]
    (copy / "frames.csv").write_text("\n".join([header, *rows]) + "\n")
    opt = stages.Options(progress=False)
    setup = stages.setup(copy, opt)
    dets = analytic_detections(truth, "cam0", like=like, noise_px=NOISE_PX, rng=np.random.default_rng(0))
    return stages.synchronise(setup, stages.observe(setup, opt, {"cam0": dets}), opt), seconds + ds.truth[
        "clock"
    ]["offset_s"]


def test_a_camera_clock_ten_seconds_off_is_found(like, tmp_path):
    """The design's frames stamped 10 s late (another time base, nothing in the metadata): at
    the zero start offset only a quarter of them fall inside the encoder log and the clock fit
    alone does not converge; the motion-matching search starts it, the fit lands on the truth,
    and a note says so."""
    sync, truth = _late(like, tmp_path, 10.0)
    assert abs(sync.clock.offset_s - truth) < 1e-4
    assert any("the clock fit started from" in n and "24 %" in n for n in sync.notes)


def test_a_clock_fit_whose_frames_change_sweeps_is_fitted_again(like, tmp_path, monkeypatch):
    """Frames stamped 0.3 s late: every frame lies inside the log at the zero start, but 60 of
    the 144 sit in another sweep's segment there. Fitted once more from the fitted offset, with
    the frames where it puts them, the clock lands closer to the truth than the single fit."""
    from jaxcal.stages import _synchronise

    sync, truth = _late(like, tmp_path, 0.3)
    monkeypatch.setattr(_synchronise, "REASSIGNED_REFIT", 1.0)  # never refit: the old behaviour
    once, _ = _late(like, tmp_path / "once", 0.3)
    assert abs(sync.clock.offset_s - truth) < 0.5 * abs(once.clock.offset_s - truth)
