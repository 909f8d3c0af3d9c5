"""Every benchmark in benchmarks/, and every mode of it, runs at its smallest size and writes the JSON
keys its docs quote; every benchmark command written in README.md and docs/*.md parses.

A smoke test, not a measurement (the figures, with their commands, are in docs/performance.md):
a refactor that breaks a benchmark's imports, calls or options fails here rather than in a
user's hands. `RUNS` holds one row per benchmark mode: its arguments at the smallest size that
still takes the mode's code path (one seed, one trial, the smallest render, `data/ur5e_sweeps`'
design, whose programs the suite compiles anyway) and the keys its JSON must hold. A new mode is
one row. The runs go through `tests/_benchmark_runner.py`, which calls each script's
`main(argv)` as its command line does, all in one Python process per `process` name with the
suite's compilation cache, in the table's order: runs of one design share their compiled
programs, and a run may read what an earlier one left in `{work}` (`certify_errors.py` reads
`certify.py --workdir`'s captures, `noise_weights.py` `realism.py --workdir`'s renders). The
larger sizes stay outside the suite: the scripts' defaults, and the commands in the docs.
"""

import argparse
import importlib
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest
from conftest import CACHE_DIR

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
RUNNER = Path(__file__).resolve().parent / "_benchmark_runner.py"


class Run(NamedTuple):
    """One benchmark mode at its smallest size: `script` (a file stem of benchmarks/), its
    arguments (`{work}`: the process's shared folder; `{cache}`: the suite's compilation cache;
    `--json` is added), the keys its JSON must hold (`a.b`: key `b` of `a`), and the process it
    runs in."""

    script: str
    args: str
    keys: str
    process: str = "main"


