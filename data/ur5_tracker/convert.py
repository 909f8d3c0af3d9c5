"""Convert the UR5 laser-tracker tables in `source/` into jaxcal tracker datasets (see data/README.md).

    .venv/bin/python data/ur5_tracker/convert.py

writes `grid/` (1000 poses, for calibration) and `test/` (20 random poses, for
`verify`) beside this file, replacing the datasets it wrote before. The same as

    .venv/bin/jaxcal import-csv data/ur5_tracker/source/3D_UR5_uncalibrated_grid_cleaned.csv \\
        --robot ur5_dh --out data/ur5_tracker/grid --overwrite \\
        --joint-columns joint_1,joint_2,joint_3,joint_4,joint_5,joint_6 --joint-unit deg \\
        --xyz x_t+x_dif,y_t+y_dif,z_t+z_dif --length-unit mm \\
        --sigma-mm 0.02 --point-mm 0,0.09,31.0 --point-name smr

and again with `3D_UR5_uncalibrated_random_cleaned.csv` into `test`. The
columns: `joint_1..6` the commanded joints (deg); `x_t, y_t, z_t` the nominal
point (the UR5's DH forward kinematics of the commanded joints with the
reflector 31 mm out on the flange; mm, base frame) and `x_dif, y_dif, z_dif`
the measured minus the nominal point (mm), so the measured point is their sum.
The tracker (GTS3800, 15 um + 6 um/m) was registered to the robot's base, so
the device frame is the base frame (`jaxcal calibrate --device-is-base`).
"""

from pathlib import Path

from jaxcal.io.csv_import import import_csv
from jaxcal.robots import ROBOTS_DIR

HERE = Path(__file__).resolve().parent
SOURCE = "Jacobi, P. (2025), github.com/pauljac7700/serial_robots_datasets (MIT licence), commit 759068d"
SETS = {
    "grid": ("3D_UR5_uncalibrated_grid_cleaned.csv", "1000 grid-like poses, for calibration"),
    "test": ("3D_UR5_uncalibrated_random_cleaned.csv", "20 random poses, for testing (verify)"),
}


def main() -> None:
    for name, (csv, what) in SETS.items():
        r = import_csv(
            HERE / "source" / csv,
            HERE / name,
            robot=ROBOTS_DIR / "ur5_dh.json",
            joints=[f"joint_{i}" for i in range(1, 7)],
            joint_unit="deg",
            xyz=["x_t+x_dif", "y_t+y_dif", "z_t+z_dif"],
            length_unit="mm",
            sigma_m=0.02e-3,  # the tracker's 15 um + 6 um/m at about 1 m
            point_m=[0.0, 0.09e-3, 31.0e-3],  # the reflector's centre on the flange
            point_name="smr",
            description=f"UR5 measured by a GTS3800 laser tracker registered to the robot's base (calibrate "
            f"with --device-is-base): {what}. {SOURCE}; see data/README.md",
            overwrite=True,
        )
        print(
            f"{r.path}: {r.samples} samples, {r.rms_from_nominal_m * 1e3:.3f} mm RMS from the nominal robot"
        )


if __name__ == "__main__":
    main()
