"""One vocabulary across the command line: an option name means one thing (one kind of action, one
type, one set of choices) in every subcommand that takes it; the spellings renamed for it still
work for one release, with a warning naming the new one; `inspect --json` writes a file like every
other `--json`."""

import argparse
import json
from pathlib import Path

import pytest

from jaxcal.cli import RENAMED, _renamed, build_parser, main, option_meanings

ROOT = Path(__file__).resolve().parents[1]
TRACKER = ROOT / "data" / "ur5_tracker" / "grid"


def _subcommands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def test_one_option_name_has_one_meaning():
    meanings = option_meanings()
    assert len(meanings) > 100 and len(meanings["--out"]) > 5  # the parsers were read
    clashes = {name: by_command for name, by_command in meanings.items() if len(set(by_command.values())) > 1}
    assert not clashes, "\n".join(f"{n}: {c}" for n, c in clashes.items())


@pytest.mark.parametrize(("command", "old"), sorted(RENAMED))
def test_a_renamed_option_still_works_for_one_release_with_a_warning(command, old, capsys):
    new = RENAMED[command, old]
    options = {s for a in _subcommands()[command]._actions for s in a.option_strings}
    assert new in options and old not in options  # the rename is real
    assert _renamed([command, "x", old, "v"]) == [command, "x", new, "v"]
    assert f"`jaxcal {command} {old}` is now `{new}`" in capsys.readouterr().err
    assert _renamed([command, f"{old}=v"]) == [command, f"{new}=v"] and new in capsys.readouterr().err
    # Another command's option of that name is left alone.
    other = next(c for c in _subcommands() if (c, old) not in RENAMED)
    assert _renamed([other, old, "v"]) == [other, old, "v"] and capsys.readouterr().err == ""


def test_inspect_json_writes_a_file_or_prints_and_the_bare_flag_still_prints(tmp_path, capsys):
    def summary(text: str) -> dict:
        return {k: v for k, v in json.loads(text).items() if k != "seconds"}  # the time it took

    out = tmp_path / "summary.json"
    assert main(["inspect", str(TRACKER), "--json", str(out)]) == 0
    written = summary(out.read_text())
    assert written["device"]["samples"] == 1000 and f"wrote {out}" in capsys.readouterr().out
    assert main(["inspect", str(TRACKER), "--json", "-"]) == 0
    assert summary(capsys.readouterr().out) == written
    # The former flag, before the dataset or at the end: printed, with a warning.
    for argv in (["inspect", "--json", str(TRACKER)], ["inspect", str(TRACKER), "--json"]):
        assert main(argv) == 0
        captured = capsys.readouterr()
        assert summary(captured.out) == written and "is now `--json -`" in captured.err
    # Never into what it reads.
    before = sorted(p.name for p in TRACKER.iterdir())
    assert main(["inspect", str(TRACKER), "--json", str(TRACKER / "summary.json")]) == 2
    assert "--json" in capsys.readouterr().err and sorted(p.name for p in TRACKER.iterdir()) == before


def test_montecarlo_sweeps_one_angle(capsys):
    assert main(["montecarlo", "--sweep-deg", "40,40,40,40,40,40", "--trials", "1"]) == 2
    assert "montecarlo --sweep-deg: one angle" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["calibrate", "x", "--terms", "auto,backlash"], "'auto' stands alone (it is not a family)"),
        (["calibrate", "x", "--terms", "backlash,compliance,backlash"], "a family named twice"),
        (["calibrate", "x", "--terms", "complaince"], "unknown terms ['complaince']"),
        (["plan", "--terms", "auto", "--out", "never.json"], "'auto' chooses terms from a capture's data"),
        (["plan", "--terms", "sag", "--out", "never.json"], "unknown terms ['sag']"),
    ],
)
def test_terms_take_one_vocabulary_and_say_what_is_wrong(argv, message, capsys):
    """`--terms` means the same in `calibrate` and `plan` (`none` in both); what one cannot take
    is refused saying why, not with a list that names it as known."""
    assert build_parser().parse_args(["plan", "--terms", "none"]).terms == ()
    with pytest.raises(SystemExit):
        main(argv)
    assert message in capsys.readouterr().err
    assert not Path("never.json").exists()
