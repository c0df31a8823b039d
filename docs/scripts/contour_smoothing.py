"""What smoothing the normals does to a noisy sphere's contour (tests/test_mesh_features.py's sphere: an icosphere of
20,480 triangles, its vertices moved by seeded noise of 0.1 of an edge along the normals, seen from one eye): the
chains of contour edges, and how far the contour's vertices are from the analytic outline (the largest angle
between a vertex's radius and the right angle to its ray from the eye), with CONTOUR_SMOOTH passes and with the
triangles' own normals (0 passes). A JSON line.

    python docs/scripts/contour_smoothing.py
"""

from __future__ import annotations

import json
import math

import numpy as np
import trimesh

from wiredsl.engine import mesh as M


def main() -> None:
    r = 0.1
    ball = trimesh.creation.icosphere(subdivisions=5, radius=r)
    edge = ball.edges_unique_length.mean()
    rng = np.random.default_rng(5)
    V = ball.vertices + ball.vertex_normals * rng.normal(0, 0.1 * edge, len(ball.vertices))[:, None]
    eye = np.array([0.5, 0.1, 0.2])
    out, default = {"triangles": len(ball.faces)}, M.CONTOUR_SMOOTH
    for smooth in (default, 0):
        M.CONTOUR_SMOOTH = smooth
        f = M.features(V, ball.faces, math.radians(30))
        cont = M.Contours.of(f.vertices, f.occluders[f.contour])
        e, chain, _ = cont.chains(np.flatnonzero(cont.seen_from(eye)))
        X = cont.ends[e].reshape(-1, 3)  # the sphere's centre is the origin
        cos = np.abs((X * (eye - X)).sum(1)) / (np.linalg.norm(X, axis=1) * np.linalg.norm(eye - X, axis=1))
        out[str(smooth)] = {"chains": int(chain.max()) + 1, "off_deg": float(np.degrees(np.arcsin(cos.max())))}
    M.CONTOUR_SMOOTH = default
    print(json.dumps(out))


if __name__ == "__main__":
    main()
