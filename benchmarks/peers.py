"""Benchmark: jaxcal side by side with FIGAROH and robotkinecal on the real UR5 tracker data (issue 53).

Each tool calibrates the UR5 on `data/ur5_tracker/grid` (1000 laser-tracker poses, the tracker
registered to the robot's base) and predicts the 20 held-out poses of `data/ur5_tracker/test`,
each through its documented workflow and in its own virtual environment, never a dependency of
jaxcal or of its tests:

- jaxcal: its command line, `jaxcal calibrate data/ur5_tracker/grid --device-is-base --out DIR`
  then `jaxcal verify DIR data/ur5_tracker/test --json OUT`, in this interpreter.
- FIGAROH (PyPI `figaroh`, on Pinocchio): a `BaseCalibration` subclass with its unified YAML
  configuration, `calibration_level: full_params` (every joint placement's geometric errors,
  identifiable ones by its QR selection, Levenberg-Marquardt with outlier removal), position-only
  measurements of the tracker's reflector, the base frame given (`known_baseframe`) and the
  reflector's point on the flange estimated; residuals are predicted minus measured points.
- robotkinecal (PyPI `robotkinecal`, on the Robotics Toolbox, NumPy < 2): `SerialRobotKineCal`
  on the URDF with point observations (product-of-exponentials, adjoint error model), its random
  joint bases seeded.

FIGAROH and robotkinecal read the same URDF of the nominal robot, written here from
`robot_dh.json` (standard DH, one revolute joint per row) with the reflector as a fixed link
`smr` on the flange at the metadata's `T_link_point_nominal`. Their scripts (`PEERS`) are
written into their environments and run there.

The JSON holds one entry per tool, `jaxcal`, `figaroh` and `robotkinecal`; a peer whose
environment is missing or whose run failed is `null`, with the reason in `reasons`. Each entry:

- `test_mean_mm`, `test_rms_mm`, `test_max_mm`: the distance between measured and predicted
  held-out points after calibrating on the grid; `test_errors_mm` per test pose.
- `fit_s`: the solver call alone (jaxcal: its compiled point fit, `jaxcal.stages._points._fit`,
  warm, in one process; FIGAROH: `solve()`; robotkinecal: `solve()`), the median of `--repeats`;
  `fit_runs_s` each of them.
- `whole_run_cold_s`, `whole_run_warm_s`: what a user waits for, fresh processes that load the
  data, calibrate and predict the test poses (jaxcal: `calibrate` plus `verify`); cold is the
  first run (jaxcal with an empty compilation cache of this benchmark's own, unless `--cache`),
  warm the median of the next `--repeats`; `whole_runs_s` all of them.
- `versions`: the tool's version and those of the libraries it stands on.

jaxcal's entry also has `timings_s` (the in-process stages of its median warm `calibrate`,
from `result.json`), `cv_mean_mm` (its 5-fold cross-validation on the grid) and
`free_parameters`; the peers' have `parameters` (FIGAROH's estimated parameters) or
`iterations` (robotkinecal's). `repeats`, `machine` and `date` describe the run.

`--setup` creates the missing environments in `--envs` (default `~/.cache/jaxcal-peers`) with
`python -m venv` and pip (it needs the network; the test suite never passes it).

    python benchmarks/peers.py --json results/peers.json [--repeats 3] [--setup] [--envs DIR] [--cache DIR]
"""

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from real_tracker import POINT_FIT_SETUP  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
GRID = ROOT / "data" / "ur5_tracker" / "grid"
TEST = ROOT / "data" / "ur5_tracker" / "test"
ENVS = Path.home() / ".cache" / "jaxcal-peers"

#: Left out of every tool's environment: a user's Python keeps its bytecode (`__pycache__`), and a
#: machine set up not to (as CI machines often are) would count compiling each tool's sources into
#: every run.
NO_BYTECODE = "PYTHONDONTWRITEBYTECODE"
#: What each peer's environment installs, and the distributions whose versions it reports.
REQUIREMENTS = {
    "figaroh": (["figaroh==1.0.2"], ["figaroh", "pin", "numpy", "scipy"]),
    "robotkinecal": (["robotkinecal==0.1.0"], ["robotkinecal", "roboticstoolbox-python", "numpy"]),
}

