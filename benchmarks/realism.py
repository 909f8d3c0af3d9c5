"""Realistic captures (issue 32): the sweeps capture through degraded cameras, calibrated as a user would.

One UR5e sweeps capture of `data/ur5e_sweeps`' design (80-degree sweeps, the
clock offset unknown, grey images, seed 0) rendered once per case through a
`jaxcal.sim.camera.CameraModel`, each case on the same arm, motion and seed
as the ideal render (the camera's noise has its own random stream), then
`jaxcal.calibrate` with its defaults. Per case: the two-stage and refined
end-effector RMS against the truth, the verdict's `status` (`ok`, `suspect`,
or `refused` when the calibration raises) and its `reasons`.

    python benchmarks/realism.py --json results/realism.json [--workdir DIR] [--cases ideal noise ...]
        [--detection-errors]
        [--resolution 800x600] [--frames-per-joint 24]
        [--analytic-seeds N [--analytic-cases ...] [--analytic-noise-px 0.054] [--analytic-design DIR]]

Cases (the issue's that the simulator supports so far): `ideal`; `noise`
(Poisson-Gaussian, 2 DN read noise, about 4 DN at mid-grey); `jpeg80`;
`defocus` (Gaussian, 1 px); `distortion_given` (k1 -0.12, k2 0.05, in the
metadata); `distortion_unknown` (the same images, the metadata says none);
`exposure_10ms` (8 sub-frames, stamped mid-exposure); `rolling_shutter_given`
(20 ms top-to-bottom readout, stamped at the first row, rendered every 0.25 ms,
the line delay in the metadata); `rolling_shutter_estimated` (the same images, `line_delay_s:
"estimate"`); `rolling_shutter_unknown` (the same images, the line delay
null: a global shutter assumed); `camera_mix` (the noise, JPEG 90,
5 ms exposure stamped mid-exposure, the distortion given); and the presets
`global_shutter` and `rolling_shutter` (`jaxcal simulate --camera`).
The arm's cases (`jaxcal.sim.arm`, ideal camera): `compliance` (the
`realistic` arm's gravity compliance alone), `backlash` (its lost motion, 1
arcmin per joint), `encoder_quantisation` (a coarse motor encoder, 1024 counts
per motor turn: a 256-line quadrature encoder), `encoder_latency` (joint
states stamped 2 ms late); `combined`: the `global-shutter` camera and the
`realistic` arm (`jaxcal simulate --camera-model global-shutter --arm realistic`).
`encoder_50hz`: the ideal capture with its encoder log at 50 Hz instead of
500 Hz (the issue's battery case: the log read between its samples while the
sweeps accelerate). `physics_arm`: the `physics` arm (`jaxcal simulate --arm
physics`: the realistic arm under MuJoCo's dynamics, `jaxcal.sim.physics`) on the
ideal camera; `ideal_two_speeds` and `physics_arm_two_speeds`: the ideal and the physics arm
with each sweep filmed on the way back too, at half the speed (`SimConfig.sweep_back`), the
capture that tells a compliant joint's lag under its inertial torques from its reduction
ratio (their ratios are to `ideal_two_speeds`). Issue 48's correlated detector errors: `lens_remap_1x` (the lens of
`distortion_given`, in the metadata, warped at the sensor's resolution by a bilinear
`cv2.remap` after the render, as another renderer or a camera's own undistortion
forms images), `rolling_shutter_coarse` (a 20 ms rolling shutter rendered in 16-row
bands: a render every 16 rows' delay, 0.53 ms, each drawing the band of rows exposed near
it and the rows between two renders cross-faded, as `rolling_shutter_given` does every
0.25 ms; the line delay in the metadata; at twice the capture's speed: the same 24 frames
per sweep in 0.4 s, the camera at 60 fps) and
`exposure_10ms_fast` (`exposure_10ms` at twice the speed).

Per case `ee_sigma_mm`, the tool point's 1-sigma uncertainty the result claims (the
verdict's RMS over random configurations), and `measured_over_claimed`, the refined EE
RMS over it.

With `--detection-errors`, each case also reports its detected corners against the
truth projected through the simulated lens (`detection`: `rms_px`, the `mean_px`
shift, `corner_fixed_rms_px`, the RMS of each corner's mean error over the frames
that saw it, and `frame_correlation`, the correlation of a corner's errors in
consecutive frames: independent errors give about 0).

With `--workdir`, the rendered captures are kept and reused (rendering is
deterministic per case).

Every case is calibrated with the default non-geometric terms (`terms="auto"`: compliance and
backlash, each kept only where held-out views say so; `terms_kept` names them); with
`--without-terms`, every arm case is calibrated again with none (`<case>_without_terms`: the rigid
model, as before issue 48).

With `--seeds N`, every rendered case is rendered and calibrated for the seeds
`--seed` ... `--seed + N - 1` (each seed draws another true arm, mounts and
noise; the cases of one seed share them), and `over_seeds` in the JSON gives
per case the seeds' refined and two-stage EE RMS, statuses, first reasons, measured
over claimed EE RMS, their medians, the refined ratio of medians to the ideal case's,
each seed's own ratio (`refined_ratio`) and their median: one render's refined EE RMS moves by 2x with its draw of detection errors
(docs/performance.md), so a ratio is judged on medians. `cases` stays the first
seed's.

With `--analytic-seeds N`, the rolling shutter against the ideal capture on analytic
corners over N seeds, without rendering (`analytic` in the JSON): the corners of the
design capture (`--analytic-design`, default `data/ur5e_sweeps`, this benchmark's ideal
render) are put where the truth puts them (`jaxcal.sim.corners`): at the frame's time
(`ideal`), or each at its own row's time (the frame's, plus its row times the line delay)
of a 20 ms readout stamped at the first row, the metadata's line delay given
(`rolling_shutter_given`) or `"estimate"` (`rolling_shutter_estimated`); the same corners
as the detector found in the design's images, plus independent Gaussian noise of
`--analytic-noise-px` per axis (default 0.054 px: the RMS per axis of the detector's errors
on the ideal render, 0.058 and 0.049 px along x and y), one draw per seed shared by the
cases. Each seed is then calibrated as `jaxcal.calibrate` does, the observe stage taking
the corners instead of detecting the images (`jaxcal.stages.observe(..., detections=)`).
Per case: the medians of the refined and two-stage EE RMS over the seeds and their `ratio`
(`ratio_two_stage`) to the ideal case's medians, the median of the seeds' own ratios, the
line delay's error (%) and the clock offset's (ms; the frames' exposure middle, with no
exposure their first row), and every seed's figures.
Given `--analytic-seeds`, the rendered cases run only when named with `--cases`.
"""

