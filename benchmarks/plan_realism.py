"""A planned capture's prediction with the camera and arm models (issue 32 item 5), and its check.

Three parts, each in the JSON:

1. `corner_noise`: the corner noise each camera preset's sensor noise and JPEG
   add on a stopped frame (`jaxcal.sim.camera.CORNER_NOISE_PX`): `data/ur5e_sweeps`'
   ideal images (every `--noise-step`-th frame), each degraded `--noise-draws`
   times (`CameraModel.degrade`, seeded), detected, and compared with the clean
   image's corners (px per axis).
2. `predictions`: `jaxcal.evaluate_plan(..., camera_model=, arm=)` for every
   camera and arm preset on each design: `--plan PLAN` (e.g. `jaxcal plan --frames 240`'s),
   the demo's sweeps (`sweep_plan("ur5e")`) and `data/ur5e_sweeps`' design
   (24 frames per 80-degree sweep at 800x600): the frames kept, the noise, the
   arm's bias (and its causes), both together (mm, RMS over the workspace).
3. `checks`: the refinement on analytic corners against the prediction, with the
   `global-shutter` camera: the plan's corners where `jaxcal.sim.arm.ArmMotion`
   puts the joints along the plan's own motion (the truth: the nominal geometry),
   the encoders reading the command; noise-free (the bias alone), then
   `--seeds` draws of the camera's corner noise. Plain least squares (the
   estimator the prediction linearises) and the refinement's robust default.
   On 24 stop-and-shoot poses (`tests/test_plan_realism.py`'s plan) and on `--plan`.

Usage:

    python benchmarks/plan_realism.py --plan plan.json --json OUT
"""

import argparse
import json
import os
import platform
import time
from pathlib import Path

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxcal
from jaxcal._refine import REFINE_ROBUST, refine, zero_params
from jaxcal._uncertainty import tool_points
from jaxcal.io.dataset import load_dataset
from jaxcal.planning import (
    CapturePlan,
    FeasibilityLimits,
    PoseSet,
    Robot,
    default_layout,
    load_plan,
    scene_of,
    sweep_plan,
    workspace,
)
from jaxcal.planning._evaluate import corner_problem
from jaxcal.planning._optimise import candidate_poses
from jaxcal.planning._scene import frame_geometry
from jaxcal.robots import link_inertials
from jaxcal.sim.arm import ARM_PRESETS, ArmMotion
from jaxcal.sim.camera import PRESETS
from jaxcal.sim.plan import plan_trajectory
from jaxcal.vision import detect

ROOT = Path(__file__).resolve().parents[1]


def corner_noise(step: int, draws: int) -> dict:
    """Part 1: per preset, the corners of degraded images against the clean image's (px)."""
    ds = load_dataset(ROOT / "data" / "ur5e_sweeps")
    rows = np.flatnonzero(ds.frames.camera == "cam0")[::step]
    spec, K = ds.targets[0].spec, ds.cameras[0].K
    clean = []
    for r in rows:
        image = cv2.cvtColor(cv2.imread(str(ds.image_path(int(r)))), cv2.COLOR_BGR2RGB)
        found = detect(image, spec, K=K)
        if found is not None and len(found.ids) >= 6:
            clean.append((image, found))
    out = {}
    for name, model in PRESETS.items():
        if model.instantaneous:
            continue
        diffs = []
        for k, (image, found) in enumerate(clean):
            for s in range(draws):
                d = detect(model.degrade(image.astype(np.float32), np.random.default_rng([k, s])), spec, K=K)
                if d is not None:
                    _, i0, i1 = np.intersect1d(found.ids, d.ids, return_indices=True)
                    diffs.append(d.pixels[i1] - found.pixels[i0])
        e = np.concatenate(diffs)
        out[name] = {
            "frames": len(clean),
            "corners": len(e),
            "rms_px_per_axis": float(np.sqrt(np.mean(e**2))),
            "mean_px": e.mean(axis=0).tolist(),
            "mad_sigma_px": (1.4826 * np.median(np.abs(e - np.median(e, axis=0)), axis=0)).tolist(),
        }
        print(name, out[name], flush=True)
    return out


def predictions(designs: dict) -> dict:
    """Part 2: every camera and arm preset on every design."""
    out = {}
    for dname, p in designs.items():
        for cam in PRESETS:
            for arm in ARM_PRESETS:
                ev = jaxcal.evaluate_plan(
                    p, camera_model=PRESETS[cam].noise_record(), arm=ARM_PRESETS[arm].figures()
                )
                row = {
                    "frames": ev.frames,
                    "lost_to_blur": ev.frames_lost_to_blur,
                    "sigma_px": ev.sigma_px,
                    "noise_mm": 1e3 * ev.ee_rms,
                    "bias_mm": 1e3 * ev.ee_bias_rms,
                    "total_mm": 1e3 * ev.ee_total_rms,
                    "total_p95_mm": 1e3 * ev.ee_total_p95,
                    "bias_parts_mm": {k: 1e3 * v for k, v in ev.bias_parts.items()},
                    "camera_note": ev.camera_note,
                }
                out[f"{dname} | {cam} | {arm}"] = row
                print(dname, cam, arm, {k: v for k, v in row.items() if k != "camera_note"}, flush=True)
    return out


