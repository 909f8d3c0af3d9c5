"""Safe writes: atomic files and output directories that never cost data.

The data-loss cases of issue 13 go through `jaxcal.cli.main` on a copy of
`data/ur5e_sweeps` and must fail before any calibration work (the pipeline is
replaced by a function that fails the test), leaving every input byte as it was.
"""

import hashlib
import json
import os
import shutil
import stat
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import pytest

from jaxcal.cli import main
from jaxcal.errors import OutputError
from jaxcal.io import _files
from jaxcal.io._files import (
    MARKER,
    atomic_directory,
    check_output_dir,
    output_lock,
    read_marker,
    rename_noreplace,
    write_marker,
    write_text_atomic,
)

SWEEPS = Path(__file__).resolve().parents[1] / "data" / "ur5e_sweeps"


@pytest.fixture
def umask_022():
    old = os.umask(0o022)
    yield
    os.umask(old)


def _digest(root: Path) -> dict:
    """SHA-256 of every file under `root` (or of `root` itself), by relative path."""
    root = Path(root)
    if root.is_file():
        return {"": hashlib.sha256(root.read_bytes()).hexdigest()}
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture
def dataset(tmp_path) -> Path:
    """A copy of data/ur5e_sweeps in tmp_path/work/ur5e (its parent holds nothing else)."""
    dst = tmp_path / "work" / "ur5e"
    shutil.copytree(SWEEPS, dst)
    return dst


@pytest.fixture
def no_calibration(monkeypatch):
    """Any call into the calibration pipeline fails the test: the checks come first."""

    def refuse(*args, **kwargs):
        raise AssertionError("the calibration started although the output check should have failed first")

    # The command's work module binds `calibrate` when first imported: imported here, before the
    # patch, so that it does not keep the refusing stand-in for the tests after this one.
    import jaxcal.cli._calibrate_run  # noqa: F401

    monkeypatch.setattr("jaxcal.pipeline.calibrate", refuse)
    monkeypatch.setattr("jaxcal.cli._calibrate_run.calibrate", refuse)
    monkeypatch.setattr("jaxcal.sim.simulate.simulate", refuse)


def _cli_fails(argv, capsys, *words) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("jaxcal: error: "), err
    for w in words:
        assert w in err, err
    return err


# --------------------------------------------------------------------------- atomic files and directories