import argparse
import json
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

import jaxcal
from jaxcal import stages
from jaxcal.errors import JaxcalError
from jaxcal.io._files import write_text_atomic
from jaxcal.io.dataset import load_dataset
from jaxcal.sim.arm import ARM_PRESETS, ArmModel
from jaxcal.sim.camera import PRESETS, CameraModel
from jaxcal.sim.corners import analytic_detections, capture_truth
from jaxcal.sim.simulate import SimConfig, simulate
from jaxcal.vision import detect_frames

ROOT = Path(__file__).resolve().parents[1]

#: The issue's lens: barrel distortion of a wide-angle lens.
LENS = (-0.12, 0.05, 0.0, 0.0, 0.0)
NOISE = {"gain_dn": 0.094, "read_noise_dn": 2.0}

REALISTIC_ARM = ARM_PRESETS["realistic"]
#: The arm's cases: each effect of the realistic arm alone (a coarse encoder for quantisation).
ARMS = {
    "compliance": ArmModel(name="compliance", compliance=REALISTIC_ARM.compliance),
    "backlash": ArmModel(name="backlash", backlash_deg=REALISTIC_ARM.backlash_deg),
    "encoder_quantisation": ArmModel(name="encoder_quantisation", counts_per_rev=1024),
    "encoder_latency": ArmModel(name="encoder_latency", latency_s=REALISTIC_ARM.latency_s),
    "combined": REALISTIC_ARM,
    "physics_arm": ARM_PRESETS["physics"],
    "physics_arm_two_speeds": ARM_PRESETS["physics"],
}

