"""When noise makes a CAD part read as a scan, and when it first adds false creases: a box (extents 1 x 0.8 x 0.6)
split four times and a 30-tooth spur gear (tests/test_mesh_full_size.py's `gear(30, 0.8, 4, 0.3)`), each vertex
moved along its normal by seeded Gaussian noise (seed 0) whose standard deviation is a share of the largest height
of the vertex's triangles, at each share of LEVELS: the planar share, scan or not, and the lines and polylines
found without a budget. A JSON line.

    python docs/scripts/mesh_noise.py
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

from test_mesh_full_size import CREASE, gear, local_height  # noqa: E402

from wiredsl.engine import mesh as M  # noqa: E402

LEVELS = (0.0, 0.002, 0.005, 0.01, 0.02, 0.03, 0.05, 0.1, 0.2)


def shapes() -> dict[str, trimesh.Trimesh]:
    box = trimesh.creation.box(extents=(1.0, 0.8, 0.6))
    V, F = box.vertices, box.faces
    for _ in range(4):
        V, F = trimesh.remesh.subdivide(V, F)
    return {"box": trimesh.Trimesh(V, F), "gear": gear(30, 0.8, 4, 0.3)}


def main() -> None:
    out = {}
    for name, mesh in shapes().items():
        unit = np.random.default_rng(0).normal(0, 1, len(mesh.vertices))
        height = local_height(mesh, np.maximum)
        rows = []
        for level in LEVELS:
            V = mesh.vertices + mesh.vertex_normals * (level * height * unit)[:, None]
            f = M.features(V, mesh.faces, CREASE, budget=None)
            rows.append({"level": level, "planar": f.planar, "scan": f.scan, "lines": len(f.lines) + len(f.polylines)})
        out[name] = {"triangles": len(mesh.faces), "rows": rows}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
