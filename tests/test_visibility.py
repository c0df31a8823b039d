"""Visibility: hidden edges of a box known by construction, nearest view-point rule, viewdep files."""

from __future__ import annotations

import json

import numpy as np
from click.testing import CliRunner
from helpers import BOX_FACES, compile_text

from wiredsl.cli import main
from wiredsl.engine.visibility import nearest_viewpoint, visible_features
from wiredsl.engine.world import build_world

# A closed 1 m box at the origin, each edge its own line so visibility is per edge.
BOX = """wiredsl 1
model box {
  line s_bottom from (0, 0, 0) to (1, 0, 0)
  line s_top from (0, 0, 1) to (1, 0, 1)
  line n_bottom from (0, 1, 0) to (1, 1, 0)
  line n_top from (0, 1, 1) to (1, 1, 1)
  line w_bottom from (0, 0, 0) to (0, 1, 0)
  line w_top from (0, 0, 1) to (0, 1, 1)
  line e_bottom from (1, 0, 0) to (1, 1, 0)
  line e_top from (1, 0, 1) to (1, 1, 1)
  line sw from (0, 0, 0) to (0, 0, 1)
  line se from (1, 0, 0) to (1, 0, 1)
  line nw from (0, 1, 0) to (0, 1, 1)
  line ne from (1, 1, 0) to (1, 1, 1)
  corner top_ne at (1, 1, 1)""" + BOX_FACES + """}
place box as b
"""


def visible_from(eye) -> set[str]:
    scene, _ = compile_text(BOX)
    w = build_world(scene)
    vis = visible_features(w, np.array([eye], dtype=float))[0]
    return {w.feature_ids[i].split(".", 1)[1] for i in np.flatnonzero(vis)}


def test_from_the_south_only_the_south_face_edges_are_seen():
    assert visible_from((0.5, -4.0, 0.5)) == {"s_bottom", "s_top", "sw", "se"}


def test_from_above_the_top_edges_and_top_corner_are_seen():
    assert visible_from((0.5, 0.5, 5.0)) == {"s_top", "n_top", "w_top", "e_top", "top_ne"}


def test_from_the_north_east_corner_above():
    seen = visible_from((4.0, 4.0, 4.0))
    # the three faces towards the eye (north, east, top) show their edges; the far bottom edges do not
    assert {"n_top", "e_top", "ne", "n_bottom", "e_bottom", "top_ne"} <= seen
    assert not seen & {"s_bottom", "w_bottom", "sw"}


def test_without_faces_everything_is_visible():
    text = "\n".join(line for line in BOX.splitlines() if "face" not in line)
    scene, _ = compile_text(text)
    w = build_world(scene)
    assert visible_features(w, np.array([[0.5, -4.0, 0.5]]))[0].all()


def test_cylinder_side_hides_nothing_in_front_but_hides_what_is_behind():
    text = """wiredsl 1
model can {
  ellipse top centre (0, 0, 1) normal (0, 0, 1) axis (1, 0, 0) radii (0.3, 0.3)
  ellipse bottom centre (0, 0, 0) normal (0, 0, 1) axis (1, 0, 0) radii (0.3, 0.3)
  silhouette side between top bottom
}
model stick { line l from (0, 0, 0.2) to (0, 0, 0.8) }
place can as c
place stick as behind at (0, 1, 0)
place stick as front at (0, -1, 0)
"""
    scene, _ = compile_text(text)
    w = build_world(scene)
    vis = dict(zip(w.feature_ids, visible_features(w, np.array([[0.0, -5.0, 0.5]]))[0], strict=True))
    assert vis["front.l"] and not vis["behind.l"] and vis["c.side"]


def test_nearest_viewpoint_and_ties():
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    robots = np.array([[0.0, 0.0], [0.9, 0.1], [0.5, 0.0], [0.5, 0.5], [1.0, 0.5], [0.5 + 1e-9, 0.0]])
    assert nearest_viewpoint(pts, robots).tolist() == [0, 1, 0, 0, 1, 1]
    # the tie-break follows declaration order, not position: reversed points, reversed winner
    assert nearest_viewpoint(pts[::-1].copy(), robots[[2, 3]]).tolist() == [2, 0]


def test_viewdep_file_is_written_and_used_by_build(tmp_path):
    scene_text = BOX + """camera eye { focal 500px
  size (640px, 480px) }
rig r { left eye at (0, 0.05, 0.5) looking (1, 0, 0)
  right eye at (0, -0.05, 0.5) looking (1, 0, 0) }
viewpoints m {
  vertex south at (0.5, -3)
  vertex north at (0.5, 4)
  visibility file "box.viewdep.json"
}
path p {
  pose (0.5, -3) heading 90deg
  pose (0.5, 4) heading -90deg
}
"""
    (tmp_path / "box.wd").write_text(scene_text)
    r = CliRunner().invoke(main, ["viewdep", str(tmp_path / "box.wd"), "-o", str(tmp_path / "box.viewdep.json")])
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "box.viewdep.json").read_text())
    assert set(doc["viewpoints"]["south"]) == {"b.s_bottom", "b.s_top", "b.sw", "b.se"}
    assert CliRunner().invoke(main, ["validate", str(tmp_path / "box.viewdep.json")]).exit_code == 0
    r = CliRunner().invoke(main, ["build", str(tmp_path / "box.wd"), "-o", "-"])
    assert r.exit_code == 0, r.output
    dump = json.loads(r.stdout)
    seen = {f["source"] for f in dump["poses"][0]["left"]["lines"]}
    assert dump["poses"][0]["viewpoint"] == "south" and seen == {"b.s_bottom", "b.s_top", "b.sw", "b.se"}
    seen_north = {f["source"] for f in dump["poses"][1]["left"]["lines"]}
    assert seen_north == {"b.n_bottom", "b.n_top", "b.nw", "b.ne"}


