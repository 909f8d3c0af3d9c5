"""Type and range checks for the dataset's JSON files, with messages that name
the file, the field path and the value (`metadata.json: cameras[0].width:
expected an integer from 1 to 100000, got 'wide'`).

Hand-written rather than a schema library: each check says what it expected
in the words of `docs/dataset.md`, and nothing here can raise anything but
`DatasetError`.
"""

import json
import math
import re
from pathlib import Path, PurePosixPath, PureWindowsPath

import numpy as np

from ..errors import DatasetError

#: Longest value repr quoted in a message.
_REPR = 60


def show(value) -> str:
    """A short repr of `value` for an error message."""
    try:
        text = json.dumps(value) if isinstance(value, dict | list) else repr(value)
    except (TypeError, ValueError, RecursionError):
        text = repr(type(value).__name__)
    return text if len(text) <= _REPR else text[: _REPR - 5] + " ...]"


class Loc:
    """Where a value sits: a file and a field path (`cameras[0].K`)."""

    __slots__ = ("file", "path")

    def __init__(self, file, path: str = ""):
        self.file = str(file)
        self.path = path

    def __str__(self) -> str:
        return f"{self.file}: {self.path}" if self.path else self.file

    def key(self, name: str) -> "Loc":
        return Loc(self.file, f"{self.path}.{name}" if self.path else name)

    def index(self, i: int) -> "Loc":
        return Loc(self.file, f"{self.path}[{i}]")

    def fail(self, message: str) -> DatasetError:
        """The error to raise: `raise loc.fail("...")`."""
        return DatasetError(f"{self}: {message}")

    def expected(self, what: str, value) -> DatasetError:
        return self.fail(f"expected {what}, got {show(value)}")


def read_text(path: Path, what: str) -> str:
    """The UTF-8 text of `path` (a BOM dropped); a missing or unreadable file, or
    one that is not UTF-8, is a `DatasetError` naming it and what it is."""
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise DatasetError(f"{path}: {what} missing") from None
    except OSError as e:
        raise DatasetError(f"{path}: cannot read the {what} ({e.strerror})") from None
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise DatasetError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None


#: Deepest nesting of lists and objects a JSON or YAML input may have (jaxcal's own files
#: nest under ten levels; Python's parsers recurse once per level).
MAX_DEPTH = 100


def _check_depth(doc) -> None:
    """A `ValueError` when `doc` nests lists and objects more than `MAX_DEPTH` deep (walked
    without recursion)."""
    stack = [(doc, 1)]
    while stack:
        x, depth = stack.pop()
        if isinstance(x, dict | list):
            if depth > MAX_DEPTH:
                raise ValueError(f"nested more than {MAX_DEPTH} levels deep")
            stack.extend((v, depth + 1) for v in (x.values() if isinstance(x, dict) else x))


def loads(text: str, **kwargs) -> object:
    """`json.loads(text, **kwargs)`, a document nested more than `MAX_DEPTH` deep refused as a
    `ValueError` (not a `RecursionError`, however deep): every JSON input jaxcal reads is parsed
    here (`read_json`, the DH tables, the targets, the hand-eye capture, the results)."""
    try:
        doc = json.loads(text, **kwargs)
    except RecursionError:
        raise ValueError(f"nested more than {MAX_DEPTH} levels deep") from None
    _check_depth(doc)
    return doc


#: YAML's quoted scalars and comments, which may hold brackets that nest nothing.
_YAML_TEXT = re.compile(r'"(?:[^"\\]|\\.)*"|\'(?:[^\']|\'\')*\'|#[^\n]*')


def _flow_depth(text: str) -> int:
    """The deepest nesting of YAML's flow brackets (`[`, `{`) outside quotes and comments."""
    code = np.frombuffer(_YAML_TEXT.sub("", text).encode("utf-8", "replace"), np.uint8)
    step = np.isin(code, (ord("["), ord("{"))).astype(np.int64) - np.isin(code, (ord("]"), ord("}")))
    return int(np.cumsum(step).max(initial=0))


def load_yaml(text: str) -> object:
    """Safe YAML (ruamel's pure parser), refused as `loads` refuses (`ValueError`); a
    malformed document raises ruamel's `YAMLError`. Flow brackets nested too deep are refused
    before parsing (ruamel's scanner takes time growing with the square of their depth)."""
    from ruamel.yaml import YAML  # only where a YAML file is read

    if _flow_depth(text) > MAX_DEPTH:
        raise ValueError(f"nested more than {MAX_DEPTH} levels deep")
    try:
        doc = YAML(typ="safe", pure=True).load(text)
    except RecursionError:
        raise ValueError(f"nested more than {MAX_DEPTH} levels deep") from None
    _check_depth(doc)
    return doc


