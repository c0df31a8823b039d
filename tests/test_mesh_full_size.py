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
from hypothesis import given, settings
from hypothesis import strategies as st
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
    path = f"tests/meshes/{name}"
    data = open(path, "rb").read() if name == "lbracket.stl" else gzip.open(f"{path}.gz").read()
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


REAL_CAD = [("counter.stl", "stl", 1e-3), ("cycloidal.ply", "ply", 1.0), ("adis16480.stl", "stl", 1.0),
            ("lbracket.stl", "stl", 1e-3)]


@pytest.mark.parametrize("name, kind, scale", REAL_CAD)
def test_sharp_edges_of_real_cad_parts_are_covered(name, kind, scale):
    """At the defaults (SHORTEST, `budget auto`, the collinear merge), 99.9% of the length of trimesh's crease
    edges lies on a feature, to the merge's lateral tolerance: every real CAD part reads as one (no budget), the
    gear's 1,500 short creases of 30-45 deg across its flanks included."""
    mesh = _load(name, kind)
    size = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0))) * scale
    pts, weight, _ = _crease_points(mesh)
    f = M.features(mesh.vertices * scale, mesh.faces, CREASE)
    assert not f.scan and f.budget is None and f.cut == 0 and f.planar >= 2 * M.CAD_PLANAR
    fp, ftol = _feature_points(f, 1e-4 * size)
    d, i = cKDTree(fp).query(pts * scale, k=8)
    covered = (d <= ftol[i] + M.MERGE_LATERAL * size + 1e-9).any(axis=1)
    share = weight[covered].sum() / weight.sum()
    assert share >= 0.999, f"{name}: {100 * (1 - share):.3f}% of crease length on no feature"
    if name == "cycloidal.ply":  # the budget that suits a scan would have cut it (to 91.6% of its crease length)
        assert len(f.lines) + len(f.polylines) > 5 * M.BUDGET
        cut = M.features(mesh.vertices * scale, mesh.faces, CREASE, budget=M.BUDGET)
        assert cut.cut == len(f.lines) + len(f.polylines) - M.BUDGET


def gear(teeth: int, inner: float, seg: int, height: float) -> trimesh.Trimesh:
    """A spur gear of outer radius 1 (a prism): `teeth` teeth, each seg / 2 outline points at radius 1 and seg / 2
    at `inner`."""
    t = np.linspace(0, 2 * math.pi, teeth * seg, endpoint=False)
    r = np.where((np.arange(len(t)) // (seg // 2)) % 2 == 0, 1.0, inner)
    return prism(np.column_stack([r * np.cos(t), r * np.sin(t)]), height)


def local_height(mesh: trimesh.Trimesh, pick) -> np.ndarray:
    """Each vertex's smallest (pick np.minimum) or largest (np.maximum) height of its triangles (each triangle's
    smallest height: twice its area over its longest side)."""
    longest = np.linalg.norm(mesh.vertices[mesh.faces] - mesh.vertices[np.roll(mesh.faces, -1, axis=1)], axis=2)
    h = 2 * mesh.area_faces / longest.max(axis=1)
    out = np.full(len(mesh.vertices), np.inf if pick is np.minimum else 0.0)
    for j in range(3):
        pick.at(out, mesh.faces[:, j], h)
    return out


@settings(max_examples=40, deadline=None)
@given(shape=st.sampled_from(["box", "gear", "cylinder"]), a=st.floats(0.05, 2.0), b=st.floats(0.05, 2.0),
       c=st.floats(0.05, 2.0), n=st.integers(1, 3), teeth=st.integers(6, 40), seg=st.integers(1, 4),
       sections=st.integers(12, 200), seed=st.integers(0, 2**32 - 1))
def test_a_cad_part_with_noise_reads_as_a_scan_only_above_the_documented_noise(shape, a, b, c, n, teeth, seg,
                                                                               sections, seed):
    """Boxes (split n times), gears and cylinders, their vertices moved along their normals by seeded noise whose
    standard deviation at a vertex is a share of its triangles' heights: at NOISE_CAD (0.2%) of the smallest every
    one still reads as a CAD part, at NOISE_SCAN (10%) of the largest every one reads as a scan
    (docs/how-to/meshes-at-full-size.md)."""
    if shape == "box":
        box = trimesh.creation.box(extents=(a, b, c))
        V, F = box.vertices, box.faces
        for _ in range(n):
            V, F = trimesh.remesh.subdivide(V, F)
        mesh = trimesh.Trimesh(V, F)
    elif shape == "gear":
        mesh = gear(teeth, min(a, b) / 2.0 + 0.45, 2 * seg, c)
    else:
        mesh = trimesh.creation.cylinder(a / 2, c, sections=sections)
    assert not M.features(mesh.vertices, mesh.faces, CREASE).scan
    rng = np.random.default_rng(seed)
    unit = rng.normal(0, 1, len(mesh.vertices))
    for level, pick, scan in ((NOISE_CAD, np.minimum, False), (NOISE_SCAN, np.maximum, True)):
        sigma = level * local_height(mesh, pick)
        f = M.features(mesh.vertices + mesh.vertex_normals * (sigma * unit)[:, None], mesh.faces, CREASE)
        assert f.scan == scan, (level, f.planar)


NOISE_CAD, NOISE_SCAN = 0.002, 0.1  # of the smallest and the largest height of a vertex's triangles, as documented


def test_real_scans_read_as_scans():
    bunny = trimesh.load(io.BytesIO(gzip.open("tests/meshes/bunny.ply.gz").read()), file_type="ply", force="mesh")
    f = M.features(bunny.vertices, bunny.faces, CREASE)
    assert f.scan and f.planar < M.CAD_PLANAR / 5 and f.budget == M.BUDGET
    assert len(f.lines) + len(f.polylines) == M.BUDGET and f.cut > 1000
    assert M.features(bunny.vertices, bunny.faces, CREASE, budget=None).cut == 0  # no budget: none cut


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
    assert "read as a CAD part (42.9% of its edge length between coplanar triangles): every line and polyline kept" \
        in res.output  # the diagonals: 2 (sqrt(5) + sqrt(10) + sqrt(13)) of 24 + that


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
