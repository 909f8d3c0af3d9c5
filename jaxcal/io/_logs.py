"""Reading the dataset's tables: `frames.csv` (with each image's size from its header) and the encoder log."""

import csv
import io
import itertools
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from . import _encoders as enc
from . import _schema as sc
from ._files import atomic_directory as atomic_directory
from ._images import image_size
from ._metadata import CameraInfo
from ._schema import Loc

#: Frame indices: below 2**31, and per camera spanning at most
#: `FRAME_SPAN_FACTOR` x its rows + `FRAME_SPAN_SLACK` (a 99 % drop rate fits;
#: nothing downstream can allocate per missing index beyond that).
MAX_FRAME_INDEX = 2**31 - 1
FRAME_SPAN_FACTOR = 100
FRAME_SPAN_SLACK = 1000


@dataclass(frozen=True)
class EncoderGlitch:
    """An isolated glitch of one joint's encoder log, removed at load.

    - `joint`: the joint whose log jumped.
    - `rows`: `(first, last)` data rows of the encoder file (0 = the first row
      after the header), inclusive; `lines`: the same as file line numbers.
    - `t_start`, `t_end`: controller-clock interval (s) in which the log is
      affected: from the last good sample before the glitch to the first good
      one after. Encoder values interpolated inside it bridge the removed rows;
      frames whose controller time falls in `[t_start, t_end]` should be dropped.
    - `size`: the jump away from the local trend (rad or m of joint motion).
    """

    joint: str
    rows: tuple[int, int]
    lines: tuple[int, int]
    t_start: float
    t_end: float
    size: float


# --------------------------------------------------------------------------- reading: files


def read_csv(path: Path, what: str) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """Header and `(line number, cells)` rows of a CSV file; blank lines are skipped."""
    text = sc.read_text(path, what)
    reader = csv.reader(io.StringIO(text, newline=""))
    rows = []
    try:
        for cells in reader:
            if cells and any(c.strip() for c in cells):
                rows.append((reader.line_num, cells))
    except csv.Error as e:
        raise DatasetError(f"{path} line {reader.line_num}: not CSV ({e})") from None
    if not rows:
        raise DatasetError(f"{path}: empty (expected a header line)")
    return rows[0][1], rows[1:]


def parse_number(text: str, where: str) -> float:
    """A finite number from a CSV cell, else a `DatasetError` naming `where`."""
    try:
        v = float(text)
    except ValueError:
        raise DatasetError(f"{where}: {text!r} is not a number") from None
    if not math.isfinite(v):
        raise DatasetError(f"{where}: value is {text} (NaN/inf not allowed)")
    return v


#: Rows of a table parsed at once by `read_number_table`: the text held in memory is bounded by
#: it, and NumPy's C parser (`np.loadtxt`) converts each block's numbers.
BLOCK_ROWS = 65536


@dataclass(frozen=True, eq=False)
class NumberTable:
    """A CSV table read by `read_number_table`: its `header`, each data row's file line number
    `lines` `(rows,)`, the values of the number columns asked for `(rows, k)` (float64, finite)
    and the text of the text columns asked for `(rows, m)` (stripped)."""

    header: list[str]
    lines: np.ndarray
    values: np.ndarray
    text: np.ndarray


def read_number_table(path: Path, what: str, columns) -> NumberTable:
    """A CSV table of numbers, streamed: `BLOCK_ROWS` lines at a time, each block's numbers
    converted by NumPy's C parser, so that a table of millions of rows is read in seconds and in
    memory proportional to its numbers (a list of rows of cell strings takes ten times more).

    `columns(header) -> (numbers, texts)`: the indices of the columns read as numbers and as
    text, from the header (it raises for a header it refuses). Blank lines (whitespace and
    commas only) are skipped; a record is one line. Errors are `DatasetError`s naming the file,
    the line and the column, as `read_csv` and `parse_number` name them: a missing or unreadable
    file, text that is not UTF-8, a row whose cells are not the header's count, a cell that is
    not a number, NaN or infinite; a block that NumPy cannot read is read again cell by cell
    with Python's `float`, so the numbers accepted are Python's.
    """
    try:
        rows = _count_lines(path)  # the arrays are made once, at their size: no copy at the end
        f = open(path, encoding="utf-8-sig", newline="")
    except FileNotFoundError:
        raise DatasetError(f"{path}: {what} missing") from None
    except OSError as e:
        raise DatasetError(f"{path}: cannot read the {what} ({e.strerror})") from None
    try:
        with f:
            header, numbers, texts, n, k = None, (), (), 0, 0
            for line in f:
                n += 1
                if line.strip(_BLANK):
                    header = _cells(line, path, n)
                    numbers, texts = columns(header)
                    break
            if header is None:
                raise DatasetError(f"{path}: empty (expected a header line)")
            lines, values = np.zeros(rows, np.int64), np.zeros((rows, len(numbers)))
            words = np.zeros((rows, len(texts)), "U1")
            while chunk := list(itertools.islice(f, BLOCK_ROWS)):
                keep = [i for i, line in enumerate(chunk) if line.strip(_BLANK)]
                if keep:
                    text = chunk if len(keep) == len(chunk) else [chunk[i] for i in keep]
                    b = _number_block(n + 1 + np.asarray(keep), text, header, numbers, texts, path)
                    if b[2].itemsize > words.itemsize:  # the text as wide as its widest cell
                        words = words.astype(b[2].dtype)
                    lines[k : k + len(text)], values[k : k + len(text)], words[k : k + len(text)] = b
                    k += len(text)
                n += len(chunk)
    except UnicodeDecodeError as e:
        raise DatasetError(f"{path}: not UTF-8 text ({e.reason})") from None
    except OSError as e:
        raise DatasetError(f"{path}: cannot read the {what} ({e.strerror})") from None
    return NumberTable(header, lines[:k], values[:k], words[:k])