RUNS = {
    "codebase_counts": Run(
        "codebase_counts",
        "--brief",
        "record_fields bag_fields string_key_reads mode_tests long_functions covariance_sites package_lines "
        "modules_over_500_lines fmt_skips cli_options config_keys option_names_with_two_meanings",
    ),
    # The humanoid upper body at 120 poses: cross-validation, the floor, geometry alone, the URDF read
    # back; its head camera filming both hands at 60 poses.
    "tree": Run(
        "tree",
        "--poses 120 --test-poses 20 --camera-poses 60 --camera-test-poses 20",
        "tree_test_mean_mm tree_floor_mm tree_geometric_mm tree_over_floor tree_terms_kept elastic_within_3sigma "
        "urdf_roundtrip_max_m<=1e-9 camera_ee_rms_mm camera_prediction_z2 camera_statuses",
    ),
    # Five units of tests/test_fleet.py's design, one of them also alone; a new unit with their prior.
    "fleet": Run(
        "fleet",
        "--units 5 --poses 48 --singles 1 --cv-folds 0 --prior-poses 24 --population-scale 0.5 --processes 2",
        "fleet_s single_s speedup max_parameter_difference statuses outliers population_std_mm "
        "prior_30_over_full_1000 noprior_30_over_full_1000 prior_share_mean ee_rms_mm "
        # Two local processes of one distributed run give what one gives (issue 52 item 3).
        "processes.wall_ratio processes.max_parameter_difference==0 processes.summary_equal==true",
        process="fleet",
    ),
    # Two quick commands, once each: the harness tests/test_progress.py shares runs whole.
    "first_line": Run(
        "first_line", "--repeats 1 --commands inspect,verify", "pipe_s terminal_s slowest_s over_2s lines"
    ),
    "render": Run("render", "--frames 2 --resolutions 160x120", "frames backend resolutions"),
    "vision": Run(
        "vision",
        "--dataset data/ur5e_sweeps --frames 3 --repeat 1",
        "frames poses overhead_pct pool_speedup median_s",
    ),
    # data/ur5e_sweeps is this design's seed 0 (`REUSED`): seed 1 is rendered.
    "realism": Run(
        "realism",
        "--cases ideal --seeds 2 --seed 0 --resolution 800x600 --frames-per-joint 24 --detection-errors "
        "--workdir {work}/realism",
        "cases.ideal.refined_mm cases.ideal.detection over_seeds.ideal.median_refined_mm "
        "cases.ideal.camera_model_sigmas.intrinsics<=3 cases.ideal.camera_model_sigmas.lens<=3",
        process="captures",
    ),
    "realism --analytic-seeds": Run(
        "realism",
        "--analytic-seeds 1 --analytic-design data/ur5e_sweeps --analytic-noise-px 0.054 "
        "--analytic-cases ideal rolling_shutter_given",
        "analytic analytic_noise_px analytic.rolling_shutter_given",
        process="captures",
    ),
    # Issue 48's rendered cases at 320x240, 6 frames per sweep (calibrated or refused; their pieces:
    # tests/test_camera_model.py, test_arm_model.py, test_covariance.py).
    "realism --cases": Run(
        "realism",
        "--cases physics_arm physics_arm_two_speeds lens_remap_1x rolling_shutter_coarse exposure_10ms_fast "
        "--resolution 320x240 --frames-per-joint 6 --seed 0 --without-terms",
        "cases.physics_arm cases.physics_arm_without_terms cases.physics_arm_two_speeds cases.lens_remap_1x "
        "cases.rolling_shutter_coarse cases.exposure_10ms_fast",
        process="captures",
    ),
    "noise_weights": Run(
        "noise_weights",
        "--workdir {work}/realism/seed0 --cases ideal --weights plain rms_px sharpness "
        "--added-noise-dn 2 --scratch {work}/noisier",
        "fit summary.ideal.rms_px calibrations.ideal.sharpness views",
        process="captures",
    ),
    "ee_uncertainty": Run("ee_uncertainty", "data/ur5e_sweeps", "dataset ee_rms_mm_measured free_parameters"),
    "prediction_check": Run(
        "prediction_check", "data/ur5e_sweeps --flips 3 --seed 0", "machine flips datasets seed_correlation"
    ),
    "corrupted": Run(
        "corrupted",
        "--seeds 0 --fraction 0.1 --shear 0.08 --resolution 800x600 --frames-per-joint 24 "
        "--workdir {work}/corrupted",
        "fraction seeds max_ratio_two_stage max_ratio_refined",
    ),
    "plan": Run(
        "plan",
        "--smoke --seeds 1 --item6-seeds 1 --frames 24 --steps 2 --starts 1 --candidates 100 "
        "--workdir {work}/plan",
        "planned_ee_rms_mm demo_ee_rms_mm ratios_within_90_interval issue_pairs_inside_probability_best_scale "
        "gradient_predicted_ee_mm greedy_predicted_ee_mm plan_seconds detected_fraction refinement_vs_two_stage "
        "panda eye_in_hand",
        process="captures",
    ),
    "plan_realism": Run(
        "plan_realism",
        "--plan {work}/plan/planned.json --no-sweeps --seeds 1 --noise-step 72 --noise-draws 1 --poses 24",
        "machine corner_noise predictions checks",
        process="captures",
    ),
    "drift --camera": Run(
        "drift",
        "--camera --smoke --seeds 1 --trials 1 --frames 24 --first-seed 0 --workdir {work}/drift_camera",
        "false_alarm_rate detectable_mm_10_images detectable_mm_bound drift_power_by_mm drift_power_by_deg "
        "estimate_within_2sigma calibration_error_ratio check_s",
        process="captures",
    ),
    # certify's `demo_sweeps` (at --smoke, data/ur5e_sweeps: `REUSED`) is read again by certify_errors
    # and by drift's --demo-camera; its `planned` renders plan.py's plan.
    "certify": Run(
        "certify",
        "--smoke --seeds 1 --poses 48 --configs 20 --render demo_sweeps planned --render-seeds 1 --first-seed 0 "
        "--plan {work}/plan/planned.json --workdir {work}/certify --reuse --camera {work}/drift_camera/res0",
        "certificate_coverage.tracker_poses certificate_coverage.demo_sweeps certificate_coverage.planned "
        "certificate_coverage.camera certificate_ratios certificate_tightness designs",
        process="captures",
    ),
    "certify_errors": Run(
        "certify_errors",
        "--workdir {work}/certify --designs planned demo_sweeps --seeds 0",
        "captures designs.planned.coverage designs.demo_sweeps.tightness_median",
        process="captures",
    ),
    "drift": Run(
        "drift",
        "--seeds 1 --poses 48 --trials 1 --sizes 5,10 --noise-um 10",
        "false_alarm_rate drift_power_by_mm estimate_within_2sigma detectable_mm_10_images detectable_mm_bound "
        "check_s",
    ),
    "drift --camera --demo-camera": Run(
        "drift",
        "--camera --demo-camera --smoke --seeds 1 --trials 1 --workdir {work}/certify",
        "false_alarm_rate detectable_mm_10_images detectable_mm_bound drift_power_by_mm check_s",
        process="captures",
    ),
    "drift --handeye": Run(
        "drift",
        "--handeye --seeds 1 --trials 1 --resolution 320x240",
        "false_alarm_rate power_1mm estimate_within_2sigma_1mm detectable_mm_bound",
    ),
    # One capture per target and arrangement at test_handeye_capture.py's 16 frames.
    "handeye": Run(
        "handeye",
        "--quick --parts protocol,rendered,captures,real,speed,noise --capture-frames 16 --noise-frames 16 "
        "--seed 0",
        "methods cramer_rao rendered captures real noisy_robot_pixels_ms pixels_ms_50 "
        "speed.noisy_robot_pixels_dense_ms noise",
    ),
    "handeye --no-dense": Run(
        "handeye", "--parts speed --no-dense", "noisy_robot_pixels_ms pixels_ms_50 speed"
    ),
    "chessboard_detect": Run(
        "chessboard_detect",
        "--seeds 0 --frames 1 --images data/visp_handeye/eye_in_hand/images/cam0 --pattern 9 6",
        "seeds frames sets pooled real",
    ),
    "arcfit": Run(
        "arcfit",
        "--problems 4 --scipy-problems 2 --repeats 1 --frames 10 --seed 0",
        "n_problems frames jaxcal_s compile_s scipy_s speedup scipy_jac_s max_abs_diff",
    ),
    "long_sweep": Run("long_sweep", "--smoke", "rows device versions notes"),
    "import_csv": Run(
        "import_csv", "--rows 200 --workdir {work}/import_csv", "rows seconds cpu_s peak_rss_mib"
    ),
    "efficiency": Run(
        "efficiency",
        "--trials 2 --frames 5 --sigma-px 0.5 --range-deg 60 --seed 0",
        "trials max_ratio_to_crlb median_ratio_to_crlb per_parameter compile_s run_s",
    ),
    # test_montecarlo.py's trials (8 over 24 frames, on one device and on four of eight): its programs.
    "montecarlo": Run(
        "montecarlo",
        "--trials 8 --scipy-trials 1 --repeats 1 --frames 24 --seed 0 --device-counts ''",
        "trials jaxcal_s compile_s scipy_s speedup success_rate ee_rms_mm_median",
    ),
    "montecarlo --scaling-only": Run(
        "montecarlo",
        "--scaling-only --trials 8 --repeats 1 --frames 24 --device-counts 4",
        "device_scaling device_scaling_note",
    ),
    "montecarlo --processes": Run(
        "montecarlo",
        "--scaling-only --trials 8 --repeats 1 --frames 24 --device-counts '' --processes 2",
        "process_scaling.wall_ratio process_scaling.max_abs_diff_ee_rms_mm<=1e-10 process_scaling.many.devices==2",
    ),
    "compile": Run(
        "compile",
        "--workers 1 --cache {cache}",
        "cold_calibrate_s cold_jax_compile_s second_dataset_compile_s first second",
    ),
    "real_tracker": Run(
        "real_tracker",
        "--rounds 1 --bad-rows 1 --cache {cache} --workdir {work}/real_tracker",
        "ur5_bad_rows_1_named ur5_bad_rows_1_named_correctly screen_ms ur5_test_mean_mm ur5_cv_mean_mm ur5_compliance_test_mean_mm ur5_best_test_mean_mm ur5_best_terms "
        "ur5_predicted_over_measured scipy_test_mean_mm fit_ms scipy_fit_ms speedup cold_fit_s",
    ),
    "startup": Run(
        "startup",
        "--repeats 1 --no-cold --cache {cache}",
        "import_s warm_cli_s inprocess_second_s handeye_warm_cli_s ee_rms_mm_after_warm cpu_s "
        "tracker_warm_cli_s tracker_terms_warm_cli_s tracker_verify_warm_cli_s tracker_cv_mean_mm "
        "tracker_best_cv_mean_mm stages_s.warm_cli_s stages_s.tracker_warm_cli_s",
    ),
    # No peer environments here (they need the network): FIGAROH and robotkinecal come out null. Its work
    # is all in child processes (jaxcal's CLI too): a process of its own, shared with no other run.
    "peers": Run(
        "peers",
        "--repeats 1 --envs {work}/no_peers --cache {cache}",
        "jaxcal.test_mean_mm jaxcal.fit_s jaxcal.whole_run_warm_s jaxcal.versions figaroh robotkinecal "
        "reasons.figaroh reasons.robotkinecal",
        process="peers",
    ),
}

