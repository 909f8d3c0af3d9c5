"""The README's commands stay valid: every `jaxcal ...` line of its shell blocks parses with
the real argument parser, every repository file it names exists, and its Python blocks
compile and import only what jaxcal exports.

Cheap by design: nothing runs here. What the commands do is run elsewhere: `jaxcal demo`
and `calibrate` in test_calibrate.py and test_cli.py, bags in test_rosbag.py, tracker data
and `import-csv` in test_tracker.py and test_import_csv.py, `plan` in test_plan.py,
`handeye` in test_handeye_capture.py, the benchmarks in test_benchmarks.py, the Python
example in notebooks/quickstart.ipynb.
"""

import ast
import importlib
import re
import shlex
from pathlib import Path

import pytest

from jaxcal.cli import _join_negative_lists, build_parser

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
#: Top-level folders whose files a command reads (outputs such as out/ or result/ are written).
INPUT_ROOTS = ("data/", "benchmarks/", "notebooks/", "docs/", "tests/")


def _blocks(lang: tuple[str, ...]) -> list[str]:
    text = README.read_text()
    return [m.group(2) for m in re.finditer(r"```(\w*)\n(.*?)```", text, re.S) if m.group(1) in lang]


def _commands() -> list[list[str]]:
    """Each command of the shell blocks as argv, continuation lines joined, comments dropped."""
    out = []
    for block in _blocks(("bash", "sh", "shell")):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split(" #", 1)[0].strip()
            if line and not line.startswith("#"):
                out.append(shlex.split(line))
    return out


def _jaxcal_commands() -> list[list[str]]:
    return [c[1:] for c in _commands() if c[0] in ("jaxcal", ".venv/bin/jaxcal")]


def test_readme_is_a_guide_not_a_diary():
    assert len(README.read_text().splitlines()) <= 350


def test_the_readme_has_commands():
    names = {c[0] for c in _jaxcal_commands()}
    assert {"demo", "calibrate", "verify", "import-csv", "plan", "handeye", "import-bag"} <= names


@pytest.mark.parametrize("argv", _jaxcal_commands(), ids=lambda a: " ".join(a)[:60])
def test_jaxcal_command_parses(argv):
    build_parser().parse_args(_join_negative_lists(argv))  # SystemExit on an unknown option


@pytest.mark.parametrize("argv", _commands(), ids=lambda a: " ".join(a)[:60])
def test_files_the_commands_read_exist(argv):
    if argv[0] in ("make", "sudo"):
        return
    if argv[0] in ("python", ".venv/bin/python"):
        assert (ROOT / argv[1]).is_file(), argv[1]
    for token in argv[1:]:
        for path in token.split(","):
            if path.startswith(INPUT_ROOTS) and "*" not in path:
                assert (ROOT / path).exists(), f"{path} (in: {' '.join(argv)})"


def test_make_targets_exist():
    makefile = (ROOT / "Makefile").read_text()
    for argv in _commands():
        if argv[0] == "make":
            assert re.search(rf"^{argv[1]}:", makefile, re.M), argv


def test_links_resolve():
    for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", README.read_text()):
        if not target.startswith("http"):
            assert (ROOT / target).exists(), target


def test_python_blocks_compile_and_import_public_names():
    for block in _blocks(("python",)):
        tree = ast.parse(block)
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("jaxcal"):
                module = importlib.import_module(node.module)
                for alias in node.names:
                    assert hasattr(module, alias.name), f"{node.module}.{alias.name}"
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
                if node.value.id == "jaxcal":
                    assert hasattr(importlib.import_module("jaxcal"), node.attr), f"jaxcal.{node.attr}"
