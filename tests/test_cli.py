"""The command line: `jaxcal montecarlo`'s errors (its run is in test_montecarlo.py, where
it shares the compiled trial; `demo` and `calibrate` are in test_calibrate.py)."""

from jaxcal.cli import main


def test_unknown_robot_is_a_clear_error(capsys):
    assert main(["montecarlo", "--robot", "kuka", "--trials", "2"]) == 2
    assert "kuka" in capsys.readouterr().err