#: Case name -> (camera model, the metadata's distortion replaced by zeros); the arm is `ARMS[name]` or ideal.
CASES = {
    "ideal": (CameraModel(), False),
    "noise": (CameraModel(name="noise", **NOISE), False),
    "jpeg80": (CameraModel(name="jpeg80", jpeg_quality=80), False),
    "defocus": (CameraModel(name="defocus", defocus_px=1.0), False),
    "distortion_given": (CameraModel(name="distortion", distortion=LENS), False),
    "distortion_unknown": (CameraModel(name="distortion", distortion=LENS), True),
    "exposure_10ms": (CameraModel(name="exposure_10ms", exposure_s=0.01, subframes=8), False),
    # Rows interpolated between renders 0.25 ms apart: at this capture's 157 deg/s a 1 ms step
    # cross-fades renders up to a pixel apart, which alone costs a millimetre (docs/performance.md).
    "rolling_shutter_given": (
        CameraModel(name="rolling_20ms", readout_s=0.02, stamp="start", step_s=2.5e-4),
        False,
    ),
    "camera_mix": (
        CameraModel(
            name="camera_mix", exposure_s=0.005, subframes=4, jpeg_quality=90, distortion=LENS, **NOISE
        ),
        False,
    ),
    "global_shutter": (PRESETS["global-shutter"], False),
    "rolling_shutter": (PRESETS["rolling-shutter"], False),
    "compliance": (CameraModel(), False),
    "backlash": (CameraModel(), False),
    "encoder_quantisation": (CameraModel(), False),
    "encoder_latency": (CameraModel(), False),
    "combined": (PRESETS["global-shutter"], False),
    "physics_arm": (CameraModel(), False),
    "ideal_two_speeds": (CameraModel(), False),
    "physics_arm_two_speeds": (CameraModel(), False),
    # The lens warped at the sensor's resolution (`cv2.remap`, bilinear), as another renderer's
    # post-process or a camera's own undistortion forms images: corner errors that repeat.
    "lens_remap_1x": (CameraModel(name="lens_remap_1x", distortion=LENS, lens_supersample=1), False),
    # A 20 ms rolling shutter rendered in 16-row bands (a render every 16 rows' delay, 0.53 ms,
    # the rows between cross-faded), at twice the speed: 2.5 px between renders at 4700 px/s.
    "rolling_shutter_coarse": (
        CameraModel(name="rolling_20ms_bands", readout_s=0.02, stamp="start", step_s=16 * 0.02 / 600),
        False,
    ),
    "exposure_10ms_fast": (CameraModel(name="exposure_10ms", exposure_s=0.01, subframes=8), False),
}

#: Twice the capture's speed: the same 24 frames at the same poses of each sweep, the sweep in
#: half the time (0.4 s; the camera at 60 fps).
FAST = {"fps": 60.0}
#: Each sweep filmed on the way back too, at half the speed (`SimConfig.sweep_back`): two speeds.
TWO_SPEEDS = {"sweep_back": 2.0}
#: Cases that change the capture's configuration itself: name -> `SimConfig` fields.
CONFIGS = {
    "encoder_50hz": {"encoder_rate_hz": 50.0},
    "ideal_two_speeds": TWO_SPEEDS,
    "physics_arm_two_speeds": TWO_SPEEDS,
    "rolling_shutter_coarse": FAST,
    "exposure_10ms_fast": FAST,
}

#: Cases that are another case's images with the metadata's cameras edited: name -> (that case, edit).
EDITED = {
    # metadata.json's K 2 % longer than the rendering camera's, or its principal point 20 px right.
    "focal_2pct": ("ideal", lambda cam: cam | {"K": _scaled(cam["K"], 1.02, 0.0)}),
    "principal_20px": ("ideal", lambda cam: cam | {"K": _scaled(cam["K"], 1.0, 20.0)}),
    "rolling_shutter_estimated": ("rolling_shutter_given", lambda cam: cam | {"line_delay_s": "estimate"}),
    "rolling_shutter_unknown": ("rolling_shutter_given", lambda cam: cam | {"line_delay_s": None}),
}


def _scaled(K, focal: float, cx_px: float) -> list:
    """`K` (rows) with its focal lengths times `focal` and its principal point `cx_px` right."""
    K = np.array(K, np.float64)
    K[0, 0], K[1, 1], K[0, 2] = focal * K[0, 0], focal * K[1, 1], K[0, 2] + cx_px
    return K.tolist()


