"""Monte Carlo entry point: one jit call over seeded trials (vmapped chunks)."""

import dataclasses
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np
import optimistix as optx
import pytest
from helpers import ur5e_setup

from jaxcal._arcfit import fit_arc
from jaxcal._linalg import concurrent_decompositions
from jaxcal._montecarlo import (
    CPU_CHUNK,
    NoiseModel,
    _free_mask_jit,
    _sharded_trials,
    draw_trial_truth,
    dynamic_setup,
    exact_arcs,
    map_in_chunks,
    monte_carlo,
    summarize,
    trial_mesh,
    trial_sweeps,
)
from jaxcal.cli import main

ROOT = Path(__file__).resolve().parents[1]
SETUP = ur5e_setup(frames=24)
TRIALS = 8  # one batch shape for every test here (and test_cli): one compilation


def test_noise_free_trials_are_exact():
    quiet = ur5e_setup(noise=NoiseModel(0.0, 0.0, 0.0), frames=24)
    res = monte_carlo(quiet, jax.random.key(0), TRIALS)
    assert np.all(np.asarray(res.success))
    assert float(np.max(res.ee_rms_mm)) < 1e-5
    assert float(np.max(res.axis_dir_deg)) < 1e-8
    assert float(np.max(res.cam_trans_mm)) < 1e-6
    assert float(np.max(np.abs(res.ratio_err_percent))) < 1e-8
    # The uncalibrated arm is millimetres off: the calibration is doing real work.
    assert float(np.min(res.ee_rms_mm_nominal)) > 1.0


def test_noisy_trials_improve_and_are_reproducible(capsys):
    res = monte_carlo(SETUP, jax.random.key(1), TRIALS, progress=True)  # says what it does on stderr
    assert capsys.readouterr().err.startswith(f"Monte Carlo: {TRIALS} trials in one compiled call")
    arc_ok = np.asarray(res.arc_result == optx.RESULTS.successful)
    assert arc_ok.shape == (TRIALS, 6) and arc_ok.all()
    s = summarize(res)
    assert s["success_rate"] == 1.0
    # 0.1 mm / 0.05 deg marker noise, 24 frames per 60 deg sweep, errors over
    # the whole workspace: about a millimetre after, many millimetres before.
    assert s["ee_rms_mm_median"] < 1.5
    assert s["ee_rms_mm_nominal_median"] > 5.0 * s["ee_rms_mm_median"]
    assert s["ratio_err_percent_max_median"] < 0.2
    again = monte_carlo(SETUP, jax.random.key(1), TRIALS)
    np.testing.assert_array_equal(np.asarray(res.ee_rms_mm), np.asarray(again.ee_rms_mm))


def test_error_grows_with_noise():
    """Same compiled trial, a noise level 4x larger: errors scale accordingly."""
    loud = ur5e_setup(noise=NoiseModel(0.4, 0.2, 0.0), frames=24)
    low = summarize(monte_carlo(SETUP, jax.random.key(2), TRIALS))
    high = summarize(monte_carlo(loud, jax.random.key(2), TRIALS))
    ratio = high["ee_rms_mm_median"] / low["ee_rms_mm_median"]
    assert 2.5 < ratio < 6.0


def test_failed_trials_are_flagged_not_raised():
    """Corrupt measurements (NaN noise) in every trial: the batch still returns,
    each trial flagged, instead of raising or reporting a bogus success."""
    broken = ur5e_setup(noise=NoiseModel(float("nan"), 0.05, 0.0), frames=24)
    res = monte_carlo(broken, jax.random.key(3), TRIALS)
    assert np.asarray(res.success).shape == (TRIALS,)
    assert not np.any(np.asarray(res.success))


