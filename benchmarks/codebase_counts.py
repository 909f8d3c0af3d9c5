"""Counts over jaxcal's syntax trees that say how far issue 34's cleanup has come.

Read from the source alone (no import of jaxcal), each count with the places it
found so that a figure can be checked by eye:

- `record_fields`: fields of the stage and result records (the public
  dataclasses and NamedTuples of `jaxcal/stages/` and `jaxcal/records.py`, less the configuration
  records `Options`, `Limits` and `CaptureKind`), and `bag_fields`, those typed
  `dict`, `list`, `object` or `Any` (with or without `| None`), per record; `bag_fields_free_form`,
  those the architecture test allows by name (`timings: dict[str, float]`, seconds per step).
- `string_key_reads`: subscripts by a string constant read in `jaxcal/`
  (`v["trans_mm"]`, not stores), and `string_key_gets`: `.get("key", ...)` calls,
  per file. The reads are also split: `string_key_reads_io`, those in `jaxcal/io/`
  (the file-format readers, where a JSON key belongs), and `string_key_reads_elsewhere`,
  results read through dicts (the figure that should go to zero).
- `mode_tests`: capture-mode tests outside `jaxcal/stages/kinds.py`: a read of
  `.device`, `.eye_in_hand`, `.encoders`, `.device_is_base`, `.mount` or
  `.motion` on a capture kind (an expression ending in `kind`), or a `Motion.X` /
  `Mount.X` member. The stages should ask a named `CaptureKind` property.
- `long_functions`: functions (methods and nested functions included) over 100
  lines.
- `covariance_sites`: functions outside the least-squares kit (`_lsq.py`,
  `_linalg.py`) that invert a normal matrix themselves: an `inv`, `pinv`,
  `cho_solve` (or `solve` against an identity) of `J.T @ J` (or of a matrix named like one: `JtJ`,
  `info`, `fisher`, `normal`, `hess`), or any of these assigned to a name with
  `cov` in it. (Inverting a pose is not a site.)

And issue 50's: `package_lines` (lines of `jaxcal/`), `modules_over_500_lines`, `fmt_skips`
(`# fmt: skip` comments in `jaxcal/`), and from the command line's parser (`jaxcal.cli`, which
builds it without JAX): `cli_options`, the options over all subcommands (flags), `config_keys`,
the configuration keys (`--config`, `jaxcal._configkeys`), and
`option_names_with_two_meanings` (`jaxcal.cli.option_meanings`).

    python benchmarks/codebase_counts.py [--json OUT] [--brief]

`--brief` prints the totals only.
"""

import argparse
import ast
import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "jaxcal"
KINDS = PACKAGE / "stages" / "kinds.py"
#: The file-format readers and writers: a string key read here is a file's key.
IO = PACKAGE / "io"
#: The typed rows and blocks the stages' records hold (`jaxcal.records`).
#: Bag fields allowed by name (tests/test_architecture.py FREE_FORM_FIELDS): seconds per step.
FREE_FORM = {"timings: dict[str, float]"}
RECORDS = sorted(PACKAGE.glob("records*.py"))  # records.py and records_<topic>.py
#: The least-squares kit: a covariance computed here is the one route.
KIT = (PACKAGE / "_lsq.py", PACKAGE / "_linalg.py")
BAG_TYPES = {"dict", "list", "object", "Any", "Dict", "List", "Mapping"}
MODE_ATTRS = {"device", "eye_in_hand", "encoders", "device_is_base", "mount", "motion"}
MODE_ENUMS = {"Motion", "Mount"}
INVERSES = {"inv", "pinv", "solve", "cho_solve"}
#: What an inverted normal matrix looks like: `J.T @ J`, `JtJ`, `info`, ...
NORMAL = re.compile(r"\.T\s*@|jtj|info|fisher|normal|hess", re.IGNORECASE)
LONG = 100
#: Records of configuration, not of results.
CONFIG = {"Options", "Limits", "CaptureKind"}


def _files(root: Path = PACKAGE) -> list[Path]:
    return sorted(p for p in root.rglob("*.py") if "__pycache__" not in p.parts)


def _rel(p: Path) -> str:
    return str(p.relative_to(ROOT))


def _parse(p: Path) -> ast.Module:
    return ast.parse(p.read_text(), str(p))


