"""The shape of the code (docs/architecture.md), held by reading its syntax trees.

- Edges point down: no calibration module imports `jaxcal.sim`, `jaxcal.cli`
  or MuJoCo, directly or through another jaxcal module, and the module
  import graph has no cycles.
- Imports are at the top of a module (what depends on what is visible
  there), with two exceptions. The command line imports what a command runs
  when it runs: the simulator for the commands that render (`demo`,
  `simulate`), so that `jaxcal calibrate` runs where MuJoCo or OpenGL is
  missing, and a command's work once it has begun to read its programs ahead
  (`jaxcal._exported.warm_start`), so that the import and the load overlap;
  these imports are edges of the graph below like any other. And `jaxcal.io`
  re-exports the URDF reader on first use.
- No private name (`_x`) is imported from another module; private modules
  (`jaxcal._arcfit`) are imported for their public names.
- Rooms stay small: no function over 120 lines, no module over 700.
- Results are typed: no field of a stage or result record (the dataclasses of
  `jaxcal/stages/`, `jaxcal/records.py` and `jaxcal/records_<topic>.py`) is a `dict`, `list`, `object` or
  `Any`, except the free-form ones allowed below with their reason.
- The numeric core (`jaxcal._*` modules and packages) imports only the core,
  `jaxcal.errors` and `jaxcal.records`: no edge (files, OpenCV) and no product.
- A product package keeps its steps to itself: no module outside
  `jaxcal/handeye/` imports its private modules (`jaxcal.handeye._observe`,
  ...); other code uses what `jaxcal.handeye` exports.
- Capture modes are resolved once: outside `jaxcal/stages/kinds.py` no code
  reads a capture kind's mode (`kind.device`, `kind.eye_in_hand`,
  `kind.encoders`, `kind.device_is_base`, `kind.mount`, `kind.motion`) or
  names a `Motion.X` / `Mount.X` member; it asks a named `CaptureKind`
  property (docs/architecture.md, "Capture kinds").
"""

import ast
import re
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "jaxcal"
#: A capture kind's mode fields, and the enums of its modes (`jaxcal.stages.kinds`).
MODE_FIELDS = {"device", "eye_in_hand", "encoders", "device_is_base", "mount", "motion"}
MODE_ENUMS = {"Motion", "Mount"}
#: `module: reason` for a module that may still test a mode outside kinds.py (none today).
MODE_TEST_EXCEPTIONS: dict[str, str] = {}
#: Record fields that may stay free-form, with the reason.
FREE_FORM_FIELDS = {
    "timings": "seconds per timed step (`detect_s`, `refine_s`, ..., `total_s`): the steps differ by capture "
    "kind and change with the stages; a `dict[str, float]` that no code branches on",
}
#: `Record.field: reason` for bag fields of the stages' inputs not typed yet (the results are).
UNTYPED_FIELDS: dict[str, str] = {}
#: Configuration records (not results) and where the records live.
CONFIG_RECORDS = {"Options", "Limits", "CaptureKind"}
BAG_TYPES = {"dict", "list", "object", "Any", "Dict", "List", "Mapping"}
#: Modules that may render (import the simulator / MuJoCo).
RENDERING = ("jaxcal.sim", "jaxcal.cli", "jaxcal.__main__")