def edited(case: str, config: SimConfig, workdir: Path) -> Path:
    """An `EDITED` case's dataset: its source case's, the metadata's cameras edited."""
    source, edit = EDITED[case]
    out = workdir / case
    shutil.copytree(capture(source, config, workdir), out)
    meta = json.loads((out / "metadata.json").read_text())
    meta["cameras"] = [edit(cam) for cam in meta["cameras"]]
    (out / "metadata.json").write_text(json.dumps(meta, indent=2))
    return out


def capture(case: str, config: SimConfig, workdir: Path) -> Path:
    """The case's rendered dataset in `workdir` (rendered once; `distortion_unknown` copies `distortion_given`'s)."""
    camera, hide_lens = CASES.get(case, (CameraModel(), False))
    out = workdir / case
    if (out / "truth.json").exists():
        return out
    if case in EDITED:
        return edited(case, config, workdir)
    if hide_lens:
        given = capture("distortion_given", config, workdir)
        shutil.copytree(given, out)
        meta = json.loads((out / "metadata.json").read_text())
        for cam in meta["cameras"]:
            cam["distortion"] = [0.0] * len(cam["distortion"])
        (out / "metadata.json").write_text(json.dumps(meta, indent=2))
        return out
    config = replace(config, camera=camera, arm=ARMS.get(case, "ideal"), **CONFIGS.get(case, {}))
    return simulate(config, out, progress=False)


def detection_errors(dataset: Path) -> dict:
    """The first camera's detections of the first target against the truth projected through the
    simulated lens (see the module docstring)."""
    ds = load_dataset(dataset)
    cam, target = ds.cameras[0], ds.targets[0]
    meta = json.loads((dataset / "metadata.json").read_text())
    lens = np.asarray(meta["simulation"]["distortion"], np.float64)
    frames = [f for f in ds.truth["frames"] if f["camera"] == cam.name]
    paths = [ds.image_path(f["row"]) for f in frames]
    dets = detect_frames(paths, [target.spec], K=cam.K, dist=cam.dist, progress=False)
    points = target.spec.points()
    errors = {}  # (corner id, frame) -> error (px)
    for f, det in zip(frames, dets):
        d = det.get(target.name)
        if d is None:
            continue
        T = np.asarray(f["T_cam_target"][target.name], np.float64)
        proj = cv2.projectPoints(points[d.ids], cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], cam.K, lens)[0][:, 0]
        errors.update({(int(i), int(f["frame"])): e for i, e in zip(d.ids, d.pixels - proj)})
    e = np.array(list(errors.values()))
    ids = np.array([i for i, _ in errors])
    fixed = np.array([e[ids == i].mean(axis=0) for i in ids])
    pairs = [(v, errors[(i, k + 1)]) for (i, k), v in errors.items() if (i, k + 1) in errors]
    num = sum(float(a @ b) for a, b in pairs)
    den = sum(0.5 * float(a @ a + b @ b) for a, b in pairs)
    return {
        "corners": len(e),
        "rms_px": float(np.sqrt(np.mean(np.sum(e**2, axis=1)))),
        "mean_px": e.mean(axis=0).tolist(),
        "corner_fixed_rms_px": float(np.sqrt(np.mean(np.sum(fixed**2, axis=1)))),
        "frame_correlation": num / den if den else None,
    }


#: The analytic comparison: the rolling shutter's top-to-bottom readout (s), the pixel noise
#: (px per axis; see the module docstring) and the cases, each an edit of the camera's metadata.
READOUT_S = 0.02
ANALYTIC_NOISE_PX = 0.054
_GLOBAL = {"exposure_s": 0.0, "stamp": "middle", "line_delay_s": 0.0}
ANALYTIC = {
    "ideal": lambda cam: cam | _GLOBAL,
    "rolling_shutter_given": lambda cam: (
        cam | _GLOBAL | {"stamp": "start", "line_delay_s": READOUT_S / cam["height"]}
    ),
    "rolling_shutter_estimated": lambda cam: cam | _GLOBAL | {"stamp": "start", "line_delay_s": "estimate"},
}


