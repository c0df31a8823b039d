"""Reading triangle meshes (OBJ, PLY, STL, glTF/GLB) for `mesh read`: vertices and triangles, checked.

trimesh parses the formats (the optional extra `mesh`, imported here only). Before it runs, the file is
read through the same gate as an included file (a regular file under MAX_MESH_BYTES: never a FIFO or a
device), and the triangle count the file declares (PLY's `element face`, binary STL's count, OBJ's `f`
lines) is checked against MAX_TRIANGLES, so a size bomb is refused before any array is allocated.
"""

from __future__ import annotations

import io
import re
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MAX_MESH_BYTES = 256 * 1024 * 1024  # a mesh file larger than this is refused
MAX_TRIANGLES = 2_000_000  # triangles a mesh may declare or hold
FORMATS = {".obj": "obj", ".ply": "ply", ".stl": "stl", ".gltf": "gltf", ".glb": "glb"}


class MeshFileError(ValueError):
    """A mesh file that cannot be used; the message says why (no path: the caller's diagnostic has it)."""


class MeshTooLarge(MeshFileError):
    """A mesh over MAX_TRIANGLES."""


@dataclass(frozen=True)
class RawMesh:
    """Vertices (n, 3) float64 in file units and triangles (m, 3) int64 indices into them."""

    vertices: np.ndarray
    triangles: np.ndarray


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
    try:
        import trimesh
    except ImportError as exc:  # pragma: no cover - the extra is part of `test`
        raise MeshFileError("reading meshes needs trimesh: pip install 'wiredsl[mesh]'") from exc
    try:
        loaded = trimesh.load(io.BytesIO(data), file_type=kind, process=False, force="mesh",
                              resolver=None if kind != "gltf" else _NoFiles())
    except MeshFileError:
        raise
    except Exception as exc:  # trimesh raises anything from ValueError to IndexError on a broken file
        raise MeshFileError(f"not a readable {kind.upper()} mesh ({type(exc).__name__}: {exc})"[:300]) from None
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=float).reshape(-1, 3)
    triangles = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
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


class _NoFiles:
    """A glTF's resolver that refuses its external buffers: a scene reads the one file it names."""

    def get(self, name: str) -> bytes:
        raise MeshFileError(f"the glTF refers to another file ({name!r}); use a .glb, which holds its buffers")

    __getitem__ = get

    def namespaced(self, namespace: str):
        return self
