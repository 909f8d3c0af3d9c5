"""The stages' typed rows (`jaxcal.records_stages`) and the frame table read as the dicts they replaced."""

import numpy as np
import pytest

from jaxcal.io.dataset import FrameTable
from jaxcal.records import plain
from jaxcal.records_stages import ByTarget, Check


def test_a_frame_by_target_reads_as_its_mapping():
    frame = ByTarget.of({"plate0": 1.5, "plate1": 2.5})
    assert frame["plate1"] == 2.5 and frame.get("plate0") == 1.5 and frame.get("board") is None
    assert "plate0" in frame and "board" not in frame and len(frame) == 2 and bool(frame)
    assert list(frame) == ["plate0", "plate1"] and list(frame.values()) == [1.5, 2.5]
    assert dict(frame.items()) == {"plate0": 1.5, "plate1": 2.5}
    with pytest.raises(KeyError):
        frame["board"]
    assert not ByTarget() and len(ByTarget()) == 0


def test_a_check_is_written_as_the_row_it_was():
    row = Check("ee_sigma_mm", 0.25, 1.0, True)
    assert plain((row,)) == [{"check": "ee_sigma_mm", "value": 0.25, "limit": 1.0, "passed": True}]
    assert row["value"] == row.value == 0.25


def test_the_frame_table_reads_as_its_columns():
    t = FrameTable(
        camera=np.array(["cam0", "cam1"]),
        frame=np.array([3, 4]),
        timestamp=np.array([0.1, 0.2]),
        file=np.array(["a.png", "b.png"]),
    )
    assert list(t) == ["camera", "frame", "timestamp", "file"] and len(t) == 4
    assert t["file"] is t.file and t["frame"][1] == 4
    with pytest.raises(KeyError):
        t["row"]
