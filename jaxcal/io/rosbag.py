"""ROS bags in: a ROS 1 bag or a ROS 2 bag (sqlite3 or MCAP) -> a jaxcal dataset directory.

`import_bag` reads the bag with `rosbags` (pure Python, no ROS install) and
writes the dataset format of `docs/dataset.md`:

- `sensor_msgs/Image` (mono8, bgr8, rgb8: lossless PNG) or
  `sensor_msgs/CompressedImage` (PNG and JPEG bytes kept as they are, after
  `cv2.imdecode` checked them) -> `images/<camera>/<frame>.png|jpg` and
  `frames.csv`; the image header stamps are the **camera clock**; frames are
  numbered in stamp order.
- `sensor_msgs/JointState` -> `encoders.csv`: the robot file's actuated joints
  (base to flange) by name, the header stamps as the **controller clock**.
  ROS reports joint positions (rad), which jaxcal's log holds as motor angles:
  `motor = position * nominal reduction ratio` (the URDF's transmission, 1
  without one), so that the commanded position `motor / ratio` is the
  position the controller published.
- `sensor_msgs/CameraInfo` (optional) -> the camera's `K` (null when absent
  or all zero: self-calibration) and distortion (plumb_bob, rational_polynomial).
- The motion segments are found in the joint log (`find_segments`:
  single-joint sweeps, or one pose-based segment for stop-and-shoot).

Stamps are written relative to `epoch_ns`, the whole second at or before
the earliest stamp of either clock (recorded as `x_ros.epoch_ns` in the
metadata): float64 seconds since 1970 would keep only 0.2 us, relative ones
keep 1 ns. Both clocks lose the same epoch, so the offset between them is
unchanged.

A bag that cannot give a dataset raises a `BagError` subclass naming the bag
and the topic (`jaxcal.errors`): a missing topic (with the topics the bag
has), a wrong message type, joint names the robot file lacks, images and
joint states that do not overlap in time, an unsupported encoding. The bag is
only read; the output is written atomically (`atomic_directory`) and checked
with `load_dataset` before it is renamed into place.
"""

import shutil
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from rosbags.highlevel import AnyReader

from ..errors import (
    BagError,
    BagJointError,
    BagMessageTypeError,
    BagTimeError,
    BagTopicError,
    DatasetError,
)
from ._files import atomic_directory, shown
from ._rosmsgs import (
    SegmentOptions,
    camera_intrinsics,
    encode_compressed,
    encode_raw,
    find_segments,
    stamp_ns,
)
from ._schema import file_name, loads
from .dataset import SCHEMA, SCHEMA_VERSION, load_dataset, write_encoders, write_frames, write_json
from .dh_tables import dh_table_model, is_table_file, read_table_file
from .urdf import load_urdf, urdf_link_names, urdf_outline

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
JOINT_TYPE = "sensor_msgs/msg/JointState"
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
#: File suffixes of bags (a ROS 2 bag is a directory with `metadata.yaml`; its storage file works too).
BAG_SUFFIXES = (".bag", ".mcap", ".db3")


def is_bag(path) -> bool:
    """Whether `path` looks like a ROS bag: a `.bag` / `.mcap` / `.db3` file, or a directory holding a
    ROS 2 bag's `metadata.yaml` (and no jaxcal `metadata.json`)."""
    p = Path(path)
    if p.is_file():
        return p.suffix in BAG_SUFFIXES
    return p.is_dir() and (p / "metadata.yaml").is_file() and not (p / "metadata.json").exists()


def _bag_path(path: Path) -> Path:
    """What `AnyReader` opens: a ROS 2 storage file's bag directory, else the path itself."""
    if path.is_file() and path.suffix in (".mcap", ".db3") and (path.parent / "metadata.yaml").is_file():
        return path.parent
    return path