def measured(plan: CapturePlan, arm, sigma_px: float, free: np.ndarray, seeds: int, robust: bool):
    """The refinement's EE error (mm, RMS over the workspace) on the plan's analytic corners where
    `arm` puts them: `(noise-free, per seed, RMS over the seeds)`."""
    robot = Robot.load(plan.robot)
    scene = scene_of(robot, plan.camera, plan.target, plan.floor_z)
    trajectory, t, _ = plan_trajectory(plan)
    nominal = robot.model
    theta = ArmMotion(arm, trajectory, nominal.reduction_ratio, nominal, link_inertials(plan.robot)).angles(t)
    q_true = jnp.asarray(theta - np.asarray(nominal.zero_offset))
    pixels = np.asarray(jax.vmap(lambda q: frame_geometry(scene, q).pixels)(q_true))
    problem = corner_problem(scene, jnp.asarray(trajectory(t)), jnp.asarray(t))
    p0 = zero_params(nominal.num_joints, 1)
    configs = jnp.asarray(workspace(robot, scene))

    def ee(cam, corr):
        return np.asarray(tool_points(scene.nominal, scene.T_fixed, scene.T_mount[None], cam, corr, configs))

    base = ee(p0.cam, p0.correction)
    ms = []
    for s in range(-1, seeds):
        noise = 0.0 if s < 0 else sigma_px * np.random.default_rng(s).standard_normal(pixels.shape)
        pr = eqx.tree_at(lambda pp: pp.data.pixels, problem, jnp.asarray(pixels + noise))
        r = refine(pr, p0, free, robust=REFINE_ROBUST if robust else None)
        e = ee(r.params.cam, r.params.correction) - base
        ms.append(float(np.mean(np.sum(e**2, axis=-1))))
    per = [1e3 * np.sqrt(v) for v in ms[1:]]
    return 1e3 * np.sqrt(ms[0]), per, float(1e3 * np.sqrt(np.mean(ms[1:]))) if per else None


def checks(plans: dict, seeds: int) -> dict:
    """Part 3: prediction against the refinement on analytic corners, ideal and realistic arms."""
    out = {}
    for pname, p in plans.items():
        for arm in (
            a for a in ARM_PRESETS if ARM_PRESETS[a].dynamics is None
        ):  # analytic corners: ArmMotion's arms
            ev = jaxcal.evaluate_plan(
                p, camera_model=PRESETS["global-shutter"].noise_record(), arm=ARM_PRESETS[arm].figures()
            )
            for robust in (False, True):
                free_mm, per, rms = measured(p, ARM_PRESETS[arm], ev.sigma_px, ev.free, seeds, robust)
                row = {
                    "frames": ev.frames,
                    "predicted_noise_mm": 1e3 * ev.ee_rms,
                    "predicted_bias_mm": 1e3 * ev.ee_bias_rms,
                    "predicted_total_mm": 1e3 * ev.ee_total_rms,
                    "measured_noise_free_mm": free_mm,
                    "measured_per_seed_mm": per,
                    "measured_rms_mm": rms,
                    "measured_over_predicted": None if rms is None else rms / (1e3 * ev.ee_total_rms),
                }
                key = f"{pname} | {arm} | {'robust' if robust else 'plain'}"
                out[key] = row
                print(key, row, flush=True)
    return out


def small_plan(poses: int = 24) -> CapturePlan:
    """`tests/test_plan_realism.py`'s plan: feasible draws within 45 deg of the UR5e's zero."""
    robot = Robot.load("ur5e")
    camera, target = default_layout(robot.model, np.zeros(6))
    scene = scene_of(robot, camera, target, -0.6)
    q, _ = candidate_poses(
        scene, FeasibilityLimits(), np.zeros(6), 3 * poses, np.radians(45.0), jax.random.key(1)
    )
    return CapturePlan(
        "ur5e", tuple(robot.model.joint_names), camera, target, np.zeros(6), (PoseSet(q[:poses]),), -0.6
    )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--plan", type=Path, help="a planned capture (jaxcal plan --out) to predict and check"
    )
    parser.add_argument("--json", required=True, type=Path, help="write the figures here")
    parser.add_argument("--seeds", type=int, default=4, help="noise draws of each analytic check")
    parser.add_argument(
        "--noise-step", type=int, default=6, help="every this many frames of data/ur5e_sweeps"
    )
    parser.add_argument("--noise-draws", type=int, default=8, help="noise draws per image")
    parser.add_argument("--poses", type=int, default=24, help="poses of the small plan")
    parser.add_argument("--no-sweeps", action="store_true", help="leave out the two sweep designs")
    args = parser.parse_args(argv)
    t0, c0 = time.perf_counter(), time.process_time()
    designs = {} if args.plan is None else {"plan": load_plan(args.plan)}
    if not args.no_sweeps:
        designs |= {
            "demo_sweeps": sweep_plan("ur5e"),
            "ur5e_sweeps_800x600": sweep_plan(
                "ur5e", frames_per_joint=24, range_deg=80, resolution=(800, 600)
            ),
        }
    plans = {f"small_{args.poses}": small_plan(args.poses)} | (
        {} if args.plan is None else {"plan": designs["plan"]}
    )
    out = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, CPU only",
        "plan": None if args.plan is None else str(args.plan),
        "corner_noise": corner_noise(args.noise_step, args.noise_draws),
        "predictions": predictions(designs),
        "checks": checks(plans, args.seeds),
    }
    out["wall_s"], out["cpu_s"] = time.perf_counter() - t0, time.process_time() - c0
    args.json.write_text(json.dumps(out, indent=1))
    print(f"wrote {args.json} ({out['cpu_s']:.0f} s CPU)")


if __name__ == "__main__":
    main()