def _count_lines(path: Path) -> int:
    """The file's line count (a bound of its data rows), read in binary blocks of 1 MiB."""
    with open(path, "rb") as f:
        return sum(block.count(b"\n") for block in iter(lambda: f.read(1 << 20), b"")) + 1


#: What a blank line holds (skipped, as `read_csv` skips rows of empty cells).
_BLANK = " \t\r\n,"


def _numbers_one_by_one(rows, count: int, header: list[str], numbers, path: Path) -> np.ndarray:
    out = np.empty((count, len(numbers)))
    for r, (n, line) in enumerate(rows):
        cells = _cells(line, path, n)
        for k, c in enumerate(numbers):
            out[r, k] = parse_number(cells[c], f"{path} line {n} column {header[c]!r}")
    return out


def _cells(line: str, path: Path, n: int) -> list[str]:
    try:
        return next(csv.reader([line]))
    except csv.Error as e:
        raise DatasetError(f"{path} line {n}: not CSV ({e})") from None


def _number_block(lines: np.ndarray, text: list[str], header: list[str], numbers, texts, path: Path):
    """`(lines, values, text)` of one block of rows: their line numbers and their text."""
    quoted = any('"' in line for line in text)
    if quoted:
        counts = np.array([len(_cells(line, path, n)) for n, line in zip(lines.tolist(), text)])
    else:
        counts = np.array([line.count(",") for line in text]) + 1
    bad = np.flatnonzero(counts != len(header))
    if bad.size:
        k = bad[0]
        raise DatasetError(
            f"{path} line {lines[k]}: expected {len(header)} cells (the header's), got {counts[k]}"
        )
    kw = dict(delimiter=",", ndmin=2, comments=None, quotechar='"' if quoted else None)
    values = np.zeros((len(text), 0))
    if numbers:
        try:
            values = np.loadtxt(text, dtype=np.float64, usecols=list(numbers), **kw)
        except ValueError:  # a cell NumPy does not read: cell by cell, with Python's float and its error
            values = _numbers_one_by_one(zip(lines.tolist(), text), len(text), header, numbers, path)
    bad = np.argwhere(~np.isfinite(values))
    if bad.size:
        r, k = bad[0]
        n, line = int(lines[r]), text[r]
        where = f"{path} line {n} column {header[numbers[k]]!r}"
        parse_number(_cells(line, path, n)[numbers[k]], where)
        raise DatasetError(f"{where}: value is {values[r, k]} (NaN/inf not allowed)")
    words = np.zeros((len(text), 0), str)
    if texts:
        words = np.char.strip(np.loadtxt(text, dtype=str, usecols=list(texts), **kw))
    return lines, values, words


# --------------------------------------------------------------------------- reading: frames.csv


@dataclass(frozen=True, eq=False)
class FrameTable(Mapping):
    """The frame table (`frames.csv`, or a tracker's samples), one entry per row: the
    camera's name (str), its capture index, its camera-clock timestamp (s) and the image
    file. It also reads as the `{column: array}` mapping it used to be (`frames.file`)."""

    camera: np.ndarray
    frame: np.ndarray
    timestamp: np.ndarray
    file: np.ndarray

    def __getitem__(self, column: str) -> np.ndarray:
        if column not in self.__dataclass_fields__:
            raise KeyError(column)
        return getattr(self, column)

    def __iter__(self) -> Iterator[str]:
        return iter(f.name for f in fields(self))

    def __len__(self) -> int:
        return len(fields(self))


