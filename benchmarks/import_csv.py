"""`jaxcal import-csv` of a large table: wall time and peak memory (issue 49; target 10^6 rows in
at most 30 s and 1 GiB).

The table is the UR5 tracker's format (`data/ur5_tracker/source/`): `step_order`, the nominal
point `x_t, y_t, z_t` (mm; the UR5's DH forward kinematics, NumPy, with the reflector 31 mm out
on the flange), the measured-minus-nominal `x_dif, y_dif, z_dif` (an arm whose upper arm is
2 mm long, whose wrist is 1 mm off and whose shoulder's zero is 0.05 deg off, plus 0.02 mm
noise), and the joints `joint_1..6` (deg, uniform over +-170 deg), seeded; written once into
`--workdir`. The import runs as a user runs it, `jaxcal import-csv` in a fresh process
(the command of `data/ur5_tracker/convert.py`), and is timed from the shell; its peak resident
memory is the child's `ru_maxrss`.

    python benchmarks/import_csv.py --rows 1000000 --json results/import_csv.json

JSON: `rows`, `csv_mib` (the table's size), `seconds` (the command's wall time), `cpu_s` (user +
system), `peak_rss_mib`, `load` (the 1-minute load average before the run), `command`, `machine`.
"""

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: The UR5's DH table (data/robots/ur5_dh.json): a, alpha, d per joint (m, rad); the reflector (m).
A = (0.0, -0.425, -0.39225, 0.0, 0.0, 0.0)
ALPHA = (np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0)
D = (0.089159, 0.0, 0.0, 0.10915, 0.09465, 0.0823)
POINT_M = (0.0, 0.09e-3, 31.0e-3)


def ur5_points(q: np.ndarray, a=A, d=D, offset=(0.0,) * 6) -> np.ndarray:
    """The reflector in the base frame (m) for joints `q` (N, 6) rad: T_i = Rz(q_i + offset_i)
    Tz(d_i) Tx(a_i) Rx(alpha_i)."""
    n = len(q)
    T = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    for i in range(6):
        c, s = np.cos(q[:, i] + offset[i]), np.sin(q[:, i] + offset[i])
        ca, sa = np.cos(ALPHA[i]), np.sin(ALPHA[i])
        Ti = np.zeros((n, 4, 4))
        Ti[:, 0] = np.stack([c, -s * ca, s * sa, a[i] * c], -1)
        Ti[:, 1] = np.stack([s, c * ca, -c * sa, a[i] * s], -1)
        Ti[:, 2] = np.array([0.0, sa, ca, d[i]])
        Ti[:, 3, 3] = 1.0
        T = T @ Ti
    return T[:, :3, 3] + T[:, :3, :3] @ np.asarray(POINT_M)


def write_table(path: Path, rows: int, seed: int = 0, chunk: int = 100_000) -> None:
    rng = np.random.default_rng(seed)
    with open(path, "w") as f:
        f.write("step_order,x_t,y_t,z_t,x_dif,y_dif,z_dif,joint_1,joint_2,joint_3,joint_4,joint_5,joint_6\n")
        for start in range(0, rows, chunk):
            n = min(chunk, rows - start)
            q = np.radians(rng.uniform(-170.0, 170.0, (n, 6)))
            nominal = 1e3 * ur5_points(q)
            a, d = np.add(A, (0, -0.002, 0, 0, 0, 0)), np.add(D, (0, 0, 0, 0.001, 0, 0))
            measured = 1e3 * ur5_points(q, a, d, (0, np.radians(0.05), 0, 0, 0, 0))
            dif = measured - nominal + 0.02 * rng.standard_normal((n, 3))
            table = np.column_stack([np.arange(start, start + n), nominal, dif, np.degrees(q)])
            np.savetxt(f, table, delimiter=",", fmt=["%d"] + ["%.10g"] * 12)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=1_000_000)
    ap.add_argument("--workdir", help="where the table and the dataset go (default: a temporary folder)")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="jaxcal-import-csv-") as tmp:
        work = Path(args.workdir or tmp)
        work.mkdir(parents=True, exist_ok=True)
        table = work / f"ur5_{args.rows}.csv"
        if not table.exists():
            write_table(table, args.rows)
        command = [
            sys.executable, "-m", "jaxcal", "import-csv", str(table), "--robot", "ur5_dh",
            "--out", str(work / "dataset"), "--overwrite",
            "--joint-columns", "joint_1,joint_2,joint_3,joint_4,joint_5,joint_6", "--joint-unit", "deg",
            "--xyz", "x_t+x_dif,y_t+y_dif,z_t+z_dif", "--length-unit", "mm",
            "--sigma-mm", "0.02", "--point-mm", "0,0.09,31.0", "--point-name", "smr",
        ]  # fmt: skip
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        load = os.getloadavg()[0]
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        proc = subprocess.run(command, env=env, capture_output=True, text=True)
        seconds = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if proc.returncode != 0:
            sys.exit(f"jaxcal import-csv failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
        out = {
            "rows": args.rows,
            "csv_mib": table.stat().st_size / 2**20,
            "seconds": seconds,
            "cpu_s": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
            "peak_rss_mib": after.ru_maxrss / 1024,
            "load": load,
            "command": " ".join(["jaxcal", *command[3:]]),
            "stdout": proc.stdout.strip().splitlines()[:3],
            "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
        }
    print(json.dumps(out, indent=1))
    if args.json:
        from jaxcal.io._files import write_text_atomic

        write_text_atomic(Path(args.json), json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
