"""Reading triangle meshes (OBJ, PLY, STL, glTF/GLB) for `mesh read`: vertices and triangles, checked.

trimesh parses the formats (the optional extra `mesh`, imported here only). Before it runs, the file is
read through the same gate as an included file (a regular file under MAX_MESH_BYTES: never a FIFO or a
device), and the triangle count the file declares (PLY's `element face`, binary STL's count, OBJ's `f`
lines) is checked against MAX_TRIANGLES, so a size bomb is refused before any array is allocated.

What trimesh reads is kept in wiredsl's cache (`files.cache_folder("meshes")`, an npz a file keyed by the
sha256 of its bytes, its format and trimesh's version), so a scene built again does not import trimesh (half
a second of CPU); the cache keeps the CACHE_FILES most recently used meshes.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import logging
import os
import re
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MAX_MESH_BYTES = 256 * 1024 * 1024  # a mesh file larger than this is refused
MAX_TRIANGLES = 2_000_000  # triangles a mesh may declare or hold
FORMATS = {".obj": "obj", ".ply": "ply", ".stl": "stl", ".gltf": "gltf", ".glb": "glb"}
CACHE_FILES = 64  # meshes kept in the cache, the least recently used removed first
READER = 2  # this reader's version in the cache key: a change of what is kept makes new keys


class MeshFileError(ValueError):
    """A mesh file that cannot be used; the message says why (no path: the caller's diagnostic has it)."""


class MeshTooLarge(MeshFileError):
    """A mesh over MAX_TRIANGLES."""


@dataclass(frozen=True)
class RawMesh:
    """Vertices (n, 3) float64 in file units and triangles (m, 3) int64 indices into them."""

    vertices: np.ndarray
    triangles: np.ndarray
    warnings: tuple[str, ...] = ()  # what the reader (trimesh) logged about the file, for W127


def declared_triangles(data: bytes, kind: str) -> int:
    """Triangles (or polygons) the file says it holds, read from its header or counted cheaply."""
    if kind == "ply":
        head = data[:65536].split(b"end_header", 1)[0]
        m = re.search(rb"element\s+face\s+(\d+)", head)
        return int(m.group(1)) if m else 0
    if kind == "stl":
        if data[:5].lower() == b"solid" and b"facet" in data[:4096]:
            return data.count(b"facet normal")
        return struct.unpack("<I", data[80:84])[0] if len(data) >= 84 else 0
    if kind == "obj":
        return data.count(b"\nf ") + data.startswith(b"f ")
    return 0  # glTF: its arrays are in the file, bounded by its size


def read_mesh(path: Path, data: bytes) -> RawMesh:
    """The mesh in `data` (the bytes of `path`, whose suffix names the format); MeshFileError if unusable."""
    kind = FORMATS.get(path.suffix.lower())
    if kind is None:
        raise MeshFileError(f"unknown mesh format '{path.suffix}' (expected one of: {', '.join(FORMATS)})")
    declared = declared_triangles(data, kind)
    if declared > MAX_TRIANGLES:
        raise MeshTooLarge(f"declares {declared:,} triangles, over the limit of {MAX_TRIANGLES:,}")
    key = _cache_key(data, kind)
    cached = _from_cache(key) if key is not None else None
    if cached is not None:
        return _checked(*cached, kind)
    if kind == "obj":
        _check_obj_vertices(data)
    try:
        import trimesh
    except ImportError as exc:  # pragma: no cover - the extra is part of `test`
        raise MeshFileError("reading meshes needs trimesh: pip install 'wiredsl[mesh]'") from exc
    log = _Log()
    try:
        with log.capturing():  # trimesh logs a damaged file's problems, tracebacks and all, on stderr
            loaded = trimesh.load(io.BytesIO(data), file_type=kind, process=False, force="mesh",
                                  resolver=None if kind != "gltf" else _NoFiles())
    except MeshFileError:
        raise
    except Exception as exc:  # trimesh raises anything from ValueError to IndexError on a broken file
        raise MeshFileError(f"not a readable {kind.upper()} mesh ({type(exc).__name__}: {exc})"[:300]) from None
    if log.errors:
        raise MeshFileError(f"not a readable {kind.upper()} mesh (the reader: {log.errors[0]})"[:300])
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=float).reshape(-1, 3)
    triangles = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
    raw = _checked(vertices, triangles, kind)
    if log.warnings:  # said each time the file is read: not cached
        return RawMesh(raw.vertices, raw.triangles, tuple(dict.fromkeys(log.warnings)))
    if key is not None:
        _to_cache(key, raw)
    return raw


