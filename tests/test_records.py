"""The typed result records (`jaxcal.records`): their JSON blocks, their mapping view
(the dict results' reads keep working) and the way back from JSON (`from_plain`)."""

import json

import numpy as np
import pytest

from jaxcal.errors import DatasetError
from jaxcal.io.result import read_result
from jaxcal.records import (
    Clock,
    FrameCounts,
    Intrinsics,
    JointError,
    Named,
    PoseError,
    ValidationReport,
    from_plain,
    plain,
    row_of,
)


def _validation() -> ValidationReport:
    return ValidationReport(
        configurations=10,
        ee_point="marker",
        ee_rms_mm_before=5.0,
        ee_max_mm_before=9.0,
        ee_rms_mm_after=0.5,
        ee_max_mm_after=0.9,
        ee_rms_mm_two_stage=0.6,
        ee_max_mm_two_stage=1.0,
        refined=True,
        T_cam_base_error=PoseError(0.1, 0.01, gauge="same fit", raw_trans_mm=0.3, raw_rot_deg=0.02),
        parameter_errors=(
            JointError("j1", 0.01, axis_position_mm=0.1, ratio_percent=None, zero_offset_deg=0.2),
            JointError("j2", 0.02, ratio_percent=0.5, zero_offset_mm=0.3),
        ),
        true_ratios=(100.0, 50.0),
    )


def test_an_optional_key_is_written_only_when_set():
    c = Clock(offset_s=0.04, std_s=None, estimated=False, drift_ppm=0.0)
    assert plain(c) == {"offset_s": 0.04, "std_s": None, "estimated": False, "drift_ppm": 0.0}
    assert "given_s" not in c and c.given_s is None
    with pytest.raises(KeyError):
        c["given_s"]
    assert plain(Clock(0.04, 1e-6, True, 0.0, given_s=0.0))["given_s"] == 0.0


def test_named_and_keyed_rows_are_json_objects():
    f = FrameCounts(
        10, 9, 1, 0, 0, 0, used_per_joint=(Named("j1", 4), Named("j2", 5)), dropped_capture_indices=(3,)
    )
    assert f["used_per_joint"] == {"j1": 4, "j2": 5} and f.used("j2") == 5
    assert f["dropped_capture_indices"] == [3]
    v = plain(_validation())
    assert v["parameter_errors"] == {
        "j1": {
            "axis_direction_deg": 0.01,
            "axis_position_mm": 0.1,
            "ratio_percent": None,
            "zero_offset_deg": 0.2,
        },
        "j2": {"axis_direction_deg": 0.02, "ratio_percent": 0.5, "zero_offset_mm": 0.3},
    }
    assert "other_cameras" not in v and "T_cam_base_error_two_stage" not in v
    assert row_of(_validation().parameter_errors, "joint", "j2").ratio_percent == 0.5


def test_a_record_reads_as_its_json_block():
    """Code written against the dict results (`v["ee_rms_mm_after"]`, `for k in v`) keeps working."""
    v = _validation()
    assert v["ee_rms_mm_after"] == v.ee_rms_mm_after == 0.5
    assert {k: v[k] for k in v if k.startswith("ee_")}["ee_max_mm_two_stage"] == 1.0
    assert v["T_cam_base_error"]["trans_mm"] == 0.1 and v.get("missing", 3) == 3
    assert dict(v) == plain(v) and json.loads(json.dumps(plain(v))) == plain(v)


def test_from_plain_inverts_plain():
    v = _validation()
    back = from_plain(ValidationReport, json.loads(json.dumps(plain(v))))
    assert plain(back) == plain(v) and back.parameter_errors[1] is not None
    assert isinstance(back.T_cam_base_error, PoseError) and back.true_ratios == (100.0, 50.0)


def test_arrays_come_back_as_float64_arrays():
    K = np.diag([600.0, 600.0, 1.0])
    i = from_plain(Intrinsics, plain(Intrinsics("metadata", K=K, distortion=np.zeros(5))))
    assert i.K.dtype == np.float64 and np.array_equal(i.K, K) and i.rms_px is None


def test_read_result_names_a_file_that_is_not_one(tmp_path):
    with pytest.raises(DatasetError, match="no such file"):
        read_result(tmp_path / "result.json")
    (tmp_path / "result.json").write_text('{"schema": "other"}')
    with pytest.raises(DatasetError, match="not a result.json"):
        read_result(tmp_path / "result.json")
