"""`mesh read`: a triangle mesh as features (cube, can, cone, sphere's contours, a real CAD part), mesh faces
as occluders against a brute-force ray caster, and bad mesh files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner

from wiredsl.cli import main
from wiredsl.diagnostics import WiredslError
from wiredsl.engine.mesh import RIM_TOL, Contours, features
from wiredsl.engine.occlusion import CHUNK, Occluders
from wiredsl.engine.world import build_world
from wiredsl.io.mesh import read_mesh
from wiredsl.language.compile import compile_file

CREASE = math.radians(30)


def test_a_triangulated_cube_gives_12_edges_8_corners_and_6_faces():
    cube = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    for mesh in (cube, cube.subdivide().subdivide()):  # split edges stay one line; diagonals never count
        f = features(mesh.vertices, mesh.faces, CREASE)
        assert (len(f.lines), len(f.polylines), len(f.corners), len(f.faces)) == (12, 0, 8, 6)
        assert not f.ellipses and not len(f.occluders)
        lengths = sorted(round(float(np.linalg.norm(b - a)), 9) for a, b in f.lines)
        assert lengths == [1.0] * 4 + [2.0] * 4 + [3.0] * 4
        for at, joins in f.corners:
            assert np.allclose(np.abs(at), (0.5, 1.0, 1.5)) and len(joins) == 3
            for kind, j in joins:  # each joined line ends at the corner
                assert kind == "line" and min(np.linalg.norm(p - at) for p in f.lines[j]) < 1e-12


def test_a_closed_can_gives_two_rims_a_silhouette_and_no_straight_edges():
    can = trimesh.creation.cylinder(radius=0.25, height=1.0, sections=40)
    f = features(can.vertices, can.faces, CREASE)
    assert not f.lines and not f.polylines and not f.corners
    assert len(f.ellipses) == 2 and f.silhouettes == [(0, 1)]
    for e in f.ellipses:
        assert e["a"] == pytest.approx(0.25, rel=1e-9) and e["b"] == pytest.approx(0.25, rel=1e-9)
        assert abs(e["normal"][2]) == pytest.approx(1.0) and abs(e["centre"][2]) == pytest.approx(0.5)
    assert len(f.faces) == 2  # the lids: convex 40-gons


def test_a_cone_gives_its_base_rim_and_a_silhouette_to_its_apex():
    cone = trimesh.creation.cone(radius=0.3, height=0.8, sections=36)
    f = features(cone.vertices, cone.faces, CREASE)
    assert not f.lines and not f.corners and len(f.silhouettes) == 1
    base, apex = (f.ellipses[i] for i in f.silhouettes[0])
    assert base["a"] == pytest.approx(0.3, rel=1e-9) and base["centre"][2] == pytest.approx(0.0, abs=1e-12)
    assert apex["a"] < 1e-5 and apex["centre"][2] == pytest.approx(0.8)


def test_a_coarse_polygon_prism_is_not_a_can():
    octagon = trimesh.creation.cylinder(radius=0.25, height=1.0, sections=8)  # fewer vertices than a rim needs
    f = features(octagon.vertices, octagon.faces, CREASE)
    assert not f.ellipses and len(f.lines) == 24 and len(f.corners) == 16


def test_sphere_contours_against_the_analytic_outline():
    """Every contour vertex seen from the eye lies on the analytic sphere's tangent cone (whose image is the
    outline conic), within the tessellation's sagitta, and the contour goes all the way round."""
    r, c = 0.5, np.array([0.2, -0.1, 0.3])
    ball = trimesh.creation.icosphere(subdivisions=4, radius=r)
    V = ball.vertices + c
    f = features(V, ball.faces, CREASE)
    assert f.contour.all() and len(f.occluders) == len(ball.faces)
    cont = Contours.of(f.vertices, f.occluders)
    edge = np.linalg.norm(np.diff(V[ball.edges_unique], axis=1), axis=2).max()
    for eye in ([3.0, 0.0, 0.0], [0.5, 2.0, 1.5], [-1.0, -1.0, 4.0]):
        eye = np.array(eye)
        ends = cont.ends[cont.seen_from(eye)].reshape(-1, 3)
        d = np.linalg.norm(c - eye)
        half = math.asin(r / d)  # the tangent cone's half angle
        ray = ends - eye
        angle = np.arccos(np.clip(ray @ (c - eye) / np.linalg.norm(ray, axis=1) / d, -1, 1))
        tol = edge / (d - r)  # one edge's width, seen from the eye
        assert np.abs(angle - half).max() < tol, (np.abs(angle - half).max(), tol)
        axis = (c - eye) / d
        u = np.cross(axis, [0.0, 0.0, 1.0] if abs(axis[2]) < 0.9 else [1.0, 0.0, 0.0])
        u /= np.linalg.norm(u)
        azimuth = np.sort(np.arctan2(ray @ np.cross(axis, u), ray @ u))
        assert np.diff(np.concatenate([azimuth, azimuth[:1] + 2 * math.pi])).max() < 0.3