class _Log(logging.Handler):
    """What trimesh logs at WARNING and above while it reads, kept (one line each, an exception's type and
    message instead of its traceback) rather than printed on stderr by logging's last-resort handler."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.warnings: list[str] = []
        self.errors: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        exc = record.exc_info[1] if record.exc_info else None
        if exc is not None:
            text += f" ({type(exc).__name__}: {exc})"
        (self.errors if record.levelno >= logging.ERROR else self.warnings).append(text[:300])

    @contextlib.contextmanager
    def capturing(self):
        logger = logging.getLogger("trimesh")
        propagate = logger.propagate
        logger.addHandler(self)
        logger.propagate = False
        try:
            yield self
        finally:
            logger.removeHandler(self)
            logger.propagate = propagate


# a vertex line with fewer than three numbers: trimesh reads the file's numbers as one run, three a vertex, so
# such a line shifts every later vertex (or the run cannot be cut into threes at all)
_SHORT_VERTEX = re.compile(rb"^v(?:[ \t]+[^\s]+){0,2}[ \t]*\r?$", re.M)


def _check_obj_vertices(data: bytes) -> None:
    """MeshFileError naming the first OBJ vertex line (`v x y z [w]`) that has fewer than three coordinates."""
    m = _SHORT_VERTEX.search(data)
    if m is not None:
        line = data.count(b"\n", 0, m.start()) + 1
        text = m.group().strip().decode("utf-8", "replace")
        shown = text if len(text) <= 40 else text[:40] + "..."
        raise MeshFileError(f"line {line}: a vertex needs x, y and z; '{shown}' has {len(text.split()) - 1} "
                            f"coordinate(s)")


def _checked(vertices: np.ndarray, triangles: np.ndarray, kind: str) -> RawMesh:
    if len(triangles) == 0:
        raise MeshFileError(f"holds no triangles (an empty mesh, or not {kind.upper()})")
    if len(triangles) > MAX_TRIANGLES:
        raise MeshTooLarge(f"holds {len(triangles):,} triangles, over the limit of {MAX_TRIANGLES:,}")
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise MeshFileError(f"vertex {int(np.flatnonzero(bad)[0]) + 1} is not finite ({bad.sum()} of "
                            f"{len(vertices)} vertices are not)")
    if triangles.min() < 0 or triangles.max() >= len(vertices):
        raise MeshFileError("a triangle refers to a vertex the file does not have")
    return RawMesh(vertices, triangles)


def _cache_key(data: bytes, kind: str) -> str | None:
    """The file's cache name: its bytes, format, trimesh's version and this reader's; None without trimesh."""
    from importlib import metadata

    try:
        version = metadata.version("trimesh")
    except metadata.PackageNotFoundError:
        return None
    h = hashlib.sha256(data)  # (data + suffix would copy a file of up to 256 MiB)
    h.update(f"\0{kind}\0{version}\0{READER}".encode())
    return h.hexdigest()[:40]


def _from_cache(key: str) -> tuple[np.ndarray, np.ndarray] | None:
    """A cached mesh's arrays, or None (not cached, or a cache file that is not one: it is read afresh)."""
    from wiredsl.io.files import cache_folder

    folder = cache_folder("meshes")
    path = folder / f"{key}.npz" if folder is not None else None
    if path is None or not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            V, F = z["vertices"], z["triangles"]
        if V.dtype != np.float64 or F.dtype != np.int64 or V.ndim != 2 or F.ndim != 2 or V.shape[1] != 3 \
                or F.shape[1] != 3:
            return None
        os.utime(path)  # recently used
        return V, F
    except Exception:  # a damaged or foreign file in the cache only costs a fresh read
        return None


def _to_cache(key: str, raw: RawMesh) -> None:
    """Keep a mesh's arrays (written atomically; a cache that cannot be written is no error), and remove the
    least recently used beyond CACHE_FILES."""
    from wiredsl.io.files import cache_folder, prune_cache, write_atomic

    folder = cache_folder("meshes")
    if folder is None:
        return
    buf = io.BytesIO()
    np.savez(buf, vertices=raw.vertices, triangles=raw.triangles)
    try:
        write_atomic(folder / f"{key}.npz", buf.getvalue(), tidy=False)
    except OSError:
        return
    prune_cache(folder, "*.npz", CACHE_FILES)


class _NoFiles:
    """A glTF's resolver that refuses its external buffers: a scene reads the one file it names."""

    def get(self, name: str) -> bytes:
        raise MeshFileError(f"the glTF refers to another file ({name!r}); use a .glb, which holds its buffers")

    __getitem__ = get

    def namespaced(self, namespace: str):
        return self