def read_frames(root: Path, cameras: tuple[CameraInfo, ...], meta_loc: Loc) -> FrameTable:
    path = root / "frames.csv"
    header, rows = read_csv(path, "frames table")
    if header != ["camera", "frame", "timestamp", "file"]:
        raise DatasetError(
            f"{path} line 1: header must be camera,frame,timestamp,file, got {','.join(header)}"
        )
    if not rows:
        raise DatasetError(f"{path}: no frames")
    cams = {c.name: c for c in cameras}
    cam, idx, ts, files, lines = [], [], [], [], []
    seen_row, seen_frame, seen_file = {}, {}, {}
    for line, row in rows:
        w = f"{path} line {line}"
        if len(row) != 4:
            raise DatasetError(f"{w}: expected 4 columns (camera,frame,timestamp,file), got {len(row)}")
        key = tuple(row)
        if key in seen_row:
            raise DatasetError(f"{w}: repeats line {seen_row[key]}")
        seen_row[key] = line
        name, frame_text, t_text, file = row
        if name not in cams:
            raise DatasetError(f"{w}: unknown camera {name!r}; metadata cameras are {sorted(cams)}")
        if not frame_text.isascii() or not frame_text.isdigit():
            raise DatasetError(f"{w}: frame {frame_text!r} is not a non-negative integer")
        frame = int(frame_text) if len(frame_text) <= 12 else MAX_FRAME_INDEX + 1
        if frame > MAX_FRAME_INDEX:
            raise DatasetError(
                f"{w}: frame {sc.show(frame_text)} is above the largest capture index {MAX_FRAME_INDEX}"
            )
        if (name, frame) in seen_frame:
            raise DatasetError(
                f"{w}: camera {name!r} frame {frame} is already on line {seen_frame[name, frame]}"
            )
        seen_frame[name, frame] = line
        t = parse_number(t_text, f"{w} column 'timestamp'")
        sc.relative_path(file, Loc(path, f"line {line} column 'file'"))
        if file in seen_file:
            raise DatasetError(f"{w}: file {file!r} is already named on line {seen_file[file]}")
        seen_file[file] = line
        cam.append(name)
        idx.append(frame)
        ts.append(t)
        files.append(file)
        lines.append(line)
    frames = FrameTable(
        camera=np.array(cam),
        frame=np.array(idx, dtype=np.int64),
        timestamp=np.array(ts, dtype=np.float64),
        file=np.array(files),
    )
    lines = np.array(lines)
    for name in cams:
        rows_c = np.flatnonzero(frames.camera == name)
        if rows_c.size == 0:
            continue
        f_c = frames.frame[rows_c]
        span = int(f_c.max() - f_c.min())
        bound = FRAME_SPAN_FACTOR * rows_c.size + FRAME_SPAN_SLACK
        if span > bound:
            worst = rows_c[np.argmax(np.abs(f_c - np.median(f_c)))]
            raise DatasetError(
                f"{path} line {lines[worst]}: camera {name!r} frame {frames.frame[worst]}: its frame indices "
                f"span {span}, more than {FRAME_SPAN_FACTOR} x its {rows_c.size} rows + {FRAME_SPAN_SLACK} "
                "(a capture index far off the others)"
            )
        order = rows_c[np.argsort(f_c, kind="stable")]
        t_c = frames.timestamp[order]
        bad = np.flatnonzero(np.diff(t_c) <= 0)
        if bad.size:
            a, b = order[bad[0]], order[bad[0] + 1]
            raise DatasetError(
                f"{path} lines {lines[a]} and {lines[b]}: camera {name!r} frame {frames.frame[a]} has timestamp "
                f"{float(frames.timestamp[a])!r} and the later frame {frames.frame[b]} has "
                f"{float(frames.timestamp[b])!r}; timestamps must increase strictly with the frame index"
            )
    _check_images(root, path, frames, lines, cameras, meta_loc)
    return frames