def _stages(setup, options, detections) -> dict:
    """`jaxcal.calibrate`'s stages on `setup` with the observe stage given `detections`: the
    figures of one analytic seed."""
    obs = stages.observe(setup, options, detections)
    sync = stages.synchronise(setup, obs, options)
    two = stages.two_stage(setup, obs, sync, options)
    refined = stages.refine(setup, obs, sync, two, options)
    verdict = stages.verdict(setup, obs, sync, two, refined, options.limits)
    v = stages.validate(setup, sync, two, refined, options).report
    delays = refined.line_delays if refined is not None else ()
    return {
        "two_stage_mm": v.ee_rms_mm_two_stage,
        "refined_mm": v.ee_rms_mm_after,
        "status": verdict.status,
        "reasons": list(verdict.reasons),
        "clock_error_ms": v.clock_offset_error_ms,
        "line_delay_s": delays[0].line_delay_s if delays else None,
    }


def analytic(design: Path, seeds: int, noise_px: float, workdir: Path, cases=tuple(ANALYTIC)) -> dict:
    """The module docstring's analytic comparison: `{case: {medians, ratios, errors, "seeds": [...]}}`."""
    ds = load_dataset(design)
    truth = capture_truth(ds)
    cam = ds.cameras[0]
    rows, _ = truth.frames[cam.name]
    like = detect_frames(
        [ds.image_path(int(r)) for r in rows],
        [t.spec for t in ds.targets],
        K=cam.K,
        dist=cam.dist,
        progress=False,
    )
    options = stages.Options(progress=False)
    out = {}
    for case in cases:
        root = workdir / "analytic" / case
        if root.exists():
            shutil.rmtree(root)
        shutil.copytree(design, root)
        meta = json.loads((root / "metadata.json").read_text())
        meta["cameras"] = [ANALYTIC[case](c) if c["name"] == cam.name else c for c in meta["cameras"]]
        (root / "metadata.json").write_text(json.dumps(meta, indent=2))
        setup = stages.setup(root, options)
        delay = READOUT_S / cam.height if case.startswith("rolling_shutter") else 0.0
        runs = []
        for seed in range(seeds):
            start = time.perf_counter()
            dets = analytic_detections(
                truth,
                cam.name,
                like=like,
                line_delay_s=delay,
                noise_px=noise_px,
                rng=np.random.default_rng(seed),
            )
            row = {"seed": seed} | _stages(setup, options, {cam.name: dets})
            row["calibrate_s"] = time.perf_counter() - start
            runs.append(row)
            print(
                json.dumps({"analytic": case} | {k: v for k, v in row.items() if k != "reasons"}), flush=True
            )
        out[case] = {"line_delay_true_s": delay, "seeds": runs}
    return _analytic_summary(out)


def _analytic_summary(out: dict) -> dict:
    """Each case's medians over the seeds, the ratios to the ideal case's and the errors of its
    line delay and clock."""
    ideal = out.get("ideal")

    def median(case, key):
        return float(np.median([r[key] for r in out[case]["seeds"]]))

    for case, block in out.items():
        runs = block["seeds"]
        block["median_refined_mm"] = median(case, "refined_mm")
        block["median_two_stage_mm"] = median(case, "two_stage_mm")
        if ideal is not None:
            block["ratio"] = block["median_refined_mm"] / median("ideal", "refined_mm")
            block["ratio_two_stage"] = block["median_two_stage_mm"] / median("ideal", "two_stage_mm")
            pairs = [r["refined_mm"] / i["refined_mm"] for r, i in zip(runs, ideal["seeds"])]
            block["median_seed_ratio"] = float(np.median(pairs))
        clock = np.abs([r["clock_error_ms"] for r in runs])
        block["median_abs_clock_error_ms"] = float(np.median(clock))
        block["max_abs_clock_error_ms"] = float(clock.max())
        if block["line_delay_true_s"]:
            err = [100.0 * (r["line_delay_s"] / block["line_delay_true_s"] - 1.0) for r in runs]
            block["line_delay_error_pct"] = float(np.median(err))
            block["max_abs_line_delay_error_pct"] = float(np.max(np.abs(err)))
        block["statuses"] = {
            s: sum(r["status"] == s for r in runs) for s in sorted({r["status"] for r in runs})
        }
    return out


