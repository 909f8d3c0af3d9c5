"""Safe writes: atomic files, atomic output directories that never cost data.

`tempfile` creates private files (0600) and directories (0700); what we hand
over gets the permissions a plain `open()` / `mkdir()` would have given
under the process's umask.

Output directories (`jaxcal calibrate --out`, `jaxcal simulate --out`,
`jaxcal demo --out`, `write_outputs`, `simulate`) follow one set of rules,
checked by `check_output_dir` before any work and again when the results are
renamed into place (`atomic_directory`):

- the output may not be an input, contain one, or lie inside one (symbolic
  links resolved), with or without `overwrite`;
- an existing non-empty directory is replaced only with `overwrite`, and only
  when jaxcal wrote it (it holds a `.jaxcal` marker of the same kind); any
  other directory is left for the user to delete;
- a run holds an exclusive lock file beside the output (`.NAME.lock`), so a
  second run on the same output fails at once;
- the final rename refuses (Linux `renameat2(RENAME_NOREPLACE)`) a directory
  that appeared at the output during the run; on any failure nothing partial
  is left and an existing output is untouched; a temporary directory that a
  killed run (SIGKILL, power loss) left beside the output is removed by the
  next run that takes the lock (`_remove_stale_temps`).

Output files (`--json`, `--plot`, `plan --out`) follow the same rules by
`check_output_file` before any work, and are written through `atomic_file`.
Every temporary directory and file, and every lock, is registered with
`jaxcal._interrupt` while it exists, so that a command the user interrupts
(Ctrl-C) leaves none of them behind, and nothing is renamed into place after
the interrupt.
"""

import ctypes
import ctypes.util
import errno
import json
import os
import re
import secrets
import shutil
import tempfile
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from .. import _interrupt
from ..errors import DatasetError, OutputError
from ._schema import loads

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: no advisory locks, the checks still apply
    fcntl = None

#: The marker file jaxcal writes into every output directory it creates.
MARKER = ".jaxcal"
#: Output kinds: a dataset written by `simulate`, a calibration result, a demo directory.
KINDS = ("dataset", "result", "demo")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextmanager
def atomic_file(path):
    """Yield a new hidden temporary path beside `path`, with its suffix (matplotlib's `savefig`
    reads the format from it), for the block to write; when the block ends without an error it
    replaces `path` at once, so that readers see the old file or the new one, never a part. On
    an error or an interrupt nothing is left."""
    path = Path(path)
    fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp" + path.suffix)
    os.close(fd)
    tmp = Path(name)
    with _interrupt.partial(lambda: tmp.unlink(missing_ok=True)):
        try:
            yield tmp
            os.chmod(tmp, 0o666 & ~_umask())
            with _interrupt.committing():
                os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise


def write_text_atomic(path, text: str) -> None:
    """Write `text` to `path` (UTF-8) so that readers see the old file or the new one, never a part."""
    with atomic_file(path) as tmp, open(tmp, "w", encoding="utf-8") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())


def make_temp_dir(parent: Path, name: str) -> Path:
    """A new hidden directory in `parent` for building `name`, with the umask's permissions."""
    tmp = Path(tempfile.mkdtemp(dir=parent, prefix=f".{name}.", suffix=".tmp"))
    os.chmod(tmp, 0o777 & ~_umask())
    return tmp


#: The robot files jaxcal ships (`jaxcal.robots.ROBOTS_DIR`).
SHIPPED_ROBOTS = Path(__file__).resolve().parents[2] / "data" / "robots"


def shown(path) -> str:
    """How a message names `path`: a robot file jaxcal ships (the user named it, `ur5_dh`) as
    `data/robots/ur5_dh.json`, not by the absolute path of the installation; any other path as
    given."""
    p = Path(path)
    try:
        return (Path("data") / "robots" / p.resolve().relative_to(SHIPPED_ROBOTS)).as_posix()
    except (ValueError, OSError, RuntimeError):
        return str(path)


def resolved(path, what: str = "", *, error=DatasetError) -> Path:
    """`Path(path).resolve()`, a loop of symbolic links refused by name (`error`, a `JaxcalError`:
    `DatasetError` for an input, `OutputError` for an output) rather than Python's `RuntimeError`
    (before 3.13) or `OSError` (ELOOP)."""
    try:
        return Path(path).resolve()
    except RuntimeError:
        pass
    except OSError as e:
        if e.errno != errno.ELOOP:
            raise
    label = f"{what} {path}" if what else str(path)
    raise error(
        f"{label}: a loop of symbolic links (it never reaches a file or directory); name the file itself"
    )


