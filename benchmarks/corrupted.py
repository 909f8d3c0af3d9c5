"""Robustness to corrupted frames: 10 % of the images sheared about the plate, against the clean capture.

Per seed: render a UR5e sweep capture (`jaxcal simulate`), copy it and warp
10 % of its images (chosen at random) by an 8 % shear about the plate's
centre (the plate still decodes, its corners move by up to ~10 px: a bent or
smeared plate, a rolling-shutter wobble), calibrate both, and compare the
end-effector error against the truth, two-stage and refined.

    python benchmarks/corrupted.py --seeds 0 1 2 --json results/corrupted.json [--workdir DIR]

With `--workdir`, the rendered captures (`clean<seed>`, `bad<seed>`) are kept
there and reused by later runs (rendering is deterministic per seed).

Acceptance (issue 13): corrupted / clean EE RMS at most 1.5 in both stages.
"""

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

import jaxcal
from jaxcal.io._files import write_text_atomic
from jaxcal.sim.faults import shear_copy
from jaxcal.sim.simulate import SimConfig, simulate


def ee(result) -> dict:
    v = result.validation
    return {
        "two_stage_mm": v["ee_rms_mm_two_stage"],
        "refined_mm": v["ee_rms_mm_after"],
        "status": result.status,
        "notes": [w for w in result.warnings if "left out" in w or "outlier" in w],
    }


def sheared_images(clean: Path, bad: Path) -> list[str]:
    """The images of `bad` that differ from `clean` (a reused work folder)."""
    files = [line.split(",")[3] for line in (clean / "frames.csv").read_text().splitlines()[1:]]
    return sorted(f for f in files if (clean / f).read_bytes() != (bad / f).read_bytes())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--fraction", type=float, default=0.1)
    parser.add_argument("--shear", type=float, default=0.08)
    parser.add_argument("--resolution", default="800x600")
    parser.add_argument("--frames-per-joint", type=int, default=24)
    parser.add_argument("--json", help="write the figures here")
    parser.add_argument(
        "--workdir", help="keep the rendered captures here and reuse them (default: a temporary folder)"
    )
    args = parser.parse_args(argv)
    w, h = (int(x) for x in args.resolution.split("x"))
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        tmp = Path(args.workdir or scratch)
        tmp.mkdir(parents=True, exist_ok=True)
        for seed in args.seeds:
            config = SimConfig(
                robot="ur5e", seed=seed, resolution=(w, h), frames_per_joint=args.frames_per_joint,
                range_deg=80.0, clock_offset_ms=40.0, clock_known=False, grayscale=True,
            )  # fmt: skip
            clean, bad = tmp / f"clean{seed}", tmp / f"bad{seed}"
            if not (clean / "truth.json").exists():
                clean = simulate(config, clean, progress=False)
            if (bad / "truth.json").exists():
                sheared = sheared_images(clean, bad)
            else:
                sheared = shear_copy(clean, bad, fraction=args.fraction, shear=args.shear, seed=seed)
            a = ee(jaxcal.calibrate(clean, progress=False))
            b = ee(jaxcal.calibrate(bad, progress=False))
            row = {
                "seed": seed,
                "sheared_images": len(sheared),
                "clean": a,
                "corrupted": b,
                "ratio_two_stage": b["two_stage_mm"] / a["two_stage_mm"],
                "ratio_refined": b["refined_mm"] / a["refined_mm"],
            }
            print(json.dumps(row), flush=True)
            rows.append(row)
    out = {
        "fraction": args.fraction,
        "shear": args.shear,
        "resolution": args.resolution,
        "seeds": rows,
        "max_ratio_two_stage": max(r["ratio_two_stage"] for r in rows),
        "max_ratio_refined": max(r["ratio_refined"] for r in rows),
        "mean_ratio_two_stage": float(np.mean([r["ratio_two_stage"] for r in rows])),
        "mean_ratio_refined": float(np.mean([r["ratio_refined"] for r in rows])),
    }
    print(json.dumps({k: v for k, v in out.items() if k != "seeds"}, indent=2))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(Path(args.json), json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
