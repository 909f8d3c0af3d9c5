"""`jaxcal import-csv CSV`: a table of joint positions and measured points into a tracker dataset
(jaxcal.io.csv_import; docs/dataset.md, "Importing a CSV")."""

import argparse
import math

from .._configkeys import knob
from ..io._csv_poses import ANGLE_UNITS, LENGTH_UNITS, ORIENTATION_FORMATS, POSE_DIRECTIONS
from ..io._tracker import DEVICE_KINDS
from ._common import finite


def _columns(count: int | None):
    """An argparse type: comma-separated column specs (`a,b+c,d`), `count` of them."""

    def parse(text: str) -> list[str]:
        cols = [c.strip() for c in text.split(",")]
        if any(not c for c in cols) or (count is not None and len(cols) != count):
            n = f"{count} " if count else ""
            raise argparse.ArgumentTypeError(f"expected {n}comma-separated column names, got {text!r}")
        return cols

    return parse


def _triple(unit: str):
    """An argparse type: three comma-separated numbers (`x,y,z`) in `unit`."""

    def parse(text: str) -> list[float]:
        try:
            v = [float(x) for x in text.split(",")]
        except ValueError:
            v = []
        if len(v) != 3 or not all(math.isfinite(x) for x in v):
            raise argparse.ArgumentTypeError(f"expected x,y,z ({unit}, finite), got {text!r}")
        return v

    return parse


def add_import_csv_parser(sub) -> None:
    p = sub.add_parser(
        "import-csv",
        help="convert a CSV of joint positions and measured points (laser tracker, motion capture) into a "
        "tracker dataset (docs/dataset.md, 'Importing a CSV')",
    )
    p.add_argument("csv", help="the CSV table: a header line, one row per pose")
    p.add_argument(
        "--robot",
        required=True,
        help="URDF or DH/MDH table file, or a shipped name (ur5e, ur5_dh, ur10e: data/robots)",
    )
    p.add_argument("--out", required=True, help="dataset directory (absent or empty)")
    p.add_argument("--overwrite", action="store_true", help="replace a dataset jaxcal wrote")
    p.add_argument(
        "--joint-columns",
        required=True,
        type=_columns(None),
        help="the joint position columns, one per robot joint in the robot's order (COL,COL,...)",
    )
    p.add_argument(
        "--joint-unit", required=True, choices=sorted(ANGLE_UNITS), help="unit of the joint columns"
    )
    p.add_argument(
        "--xyz",
        required=True,
        type=_columns(None),
        help="the measured point's x,y,z columns in the device frame; a column may be a sum (x_t+x_dif); "
        "for a tree (several --link), x,y,z of each link's point in turn",
    )
    p.add_argument(
        "--length-unit",
        required=True,
        choices=sorted(LENGTH_UNITS),
        help="unit of the x,y,z (and prismatic) columns",
    )
    p.add_argument("--sigma-mm", required=True, type=finite, help="position noise, 1-sigma per axis (mm)")
    p.add_argument(
        "--point-mm", type=_triple("mm"), help="the point's offset on --link, x,y,z (mm; default unknown)"
    )
    knob(
        p,
        "--point-rotvec-deg",
        type=_triple("deg"),
        help="the point frame's rotation on --link, a rotation vector x,y,z (deg; with --point-mm; default "
        "none), e.g. 0,0,90 for a camera turned a quarter turn about its axis",
    )
    p.add_argument(
        "--orientation-columns",
        type=_columns(None),
        help="the orientation's columns, as many as --orientation-format has (a full pose per row)",
    )
    p.add_argument(
        "--orientation-format",
        choices=sorted(ORIENTATION_FORMATS),
        help="with --orientation-columns: quat-xyzw or quat-wxyz (a unit quaternion, scalar last or first), rotvec-rad "
        "or rotvec-deg (a rotation vector), matrix (9 columns, row by row: r11,r12,...,r33)",
    )
    p.add_argument(
        "--pose-direction",
        choices=POSE_DIRECTIONS,
        help="with --orientation-columns: each row is the point's pose in the device frame (a 6-DoF probe, a mocap "
        "body, a flange camera's pose in the board's frame), or the device's in the point's (PnP's board "
        "pose in the camera frame; inverted on import)",
    )
    p.add_argument(
        "--sigma-deg",
        type=finite,
        help="orientation noise, 1-sigma per axis (deg; required with --orientation-columns)",
    )
    knob(p, "--time", help="a timestamp column (s, strictly increasing; default: the row index)")
    knob(p, "--device-name", default="tracker", help="the device's name (names its frame)")
    knob(p, "--device-kind", default="laser_tracker", choices=DEVICE_KINDS)
    p.add_argument("--point-name", default="point", help="the measured point's name (smr, probe)")
    p.add_argument(
        "--link",
        help="the link the point rides on (default: the robot's flange); several, comma-separated, for a robot "
        "that is a tree measured on several links at once (a tree dataset, docs/trees.md)",
    )
    knob(p, "--description", help="the dataset's description")
    p.set_defaults(func=cmd_import_csv)