def _check_images(root: Path, path: Path, frames: dict, lines, cameras, meta_loc: Loc) -> None:
    """Every image exists, is an image, and has its camera's size (from the file header)."""
    index = {c.name: i for i, c in enumerate(cameras)}
    wrong: dict[str, list] = {}
    for k, (name, file) in enumerate(zip(frames.camera.tolist(), frames.file.tolist())):
        try:
            size = image_size(root / file, f"{path} line {lines[k]}: {file}")
        except DatasetError as e:  # say what to do: a capture is not lost to one bad image
            raise DatasetError(
                f"{e}; restore the file, or delete line {lines[k]} of {path.name} (a copy of the dataset) "
                "to calibrate without that frame"
            ) from None
        cam = cameras[index[name]]
        if size != (cam.width, cam.height):
            wrong.setdefault(name, []).append((k, size))
    for name, bad in wrong.items():
        k, (w, h) = bad[0]
        cam = cameras[index[name]]
        total = int(np.sum(frames.camera == name))
        more = f"; so are {len(bad) - 1} more of its {total} images" if len(bad) > 1 else ""
        raise DatasetError(
            f"{path} line {lines[k]}: {frames.file[k]} is {w}x{h} pixels, but {meta_loc.key('cameras')}"
            f"[{index[name]}] ({name!r}) says {cam.width}x{cam.height}{more}"
        )


# --------------------------------------------------------------------------- reading: the encoder log