def test_missing_viewdep_file_is_a_diagnostic(tmp_path):
    (tmp_path / "s.wd").write_text(BOX + 'camera eye { focal 500px\n size (640px, 480px) }\n'
                                   'rig r { left eye at (0, 0.05, 0.5) looking (1, 0, 0)\n'
                                   ' right eye at (0, -0.05, 0.5) looking (1, 0, 0) }\n'
                                   'viewpoints m {\n vertex a at (0, -3)\n visibility file "none.json"\n}\n'
                                   'path p { pose (0, -3) heading 90deg }\n')
    r = CliRunner().invoke(main, ["build", str(tmp_path / "s.wd"), "-o", "-"])
    assert r.exit_code == 1 and "cannot read view-dependency file" in r.stderr and "wiredsl viewdep" in r.stderr


def test_exact_cone_and_cylinder_sides_agree_with_a_fine_triangulation():
    """The closed-form ray test against a cone or cylinder side equals 4,000 quads around, but for grazing rays."""
    from wiredsl.engine import visibility
    from wiredsl.engine.world import World, surface_triangles

    rng = np.random.default_rng(4)
    differ = total = 0
    for _ in range(6):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        u = np.cross(axis, rng.normal(size=3))
        u /= np.linalg.norm(u)
        v = np.cross(axis, u)
        r, grow, h = rng.uniform(0.2, 1.0), rng.uniform(0.3, 1.7), rng.uniform(0.5, 2.0)
        c = rng.normal(size=3)
        w = World(feature_ids=["p.a", "p.b", "p.s"], feature_kind=["ellipse", "ellipse", "silhouette"])
        w.ell_c = np.stack([c, c + h * axis])
        w.ell_U, w.ell_V = np.stack([r * u, grow * r * u]), np.stack([r * v, grow * r * v])
        w.ell_arc, w.ell_full, w.ell_fid = np.tile([0.0, 2 * np.pi], (2, 1)), np.ones(2, bool), np.arange(2)
        w.sil_pair, w.sil_fid = np.array([[0, 1]]), np.array([2])
        occ = visibility.occluders(w)
        assert len(occ.origin) == 1 and len(occ.triangles) == 0  # the exact surface, no triangles
        fine, _ = surface_triangles(w, segments=4000)
        eye = c + rng.normal(size=3) * 3
        targets = c + rng.normal(size=(3000, 3)) * 1.5
        exact = visibility.seen(eye, targets, occ)
        approx = visibility.seen(eye, targets, fine)
        differ += int((exact != approx).sum())
        total += len(targets)
        assert 0 < (~exact).sum() < len(targets)  # some rays are blocked, some are not
    assert differ <= total * 1e-3, differ


def test_ray_casting_memory_is_capped_by_chunks():
    """Tiny chunks give the same answer as one big chunk."""
    from wiredsl.engine import visibility

    scene, _ = compile_text(BOX)
    w = build_world(scene)
    pts, _ = visibility.samples(w)
    occ = visibility.occluders(w)
    eye = np.array([0.5, -4.0, 0.5])
    assert (visibility.seen(eye, pts, occ, cap=7) == visibility.seen(eye, pts, occ)).all()


def test_direction_chunks_test_the_same_pairs_that_can_hit_as_brute_force():
    """Culling occluders by direction and distance per chunk of targets changes no answer."""
    from wiredsl.engine import visibility

    rng = np.random.default_rng(12)
    for _ in range(4):
        v0 = rng.uniform(-5, 5, (300, 3))
        tris = v0[:, None] + rng.normal(size=(300, 3, 3)) * rng.uniform(0.05, 1.0, (300, 1, 1))
        occ = visibility.Occluders(tris, np.array([[0.0, 0.0, -1.0]]), np.linalg.inv(np.diag([0.5, 0.5, 2.0]))[None],
                                   np.array([-0.4]))
        eye = rng.uniform(-6, 6, 3)
        targets = rng.uniform(-6, 6, (4000, 3))
        d = targets - eye
        brute = ~(visibility._hits_triangles(eye, d, tris)
                  | visibility._hits_quadrics(eye, d, occ.origin, occ.to_local, occ.growth))
        got = visibility.seen(eye, targets, occ)
        assert (got == brute).all()
        assert 0.05 < brute.mean() < 0.95
