"""What `mesh read "lbracket.stl" units mm` finds in the real L bracket of tests/meshes/ at the defaults (a JSON
line: its triangles, lines, polylines, corners, rims with their radii in mm, silhouettes, faces, occluding
triangles).

    python docs/scripts/lbracket_features.py
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import trimesh

from wiredsl.engine import mesh as M

ROOT = Path(__file__).resolve().parents[2]


def main() -> None:
    mesh = trimesh.load(ROOT / "tests/meshes/lbracket.stl", force="mesh")
    f = M.features(mesh.vertices * 1e-3, mesh.faces, math.radians(30))
    radii = sorted({round(1000 * e["a"], 1) for e in f.ellipses})
    print(json.dumps({"triangles": len(mesh.faces), "lines": len(f.lines), "polylines": len(f.polylines),
                      "corners": len(f.corners), "rims": len(f.ellipses), "radii_mm": radii,
                      "silhouettes": len(f.silhouettes), "faces": len(f.faces), "occluders": len(f.occluders)}))


if __name__ == "__main__":
    main()
