"""Atomic output: files and whole output folders are written under a temporary name, then renamed into place.

Temporaries are named `.<target>.wiredsl-<host>-<pid>-<token>.tmp` (and `.old` for a folder moved aside),
so the next write to the same target can recognise and remove those a killed process left: on this host,
when its pid no longer runs (another host's, on a shared file system, are left to that host).
Every writer passes its values through `require_finite` (or `json_text`, built on it): no output can
hold NaN, infinity or a number its format cannot store. It imports nothing of wiredsl: every layer writes
through it (the engine's kernel cache, io's dumps and meshes' caches, studies, the commands).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import secrets
import shutil
import signal
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from wiredsl import check_stop

_TEMP = re.compile(r"^\.(?P<target>.+)\.wiredsl-(?P<host>[A-Za-z0-9_]+)-(?P<pid>\d+)-[A-Za-z0-9_]+\.(tmp|old)$")
_SIGNALS = {signal.SIGINT, signal.SIGTERM}
_HOST = re.sub(r"[^A-Za-z0-9]", "_", os.uname().nodename)[:64] or "host"  # socket.gethostname(), without socket


class UnwritableValue(ValueError):
    """A value no output may hold (NaN, infinity, or beyond the format's range): refused before writing."""


class OutputFolderError(ValueError):
    """An output folder that cannot or must not be replaced (a file, or a folder of someone else's files)."""


def require_finite(value, where: str = "value", dtype: type | None = None):
    """`value` (number, array, or nested dict/list of them) unchanged, or UnwritableValue naming where it fails.

    With `dtype` (e.g. np.float32) an array is returned cast to it, and values beyond its range are refused.
    """
    if isinstance(value, np.ndarray | np.generic):
        a = np.asarray(value)
        if a.dtype.kind in "fc" and not np.isfinite(a).all():
            i = tuple(int(j) for j in np.argwhere(~np.isfinite(a))[0])
            raise UnwritableValue(f"{where}{list(i) if i else ''} is {a[i]} (not a finite number)")
        if dtype is not None and np.dtype(dtype).kind == "f" and a.dtype != dtype:
            with np.errstate(over="ignore"):
                cast = a.astype(dtype)
            if not np.isfinite(cast).all():
                i = tuple(int(j) for j in np.argwhere(~np.isfinite(cast))[0])
                raise UnwritableValue(f"{where}{list(i) if i else ''} is {a[i]:g}, beyond the range of "
                                      f"{np.dtype(dtype).name} ({np.finfo(dtype).max:g})")
            return cast
        if dtype is not None and a.dtype != dtype:
            info = np.iinfo(dtype)
            if a.size and (a.min() < info.min or a.max() > info.max):
                raise UnwritableValue(f"{where} holds {a.max() if a.max() > info.max else a.min()}, beyond the "
                                      f"range of {np.dtype(dtype).name} ({info.min}..{info.max})")
            return a.astype(dtype)
        return a
    if isinstance(value, float):
        if not math.isfinite(value):
            raise UnwritableValue(f"{where} is {value} (not a finite number)")
    elif isinstance(value, dict):
        for k, v in value.items():
            require_finite(v, f"{where}.{k}")
    elif isinstance(value, list | tuple):
        for i, v in enumerate(value):
            require_finite(v, f"{where}[{i}]")
    return value


class UnreadableFile(ValueError):
    """A path refused before reading: not a regular file, or larger than the reader's limit."""


def regular_size(path: str | os.PathLike, limit: int) -> int:
    """The size of a regular file of at most `limit` bytes, else UnreadableFile saying why.

    Only a stat: a FIFO or /dev/stdin is never opened (opening one would block), /dev/zero never read.
    """
    st = os.stat(path)
    if stat.S_ISDIR(st.st_mode):
        raise UnreadableFile("is a directory")
    if not stat.S_ISREG(st.st_mode):
        raise UnreadableFile("is not a regular file (a FIFO, device or socket)")
    if st.st_size > limit:
        raise UnreadableFile(f"is {st.st_size:,} bytes, over the limit of {limit:,}")
    return st.st_size


def read_regular(path: str | os.PathLike, limit: int) -> bytes:
    """A regular file's bytes (at most `limit`, even if it grows while read); see `regular_size`.

    The one reader of every input (scenes, includes, matrices, dumps): OSError as open raises it.
    """
    regular_size(path, limit)
    with open(path, "rb") as fh:
        data = fh.read(limit + 1)
    if len(data) > limit:
        raise UnreadableFile(f"is over the limit of {limit:,} bytes")
    return data


def json_text(obj, indent: int | None = 1, sort_keys: bool = False, where: str = "document") -> str:
    """JSON text of plain data, refusing non-finite numbers (located by `require_finite`)."""
    try:
        return json.dumps(obj, indent=indent, sort_keys=sort_keys, allow_nan=False) + "\n"
    except ValueError:
        require_finite(obj, where)  # names the first offending number
        raise


_NON_FINITE = re.compile(r"-?Infinity|NaN")
MAX_INT_DIGITS = 4300  # CPython's default limit on int(str)


def json_loads(text: str):
    """json.loads that refuses NaN, Infinity and -Infinity (Python's extensions; not JSON, RFC 8259) with a
    JSONDecodeError at the token, as for any other text that is not JSON. Read by orjson, and by the standard
    library's reader for the message when orjson refuses the text."""
    def refuse(token: str):
        at = next((m.start() for m in _NON_FINITE.finditer(text) if m.group() == token
                   and _outside_strings(text, m.start())), 0)
        raise json.JSONDecodeError(f"{token} is not a JSON number (JSON has no NaN or infinity)", text, at)

    def number(token: str) -> float:
        x = float(token)
        if not math.isfinite(x):  # 1e999: Python reads it as infinity
            raise json.JSONDecodeError(f"{token} is beyond the range of a double", text, text.find(token))
        return x

    def integer(token: str) -> int:
        if len(token) > MAX_INT_DIGITS:  # int() refuses it (ValueError, CPython's limit on digits), as should we
            raise json.JSONDecodeError(f"an integer of {len(token):,} digits is beyond any number a document holds",
                                       text, text.find(token))
        return int(token)

    import orjson

    try:
        return orjson.loads(text)  # several times faster; it refuses NaN and infinity too
    except orjson.JSONDecodeError:
        pass  # the reader below says where and why, or reads what orjson does not (integers past 64 bits)
    try:
        return json.loads(text, parse_constant=refuse, parse_float=number, parse_int=integer)
    except RecursionError:
        raise json.JSONDecodeError("nested too deeply for this reader", text, 0) from None


def _outside_strings(text: str, at: int) -> bool:
    """Whether position `at` of JSON text is outside every string (an even count of unescaped quotes before)."""
    return len(re.findall(r'(?<!\\)(?:\\\\)*"', text[:at])) % 2 == 0


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale(target: str | os.PathLike) -> list[Path]:
    """Remove the temporaries of `target` (file or folder) left beside it by processes that no longer run."""
    target = Path(target)
    gone = []
    with contextlib.suppress(OSError):
        for p in target.parent.iterdir():
            m = _TEMP.match(p.name)
            if (m and m["target"] == target.name and m["host"] == _HOST and int(m["pid"]) != os.getpid()
                    and not _alive(int(m["pid"]))):
                _remove(p)
                gone.append(p)
    return gone


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            p.unlink()


def _tag() -> str:
    return f"wiredsl-{_HOST}-{os.getpid()}-"


def _temp_name(target: Path, suffix: str) -> Path:
    return target.parent / f".{target.name}.{_tag()}{secrets.token_hex(4)}{suffix}"


def temporary(target: str | os.PathLike, suffix: str = ".tmp") -> Path:
    """A fresh name for a temporary of `target` beside it, which `remove_stale(target)` removes once its process
    no longer runs."""
    return _temp_name(Path(target), suffix)


def _named(exc: OSError, path: Path) -> OSError:
    """The same error naming the target, not the temporary the user never asked for."""
    return type(exc)(exc.errno, exc.strerror or str(exc), str(path))


def publish(tmp: str | os.PathLike, path: str | os.PathLike) -> None:
    """Give a finished temporary file ordinary permissions (mkstemp makes it private) and rename it, unless a
    signal came that the code it landed in dropped: then the temporary goes and the output stays as it was."""
    check_stop()
    os.chmod(tmp, 0o666 & ~_umask())
    os.replace(tmp, path)


def write_atomic(path: str | os.PathLike, data: str | bytes, tidy: bool = True) -> None:
    """Replace `path` with `data` so that readers see the old file or the new one, never a part.

    A device or FIFO (e.g. /dev/null) is written into, not replaced. `tidy` first removes the temporaries a
    killed writer of `path` left (a listing of the folder: pass False for the many files of a fresh folder).
    """
    path = Path(path)
    if path.is_dir():
        raise OutputFolderError(f"{path} is a folder")
    raw = data.encode("utf-8") if isinstance(data, str) else data
    if path.exists() and not path.is_file():  # /dev/null, a FIFO: write into it, never rename over it
        try:
            with open(path, "wb") as fh:
                fh.write(raw)
            return
        except OSError as exc:
            raise _named(exc, path) from None
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        if tidy:
            remove_stale(path)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{_tag()}", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as fh:
                fh.write(raw)
                fh.flush()
                os.fsync(fh.fileno())
            publish(tmp, path)
        finally:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)  # still there only when something failed
    except OSError as exc:
        raise _named(exc, path) from None