def run_case(dataset: Path, terms="auto") -> dict:
    """Calibrate `dataset` with the defaults (`terms`: the non-geometric terms to try): EE RMS of both
    stages, the verdict and its reasons, the terms kept."""
    try:
        result = jaxcal.calibrate(dataset, progress=False, terms=terms)
    except JaxcalError as e:
        return {"two_stage_mm": None, "refined_mm": None, "status": "refused", "reasons": [str(e)]}
    v = result.validation
    delays = (result.refinement.line_delay or ()) if result.refinement is not None else ()
    sigma = next((c.value for c in result.verdict.checks if c.check == "ee_sigma_mm"), None)
    return {
        "two_stage_mm": v["ee_rms_mm_two_stage"],
        "refined_mm": v["ee_rms_mm_after"],
        "ee_sigma_mm": sigma,
        "measured_over_claimed": v["ee_rms_mm_after"] / sigma if sigma else None,
        "status": result.status,
        "reasons": list(result.reasons),
        "clock_error_ms": v["clock_offset_error_ms"],
        "line_delay_s": delays[0].line_delay_s if delays else None,
        "line_delay_estimated": bool(delays and delays[0].estimated),
        "terms_kept": [] if result.terms is None else list(result.terms.kept),
        "terms_why": [] if result.terms is None else [m.why for m in result.terms.models if m.why],
        # The score tests of the first camera's held lens and intrinsics (sigmas; null: not tested).
        "camera_model_sigmas": {
            "lens": getattr(getattr(result.refinement, "lens_test", None), "sigmas", None),
            "intrinsics": getattr(getattr(result.refinement, "intrinsics_test", None), "sigmas", None),
        },
    }


def over_seeds(per_seed: dict, height: int = 600) -> dict:
    """Per case: the seeds' figures and statuses, their medians, the refined ratio of
    medians and median of ratios to the ideal case (`ideal_two_speeds` for a two-speed case;
    `None` where a seed was refused), the
    largest clock error and, where the line delay was estimated, its errors against the
    rendered camera's (`height` rows)."""
    out = {}
    for case in next(iter(per_seed.values())):
        rows = [cases[case] for cases in per_seed.values()]
        refined = [r["refined_mm"] for r in rows]
        row = {
            "refined_mm": refined,
            "two_stage_mm": [r["two_stage_mm"] for r in rows],
            "status": [r["status"] for r in rows],
            "measured_over_claimed": [r.get("measured_over_claimed") for r in rows],
            "first_reason": [(r.get("reasons") or [None])[0] for r in rows],
            "median_refined_mm": _median(refined),
            "median_two_stage_mm": _median([r["two_stage_mm"] for r in rows]),
        }
        clock = [r.get("clock_error_ms") for r in rows]
        if all(c is not None for c in clock):
            row["max_abs_clock_error_ms"] = float(np.max(np.abs(clock)))
        if all(r.get("line_delay_estimated") for r in rows):
            camera = CASES[EDITED[case][0] if case in EDITED else case][0]
            true = camera.line_delay(height)
            err = [100.0 * (r["line_delay_s"] / true - 1.0) for r in rows]
            row["line_delay_true_s"], row["line_delay_error_pct"] = true, err
            row["max_abs_line_delay_error_pct"] = float(np.max(np.abs(err)))
        base = "ideal_two_speeds" if case.endswith("_two_speeds") else "ideal"
        if all(base in cases for cases in per_seed.values()):
            ideal = [cases[base]["refined_mm"] for cases in per_seed.values()]
            if row["median_refined_mm"] is not None and _median(ideal):
                row["refined_ratio_of_medians"] = row["median_refined_mm"] / _median(ideal)
            row["refined_ratio"] = [a / b if a is not None and b else None for a, b in zip(refined, ideal)]
            row["median_refined_ratio"] = _median(row["refined_ratio"])
        out[case] = row
    return out


