"""Real CAD parts at full size (issue 25): rims that are really round (a filleted polygon stays a polyline with
its straight sides), sharp-edge coverage of real parts against trimesh's own crease edges, and the cheap
collinear-point removal."""

from __future__ import annotations

import gzip
import io
import math

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from wiredsl.engine import mesh as M

CREASE = math.radians(30)


def rounded_polygon(n_sides: int, R: float, rho: float, segs: int, stretch: float = 1.0) -> np.ndarray:
    """Outline (k, 2) of a regular n-gon of circumradius R whose corners are filleted (radius rho, segs segments),
    stretched along x."""
    pts = []
    for i in range(n_sides):
        th = 2 * math.pi * i / n_sides
        centre = (R - rho / math.cos(math.pi / n_sides)) * np.array([math.cos(th), math.sin(th)])
        for j in range(segs + 1):
            a = th - math.pi / n_sides + (2 * math.pi / n_sides) * j / segs
            pts.append(centre + rho * np.array([math.cos(a), math.sin(a)]))
    P = np.array(pts)
    P[:, 0] *= stretch
    return P


def prism(outline: np.ndarray, height: float) -> trimesh.Trimesh:
    """A closed prism over a convex outline (k, 2): two fan-triangulated lids and a side of quads."""
    k = len(outline)
    V = np.vstack([np.column_stack([outline, np.zeros(k)]), np.column_stack([outline, np.full(k, height)]),
                   [[*outline.mean(0), 0.0], [*outline.mean(0), height]]])
    i, j = np.arange(k), (np.arange(k) + 1) % k
    F = np.vstack([np.column_stack([i, j, j + k]), np.column_stack([i, j + k, i + k]),
                   np.column_stack([np.full(k, 2 * k), j, i]), np.column_stack([np.full(k, 2 * k + 1), i + k, j + k])])
    return trimesh.Trimesh(V, F, process=False)


def _on_polylines(points: np.ndarray, found: M.MeshFeatures) -> np.ndarray:
    """Distance of each point to the nearest line or polyline segment found."""
    segs = [np.array([a, b]) for a, b in found.lines] + list(found.polylines)
    A = np.vstack([s[:-1] for s in segs])
    B = np.vstack([s[1:] for s in segs])
    D = B - A
    u = np.clip(((points[:, None] - A[None]) * D[None]).sum(-1) / np.maximum((D * D).sum(-1), 1e-300), 0, 1)
    return np.linalg.norm(points[:, None] - (A[None] + u[..., None] * D[None]), axis=2).min(axis=1)


@pytest.mark.parametrize("n_sides, rho, stretch", [(6, 0.5, 1.0), (6, 0.3, 1.0), (4, 0.5, 1.6), (4, 0.3, 1.0)])
def test_a_polygon_with_filleted_corners_stays_a_polyline_with_its_straight_sides(n_sides, rho, stretch):
    outline = rounded_polygon(n_sides, 10.0, rho, 3, stretch) * 1e-3  # a 20 mm pocket, 3-segment fillets
    r = np.linalg.norm(outline - outline.mean(0), axis=1)
    if stretch == 1.0:  # the trap: every vertex is within RIM_TOL of one circle, the sides are not
        assert (r.max() - r.min()) / r.mean() < M.RIM_TOL
    mesh = prism(outline, 5e-3)
    f = M.features(mesh.vertices, mesh.faces, CREASE)
    assert not f.ellipses and not f.silhouettes
    # every edge of both outlines (ends and middles) lies on a line or polyline found, to the collinear merge's
    # lateral tolerance (a fillet's vertices may be merged into a chord): no sharp edge dropped
    merge = M.MERGE_LATERAL * float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
    for z in (0.0, 5e-3):
        P = np.column_stack([outline, np.full(len(outline), z)])
        mids = (P + np.roll(P, -1, axis=0)) / 2
        assert _on_polylines(np.vstack([P, mids]), f).max() <= merge + 1e-12
    # each straight side (the outline's long edges) lies on one segment of a line or polyline found (to the
    # merge's tolerance: a segment may reach on into the fillet)
    segs = [np.array([a, b]) for P in [np.array(x) for x in f.lines] + list(f.polylines)
            for a, b in zip(P[:-1], P[1:], strict=True)]
    side = np.linalg.norm(np.roll(outline, -1, axis=0) - outline, axis=1)
    for z in (0.0, 5e-3):
        P = np.column_stack([outline, np.full(len(outline), z)])
        for i in np.flatnonzero(side > 2 * rho * 1e-3):
            ab = np.array([P[i], P[(i + 1) % len(P)]])
            assert any(_on_polylines(ab, M.MeshFeatures(polylines=[s])).max() <= merge + 1e-12 for s in segs)