def _outer_types(node: ast.expr | None) -> list[str]:
    """The outer type names of an annotation, through `X | None`, `Optional[X]`, `Union[...]`."""
    if node is None:
        return []
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return _outer_types(ast.parse(node.value, mode="eval").body)
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.BitOr):
        return _outer_types(node.left) + _outer_types(node.right)
    if isinstance(node, ast.Subscript):
        base = _outer_types(node.value)
        if base in (["Optional"], ["Union"]):
            inner = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
            return [t for e in inner for t in _outer_types(e)]
        return base
    if isinstance(node, ast.Name):
        return [node.id]
    if isinstance(node, ast.Attribute):
        return [node.attr]
    return []


def _is_record(cls: ast.ClassDef) -> bool:
    deco = {ast.unparse(d).split("(")[0].split(".")[-1] for d in cls.decorator_list}
    bases = {ast.unparse(b).split(".")[-1] for b in cls.bases}
    return "dataclass" in deco or "NamedTuple" in bases


def record_fields() -> dict:
    """Per public record of `jaxcal/stages/`: its fields and the bag-typed ones."""
    records = {}
    for p in [*_files(PACKAGE / "stages"), *RECORDS]:
        for cls in ast.walk(_parse(p)):
            if (
                not (isinstance(cls, ast.ClassDef) and _is_record(cls))
                or cls.name.startswith("_")
                or cls.name in CONFIG
            ):
                continue
            fields = [n for n in cls.body if isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name)]
            fields = [n for n in fields if "ClassVar" not in ast.unparse(n.annotation)]
            bags = [
                f"{n.target.id}: {ast.unparse(n.annotation)}"
                for n in fields
                if BAG_TYPES & set(_outer_types(n.annotation))
            ]
            records[f"{_rel(p)}:{cls.name}"] = {"fields": len(fields), "bag_fields": bags}
    return records


def string_keys() -> tuple[dict, dict]:
    """Per file: string-constant subscripts read, and `.get("key")` calls."""
    reads, gets = {}, {}
    for p in _files():
        r = g = 0
        for n in ast.walk(_parse(p)):
            if (
                isinstance(n, ast.Subscript)
                and isinstance(n.ctx, ast.Load)
                and isinstance(n.slice, ast.Constant)
                and isinstance(n.slice.value, str)
            ):
                r += 1
            elif (
                isinstance(n, ast.Call)
                and isinstance(n.func, ast.Attribute)
                and n.func.attr == "get"
                and n.args
                and isinstance(n.args[0], ast.Constant)
                and isinstance(n.args[0].value, str)
            ):
                g += 1
        if r:
            reads[_rel(p)] = r
        if g:
            gets[_rel(p)] = g
    return reads, gets


def _in_io(rel: str) -> bool:
    """Whether the file `rel` (relative to the repository) is one of `jaxcal/io/`'s."""
    return (ROOT / rel).is_relative_to(IO)


def _ends_in_kind(node: ast.expr) -> bool:
    return (isinstance(node, ast.Name) and node.id == "kind") or (
        isinstance(node, ast.Attribute) and node.attr == "kind"
    )


def mode_test_sites(files: list[Path] | None = None) -> list[str]:
    """`file:line expression` of every capture-mode test outside `kinds.py`."""
    found = []
    for p in files if files is not None else _files():
        if p == KINDS:
            continue
        for n in ast.walk(_parse(p)):
            if not isinstance(n, ast.Attribute) or not isinstance(n.ctx, ast.Load):
                continue
            kind_read = n.attr in MODE_ATTRS and _ends_in_kind(n.value)
            member = isinstance(n.value, ast.Name) and n.value.id in MODE_ENUMS and n.attr.isupper()
            if kind_read or member:
                found.append(f"{_rel(p)}:{n.lineno} {ast.unparse(n)}")
    return found


def long_functions(limit: int = LONG) -> list[str]:
    out = []
    for p in _files():
        for n in ast.walk(_parse(p)):
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)):
                size = n.end_lineno - n.lineno + 1
                if size > limit:
                    out.append(f"{_rel(p)}:{n.lineno} {n.name} ({size} lines)")
    return out


def _call_name(n: ast.Call) -> str:
    f = n.func
    return f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""