# --------------------------------------------------------------------------- output folders

# What other commands (viewdep, bench, export-calibration) write into a build folder: a rebuild keeps it.
KEPT = ("viewdep.json", "bench.svg", "bench.png", "bench.pdf", "calibration")
_OURS = re.compile(r"^(manifest\.json|features\.(json|jsonl|npz)|pose_\d+\.svg|viewdep\.json|bench\.(svg|png|pdf)"
                   r"|calibration|render\.json|(left|right)_\d+\.png|ideal|trial_\d{5,})$")


def check_output_folder(target: str | os.PathLike, force: bool = False) -> None:
    """Refuse a target that is a file, holds the working directory, or holds files wiredsl did not write."""
    target = Path(target)
    if target.exists() and not target.is_dir():
        raise OutputFolderError(f"must be a folder: {target} is a file")
    here = Path.cwd().resolve()
    resolved = target.resolve()
    if resolved == here or resolved in here.parents or resolved == Path.home().resolve():
        raise OutputFolderError(f"{target} holds the working or home folder; name a folder of its own")
    if target.is_dir() and not force:
        foreign = sorted(p.name for p in target.iterdir() if not _OURS.match(p.name))
        if foreign:
            raise OutputFolderError(f"{target} holds files wiredsl did not write ({', '.join(foreign[:3])}"
                                    f"{', ...' if len(foreign) > 3 else ''}); pass --force to replace it whole")


