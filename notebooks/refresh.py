"""Run the notebooks at their full size and store their outputs (plots included) in them, so that a
reader sees the results before running anything: `make notebooks`.

    python notebooks/refresh.py [NOTEBOOK ...]     # default: every notebooks/*.ipynb

Each notebook is executed in a fresh kernel from this folder's parent (the repository), its figures
drawn as PNG at 72 dpi to keep the files small, and written back atomically only when every cell
ran without error. The hash of its code cells is stored in its metadata (`jaxcal.source_sha256`):
`tests/test_notebooks.py` fails when a notebook's code changed after its outputs were stored, so the
outputs shown are always those of the code shown.
"""

import hashlib
import os
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def source_hash(nb) -> str:
    """SHA-256 of a notebook's code cells, in order (outputs, markdown and metadata left out)."""
    h = hashlib.sha256()
    for cell in nb.cells:
        if cell.cell_type == "code":
            h.update(cell.source.encode())
            h.update(b"\0")
    return h.hexdigest()


def refresh(path: Path) -> float:
    """Execute `path` in place; the seconds it took."""
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read(path, as_version=4)
    settings = "%config InlineBackend.figure_formats = ['png']\n%config InlineBackend.rc = {'figure.dpi': 72}"
    nb.cells.insert(0, nbformat.v4.new_code_cell(settings))
    start = time.perf_counter()
    NotebookClient(
        nb, timeout=1800, kernel_name="python3", resources={"metadata": {"path": str(HERE.parent)}}
    ).execute()
    nb.cells.pop(0)  # the display settings, not part of the notebook
    errors = [
        o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []) if o.output_type == "error"
    ]
    if errors:
        raise RuntimeError(f"{path}: {errors[0].ename}: {errors[0].evalue}")
    nb.metadata["jaxcal"] = {"source_sha256": source_hash(nb)}
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".ipynb.tmp")
    with os.fdopen(fd, "w") as f:
        nbformat.write(nb, f)
    os.replace(tmp, path)
    return time.perf_counter() - start


def main(argv: list[str]) -> int:
    paths = [Path(a) for a in argv] or sorted(HERE.glob("*.ipynb"))
    for path in paths:
        print(f"running {path} ...", flush=True)
        print(f"wrote {path} ({refresh(path):.0f} s, {path.stat().st_size / 1e3:.0f} kB)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
