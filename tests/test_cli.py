"""The command line: `jaxcal montecarlo` (`demo` and `calibrate` are in test_calibrate.py)."""

import json

import pytest

from jaxcal.cli import main


@pytest.mark.slow
def test_montecarlo_detail_prints_before_after_and_succeeds(capsys):
    assert main(["montecarlo", "--detail", "--trials", "8", "--frames", "24"]) == 0
    out = capsys.readouterr().out
    assert "Before / after" in out and "Identifiability" in out
    assert "shoulder_pan_joint.zero_offset" in out  # named as held at nominal


def test_montecarlo_writes_json_atomically(tmp_path, capsys):
    out = tmp_path / "sub" / "mc.json"
    assert main(["montecarlo", "--trials", "8", "--frames", "24", "--json", str(out)]) == 0
    summary = json.loads(out.read_text())
    assert summary["trials"] == 8 and summary["success_rate"] == 1.0
    assert summary["ee_rms_mm_median"] < 1.0
    assert [p.name for p in out.parent.iterdir()] == ["mc.json"]  # no temp files left


def test_unknown_robot_is_a_clear_error(capsys):
    assert main(["montecarlo", "--robot", "kuka", "--trials", "2"]) == 2
    assert "kuka" in capsys.readouterr().err