def _encoder_table(
    path: Path, what: str, joints: tuple[str, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The encoder file's timestamps (T,), logged values (T, joints) and line numbers (T,)."""
    header, rows = read_csv(path, what)
    if not header or header[0] != "timestamp":
        raise DatasetError(f"{path} line 1: the header must start with 'timestamp', got {','.join(header)!r}")
    if tuple(header[1:]) != joints:
        unknown = [h for h in header[1:] if h not in joints]
        missing = [j for j in joints if j not in header[1:]]
        parts = [f"no column for joint(s) {missing}"] if missing else []
        parts += [f"unknown joint names {unknown}"] if unknown else []
        detail = "; ".join(parts) or f"columns {header[1:]} in another order or repeated"
        raise DatasetError(
            f"{path} line 1: {detail}; expected the robot's joints {list(joints)}, in that order"
        )
    if len(rows) < 2:
        raise DatasetError(f"{path}: fewer than 2 encoder readings")
    for line, row in rows:
        if len(row) != len(header):
            raise DatasetError(f"{path} line {line}: expected {len(header)} columns, got {len(row)}")
    try:
        values = np.array([row for _, row in rows], dtype=np.float64)
    except ValueError:
        values = None
    if values is None or not np.all(np.isfinite(values)):  # find the cell, name it
        for line, row in rows:
            for c, text in enumerate(row):
                parse_number(text, f"{path} line {line} column {header[c]!r}")
    lines = np.array([line for line, _ in rows])
    t = values[:, 0]
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        k = bad[0]
        raise DatasetError(
            f"{path} line {lines[k + 1]}: timestamp {float(t[k + 1])!r} is not after line {lines[k]}'s "
            f"{float(t[k])!r}; timestamps must increase strictly"
        )
    return t, values[:, 1:], lines


def _speed_limit(limits) -> float:
    return limits.velocity or enc.DEFAULT_VELOCITY[limits.joint_type]


def _glitches(t, q, lines, joints, limits) -> tuple[list[EncoderGlitch], list, np.ndarray]:
    """Every joint's isolated glitches, its jumps that stay, and the rows to drop."""
    glitches, jumps, drop = [], [], np.zeros(len(t), bool)
    for j, name in enumerate(joints):
        vmax = _speed_limit(limits[name])
        runs, leaps = enc.find_glitches(t, q[:, j], vmax)
        jumps += [(name, leap, vmax) for leap in leaps]
        for a, b in runs:
            before, after = max(a - 1, 0), min(b + 1, len(t) - 1)
            line = np.interp(t[a : b + 1], t[[before, after]], q[[before, after], j])
            size = float(np.max(np.abs(q[a : b + 1, j] - line)))
            glitches.append(
                EncoderGlitch(
                    name, (a, b), (int(lines[a]), int(lines[b])), float(t[before]), float(t[after]), size
                )
            )
            drop[a : b + 1] = True
    return glitches, jumps, drop


def _glitch_note(path: Path, glitches: list[EncoderGlitch], rows: int) -> str:
    where = "; ".join(
        f"line {g.lines[0]}"
        + (f"-{g.lines[1]}" if g.lines[1] != g.lines[0] else "")
        + f" ({g.joint}, {g.size:.3g} off, t = {g.t_start:.4f}..{g.t_end:.4f} s)"
        for g in glitches[:10]
    )
    return (
        f"{path}: {len(glitches)} isolated encoder glitch{'es' if len(glitches) > 1 else ''} removed ({rows} "
        f"rows): {where}{'; ...' if len(glitches) > 10 else ''}; frames taken in those controller-clock "
        "intervals are unreliable"
    )


def read_encoders(root: Path, emeta: dict, loc: Loc, joints: tuple[str, ...], limits: dict):
    """The encoder log in radians, checked and cleaned: `(t, motor, glitches, notes)`.

    Glitches are found first (one wild sample must not read as a unit mistake);
    the units are then checked on the clean rows (on all of them when the log is
    too glitchy to clean), and the speeds last.
    """
    path = root / emeta["file"]
    t, raw, lines = _encoder_table(path, f"encoder log (named by {loc.key('file')})", joints)
    prismatic = [j for j in joints if limits[j].joint_type == "prismatic"]
    if prismatic and emeta["unit"] != "rad":
        raise DatasetError(
            f"{loc.key('unit')} is {emeta['unit']!r}, an angle unit, but joint(s) {prismatic} are prismatic: "
            f"their columns of {path.name} hold metres; log every joint in SI units (rad and m) with unit 'rad'"
        )
    factor = enc.to_radians(emeta["unit"], emeta["counts_per_rev"])
    q = raw * factor / np.array([limits[j].reduction_ratio for j in joints])
    glitches, jumps, drop = _glitches(t, q, lines, joints, limits)
    reliable = not jumps and len(glitches) <= enc.GLITCH_MAX_COUNT and drop.mean() <= enc.GLITCH_MAX_FRACTION
    keep = ~drop if reliable else np.ones(len(t), bool)
    for j, name in enumerate(joints):
        problem = enc.unit_problem(
            raw[keep, j],
            factor,
            emeta["unit"],
            emeta["counts_per_rev"],
            limits[name],
            np.asarray(lines)[keep],
        )
        if problem is not None:
            raise DatasetError(f"{path} column {name!r}: {problem}")
    if jumps:
        name, leap, vmax = jumps[0]
        k = leap.index
        raise DatasetError(
            f"{path} line {lines[k]}: joint {name!r} jumps by {leap.size:.4g} (rad or m, joint side) in "
            f"{t[k] - t[k - 1]:.4g} s, beyond its speed limit of {vmax:.4g}/s, and does not come back within "
            f"{enc.GLITCH_MAX_RUN} samples: not an isolated glitch (an encoder reset, or a change of unit?)"
        )
    if not reliable:
        raise DatasetError(
            f"{path}: {len(glitches)} glitches over {int(drop.sum())} of {len(t)} rows (more than "
            f"{enc.GLITCH_MAX_COUNT} glitches or {100 * enc.GLITCH_MAX_FRACTION:g} % of the rows): the log is "
            f"unreliable (first at line {glitches[0].lines[0]}, joint {glitches[0].joint!r})"
        )
    t, q, raw, lines = t[keep], q[keep], raw[keep], lines[keep]
    if len(t) < 2:
        raise DatasetError(f"{path}: fewer than 2 encoder readings once the glitches are removed")
    for j, name in enumerate(joints):
        vmax = _speed_limit(limits[name])
        speed = np.abs(enc.local_rate(t, q[:, j]))
        k = int(np.argmax(speed))
        if speed[k] > enc.SPEED_FACTOR * vmax:
            unit = emeta["unit"]
            hint = " (degrees logged as radians move 57 times too fast)" if unit == "rad" else ""
            raise DatasetError(
                f"{path} line {lines[k]}: joint {name!r} moves at {speed[k]:.4g}/s (joint side), "
                f"{speed[k] / vmax:.0f} times its URDF velocity limit {vmax:.4g}/s; is encoders.unit "
                f"({unit!r}) right?{hint}"
            )
    notes = [_glitch_note(path, glitches, int(drop.sum()))] if glitches else []
    for j, name in enumerate(joints):  # within the unit check's margin, but past what the robot file allows
        lo, hi = limits[name].lower, limits[name].upper
        if lo is not None and hi is not None and (q[:, j].min() < lo or q[:, j].max() > hi):
            k = int(np.argmax(np.maximum(lo - q[:, j], q[:, j] - hi)))
            notes.append(
                f"{path} line {lines[k]}: joint {name!r} reaches {q[k, j]:.4g} (rad or m, joint side), outside "
                f"its URDF limits [{lo:.4g}, {hi:.4g}]: is the robot file this arm's (or its zero offset large)?"
            )
    if emeta["rate_hz"] is not None:
        rate = 1.0 / float(np.median(np.diff(t)))
        if abs(rate / emeta["rate_hz"] - 1.0) > 0.1:
            notes.append(
                f"{loc.key('rate_hz')} is {emeta['rate_hz']:g} Hz but {path.name} is sampled at {rate:.4g} Hz "
                "(median interval); the timestamps are used"
            )
    return t, raw * factor, tuple(glitches), notes