@contextlib.contextmanager
def output_folder(target: str | os.PathLike, force: bool = False) -> Iterator[Path]:
    """A fresh temporary sibling of `target` to write a whole run into; swapped into place when the block ends.

    On any exception (a signal included) the temporary is removed and `target` is left as it was. The swap
    renames the old folder aside, the new one in, and removes the old one, with SIGINT and SIGTERM held off,
    so `target` always holds one whole run, and of two concurrent runs the last to finish wins whole.
    """
    target = Path(target)
    if target.is_symlink() and target.is_dir():  # the run goes where the link points; the link stays
        target = Path(os.path.realpath(target))
    check_output_folder(target, force)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        remove_stale(target)
        stage = _temp_name(target, ".tmp")
        stage.mkdir()
    except OSError as exc:
        raise _named(exc, target) from None
    try:
        yield stage
        _swap(stage, target)
    except OSError as exc:
        raise _named(exc, target) from None
    finally:
        _remove(stage)


def _swap(stage: Path, target: Path) -> None:
    """Rename `target` aside, `stage` in (the commit), remove the aside; signals held off the whole while. A signal
    that came before the commit puts the old folder back and stops the run (check_stop); one that came after it
    came too late to stop a run now whole, and is dropped."""
    from wiredsl import clear_stops, hold_stops, pending_stop

    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)
    hold_stops(True)
    try:
        check_stop()  # a signal dropped where it landed: the run is not swapped in
        os.chmod(stage, 0o777 & ~_umask())
        for name in KEPT:  # files hard-linked (free), folders copied: the old folder's copy goes with it
            old, new = target / name, stage / name
            if new.exists() or old.is_symlink():
                continue
            with contextlib.suppress(OSError):
                if old.is_file():
                    os.link(old, new)
                elif old.is_dir():
                    shutil.copytree(old, new, symlinks=True)
        for _ in range(100):  # another run may swap in between our two renames: move it aside too
            aside = _temp_name(target, ".old")
            moved = False
            with contextlib.suppress(FileNotFoundError):
                os.rename(target, aside)
                moved = True
            if pending_stop() is not None:  # before the commit: the old folder back, and stop
                if moved:
                    with contextlib.suppress(OSError):
                        os.rename(aside, target)
                check_stop()
            try:
                os.rename(stage, target)
            except OSError:
                _remove(aside)
                if not target.is_dir():
                    raise
                continue
            _remove(aside)
            if pending_stop() is not None:  # after the commit: the run is whole and in place
                clear_stops()
            return
        raise OSError(f"{target} kept being replaced by other runs")
    finally:
        hold_stops(False)
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)