#: Captures a run would render that are `data/ur5e_sweeps` itself (its design and seed): copied
#: into the run's folder, where the script reuses what it finds (its --workdir).
REUSED = {
    "realism": "realism/seed0/ideal",
    "corrupted": "corrupted/clean0",
    "drift --camera": "drift_camera/cal0",
    "certify": "certify/demo_sweeps_ds0",
    "plan": "plan/ur5e_sweeps_seed0",
}

#: `--quick` presets of sizes larger than the runs', which set the sizes one by one (long_sweep's
#: runs its rows in child processes, as its full size does; its `--smoke` row runs in-process).
PRESETS = {name: ["--quick"] for name in ("arcfit", "efficiency", "long_sweep", "montecarlo")}
#: Options whose value picks what runs, and the values the runs give between them: numbers that
#: switch a part on (realism's seeds summarised, its analytic comparison) and comma-separated parts.
#: (Other numbers are sizes and parameters; every other option must be given by a run.)
MODE_VALUES = {
    ("realism", "--seeds"): ["2"],
    ("realism", "--analytic-seeds"): ["1"],
    ("handeye", "--parts"): ["protocol", "rendered", "captures", "real", "speed", "noise"],
    ("montecarlo", "--device-counts"): ["4"],
    ("montecarlo", "--processes"): ["2"],
    ("fleet", "--processes"): ["2"],
}
#: Choice options whose choices are not each run: realism's cases are its camera and arm models
#: (`jaxcal.sim.camera`, `jaxcal.sim.arm`: tests/test_camera_model.py, test_rolling_shutter.py),
#: rendered and calibrated through one code path (the run renders `ideal`), and its analytic cases
#: edits of the capture's metadata, calibrated through one other.
CHOICES_NOT_RUN = {("realism", "--cases"), ("realism", "--analytic-cases")}