# --------------------------------------------------------------------------- the marker


def _version() -> str:
    import importlib.metadata

    try:
        return importlib.metadata.version("jaxcal")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - source checkout
        return "0.0.0"


def _files_in(directory: Path) -> list[str]:
    """Every file under `directory` but the marker, as sorted relative POSIX paths."""
    return sorted(
        p.relative_to(directory).as_posix()
        for p in directory.rglob("*")
        if not p.is_dir() and p.name != MARKER
    )


def write_marker(directory, kind: str, *, complete: bool = False) -> None:
    """Write the `.jaxcal` marker (JSON: tool, kind, version) into `directory`; `complete`: the
    directory is whole, and the marker lists its files (`--overwrite` then refuses to delete a file
    added since)."""
    if kind not in KINDS:
        raise ValueError(f"unknown output kind {kind!r}; expected one of {KINDS}")
    payload = {"tool": "jaxcal", "kind": kind, "version": _version()}
    if complete:
        payload["files"] = _files_in(Path(directory))
    (Path(directory) / MARKER).write_text(json.dumps(payload) + "\n")


def note_written(directory, *names: str) -> None:
    """Add files jaxcal wrote into a finished output `directory` (after its atomic commit) to the
    marker's list, so that `--overwrite` may replace them."""
    directory = Path(directory)
    marker = read_marker(directory)
    if marker is None or not isinstance(marker.get("files"), list):
        return
    marker["files"] = sorted(set(marker["files"]) | set(names))
    write_text_atomic(directory / MARKER, json.dumps(marker) + "\n")


