"""ROS bags in (`jaxcal.io.rosbag`, `jaxcal import-bag`): data/ur5e_sweeps written as ROS 1 and ROS 2
bags (sqlite3, MCAP; raw and compressed images) by rosbags' writers, imported, compared with the source."""

import hashlib
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from bagwriter import COMPRESSED, IMAGES, INFO, JOINTS, write_bag

from jaxcal.cli import main
from jaxcal.errors import (
    BagEncodingError,
    BagError,
    BagJointError,
    BagMessageTypeError,
    BagTimeError,
    BagTopicError,
    DatasetError,
)
from jaxcal.io._rosmsgs import encode_raw, find_segments
from jaxcal.io.dataset import load_dataset
from jaxcal.io.rosbag import import_bag, is_bag
from jaxcal.stages.kinds import CaptureKind, Motion

SOURCE = Path(__file__).resolve().parents[1] / "data" / "ur5e_sweeps"
ROBOT = SOURCE / "robot.urdf"
TARGETS = SOURCE / "metadata.json"  # its 'targets' list
SUBSET = np.arange(0, 144, 12)  # 12 frames, one or two per sweep, for the raw-image bags


@pytest.fixture(scope="module")
def source():
    return load_dataset(SOURCE)


def _import(bag, out, *, images=COMPRESSED, camera_info=INFO, **kw):
    return import_bag(
        bag, out, images=images, joints=JOINTS, camera_info=camera_info, robot=ROBOT, targets=TARGETS, **kw
    )


def _digest(path: Path) -> str:
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    return hashlib.sha256(b"".join(p.read_bytes() for p in files)).hexdigest()


def _check_same(src, ds, rows):
    """The imported dataset `ds` holds the source's `rows`: stamps to 1 ns, pixels, encoders, K."""
    assert len(ds.frames["file"]) == len(rows)
    np.testing.assert_allclose(ds.frames["timestamp"], src.frames["timestamp"][rows], rtol=0, atol=1e-9)
    for i, r in enumerate(rows):
        a = cv2.imread(str(ds.image_path(i)), cv2.IMREAD_UNCHANGED)
        b = cv2.imread(str(src.image_path(r)), cv2.IMREAD_UNCHANGED)
        if a.ndim == 3:
            assert np.array_equal(a[..., 0], a[..., 2])
            a = a[..., 0]
        assert np.array_equal(a, b)
    np.testing.assert_allclose(ds.encoder_t, src.encoder_t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ds.encoder_motor, src.encoder_motor, rtol=1e-13, atol=1e-13)
    assert ds.joint_names == src.joint_names
    assert (ds.base_link, ds.flange_link) == (src.base_link, src.flange_link)
    assert [t.name for t in ds.targets] == [t.name for t in src.targets]


def _check_segments(src, ds):
    """Every source sweep segment lies inside the imported segment of the same joint, and no other."""
    assert [j for j, _, _ in ds.segments] == [j for j, _, _ in src.segments]
    for (j, s0, e0), (_, s1, e1) in zip(src.segments, ds.segments):
        assert s1 <= s0 + 0.06 and e0 - 0.06 <= e1, (j, (s0, e0), (s1, e1))
    ends = [e for _, _, e in ds.segments]
    starts = [s for _, s, _ in ds.segments]
    assert all(e < s for e, s in zip(ends[:-1], starts[1:]))


@pytest.fixture(scope="module")
def mcap_bag(tmp_path_factory):
    return write_bag(SOURCE, tmp_path_factory.mktemp("bags") / "mcap", storage="mcap")