@contextmanager
def open_bag(path):
    """Yield an opened `AnyReader` on the bag at `path` (ROS 2 bags without message definitions use
    ROS 2 Humble's types), closed at the end. Raises `BagError` naming the path when it is no bag
    `rosbags` can read."""
    # rosbags is imported here: a dataset folder's commands (`is_bag` first) never load it.
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: bag not found")
    try:
        reader = AnyReader([_bag_path(path)], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except (AnyReaderError, OSError, ValueError, KeyError) as e:
        raise BagError(f"{path}: cannot read the bag: {e}") from e
    try:
        yield reader
    finally:
        reader.close()


def bag_topics(reader: "AnyReader") -> dict[str, tuple[str, int]]:
    """The bag's topics: `topic -> (message type, message count)`."""
    return {name: (info.msgtype, info.msgcount) for name, info in reader.topics.items()}


def _connections(reader: "AnyReader", bag: Path, topic: str, types: tuple[str, ...], option: str):
    topics = bag_topics(reader)
    if topic not in topics:
        listing = "; ".join(f"{t} ({m}, {n} messages)" for t, (m, n) in sorted(topics.items())) or "none"
        raise BagTopicError(f"{bag}: no topic {topic!r} ({option}); the bag's topics: {listing}")
    msgtype = topics[topic][0]
    if msgtype not in types:
        raise BagMessageTypeError(
            f"{bag}: topic {topic!r} ({option}) holds {msgtype} messages; expected {' or '.join(types)}"
        )
    return [c for c in reader.connections if c.topic == topic]


def read_targets(path) -> list[dict]:
    """The targets of a JSON file: a list of `targets[]` objects of docs/dataset.md, one such object, or
    an object with a `targets` list (a dataset's `metadata.json` works). Checked with the dataset."""
    path = Path(path)
    try:
        data = loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise DatasetError(f"{path}: cannot read the target file: {e}") from e
    if isinstance(data, dict):
        data = data.get("targets", [data])
    if not isinstance(data, list) or not data or not all(isinstance(x, dict) for x in data):
        raise DatasetError(
            f"{path}: expected a target object, a list of them or an object with 'targets' (docs/dataset.md)"
        )
    return data


@dataclass(frozen=True)
class BagImport:
    """What `import_bag` wrote: the dataset, its image and joint-state counts, the motion segments and notes."""

    path: Path
    frames: int
    joint_samples: int
    segments: tuple
    epoch_ns: int
    notes: tuple[str, ...]


def _read_joints(
    reader, conns, bag: Path, topic: str, chain, urdf_joints
) -> tuple[np.ndarray, np.ndarray, list]:
    """`(stamps ns (T,), positions (T, chain))` of the joint states, sorted, repeated stamps dropped.
    The chain's joints are picked by name: other joints in a message (a gripper's) are left out,
    and messages holding none of the chain's (a gripper's own, on the same topic) are skipped."""
    stamps, rows, names, index, other, skipped = [], [], None, None, set(), {}
    for k, (conn, _, raw) in enumerate(reader.messages(connections=conns)):
        msg = reader.deserialize(raw, conn.msgtype)
        where = f"{bag}: {topic} message {k}"
        if list(msg.name) != names:
            names = list(msg.name)
            held = [n for n in chain if n in names]
            if held and len(held) < len(chain):
                raise BagJointError(
                    f"{where}: the joint states lack the robot's joints "
                    f"{[n for n in chain if n not in names]} (they hold {names})"
                )
            index = [names.index(n) for n in chain] if held else None
        pos = np.asarray(msg.position, np.float64)
        if pos.size != len(names):
            raise BagJointError(f"{where}: {len(names)} joint names but {pos.size} positions")
        if index is None:
            skipped.setdefault(tuple(names), k)
            continue
        other.update(n for n in names if n not in chain)
        if not np.all(np.isfinite(pos[index])):
            bad = [n for n, x in zip(chain, pos[index]) if not np.isfinite(x)]
            raise BagJointError(
                f"{where} (stamp {stamp_ns(msg.header) / 1e9:.6f} s): joint position(s) of {bad} are NaN or "
                "infinite"
            )
        stamps.append(stamp_ns(msg.header))
        rows.append(pos[index])
    if not stamps and skipped:
        held = sorted({n for names in skipped for n in names})
        unknown = [n for n in held if n not in urdf_joints]
        raise BagJointError(
            f"{bag}: no message of {topic} holds the robot's joints {list(chain)} (they hold {held}"
            + (f"; {unknown} are not joints of the robot file" if unknown else "")
            + ")"
        )
    _distinct(stamps, bag, topic, "joint state")
    stamps = np.asarray(stamps, np.int64)
    order = np.argsort(stamps, kind="stable")
    stamps, q = stamps[order], np.asarray(rows)[order]
    keep = np.r_[True, np.diff(stamps) > 0]
    notes = [] if keep.all() else [f"{int((~keep).sum())} joint state(s) repeating an earlier stamp dropped"]
    if other:
        notes.append(f"joints of {topic} not in the robot's chain, left out: {sorted(other)}")
    for names, k in skipped.items():
        notes.append(f"{topic} messages holding only {list(names)} (the first: message {k}) skipped")
    return stamps[keep], q[keep], notes


def _distinct(stamps: list[int], bag: Path, topic: str, what: str) -> None:
    """Refuse a topic whose messages do not have two different header stamps (unset stamps)."""
    if len(stamps) < 2:
        raise BagTimeError(f"{bag}: topic {topic!r} holds {len(stamps)} {what}(s); a log needs at least two")
    if len(set(stamps)) < 2:
        raise BagTimeError(
            f"{bag}: topic {topic!r}: all {len(stamps)} {what}s have the header stamp {stamps[0] / 1e9:.9f} s; "
            "is header.stamp set by the publisher?"
        )


def _read_images(reader, conns, bag: Path, topic: str, folder: Path, camera: str) -> tuple[list, list, tuple]:
    """Write every image of `topic` into `folder` (by stamp order); `(rows (stamp ns, file), notes, (width, height))`."""
    written, size = [], None
    folder.mkdir(parents=True)
    for k, (conn, _, raw) in enumerate(reader.messages(connections=conns)):
        msg = reader.deserialize(raw, conn.msgtype)
        where = f"{bag}: {topic} message {k}"
        img = encode_raw(msg, where) if conn.msgtype == IMAGE_TYPES[0] else encode_compressed(msg, where)
        if size is None:
            size = (img.width, img.height)
        elif (img.width, img.height) != size:
            raise BagError(
                f"{where}: image of {img.width}x{img.height}; the topic's first was {size[0]}x{size[1]}"
            )
        tmp = folder / f".{k}{img.suffix}"
        tmp.write_bytes(img.data)
        written.append((stamp_ns(msg.header), tmp))
    if not written:
        raise BagTimeError(f"{bag}: topic {topic!r} holds no images")
    _distinct([t for t, _ in written], bag, topic, "image")
    written.sort(key=lambda x: x[0])
    rows, notes, last = [], [], None
    for stamp, tmp in written:
        if stamp == last:
            tmp.unlink()
            continue
        name = f"{len(rows):06d}{tmp.suffix}"
        tmp.rename(folder / name)
        rows.append((stamp, f"images/{camera}/{name}"))
        last = stamp
    if len(rows) < len(written):
        notes.append(f"{len(written) - len(rows)} image(s) repeating an earlier stamp dropped")
    return rows, notes, size


def _camera(reader, bag: Path, topic: str | None, size, camera: str, mount: str) -> dict:
    cam = {
        "name": camera,
        "width": size[0],
        "height": size[1],
        "K": None,
        "distortion": [0.0] * 5,
        "mount": mount,
    }
    if topic is None:
        return cam
    conns = _connections(reader, bag, topic, (INFO_TYPE,), "--camera-info")
    infos = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=conns)]
    if not infos:
        raise BagTimeError(f"{bag}: topic {topic!r} (--camera-info) holds no messages")
    calibrated = [
        (k, m) for k, m in enumerate(infos) if np.any(np.asarray(getattr(m, "k", getattr(m, "K", ()))) != 0)
    ]
    first, msg = (calibrated or [(0, infos[0])])[0]
    K, dist, w, h = camera_intrinsics(msg, f"{bag}: {topic}")
    for k, m in calibrated[1:]:  # a camera recalibrated, refocused or resized within the bag
        K2, dist2, w2, h2 = camera_intrinsics(m, f"{bag}: {topic} message {k}")
        if (w2, h2) != (w, h) or not np.allclose(K2, K, rtol=1e-9, atol=0.0) or not np.allclose(dist2, dist):
            raise BagError(
                f"{bag}: {topic} message {k} gives other intrinsics than message {first} (K {np.asarray(K2).tolist()} "
                f"against {np.asarray(K).tolist()}, {w2}x{h2} against {w}x{h}): one capture needs one camera "
                "model; cut the bag where it changed, or give the right one in the dataset's metadata.json"
            )
    if (w, h) != tuple(size) and (w, h) != (0, 0):
        raise BagError(f"{bag}: {topic} says {w}x{h} but the images are {size[0]}x{size[1]}")
    cam.update(K=K, distortion=dist)
    return cam


