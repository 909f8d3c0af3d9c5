"""Notebooks are executed, so they never rot."""

import os
from pathlib import Path

import nbformat
import pytest
from conftest import CACHE_DIR
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_executes(path, monkeypatch, tmp_path):
    # The kernel shares the suite's compilation cache, draws into a file backend and runs
    # each notebook at its smallest size (the notebook reads JAXCAL_NOTEBOOK_SMALL).
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(CACHE_DIR))
    monkeypatch.setenv("JAXCAL_NOTEBOOK_SMALL", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.setenv("TMPDIR", str(tmp_path))  # the notebooks' scratch folders go with the test's
    nb = nbformat.read(path, as_version=4)
    NotebookClient(
        nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    ).execute()
    errors = [
        o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []) if o.output_type == "error"
    ]
    assert not errors
    assert os.path.exists(path)  # the notebook on disk is never modified by the run
