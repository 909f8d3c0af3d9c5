"""Write a jaxcal dataset as a ROS 1 or ROS 2 bag (rosbags' writers), for the import tests and data/.

`write_bag(dataset, bag, ...)` films the dataset's first camera onto an image
topic (raw `sensor_msgs/Image` in a chosen encoding, or `CompressedImage`
with the dataset's PNG bytes as they are), its encoder log onto
`/joint_states` (joint positions = motor / nominal ratio) and its intrinsics
onto `/camera_info`, every stamp shifted by `epoch_s` whole seconds.

Run as a script to write data/'s example bag:
`python tests/bagwriter.py data/ur5e_sweeps data/ros/ur5e_sweeps_mcap --storage mcap`.
"""

import argparse
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from jaxcal.io.dataset import load_dataset

IMAGES = "/camera/image_raw"
COMPRESSED = "/camera/image_raw/compressed"
JOINTS = "/joint_states"
INFO = "/camera/camera_info"


def _stamp(ts, ns: int, ros1: bool):
    Time = ts.types["builtin_interfaces/msg/Time"]
    Header = ts.types["std_msgs/msg/Header"]
    t = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    return Header(seq=0, stamp=t, frame_id="camera") if ros1 else Header(stamp=t, frame_id="camera")


def to_ns(t: float, epoch_s: int) -> int:
    """A dataset time (s) as integer nanoseconds since 1970, `epoch_s` whole seconds added."""
    return epoch_s * 1_000_000_000 + int(round(t * 1e9))


def _image_msg(ts, header, path: Path, encoding: str | None):
    """`encoding` None: a CompressedImage of the file's bytes; else a raw Image in that encoding."""
    if encoding is None:
        data = np.frombuffer(path.read_bytes(), np.uint8)
        fmt = "png" if path.suffix == ".png" else "jpeg"
        return ts.types["sensor_msgs/msg/CompressedImage"](header=header, format=fmt, data=data)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    gray = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    pixels = {"mono8": gray, "bgr8": cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)}.get(encoding)
    if pixels is None:  # rgb8, or an unsupported encoding written as RGB bytes
        pixels = cv2.cvtColor(gray, cv2.COLOR_GRAY2RGB)
    h, w = pixels.shape[:2]
    ch = 1 if pixels.ndim == 2 else 3
    Image = ts.types["sensor_msgs/msg/Image"]
    return Image(
        header=header,
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=w * ch,
        data=np.ascontiguousarray(pixels).reshape(-1),
    )


def _info_msg(ts, header, cam, ros1: bool, model: str = "plumb_bob"):
    K = np.zeros(9) if cam.K is None else np.asarray(cam.K, np.float64).reshape(-1)
    P = np.zeros(12)
    P[[0, 1, 2, 4, 5, 6, 10]] = K[[0, 1, 2, 3, 4, 5, 8]]
    fields = {
        ("D" if ros1 else "d"): np.asarray(cam.dist, np.float64),
        ("K" if ros1 else "k"): K,
        ("R" if ros1 else "r"): np.eye(3).reshape(-1),
        ("P" if ros1 else "p"): P,
    }
    roi = ts.types["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    return ts.types["sensor_msgs/msg/CameraInfo"](
        header=header,
        height=cam.height,
        width=cam.width,
        distortion_model=model,
        binning_x=0,
        binning_y=0,
        roi=roi,
        **fields,
    )


