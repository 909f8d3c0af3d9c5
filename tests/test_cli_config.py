"""Rarely used knobs are configuration keys (`jaxcal._configkeys`): set in a TOML file
(`--config FILE`, a table per subcommand) or one at a time (`--config KEY=VALUE`), later entries
winning, converted and checked as the flags they replaced were; a key the command does not take,
or a value it cannot use, is refused naming the file, the table and the key; the replaced flags
still work for one release, with a warning; docs/config.md lists every key.

`python tests/test_cli_config.py` rewrites docs/config.md's list of keys."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from jaxcal import _configkeys as _config
from jaxcal.cli import Refused, main, option_meanings, parse, subcommands

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "config.md"
MARK = "<!-- the keys, written by `python tests/test_cli_config.py` -->"


def _write(tmp_path, text: str, name: str = "cell.toml") -> str:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return str(path)


CALIBRATE = ["calibrate", "DATA", "--out", "OUT"]


def test_a_file_and_inline_keys_set_what_the_flags_set(tmp_path):
    cell = _write(
        tmp_path,
        '[calibrate]\nworkers = 2\narc-loss = "huber"\ncv_folds = 3\nrefine-intrinsics = false\n'
        "single-camera = true\n[plan]\nstarts = 7\n",
    )
    args = parse([*CALIBRATE, "--config", cell])
    assert (args.workers, args.arc_loss, args.cv_folds) == (2, "huber", 3)
    assert args.refine_intrinsics is False and args.single_camera is True
    # The defaults where nothing is said: the flags' own.
    plain = parse(CALIBRATE)
    assert (plain.arc_loss, plain.cv_folds, plain.refine_intrinsics, plain.single_camera) == (
        "cauchy",
        5,
        None,
        False,
    )
    # Later entries win, a file's or an inline one's; `false` sets a switch back.
    args = parse([*CALIBRATE, "--config", cell, "--config", "cv-folds=0", "--config", "single-camera=no"])
    assert (args.cv_folds, args.single_camera, args.arc_loss) == (0, False, "huber")
    args = parse([*CALIBRATE, "--config", "cv-folds=0", "--config", cell])
    assert args.cv_folds == 3
    # The plan's table is the plan's.
    assert parse(["plan", "--config", cell]).starts == 7


def test_values_of_every_shape_convert_as_the_flags(tmp_path, capsys):
    cell = _write(
        tmp_path,
        "[simulate]\ndistortion = [0.1, 0, 0, 0.002, 0]\nhome-deg = [0, -20, 30, -15, 20, 0]\n"
        "no-encoders = true\nclock-offset-ms = 20\n",
    )
    by_file = parse(["simulate", "--out", "X", "--config", cell])
    inline = parse(
        [
            "simulate",
            "--out",
            "X",
            "--config",
            "distortion=0.1,0,0,0.002,0",
            "--config",
            "home-deg=0,-20,30,-15,20,0",
        ]
        + ["--config", "no-encoders=true", "--config", "clock-offset-ms=20"]
    )
    old = parse(
        [
            "simulate",
            "--out",
            "X",
            "--distortion",
            "0.1",
            "0",
            "0",
            "0.002",
            "0",
            "--home-deg",
            "0,-20,30,-15,20,0",
        ]
        + ["--no-encoders", "--clock-offset-ms", "20"]
    )
    # ... and a list as the help (and a TOML file) writes it.
    bracketed = parse(["simulate", "--out", "X", "--config", "distortion=[0.1, 0, 0, 0.002, 0]"])
    assert bracketed.distortion == [0.1, 0.0, 0.0, 0.002, 0.0]
    for args in (by_file, inline, old):
        assert (
            args.distortion == [0.1, 0.0, 0.0, 0.002, 0.0]
            and args.no_encoders
            and args.clock_offset_ms == 20.0
        )
        assert args.home_deg == (0.0, -20.0, 30.0, -15.0, 20.0, 0.0)
    # The replaced flags: each named once, with its key, for one release.
    err = capsys.readouterr().err
    for flag in ("--distortion", "--home-deg", "--no-encoders", "--clock-offset-ms"):
        key = flag[2:]
        assert f"`jaxcal simulate {flag}` is now the configuration key {key} (--config {key}=VALUE" in err
    assert err.count("warning") == 4


@pytest.mark.parametrize(
    ("argv", "text", "message"),
    [
        (
            CALIBRATE,
            "[calibrate]\narc-los = 'huber'\n",
            r"cell.toml: \[calibrate\] arc-los: jaxcal calibrate has no "
            r"configuration key arc-los \(did you mean arc-loss\?\)",
        ),
        (
            CALIBRATE,
            "[calibrat]\narc-loss = 'huber'\n",
            r"cell.toml: \[calibrat\] is not a jaxcal subcommand \(did "
            r"you mean calibrate\?\)",
        ),
        (CALIBRATE, "starts = 3\n", r"cell.toml: starts: jaxcal calibrate has no configuration key starts"),
        (
            CALIBRATE,
            "workers = 3\n[plan]\nstarts = 3\n",
            r"cell.toml: workers outside a table; a file with \[subcommand\]",
        ),
        (
            CALIBRATE,
            "[calibrate]\ncv-folds = 1000\n",
            r"cell.toml: \[calibrate\] cv-folds: .*100",
        ),
        (
            CALIBRATE,
            "[calibrate]\narc-loss = 'l1'\n",
            r"cell.toml: \[calibrate\] arc-loss: .*invalid choice: 'l1'",
        ),
        (
            CALIBRATE,
            "[calibrate]\nsingle-camera = 'maybe'\n",
            r"single-camera: expected true or false, got 'maybe'",
        ),
        (CALIBRATE, "[calibrate]\ncv-folds = true\n", r"cv-folds: expected a value, not true"),
        (CALIBRATE, "[calibrate\n", r"cell.toml: not TOML: "),
        (
            ["simulate", "--out", "X"],
            "[simulate]\nclock-offset-ms = nan\n",
            r"\[simulate\] clock-offset-ms: expected a finite number, got 'nan'",
        ),
        (["verify", "R", "D"], "x = 1\n", None),  # verify takes no configuration: no --config at all
    ],
)
def test_what_cannot_be_used_is_named_by_file_table_and_key(tmp_path, argv, text, message, capsys):
    cell = _write(tmp_path, text)
    before = Path(cell).read_bytes()
    if message is None:
        with pytest.raises(SystemExit):
            parse([*argv, "--config", cell])
        assert "takes no option --config" in capsys.readouterr().err
    else:
        with pytest.raises(Refused, match=message):
            parse([*argv, "--config", cell])
    assert Path(cell).read_bytes() == before  # read, never written


def test_inline_keys_and_missing_files_are_named(capsys):
    with pytest.raises(
        Refused, match=r"--config cv-fold=3: jaxcal calibrate has no configuration key cv-fold \(did you "
    ):
        parse([*CALIBRATE, "--config", "cv-fold=3"])
    with pytest.raises(Refused, match=r"--config nowhere.toml: no such file \(and not a KEY=VALUE\)"):
        parse([*CALIBRATE, "--config", "nowhere.toml"])
    with pytest.raises(Refused, match=r"--config workers=0: \S"):
        parse([*CALIBRATE, "--config", "workers=0"])
    # A misspelt former flag is pointed at the key, and main says so with exit 2.
    with pytest.raises(SystemExit) as exit:
        main([*CALIBRATE, "--arc-los", "huber"])
    assert exit.value.code == 2
    assert "did you mean the configuration key arc-loss: --config arc-loss=VALUE?" in capsys.readouterr().err


def test_another_commands_key_or_flag_is_not_taken(capsys):
    # simulate-tracker's knob `bad-fraction` is not simulate's: refused, as any option it does not take.
    with pytest.raises(SystemExit):
        parse(["simulate", "--out", "X", "--bad-fraction", "0.1"])
    assert "takes no option --bad-fraction" in capsys.readouterr().err
    with pytest.raises(Refused, match="jaxcal simulate has no configuration key bad-fraction"):
        parse(["simulate", "--out", "X", "--config", "bad-fraction=0.1"])


def _every_key():
    for command, parser in subcommands().items():
        for name, action in _config.keys(parser).items():
            yield command, name, action


def test_every_key_takes_its_own_default_and_is_listed_in_help_and_docs():
    doc = DOC.read_text(encoding="utf-8")
    keys = list(_every_key())
    assert len(keys) > 90
    for command, name, action in keys:
        default = action.default
        if isinstance(default, (list, tuple)):
            value = ("x" if "resolution" in getattr(action.type, "__qualname__", "") else ",").join(
                map(str, default)
            )
        elif isinstance(default, bool):
            value = str(default).lower()
        elif default is None or action.type is not None and not isinstance(default, (int, float, str)):
            continue
        else:
            value = str(default)
        args = parse([command, *_positional(command), "--config", f"{name}={value}"])
        assert getattr(args, action.dest) == (tuple(default) if isinstance(default, tuple) else default), (
            command,
            name,
        )
        assert f"| `{name}` |" in doc, f"docs/config.md lacks {command}'s {name}"
    for command, parser in subcommands().items():
        if _config.keys(parser):
            assert "configuration keys (--config KEY=VALUE" in parser.format_help(), command


def _positional(command: str) -> list[str]:
    """The arguments `command` needs to parse (not to run)."""
    needs = {
        "calibrate": ["DATA", "--out", "OUT"],
        "import-bag": [
            "BAG",
            "--out",
            "OUT",
            "--images",
            "i",
            "--joints",
            "j",
            "--robot",
            "r",
            "--target",
            "t",
        ],
        "inspect": ["DATA"],
        "import-csv": ["T.csv", "--out", "O", "--robot", "r", "--joint-columns", "a,b", "--joint-unit", "deg"]
        + ["--xyz", "x,y,z", "--length-unit", "mm", "--sigma-mm", "0.1"],
        "simulate": ["--out", "O"],
        "simulate-tracker": ["--out", "O"],
        "simulate-plan": ["PLAN", "--out", "O"],
        "simulate-handeye": ["--out", "O"],
        "handeye": ["CAPTURE", "--out", "O"],
        "certify": ["RESULT", "--region", "0,0,0,1,1,1"],
    }
    return needs.get(command, [])


def test_docs_list_the_keys_as_the_parser_has_them():
    doc = DOC.read_text(encoding="utf-8")
    assert MARK in doc, "docs/config.md lost its marker"
    assert doc.split(MARK)[1].strip() == _config.reference(subcommands()).strip(), (
        "docs/config.md is behind the parser: run python tests/test_cli_config.py"
    )


def test_the_configuration_keys_are_fewer_flags():
    """Issue 50's count: the flags over all subcommands at most 150, the keys apart."""
    flags = sum(len(by_command) for by_command in option_meanings(keys=False).values())
    everything = sum(len(by_command) for by_command in option_meanings().values())
    assert flags <= 150 and everything - flags > 90