def test_exact_arcs_equal_noise_free_arc_fits():
    """The reference fit's shortcut: `exact_arcs` gives what arc fits of
    noise-free sweeps measure (line coordinates and zero poses, in the fits'
    own references), so the gauge reference is the same fit, minus six LM solves."""

    def make(key):
        true, T_cam_base, T_flange_marker = draw_trial_truth(SETUP, key)
        quiet = trial_sweeps(SETUP, true, T_cam_base, T_flange_marker, key, NoiseModel(0.0, 0.0, 0.0))
        arcs = jax.vmap(lambda d: fit_arc(d, scale_covariance=False))(quiet)
        return arcs, exact_arcs(arcs, true, T_cam_base, T_flange_marker, SETUP.nominal.reduction_ratio)

    arcs, exact = jax.jit(make)(jax.random.key(4))
    np.testing.assert_allclose(exact.meas, arcs.meas, rtol=0, atol=1e-8)
    np.testing.assert_allclose(exact.direction, arcs.direction, rtol=0, atol=1e-9)
    np.testing.assert_allclose(exact.point, arcs.point, rtol=0, atol=1e-8)
    np.testing.assert_allclose(exact.rate, arcs.rate, rtol=0, atol=1e-9)
    np.testing.assert_allclose(exact.T_cam_marker0, arcs.T_cam_marker0, rtol=0, atol=1e-8)


def test_without_encoders_trials_register_the_right_way_round_and_score_in_their_gauge():
    """Without encoders an arc's direction sign is arbitrary: the line registration
    tries both for every joint (holding the first at + once turned 4 of these 8
    trials' arms half round: 180 deg axes, a camera 0.3 m off, scored a metre
    wrong and "successful"). Errors are taken against the same fit on noise-free
    sweeps (the last zero and the mount are gauge): exact without noise; ratios NaN."""
    blind = dataclasses.replace(SETUP, use_encoders=False)
    quiet = dataclasses.replace(blind, noise=NoiseModel(0.0, 0.0, 0.0))
    exact = monte_carlo(quiet, jax.random.key(0), TRIALS)
    assert np.all(np.asarray(exact.success))
    assert float(np.max(exact.ee_rms_mm)) < 1e-5 and float(np.max(exact.axis_dir_deg)) < 1e-8
    res = monte_carlo(blind, jax.random.key(0), TRIALS)
    assert np.all(np.asarray(res.success))
    assert float(np.max(res.axis_dir_deg)) < 0.5  # the mirror: 180
    assert float(np.max(res.cam_trans_mm)) < 5.0  # the mirror: 325
    assert float(np.max(res.ee_rms_mm)) < 15.0 and float(np.median(res.ee_rms_mm)) < 5.0  # 1.7-6.2 mm here
    assert float(np.median(res.ee_rms_mm_nominal)) > 2.0 * float(np.median(res.ee_rms_mm))
    assert np.all(np.isnan(np.asarray(res.ratio_err_percent)))