def printable_path(text: str) -> str:
    """Text for a UTF-8 document (JSON, SVG) from text that may hold a path that is not UTF-8: os.fsdecode keeps
    such bytes as lone surrogates, which no UTF-8 writer takes, so each shows as U+FFFD."""
    return re.sub("[\ud800-\udfff]", "\ufffd", text)


def cache_folder(kind: str) -> Path | None:
    """wiredsl's on-disk cache of `kind` (kernels, meshes): $XDG_CACHE_HOME/wiredsl/kind (default ~/.cache), else
    a folder of this user's under the temporary directory when the home is read-only; None if neither can be
    made. A cache only saves time: callers go on without one. A folder is used only if this user owns it and
    nobody else may write into it, since what it holds is loaded as code (kernels) or trusted as data (meshes):
    a shared temporary directory lets another user make the folder first."""
    uid = getattr(os, "getuid", lambda: None)()
    home = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "wiredsl" / kind
    spare = Path(tempfile.gettempdir()) / f"wiredsl-{kind}-{uid}"
    for folder in (home, spare):
        try:
            folder.mkdir(mode=0o700, parents=True, exist_ok=True)
            st = folder.lstat()
        except OSError:
            continue
        if not stat.S_ISDIR(st.st_mode) or (uid is not None and st.st_uid != uid) or st.st_mode & 0o022:
            continue
        if os.access(folder, os.W_OK | os.X_OK):
            return folder
    return None


def prune_cache(folder: Path, pattern: str, keep: int, companions=lambda path: ()) -> None:
    """Remove the files of `folder` matching `pattern` beyond the `keep` most recently used (by access time,
    which the caches set on each use), each with its `companions(path)`; a file another process removed first
    is no error."""
    with contextlib.suppress(OSError):
        files = sorted(folder.glob(pattern), key=lambda p: p.stat().st_atime_ns, reverse=True)
        for old in files[keep:]:
            for f in (old, *companions(old)):
                f.unlink(missing_ok=True)
