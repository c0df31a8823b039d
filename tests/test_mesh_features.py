"""Features a recognition module can use (issue 25, item 5): a scan's features bounded at the defaults (the real
bunny of tests/meshes/ and a 114k-triangle scan made from it), the budget honoured and ranked, nearly collinear
crease edges merged within their documented tolerance, and contours chained into polylines per view."""

from __future__ import annotations

import gzip
import io
import json
import math

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner

from wiredsl.cli import main
from wiredsl.engine import mesh as M

CREASE = math.radians(30)
FEW_HUNDRED = 500  # lines, polylines, corners and faces of a model, all told


def _bunny() -> trimesh.Trimesh:
    data = gzip.open("tests/meshes/bunny.ply.gz").read()
    return trimesh.load(io.BytesIO(data), file_type="ply", force="mesh", process=False)


def _scan() -> trimesh.Trimesh:
    """A 114k-triangle scan: the bunny split to finer triangles and its vertices moved along their
    normals by noise of 0.1 of the mean edge (seeded): a real scan's swarm of small creases, at full size."""
    m = trimesh.Trimesh(*trimesh.remesh.subdivide(_bunny().vertices, _bunny().faces))
    v, f = trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=np.percentile(m.edges_unique_length, 75))
    s = trimesh.Trimesh(v, f)
    rng = np.random.default_rng(25)
    s.vertices += s.vertex_normals * rng.normal(0, 0.1 * s.edges_unique_length.mean(), len(s.vertices))[:, None]
    return s


@pytest.fixture(scope="module")
def scan() -> trimesh.Trimesh:
    return _scan()


def _count(f: M.MeshFeatures) -> int:
    return len(f.lines) + len(f.polylines) + len(f.corners) + len(f.faces) + len(f.ellipses) + len(f.silhouettes)


def test_a_real_scan_and_a_100k_scan_give_a_few_hundred_features_at_the_defaults(scan):
    assert len(scan.faces) > 100_000
    for m in (_bunny(), scan):
        every = M.features(m.vertices, m.faces, CREASE, 0.0, 10**9)
        f = M.features(m.vertices, m.faces, CREASE)
        assert _count(every) > 1_000  # what the crease alone gives: a swarm
        assert len(f.lines) + len(f.polylines) <= M.BUDGET
        assert _count(f) <= FEW_HUNDRED, _count(f)
        # every face is a planar region at least SHORTEST of the diagonal across, and no lone noisy triangle
        size = float(np.linalg.norm(np.ptp(m.vertices, axis=0)))
        assert all(np.ptp(P, axis=0).max() >= M.SHORTEST * size for P in f.faces)


def test_corners_are_only_where_kept_features_meet():
    f = M.features(_bunny().vertices, _bunny().faces, CREASE)
    ends = [np.stack(x) for x in f.lines] + list(f.polylines)
    for at, refs in f.corners:
        assert len(refs) >= 2
        for kind, j in refs:
            P = np.stack(f.lines[j]) if kind == "line" else f.polylines[j]
            assert np.array_equal(P[0], at) or np.array_equal(P[-1], at)
    assert len(f.corners) <= 2 * len(ends)


def test_the_budget_keeps_the_longest_and_sharpest():
    m = _bunny()
    every = M.features(m.vertices, m.faces, CREASE, budget=10**9)
    pieces = {tuple(np.round(np.concatenate([p[0], p[-1]]), 12)) for p in
              [np.stack(x) for x in every.lines] + list(every.polylines)}
    previous = set()
    for budget in (0, 10, 40, 160):
        f = M.features(m.vertices, m.faces, CREASE, budget=budget)
        kept = {tuple(np.round(np.concatenate([p[0], p[-1]]), 12)) for p in
                [np.stack(x) for x in f.lines] + list(f.polylines)}
        assert len(f.lines) + len(f.polylines) == budget  # honoured, and there are more to choose from
        assert kept <= pieces and previous <= kept  # the same pieces, a larger budget keeps more of them
        previous = kept
    # the kept ones rank first: longer than the typical piece (the sharpest, non-manifold and boundary edges
    # rank high too)
    length = lambda P: float(np.linalg.norm(np.diff(P, axis=0), axis=1).sum())  # noqa: E731
    f = M.features(m.vertices, m.faces, CREASE, budget=40)
    kept_len = [length(np.stack(x)) for x in f.lines] + [length(P) for P in f.polylines]
    all_len = [length(np.stack(x)) for x in every.lines] + [length(P) for P in every.polylines]
    assert np.median(kept_len) > 1.3 * np.median(all_len)


def test_shortest_drops_short_features():
    m = _bunny()
    size = float(np.linalg.norm(np.ptp(m.vertices, axis=0)))
    f = M.features(m.vertices, m.faces, CREASE, shortest=0.03 * size, budget=10**9)
    for P in [np.stack(x) for x in f.lines] + list(f.polylines):
        # a piece's length along the mesh edges is at least `shortest`; its merged chords are at most as long
        assert np.linalg.norm(np.diff(P, axis=0), axis=1).sum() >= 0.03 * size * math.cos(M.MERGE_ANGLE) - 1e-12
    assert len(f.lines) + len(f.polylines) < len(M.features(m.vertices, m.faces, CREASE, 0.0, 10**9).lines)