@pytest.mark.parametrize("sections, radius", [(16, 0.02), (40, 0.25), (256, 0.5)])
def test_a_fine_regular_polygon_is_still_a_rim(sections, radius):
    can = trimesh.creation.cylinder(radius=radius, height=0.1, sections=sections)
    f = M.features(can.vertices, can.faces, CREASE)
    assert len(f.ellipses) == 2 and f.silhouettes == [(0, 1)]
    assert f.ellipses[0]["a"] == pytest.approx(radius, rel=1e-9)


def test_a_coarse_large_polygon_is_not_a_rim_in_absolute_length():
    # a 16-gon of radius 0.2 m: its sides are 3.8 mm (1.9% of the radius) inside the circle: over RIM_EDGE_ABS
    can = trimesh.creation.cylinder(radius=0.2, height=0.1, sections=16)
    f = M.features(can.vertices, can.faces, CREASE)
    assert not f.ellipses
    assert len(M.features(can.vertices * 0.05, can.faces, CREASE).ellipses) == 2  # 1 cm: a rim


def _load(name: str, kind: str) -> trimesh.Trimesh:
    data = gzip.open(f"tests/meshes/{name}.gz").read()
    return trimesh.load(io.BytesIO(data), file_type=kind, force="mesh")  # processed: repeated vertices merged