#: The part every peer script shares: arguments, the samples' CSV, the printed result.
COMMON = """
import csv, json, sys, time
from importlib.metadata import version
import numpy as np

URDF, GRID, TEST, WORK = sys.argv[1:5]
JOINTS = json.loads(sys.argv[5])

def load(path):
    rows = list(csv.DictReader(open(path)))
    q = np.array([[float(r[j]) for j in JOINTS] for r in rows])
    return q, np.array([[float(r[c]) for c in "xyz"] for r in rows])

def report(fit_s, predicted, yt, **extra):
    errors = 1e3 * np.linalg.norm(predicted - yt, axis=1)
    versions = {name: version(name) for name in json.loads(sys.argv[6])}
    print(json.dumps({"fit_s": fit_s, "test_errors_mm": errors.tolist(), "versions": versions, **extra}))

qg, yg = load(GRID)
qt, yt = load(TEST)
"""

#: The peers' own scripts (after `COMMON`).
PEERS = {
    "figaroh": """
from figaroh.calibration import BaseCalibration
from figaroh.calibration.calibration_tools import calc_updated_fkm
from figaroh.tools.load_robot import load_robot

CONFIG = '''
robot:
  name: ur5
  properties:
    joints:
      active_joints: %s
tasks:
  calibration:
    enabled: true
    parameters:
      calibration_level: full_params
      outlier_threshold: 0.02
    kinematics:
      base_frame: universe
      tool_frame: smr
    measurements:
      markers:
        - name: smr
          reference_joint: wrist_3_joint
          measurable_dof: [true, true, true, false, false, false]
          sensor_type: laser_tracker
      poses:
        base_pose: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        tool_pose: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    data:
      source_file: %s/grid.csv
      number_of_samples: %d
'''

class UR5Calibration(BaseCalibration):
    def cost_function(self, var):
        estimated = calc_updated_fkm(self.model, self.data, var, self.q_measured, self.calib_config)
        return estimated - self.PEE_measured  # positions only: the world-frame log-map residual

with open(f"{WORK}/grid.csv", "w", newline="") as f:  # FIGAROH's layout: x1, y1, z1, joints
    csv.writer(f).writerows([["x1", "y1", "z1", *JOINTS], *np.hstack([yg, qg]).tolist()])
open(f"{WORK}/ur5.yaml", "w").write(CONFIG % (json.dumps(JOINTS), WORK, len(qg)))
cal = UR5Calibration(load_robot(URDF, load_by_urdf=True), f"{WORK}/ur5.yaml")
cal.calib_config["known_baseframe"] = True  # the tracker is registered to the base
cal.calib_config["known_tipframe"] = False  # the reflector's point on the flange is estimated
cal.initialize()
t0 = time.perf_counter()
cal.solve(enable_logging=False)
fit_s = time.perf_counter() - t0
var = cal.LM_result.x
predicted = calc_updated_fkm(cal.model, cal.data, var, qt, dict(cal.calib_config, NbSample=len(qt)))
report(fit_s, predicted.reshape(3, -1).T, yt, parameters=len(var))
""",
    "robotkinecal": """
import roboticstoolbox as rtb
from robotkinecal import SerialRobotKineCal

np.random.seed(0)  # robotkinecal draws each joint's error basis at random
cal = SerialRobotKineCal(rtb.ERobot.URDF(URDF), ee_name="smr")
cal.set_observations(list(qg), list(yg))
t0 = time.perf_counter()
result = cal.solve()
fit_s = time.perf_counter() - t0
predicted = np.array([cal.forward_kinematics(cal.N_JOINTS + 1, q).t for q in qt])
report(fit_s, predicted, yt, iterations=result.nb_iterations_executed)
""",
}

#: jaxcal's point fit timed in one process (as benchmarks/real_tracker.py does): a first call
#: compiles, the next `repeats` are timed.
JAXCAL_FIT = (
    POINT_FIT_SETUP
    + """
jax.block_until_ready(_fit(problem, cand, 1e-3, scale))
runs = []
for _ in range(int(sys.argv[2])):
    t0 = time.perf_counter()
    jax.block_until_ready(_fit(problem, cand, 1e-3, scale))
    runs.append(time.perf_counter() - t0)
print(json.dumps(runs))
"""
)


def _row(a: float, alpha: float, d: float, theta: float) -> tuple:
    """A standard DH row's fixed part `Rz(theta) Tz(d) Tx(a) Rx(alpha)` as a URDF origin (xyz, rpy)."""
    return (a * np.cos(theta), a * np.sin(theta), d, alpha, 0.0, theta)


