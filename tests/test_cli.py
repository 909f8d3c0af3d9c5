"""The command line: `jaxcal montecarlo`'s errors (its run is in test_montecarlo.py, where
it shares the compiled trial; `demo` and `calibrate` are in test_calibrate.py)."""

import pytest

from jaxcal.cli import main


def test_unknown_robot_is_a_clear_error(capsys):
    assert main(["montecarlo", "--robot", "kuka", "--trials", "2"]) == 2
    assert "kuka" in capsys.readouterr().err


def test_a_negative_noise_is_refused_and_the_noise_is_said_per_axis(capsys):
    """A standard deviation below zero once ran (a new user's typo); the help says what the number is."""
    for option in ("--noise-mm", "--noise-deg"):
        with pytest.raises(SystemExit):
            main(["montecarlo", option, "-0.5", "--trials", "2"])
        assert f"argument {option}: expected a number of zero or more, got '-0.5'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["montecarlo", "--help"])
    assert "1-sigma per axis" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (
            ["calibrate", "data/ur5_tracker/grid", "--device-is-bse", "--out", "m1"],
            ["usage: jaxcal calibrate", "takes no option --device-is-bse (did you mean --device-is-base?)"],
        ),
        (
            ["verify", "out/ur5", "data/ur5_tracker/test", "--plto", "x.png"],
            ["usage: jaxcal verify", "takes no option --plto (did you mean --plot?)"],
        ),
        # A misspelt --out is named first, not reported as a missing --out only.
        (
            ["calibrate", "data/ur5e_sweeps", "--ouput", "m1"],
            [
                "takes no option --ouput (did you mean --out?)",
                "Also: the following arguments are required: --out",
            ],
        ),
    ],
)
def test_an_unknown_option_is_named_with_the_closest_known_one(argv, words, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # nothing could be written: refused while parsing
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and all(w in err for w in words), err
    assert not list(tmp_path.iterdir())


def test_a_negative_number_is_a_value_not_an_unknown_option(capsys):
    with pytest.raises(SystemExit) as e:  # the value, refused by --frames' own type (a count)
        main(["plan", "--region=-0.5,-0.5,0,0.5,0.5,0.5", "--frames", "-5", "--out", "x.json"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "argument --frames: expected a positive integer, got '-5'" in err, err