def _unused_camera_info(reader, bag: Path) -> list[str]:
    """A note naming the bag's CameraInfo topics when `--camera-info` was not given (K is then
    null: self-calibrated, and a result without the refinement is suspect)."""
    topics = sorted({c.topic for c in reader.connections if c.msgtype == INFO_TYPE})
    if not topics:
        return []
    return [
        f"no --camera-info given, so the camera's K is null (self-calibrated from the images); {bag.name} "
        f"has sensor_msgs/CameraInfo on {', '.join(topics)}: give --camera-info {topics[0]} to use it"
    ]


def _flange(robot: Path, flange_link, targets: list) -> str | None:
    """The chain's last link: `flange_link` when given; else, for a URDF whose targets all ride on
    one of its links, that link (a gripper's joints beyond it are then not the arm's); else None
    (the URDF's one leaf)."""
    links = {t.get("link") for t in targets if isinstance(t, dict)}
    if flange_link is not None or is_table_file(robot) or len(links) != 1:
        return flange_link
    (link,) = links
    try:
        return link if link in urdf_link_names(robot) else None
    except (OSError, ValueError):
        return None  # the robot file's own error comes from loading it


def _robot_model(robot: Path, base_link, flange_link):
    """The robot file's model, its movable joints, the chain's reduction ratios, and the
    metadata key and file name it is copied under (`urdf`, `robot.urdf`, or `table`, `robot_dh.json`)."""
    try:
        if is_table_file(robot):
            model = dh_table_model(robot)
            t = read_table_file(robot)
            ratio = np.ones(model.num_joints) if t.reduction_ratio is None else t.reduction_ratio
            return model, set(model.joint_names), ratio, "table", f"robot_dh{robot.suffix.lower()}"
        model = load_urdf(robot, base_link, flange_link)
        outline = urdf_outline(robot, tuple(model.joint_names))
    except (OSError, ValueError) as e:
        raise DatasetError(f"{shown(robot)}: cannot load the robot model: {e}") from e
    movable = {j for j, kind, _ in outline.parent_joint.values() if kind != "fixed"}
    ratio = np.array([outline.limits[j].reduction_ratio for j in model.joint_names])
    return model, movable, ratio, "urdf", "robot.urdf"


