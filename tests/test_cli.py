"""The command line: `jaxcal montecarlo` (`demo` and `calibrate` are in test_calibrate.py)."""

import json

import pytest

from jaxcal.cli import main


@pytest.mark.slow
def test_montecarlo_detail_and_json(tmp_path, capsys):
    """One run (the trial program compiles once): the detailed trial's tables, then
    the summary written atomically."""
    out = tmp_path / "sub" / "mc.json"
    assert main(["montecarlo", "--detail", "--trials", "8", "--frames", "24", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "Before / after" in text and "Identifiability" in text
    assert "shoulder_pan_joint.zero_offset" in text  # named as held at nominal
    summary = json.loads(out.read_text())
    assert summary["trials"] == 8 and summary["success_rate"] == 1.0
    assert summary["ee_rms_mm_median"] < 1.0
    assert [p.name for p in out.parent.iterdir()] == ["mc.json"]  # no temp files left


def test_unknown_robot_is_a_clear_error(capsys):
    assert main(["montecarlo", "--robot", "kuka", "--trials", "2"]) == 2
    assert "kuka" in capsys.readouterr().err