def _argv(run: Run, work: Path, out: Path) -> list[str]:
    return [*shlex.split(run.args.format(work=work, cache=CACHE_DIR)), "--json", str(out)]


@pytest.fixture(scope="module")
def ran(tmp_path_factory):
    """`ran(name)`: the record of `RUNS[name]` and its JSON path; each process's runs run together,
    on the first test that asks for one of them."""
    done = {}

    def get(name: str):
        process = RUNS[name].process
        if process not in done:
            work = tmp_path_factory.mktemp(f"bench_{process}")
            for n, folder in REUSED.items():
                if RUNS[n].process == process:
                    shutil.copytree(ROOT / "data" / "ur5e_sweeps", work / folder)
            runs = [
                {"name": n, "script": r.script, "args": _argv(r, work, work / f"{n}.json")}
                for n, r in RUNS.items()
                if r.process == process
            ]
            (work / "runs.json").write_text(json.dumps(runs))
            env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=str(CACHE_DIR), PYTHONPATH=str(ROOT))
            log = work / "runner.log"
            with log.open("w") as f:
                subprocess.run(
                    [sys.executable, str(RUNNER), str(work / "runs.json"), str(work / "records.jsonl")],
                    cwd=ROOT,
                    env=env,
                    stdout=f,
                    stderr=subprocess.STDOUT,
                    check=False,
                )
            path = work / "records.jsonl"
            records = [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []
            done[process] = (work, {r["name"]: r for r in records}, log)
        work, records, log = done[process]
        assert name in records, f"the runner ended before {name}:\n{log.read_text()[-4000:]}"
        return records[name], work / f"{name}.json"

    return get


#: A key that also states its value: `a.b<=1e-9`, `a.c==true`, `a.d>=0.5` (JSON after the operator).
CHECK = re.compile(r"^([\w.]+)(<=|>=|==)(.+)$")


def _missing(doc: dict, key: str) -> str | None:
    """Why `doc` does not hold `key` (a `RUNS` key, with or without a stated value); None if it does."""
    check = CHECK.match(key)
    path = check.group(1) if check else key
    for part in path.split("."):
        if not isinstance(doc, dict) or part not in doc:
            return f"{path}: missing"
        doc = doc[part]
    if check:
        op, want = check.group(2), json.loads(check.group(3))
        ok = {"<=": lambda: doc <= want, ">=": lambda: doc >= want, "==": lambda: doc == want}[op]()
        if not ok:
            return f"{path} = {doc!r}, not {op} {want!r}"
    return None


#: The processes whose runs `tests/test_benchmarks_captures.py` runs: the rendered captures' chain
#: (realism's renders read by noise_weights, plan's plan by plan_realism and certify, ...), about as
#: long as this file's other runs, so that each of `make test`'s two workers starts on one of them.
CAPTURES = ("captures",)


def check_run(name: str, ran) -> None:
    """`RUNS[name]` ran without error and wrote the keys it must."""
    record, out = ran(name)
    assert record["error"] is None, record["error"][-3000:]
    doc = json.loads(out.read_text())
    wrong = [why for k in RUNS[name].keys.split() if (why := _missing(doc, k))]
    assert not wrong, wrong


@pytest.mark.parametrize("name", [n for n, r in RUNS.items() if r.process not in CAPTURES])
def test_benchmark_runs_at_its_smallest_size(name, ran):
    check_run(name, ran)


class _Parsed(Exception):
    pass


def _parser(script: str) -> argparse.ArgumentParser:
    """The script's argument parser, as its `main` builds it (nothing runs)."""

    def grab(self, args=None, namespace=None):
        raise _Parsed(self)

    sys.path.insert(0, str(BENCH))
    try:
        module = importlib.import_module(script)
        original = argparse.ArgumentParser.parse_args
        argparse.ArgumentParser.parse_args = grab
        try:
            module.main([])
        except _Parsed as e:
            return e.args[0]
        finally:
            argparse.ArgumentParser.parse_args = original
    finally:
        sys.path.remove(str(BENCH))
    raise AssertionError(f"benchmarks/{script}.py: main() parsed no arguments")


SCRIPTS = sorted(p.stem for p in BENCH.glob("*.py") if not p.stem.startswith("_"))


def test_every_benchmark_and_every_mode_of_it_runs():
    """Every script has a run; every option of it that is not a number (a switch, a file or a
    folder, a choice: but `--json`, `--help`, the hidden ones and `PRESETS`) is given by one of
    its runs, every choice of a choice option too, and every value of `MODE_VALUES`."""
    assert {r.script for r in RUNS.values()} == set(SCRIPTS)
    missing = []
    for script in SCRIPTS:
        argvs = [shlex.split(r.args) for r in RUNS.values() if r.script == script]
        given = {tok for argv in argvs for tok in argv}
        for action in _parser(script)._actions:
            flags = [s for s in action.option_strings if s.startswith("--")]
            if not flags or action.help == argparse.SUPPRESS or flags[0] in ("--help", "--json"):
                continue
            if action.type in (int, float) or flags[0] in PRESETS.get(script, ()):
                continue
            if not set(action.option_strings) & given:
                missing.append(f"{script} {flags[0]}")
            for choice in action.choices or ():
                if choice not in given and (script, flags[0]) not in CHOICES_NOT_RUN:
                    missing.append(f"{script} {flags[0]} {choice}")
    for (script, option), values in MODE_VALUES.items():
        given = set()
        for argv in (shlex.split(r.args) for r in RUNS.values() if r.script == script):
            given |= {v for k, tok in enumerate(argv[:-1]) if tok == option for v in argv[k + 1].split(",")}
        missing += [f"{script} {option} {v}" for v in values if v not in given]
    assert not missing, missing


#: A documented command: `python benchmarks/NAME.py ...` in a code block or an inline code span.
COMMAND = re.compile(r"(?:(?:\S*/)?python3?\s+)?benchmarks/(\w+)\.py\b(.*)")


def _doc_commands() -> list[tuple[str, str, str, bool]]:
    """(where, script, arguments, whole): every benchmark command of README.md and docs/*.md,
    from code blocks (continuation lines joined, comments dropped) and inline code spans (which
    may wrap), and of the Makefile's recipes; `whole` when it is a command as typed (starting
    with `python`), else a mention of its options."""
    out = []
    for k, line in enumerate((ROOT / "Makefile").read_text().splitlines()):
        m = re.search(r"\$\(PY\) benchmarks/(\w+)\.py\b(.*)", line)
        if m:
            out.append((f"Makefile:{k + 1}", m.group(1), m.group(2), True))
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        text = path.read_text()
        spans = []
        for block in re.finditer(r"^```[^\n]*\n(.*?)^```", text, re.S | re.M):
            for line in block.group(1).replace("\\\n", " ").splitlines():
                spans.append((block.start(), line.split(" #", 1)[0]))
        prose = re.sub(
            r"^```[^\n]*\n.*?^```", lambda m: "\n" * m.group(0).count("\n"), text, flags=re.S | re.M
        )
        for m in re.finditer(r"`([^`]+)`", prose):
            spans.append((m.start(), m.group(1).replace("\\|", "|").replace("\n", " ")))
        for start, span in spans:
            m = COMMAND.search(span)
            if m:
                where = f"{path.name}:{text.count(chr(10), 0, start) + 1}"
                out.append((where, m.group(1), m.group(2), "python" in span[: m.start(1)]))
    return out


def test_every_documented_benchmark_command_parses():
    """Each benchmark command in README.md, docs/*.md and the Makefile parses with its script's options;
    `[...]` marks optional parts (kept), a lone `...` an elision (dropped). A mention without `python`
    (`benchmarks/drift.py --camera`) names options the script has."""
    commands = _doc_commands()
    assert len(commands) > 40  # the extraction found the docs' commands
    parsers = {}
    bad = []
    for where, script, args, whole in commands:
        if script not in SCRIPTS:  # a module of theirs (`_scipy_tracker.py`) named
            if not (BENCH / f"{script}.py").is_file():
                bad.append(f"{where}: no benchmarks/{script}.py")
            continue
        parser = parsers.setdefault(script, _parser(script))
        tokens = [t for t in shlex.split(args.replace("[", " ").replace("]", " ")) if t != "..."]
        if not whole:
            known = {s for a in parser._actions for s in a.option_strings}
            bad += [
                f"{where}: {script}.py has no {t}" for t in tokens if t.startswith("--") and t not in known
            ]
            continue

        def error(message, where=where, script=script, args=args):
            raise ValueError(f"{where}: {script}.py{args}: {message}")

        parser.error = error
        try:
            parser.parse_args(tokens)
        except ValueError as e:
            bad.append(str(e))
    assert not bad, "\n".join(bad)


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