def ur5_urdf(dh: dict, point: list[float]) -> str:
    """A URDF of the nominal robot from its standard DH table (`T_i = Rz(theta_i + q_i) Tz(d_i) Tx(a_i)
    Rx(alpha_i)`: joint i+1's origin is row i's fixed part), the table's flange row after the last and the
    tracker's reflector as a fixed link `smr` at `point` (m) in the flange frame."""

    def joint(name, kind, parent, child, origin, extra=""):
        x, y, z, roll, pitch, yaw = (float(v) for v in origin)
        return (
            f'  <joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
            f'<origin xyz="{x!r} {y!r} {z!r}" rpy="{roll!r} {pitch!r} {yaw!r}"/>{extra}</joint>'
        )

    lines = ['<?xml version="1.0"?>', f'<robot name="{dh["robot"]}">', f'  <link name="{dh["base_link"]}"/>']
    parent, origin = dh["base_link"], (0.0,) * 6
    for i, name in enumerate(dh["joint_names"]):
        child = f"link{i + 1}"
        limit = (
            f'<axis xyz="0 0 1"/><limit lower="{dh["lower"][i]!r}" upper="{dh["upper"][i]!r}" effort="100" '
            f'velocity="{dh["velocity"][i]!r}"/>'
        )
        lines += [f'  <link name="{child}"/>', joint(name, "revolute", parent, child, origin, limit)]
        origin = _row(*(dh[k][i] for k in ("a", "alpha", "d", "theta")))
        parent = child
    f = dh["flange"]
    lines += [
        '  <link name="frame6"/>',
        joint("frame6_joint", "fixed", parent, "frame6", origin),
        f'  <link name="{dh["flange_link"]}"/>',
        joint(
            "flange_joint", "fixed", "frame6", dh["flange_link"], _row(f["a"], f["alpha"], f["d"], f["theta"])
        ),
        '  <link name="smr"/>',
        joint("smr_joint", "fixed", dh["flange_link"], "smr", (*point, 0.0, 0.0, 0.0)),
        "</robot>",
    ]
    return "\n".join(lines) + "\n"


def _errors(errors_mm: list[float]) -> dict:
    e = np.asarray(errors_mm)
    return {
        "test_mean_mm": float(e.mean()),
        "test_rms_mm": float(np.sqrt(np.mean(e**2))),
        "test_max_mm": float(e.max()),
        "test_errors_mm": e.tolist(),
    }


def _whole(runs: list[float]) -> dict:
    return {
        "whole_run_cold_s": runs[0],
        "whole_run_warm_s": statistics.median(runs[1:]),
        "whole_runs_s": runs,
    }


def _env_python(envs: Path, name: str) -> Path:
    return envs / name / "bin" / "python"


def setup(envs: Path) -> None:
    """Create each missing peer environment: `python -m venv`, then pip."""
    for name, (requirements, _) in REQUIREMENTS.items():
        python = _env_python(envs, name)
        if python.exists():
            continue
        print(f"{name}: creating {envs / name}", flush=True)
        subprocess.run([sys.executable, "-m", "venv", "--clear", str(envs / name)], check=True)
        subprocess.run([str(python), "-m", "pip", "install", "--quiet", *requirements], check=True)


def peer(name: str, envs: Path, work: Path, repeats: int) -> tuple[dict | None, str | None]:
    """One peer's figures from 1 + `repeats` fresh runs in its environment, or None and why."""
    python = _env_python(envs, name)
    if not python.exists():
        return None, f"no environment at {envs / name} (create it with --setup)"
    script = envs / name / "jaxcal_peer_run.py"
    script.write_text(COMMON + PEERS[name])
    dh = json.loads((GRID / "robot_dh.json").read_text())
    (work / name).mkdir()
    cmd = [
        str(python),
        str(script),
        str(work / "ur5.urdf"),
        str(GRID / "samples.csv"),
        str(TEST / "samples.csv"),
        str(work / name),
        json.dumps(dh["joint_names"]),
        json.dumps(REQUIREMENTS[name][1]),
    ]
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", NO_BYTECODE)}
    walls, outs = [], []
    for _ in range(1 + repeats):
        t0 = time.perf_counter()
        p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=work / name)
        walls.append(time.perf_counter() - t0)
        if p.returncode != 0:
            return None, f"its run exited {p.returncode}: {p.stderr.strip()[-1500:]}"
        outs.append(json.loads(p.stdout.strip().splitlines()[-1]))
    fits = [o["fit_s"] for o in outs[1:]]
    extra = {k: v for k, v in outs[0].items() if k not in ("fit_s", "test_errors_mm", "versions")}
    out = {**_errors(outs[0]["test_errors_mm"]), "fit_s": statistics.median(fits), "fit_runs_s": fits}
    return {**out, **_whole(walls), "versions": outs[0]["versions"], **extra}, None