def _crease_points(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Trimesh's sharp edges (adjacent faces' normals over CREASE apart, boundary and non-manifold edges) as
    points along them (each edge's 1/4, 1/2, 3/4) and the length each point stands for."""
    sharp = mesh.face_adjacency_angles > CREASE
    adj = mesh.face_adjacency_edges[sharp]
    e = np.sort(mesh.edges, axis=1)
    uniq, count = np.unique(e, axis=0, return_counts=True)
    E = np.vstack([adj, uniq[count != 2]])
    angle = np.concatenate([mesh.face_adjacency_angles[sharp], np.full((count != 2).sum(), math.pi)])
    A, B = mesh.vertices[E[:, 0]], mesh.vertices[E[:, 1]]
    pts = np.vstack([A + s * (B - A) for s in (0.25, 0.5, 0.75)])
    return pts, np.tile(np.linalg.norm(B - A, axis=1) / 3, 3), np.tile(angle, 3)


def _feature_points(f: M.MeshFeatures, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every `step` or closer along every feature found, and the distance within which each covers."""
    pts, tol = [], []
    for P in [np.array([a, b]) for a, b in f.lines] + list(f.polylines):
        for a, b in zip(P[:-1], P[1:], strict=True):
            n = max(2, int(np.linalg.norm(b - a) / step) + 2)
            pts.append(a + np.linspace(0, 1, n)[:, None] * (b - a))
            tol.append(np.full(n, step))
    for e in f.ellipses:
        if e["a"] <= M.APEX_RADIUS:
            continue
        v = np.cross(e["normal"], e["axis"])
        n = max(64, int(2 * math.pi * e["a"] / step) + 2)
        t = np.linspace(0, 2 * math.pi, n)
        pts.append(e["centre"] + e["a"] * np.cos(t)[:, None] * e["axis"] + e["b"] * np.sin(t)[:, None] * v)
        tol.append(np.full(n, step + min(M.RIM_EDGE * e["a"], M.RIM_EDGE_ABS)))  # a rim's chords are inside it
    return np.vstack(pts), np.concatenate(tol)


@pytest.mark.parametrize("name, kind", [("counter.stl", "stl"), ("cycloidal.ply", "ply"), ("adis16480.stl", "stl")])
def test_sharp_edges_of_real_cad_parts_are_covered(name, kind):
    """At the defaults (SHORTEST, BUDGET, the collinear merge), 99.9% of the length of trimesh's crease edges
    lies on a feature, to the merge's lateral tolerance. The cycloidal gear's flanks are tessellated with
    creases of 30-45 deg (1,500 short lines across its thickness): the budget keeps its real edges (90 deg,
    the outlines of its faces) and drops those, so there the share is taken of creases sharper than 85 deg
    (99.91%; 99.83% of those over 60 deg, 91.6% of all);
    with no budget and no shortest length, all of its crease length is covered."""
    mesh = _load(name, kind)
    scale = 1e-3 if name == "counter.stl" else 1.0
    size = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0))) * scale
    pts, weight, angle = _crease_points(mesh)
    pts = pts * scale
    step = 1e-4 * size
    options = [({}, 0.0)] + ([({"shortest": 0.0, "budget": 10**6}, 0.0), ({}, math.radians(85))]
                              if name == "cycloidal.ply" else [])
    for opts, sharper in options[1:] if name == "cycloidal.ply" else options:
        f = M.features(mesh.vertices * scale, mesh.faces, CREASE, **opts)
        fp, ftol = _feature_points(f, step)
        d, i = cKDTree(fp).query(pts, k=8)
        covered = (d <= ftol[i] + M.MERGE_LATERAL * size + 1e-9).any(axis=1)
        w = weight * (angle >= sharper)
        share = w[covered].sum() / w.sum()
        assert share >= 0.999, f"{name} {opts} {sharper}: {100 * (1 - share):.3f}% of crease length on no feature"
    if name != "cycloidal.ply":
        assert len(f.lines) + len(f.polylines) < M.BUDGET  # the budget cut nothing of these parts


def test_collinear_points_are_dropped_in_few_rounds_and_never_off_the_line():
    rng = np.random.default_rng(25)
    t = np.sort(rng.uniform(0, 1, 5000))
    line = np.column_stack([t, 2 * t, -t])
    kept = M._drop_collinear(line, closed=False)
    assert len(kept) == 2 and np.array_equal(kept[0], line[0]) and np.array_equal(kept[-1], line[-1])
    square = np.array([[0, 0, 0], [0.5, 0, 0], [1, 0, 0], [1, 0.5, 0], [1, 1, 0], [0.5, 1, 0], [0, 1, 0], [0, 0.5, 0]])
    assert len(M._drop_collinear(square.astype(float), closed=True)) == 4
    wiggle = np.column_stack([t, np.sin(20 * t), np.zeros_like(t)])  # a curve: every point kept is on it
    kept = M._drop_collinear(wiggle, closed=False)
    assert 10 < len(kept) < len(t)


# --------------------------------------------------------------------------- units, placement, cache


def _compile(tmp_path, line: str, extra: str = ""):
    from wiredsl.language.compile import compile_file

    path = tmp_path / "s.wd"
    path.write_text(f"wiredsl 1\nmodel m {{\n  {line}\n}}\n{extra}")
    return compile_file(path)


def _ends(scene) -> np.ndarray:
    return np.array([p for ln in scene.model("m").lines for p in (ln.start, ln.end)])


@pytest.mark.parametrize("clause, metres", [("scale 1in", 0.0254), ("units in", 0.0254), ("scale 1mm", 1e-3),
                                            ("units ft", 0.3048), ("scale 0.001", 1e-3), ("scale 2cm", 0.02)])
def test_scale_takes_a_unit(tmp_path, monkeypatch, clause, metres):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    trimesh.creation.box(extents=(1.0, 2.0, 3.0)).export(tmp_path / "b.stl")
    scene = _compile(tmp_path, f'mesh read "b.stl" {clause}')[0]
    assert np.allclose(np.ptp(_ends(scene), axis=0), np.array([1.0, 2.0, 3.0]) * metres)


def test_scale_and_units_together_are_an_error(tmp_path):
    from wiredsl.diagnostics import WiredslError

    trimesh.creation.box(extents=(1.0, 2.0, 3.0)).export(tmp_path / "b.stl")
    with pytest.raises(WiredslError) as err:
        _compile(tmp_path, 'mesh read "b.stl" scale 1in units mm')
    assert err.value.diagnostics[0].code == "E103" and "once" in err.value.diagnostics[0].message


@pytest.mark.parametrize("origin, centre", [("centre", (0, 0, 0)), ("base", (0, 0, 0.15)), ("file", (0.5, 0.6, 0.95))])
def test_origin_places_the_part_by_its_centre_or_base(tmp_path, monkeypatch, origin, centre):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    box = trimesh.creation.box(extents=(100.0, 200.0, 300.0))
    box.apply_translation((500, 600, 950))  # mm: the file's origin is 0.8 m below the part
    box.export(tmp_path / "b.stl")
    scene, warnings, program = _compile(tmp_path, f'mesh read "b.stl" units mm origin {origin}')
    ends = _ends(scene)
    assert np.allclose((ends.min(0) + ends.max(0)) / 2, centre)
    codes = [w.code for w in warnings]
    assert codes == (["W127"] if origin == "file" else [])
    if origin == "file":
        assert "its origin is 1.05 m outside the part" in warnings[0].message  # |(0.45, 0.5, 0.8)| to the box
    (span, text), = program.mesh_reports
    assert "100 mm x 200 mm x 300 mm" in text and span.line == 3


def test_check_reports_each_mesh_size_and_bounds(tmp_path, monkeypatch):
    from click.testing import CliRunner

    from wiredsl.cli import main

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    trimesh.creation.box(extents=(1.0, 2.0, 3.0)).export(tmp_path / "b.stl")
    _compile(tmp_path, 'mesh read "b.stl" units in origin base')
    res = CliRunner().invoke(main, ["check", str(tmp_path / "s.wd")])
    assert res.exit_code == 0
    assert "note: mesh b.stl: 25.4 mm x 50.8 mm x 76.2 mm, from (-0.0127, -0.0254, 0) to (0.0127, 0.0254, 0.0762)" \
        in res.output


def test_a_second_build_reads_the_features_from_the_cache(tmp_path, monkeypatch):
    from wiredsl.engine import mesh as engine_mesh
    from wiredsl.io import mesh as io_mesh

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    (tmp_path / "c.stl").write_bytes(gzip.open("tests/meshes/adis16480.stl.gz").read())
    first = _compile(tmp_path, 'mesh read "c.stl" origin centre')[0]

    def no_mesh_work(*args, **kwargs):
        raise AssertionError("mesh work on a cached mesh")

    monkeypatch.setattr(engine_mesh, "features", no_mesh_work)
    monkeypatch.setattr(io_mesh, "read_mesh", no_mesh_work)
    again = _compile(tmp_path, 'mesh read "c.stl" origin centre')[0]
    assert again.model("m").model_dump() == first.model("m").model_dump()
    with pytest.raises(AssertionError, match="mesh work"):  # other options: other features, read afresh
        _compile(tmp_path, 'mesh read "c.stl" origin base')


def test_a_ply_of_triangle_strips_says_what_it_holds(tmp_path):
    from click.testing import CliRunner

    from wiredsl.cli import main

    (tmp_path / "strips.ply").write_bytes(open("tests/meshes/bad_strips.ply", "rb").read())
    (tmp_path / "s.wd").write_text('wiredsl 1\nmodel m {\n  mesh read "strips.ply"\n}\n')
    res = CliRunner().invoke(main, ["check", str(tmp_path / "s.wd")])
    assert res.exit_code == 1
    assert "error[E125]" in res.output and "1 tristrips (triangle strips: convert them to faces" in res.output