def _import_tree(args) -> int:
    """`import-csv --link A,B ...`: a tree dataset (`jaxcal.io.tree_dataset.import_tree_csv`)."""
    chain_only = {
        "--orientation-columns": args.orientation_columns,
        "--point-mm": args.point_mm,
        "--point-rotvec-deg": args.point_rotvec_deg,
        "--time": args.time,
    }
    given = [k for k, v in chain_only.items() if v is not None]
    if given:
        raise ValueError(f"{', '.join(given)}: not options of a tree's import (several --link)")
    from ..io._files import check_output_dir
    from ..robots import robot_file

    robot = robot_file(args.robot)
    check_output_dir(
        args.out, inputs=[args.csv, robot], overwrite=args.overwrite, kind="dataset", what="--out"
    )
    print(f"importing {args.csv} into {args.out} (a tree dataset) ...", flush=True)
    from ..io.tree_dataset import IMPORT_FAR_M, import_tree_csv  # JAX: after the options are checked

    links = [s.strip() for s in args.link.split(",")]
    units = {"joint_unit": args.joint_unit, "length_unit": args.length_unit, "sigma_m": 1e-3 * args.sigma_mm}
    folder, rows, rms = import_tree_csv(
        args.csv,
        args.out,
        robot=robot,
        links=links,
        joints=args.joint_columns,
        xyz=args.xyz,
        overwrite=args.overwrite,
        **units,
    )
    print(
        f"wrote {folder}: {rows} rows of {', '.join(links)}; after the best rigid alignment the points lie "
        f"{1e3 * rms:.3g} mm RMS from the robot file's link origins"
    )
    if rms > IMPORT_FAR_M:
        print(
            f"warning: over {1e3 * IMPORT_FAR_M:g} mm: check the columns (--xyz in link order), --length-unit and "
            "--joint-unit before calibrating"
        )
    return 0


def cmd_import_csv(args) -> int:
    if args.link and "," in args.link:
        return _import_tree(args)
    if len(args.xyz) != 3:
        raise ValueError(f"--xyz: expected 3 comma-separated column names (x,y,z), got {len(args.xyz)}")
    if args.orientation_columns:
        missing = [
            o
            for o, v in (
                ("--orientation-format", args.orientation_format),
                ("--pose-direction", args.pose_direction),
                ("--sigma-deg", args.sigma_deg),
            )
            if v is None
        ]
        if missing:
            raise ValueError(
                f"--orientation-columns needs {', '.join(missing)} (no defaults: state the convention)"
            )
    elif args.orientation_format or args.pose_direction:
        raise ValueError(
            "--orientation-format and --pose-direction describe --orientation-columns: none given"
        )
    print(f"importing {args.csv} into {args.out} ...", flush=True)
    from ..io.csv_import import import_csv  # JAX (the robot's kinematics): after the options are checked
    from ..robots import robot_file

    r = import_csv(
        args.csv,
        args.out,
        robot=robot_file(args.robot),
        joints=args.joint_columns,
        joint_unit=args.joint_unit,
        xyz=args.xyz,
        length_unit=args.length_unit,
        sigma_m=args.sigma_mm * 1e-3,
        point_m=None if args.point_mm is None else [v * 1e-3 for v in args.point_mm],
        point_rotvec_rad=None
        if args.point_rotvec_deg is None
        else [math.radians(v) for v in args.point_rotvec_deg],
        orientation=args.orientation_columns,
        orientation_format=args.orientation_format,
        pose_direction=args.pose_direction,
        sigma_rad=None if args.sigma_deg is None else math.radians(args.sigma_deg),
        time=args.time,
        device_name=args.device_name,
        device_kind=args.device_kind,
        point_name=args.point_name,
        link=args.link,
        description=args.description,
        overwrite=args.overwrite,
    )
    print(
        f"wrote {r.path}: {r.samples} samples; after the best rigid alignment the points lie "
        f"{r.rms_from_nominal_m * 1e3:.3g} mm RMS from the nominal robot's (reach {r.reach_m:.3g} m)"
    )
    for note in r.notes:
        print(f"note: {note}")
    for warning in r.warnings:
        print(f"warning: {warning}")
    return 0