def _trial_program(setup, trials: int = TRIALS):
    """`monte_carlo(setup, key, trials)`'s own compiled program, as a function of
    the key: checking it reuses the trace the tests here already made."""
    mesh = trial_mesh(None)
    setup = dynamic_setup(setup)
    free = np.asarray(_free_mask_jit(setup))
    chunk = min(CPU_CHUNK, -(-trials // mesh.size))
    return lambda key: _sharded_trials(setup, key, free, trials=trials, chunk=chunk, mesh=mesh)


def test_batched_trials_keep_lapack_calls_ordered():
    """No two LAPACK calls of a vmapped trial can run side by side: on a
    two-core machine that deadlocks jaxlib's CPU thread pool (see jaxcal._linalg).
    With and without encoders (different arc and axis fit paths)."""
    for setup in (SETUP, dataclasses.replace(SETUP, use_encoders=False)):
        assert concurrent_decompositions(_trial_program(setup), jax.random.key(0)) == []


@pytest.mark.slow
def test_montecarlo_detail_and_json(tmp_path, capsys):
    """`jaxcal montecarlo`: the detailed trial's tables, then the summary written
    atomically. Here, not in test_cli.py: the command's trials are `SETUP`'s
    program, which this file's tests have traced and compiled already."""
    out = tmp_path / "mc.json"
    assert (
        main(
            [
                "montecarlo",
                "--config",
                "detail=true",
                "--trials",
                "8",
                "--frames-per-joint",
                "24",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    text = capsys.readouterr().out
    assert "Before / after" in text and "Identifiability" in text
    assert "shoulder_pan_joint.zero_offset" in text  # named as held at nominal
    summary = json.loads(out.read_text())
    assert summary["trials"] == 8 and summary["success_rate"] == 1.0
    assert summary["ee_rms_mm_median"] < 1.0
    assert [p.name for p in out.parent.iterdir()] == ["mc.json"]  # no temp files left


def test_chunks_give_the_same_results_as_one_batch():
    """`monte_carlo`'s chunking (equal chunks, padding dropped) is invisible in the results."""

    def f(k):
        x = jax.random.normal(k, (3,))
        return {"x": x, "n": jax.numpy.linalg.norm(x)}

    keys = jax.random.split(jax.random.key(5), 10)
    ref = jax.vmap(f)(keys)
    for chunk in (1, 3, 4, 9, 10, 64):
        got = jax.jit(lambda k, c=chunk: map_in_chunks(f, k, c))(keys)
        assert got["x"].shape == (10, 3)
        np.testing.assert_allclose(got["x"], ref["x"], rtol=1e-14)
        np.testing.assert_allclose(got["n"], ref["n"], rtol=1e-14)  # vector width may differ


def test_bad_trial_counts():
    with pytest.raises(ValueError, match="trials must be from 1"):
        monte_carlo(SETUP, jax.random.key(0), 0)
    with pytest.raises(ValueError, match="chunk must be at least 1"):
        monte_carlo(SETUP, jax.random.key(0), 4, chunk=0)


# Eight forced CPU devices, a mesh over four (or three): a pool of eight threads
# leaves jaxlib's LAPACK chunks threads to run on (see `default_devices`).
_SHARDED = """
import os, sys
os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=8 --xla_backend_optimization_level=0"
import jax
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_compilation_cache_dir", sys.argv[2])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
import numpy as np
import optimistix as optx
sys.path.insert(0, sys.argv[3])
from helpers import ur5e_setup
from jaxcal._montecarlo import default_devices, map_over_devices, monte_carlo, trial_mesh

assert jax.device_count() == 8 and len(default_devices()) >= 4
res = monte_carlo(ur5e_setup(frames=24), jax.random.key(1), 8, devices=jax.devices()[:4])
assert len(res.ee_rms_mm.sharding.device_set) == 4 and res.ee_rms_mm.sharding.is_fully_replicated
# Padding: 10 entries over 3 devices (12 rows), chunks of 3.
xs = jax.random.normal(jax.random.key(2), (10, 3))
mesh = trial_mesh(jax.devices()[:3])
ys = jax.jit(lambda x: map_over_devices(lambda v: {"s": v.sum(), "x": 2 * v}, x, mesh, 3))(xs)
np.savez(sys.argv[1], ys_s=np.asarray(ys["s"]), ys_x=np.asarray(ys["x"]), xs=np.asarray(xs),
         **{k: np.asarray(getattr(res, k)) for k in ("ee_rms_mm", "cam_trans_mm", "cam_rot_deg",
            "axis_dir_deg", "axis_pos_mm", "ratio_err_percent", "success")},
         arc_ok=np.asarray(res.arc_result == optx.RESULTS.successful),
         axis_ok=np.asarray(res.axis_result == optx.RESULTS.successful))
"""


def test_sharded_over_four_devices_equals_one_device(tmp_path):
    """The same trials on four (forced CPU) devices as on one, to round-off;
    uneven sharding pads and drops the padding."""
    out = tmp_path / "sharded.npz"
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    cache = jax.config.jax_compilation_cache_dir or str(tmp_path / "cache")
    proc = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(_SHARDED), str(out), cache, str(ROOT / "tests")],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = np.load(out)
    np.testing.assert_allclose(got["ys_s"], got["xs"].sum(-1), rtol=1e-14)
    np.testing.assert_array_equal(got["ys_x"], 2 * got["xs"])
    one = monte_carlo(SETUP, jax.random.key(1), TRIALS)  # test_noisy_trials_improve's program
    np.testing.assert_array_equal(got["success"], np.asarray(one.success))
    np.testing.assert_array_equal(got["arc_ok"], np.asarray(one.arc_result == optx.RESULTS.successful))
    np.testing.assert_array_equal(got["axis_ok"], np.asarray(one.axis_result == optx.RESULTS.successful))
    for name in (
        "ee_rms_mm",
        "cam_trans_mm",
        "cam_rot_deg",
        "axis_dir_deg",
        "axis_pos_mm",
        "ratio_err_percent",
    ):
        np.testing.assert_allclose(got[name], np.asarray(getattr(one, name)), rtol=0, atol=1e-12)