def test_ros2_mcap_compressed_images_round_trip(source, mcap_bag, tmp_path):
    before = _digest(mcap_bag)
    r = _import(mcap_bag, tmp_path / "ds")
    assert _digest(mcap_bag) == before  # the bag is only read
    ds = load_dataset(r.path)
    _check_same(source, ds, np.arange(144))
    _check_segments(source, ds)
    assert r.epoch_ns == 1_700_000_000 * 10**9 and ds.metadata["x_ros"]["epoch_ns"] == r.epoch_ns
    np.testing.assert_allclose(ds.cameras[0].K, source.cameras[0].K, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(ds.cameras[0].dist, source.cameras[0].dist)
    # The PNG bytes are kept as they are, not compressed a second time.
    assert ds.image_path(5).read_bytes() == source.image_path(5).read_bytes()
    kind = CaptureKind.of(camera_on_flange=False, segments=ds.segments, encoders=True, link_targets=False)
    assert kind.motion is Motion.SWEEPS


def test_ros2_sqlite3_raw_mono8(source, tmp_path):
    bag = write_bag(SOURCE, tmp_path / "sqlite", encoding="mono8", rows=SUBSET)
    ds = load_dataset(_import(bag, tmp_path / "ds", images=IMAGES).path)
    _check_same(source, ds, SUBSET)
    _check_segments(source, ds)


@pytest.mark.parametrize("encoding", ["bgr8", "rgb8"])
def test_ros1_raw_colour_without_camera_info(source, tmp_path, encoding):
    bag = write_bag(
        SOURCE, tmp_path / "cap.bag", ros1=True, encoding=encoding, rows=SUBSET, camera_info=False
    )
    assert is_bag(bag)
    ds = load_dataset(_import(bag, tmp_path / "ds", images=IMAGES, camera_info=None).path)
    _check_same(source, ds, SUBSET)
    assert ds.cameras[0].K is None  # no CameraInfo: self-calibration


def test_ros1_compressed_with_camera_info(source, tmp_path):
    bag = write_bag(SOURCE, tmp_path / "cap.bag", ros1=True, rows=SUBSET)
    r = _import(bag, tmp_path / "ds")
    ds = load_dataset(r.path)
    _check_same(source, ds, SUBSET)
    np.testing.assert_allclose(ds.cameras[0].K, source.cameras[0].K, rtol=0, atol=1e-12)
    assert not any("--camera-info" in n for n in r.notes)
    # The same bag without --camera-info: K null, and a note names the topic that was left out.
    r = _import(bag, tmp_path / "ds_no_info", camera_info=None)
    assert load_dataset(r.path).cameras[0].K is None
    assert any(f"give --camera-info {INFO} to use it" in n for n in r.notes), r.notes


def test_rgb8_is_written_in_opencv_order():
    rgb = np.zeros((2, 3, 3), np.uint8)
    rgb[..., 0] = 200  # red
    msg = SimpleNamespace(encoding="rgb8", height=2, width=3, step=9, data=rgb.reshape(-1))
    img = cv2.imdecode(np.frombuffer(encode_raw(msg, "m").data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img[0, 0].tolist() == [0, 0, 200]  # BGR
    # bgr8 pixels labelled mono8: the rows are three times as long as mono8's; named, not cut to a third.
    bgr = SimpleNamespace(encoding="mono8", height=2, width=3, step=9, data=rgb.reshape(-1))
    with pytest.raises(
        BagEncodingError, match=r"step 9: 3 times the 3 bytes a mono8 row holds, as the rows of bgr8 or rgb8"
    ):
        encode_raw(bgr, "m")
    padded = SimpleNamespace(encoding="mono8", height=2, width=3, step=4, data=np.zeros(8, np.uint8))
    assert encode_raw(padded, "m").width == 3  # a row padded for alignment is no mislabel


def test_stop_and_shoot_is_one_pose_segment():
    """Several joints moving together between still poses: one `joint: null` segment (pose-based)."""
    t = np.arange(0.0, 6.0, 0.002)
    q = np.zeros((t.size, 6))
    for k, t0 in enumerate((1.0, 3.0)):  # two moves of joints 0, 1, 2 together, still between
        ramp = np.clip((t - t0) / 0.5, 0.0, 1.0)
        q[:, :3] += 0.3 * (k + 1) * ramp[:, None]
    segments, notes = find_segments(t, q, [f"j{i}" for i in range(6)])
    assert segments == [{"joint": None, "start": 0.0, "end": t[-1]}]
    kind = CaptureKind.of(
        camera_on_flange=False,
        segments=tuple((s["joint"], s["start"], s["end"]) for s in segments),
        encoders=True,
        link_targets=False,
    )
    assert kind.motion is Motion.POSES
    assert "stop-and-shoot" in notes[0]


def test_stepped_sweep_is_one_segment():
    """One joint stepping with pauses (an image at each stop): one segment over all its steps."""
    t = np.arange(0.0, 5.0, 0.002)
    q = np.zeros((t.size, 2))
    for t0 in (1.0, 2.0, 3.0):
        q[:, 1] += 0.2 * np.clip((t - t0) / 0.3, 0.0, 1.0)
    segments, _ = find_segments(t, q, ["a", "b"])
    assert len(segments) == 1 and segments[0]["joint"] == "b"
    assert segments[0]["start"] < 1.0 and segments[0]["end"] > 3.3


# --------------------------------------------------------------------------- bad bags


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory):
    return write_bag(SOURCE, tmp_path_factory.mktemp("small") / "small", rows=SUBSET)


def test_missing_topic_lists_the_topics(small_bag, tmp_path):
    with pytest.raises(BagTopicError) as e:
        _import(small_bag, tmp_path / "ds", images="/camera/color/image_raw")
    msg = str(e.value)
    assert "/camera/color/image_raw" in msg and "/joint_states (sensor_msgs/msg/JointState" in msg
    assert "/camera/image_raw/compressed (sensor_msgs/msg/CompressedImage" in msg
    assert not (tmp_path / "ds").exists()


def test_wrong_message_type(tmp_path):
    bag = write_bag(SOURCE, tmp_path / "bag", rows=SUBSET, image_type="sensor_msgs/msg/JointState")
    with pytest.raises(BagMessageTypeError, match="holds sensor_msgs/msg/JointState messages"):
        _import(bag, tmp_path / "ds")


def test_wrong_message_type_of_camera_info(small_bag, tmp_path):
    with pytest.raises(BagMessageTypeError, match="expected sensor_msgs/msg/CameraInfo"):
        _import(small_bag, tmp_path / "ds", camera_info=JOINTS)


def test_a_grippers_joints_are_left_out(source, small_bag, tmp_path):
    """A gripper's joints on the joint-state topic, in the arm's messages or in its own between
    them (a second driver publishing there): the chain's joints are picked by name, the rest said,
    and the encoder log is the arm's alone."""
    plain = load_dataset(_import(small_bag, tmp_path / "plain").path)
    for kw in ({"extra_joints": ("finger_joint", "left_inner_knuckle_joint")}, {"gripper": "finger_joint"}):
        bag = write_bag(
            SOURCE,
            tmp_path / f"bag{len(kw['extra_joints']) if 'extra_joints' in kw else 1}",
            rows=SUBSET,
            **kw,
        )
        done = _import(bag, tmp_path / f"ds_{next(iter(kw))}")
        ds = load_dataset(done.path)
        np.testing.assert_array_equal(ds.encoder_motor, plain.encoder_motor)
        np.testing.assert_array_equal(ds.encoder_t, plain.encoder_t)
        said = " ".join(done.notes)
        assert ("left out: ['finger_joint', 'left_inner_knuckle_joint']" in said) == ("extra_joints" in kw), (
            said
        )
        assert ("messages holding only ['finger_joint']" in said) == ("gripper" in kw), said


def test_a_gripper_in_the_robot_file_is_not_the_arm(source, small_bag, tmp_path):
    """A URDF whose chain goes on past the flange to a gripper's finger (its one leaf), the finger's
    joint in the joint states: the chain ends where the targets ride (the flange), not at the leaf,
    and the finger is left out as a joint of the topic beyond the chain."""
    text = ROBOT.read_text()
    finger = (
        '<link name="finger_link"/><joint name="finger_joint" type="prismatic"><parent link="flange"/>'
        '<child link="finger_link"/><axis xyz="0 1 0"/><limit lower="0" upper="0.04" effort="10" velocity="0.1"/>'
        "</joint></robot>"
    )
    robot = tmp_path / "gripper.urdf"
    robot.write_text(text[: text.rindex("</robot>")] + finger)
    bag = write_bag(SOURCE, tmp_path / "bag", rows=SUBSET, extra_joints=("finger_joint",))
    done = import_bag(
        bag, tmp_path / "ds", images=COMPRESSED, joints=JOINTS, camera_info=INFO, robot=robot, targets=TARGETS
    )
    ds = load_dataset(done.path)
    assert ds.joint_names == source.joint_names and ds.flange_link == "flange"
    assert any("left out: ['finger_joint']" in n for n in done.notes), done.notes
    np.testing.assert_array_equal(
        ds.encoder_motor, load_dataset(_import(small_bag, tmp_path / "plain").path).encoder_motor
    )


def test_joint_names_not_in_the_urdf(source, tmp_path):
    """Joint states that hold none of the chain's joints (a driver's name prefix) are refused
    naming the names that are not the robot file's; a message lacking some of them, naming those."""
    bag = write_bag(
        SOURCE, tmp_path / "bag", rows=SUBSET, joint_names=[f"ur_{n}" for n in source.joint_names]
    )
    with pytest.raises(
        BagJointError,
        match=r"no message of /joint_states holds the robot's joints.*ur_elbow_joint.*not joints of the robot file",
    ):
        _import(bag, tmp_path / "ds")
    names = list(source.joint_names[:5]) + ["gripper_finger_joint"]
    bag = write_bag(SOURCE, tmp_path / "bag2", rows=SUBSET, joint_names=names)
    with pytest.raises(
        BagJointError, match=r"message 0: the joint states lack the robot's joints \['wrist_3_joint'\]"
    ):
        _import(bag, tmp_path / "ds")
    assert not (tmp_path / "ds").exists()


def test_a_nan_joint_state_is_named_by_message_and_joint(source, tmp_path):
    bag = write_bag(SOURCE, tmp_path / "bag", rows=SUBSET, nan_message=7)
    with pytest.raises(
        BagJointError,
        match=r"/joint_states message 7 \(stamp .* s\): joint position\(s\) of \['shoulder_pan_joint'\]",
    ):
        _import(bag, tmp_path / "ds")


def test_unset_stamps_are_named(tmp_path):
    bag = write_bag(SOURCE, tmp_path / "bag", rows=SUBSET, zero_stamps=True)
    with pytest.raises(
        BagTimeError, match=r"all \d+ joint states have the header stamp 0.000000000 s; is header.stamp set"
    ):
        _import(bag, tmp_path / "ds")


def test_a_camera_info_that_changes_within_the_bag_is_refused(tmp_path):
    """A camera recalibrated (or refocused) within the bag: one capture, one camera model."""
    bag = write_bag(SOURCE, tmp_path / "bag", rows=SUBSET, focal_from=(6, 1.1))
    with pytest.raises(
        BagError, match=r"/camera/camera_info message 6 gives other intrinsics than message 0"
    ):
        _import(bag, tmp_path / "ds")


def test_joint_states_in_degrees_are_named_by_bag_and_topic(tmp_path):
    """A driver that publishes degrees: refused naming the bag and its joint-state topic, not the
    temporary folder the import builds (gone once it is refused) or a field the user never wrote."""
    bag = write_bag(SOURCE, tmp_path / "bag", rows=SUBSET, joint_scale=180.0 / np.pi)
    with pytest.raises(DatasetError) as e:
        _import(bag, tmp_path / "ds")
    text = str(e.value)
    assert f"{bag} topic /joint_states" in text and "radians (sensor_msgs/JointState)" in text, text
    assert "degrees" in text and ".tmp" not in text and "encoders.unit" not in text, text
    assert not (tmp_path / "ds").exists()


def test_no_time_overlap(tmp_path):
    bag = write_bag(SOURCE, tmp_path / "bag", rows=SUBSET, joints_shift_s=1000.0)
    with pytest.raises(BagTimeError, match="do not overlap in time"):
        _import(bag, tmp_path / "ds")
    assert not (tmp_path / "ds").exists() and list(tmp_path.iterdir()) == [bag]


def test_unsupported_image_encoding(tmp_path):
    bag = write_bag(SOURCE, tmp_path / "bag", rows=SUBSET[:2], encoding="yuv422")
    with pytest.raises(BagEncodingError, match="'yuv422' is not supported"):
        _import(bag, tmp_path / "ds", images=IMAGES)


def test_cli_import_bag(small_bag, tmp_path, capsys):
    args = ["import-bag", str(small_bag), "--images", COMPRESSED, "--joints", JOINTS, "--robot", str(ROBOT)]
    args += ["--target", str(TARGETS), "--camera-info", INFO, "--out", str(tmp_path / "ds")]
    assert main(args) == 0
    assert "wrote" in capsys.readouterr().out
    assert len(load_dataset(tmp_path / "ds").frames["file"]) == SUBSET.size
    # Calibrated directly, a bag too short to calibrate (12 frames) is refused naming the bag, not the
    # temporary folder it was imported into (gone by the time the error is read).
    calib = ["calibrate", str(small_bag), *args[2:-1], str(tmp_path / "res"), "--quiet"]
    assert main(calib) == 2
    err = capsys.readouterr().err
    assert f"the dataset imported from {small_bag}" in err and "jaxcal-bag-" not in err, err
    assert main(args) == 2  # the output exists: refused, exit code 2
    assert main([*args[:3], "/nope", *args[4:-1], str(tmp_path / "ds2")]) == 2
    assert "no topic '/nope'" in capsys.readouterr().err