@pytest.mark.parametrize("seed", range(6))
def test_the_collinear_merge_keeps_every_dropped_point_within_its_tolerance(seed):
    rng = np.random.default_rng(seed)
    n = 200
    t = np.sort(rng.uniform(0, 1, n))
    bend = rng.uniform(0, 0.3)  # from nearly straight to an arc
    P = np.column_stack([t, bend * np.sin(math.pi * t) + rng.normal(0, 2e-4, n), rng.normal(0, 2e-4, n)])
    lateral = 1e-3
    kept = M._simplify(P, lateral)
    assert kept[0] == 0 and kept[-1] == n - 1 and (np.diff(kept) > 0).all()
    for a, b in zip(kept[:-1], kept[1:], strict=True):
        A, B = P[a], P[b]
        L = np.linalg.norm(B - A)
        u = (B - A) / L
        for X in P[a + 1:b]:
            along = (X - A) @ u
            off = np.linalg.norm(X - A - along * u)
            assert 0 <= along <= L
            assert off <= min(lateral, math.tan(M.MERGE_ANGLE) * L) + 1e-15
    if bend == 0:
        assert len(kept) == 2


def test_a_slightly_wavy_crease_is_one_line():
    """A box whose top edge wanders by 0.01% of its size (a scan of a straight edge): one line, not a chain."""
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    box = box.subdivide().subdivide().subdivide()
    rng = np.random.default_rng(1)
    V = box.vertices.copy()
    V += rng.normal(0, 1e-4, V.shape) * (np.abs(V) < 0.5 - 1e-9)  # inner points of faces and edges only
    f = M.features(V, box.faces, CREASE)
    assert len(f.lines) == 12 and not f.polylines
    assert len(f.corners) == 8


def _build(tmp_path, mesh: trimesh.Trimesh, extra: str = "") -> list[dict]:
    mesh.export(tmp_path / "s.ply")
    (tmp_path / "s.wd").write_text(f"""wiredsl 1
scene s
model obj {{
  mesh read "s.ply" up y origin base {extra}
}}
place obj as obj1 at (0.6m, 0, 0)
camera eye {{
  focal 4mm
  pixel 0.008mm
  size (640px, 480px)
}}
rig pair {{
  left eye at (0, 0.05m, 0.1m) looking (1, 0, 0)
  right eye at (0, -0.05m, 0.1m) looking (1, 0, 0)
}}
path p {{
  straight from (0, 0) to (0.2m, 0) step 0.2m
}}
""")
    # the view-point lists, not exact visibility (build's default for meshes): every contour edge is kept
    r = CliRunner().invoke(main, ["build", str(tmp_path / "s.wd"), "-o", "-", "--no-effects", "--seed", "1",
                                  "--visibility", "scene"])
    assert r.exit_code == 0, r.output
    return json.loads(r.stdout)["poses"]


