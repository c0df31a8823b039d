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

from wiredsl import install_hint

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
    warnings: tuple[str, ...] = ()  # what the reader (trimesh) logged about the file, for W128


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
        raise MeshFileError(f"reading meshes needs trimesh: {install_hint('mesh')}") from exc
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
    if len(triangles) == 0 and kind == "ply":
        _ply_without_faces(data, len(vertices))
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


def _ply_without_faces(data: bytes, n_vertices: int) -> None:
    """Say what a PLY without triangles holds instead (its header's elements), e.g. triangle strips."""
    head = data[:65536].split(b"end_header", 1)[0].decode("latin-1", "replace")
    elements = re.findall(r"element\s+(\S+)\s+(\d+)", head)
    if not elements:
        return
    held = ", ".join(f"{int(n):,} {name}" for name, n in elements)
    hint = (" (triangle strips: convert them to faces first, e.g. in MeshLab or with trimesh)"
            if any("strip" in name for name, _ in elements) else "")
    raise MeshFileError(f"holds no triangles: its header declares {held}{hint}; {n_vertices:,} vertices were read")


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
    a = _cache_read(key, ("vertices", "triangles"))
    if a is None:
        return None
    V, F = a["vertices"], a["triangles"]
    if V.dtype != np.float64 or F.dtype != np.int64 or V.ndim != 2 or F.ndim != 2 or V.shape[1] != 3 \
            or F.shape[1] != 3:
        return None
    return V, F


def _to_cache(key: str, raw: RawMesh) -> None:
    """Keep a mesh's arrays."""
    _cache_write(key, {"vertices": raw.vertices, "triangles": raw.triangles})


def _cache_read(key: str, names) -> dict[str, np.ndarray] | None:
    """The arrays `names` of the cache file `key` (marked recently used), or None: no cache folder, not cached, or
    a file that is not one (a damaged or foreign file in the cache only costs reading the mesh afresh)."""
    from wiredsl.files import cache_folder

    folder = cache_folder("meshes")
    path = folder / f"{key}.npz" if folder is not None else None
    if path is None or not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {name: z[name] for name in names}
        os.utime(path)  # recently used
        return arrays
    except Exception:
        return None


def _cache_write(key: str, arrays: dict[str, np.ndarray]) -> None:
    """Keep `arrays` as the cache file `key` (written atomically; a cache that cannot be written is no error), and
    remove the least recently used beyond CACHE_FILES."""
    from wiredsl.files import cache_folder, prune_cache, write_atomic

    folder = cache_folder("meshes")
    if folder is None:
        return
    buf = io.BytesIO()
    np.savez(buf, **arrays)
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


# --------------------------------------------------------------------------- the features' cache

def features_key(data: bytes, kind: str, options: tuple) -> str:
    """The cache name of a mesh's features: its bytes, format, the options that shape them (scale, up, crease,
    placement, budgets...), wiredsl's version and the source of the code that finds them (engine/mesh.py)."""
    import wiredsl
    from wiredsl.engine import mesh as engine_mesh

    h = hashlib.sha256((_cache_key(data, kind) or hashlib.sha256(data).hexdigest()).encode())  # trimesh's version too
    h.update(f"\0{kind}\0{options!r}\0{wiredsl.__version__}\0{READER}\0".encode())
    h.update(Path(engine_mesh.__file__).read_bytes())
    return "f" + h.hexdigest()[:39]


_ARRAYS = ("lines", "poly_points", "poly_len", "ell", "sil", "corner_at", "corner_len", "corner_kind",
           "corner_ref", "face_points", "face_len", "vertices", "occluders", "contour", "counts", "read_as")


def load_features(key: str):
    """The cached MeshFeatures of `key`, or None (not cached, or a file that is not one)."""
    from wiredsl.engine.mesh import MeshFeatures

    a = _cache_read(key, _ARRAYS)
    if a is None:
        return None
    try:
        split = lambda x, n: np.split(x, np.cumsum(n)[:-1]) if len(n) else []  # noqa: E731
        f = MeshFeatures(lines=[(p[0], p[1]) for p in a["lines"]], polylines=split(a["poly_points"], a["poly_len"]),
                         ellipses=[{"centre": e[0:3], "normal": e[3:6], "axis": e[6:9], "a": float(e[9]),
                                    "b": float(e[10])} for e in a["ell"]],
                         silhouettes=[(int(x), int(y)) for x, y in a["sil"]],
                         faces=split(a["face_points"], a["face_len"]), vertices=a["vertices"],
                         occluders=a["occluders"], contour=a["contour"],
                         degenerate=int(a["counts"][0]), nonmanifold=int(a["counts"][1]),
                         triangles=int(a["counts"][2]), planar=float(a["read_as"][0]), scan=bool(a["read_as"][1]),
                         budget=None if a["read_as"][2] < 0 else int(a["read_as"][2]), cut=int(a["read_as"][3]))
        kinds = ("line", "polyline")
        refs = split(np.column_stack([a["corner_kind"], a["corner_ref"]]), a["corner_len"])
        f.corners = [(p, [(kinds[int(k)], int(j)) for k, j in r]) for p, r in zip(a["corner_at"], refs, strict=True)]
        return f
    except Exception:  # arrays that do not make features (a foreign file) only cost a fresh extraction
        return None


def save_features(key: str, f) -> None:
    """Keep a mesh's features."""
    cat = lambda xs, shape: np.concatenate(xs) if xs else np.zeros(shape)  # noqa: E731
    refs = [r for _, rs in f.corners for r in rs]
    arrays = {
        "lines": np.array([np.stack(x) for x in f.lines]).reshape(-1, 2, 3),
        "poly_points": cat(f.polylines, (0, 3)), "poly_len": np.array([len(p) for p in f.polylines], np.int64),
        "ell": np.array([[*e["centre"], *e["normal"], *e["axis"], e["a"], e["b"]] for e in f.ellipses]).reshape(-1, 11),
        "sil": np.array(f.silhouettes, np.int64).reshape(-1, 2),
        "corner_at": np.array([p for p, _ in f.corners]).reshape(-1, 3),
        "corner_len": np.array([len(r) for _, r in f.corners], np.int64),
        "corner_kind": np.array([k == "polyline" for k, _ in refs], np.int64),
        "corner_ref": np.array([j for _, j in refs], np.int64),
        "face_points": cat(f.faces, (0, 3)), "face_len": np.array([len(p) for p in f.faces], np.int64),
        "vertices": f.vertices, "occluders": np.asarray(f.occluders, np.int64).reshape(-1, 3),
        "contour": np.asarray(f.contour, bool),
        "counts": np.array([f.degenerate, f.nonmanifold, f.triangles], np.int64),
        "read_as": np.array([f.planar, f.scan, -1 if f.budget is None else f.budget, f.cut], np.float64)}
    _cache_write(key, arrays)