def read_json(path: Path, what: str) -> object:
    """Parse the JSON file `path`; every failure is a `DatasetError` naming it."""
    text = read_text(path, what)
    try:
        return loads(text, parse_constant=_no_constant)
    except json.JSONDecodeError as e:
        raise DatasetError(f"{path}: not valid JSON ({e})") from None
    except ValueError as e:  # NaN/Infinity literals, integers too long to convert, nesting
        raise DatasetError(f"{path}: not valid JSON ({e})") from None


def _no_constant(name: str):
    raise ValueError(f"{name} is not JSON (write null or a finite number)")


def obj(x, loc: Loc, required=(), optional=(), ignored=()) -> dict:
    """`x` as a JSON object with the `required` keys, some `optional` ones, and
    nothing else (keys in `ignored`, or starting with `x_`, are allowed and not read)."""
    if not isinstance(x, dict):
        raise loc.expected("a JSON object", x)
    known = set(required) | set(optional) | set(ignored)
    unknown = sorted(k for k in x if k not in known and not k.startswith("x_"))
    for k in required:
        if k not in x:
            # A misspelt field is both missing and unknown: say both, so the typo shows.
            also = (
                f" (unknown field{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))})"
                if unknown
                else ""
            )
            raise loc.fail(f"missing field {k!r}{also}")
    if unknown:
        raise loc.fail(
            f"unknown field{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))}; known fields are "
            f"{', '.join(map(repr, sorted(set(required) | set(optional))))} (your own notes go under keys "
            "starting with 'x_')"
        )
    return x


def string(x, loc: Loc, *, choices=None, allow_empty: bool = False) -> str:
    if not isinstance(x, str) or (not x and not allow_empty):
        raise loc.expected("a non-empty string" if not allow_empty else "a string", x)
    if choices is not None and x not in choices:
        raise loc.expected(f"one of {', '.join(map(repr, choices))}", x)
    return x


def integer(x, loc: Loc, lo: int | None = None, hi: int | None = None) -> int:
    if (
        isinstance(x, bool)
        or not isinstance(x, int)
        or (lo is not None and x < lo)
        or (hi is not None and x > hi)
    ):
        raise loc.expected(_range_words("an integer", lo, hi), x)
    return x


def number(
    x,
    loc: Loc,
    lo: float | None = None,
    hi: float | None = None,
    *,
    above: float | None = None,
    metres: bool = False,
) -> float:
    """A finite JSON number (not a bool, not a string) in [`lo`, `hi`], or > `above`.
    `metres`: a length in metres, so a value too large that fits once read as
    millimetres is named as such."""
    ok = isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
    if ok and (
        (lo is not None and x < lo) or (hi is not None and x > hi) or (above is not None and x <= above)
    ):
        ok = False
    if not ok:
        what = _range_words("a finite number", lo, hi)
        if above is not None:
            what = f"a finite number greater than {above:g}" + ("" if hi is None else f" and at most {hi:g}")
        if metres:
            what = what.replace("a finite number", "a length in metres", 1)
            if isinstance(x, int | float) and not isinstance(x, bool) and hi is not None and x > hi:
                hint = f"{x:g} looks like millimetres: {x / 1000:g} m?"
                raise loc.fail(f"expected {what}, got {show(x)} ({hint})")
        raise loc.expected(what, x)
    return float(x)


def _range_words(what: str, lo, hi) -> str:
    if lo is not None and hi is not None:
        return f"{what} from {lo:g} to {hi:g}"
    if lo is not None:
        return f"{what} >= {lo:g}"
    if hi is not None:
        return f"{what} <= {hi:g}"
    return what


def array(x, loc: Loc, shape: tuple) -> np.ndarray:
    """Nested lists of finite JSON numbers of exactly `shape` (`shape[0]` may be
    `None`: any length)."""
    flat: list[float] = []
    words = f"a {_shape_words(shape)} array of numbers"

    def walk(v, depth: int, where: Loc) -> None:
        if depth == len(shape):
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise where.expected("a finite number", v)
            flat.append(float(v))
            return
        n = shape[depth]
        if not isinstance(v, list) or (n is not None and len(v) != n):
            raise loc.expected(words, x)
        for i, item in enumerate(v):
            walk(item, depth + 1, where.index(i))

    walk(x, 0, loc)
    full = (len(x) if shape[0] is None else shape[0], *shape[1:])
    return np.asarray(flat, np.float64).reshape(full)


def _shape_words(shape: tuple) -> str:
    return "x".join("N" if n is None else str(n) for n in shape)


