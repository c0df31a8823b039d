"""The user's input files read: regular files only, within a size limit, UTF-8, each failure an E010 diagnostic.

Scenes and their includes (language/ast.py), the files a scene names (trajectories, calibrations, meshes) and
view-dependency files (viewdep.py) all come through here. No numpy: `wiredsl check` and the editor import it.
"""

from __future__ import annotations

import os
from pathlib import Path

from wiredsl.diagnostics import Diagnostic, Span, WiredslError

MAX_SOURCE_BYTES = 16 * 1024 * 1024  # a scene, include or matrix file larger than this is refused


def display_path(path: Path) -> str:
    """A path as the user should see it: relative to the working directory when inside it."""
    try:
        rel = os.path.relpath(path)
    except ValueError:  # another drive on Windows
        return str(path)
    return str(path) if rel.startswith(os.pardir) and os.path.isabs(path) else rel  # not '../../../dev/zero'


def read_bytes(path: Path, what: str, where: Span | None = None, limit: int | None = None) -> bytes:
    """A regular file's bytes, at most `limit`; FIFOs, devices, directories and loops are refused (E010).

    The stat comes first so that a FIFO or /dev/stdin is never opened (opening one would block).
    """
    from wiredsl.files import read_regular

    limit = MAX_SOURCE_BYTES if limit is None else limit
    shown = display_path(path) if "\0" not in str(path) else repr(str(path))
    try:
        if "\0" in str(path):
            raise ValueError("a path cannot contain a NUL byte")
        return read_regular(path, limit)
    except FileNotFoundError:
        msg = f"no such file: {shown}" if what == "file" else f"cannot read {what} {shown}: no such file"
    except ValueError as exc:
        msg = f"cannot read {what} {shown}: {exc}"
    except (OSError, RuntimeError) as exc:  # ELOOP, EACCES, ...; RuntimeError: a symlink loop in resolve()
        msg = f"cannot read {what} {shown}: {getattr(exc, 'strerror', None) or exc}"
    raise WiredslError([Diagnostic("error", "E010", msg, where)])


def decode(data: bytes, path: Path, what: str, where: Span | None = None) -> str:
    """UTF-8 text, or E010 at the line and column of the first bad byte."""
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        col = exc.start - (data.rfind(b"\n", 0, exc.start) + 1) + 1
        span = Span(display_path(path), line, col, line, col + 1)
        note = (f"{span.file} included from {where}",) if where is not None else ()
        raise WiredslError([Diagnostic("error", "E010", f"{what} {display_path(path)} is not UTF-8 text "
                                       f"({exc.reason} at byte {exc.start})", span, notes=note)]) from None