def _checked(tmp: Path, bag: Path, joints: str) -> None:
    """`load_dataset`'s every check of the dataset built in `tmp`, before the rename; what it finds
    is said of the bag and its topics (the folder is gone once the import is refused)."""
    try:
        load_dataset(tmp)
    except DatasetError as e:
        text = str(e).replace(str(tmp / "encoders.csv"), f"{bag} topic {joints}")
        text = text.replace("encoders.unit is 'rad'", "the joint states are radians (sensor_msgs/JointState)")
        raise DatasetError(text.replace(str(tmp), f"the dataset imported from {bag}")) from None


def import_bag(
    bag,
    out,
    *,
    images: str,
    joints: str,
    robot,
    targets,
    camera_info: str | None = None,
    camera: str = "cam0",
    mount: str = "world",
    base_link: str | None = None,
    flange_link: str | None = None,
    segments: SegmentOptions | None = None,
    overwrite: bool = False,
) -> BagImport:
    """Convert the ROS bag `bag` into the dataset directory `out` (see the module docstring).

    **Arguments:**
    - `images`, `joints`, `camera_info`: topic names (CameraInfo optional).
    - `robot`: the URDF file (copied as `robot.urdf`), or a DH/MDH table file
      (copied as `robot_dh.json` / `.yaml`, named by `robot.table`); `base_link`,
      `flange_link`: the chain's ends (default: its root and its one leaf; a table's own).
    - `targets`: a JSON file (`read_targets`) or a list of target objects.
    - `camera`, `mount`: the camera's name and mount (`"world"` or a link).
    - `segments`: how motion segments are found in the joint log.
    - `overwrite`: replace a dataset jaxcal wrote at `out`.

    **Returns:** a `BagImport`. Raises a `BagError` subclass for a bag that
    cannot give a dataset, `DatasetError` when the result fails `load_dataset`'s
    checks (nothing is then left at `out`), `OutputError` for `out`.
    """
    bag, robot = Path(bag), Path(robot)
    file_name(camera, "camera (camera-name)")  # it names images/<camera>/: checked before anything is written
    target_list = read_targets(targets) if isinstance(targets, (str, Path)) else list(targets)
    model, movable, ratio, robot_key, robot_name = _robot_model(
        robot, base_link, _flange(robot, flange_link, target_list)
    )
    chain = tuple(model.joint_names)
    inputs = [bag, robot] + ([targets] if isinstance(targets, (str, Path)) else [])
    with (
        open_bag(bag) as reader,
        atomic_directory(out, overwrite=overwrite, inputs=inputs, kind="dataset", what="--out") as tmp,
    ):
        image_conns = _connections(reader, bag, images, IMAGE_TYPES, "--images")
        joint_conns = _connections(reader, bag, joints, (JOINT_TYPE,), "--joints")
        enc_ns, q, notes = _read_joints(reader, joint_conns, bag, joints, chain, movable)
        rows, more, size = _read_images(reader, image_conns, bag, images, tmp / "images" / camera, camera)
        notes += more
        img_ns = np.array([s for s, _ in rows], np.int64)
        if img_ns[-1] < enc_ns[0] or img_ns[0] > enc_ns[-1]:
            raise BagTimeError(
                f"{bag}: the images ({images}, stamps {img_ns[0] * 1e-9:.3f}-{img_ns[-1] * 1e-9:.3f} s) and the "
                f"joint states ({joints}, {enc_ns[0] * 1e-9:.3f}-{enc_ns[-1] * 1e-9:.3f} s) do not overlap in time"
            )
        cam = _camera(reader, bag, camera_info, size, camera, mount)
        if camera_info is None:
            notes += _unused_camera_info(reader, bag)
        epoch = (min(int(img_ns[0]), int(enc_ns[0])) // 1_000_000_000) * 1_000_000_000
        t_enc = (enc_ns - epoch) * 1e-9
        motion, more = find_segments(t_enc, q, chain, segments or SegmentOptions())
        notes += more
        shutil.copyfile(robot, tmp / robot_name)
        write_frames(
            tmp / "frames.csv",
            [camera] * len(rows),
            range(len(rows)),
            (img_ns - epoch) * 1e-9,
            [f for _, f in rows],
        )
        write_encoders(tmp / "encoders.csv", t_enc, q * ratio, chain)
        meta = {
            "schema": SCHEMA,
            "schema_version": SCHEMA_VERSION,
            "description": f"imported from the ROS bag {bag.name} by jaxcal import-bag",
            "robot": {
                robot_key: robot_name,
                "base_link": model.link_names[0],
                "flange_link": model.link_names[-1],
                "joints": list(chain),
            },
            "cameras": [cam],
            "targets": target_list,
            "encoders": {
                "file": "encoders.csv",
                "quantity": "motor_angle",
                "unit": "rad",
                "rate_hz": float(np.round(1.0 / np.median(np.diff(t_enc)), 6)),
            },
            "clock": {"offset_s": None},
            "motion": motion or None,
            "x_ros": {
                "bag": bag.name,
                "epoch_ns": epoch,
                "images": images,
                "joints": joints,
                "camera_info": camera_info,
                "notes": notes,
            },
        }
        write_json(tmp / "metadata.json", meta)
        _checked(tmp, bag, joints)
    seg = tuple((s["joint"], s["start"], s["end"]) for s in motion)
    return BagImport(Path(out), len(rows), len(enc_ns), seg, epoch, tuple(notes))
