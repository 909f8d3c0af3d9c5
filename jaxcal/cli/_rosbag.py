"""`jaxcal import-bag` and the bag options of `jaxcal calibrate BAG`: ROS bags in (jaxcal.io.rosbag)."""

import argparse
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

from .. import _interrupt
from .._configkeys import knob
from ..errors import BagError, JaxcalError
from ..io._rosmsgs import SegmentOptions
from ._common import finite


def add_bag_args(p: argparse.ArgumentParser, *, required: bool) -> None:
    """The topics, robot and target of a bag (required for `import-bag`; for `calibrate` when DATASET is a bag)."""
    need = " (required)" if required else " (required when DATASET is a ROS bag)"
    p.add_argument(
        "--images", required=required, help="image topic: sensor_msgs/Image or CompressedImage" + need
    )
    p.add_argument("--joints", required=required, help="sensor_msgs/JointState topic" + need)
    p.add_argument(
        "--camera-info", help="sensor_msgs/CameraInfo topic (default: none, K null: self-calibration)"
    )
    p.add_argument(
        "--robot", required=required, help="the robot's URDF file, or its DH/MDH table (.json/.yaml)" + need
    )
    p.add_argument(
        "--target",
        required=required,
        help="JSON file: the target(s) as metadata.json's 'targets' (docs/dataset.md)" + need,
    )
    knob(p, "--camera-name", default="cam0", help="the camera's name in the dataset")
    knob(p, "--camera-mount", default="world", help="'world' (eye-to-hand) or the flange link (eye-in-hand)")
    knob(p, "--base-link", help="the chain's base link (default: the URDF's root)")
    knob(p, "--flange-link", help="the chain's flange link (default: the URDF's one leaf)")
    knob(
        p,
        "--velocity-threshold",
        type=finite,
        default=SegmentOptions.velocity_threshold,
        help="a joint moves above this speed (rad/s): motion segments from the joint log",
    )


def _import(args, bag, out, *, overwrite: bool):
    missing = [
        f"--{k.replace('_', '-')}" for k in ("images", "joints", "robot", "target") if not getattr(args, k)
    ]
    if missing:
        raise BagError(f"{bag} is a ROS bag: give {', '.join(missing)}")
    from ..io.rosbag import import_bag

    return import_bag(
        bag,
        out,
        images=args.images,
        joints=args.joints,
        camera_info=args.camera_info,
        robot=args.robot,
        targets=args.target,
        camera=args.camera_name,
        mount=args.camera_mount,
        base_link=args.base_link,
        flange_link=args.flange_link,
        segments=SegmentOptions(velocity_threshold=args.velocity_threshold),
        overwrite=overwrite,
    )


def cmd_import_bag(args) -> int:
    print(f"importing {args.bag} into {args.out} ...", flush=True)
    r = _import(args, args.bag, args.out, overwrite=args.overwrite)
    print(f"wrote {r.path}: {r.frames} images, {r.joint_samples} joint states (stamps from {r.epoch_ns} ns)")
    for note in r.notes:
        print(f"note: {note}")
    return 0


@contextmanager
def dataset_of(args, say=print):
    """The dataset `calibrate` runs on: DATASET itself, or a ROS bag imported into a temporary dataset
    (removed at the end)."""
    from ..io.rosbag import is_bag

    if not is_bag(args.dataset):
        yield args.dataset
        return
    with (
        tempfile.TemporaryDirectory(prefix="jaxcal-bag-") as tmp,
        _interrupt.partial(lambda: shutil.rmtree(tmp, ignore_errors=True)),
    ):
        r = _import(args, args.dataset, Path(tmp) / "dataset", overwrite=False)
        say(f"imported {args.dataset}: {r.frames} images, {r.joint_samples} joint states")
        for note in r.notes:
            say(note)
        try:
            yield r.path
        except JaxcalError as e:  # said of the bag, not of the temporary folder (gone by then)
            e.args = (str(e).replace(str(r.path), f"the dataset imported from {args.dataset}"), *e.args[1:])
            raise
