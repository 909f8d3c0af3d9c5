"""`calibrate(clock=...)`: one option for the clock offset, the two flags it replaced deprecated."""

import warnings

import pytest

from jaxcal.cli import build_parser
from jaxcal.pipeline import _clock_mode


def test_clock_modes_pass_through_without_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert [_clock_mode(m, None, None) for m in ("auto", "estimate", "given")] == [
            "auto",
            "estimate",
            "given",
        ]


@pytest.mark.parametrize(
    "estimate_clock, trust_clock, mode",
    [(True, None, "estimate"), (None, True, "given"), (False, None, "auto"), (None, False, "auto")],
)
def test_the_old_flags_map_to_their_mode_with_a_deprecation_warning(estimate_clock, trust_clock, mode):
    with pytest.warns(DeprecationWarning, match="clock='estimate'.*clock='given'"):
        assert _clock_mode("auto", estimate_clock, trust_clock) == mode


def test_contradictions_and_unknown_modes_are_refused():
    with pytest.raises(ValueError, match="'auto', 'estimate', 'given'.*'sometimes'"):
        _clock_mode("sometimes", None, None)
    with pytest.warns(DeprecationWarning), pytest.raises(ValueError, match="contradict"):
        _clock_mode("auto", True, True)
    with (
        pytest.warns(DeprecationWarning),
        pytest.raises(ValueError, match="clock='given' and estimate_clock"),
    ):
        _clock_mode("given", True, None)


def test_the_command_line_offers_clock_and_hides_the_old_flags():
    p = build_parser()
    calibrate = next(a for a in p._subparsers._group_actions[0].choices.items() if a[0] == "calibrate")[1]
    text = calibrate.format_help()
    assert "--clock {auto,estimate,given}" in text and "--trust-clock" not in text
    args = p.parse_args(["calibrate", "DATA", "--out", "OUT", "--trust-clock"])
    assert args.trust_clock and args.clock == "auto"
    assert p.parse_args(["calibrate", "DATA", "--out", "OUT", "--clock", "given"]).clock == "given"


def test_the_command_lines_clock_modes_are_the_stages():
    from jaxcal import stages
    from jaxcal.cli._common import CLOCK_MODES

    assert CLOCK_MODES == stages.CLOCK_MODES