def _modules() -> dict[str, ast.Module]:
    out = {}
    for p in sorted(PACKAGE.rglob("*.py")):
        parts = list(p.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = ast.parse(p.read_text(), str(p))
    return out


MODULES = _modules()


def _is_package(name: str) -> bool:
    return (PACKAGE.parent / Path(*name.split(".")) / "__init__.py").is_file()


def _resolve(module: str, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    base = module.split(".")
    if not _is_package(module):
        base = base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _imports(module: str, tree: ast.Module, *, top_level: bool):
    """`(line, imported module, names)` of the module's imports (top level, or inside functions)."""
    scopes = (
        [tree]
        if top_level
        else [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
    )
    for scope in scopes:
        body = scope.body if top_level else list(ast.walk(scope))
        for node in body:
            if isinstance(node, ast.Import):
                for a in node.names:
                    yield node.lineno, a.name, []
            elif isinstance(node, ast.ImportFrom):
                target = _resolve(module, node)
                names = [a.name for a in node.names]
                # `from . import _arcfit` imports a module, not a name.
                subs = [n for n in names if f"{target}.{n}" in MODULES]
                for n in subs:
                    yield node.lineno, f"{target}.{n}", []
                rest = [n for n in names if n not in subs]
                if rest or not subs:
                    yield node.lineno, target, rest


#: Modules that may import jaxcal modules inside functions (module docstring): the command line,
#: `jaxcal.io`'s lazy re-export of the URDF reader, and the metadata reader's robot-file readers
#: (JAX's robot model), so that the command line's parsers, which read the datasets' vocabulary,
#: import no JAX (tests/test_cli_config.py).
LOCAL_IMPORTS = {
    "jaxcal.io": ("jaxcal.io.urdf",),
    "jaxcal.io._metadata": ("jaxcal.io.urdf", "jaxcal.io.dh_tables"),
}


def _local_import_allowed(name: str, target: str) -> bool:
    return name.startswith("jaxcal.cli") or target in LOCAL_IMPORTS.get(name, ())


def _graph() -> dict[str, set[str]]:
    """Each module's imports: at its top, and the function-local ones allowed (edges all the same)."""
    graph = {}
    for name, tree in MODULES.items():
        deps = set()
        for _, target, _ in _imports(name, tree, top_level=True):
            deps.add(target)
        for _, target, _ in _imports(name, tree, top_level=False):
            if _local_import_allowed(name, target):
                deps.add(target)
        graph[name] = deps
    return graph


def test_no_function_local_imports_of_jaxcal_modules():
    found = []
    for name, tree in MODULES.items():
        for line, target, _ in _imports(name, tree, top_level=False):
            if target.startswith("jaxcal") and not _local_import_allowed(name, target):
                found.append(f"{name}:{line} imports {target}")
    assert found == []


def test_no_private_names_imported_across_modules():
    found = []
    for name, tree in MODULES.items():
        for line, target, names in _imports(name, tree, top_level=True):
            if target.startswith("jaxcal"):
                found += [
                    f"{name}:{line} {target}.{n}" for n in names if n.startswith("_") and n != "__version__"
                ]
    assert found == []


def test_the_import_graph_has_no_cycles():
    graph = {m: {d for d in deps if d in MODULES} for m, deps in _graph().items()}
    state: dict[str, int] = {}
    cycles = []

    def visit(m, path):
        state[m] = 1
        for d in sorted(graph[m]):
            if d == m or d.startswith(m + "."):  # a package importing its own submodules
                continue
            if state.get(d) == 1:
                cycles.append(path[path.index(d) :] + [d] if d in path else [m, d])
            elif d not in state:
                visit(d, path + [d])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert cycles == []


def test_calibration_modules_never_reach_the_simulator_or_mujoco():
    graph = _graph()

    def reach(m, seen):
        for d in graph.get(m, ()):
            if d not in seen:
                seen.add(d)
                reach(d, seen)
        return seen

    bad = []
    for m in MODULES:
        if m.startswith(RENDERING) or m == "jaxcal.sim":
            continue
        for d in reach(m, set()):
            if d.startswith(("jaxcal.sim", "jaxcal.cli", "mujoco")) or d == "jaxcal.sim":
                bad.append(f"{m} -> {d}")
    assert bad == []


#: What the numeric core may import besides itself.
CORE_MAY_IMPORT = ("jaxcal.errors", "jaxcal.records")
#: Product packages whose private modules only the package itself imports.
PRODUCT_PACKAGES = ("jaxcal.handeye",)


def _is_core(name: str) -> bool:
    parts = name.split(".")
    return len(parts) > 1 and parts[0] == "jaxcal" and parts[1].startswith("_") and parts[1] != "__main__"


def test_the_core_imports_no_edge_and_no_product():
    found = [
        f"{m} -> {d}"
        for m, deps in _graph().items()
        if _is_core(m)
        for d in sorted(deps)
        if d.startswith("jaxcal.") and not _is_core(d) and d not in CORE_MAY_IMPORT
    ]
    assert found == [], "the numeric core is pure: move the impure part to an edge or a product package"


def test_product_packages_keep_their_steps_private():
    found = [
        f"{m} -> {d}"
        for m, deps in _graph().items()
        for pkg in PRODUCT_PACKAGES
        if not (m == pkg or m.startswith(pkg + "."))
        for d in sorted(deps)
        if d.startswith(pkg + "._")
    ]
    assert found == [], "import what the package exports (its __init__), not its private modules"


def test_functions_and_modules_stay_small():
    long_functions, long_modules = [], []
    for name, tree in MODULES.items():
        lines = max((getattr(n, "end_lineno", 0) or 0) for n in ast.walk(tree))
        if lines > 700:
            long_modules.append(f"{name} ({lines} lines)")
        for n in ast.walk(tree):
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.end_lineno - n.lineno + 1 > 120:
                long_functions.append(f"{name}.{n.name} ({n.end_lineno - n.lineno + 1} lines)")
    assert long_functions == [] and long_modules == []


def _mode_tests(tree: ast.Module) -> list[str]:
    """Reads of a capture kind's mode (`x.kind.motion`, `kind.encoders`) and `Motion.X` / `Mount.X`."""
    found = []
    for n in ast.walk(tree):
        if not isinstance(n, ast.Attribute):
            continue
        on_kind = (isinstance(n.value, ast.Name) and n.value.id == "kind") or (
            isinstance(n.value, ast.Attribute) and n.value.attr == "kind"
        )
        member = isinstance(n.value, ast.Name) and n.value.id in MODE_ENUMS and n.attr.isupper()
        if (on_kind and n.attr in MODE_FIELDS) or member:
            found.append(f"{n.lineno} {ast.unparse(n)}")
    return found


def test_the_mode_test_finder_finds_them():
    src = "if setup.kind.motion is Motion.SWEEPS or kind.eye_in_hand:\n    x = kind.has_arcs\n"
    assert sorted(_mode_tests(ast.parse(src))) == [
        "1 Motion.SWEEPS",
        "1 kind.eye_in_hand",
        "1 setup.kind.motion",
    ]


def test_capture_modes_are_tested_only_in_kinds():
    found = [
        f"{name}:{site}"
        for name, tree in MODULES.items()
        if name != "jaxcal.stages.kinds" and name not in MODE_TEST_EXCEPTIONS
        for site in _mode_tests(tree)
    ]
    assert found == [], "ask a named CaptureKind property (jaxcal/stages/kinds.py) instead"


def _annotation_names(node) -> set[str]:
    """Every type name in an annotation (`tuple[dict, ...] | None` -> tuple, dict, None)."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return _annotation_names(ast.parse(node.value, mode="eval").body)
    return {n.id for n in ast.walk(node) if isinstance(n, ast.Name)} | {
        n.attr for n in ast.walk(node) if isinstance(n, ast.Attribute)
    }


def _record_bag_fields(tree: ast.Module) -> list[str]:
    """`Record.field: annotation` of every dict/list/object/Any-typed field of the public records."""
    found = []
    for cls in ast.walk(tree):
        if not isinstance(cls, ast.ClassDef) or cls.name.startswith("_") or cls.name in CONFIG_RECORDS:
            continue
        deco = {ast.unparse(d).split("(")[0].split(".")[-1] for d in cls.decorator_list}
        bases = {ast.unparse(b).split(".")[-1] for b in cls.bases}
        if "dataclass" not in deco and "NamedTuple" not in bases:
            continue
        for n in cls.body:
            if isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name):
                if "ClassVar" not in ast.unparse(n.annotation) and BAG_TYPES & _annotation_names(
                    n.annotation
                ):
                    found.append(f"{cls.name}.{n.target.id}: {ast.unparse(n.annotation)}")
    return found


def test_the_record_field_finder_finds_bags():
    src = (
        "@dataclass(frozen=True)\nclass R:\n    a: dict\n    b: tuple[dict, ...] | None\n    c: Any = None\n"
        "    d: tuple[Named, ...] = ()\n    e: np.ndarray\n"
    )
    assert _record_bag_fields(ast.parse(src)) == ["R.a: dict", "R.b: tuple[dict, ...] | None", "R.c: Any"]


def test_result_records_are_typed():
    modules = {n: t for n, t in MODULES.items() if n.startswith(("jaxcal.stages.", "jaxcal.records"))}
    found = []
    for tree in modules.values():
        for site in _record_bag_fields(tree):
            name, annotation = site.split(": ", 1)
            if name in UNTYPED_FIELDS:
                continue
            if name.split(".")[1] in FREE_FORM_FIELDS and annotation == "dict[str, float]":
                continue
            found.append(site)
    assert found == [], "give the field a typed record (jaxcal/records.py), or a reason in FREE_FORM_FIELDS"
    stale = [
        f
        for f in UNTYPED_FIELDS
        if not any(f"{f}:" in s for t in modules.values() for s in _record_bag_fields(t))
    ]
    assert stale == [], "typed now: remove from UNTYPED_FIELDS"


def test_the_package_layout_names_every_module_and_subcommand():
    """docs/architecture.md's "Package layout" names every module and package at the top of
    `jaxcal/` and every `jaxcal` subcommand, so that someone new finds where each part lives."""
    from jaxcal.cli import option_meanings

    doc = (PACKAGE.parent / "docs" / "architecture.md").read_text()
    block = doc[doc.index("## Package layout") :]
    block = block[: block.index("```", block.index("```") + 3)]
    named = set(re.findall(r"[\w.]+(?:\.py|/)", block))
    package = PACKAGE
    top = [p.name for p in package.glob("*.py")] + [
        f"{p.name}/" for p in package.iterdir() if (p / "__init__.py").exists()
    ]
    assert sorted(set(top) - named) == []
    commands = {c for by_command in option_meanings().values() for c in by_command}
    cli = block[block.index("  cli/") : block.index("benchmarks/")]
    assert (
        len(commands) >= 15
        and sorted(c for c in commands if f" {c} " not in cli.replace("\n", " ") + " ") == []
    )
