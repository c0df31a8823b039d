"""How `mesh read` tells a CAD part from a scan on the meshes the tests hold: each mesh's planar share of its
interior edge length, what it is read as, and its features with a budget of 200 and at `budget auto` (with the
share of trimesh's crease length kept, where the two differ); then the smallest CAD share met (the parts above and
those of scenes/meshes/), the largest scan share, and the four CAD parts' shares moved 100 m from their origin and
rounded to float32 (binary STL's numbers).

    python docs/scripts/mesh_cad_or_scan.py

docs/how-to/meshes-at-full-size.md shows its output (docs/reproduce.py's block `mesh-cad-or-scan`).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

from test_mesh_features import _bunny, _scan  # noqa: E402
from test_mesh_full_size import CREASE, REAL_CAD, _crease_points, _feature_points, _load  # noqa: E402

from wiredsl.engine import mesh as M  # noqa: E402

ROWS = [("L bracket (`lbracket.stl`)", "lbracket.stl"), ("sensor housing (`adis16480.stl`)", "adis16480.stl"),
        ("counter (`counter.stl`)", "counter.stl"), ("cycloidal gear (`cycloidal.ply`)", "cycloidal.ply"),
        ("bunny (`bunny.ply`, a real scan)", "bunny"), ("114k scan made from the bunny", "scan")]


def share(p: float) -> str:
    return f"{100 * p:.1f}%" if p >= 0.1 else f"{100 * p:.2f}%"


def counts(f: M.MeshFeatures) -> str:
    return " / ".join(f"{len(x):,}" for x in (f.lines, f.polylines, f.corners, f.faces))


def crease_kept(mesh: trimesh.Trimesh, scale: float, f: M.MeshFeatures) -> float:
    """The share of trimesh's crease length on a feature found (as tests/test_mesh_full_size.py measures it)."""
    size = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0))) * scale
    pts, weight, _ = _crease_points(mesh)
    fp, ftol = _feature_points(f, 1e-4 * size)
    d, i = cKDTree(fp).query(pts * scale, k=8)
    covered = (d <= ftol[i] + M.MERGE_LATERAL * size + 1e-9).any(axis=1)
    return float(weight[covered].sum() / weight.sum())


def main() -> None:
    cad = {name: (kind, scale) for name, kind, scale in REAL_CAD}
    out = {"shares": {}}
    print("| mesh | triangles | planar | read as | lines / polylines / corners / faces, budget 200 "
          "| at `budget auto` |")
    print("| --- | ---: | ---: | --- | --- | --- |")
    for label, name in ROWS:
        if name in cad:
            kind, scale = cad[name]
            mesh = _load(name, kind)
        else:
            mesh, scale = (_bunny() if name == "bunny" else _scan()), 1.0
        V = mesh.vertices * scale
        auto = M.features(V, mesh.faces, CREASE)
        cut = M.features(V, mesh.faces, CREASE, budget=M.BUDGET)
        read = "scan" if auto.scan else "CAD part"
        out["shares"][name] = (auto.planar, auto.scan)
        if counts(auto) == counts(cut):
            budget, at_auto = counts(cut) + (f" ({cut.cut:,} cut)" if cut.cut else ""), "the same"
        else:
            budget = f"{counts(cut)} ({share(crease_kept(mesh, scale, cut))} of crease length)"
            at_auto = f"{counts(auto)} ({share(crease_kept(mesh, scale, auto)).replace('100.0%', '100%')})"
        print(f"| {label} | {len(mesh.faces):,} | {share(auto.planar)} | {read} | {budget} | {at_auto} |")
    for name in ("crate.obj", "can.stl", "cone.ply", "ball.glb"):
        mesh = trimesh.load(ROOT / "scenes/meshes" / name, force="mesh")
        f = M.features(mesh.vertices, mesh.faces, CREASE)
        out["shares"][f"scenes/meshes/{name}"] = (f.planar, f.scan)
    rounded = {}
    for name, (kind, scale) in cad.items():
        mesh = _load(name, kind)
        V = (mesh.vertices * scale + 100.0).astype(np.float32).astype(float)
        rounded[name] = M.features(V, mesh.faces, CREASE).planar
    out["rounded"] = rounded
    out["threshold"] = M.CAD_PLANAR
    print(json.dumps(out))


if __name__ == "__main__":
    main()
