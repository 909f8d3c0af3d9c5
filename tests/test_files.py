"""Atomic writes hand over files with the umask's permissions, never tempfile's private ones."""

import os
import stat

import pytest

from jaxcal.io._files import write_text_atomic
from jaxcal.io.dataset import atomic_directory


@pytest.fixture
def umask_022():
    old = os.umask(0o022)
    yield
    os.umask(old)


def test_atomic_file_mode_and_content(tmp_path, umask_022):
    path = tmp_path / "a.txt"
    path.write_text("old")
    write_text_atomic(path, "new")
    assert path.read_text() == "new"
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_atomic_directory_mode_and_failure(tmp_path, umask_022):
    dest = tmp_path / "out"
    with atomic_directory(dest) as tmp:
        (tmp / "x").write_text("1")
    assert stat.S_IMODE(dest.stat().st_mode) == 0o755
    with pytest.raises(RuntimeError), atomic_directory(dest, overwrite=True) as tmp:
        (tmp / "y").write_text("2")
        raise RuntimeError("boom")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # nothing partial left
    assert [p.name for p in dest.iterdir()] == ["x"]  # the old result is untouched