def read_marker(directory) -> dict | None:
    """The `.jaxcal` marker of `directory` (`tool`, `kind`, `version`), or `None`
    when there is none or it is not one jaxcal wrote."""
    try:
        data = loads((Path(directory) / MARKER).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or data.get("tool") != "jaxcal" or data.get("kind") not in KINDS:
        return None
    return data


# --------------------------------------------------------------------------- the checks


@dataclass(frozen=True)
class OutputDir:
    """What `check_output_dir` found at an output path.

    - `path`: the output as given; `kind`: what will be written there.
    - `replaces`: `(st_dev, st_ino)` of the jaxcal directory of the same kind
      that the output will replace (`overwrite`), `None` when the output is
      absent or an empty directory. `atomic_directory(..., checked=...)`
      refuses to replace anything else at the end of the run.
    """

    path: Path
    kind: str
    replaces: tuple[int, int] | None


def _is_within(a: Path, b: Path) -> bool:
    return a == b or b in a.parents


def check_output_dir(out, *, inputs=(), overwrite: bool = False, kind: str, what: str = "output directory"):
    """Check, before any work, that `out` can receive a jaxcal output directory of `kind`.

    **Arguments:**
    - `out`: the output directory (absent, empty, or with `overwrite` one that
      jaxcal wrote: it holds a `.jaxcal` marker of the same `kind`).
    - `inputs`: files and directories the run reads; `out` may not be one of
      them, contain one, or lie inside one (symbolic links resolved).
    - `overwrite`: allow replacing a non-empty directory that jaxcal wrote.
    - `kind`: `"dataset"`, `"result"` or `"demo"`.
    - `what`: how messages name the output (e.g. `"--out"`).

    **Returns:** an `OutputDir` recording what `out` holds now.

    Raises `OutputError` naming `out`, the input or the obstacle, and what to do.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown output kind {kind!r}; expected one of {KINDS}")
    out = Path(out)
    label = f"{what} {out}"
    if out.is_symlink():
        raise OutputError(f"{label}: is a symbolic link; name the directory itself")
    real = resolved(out, what, error=OutputError)
    if real.parent == real:
        raise OutputError(f"{label}: is a filesystem root")
    for inp in inputs:
        source = resolved(inp)
        if real == source:
            raise OutputError(f"{label}: is the input {inp}; jaxcal never writes over its inputs")
        if _is_within(source, real):
            raise OutputError(
                f"{label}: contains the input {inp}; replacing it would delete the input. Choose another {what}"
            )
        if _is_within(real, source):
            raise OutputError(
                f"{label}: lies inside the input {inp}; jaxcal never writes into its inputs. "
                f"Choose another {what}"
            )
    replaces = None
    if out.exists() and not out.is_dir():
        raise OutputError(f"{label}: exists and is not a directory")
    if out.is_dir():
        try:
            empty = not any(out.iterdir())
        except OSError as e:
            raise OutputError(f"{label}: cannot be listed ({e.strerror})") from None
        if not empty:
            if not overwrite:
                raise OutputError(
                    f"{label}: not empty (pass --overwrite / overwrite=True to replace a directory jaxcal wrote)"
                )
            marker = read_marker(out)
            if marker is None:
                raise OutputError(
                    f"{label}: not empty and not written by jaxcal (no {MARKER} marker file); --overwrite "
                    f"replaces only directories jaxcal wrote. Delete it yourself or choose another {what}"
                )
            if marker["kind"] != kind:
                raise OutputError(
                    f"{label}: holds a jaxcal {marker['kind']}, not a {kind}; --overwrite replaces only a "
                    f"{kind}. Delete it yourself or choose another {what}"
                )
            if isinstance(marker.get("files"), list):
                added = sorted(set(_files_in(out)) - set(marker["files"]))
                if added:
                    more = f" and {len(added) - 5} more" if len(added) > 5 else ""
                    raise OutputError(
                        f"{label}: holds file(s) jaxcal did not write there ({', '.join(added[:5])}{more}); "
                        "--overwrite would delete them. Move them out (or delete them yourself), or choose "
                        f"another {what}"
                    )
            st = out.lstat()
            replaces = (st.st_dev, st.st_ino)
    parent = real.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise OutputError(f"{label}: cannot be created: {parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"{label}: cannot write in {parent}")
    return OutputDir(out, kind, replaces)


def check_output_file(path, *, inputs=(), overwrite: bool = False, what: str = "output file") -> Path | None:
    """Check, before any work, that the file `path` may be written (`None` passes through).

    Refused, with an `OutputError` naming `what` and `path`: one of the `inputs`, or a file
    inside one (whatever `overwrite` says: jaxcal never writes into what it reads); an
    existing file without `overwrite`; a directory; a file whose folder does not exist. An
    output file's folder is not created (a misspelt folder would appear silently); an
    output directory's missing parents are (`output_lock`).
    """
    if path is None:
        return None
    path = Path(path)
    real = resolved(path, what, error=OutputError)
    for given in inputs:
        if given is not None and Path(given).exists():
            source = resolved(given)
            if _is_within(real, source):
                where = "is the input" if real == source else "lies inside the input"
                raise OutputError(f"{what} {path}: {where} {given}; jaxcal never writes over its inputs")
    if real.is_dir():
        raise OutputError(f"{what} {path}: is a directory; name a file")
    if path.exists() and not overwrite:
        raise OutputError(f"{what} {path}: exists (pass --overwrite to replace it)")
    if real.parent.exists() and not real.parent.is_dir():
        raise OutputError(f"{what} {path}: {path.parent} is not a folder")
    if not real.parent.is_dir():
        raise OutputError(
            f"{what} {path}: the folder {path.parent} does not exist; create it first (jaxcal creates an "
            "output directory's parents, not an output file's folder)"
        )
    return path


# --------------------------------------------------------------------------- the lock

_held: dict[str, list] = {}  # lock path -> [fd, depth]: re-entrant within one process
_held_guard = threading.Lock()


def _lock_path(out: Path, what: str) -> Path:
    real = resolved(out, what, error=OutputError)
    return real.parent / f".{real.name}.lock"


def _missing_ancestors(path: Path) -> list[Path]:
    missing = []
    while not path.exists():
        missing.append(path)
        path = path.parent
    return missing


@contextmanager
def output_lock(out, *, what: str = "output directory"):
    """Hold the exclusive lock file beside `out` (`.NAME.lock`) for the block.

    A second jaxcal process asking for the same output fails at once with an
    `OutputError`; within one process the lock is re-entrant. The lock file
    is removed on exit, and so are parent directories this call created if
    `out` was not made.
    """
    out = Path(out)
    if out.is_symlink():
        raise OutputError(f"{what} {out}: is a symbolic link; name the directory itself")
    lock = _lock_path(out, what)
    key = str(lock)
    with _held_guard:
        if key in _held:
            _held[key][1] += 1
            reentered = True
        else:
            reentered = False
    if reentered:
        try:
            yield lock
        finally:
            with _held_guard:
                _held[key][1] -= 1
        return
    created = _missing_ancestors(lock.parent)
    try:
        lock.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{what} {out}: cannot create {lock.parent} ({e.strerror})") from None
    fd = _acquire(lock, out, what)
    with _held_guard:
        _held[key] = [fd, 1]
    try:
        with _interrupt.partial(lambda: _release(fd, lock, out, created)):
            yield lock
    finally:
        with _held_guard:
            del _held[key]
        try:
            _release(fd, lock, out, created)
        finally:
            os.close(fd)


def _release(fd: int, lock: Path, out: Path, created: list[Path]) -> None:
    """Remove the lock file (if it is still the one `fd` holds), and the parent directories
    `output_lock` created when `out` was not made."""
    if fcntl is None or _same_file(fd, lock):
        lock.unlink(missing_ok=True)
    if not out.exists():
        for d in created:  # deepest first
            try:
                d.rmdir()
            except OSError:
                break


def _same_file(fd: int, path: Path) -> bool:
    try:
        a, b = os.fstat(fd), os.stat(path)
    except OSError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def _acquire(lock: Path, out: Path, what: str) -> int:
    for _ in range(20):
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o666)
        except OSError as e:
            raise OutputError(f"{what} {out}: cannot create the lock file {lock} ({e.strerror})") from None
        if fcntl is None:
            return fd
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            os.close(fd)
            if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise OutputError(
                    f"{what} {out}: another jaxcal run is writing there (it holds {lock}); wait for it to "
                    f"finish or choose another {what}"
                ) from None
            raise OutputError(f"{what} {out}: cannot lock {lock} ({e.strerror})") from None
        if _same_file(fd, lock):  # not unlinked by the previous holder meanwhile
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
            return fd
        os.close(fd)
    raise OutputError(f"{what} {out}: could not take the lock {lock} (it keeps changing)")


# --------------------------------------------------------------------------- the rename


def _libc_renameat2():
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    return fn


_renameat2 = _libc_renameat2()
_AT_FDCWD = -100
_RENAME_NOREPLACE = 1


def rename_noreplace(src, dst) -> None:
    """Rename `src` to `dst`, refusing (FileExistsError) if `dst` exists.

    Linux: one atomic `renameat2(RENAME_NOREPLACE)`. Elsewhere, or on a
    filesystem without it: a check then `os.rename`, which replaces at most an
    empty directory created in between (never data).
    """
    if _renameat2 is not None:
        if _renameat2(_AT_FDCWD, os.fsencode(src), _AT_FDCWD, os.fsencode(dst), _RENAME_NOREPLACE) == 0:
            return
        err = ctypes.get_errno()
        if err in (errno.EEXIST, errno.ENOTEMPTY):
            raise FileExistsError(err, os.strerror(err), str(dst))
        if err not in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP):
            raise OSError(err, os.strerror(err), str(src))
    if os.path.lexists(dst):
        raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), str(dst))
    try:
        os.rename(src, dst)
    except OSError as e:
        if e.errno in (errno.EEXIST, errno.ENOTEMPTY):
            raise FileExistsError(e.errno, e.strerror, str(dst)) from None
        raise


def _identity(path: Path) -> tuple[int, int] | None:
    try:
        st = path.lstat()
    except FileNotFoundError:
        return None
    return (st.st_dev, st.st_ino)


def _commit(tmp: Path, dest: Path, replaces: tuple[int, int] | None, label: str) -> None:
    """Rename `tmp` to `dest`, replacing only the directory `replaces` names (or an empty one)."""
    appeared = (
        f"{label}: a directory appeared there during the run (another process?); refusing to replace it. "
        "Nothing was written"
    )
    changed = f"{label}: changed during the run; refusing to replace it. Nothing was written"
    now = _identity(dest)
    if now is not None and now != replaces:
        try:
            dest.rmdir()  # an empty directory holds nothing to lose
        except OSError:
            raise OutputError(appeared if replaces is None else changed) from None
        now = None
    if now is None:
        try:
            rename_noreplace(tmp, dest)
        except FileExistsError:
            raise OutputError(appeared) from None
        return
    old = dest.parent / f".{dest.name}.{os.getpid()}.{secrets.token_hex(4)}.old"
    rename_noreplace(dest, old)
    if _identity(old) != replaces:  # swapped in the instant between the check and the rename
        rename_noreplace(old, dest)
        raise OutputError(changed)
    try:
        rename_noreplace(tmp, dest)
    except FileExistsError:
        try:
            rename_noreplace(old, dest)
        except OSError:
            raise OutputError(f"{appeared}; the previous {dest.name} is kept as {old}") from None
        raise OutputError(appeared) from None
    shutil.rmtree(old, ignore_errors=True)


@contextmanager
def atomic_directory(
    dest,
    *,
    overwrite: bool = False,
    inputs=(),
    kind: str = "result",
    what: str = "output directory",
    checked: OutputDir | None = None,
):
    """Yield a temporary directory beside `dest`; on success it becomes `dest`.

    The rules of `check_output_dir` apply (`inputs`, `overwrite`, `kind`,
    `what`); the `.jaxcal` marker of `kind` is written into the directory; the
    lock beside `dest` is held throughout. `checked`: the `OutputDir` that
    `check_output_dir` gave when the run started: the directory it found is
    the only one that may be replaced (one that appeared since is refused).
    On failure nothing is left behind and an existing `dest` is untouched.
    """
    dest = Path(dest)
    label = f"{what} {dest}"
    with output_lock(dest, what=what):
        found = check_output_dir(dest, inputs=inputs, overwrite=overwrite, kind=kind, what=what)
        replaces = found.replaces
        if checked is not None and replaces is not None and replaces != checked.replaces:
            raise OutputError(
                f"{label}: a different directory is there than when the run started; refusing to replace it"
            )
        parent = resolved(dest, what, error=OutputError).parent
        _remove_stale_temps(parent, dest.name)
        tmp = make_temp_dir(parent, dest.name)
        with _interrupt.partial(lambda: _remove_tree(tmp)):
            try:
                yield tmp
                write_marker(tmp, kind, complete=True)
                with _interrupt.committing():
                    _commit(tmp, parent / dest.name, replaces, label)
            except BaseException:
                shutil.rmtree(tmp, ignore_errors=True)
                raise


def _remove_stale_temps(parent: Path, name: str) -> None:
    """Remove the temporary directories of output `name` (`make_temp_dir`'s `.NAME.XXXXXXXX.tmp`)
    that runs killed outright left in `parent`: whoever holds the output's lock is the only run
    that writes one, so those found while holding it are dead runs'."""
    stale = re.compile(rf"\.{re.escape(name)}\.[a-z0-9_]{{8}}\.tmp")
    for entry in parent.iterdir():
        if stale.fullmatch(entry.name) and entry.is_dir() and not entry.is_symlink():
            _remove_tree(entry)


def _remove_tree(path: Path) -> None:
    """`shutil.rmtree`, again while the main thread may still be adding to it (an interrupt)."""
    for _ in range(3):
        shutil.rmtree(path, ignore_errors=True)
        if not path.exists():
            return


@contextmanager
def marked_directory(out, *, kind: str, what: str = "output directory"):
    """A plain (not atomic) output directory that jaxcal fills piece by piece
    (the demo's dataset and result): checked as by `check_output_dir` with
    `overwrite` (absent, empty, or a jaxcal directory of `kind`), locked,
    created with its `.jaxcal` marker. If the block fails and this call created
    the directory, it is removed again when it holds nothing but the marker."""
    out = Path(out)
    check_output_dir(out, overwrite=True, kind=kind, what=what)
    with output_lock(out, what=what):
        check_output_dir(out, overwrite=True, kind=kind, what=what)
        created = not out.exists()
        out.mkdir(parents=True, exist_ok=True)
        fresh = read_marker(out) is None
        if fresh:
            write_marker(out, kind)

        def unmake() -> None:
            if fresh and [p.name for p in out.iterdir()] == [MARKER]:
                (out / MARKER).unlink()
                if created:
                    out.rmdir()

        with _interrupt.partial(unmake):
            try:
                yield out
            except BaseException:
                unmake()
                raise