def pose(x, loc: Loc) -> np.ndarray:
    """A 4x4 rigid transform: finite, bottom row (0, 0, 0, 1), a rotation block."""
    T = array(x, loc, (4, 4))
    if not np.abs(T[3] - (0.0, 0.0, 0.0, 1.0)).max() <= 1e-9:
        raise loc.fail(f"bottom row must be [0, 0, 0, 1], got {T[3].tolist()}")
    R = T[:3, :3]
    if not np.abs(R.T @ R - np.eye(3)).max() <= 1e-6 or np.linalg.det(R) <= 0:
        raise loc.fail("the upper-left 3x3 block is not a rotation matrix (orthonormal, determinant +1)")
    return T


#: The lengths of OpenCV's distortion models (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tx ty]]]]).
DISTORTION_LENGTHS = (4, 5, 8, 12, 14)


def camera_matrix(x, loc: Loc, width: int, height: int) -> np.ndarray:
    """A camera matrix `[[fx, s, cx], [0, fy, cy], [0, 0, 1]]` (px): focal lengths positive,
    the principal point inside the `width` x `height` image."""
    K = array(x, loc, (3, 3))
    fx, fy = K[0, 0], K[1, 1]
    if not (fx > 0 and fy > 0):
        raise loc.fail(f"focal lengths K[0][0], K[1][1] must be positive, got fx = {fx:g}, fy = {fy:g}")
    if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0:
        raise loc.fail(
            f"the entries below the diagonal must be 0, got {[float(K[1, 0]), float(K[2, 0]), float(K[2, 1])]}"
        )
    if K[2, 2] != 1:
        raise loc.fail(f"bottom row must be [0, 0, 1], got {K[2].tolist()}")
    cx, cy = K[0, 2], K[1, 2]
    if not (-0.5 <= cx <= width - 0.5 and -0.5 <= cy <= height - 0.5):
        raise loc.fail(
            f"principal point ({cx:g}, {cy:g}) lies outside the {width}x{height} image "
            "(pixel centres run from 0 to width - 1)"
        )
    if not (0.1 * width <= cx <= 0.9 * width and 0.1 * height <= cy <= 0.9 * height):
        raise loc.fail(
            f"principal point ({cx:g}, {cy:g}) lies at the edge of the {width}x{height} image, where no lens "
            "puts it: a K of another resolution (the images resized or cropped since)?"
        )
    return K


def distortion(x, loc: Loc) -> np.ndarray:
    """OpenCV distortion coefficients: a list of 4, 5, 8, 12 or 14 finite numbers."""
    if not isinstance(x, list) or len(x) not in DISTORTION_LENGTHS:
        raise loc.expected("a list of 4, 5, 8, 12 or 14 OpenCV coefficients", x)
    return array(x, loc, (None,))


def names(x, loc: Loc, *, unique: bool = True) -> list[str]:
    """A non-empty list of non-empty strings (distinct when `unique`)."""
    if not isinstance(x, list) or not x:
        raise loc.expected("a non-empty list of names", x)
    out = [string(v, loc.index(i)) for i, v in enumerate(x)]
    if unique and len(set(out)) != len(out):
        dup = sorted({n for n in out if out.count(n) > 1})
        raise loc.fail(f"names must be distinct, {', '.join(map(repr, dup))} repeated")
    return out


#: Names that become file and folder names (`images/<camera>/`, `camera_<name>.yaml`,
#: `ros_<name>.txt`): a letter or digit, then letters, digits, `_`, `.` or `-`, 64 at most; so
#: never a path (`/`, `..`), hidden, or a character a file system refuses.
FILE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


def file_name(name, where) -> str:
    """`name` when it may name a file or folder (`FILE_NAME`), else a `DatasetError` naming
    `where` (a `Loc`, or an option such as `"--camera-name"`): checked wherever a name from a
    user becomes part of a path, before anything is written."""
    if not isinstance(name, str) or not FILE_NAME.fullmatch(name):
        raise DatasetError(
            f"{where}: expected letters, digits, '_', '.' or '-' (it names output files), starting with a "
            f"letter or digit, 64 at most, got {show(name)}"
        )
    return name


def relative_path(text: str, loc: Loc) -> str:
    """A path relative to the dataset directory that stays inside it."""
    if "\\" in text or "\x00" in text:
        raise loc.expected("a relative path with '/' separators", text)
    p = PurePosixPath(text)
    if p.is_absolute() or PureWindowsPath(text).drive or ".." in p.parts or not p.parts:
        raise loc.expected("a path relative to the dataset directory that stays inside it", text)
    return text