def _inverts_normal(c: ast.Call) -> bool:
    """`inv(J.T @ J)`, `pinv(info)`, `solve(H, eye(n))`; not a Gauss-Newton step `solve(H, g)`."""
    name = _call_name(c)
    if name not in INVERSES or not c.args or not NORMAL.search(ast.unparse(c.args[0])):
        return False
    return name != "solve" or (len(c.args) > 1 and "eye" in ast.unparse(c.args[1]))


def covariance_sites() -> list[str]:
    """Innermost functions outside the kit that invert a normal matrix into a covariance."""
    out = []
    for p in _files():
        if p in KIT:
            continue
        for fn in ast.walk(_parse(p)):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            inner = {
                c
                for d in ast.walk(fn)
                if d is not fn and isinstance(d, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
                for c in ast.walk(d)
            }
            own = [n for n in ast.walk(fn) if n not in inner]
            hits = [c for c in own if isinstance(c, ast.Call) and _inverts_normal(c)]
            for a in own:
                if isinstance(a, ast.Assign) and "cov" in ast.unparse(a.targets[0]).lower():
                    hits += [
                        c
                        for c in ast.walk(a.value)
                        if isinstance(c, ast.Call) and _call_name(c) in INVERSES - {"solve"}
                    ]
            if hits:
                names = sorted({_call_name(c) for c in hits})
                out.append(f"{_rel(p)}:{fn.lineno} {fn.name} ({', '.join(names)})")
    return out


def package_sizes() -> tuple[int, list[str], int]:
    """Lines of `jaxcal/`, its modules over 500 lines (`path (lines)`), and its `# fmt: skip` comments."""
    lines, long, skips = 0, [], 0
    for p in sorted(PACKAGE.rglob("*.py")):
        text = p.read_text()
        n = text.count("\n")
        lines += n
        skips += text.count("# fmt: skip")
        if n > 500:
            long.append(f"{_rel(p)} ({n})")
    return lines, long, skips


def cli_vocabulary() -> tuple[int, int, list[str]]:
    """Options over all subcommands (the flags), their configuration keys (`--config`), and the
    names, flags and keys together, with more than one meaning."""
    from jaxcal.cli import option_meanings

    meanings = option_meanings()
    flags = sum(len(by_command) for by_command in option_meanings(keys=False).values())
    keys = sum(len(by_command) for by_command in meanings.values()) - flags
    return flags, keys, sorted(n for n, by_command in meanings.items() if len(set(by_command.values())) > 1)


def counts() -> dict:
    records = record_fields()
    lines, long_modules, skips = package_sizes()
    options, keys, two_meanings = cli_vocabulary()
    reads, gets = string_keys()
    modes = mode_test_sites()
    longs = long_functions()
    covs = covariance_sites()
    return {
        "record_fields": sum(r["fields"] for r in records.values()),
        "bag_fields": sum(len(r["bag_fields"]) for r in records.values()),
        # Of those, the ones the architecture test allows by name (`timings: dict[str, float]`).
        "bag_fields_free_form": sum(b in FREE_FORM for r in records.values() for b in r["bag_fields"]),
        "string_key_reads": sum(reads.values()),
        "string_key_reads_io": sum(n for f, n in reads.items() if _in_io(f)),
        "string_key_reads_elsewhere": sum(n for f, n in reads.items() if not _in_io(f)),
        "string_key_gets": sum(gets.values()),
        "mode_tests": len(modes),
        "mode_test_files": len({m.split(":")[0] for m in modes}),
        "long_functions": len(longs),
        "covariance_sites": len(covs),
        "package_lines": lines,
        "modules_over_500_lines": len(long_modules),
        "fmt_skips": skips,
        "cli_options": options,
        "config_keys": keys,
        "option_names_with_two_meanings": len(two_meanings),
        "detail": {
            "records": records,
            "string_key_reads": dict(sorted(reads.items(), key=lambda kv: -kv[1])),
            "string_key_gets": dict(sorted(gets.items(), key=lambda kv: -kv[1])),
            "mode_tests": modes,
            "long_functions": longs,
            "covariance_sites": covs,
            "modules_over_500_lines": long_modules,
            "option_names_with_two_meanings": two_meanings,
        },
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="write the counts here")
    parser.add_argument("--brief", action="store_true", help="print the totals only")
    args = parser.parse_args(argv)
    out = counts()
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    shown = {k: v for k, v in out.items() if k != "detail"} if args.brief else out
    print(json.dumps(shown, indent=2))


if __name__ == "__main__":
    main()