def jaxcal_figures(work: Path, repeats: int, cache: str | None) -> dict:
    """jaxcal's CLI runs (the first cold, with an empty cache of this benchmark's own) and its fit time."""
    from importlib.metadata import version

    env = {**os.environ, "XDG_CACHE_HOME": str(work / "cache")}
    for var in ("JAX_COMPILATION_CACHE_DIR", "JAXCAL_NO_CACHE", NO_BYTECODE):
        env.pop(var, None)
    if cache:
        env["JAX_COMPILATION_CACHE_DIR"] = cache
    jaxcal = [sys.executable, "-m", "jaxcal"]
    walls, timings = [], []
    for k in range(1 + repeats):
        out, verdict = work / f"jaxcal{k}", work / f"jaxcal{k}_verify.json"
        t0 = time.perf_counter()
        calibrate = [*jaxcal, "calibrate", str(GRID), "--device-is-base", "--quiet", "--out", str(out)]
        subprocess.run(calibrate, env=env, cwd=ROOT, check=True, capture_output=True)
        verify = [*jaxcal, "verify", str(out), str(TEST), "--json", str(verdict)]
        subprocess.run(verify, env=env, cwd=ROOT, check=True, capture_output=True)
        walls.append(time.perf_counter() - t0)
        timings.append(json.loads((out / "result.json").read_text())["timings_s"])
    doc = json.loads((work / "jaxcal0" / "result.json").read_text())
    kept = next(m for m in doc["point_fit"]["models"] if m["kept"])
    test = json.loads((work / "jaxcal0_verify.json").read_text())
    fit = subprocess.run(
        [sys.executable, "-c", JAXCAL_FIT, str(GRID), str(repeats)],
        env=env, cwd=ROOT, check=True, capture_output=True, text=True,
    )  # fmt: skip
    fits = json.loads(fit.stdout.strip().splitlines()[-1])
    median_warm = sorted(range(1, 1 + repeats), key=walls.__getitem__)[repeats // 2]
    return {
        **_errors([s["error_mm"] for s in test["samples"]]),
        "fit_s": statistics.median(fits),
        "fit_runs_s": fits,
        **_whole(walls),
        "versions": {name: version(name) for name in ("jaxcal", "jax", "numpy")},
        "timings_s": timings[median_warm],
        "cv_mean_mm": kept["cv_mean_mm"],
        "free_parameters": int(sum(doc["point_fit"]["free"])),
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", metavar="OUT", help="also write the JSON here")
    parser.add_argument("--repeats", type=int, default=3, help="warm runs (and timed fits) per tool")
    parser.add_argument("--envs", default=str(ENVS), help=f"the peers' virtual environments (default {ENVS})")
    parser.add_argument("--setup", action="store_true", help=argparse.SUPPRESS)  # needs the network
    parser.add_argument(
        "--cache",
        help="jaxcal's compilation cache (default: a fresh empty one, so that its first run is cold; "
        "the tests give a warm one to check the script runs: whole_run_cold_s is then not cold)",
    )
    args = parser.parse_args(argv)
    envs = Path(args.envs).expanduser()
    if args.setup:
        setup(envs)
    report: dict = {}
    reasons: dict = {}
    with tempfile.TemporaryDirectory(prefix="jaxcal-peers-") as tmp:
        work = Path(tmp)
        meta = json.loads((GRID / "metadata.json").read_text())
        point = np.asarray(meta["device"]["T_link_point_nominal"])[:3, 3].tolist()
        dh = json.loads((GRID / meta["robot"]["table"]).read_text())
        (work / "ur5.urdf").write_text(ur5_urdf(dh, point))
        report["jaxcal"] = jaxcal_figures(work, args.repeats, args.cache)
        for name in PEERS:
            report[name], reason = peer(name, envs, work, args.repeats)
            if reason:
                reasons[name] = reason
    report |= {
        "reasons": reasons,
        "repeats": args.repeats,
        "machine": {
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": sys.version.split()[0],
        },
        "date": time.strftime("%Y-%m-%d"),
    }
    for name in ("jaxcal", *PEERS):
        r = report[name]
        if r is None:
            print(f"{name}: null ({reasons[name][:200]})")
            continue
        print(
            f"{name} {r['versions'][name]}: held-out mean {r['test_mean_mm']:.4f} mm, RMS {r['test_rms_mm']:.4f}, "
            f"max {r['test_max_mm']:.4f}; fit {r['fit_s']:.3f} s; whole run cold {r['whole_run_cold_s']:.1f} s, "
            f"warm {r['whole_run_warm_s']:.1f} s"
        )
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(report, indent=1) + "\n")
    return report


if __name__ == "__main__":
    main()