def _median(values) -> float | None:
    """The median of `values`, or `None` if any is missing (a refused seed)."""
    return None if not values or any(v is None for v in values) else float(np.median(values))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--cases", nargs="*", choices=list(dict.fromkeys([*CASES, *EDITED, *CONFIGS])), default=None
    )
    parser.add_argument(
        "--analytic-seeds",
        type=int,
        default=0,
        help="the analytic rolling-shutter comparison over this many seeds",
    )
    parser.add_argument("--analytic-design", default=str(ROOT / "data" / "ur5e_sweeps"))
    parser.add_argument("--analytic-noise-px", type=float, default=ANALYTIC_NOISE_PX)
    parser.add_argument("--analytic-cases", nargs="+", choices=list(ANALYTIC), default=list(ANALYTIC))
    parser.add_argument("--resolution", default="800x600")
    parser.add_argument("--frames-per-joint", type=int, default=24)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--seeds", type=int, default=1, help="render every case for this many seeds from --seed"
    )
    parser.add_argument("--json", help="write the figures here")
    parser.add_argument(
        "--without-terms",
        action="store_true",
        help="also calibrate every arm case with no non-geometric term (`<case>_without_terms`)",
    )
    parser.add_argument("--workdir", help="keep the rendered captures here and reuse them")
    parser.add_argument(
        "--detection-errors",
        action="store_true",
        help="also the detected corners against the projected truth",
    )
    args = parser.parse_args(argv)
    if args.cases is None:
        args.cases = [] if args.analytic_seeds else [*CASES, *EDITED, *CONFIGS]
    if args.seeds < 1:
        parser.error("--seeds must be at least 1")
    w, h = (int(x) for x in args.resolution.split("x"))
    config = SimConfig(
        robot="ur5e", seed=args.seed, resolution=(w, h), frames_per_joint=args.frames_per_joint,
        range_deg=80.0, clock_offset_ms=40.0, clock_known=False, grayscale=True,
    )  # fmt: skip
    per_seed = {}
    with tempfile.TemporaryDirectory() as scratch:
        workdir = Path(args.workdir or scratch)
        workdir.mkdir(parents=True, exist_ok=True)
        for seed in range(args.seed, args.seed + args.seeds):
            root = workdir if args.seeds == 1 else workdir / f"seed{seed}"
            root.mkdir(parents=True, exist_ok=True)
            per_seed[seed] = cases = {}
            for case in args.cases:
                start = time.perf_counter()
                dataset = capture(case, replace(config, seed=seed), root)
                rendered = time.perf_counter()
                cases[case] = run_case(dataset) | {
                    "render_s": rendered - start,
                    "calibrate_s": time.perf_counter() - rendered,
                }
                if args.detection_errors:
                    cases[case]["detection"] = detection_errors(dataset)
                print(
                    json.dumps({case: cases[case]} | ({"seed": seed} if args.seeds > 1 else {})), flush=True
                )
                if args.without_terms and case in ARMS:
                    start = time.perf_counter()
                    rigid = f"{case}_without_terms"
                    cases[rigid] = run_case(dataset, terms=()) | {"calibrate_s": time.perf_counter() - start}
                    print(
                        json.dumps({rigid: cases[rigid]} | ({"seed": seed} if args.seeds > 1 else {})),
                        flush=True,
                    )
        if args.analytic_seeds:
            found = analytic(
                Path(args.analytic_design),
                args.analytic_seeds,
                args.analytic_noise_px,
                workdir,
                args.analytic_cases,
            )
    for cases in per_seed.values():
        ideal = cases.get("ideal")
        if ideal and ideal["refined_mm"]:
            for row in cases.values():
                if row["refined_mm"] is not None:
                    row["refined_vs_ideal"] = row["refined_mm"] / ideal["refined_mm"]
    out = {
        "resolution": args.resolution,
        "frames_per_joint": args.frames_per_joint,
        "sweep_deg": 80.0,
        "seed": args.seed,
        "cases": per_seed[args.seed],
    }
    if args.seeds > 1:
        out["seeds"] = {str(seed): cases for seed, cases in per_seed.items()}
        out["over_seeds"] = over_seeds(per_seed, h)
    if args.analytic_seeds:
        out["analytic_design"] = args.analytic_design
        out["analytic_noise_px"] = args.analytic_noise_px
        out["analytic"] = found
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(Path(args.json), json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
