"""`calibrate(clock=...)`: one option for the clock offset; the two flags it replaced are gone."""

import pytest

from jaxcal.cli import build_parser


def test_unknown_modes_and_the_old_keywords_are_refused():
    import jaxcal

    with pytest.raises(ValueError, match="'auto', 'estimate', 'given'.*'sometimes'"):
        jaxcal.calibrate("nowhere", clock="sometimes")
    # estimate_clock= and trust_clock= were deprecated for a release; now Python's own error.
    for old in ("estimate_clock", "trust_clock"):
        with pytest.raises(TypeError, match=old):
            jaxcal.calibrate("nowhere", **{old: True})


def test_the_command_line_offers_clock_as_a_key_and_the_old_flags_are_gone(capsys):
    from jaxcal.cli import parse

    p = build_parser()
    calibrate = next(a for a in p._subparsers._group_actions[0].choices.items() if a[0] == "calibrate")[1]
    text = calibrate.format_help()
    assert "clock = auto|estimate|given" in text and "--trust-clock" not in text
    assert parse(["calibrate", "DATA", "--out", "OUT", "--config", "clock=given"]).clock == "given"
    assert parse(["calibrate", "DATA", "--out", "OUT"]).clock == "auto"
    with pytest.raises(SystemExit):
        parse(["calibrate", "DATA", "--out", "OUT", "--trust-clock"])
    assert "takes no option --trust-clock" in capsys.readouterr().err


def test_the_command_lines_clock_modes_are_the_stages():
    from jaxcal import stages
    from jaxcal.cli._common import CLOCK_MODES

    assert CLOCK_MODES == stages.CLOCK_MODES
