"""`jaxcal inspect` (jaxcal.inspection): a capture summarised without any fit."""

from pathlib import Path

import pytest
from bagwriter import COMPRESSED, JOINTS, write_bag

from jaxcal.cli import main
from jaxcal.inspection import inspect_dataset

SOURCE = Path(__file__).resolve().parents[1] / "data" / "ur5e_sweeps"


def test_inspect_dataset():
    s = inspect_dataset(SOURCE, sample=3)
    assert s["cameras"] == [
        {"name": "cam0", "size": [800, 600], "K_given": True, "mount": "world", "frames": 144}
    ]
    assert s["segments_from"] == "metadata.json" and len(s["segments"]) == 6
    for g in s["segments"]:
        assert g["range_deg"] == pytest.approx([-40.0, 40.0], abs=0.05)
        assert 20 <= g["frames"]["cam0"] <= 24
    assert s["clock"]["offset_s"] is None and s["clock"]["frames_outside_log"] == 0
    assert s["clock"]["overlap_s"] == pytest.approx(13.623 - 0.857, abs=1e-3)
    assert s["detection_sample"]["cam0"] == {"frames": 3, "found": {"plate0": 3}}
    assert s["kind"] == "eye-to-hand, single-joint sweeps, encoder log"


def test_inspect_bag(tmp_path, capsys):
    bag = write_bag(SOURCE, tmp_path / "bag", rows=range(0, 144, 24))
    assert main(["inspect", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "/joint_states  sensor_msgs/msg/JointState  (7201 messages)" in out and "give --images" in out
    args = [
        "inspect",
        str(bag),
        "--images",
        COMPRESSED,
        "--joints",
        JOINTS,
        "--robot",
        str(SOURCE / "robot.urdf"),
    ]
    assert main([*args, "--target", str(SOURCE / "metadata.json"), "--sample", "2"]) == 0
    out = capsys.readouterr().out
    assert "motion segments (metadata.json)" in out and "shoulder_pan_joint: " in out
    assert "detection on 2 sample frames of cam0: plate0 2/2" in out and "K null" in out  # no --camera-info