def test_atomic_file_mode_and_content(tmp_path, umask_022):
    path = tmp_path / "a.txt"
    path.write_text("old")
    write_text_atomic(path, "new")
    assert path.read_text() == "new"
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_atomic_directory_mode_marker_and_failure(tmp_path, umask_022):
    dest = tmp_path / "out"
    with atomic_directory(dest, kind="result") as tmp:
        (tmp / "x").write_text("1")
    assert stat.S_IMODE(dest.stat().st_mode) == 0o755
    marker = read_marker(dest)
    assert marker["tool"] == "jaxcal" and marker["kind"] == "result" and marker["version"]
    with pytest.raises(RuntimeError), atomic_directory(dest, overwrite=True, kind="result") as tmp:
        (tmp / "y").write_text("2")
        raise RuntimeError("boom")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # nothing partial left, no lock file
    assert sorted(p.name for p in dest.iterdir()) == [MARKER, "x"]  # the old result is untouched
    with atomic_directory(dest, overwrite=True, kind="result") as tmp:
        (tmp / "z").write_text("3")
    assert sorted(p.name for p in dest.iterdir()) == [MARKER, "z"]  # replaced: it was jaxcal's
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_killed_runs_temporary_directory_is_removed_by_the_next_run(tmp_path):
    """A run killed outright (SIGKILL: nothing of it runs again) leaves its temporary directory
    beside the output; the next run on that output removes it once it holds the lock, and
    nothing else: not another output's, nor a file or folder that only looks like one."""
    dest = tmp_path / "out"
    killed = textwrap.dedent(
        f"""
        import os, signal
        from jaxcal.io._files import atomic_directory
        with atomic_directory({str(dest)!r}, kind="result") as tmp:
            (tmp / "half.json").write_text("{{")
            os.kill(os.getpid(), signal.SIGKILL)
        """
    )
    run = subprocess.run([sys.executable, "-c", killed], capture_output=True, check=False)
    assert run.returncode == -9, run.stderr
    left = [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    assert len(left) == 1 and left[0].startswith(".out."), left
    kept = [".outer.abcdefgh.tmp", ".out.abcdefghi.tmp", ".out.x.tmp"]  # other names, not ours
    for name in kept:
        (tmp_path / name).mkdir()
    (tmp_path / ".out.abcdefgh.tmp").write_text("a user's file")
    with atomic_directory(dest, kind="result") as tmp:
        (tmp / "result.json").write_text("{}")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([*kept, ".out.abcdefgh.tmp", "out"])
    assert (tmp_path / ".out.abcdefgh.tmp").read_text() == "a user's file"


def test_atomic_directory_creates_missing_parents_and_removes_them_on_failure(tmp_path):
    dest = tmp_path / "a" / "b" / "out"
    with pytest.raises(RuntimeError), atomic_directory(dest, kind="result"):
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    with atomic_directory(dest, kind="result") as tmp:
        (tmp / "x").write_text("1")
    assert (dest / "x").read_text() == "1"


# --------------------------------------------------------------------------- the rules


@pytest.mark.parametrize("overwrite", [False, True])
def test_output_may_not_be_contain_or_lie_inside_an_input(dataset, overwrite):
    before = _digest(dataset.parent)
    cases = [
        (dataset, "is the input"),
        (dataset.parent, "contains the input"),
        (dataset / "result", "lies inside the input"),
        (dataset / "images" / "cam0", "lies inside the input"),
    ]
    for out, words in cases:
        with pytest.raises(OutputError, match=words):
            check_output_dir(out, inputs=[dataset], overwrite=overwrite, kind="result")
        with (
            pytest.raises(OutputError, match=words),
            atomic_directory(out, inputs=[dataset], overwrite=overwrite, kind="result"),
        ):
            raise AssertionError("never reached")
    assert _digest(dataset.parent) == before


def test_symbolic_links_are_resolved(dataset, tmp_path):
    link = tmp_path / "link_to_work"
    link.symlink_to(dataset.parent, target_is_directory=True)
    with pytest.raises(OutputError, match="is the input"):
        check_output_dir(link / "ur5e", inputs=[dataset], overwrite=True, kind="result")
    with pytest.raises(OutputError, match="lies inside the input"):
        check_output_dir(link / "ur5e" / "res", inputs=[dataset], kind="result")
    # The input named through a link, the output directly.
    with pytest.raises(OutputError, match="contains the input"):
        check_output_dir(dataset.parent, inputs=[link / "ur5e"], overwrite=True, kind="result")
    # An output that is itself a link is refused (renaming would replace the link, not its target).
    out_link = tmp_path / "out_link"
    out_link.symlink_to(tmp_path / "elsewhere")
    with pytest.raises(OutputError, match="symbolic link"):
        check_output_dir(out_link, kind="result")


def test_overwrite_replaces_only_a_directory_jaxcal_wrote_of_the_same_kind(tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("years of work")
    with pytest.raises(OutputError, match="not empty"):
        check_output_dir(mine, kind="result")
    with pytest.raises(OutputError, match="not written by jaxcal.*Delete it yourself"):
        check_output_dir(mine, overwrite=True, kind="result")
    (mine / MARKER).write_text("{not json")  # a broken marker is no marker
    with pytest.raises(OutputError, match="not written by jaxcal"):
        check_output_dir(mine, overwrite=True, kind="result")
    write_marker(mine, "dataset")
    with pytest.raises(OutputError, match="holds a jaxcal dataset, not a result"):
        check_output_dir(mine, overwrite=True, kind="result")
    assert (mine / "thesis.tex").read_text() == "years of work"
    write_marker(mine, "result")
    assert check_output_dir(mine, overwrite=True, kind="result").replaces is not None
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="not a directory"):
        check_output_dir(tmp_path / "file", overwrite=True, kind="result")
    with pytest.raises(OutputError, match="cannot be created"):
        check_output_dir(tmp_path / "file" / "out", kind="result")
    assert check_output_dir(tmp_path / "new", kind="result").replaces is None
    (tmp_path / "empty").mkdir()
    assert check_output_dir(tmp_path / "empty", kind="result").replaces is None


def test_overwrite_never_deletes_a_file_added_to_a_result(tmp_path):
    """A result jaxcal wrote lists its files in its marker: a file the user put there since is
    named and kept, and --overwrite refused until it is moved out."""
    dest = tmp_path / "out"
    with atomic_directory(dest, kind="result") as tmp:
        (tmp / "result.json").write_text("{}")
        (tmp / "plots").mkdir()
        (tmp / "plots" / "a.png").write_bytes(b"png")
    assert json.loads((dest / MARKER).read_text())["files"] == ["plots/a.png", "result.json"]
    (dest / "plots" / "my_notes.txt").write_text("keep me")
    with pytest.raises(
        OutputError, match=r"jaxcal did not write there \(plots/my_notes.txt\).*Move them out"
    ):
        with atomic_directory(dest, overwrite=True, kind="result") as tmp:
            (tmp / "result.json").write_text("{}")
    assert (dest / "plots" / "my_notes.txt").read_text() == "keep me"
    (dest / "plots" / "my_notes.txt").unlink()  # moved out: replaced as before
    with atomic_directory(dest, overwrite=True, kind="result") as tmp:
        (tmp / "result.json").write_text('{"new": 1}')
    assert json.loads((dest / "result.json").read_text()) == {"new": 1}


# --------------------------------------------------------------------------- races


@pytest.mark.parametrize("native", [True, False], ids=["renameat2", "fallback"])
def test_a_directory_that_appears_during_the_run_is_refused_not_replaced(tmp_path, monkeypatch, native):
    if not native:
        monkeypatch.setattr(_files, "_renameat2", None)
    elif _files._renameat2 is None:
        pytest.skip("no renameat2 in this C library")
    dest = tmp_path / "out"
    with pytest.raises(OutputError, match="appeared there during the run"):
        with atomic_directory(dest, kind="result") as tmp:
            (tmp / "result.json").write_text("{}")
            dest.mkdir()  # another process, meanwhile
            (dest / "theirs.txt").write_text("theirs")
    assert [p.name for p in dest.iterdir()] == ["theirs.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    # An empty directory that appeared holds nothing to lose: it is replaced.
    other = tmp_path / "other"
    with atomic_directory(other, kind="result") as tmp:
        (tmp / "x").write_text("1")
        other.mkdir()
    assert (other / "x").read_text() == "1"


def test_rename_noreplace_refuses_an_existing_destination(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "f").write_text("keep")
    with pytest.raises(FileExistsError):
        rename_noreplace(tmp_path / "a", tmp_path / "b")
    assert (tmp_path / "b" / "f").read_text() == "keep" and (tmp_path / "a").is_dir()
    rename_noreplace(tmp_path / "a", tmp_path / "c")
    assert (tmp_path / "c").is_dir() and not (tmp_path / "a").exists()


def test_a_result_that_replaced_the_checked_one_during_the_run_is_refused(tmp_path):
    dest = tmp_path / "out"
    checked = check_output_dir(dest, kind="result")  # absent when the run started
    with atomic_directory(tmp_path / "elsewhere", kind="result") as tmp:
        (tmp / "theirs").write_text("theirs")
    os.rename(tmp_path / "elsewhere", dest)  # a jaxcal result appears at dest meanwhile
    with pytest.raises(OutputError, match="different directory"):
        with atomic_directory(dest, overwrite=True, kind="result", checked=checked) as tmp:
            (tmp / "mine").write_text("mine")
    assert sorted(p.name for p in dest.iterdir()) == [MARKER, "theirs"]


_HOLDER = textwrap.dedent(
    """
    import sys, time
    from jaxcal.io._files import atomic_directory
    with atomic_directory(sys.argv[1], kind="result") as tmp:
        (tmp / "who").write_text("first")
        print("holding", flush=True)
        sys.stdin.readline()
    """
)


def _holder(out: Path) -> subprocess.Popen:
    """Another process writing `out` through atomic_directory, until its stdin gets a line."""
    p = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, str(out)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    assert p.stdout.readline().strip() == "holding"
    return p


def test_concurrent_runs_on_one_output_give_one_result_and_one_clear_error(tmp_path, dataset, capsys):
    out = tmp_path / "res"
    first = _holder(out)
    try:
        with pytest.raises(OutputError, match="another jaxcal run is writing there"):
            with atomic_directory(out, kind="result") as tmp:
                (tmp / "who").write_text("second")
        # The command line fails at once too, before any work.
        before = _digest(dataset)
        _cli_fails(["calibrate", str(dataset), "--out", str(out), "--quiet"], capsys, "another jaxcal run")
        assert _digest(dataset) == before
    finally:
        first.communicate("go\n", timeout=60)
    assert first.returncode == 0
    assert (out / "who").read_text() == "first"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res", "work"]  # the lock file is gone
    with output_lock(out):  # free again
        pass


# --------------------------------------------------------------------------- the command line


def test_cli_refuses_every_data_loss_case_before_any_work(dataset, tmp_path, capsys, no_calibration):
    before = _digest(dataset.parent)
    ds = str(dataset)
    _cli_fails(["calibrate", ds, "--out", ds, "--overwrite"], capsys, "is the input")
    _cli_fails(["calibrate", ds, "--out", ds], capsys, "is the input")
    _cli_fails(["calibrate", ds, "--out", str(dataset.parent), "--overwrite"], capsys, "contains the input")
    _cli_fails(["calibrate", ds, "--out", str(dataset / "result")], capsys, "lies inside the input")
    _cli_fails(["calibrate", ds, "--out", str(dataset / "images"), "--overwrite"], capsys, "lies inside")
    link = tmp_path / "link"
    link.symlink_to(dataset, target_is_directory=True)
    _cli_fails(["calibrate", ds, "--out", str(link), "--overwrite"], capsys, "symbolic link")
    _cli_fails(["calibrate", str(link), "--out", str(dataset.parent), "--overwrite"], capsys, "contains")
    # A directory jaxcal did not write is never replaced, --overwrite or not.
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "notes.txt").write_text("mine")
    _cli_fails(["calibrate", ds, "--out", str(theirs), "--overwrite"], capsys, "not written by jaxcal")
    _cli_fails(["calibrate", ds, "--out", str(theirs)], capsys, "not empty")
    _cli_fails(["demo", "--out", str(theirs)], capsys, "not written by jaxcal")
    _cli_fails(["demo", "--out", str(dataset.parent)], capsys, "not written by jaxcal")
    _cli_fails(["simulate", "--out", ds, "--overwrite"], capsys, "not written by jaxcal")
    _cli_fails(["simulate", "--out", str(theirs), "--overwrite"], capsys, "not written by jaxcal")
    urdf = str(dataset / "robot.urdf")
    _cli_fails(["simulate", "--robot", urdf, "--out", str(dataset.parent), "--overwrite"], capsys, "contains")
    # A dataset jaxcal wrote is not a result: calibrate --overwrite leaves it alone.
    write_marker(theirs, "dataset")
    _cli_fails(["calibrate", ds, "--out", str(theirs), "--overwrite"], capsys, "holds a jaxcal dataset")
    assert _digest(dataset.parent) == before
    assert (theirs / "notes.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link", "theirs", "work"]  # no lock files left


def test_write_outputs_refuses_the_results_dataset(dataset):
    from jaxcal.report import write_outputs

    before = _digest(dataset)
    result = SimpleNamespace(dataset=dataset)  # the check comes before anything reads the result
    for out in (dataset, dataset / "result", dataset.parent):
        with pytest.raises(OutputError, match="input"):
            write_outputs(result, out, overwrite=True)
    assert _digest(dataset) == before


def test_workers_must_be_a_positive_integer(dataset, tmp_path, capsys, no_calibration):
    for argv in (
        ["calibrate", str(dataset), "--out", str(tmp_path / "r"), "--config", "workers=0"],
        ["calibrate", str(dataset), "--out", str(tmp_path / "r"), "--config", "workers=-2"],
        ["calibrate", str(dataset), "--out", str(tmp_path / "r"), "--config", "workers=two"],
        ["demo", "--out", str(tmp_path / "d"), "--config", "workers=0"],
        ["demo", "--out", str(tmp_path / "d"), "--workers", "0"],  # the former flag, for one release
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "workers" in err and ": expected a positive integer" in err, err
    assert not (tmp_path / "r").exists() and not (tmp_path / "d").exists()


def test_demo_directory_is_marked_and_removed_again_on_failure(tmp_path, no_calibration, capsys):
    out = tmp_path / "demo"
    # The (replaced) simulator fails: the demo directory this run created is removed again.
    with pytest.raises(AssertionError, match="calibration started"):
        main(["demo", "--out", str(out), "--quiet"])
    assert not out.exists() and list(tmp_path.iterdir()) == []
    out.mkdir()
    write_marker(out, "demo")
    (out / "dataset").mkdir()
    with pytest.raises(AssertionError):
        main(["demo", "--out", str(out), "--quiet"])
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "dataset"]  # an earlier demo's, kept
    assert json.loads((out / MARKER).read_text())["kind"] == "demo"