def test_contours_are_polylines_chained_end_to_end(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    bunny = _bunny()
    poses = _build(tmp_path, bunny)
    from wiredsl.language.compile import compile_file

    scene = compile_file(tmp_path / "s.wd")[0]
    surface = scene.model("obj").surfaces[0]
    whole = 0
    for pose in poses:
        view = pose["left"]
        records = [r for r in view["lines"] + view["polylines"] if r.get("contour")]
        edges = sum(len(r["points"]) - 1 for r in records)
        assert records and all(r["source"] == "obj1.surface" for r in records)
        assert len(records) < edges / 3  # chains, not one record an edge
        # each polyline's points are its edges' ends, each edge starting where the one before ended: its
        # points are distinct but for a closed loop's last, and consecutive ones are a mesh edge apart
        for r in records:
            P = np.array(r["points"])
            assert np.isfinite(P).all() and len(P) >= 2
        # the records' edges are all the contour edges Contours finds for this camera when none is cut: the
        # chaining loses none
        if not any(r["clipped"] for r in records):
            V = np.array(surface.vertices)
            F = np.array(surface.triangles)[surface.contour]
            cont = M.Contours.of(V, F)
            eye = _eye(scene, pose)
            assert edges == int(cont.seen_from(eye).sum())
            whole += 1
    assert whole == len(poses) == 2  # the bunny is whole in every view


def _eye(scene, pose) -> np.ndarray:
    """The left camera's centre in the model's frame (the model is placed at (0.6 m, 0, 0), unturned)."""
    x, y = pose["pose"][:2] if "pose" in pose else (0.0, 0.0)
    return np.array([x, y + 0.05, 0.1]) - np.array([0.6, 0.0, 0.0])


def test_shortest_and_budget_are_options_of_mesh_read_and_keys_of_the_cache(tmp_path, monkeypatch):
    from wiredsl.language.compile import compile_file

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    _bunny().export(tmp_path / "b.ply")
    counts = []
    for extra in ("", "budget 7", "budget 7 shortest 1cm", "", "budget 0", "budget auto", "budget 100000"):
        (tmp_path / "s.wd").write_text(f'wiredsl 1\nmodel m {{\n  mesh read "b.ply" {extra}\n}}\n')
        m = compile_file(tmp_path / "s.wd")[0].model("m")
        counts.append((len(m.lines) + len(m.polylines), len(m.corners)))
    assert counts[0] == counts[3] == counts[5] and counts[0][0] == M.BUDGET  # a scan: auto is BUDGET
    assert counts[1][0] == 7 and counts[2][0] <= 7 and counts[4] == (0, 0) and counts[6][0] > 1000
    r = CliRunner().invoke(main, ["check", str(tmp_path / "s.wd")])  # what was read, and what the budget cut
    assert "read as a scan (1.06% of its edge length between coplanar triangles): budget 100000 cut nothing" \
        in r.output
    (tmp_path / "s.wd").write_text('wiredsl 1\nmodel m {\n  mesh read "b.ply"\n}\n')
    r = CliRunner().invoke(main, ["check", str(tmp_path / "s.wd")])
    assert "read as a scan (1.06% of its edge length between coplanar triangles): budget 200 left out 1,028 " \
           "lines and polylines" in r.output
    for bad, code in (("budget -1", "E110"), ("budget all", "E106"), ("budget 2.5", "E106")):
        (tmp_path / "s.wd").write_text(f'wiredsl 1\nmodel m {{\n  mesh read "b.ply" {bad}\n}}\n')
        r = CliRunner().invoke(main, ["check", str(tmp_path / "s.wd")])
        assert r.exit_code == 1 and code in r.output and "Traceback" not in r.output, r.output


def test_a_changed_default_is_a_new_cache_key(tmp_path, monkeypatch):
    """The defaults of `budget auto` (BUDGET, PLANAR_EDGE, CAD_PLANAR) live in engine/mesh.py, whose source is part
    of the features' cache key: changing one reads the mesh afresh."""
    from wiredsl.io import mesh as io_mesh

    data, options = b"solid x\nendsolid x\n", (1.0, "z", CREASE, "file", None, "auto")
    key = io_mesh.features_key(data, "stl", options)
    source = open(M.__file__).read()
    for name in ("BUDGET", "PLANAR_EDGE", "CAD_PLANAR"):
        line = next(x for x in source.splitlines() if x.startswith(f"{name} = "))
        changed = tmp_path / f"{name}.py"
        changed.write_text(source.replace(line, line.replace(" = ", " = 2 * ", 1)))
        monkeypatch.setattr(M, "__file__", str(changed))
        assert io_mesh.features_key(data, "stl", options) != key
    monkeypatch.setattr(M, "__file__", str(tmp_path / "BUDGET.py"))
    monkeypatch.undo()
    assert io_mesh.features_key(data, "stl", options) == key
    assert io_mesh.features_key(data, "stl", (*options[:-1], M.BUDGET)) != key  # auto is not the number


def test_a_noisy_sphere_has_a_few_contour_chains_on_its_analytic_outline(monkeypatch):
    """A noisy icosphere (20,480 triangles, vertices moved by 0.1 of an edge along the normals): the contour
    from smoothed normals lies on the analytic sphere's tangent cone from the eye (the radius at each contour
    vertex at right angles to the ray from the eye) to within three edges' angular width, in a few chains;
    from the triangles' own normals (CONTOUR_SMOOTH 0) it is hundreds of bits, far off the outline."""
    r = 0.1
    ball = trimesh.creation.icosphere(subdivisions=5, radius=r)
    edge = ball.edges_unique_length.mean()
    rng = np.random.default_rng(5)
    V = ball.vertices + ball.vertex_normals * rng.normal(0, 0.1 * edge, len(ball.vertices))[:, None]
    eye = np.array([0.5, 0.1, 0.2])
    found, default = {}, M.CONTOUR_SMOOTH
    for smooth in (default, 0):
        monkeypatch.setattr(M, "CONTOUR_SMOOTH", smooth)
        f = M.features(V, ball.faces, CREASE)
        cont = M.Contours.of(f.vertices, f.occluders[f.contour])
        e, chain, _ = cont.chains(np.flatnonzero(cont.seen_from(eye)))
        X = cont.ends[e].reshape(-1, 3)  # the sphere's centre is the origin
        cos = np.abs((X * (eye - X)).sum(1)) / (np.linalg.norm(X, axis=1) * np.linalg.norm(eye - X, axis=1))
        found[smooth] = (int(chain.max()) + 1, float(cos.max()))
    chains, off = found[default]
    assert chains <= 30 and off <= 3 * edge / r, found
    assert found[0][0] > 10 * chains and found[0][1] > 3 * edge / r  # what the smoothing is for
