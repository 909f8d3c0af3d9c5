"""Notebooks are executed, so they never rot."""

import importlib.util
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


def _source_hash(nb) -> str:
    spec = importlib.util.spec_from_file_location("refresh", NOTEBOOKS[0].parent / "refresh.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.source_hash(nb)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_stored_outputs_are_those_of_the_code_shown(path):
    """The notebooks are committed with their outputs (`make notebooks`: full size, plots included),
    stored with the hash of the code that made them: a code change without a refresh fails here."""
    nb = nbformat.read(path, as_version=4)
    stored = nb.metadata.get("jaxcal", {}).get("source_sha256")
    assert stored == _source_hash(nb), (
        f"{path.name}: its code changed after its outputs were stored: make notebooks"
    )
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert any("image/png" in o.get("data", {}) for o in outputs)  # its plots are there to see
    assert path.stat().st_size < 1_500_000  # small enough to read on GitHub
