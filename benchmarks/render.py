"""Rendering throughput of the synthetic arm (`jaxcal.sim`), frames per second.

The primitive UR5e with its ChArUco plate, posed along a joint sweep, one
fixed camera. jaxcal renders with shadows and reflections off; the peer is
the same scene with MuJoCo's default look (a shadow-casting light, shadows and
reflections on), measured
in the same run. Also the end-to-end `simulate` rate (render + PNG write).

    python benchmarks/render.py --json results/render.json

The JSON holds `frames`, `backend` and, per resolution under `resolutions`,
`jaxcal_fps`, `mujoco_default_fps`, `speedup` and
`simulate_fps_incl_png_and_setup`. Smallest run (the tests'):
`--frames 4 --resolutions 160x120`.
"""

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _fps(scene, camera: str, frames: int, theta) -> float:
    scene.set_angles(theta[0])
    scene.render(camera)  # warm up (context creation, texture upload)
    start = time.perf_counter()
    for k in range(frames):
        scene.set_angles(theta[k % len(theta)])
        scene.render(camera)
    return frames / (time.perf_counter() - start)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60, help="rendered frames per measurement")
    parser.add_argument(
        "--resolutions", nargs="+", default=["640x480", "1280x960"], help="image sizes WxH to measure"
    )
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args(argv)

    from jaxcal.sim import build_scene
    from jaxcal.sim.simulate import SimConfig, draw_truth, nominal_robot, scene_layout, simulate

    results = {"frames": args.frames, "backend": os.environ.get("MUJOCO_GL"), "resolutions": {}}
    for w, h in (tuple(int(v) for v in r.split("x")) for r in args.resolutions):
        config = SimConfig(resolution=(w, h))
        nominal, _ = nominal_robot(config.robot)
        true = draw_truth(nominal, config)
        _, plates, _, cameras = scene_layout(nominal, true, config, np.random.default_rng(0))
        theta = np.zeros((30, nominal.num_joints))
        theta[:, 1] = np.deg2rad(np.linspace(-20, 20, 30))
        with build_scene(true, plates=plates, cameras=cameras, floor_z=-0.6) as scene:
            fps = _fps(scene, "cam0", args.frames, theta)
        with build_scene(true, plates=plates, cameras=cameras, floor_z=-0.6, shadows=True) as scene:
            fps_default = _fps(scene, "cam0", args.frames, theta)
        with tempfile.TemporaryDirectory() as tmp:
            frames_per_joint = max(2, args.frames // nominal.num_joints)
            start = time.perf_counter()
            simulate(
                SimConfig(resolution=(w, h), frames_per_joint=frames_per_joint),
                Path(tmp) / "ds",
                progress=False,
            )
            sim_fps = frames_per_joint * nominal.num_joints / (time.perf_counter() - start)
        results["resolutions"][f"{w}x{h}"] = {
            "jaxcal_fps": fps,
            "mujoco_default_fps": fps_default,
            "speedup": fps / fps_default,
            "simulate_fps_incl_png_and_setup": sim_fps,
        }
    text = json.dumps(results, indent=2)
    print(text)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