def test_a_real_cad_part_gives_holes_as_rims_and_its_edges_as_lines():
    path = Path("tests/meshes/lbracket.stl")  # an L bracket with counterbored holes (tests/meshes/README.md)
    raw = read_mesh(path, path.read_bytes())
    f = features(raw.vertices * 1e-3, raw.triangles, CREASE)  # millimetres: features() takes metres
    radii = sorted({round(e["a"] * 1e3, 3) for e in f.ellipses})
    assert radii == [1.5, 3.0, 3.303, 5.0]
    assert all(abs(e["a"] - e["b"]) <= RIM_TOL * e["a"] for e in f.ellipses)
    assert len(f.silhouettes) == 8 and len(f.lines) == 36 and len(f.corners) == 24
    assert f.degenerate == 0 and f.nonmanifold == 0


def _brute_hidden(P: np.ndarray, eye: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Whether each point is hidden from the eye: every triangle tested (Moller-Trumbore), no acceleration."""
    out = np.zeros(len(P), bool)
    e1, e2, s = tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0], eye - tris[:, 0]  # (T, 3)
    q = np.cross(s, e1)
    for lo in range(0, len(P), 256):
        d = P[lo:lo + 256, None, :] - eye  # (n, 1, 3)
        h = np.cross(d, e2)  # (n, T, 3)
        a = (e1 * h).sum(-1)
        ok = np.abs(a) > 1e-15
        a = np.where(ok, a, 1.0)
        u = (s * h).sum(-1) / a
        v = (q * d).sum(-1) / a
        t = (q * e2).sum(-1) / a
        out[lo:lo + 256] = (ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6) & (t < 1 - 1e-6)).any(axis=1)
    return out


def test_hidden_lines_by_mesh_faces_match_a_brute_force_ray_caster(tmp_path):
    """The grid-accelerated exact visibility against every triangle tested for every sample point."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.4)
    ball.apply_translation((2.0, 0.0, 1.0))
    ball.export(tmp_path / "ball.stl")
    w = build_world(compile_file(_scene(tmp_path, 'mesh read "ball.stl"', "place m as m1\n"))[0])
    assert len(w.triangles) == 1280
    rng = np.random.default_rng(7)
    eye = np.array([0.0, 0.05, 1.1])
    # segments behind, through and beside the ball
    A = rng.uniform((2.3, -1.0, 0.3), (3.5, 1.0, 1.7), (60, 3))
    B = A + rng.normal(0, 0.5, (60, 3))
    R = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # a camera looking along world x
    e = Occluders.of_world(w).seen_from(R, -R @ eye)
    assert e.grid.n == 1280 // CHUNK  # every chunk binned: the grid, not the fallback, is what is tested
    r, u0, u1, _ = e.segment_pieces((A - eye) @ R.T, (B - eye) @ R.T, np.zeros(60), np.ones(60))
    u = np.linspace(0.0, 1.0, 41)
    P = (A[:, None] + u[None, :, None] * (B - A)[:, None]).reshape(-1, 3)
    want = _brute_hidden(P, eye, w.triangles).reshape(60, 41)
    shown = np.zeros((60, 41), bool)
    near_edge = np.zeros((60, 41), bool)
    for row, a, b in zip(r, u0, u1, strict=True):
        shown[row] |= (u >= a) & (u <= b)
        near_edge[row] |= (np.abs(u - a) < 1e-6) | (np.abs(u - b) < 1e-6)
    assert want.any() and (~want).any()
    assert ((shown == ~want) | near_edge).all()
    got_points = e.hidden_by_faces((P - eye) @ R.T)
    assert (got_points == want.ravel()).mean() > 0.999


def test_arcs_hidden_by_mesh_faces_match_a_brute_force_ray_caster(tmp_path):
    """Ellipse arcs behind a faceted ball: the exact arc-against-triangle intervals (four circular intervals a
    pair) against every triangle tested at 721 points of each arc."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.4)
    ball.apply_translation((2.0, 0.0, 1.0))
    ball.export(tmp_path / "ball.stl")
    w = build_world(compile_file(_scene(tmp_path, 'mesh read "ball.stl"', "place m as m1\n"))[0])
    rng = np.random.default_rng(11)
    eye = np.array([0.0, 0.05, 1.1])
    n = 40
    c = rng.uniform((2.6, -0.6, 0.4), (3.6, 0.6, 1.6), (n, 3))  # ellipses behind and beside the ball
    U, V = rng.normal(0, 0.3, (n, 3)), rng.normal(0, 0.3, (n, 3))
    lo = rng.uniform(-np.pi, np.pi, n)
    hi = lo + rng.uniform(0.5, 2 * np.pi, n)
    R = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    e = Occluders.of_world(w).seen_from(R, -R @ eye)
    r, t0, t1, _ = e.arc_pieces((c - eye) @ R.T, U @ R.T, V @ R.T, lo, hi)
    s = np.linspace(0.0, 1.0, 721)
    t = lo[:, None] + (hi - lo)[:, None] * s
    P = (c[:, None] + np.cos(t)[..., None] * U[:, None] + np.sin(t)[..., None] * V[:, None]).reshape(-1, 3)
    want = _brute_hidden(P, eye, w.triangles).reshape(n, len(s))
    shown, near_edge = np.zeros_like(want), np.zeros_like(want)
    for row, a, b in zip(r, t0, t1, strict=True):
        shown[row] |= (t[row] >= a) & (t[row] <= b)
        near_edge[row] |= (np.abs(t[row] - a) < 1e-6) | (np.abs(t[row] - b) < 1e-6)
    assert 0.1 < want.mean() < 0.9  # the ball hides part of the arcs, not all
    assert ((shown == ~want) | near_edge).all()


def _scene(tmp_path: Path, mesh: str, extra: str = "") -> Path:
    path = tmp_path / "s.wd"
    path.write_text(f"wiredsl 1\nmodel m {{\n  {mesh}\n}}\n{extra}")
    return path


def test_scale_up_and_file_units(tmp_path):
    trimesh.creation.box(extents=(100.0, 200.0, 300.0)).export(tmp_path / "b.obj")
    scene = compile_file(_scene(tmp_path, 'mesh read "b.obj" scale 0.001 up y'))[0]
    ends = np.array([p for ln in scene.model("m").lines for p in (ln.start, ln.end)])
    assert np.allclose(np.ptp(ends, axis=0), (0.1, 0.3, 0.2))  # y-up: the file's y (0.2 m) is now z
    path = tmp_path / "mm.wd"
    path.write_text('wiredsl 1\nunits length mm\nmodel m {\n  mesh read "b.obj"\n}\n')
    ends = np.array([p for ln in compile_file(path)[0].model("m").lines for p in (ln.start, ln.end)])
    assert np.allclose(np.ptp(ends, axis=0), (0.1, 0.2, 0.3))


def test_degenerate_and_nonmanifold_triangles_are_warned_at_the_statement(tmp_path):
    (tmp_path / "w.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv 2 0 0\n"
                                    "f 1 2 3\nf 1 2 4\nf 2 1 3\nf 1 2 5\n")
    _, warnings, _ = compile_file(_scene(tmp_path, 'mesh read "w.obj"'))
    got = [(d.code, d.span.line, d.span.col) for d in warnings]
    assert ("W125", 3, 13) in got and ("W126", 3, 13) in got


def test_contours_are_marked_in_the_dump_and_cut_by_exact_visibility():
    r = CliRunner().invoke(main, ["build", "scenes/meshes.wd", "-o", "-", "--no-effects", "--pose", "1",
                                  "--visibility", "exact"])
    assert r.exit_code == 0, r.output
    import json

    views = json.loads(r.stdout)["poses"][0]
    lines = views["left"]["lines"]
    contour = [ln for ln in lines + views["left"]["polylines"] if ln.get("contour")]
    assert contour and all(ln["source"] == "ball1.surface" for ln in contour)
    assert [ln for ln in contour if ln["kind"] == "polyline"]  # chained end to end
    assert not [ln for ln in lines if ln["source"] == "ball1.surface" and not ln.get("contour")]
    crate = {ln["source"] for ln in lines if ln["source"].startswith("crate1.")
             and math.dist(*ln["points"]) > 0.5}  # (hidden edges keep slivers of 1e-5 px at visible corners)
    assert len(crate) == 9  # three faces seen: the crate's three far edges are hidden by its own faces
    cut = [ln for ln in lines if ln["source"] == "crate1.edge11"]
    assert len(cut) == 2 and all(ln["occluded"] for ln in cut)  # its back top edge, broken by the can on it


def test_a_fifo_is_refused_without_opening_it(tmp_path):
    import os

    os.mkfifo(tmp_path / "pipe.stl")  # opening it would block until a writer came
    path = _scene(tmp_path, 'mesh read "pipe.stl"')
    r = CliRunner().invoke(main, ["check", str(path)])
    assert r.exit_code == 1 and "error[E010]" in r.stderr and "FIFO" in r.stderr


def test_hover_on_mesh_names_its_file_and_counts_what_it_found():
    from wiredsl.lsp import hover

    text = Path("scenes/meshes.wd").read_text()
    line = text.splitlines().index('  mesh read "meshes/can.stl" crease 30deg') + 1
    md = hover(None, text, "scenes/meshes.wd", line, 4)
    assert "`meshes/can.stl`: 192 triangles" in md and "2 ellipses, 1 silhouette, 0 corners, 2 faces" in md


def test_gltf_reads_embedded_buffers_and_refuses_other_files(tmp_path):
    import base64
    import json

    from wiredsl.io.mesh import MeshFileError

    files = trimesh.exchange.gltf.export_gltf(trimesh.Scene(trimesh.creation.box()))
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    doc = json.loads(files["model.gltf"])
    for b in doc["buffers"]:
        b["uri"] = "data:application/octet-stream;base64," + base64.b64encode(files[b["uri"]]).decode()
    (tmp_path / "embedded.gltf").write_text(json.dumps(doc))
    assert len(read_mesh(tmp_path / "embedded.gltf", (tmp_path / "embedded.gltf").read_bytes()).triangles) == 12
    with pytest.raises(MeshFileError, match="refers to another file"):
        read_mesh(tmp_path / "model.gltf", (tmp_path / "model.gltf").read_bytes())


def test_mesh_faces_hide_features_from_view_points(tmp_path):
    """visibility auto: a wall read from a mesh stands between a view-point and a hand-written line."""
    from wiredsl.engine import visibility

    trimesh.creation.box(extents=(0.1, 2.0, 2.0)).export(tmp_path / "wall.stl")
    path = tmp_path / "s.wd"
    path.write_text('wiredsl 1\nmodel wall {\n  mesh read "wall.stl"\n}\n'
                    "model post {\n  line p from (0, 0, 0) to (0, 0, 1)\n}\n"
                    "place wall as w1 at (2m, 0, 1m)\nplace post as p1 at (4m, 0, 0)\n")
    w = build_world(compile_file(path)[0])
    seen = visibility.visible_features(w, np.array([[0.0, 0.0, 1.0], [4.0, 3.0, 1.0]]))
    post = w.feature_ids.index("p1.p")
    assert not seen[0, post] and seen[1, post]  # behind the wall from the first eye, in the open from the second


@pytest.mark.parametrize(("clause", "message", "col"), [
    ("crease -5deg", "crease angle must be in 0..180 deg, got -5 deg", 28),
    ("crease 200deg", "crease angle must be in 0..180 deg, got 200 deg", 28),
    ("scale 1e30", "mesh scale must be in (0, 1e+09], got 1e+30", 27),
])
def test_a_crease_or_scale_out_of_range_is_refused_at_its_value(tmp_path, clause, message, col):
    """A negative crease made every edge a feature (the diagonals of flat faces too), over 180 deg none; a
    scale of 1e30 was refused as 'must be positive'."""
    trimesh.creation.box(extents=(1.0, 1.0, 1.0)).export(tmp_path / "b.obj")
    with pytest.raises(WiredslError) as info:
        compile_file(_scene(tmp_path, f'mesh read "b.obj" {clause}'))
    got = [(d.code, d.message, d.span.line, d.span.col) for d in info.value.diagnostics]
    assert got == [("E110", message, 3, col)]


MESH_FILES = sorted(p for p in Path("scenes/meshes").iterdir() if p.suffix in (".obj", ".ply", ".stl", ".glb"))


def test_a_mesh_read_again_comes_from_the_cache_bit_for_bit(tmp_path, monkeypatch):
    """Every mesh of scenes/meshes and the CAD bracket: the second read is served from the cache (trimesh is
    not called) with the very arrays trimesh gave; a damaged cache file is read afresh and replaced; the cache
    keeps the CACHE_FILES most recently used; without a cache folder the mesh is still read."""
    from wiredsl.io import mesh as io_mesh

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    files = [*MESH_FILES, Path("tests/meshes/lbracket.stl")]
    first = [read_mesh(p, p.read_bytes()) for p in files]
    folder = tmp_path / "wiredsl" / "meshes"
    assert len(list(folder.glob("*.npz"))) == len(files)

    def no_trimesh(*a, **k):
        raise AssertionError("trimesh was called for a cached mesh")

    with monkeypatch.context() as m:
        m.setattr(trimesh, "load", no_trimesh)
        again = [read_mesh(p, p.read_bytes()) for p in files]
    for a, b in zip(first, again, strict=True):
        assert a.vertices.dtype == b.vertices.dtype and np.array_equal(a.vertices, b.vertices)
        assert a.triangles.dtype == b.triangles.dtype and np.array_equal(a.triangles, b.triangles)
    victim = sorted(folder.glob("*.npz"))[0]
    for damage in (b"not an npz", victim.read_bytes()[:100]):
        victim.write_bytes(damage)
        assert [np.array_equal(r.vertices, f.vertices) for r, f in
                zip((read_mesh(p, p.read_bytes()) for p in files), first, strict=True)] == [True] * len(files)
        assert np.load(victim)["vertices"].dtype == np.float64  # rewritten
    monkeypatch.setattr(io_mesh, "CACHE_FILES", 2)
    obj = Path("scenes/meshes/crate.obj")
    read_mesh(obj, obj.read_bytes() + b"\n")  # a new file: the cache is cut to the 2 newest
    assert len(list(folder.glob("*.npz"))) == 2
    monkeypatch.setattr("wiredsl.files.cache_folder", lambda kind: None)
    assert np.array_equal(read_mesh(obj, obj.read_bytes() + b"\n\n").triangles, first[files.index(obj)].triangles)


def test_a_mesh_scene_built_again_does_not_import_trimesh(tmp_path):
    """Through the command line: the second build of scenes/meshes.wd reads its four meshes from the cache, so
    trimesh (half a second of CPU) is not imported, and the dump is the same bytes."""
    import subprocess
    import sys

    script = ("import sys\nfrom wiredsl.cli import main\n"
              "try:\n    main(sys.argv[1:])\nexcept SystemExit as e:\n    assert not e.code, e.code\n"
              "print('trimesh' in sys.modules)\n")
    env = {**__import__("os").environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}
    seen = []
    for out in ("a", "b"):
        proc = subprocess.run([sys.executable, "-c", script, "build", "scenes/meshes.wd", "--no-svg", "-o",
                               str(tmp_path / out)], capture_output=True, text=True, env=env)
        assert proc.returncode == 0, proc.stderr
        seen.append(proc.stdout.strip().splitlines()[-1])
    assert seen == ["True", "False"]
    assert (tmp_path / "a" / "features.json").read_bytes() == (tmp_path / "b" / "features.json").read_bytes()


def test_a_cache_folder_others_may_write_into_is_not_used(tmp_path, monkeypatch):
    """What the caches hold is loaded as code (kernels) or trusted as data (meshes): a cache folder with group or
    other write permission (another user could have made it first in a shared temporary directory) is passed
    over for this user's own, made private; with none usable there is no cache."""
    import os
    import tempfile

    from wiredsl.files import cache_folder

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "home"))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    shared = tmp_path / "home" / "wiredsl" / "meshes"
    shared.mkdir(parents=True)
    shared.chmod(0o777)
    got = cache_folder("meshes")
    assert got == tmp_path / "tmp" / f"wiredsl-meshes-{os.getuid()}" and got.stat().st_mode & 0o077 == 0
    got.chmod(0o773)
    assert cache_folder("meshes") is None
    shared.chmod(0o755)
    assert cache_folder("meshes") == shared
