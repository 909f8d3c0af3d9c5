"""Every script in benchmarks/ runs at its smallest size and writes the JSON keys it promises.

A smoke test, not a measurement: each benchmark runs in a subprocess (as a user
runs it), with the suite's compilation cache, so a refactor that breaks a
benchmark's imports or calls fails here rather than in a user's hands. The
figures themselves are in docs/performance.md. Not run here, minutes even at their
smallest: `real_tracker.py` (three calibrations of the real UR5; its pipeline is
`tests/test_pointfit.py`'s), `startup.py` (fresh processes, cold caches),
`certify.py`, `drift.py` (many rendered or simulated calibrations; their pieces are in
`tests/test_certify.py`, `test_check_camera.py`), `certify_errors.py` (it reads `certify.py`'s
renders), `noise_weights.py` (it reads `realism.py`'s renders; its pieces are in
`tests/test_noise_weights.py`) and `plan.py`, which plans four designs and renders and calibrates a
dozen captures: of `certify_errors.py`, `noise_weights.py` and `plan.py` only the imports and
options are checked. The smoke runs over ~20 s each are marked
`bench`: `make test-bench` runs them, `make test` (and CI) leaves them out to keep the suite near
ten minutes.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import CACHE_DIR

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"

#: name -> (smallest arguments, keys the JSON promises). `{out}` is the JSON path.
CASES = {
    "arcfit": (
        ["--problems", "4", "--scipy-problems", "2", "--repeats", "1", "--frames", "10"],
        [
            "n_problems",
            "frames",
            "jaxcal_s",
            "compile_s",
            "scipy_s",
            "speedup",
            "scipy_jac_s",
            "max_abs_diff",
        ],
    ),
    "long_sweep": (["--smoke"], ["rows", "device", "versions", "notes"]),
    "codebase_counts": (
        ["--brief"],
        [
            "record_fields",
            "bag_fields",
            "string_key_reads",
            "mode_tests",
            "long_functions",
            "covariance_sites",
        ],
    ),
    "render": (
        ["--frames", "2", "--resolutions", "160x120"],
        ["frames", "backend", "resolutions"],
    ),
    "vision": (
        ["--dataset", "data/ur5e_sweeps", "--frames", "3", "--repeat", "1"],
        ["frames", "poses", "overhead_pct", "pool_speedup", "median_s"],
    ),
    "handeye": (
        ["--quick", "--parts", "protocol,real,speed", "--no-dense"],
        ["methods", "cramer_rao", "noisy_robot_pixels_ms", "pixels_ms_50", "speed", "real"],
    ),
    "efficiency": (
        ["--trials", "2", "--frames", "5"],
        ["trials", "max_ratio_to_crlb", "median_ratio_to_crlb", "per_parameter", "compile_s", "run_s"],
    ),
    "montecarlo": (
        ["--trials", "4", "--scipy-trials", "1", "--repeats", "1", "--frames", "10", "--device-counts", ""],
        ["trials", "jaxcal_s", "compile_s", "scipy_s", "speedup", "success_rate", "ee_rms_mm_median"],
    ),
    "ee_uncertainty": (["data/ur5e_sweeps"], ["dataset", "ee_rms_mm_measured", "free_parameters"]),
    "prediction_check": (
        ["data/ur5e_sweeps", "--flips", "3"],
        ["machine", "flips", "datasets", "seed_correlation"],
    ),
    "corrupted": (
        ["--seeds", "0", "--resolution", "640x480", "--frames-per-joint", "12"],
        ["fraction", "seeds", "max_ratio_two_stage", "max_ratio_refined"],
    ),
    # Its analytic comparison (one seed, two cases) and issue 48's rendered cases at 320x240, 6
    # frames per sweep (calibrated or refused; their pieces: `tests/test_camera_model.py`,
    # `tests/test_arm_model.py`, `tests/test_covariance.py`).
    "realism": (
        [
            "--analytic-seeds",
            "1",
            "--analytic-cases",
            "ideal",
            "rolling_shutter_given",
            "--cases",
            "physics_arm",
            "lens_remap_1x",
            "rolling_shutter_coarse",
            "exposure_10ms_fast",
            "--resolution",
            "320x240",
            "--frames-per-joint",
            "6",
        ],
        ["analytic", "analytic_noise_px", "cases"],
    ),  # fmt: skip
    # No sweep designs, one image, one noise draw, a 6-pose plan, one seed.
    "plan_realism": (
        ["--no-sweeps", "--seeds", "1", "--noise-step", "72", "--noise-draws", "1", "--poses", "6"],
        ["machine", "corner_noise", "predictions", "checks"],
    ),
    # One frame per rendered capture (4 captures, 8 image sets), no real images.
    "chessboard_detect": (["--seeds", "0", "--frames", "1"], ["seeds", "frames", "sets", "pooled"]),
    "compile": (
        ["--workers", "1", "--cache", str(CACHE_DIR)],
        ["cold_calibrate_s", "cold_jax_compile_s", "second_dataset_compile_s", "first", "second"],
    ),
}

#: Over ~20 s each even with a warm compilation cache (they calibrate a dataset or compile a
#: whole Monte Carlo trial / refinement): marked `bench`, 4-6 minutes together on a 2-core machine.
SLOW = {
    "chessboard_detect", "compile", "corrupted", "ee_uncertainty", "efficiency", "handeye", "montecarlo", "plan_realism",
    "prediction_check", "realism",
}  # fmt: skip

#: Not smoke-run here (see the module docstring).
NOT_RUN = {"real_tracker", "startup", "plan", "certify", "certify_errors", "drift", "noise_weights"}


def _run(args: list[str], timeout: float = 600) -> subprocess.CompletedProcess:
    env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=str(CACHE_DIR), PYTHONPATH=str(ROOT))
    return subprocess.run(
        [sys.executable, *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout
    )


def test_every_benchmark_is_covered():
    scripts = {p.stem for p in BENCH.glob("*.py") if not p.stem.startswith("_")}
    assert scripts - NOT_RUN == set(CASES)


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.bench) if n in SLOW else n for n in sorted(CASES)]
)
def test_benchmark_runs_at_its_smallest_size(name, tmp_path):
    args, keys = CASES[name]
    out = tmp_path / f"{name}.json"
    proc = _run([str(BENCH / f"{name}.py"), *args, "--json", str(out)])
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(out.read_text())
    assert set(keys) <= set(result), sorted(set(keys) - set(result))


@pytest.mark.parametrize(
    ("name", "option"),
    [("plan", "--candidates"), ("certify_errors", "--workdir"), ("noise_weights", "--workdir")],
)
def test_long_benchmarks_parse_their_options(name, option):
    proc = _run([str(BENCH / f"{name}.py"), "--help"], timeout=60)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert option in proc.stdout


def test_realism_summarises_rendered_seeds_by_their_medians():
    """`benchmarks/realism.py --seeds N`: per case the seeds' figures, medians, the ratio of
    medians to the ideal case's and the median of the seeds' own ratios; a refused seed
    (no figure) leaves its medians undefined instead of dropping it."""
    sys.path.insert(0, str(BENCH))
    try:
        from realism import over_seeds
    finally:
        sys.path.remove(str(BENCH))

    def row(refined, two_stage, status="ok"):
        return {"refined_mm": refined, "two_stage_mm": two_stage, "status": status}

    per_seed = {
        0: {"ideal": row(1.0, 2.0), "rs": row(1.5, 9.0), "gone": row(None, None, "refused")},
        1: {"ideal": row(0.5, 1.0), "rs": row(0.4, 8.0), "gone": row(0.6, 1.0)},
        2: {"ideal": row(0.8, 1.5), "rs": row(1.0, 7.0, "suspect"), "gone": row(0.7, 1.0)},
    }
    for cases in per_seed.values():  # the clock's error everywhere; the line delay estimated
        for name, row_ in cases.items():
            row_["clock_error_ms"] = -0.02 if name == "rs" else 0.01
        cases["rolling_shutter_estimated"] = dict(cases["rs"], line_delay_estimated=True)
    true = 0.02 / 600  # the rendered case's 20 ms readout over 600 rows
    for k, cases in enumerate(per_seed.values()):
        cases["rolling_shutter_estimated"]["line_delay_s"] = true * (1.0 + 0.01 * k)
    out = over_seeds(per_seed, height=600)
    rs = out["rs"]
    assert rs["max_abs_clock_error_ms"] == 0.02 and "line_delay_error_pct" not in rs
    est = out["rolling_shutter_estimated"]
    assert est["line_delay_true_s"] == true
    np.testing.assert_allclose(est["line_delay_error_pct"], [0.0, 1.0, 2.0], atol=1e-9)
    assert est["max_abs_line_delay_error_pct"] == pytest.approx(2.0)
    assert rs["refined_mm"] == [1.5, 0.4, 1.0] and rs["status"] == ["ok", "ok", "suspect"]
    assert rs["median_refined_mm"] == 1.0 and rs["median_two_stage_mm"] == 8.0
    assert rs["refined_ratio_of_medians"] == pytest.approx(1.0 / 0.8)
    assert rs["median_refined_ratio"] == pytest.approx(1.25)  # of 1.5, 0.8, 1.25
    assert out["ideal"]["refined_ratio_of_medians"] == 1.0
    assert out["gone"]["median_refined_mm"] is None and out["gone"]["median_refined_ratio"] is None
