"""The pose figures (hand-written SVG) in every layout, and the bench plot (matplotlib).

Structural checks, not pixel goldens: well-formed XML, a tooltip naming the source of every
feature, a legend listing every colour drawn, a fixed width whatever the world's shape, legible
text and strokes at one column's width, and byte-identical output for the same seed.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from click.testing import CliRunner

from wiredsl import bench
from wiredsl.cli import main
from wiredsl.engine.simulate import Options, simulate
from wiredsl.engine.world import build_world
from wiredsl.io import svg
from wiredsl.language.compile import compile_file

NS = "{http://www.w3.org/2000/svg}"
CORRIDOR = """wiredsl 1
scene corridor

model hall {
  polyline floor closed through (0, 0, 0) (10, 0, 0) (10, 1, 0) (0, 1, 0)
  line post from (10, 1, 0) to (10, 1, 2)
  corner foot at (10, 1, 0) joins floor post
}

place hall as hall1

camera cam {
  focal 6mm
  pixel 0.01mm
  size (640px, 480px)
}

rig head {
  left cam at (0.1m, 0.06m, 1.2m) looking (1, 0, -0.15)
  right cam at (0.1m, -0.06m, 1.2m) looking (1, 0, -0.15)
}

path walk {
  straight from (0.5m, 0.5m) to (8m, 0.5m) step 2.5m
}
"""


def _build(tmp_path: Path, *args: str, scene: str = "scenes/lab.wd") -> dict[str, bytes]:
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["build", scene, "-o", str(out), *args])
    assert r.exit_code == 0, r.output
    return {p.name: p.read_bytes() for p in sorted(out.glob("pose_*.svg"))}


def _colour(el: ET.Element) -> set[str]:
    return {c for c in (el.get("stroke"), el.get("fill")) if c and c != "none"}


def _check_figure(data: bytes, sources: set[str]) -> ET.Element:
    """The checks every figure passes; returns its root."""
    root = ET.fromstring(data)
    assert root.tag == NS + "svg" and root.get("width") == "1000"
    assert root.get("viewBox").split()[2] == "1000"
    features = [e for e in root.iter() if e.get("class") == "feature"]
    assert features
    for e in features:  # every feature names its source
        title = e.find(NS + "title")
        assert title is not None and title.text.split(",")[0].split(" (")[0] in sources, ET.tostring(e)
    legend = next(e for e in root.iter(NS + "g") if e.get("class") == "legend")
    listed = set()
    for key in (e for e in legend.iter() if e.get("class") == "key"):
        for el in key.iter():
            listed |= _colour(el)
    drawn = set()
    for e in root.iter():
        if e.get("class") in ("feature", "map"):
            drawn |= _colour(e)
    assert drawn and drawn <= listed, drawn - listed
    for e in root.iter(NS + "text"):  # at least 11 px at the figure's 1000 px
        assert float(e.get("font-size")) >= 11
    for e in root.iter():
        if e.get("class") in ("feature", "map") and e.get("stroke-width"):
            assert float(e.get("stroke-width")) >= 1.3
        if e.get("class") == "feature":
            assert float(e.get("stroke-width")) >= 1.5
    return root


def _texts(root: ET.Element) -> list[str]:
    return ["".join(e.itertext()) for e in root.iter(NS + "text")]


@pytest.fixture(scope="module")
def lab_sources() -> set[str]:
    scene, _, _ = compile_file("scenes/lab.wd")
    return set(build_world(scene).feature_ids)


def test_overlay_figure_has_legend_axes_names_fov_and_caption(tmp_path, lab_sources):
    svgs = _build(tmp_path, "--seed", "5", "--pose", "3")
    root = _check_figure(svgs["pose_003.svg"], lab_sources)
    texts = _texts(root)
    assert {"left camera (cam_l)", "right camera (cam_r)", "u (px)", "v (px)", "x (m)", "y (m)"} <= set(texts)
    for name in ("walls", "bin1", "bin2", "lamp", "table1", "cab", "door1"):  # every object named on the map
        assert name in texts
    assert "left camera's field of view" in texts and "right camera's field of view" in texts
    assert re.fullmatch(r"\d+ m", next(t for t in texts if t.endswith(" m") and t[0].isdigit()))  # scale bar
    caption = [e.text for e in root.iter(NS + "text") if e.get("class") == "caption"]
    assert "pose 3" in caption[0] and "heading" in caption[0] and "x = 1.91 m" in caption[0]
    assert "pipeline 'paper', seed 5, trial 0" in caption[1]
    tips = [e.find(NS + "title").text for e in root.iter() if e.get("class") == "feature"]
    assert any("(ideal)" in t for t in tips) and any("(shown)" in t for t in tips)
    assert any("segment" in t for t in tips)
    door = [e for e in root.iter(NS + "polyline") if e.get("class") == "map" and e.findtext(NS + "title") == "door1"]
    walls = [e for e in root.iter(NS + "polyline") if e.get("class") == "map" and e.findtext(NS + "title") == "walls"]
    order = list(root.iter())
    assert door and walls and order.index(door[0]) > order.index(walls[-1])  # the door is drawn over the wall
    assert door[0].get("stroke") != walls[0].get("stroke")


def test_same_seed_gives_the_same_bytes_in_every_layout(tmp_path):
    for layout in svg.LAYOUTS:
        a = _build(tmp_path / "a", "--seed", "9", "--pose", "2", "--layout", layout)
        b = _build(tmp_path / "b", "--seed", "9", "--pose", "2", "--layout", layout)
        assert a == b and a


def test_side_by_side_shows_original_beside_disturbed(tmp_path, lab_sources):
    svgs = _build(tmp_path, "--seed", "5", "--pose", "1", "--layout", "side-by-side")
    root = _check_figure(svgs["pose_001.svg"], lab_sources)
    titles = [t for t in _texts(root) if t.startswith(("left camera (", "right camera ("))]
    assert titles == ["left camera (cam_l): original", "left camera (cam_l): disturbed (paper)",
                      "right camera (cam_r): original", "right camera (cam_r): disturbed (paper)"]


def test_visibility_layout_dashes_what_view_dependency_hides():
    scene, _, _ = compile_file("scenes/box.wd")
    world = build_world(scene)
    without = simulate(scene, Options(visibility="all"), world)[1]
    with_ = simulate(scene, Options(visibility="scene"), world)[1]
    root = _check_figure(svg.visibility_pair(scene, world, without, with_, svg.Info(layout="visibility")).encode(),
                         set(world.feature_ids))
    hidden = [e for e in root.iter() if e.get("class") == "feature" and e.get("stroke") == svg.HIDDEN]
    shown_with = {f.fid for f in with_.left.features}
    expected = {world.feature_ids[f.fid] for f in without.left.features if f.fid not in shown_with}
    assert expected and {e.findtext(NS + "title").split(" (")[0] for e in hidden} == expected
    assert all(e.get("stroke-dasharray") for e in hidden)
    assert "hidden by view-dependency" in _texts(root)


def test_visibility_layout_refuses_all_and_side_by_side_needs_a_pipeline(tmp_path):
    r = CliRunner().invoke(main, ["build", "scenes/lab.wd", "-o", str(tmp_path), "--layout", "visibility",
                                  "--visibility", "all"])
    assert r.exit_code == 2 and "--layout" in r.output
    r = CliRunner().invoke(main, ["build", "scenes/lab.wd", "-o", str(tmp_path), "--layout", "side-by-side",
                                  "--no-effects"])
    assert r.exit_code == 2 and "pipeline" in r.output


def test_a_corridor_keeps_the_figure_width_and_the_camera_panes(tmp_path):
    scene = tmp_path / "corridor.wd"
    scene.write_text(CORRIDOR)
    svgs = _build(tmp_path, "--no-effects", scene=str(scene))
    root = _check_figure(svgs["pose_001.svg"], {"hall1.floor", "hall1.post", "hall1.foot"})
    frames = [e for e in root.iter(NS + "rect") if e.get("fill") == "#fafafa"]  # the camera images
    assert frames and all(float(e.get("width")) > 400 for e in frames)
    assert float(root.get("viewBox").split()[3]) < 1000  # a 10 m x 1 m world does not make a tall figure


def test_nice_steps():
    assert [svg.nice_step(s) for s in (6.0, 10.0, 640, 0.3)] == [1, 2, 200, 0.05]


def test_bench_plot_is_a_matplotlib_figure_with_labelled_axes_and_a_zero_floor():
    tables = [bench.Table("t", ["arithmetic", "max difference (px)", "time (ms)"], [["float64", 0.0, 9.0],
                                                                                    ["float32", 0.01, 5.0]],
                          plot=(2, 1), short="float32 against float64"),
              bench.Table("u", ["n", "err", "s"], [[10, 0.1, 0.3], [1000, 0.01, 3.0], [100, 0.03, 1.0]],
                          plot=(2, 1), short="trials")]
    data = bench.plot(tables)
    assert data == bench.plot(tables)  # deterministic
    root = ET.fromstring(data)
    text = " ".join(" ".join(e.itertext()) for e in root.iter(NS + "text"))
    for label in ("time (ms) (log)", "max difference (px) (log)", "float64: zero error", "float32 against float64",
                  "s (log)", "err (log)"):
        assert label in text
    assert bench.plot(tables, "png").startswith(b"\x89PNG")
    from matplotlib.figure import Figure

    ax = Figure().subplots()
    bench._panel(ax, tables[1])  # points joined in order of x, whatever the rows' order
    assert list(ax.lines[0].get_xdata()) == [0.3, 1.0, 3.0] and list(ax.lines[0].get_ydata()) == [0.1, 0.03, 0.01]
    assert ax.get_xscale() == ax.get_yscale() == "log" and ax.get_xlabel() == "s (log)"
    assert ax.get_xticks().size > 1 and ax.get_yticks().size > 1


# --------------------------------------------------------------------------- many placements (issue 23)

def _many(n: int) -> str:
    lines = ["wiredsl 1", "model box {",
             "  polyline b closed through (0, 0, 0) (0.4, 0, 0) (0.4, 0.4, 0) (0, 0.4, 0)",
             "  line up from (0, 0, 0) to (0, 0, 0.5)", "}"]
    lines += [f"place box as crate_number_{i} at ({2.0 + 0.5 * (i % 6)}, {-1.2 + 0.8 * (i // 6)}, 0)"
              for i in range(n)]
    lines += ["camera c {", "  focal 400px", "  size (640px, 480px)", "}", "rig r {",
              "  left c at (0, 0.06, 0.6) looking (1, 0, -0.1)", "  right c at (0, -0.06, 0.6) looking (1, 0, -0.1)",
              "}", "path run { pose (0, 0) }"]
    return "\n".join(lines) + "\n"


def test_a_legend_of_many_placements_says_how_many_it_leaves_out_and_names_never_overlap(tmp_path):
    (tmp_path / "many.wd").write_text(_many(18))
    (data,) = _build(tmp_path, scene=str(tmp_path / "many.wd")).values()
    root = ET.fromstring(data)
    legend = next(e for e in root.iter(NS + "g") if e.get("class") == "legend")
    keys = [e.get("data-label") for e in legend.iter() if e.get("class") == "key"]
    named = [k for k in keys if k.startswith("crate_number_")]
    assert len(named) == len(svg.PALETTE)  # one a colour: each colour means one placement in the legend
    assert f"and {18 - len(svg.PALETTE)} more placements (colours repeat)" in _texts(root)
    # the names on the map: halo and text, each a box of about 0.66 em a character; no two overlap
    boxes = []
    for e in root.iter(NS + "text"):
        if e.get("font-weight") == "bold" and e.get("fill") != "#ffffff":
            w, x, y = 0.66 * svg.SMALL * len(e.text), float(e.get("x")), float(e.get("y"))
            x0 = x - {"start": 0.0, "middle": w / 2, "end": w}[e.get("text-anchor", "start")]
            boxes.append((x0, y - 0.8 * svg.SMALL, x0 + w, y + 0.25 * svg.SMALL))
    assert 3 < len(boxes) < 18  # crowded: some names left off (their outlines' tooltips keep them)
    for i, a in enumerate(boxes):
        for b in boxes[i + 1:]:
            assert a[2] < b[0] or b[2] < a[0] or a[3] < b[1] or b[3] < a[1], (a, b)


def test_few_placements_are_all_listed_without_and_more(tmp_path):
    (tmp_path / "few.wd").write_text(_many(3))
    (data,) = _build(tmp_path, scene=str(tmp_path / "few.wd")).values()
    root = ET.fromstring(data)
    assert not any(t.startswith("and ") for t in _texts(root))
    assert {f"crate_number_{i}" for i in range(3)} <= set(_texts(root))


def test_placement_colours_are_a_scheme_apart_from_the_feature_kinds():
    import itertools
    import math

    def rgb(h):
        return tuple(int(h[i:i + 2], 16) for i in (1, 3, 5))

    others = {*svg.KIND_COLOURS.values(), *svg.FOV.values(), svg.IDEAL, svg.HIDDEN, svg.ROOM, svg.MESH,
              svg.MESH_POINT, svg.NEAREST, svg.PATH, svg.ROBOT}
    for p in svg.PALETTE:  # was: teal, brown, indigo and orange in both the palette and the kinds
        assert min(math.dist(rgb(p), rgb(o)) for o in others) >= 45, p
    assert min(math.dist(rgb(a), rgb(b)) for a, b in itertools.combinations(svg.PALETTE, 2)) >= 60