def write_bag(
    dataset,
    bag,
    *,
    ros1: bool = False,
    storage: str = "sqlite3",
    encoding: str | None = None,
    rows=None,
    epoch_s: int = 1_700_000_000,
    joint_names=None,
    joints_shift_s: float = 0.0,
    camera_info: bool = True,
    image_type: str | None = None,
    joint_scale: float = 1.0,
    extra_joints: tuple[str, ...] = (),
    gripper: str | None = None,
    nan_message: int | None = None,
    zero_stamps: bool = False,
    focal_from: tuple[int, float] | None = None,
) -> Path:
    """Write `dataset` (a directory) as the bag `bag` (a `.bag` file for ROS 1, a directory for ROS 2).

    `rows`: the frames.csv rows to film (default all); `encoding`: None for
    CompressedImage, else a raw Image encoding; `joint_names`: the names the
    joint states carry (default the robot's); `joints_shift_s`: added to the
    joint states' stamps (to break the overlap); `image_type`: a message type
    to put on the image topic instead (to test the wrong-type error); `joint_scale`: the joint
    positions' factor (degrees: `180 / pi`, a driver that breaks the message's radians);
    `extra_joints`: more names (at 0 rad) in every joint state (a gripper's); `gripper`: a joint
    published alone on the joint-state topic between the arm's messages (a gripper driver's);
    `nan_message`: that joint state's first position NaN; `zero_stamps`: every header stamp
    zero (unset); `focal_from`: `(k, f)`, the camera info's focal lengths times `f` from its k-th
    message on (a camera recalibrated within the bag).
    """
    ds = load_dataset(dataset)
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    ratio = np.array([ds.joint_limits[j].reduction_ratio for j in ds.joint_names])
    cam = ds.cameras[0]
    rows = np.flatnonzero(ds.frames["camera"] == cam.name) if rows is None else rows
    names = list(ds.joint_names if joint_names is None else joint_names)
    image_topic = IMAGES if encoding is not None else COMPRESSED
    image_msgtype = "sensor_msgs/msg/Image" if encoding is not None else "sensor_msgs/msg/CompressedImage"
    if ros1:
        writer = Writer1(bag)
    else:
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(bag, version=9, storage_plugin=plugin)
    with writer:
        conn = {
            "img": writer.add_connection(image_topic, image_type or image_msgtype, typestore=ts),
            "joints": writer.add_connection(JOINTS, "sensor_msgs/msg/JointState", typestore=ts),
        }
        if camera_info:
            conn["info"] = writer.add_connection(INFO, "sensor_msgs/msg/CameraInfo", typestore=ts)
        JointState = ts.types["sensor_msgs/msg/JointState"]

        def state(ns, names, pos):
            header = _stamp(ts, 0 if zero_stamps else ns, ros1)
            msg = JointState(
                header=header, name=names, position=pos, velocity=np.zeros(0), effort=np.zeros(0)
            )
            writer.write(conn["joints"], ns, ser(msg, "sensor_msgs/msg/JointState"))

        for k, (t, m) in enumerate(zip(ds.encoder_t, ds.encoder_motor)):
            ns = to_ns(t + joints_shift_s, epoch_s)
            pos = np.r_[np.asarray(joint_scale * m / ratio, np.float64), np.zeros(len(extra_joints))]
            if k == nan_message:
                pos[0] = np.nan
            state(ns, [*names, *extra_joints], pos)
            if gripper is not None:
                state(ns + 1, [gripper], np.zeros(1))
        for n, i in enumerate(rows):
            ns = to_ns(float(ds.frames["timestamp"][i]), epoch_s)
            header = _stamp(ts, 0 if zero_stamps else ns, ros1)
            if image_type is not None:
                msg = JointState(
                    header=header, name=[], position=np.zeros(0), velocity=np.zeros(0), effort=np.zeros(0)
                )
            else:
                msg = _image_msg(ts, header, ds.image_path(i), encoding)
            writer.write(conn["img"], ns, ser(msg, image_type or image_msgtype))
            if camera_info:
                seen = cam
                if focal_from is not None and n >= focal_from[0]:
                    K = np.asarray(cam.K, np.float64) * np.array(
                        [[focal_from[1]] * 2 + [1.0], [1.0, focal_from[1], 1.0], [1.0] * 3]
                    )
                    seen = SimpleNamespace(K=K, dist=cam.dist, width=cam.width, height=cam.height)
                writer.write(
                    conn["info"], ns, ser(_info_msg(ts, header, seen, ros1), "sensor_msgs/msg/CameraInfo")
                )
    return Path(bag)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("bag")
    ap.add_argument("--storage", choices=("sqlite3", "mcap"), default="mcap")
    args = ap.parse_args()
    print(write_bag(args.dataset, args.bag, storage=args.storage))