def test_the_plans_help_states_the_planners_default_noise():
    """`jaxcal plan`'s parser imports nothing of the planner: its help states the default noise
    the planner applies (`sigma-px` not given)."""
    from jaxcal.cli._plan import SIGMA_PX_HELP
    from jaxcal.planning import DEFAULT_SIGMA_PX, sigma_for

    assert sigma_for(1280) == DEFAULT_SIGMA_PX and sigma_for(1280, 0.1) == 0.1
    assert f"{sigma_for(1280):g} at 1280 px, {sigma_for(640):.3f} at 640" in SIGMA_PX_HELP
    # The rendered captures' corner noise it stands for (the refinement's: data/ur5e_sweeps at 800 px,
    # 0.054; a planned capture at 640 px, 0.056 and 0.061).
    assert 0.052 < sigma_for(800) < 0.056 and 0.056 < sigma_for(640) < 0.061
    assert parse(["plan", "--out", "p.json"]).sigma_px is None  # the planner's sigma_for
    assert parse(["plan", "--out", "p.json", "--config", "sigma-px=0.1"]).sigma_px == 0.1


def test_the_parsers_import_no_jax():
    """`import jaxcal` and every subcommand's parser (all of them, as `jaxcal --help` builds them)
    import neither JAX nor SciPy nor matplotlib: each takes a second, before a command has said what
    it does. JAX is still set up for the process: float64 and jaxcal's cache, once imported."""
    script = (
        "import sys\n"
        "from jaxcal.cli import build_parser\n"
        "from jaxcal.cli import parse\n"
        "build_parser()\n"
        "parse(['calibrate', 'data/ur5e_sweeps', '--out', 'r', '--terms', 'compliance'])\n"
        "parse(['demo', '--out', 'd'])\n"
        "heavy = sorted({'jax', 'scipy', 'matplotlib', 'equinox'} & set(sys.modules))\n"
        "assert not heavy, heavy\n"
        "import os\n"
        "assert not {'JAX_ENABLE_X64', 'JAX_COMPILATION_CACHE_DIR'} & set(os.environ)  # children inherit it\n"
        "import jax, jax.numpy as jnp\n"
        "assert jnp.ones(1).dtype == jnp.float64\n"
        "print(jax.config.jax_compilation_cache_dir)\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_ENABLE_X64", "JAX_COMPILATION_CACHE_DIR")}
    env["XDG_CACHE_HOME"] = "/nonexistent-cache-home"
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "/nonexistent-cache-home/jaxcal/xla"


def test_the_parsers_bounds_are_the_modules():
    """The bounds the light parsers state equal those of the modules they stand for."""
    from jaxcal import _montecarlo, _terms, certification
    from jaxcal.cli import _calibrate, _certify, _study

    assert (_study.MAX_TRIALS, _study.MAX_FRAMES) == (_montecarlo.MAX_TRIALS, _montecarlo.MAX_FRAMES)
    assert _certify.MAX_POSES == certification.MAX_POSES
    assert _calibrate.TERMS == tuple(_terms.TERMS)


if __name__ == "__main__":
    text = DOC.read_text(encoding="utf-8")
    head = text.split(MARK)[0]
    DOC.write_text(head + MARK + "\n\n" + _config.reference(subcommands()), encoding="utf-8")
    print(f"wrote {DOC}", file=sys.stderr)
