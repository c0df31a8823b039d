"""Issue 35, item 3: the built-in `paper` pipeline that any scene can name and extend, and calibration_error's
sigma diagnosed for what it scales (W163 with a declared covariance far below 1)."""

from __future__ import annotations

import re

from click.testing import CliRunner
from helpers import compile_text

from wiredsl.cli import main
from wiredsl.language.compile import compile_file
from wiredsl.scene import PAPER_STAGES

SCENE = """wiredsl 1
model m {
  line a from (2, -0.5, 0.3) to (2, 0.5, 1.8)
  corner c at (2, -0.5, 0.3) joins a
}
place m as m1 at (0, 0, 0)
camera c {
  focal 500px
  size (640px, 480px)
}
rig r {
  left c at (0, 0.06, 1) looking (1, 0, 0)
  right c at (0, -0.06, 1) looking (1, 0, 0)
CALIBRATION}
path p {
  straight from (0, 0) to (0.5m, 0) step 0.25m
}
"""
COVARIANCE = "  calibration covariance order [left.f, right.f] matrix [[4, 0], [0, 4]]\n"
PAPER = ["calibration_error", "edge_loss", "lateral_shift", "approx_error", "corner_loss", "corner_mismatch",
         "stereo_mismatch"]


def _scene(calibration: str = "", extra: str = ""):
    return SCENE.replace("CALIBRATION", calibration) + extra


def test_a_new_scene_builds_the_paper_pipeline_by_name(tmp_path):
    """The user's table-box-cup scene declares no pipeline: `--pipeline paper` runs the paper's sources (no
    calibration_error: its rig has no calibration); an unknown name lists the built-in one."""
    r = CliRunner().invoke(main, ["build", "tests/data/table_box_cup.wd", "--pipeline", "paper", "--seed", "1",
                                  "-o", str(tmp_path / "o"), "--no-svg"])
    assert r.exit_code == 0, r.output
    assert "pipeline paper: " + ", ".join(PAPER[1:]) in r.stderr
    r = CliRunner().invoke(main, ["build", "tests/data/table_box_cup.wd", "--pipeline", "papr", "-o", "-"])
    assert r.exit_code == 2 and "(it has: the built-in paper)" in r.output


def test_the_paper_pipeline_is_the_papers_magnitudes_and_a_scenes_own_replaces_it():
    scene, _ = compile_text(_scene(COVARIANCE))
    paper = scene.pipeline("paper")
    assert [st.effect for st in paper.stages] == PAPER == [n for n, _ in PAPER_STAGES]
    p = {st.effect: st.params for st in paper.stages}
    assert p["calibration_error"]["sigma"] == 1.0 and p["edge_loss"]["fraction"] == 0.29
    assert p["lateral_shift"]["range"] == 3.0 and p["approx_error"]["sigma"] == 0.15
    assert p["corner_loss"]["keep"] == 0.85 and p["corner_mismatch"] == {"fraction": 0.01, "radius": 10.0}
    assert abs(p["stereo_mismatch"]["band"] - 5 * 3.141592653589793 / 180) < 1e-15
    assert scene.pipeline() is None  # naming it is what runs it: a build without --pipeline stays ideal
    lab = compile_file("scenes/lab.wd")[0]
    assert lab.pipeline("paper").stages[0].params["sigma"] == 0.01  # the lab's own


def test_a_pipeline_like_paper_overrides_adds_and_leaves_out():
    scene, warnings = compile_text(_scene(COVARIANCE, """pipeline mine like paper without [corner_mismatch] {
  lateral_shift range 2px
  corner_error sigma 0.3px
}
pipeline again like mine default
study s {
  pipeline paper
  trials 2
  vary lateral_shift.range from 1px to 3px steps 2
  measure survival
}
"""))
    mine = {st.effect: st.params for st in scene.pipeline("mine").stages}
    assert list(mine) == ["calibration_error", "edge_loss", "lateral_shift", "approx_error", "corner_loss",
                          "corner_error", "stereo_mismatch"]  # corner_error in data-flow order
    assert mine["lateral_shift"]["range"] == 2.0 and mine["edge_loss"]["fraction"] == 0.29
    assert mine["corner_error"]["sigma"] == 0.3
    assert scene.pipeline() == scene.pipeline("again") and scene.pipeline("again").stages == \
        scene.pipeline("mine").stages
    assert scene.studies[0].pipeline == "paper" and not warnings
    without, _ = compile_text(_scene("", "pipeline mine like paper\n"))  # no calibration: no calibration_error
    assert [st.effect for st in without.pipeline("mine").stages] == PAPER[1:]


def test_like_and_without_are_checked(tmp_path):
    bad = tmp_path / "bad.wd"
    bad.write_text(_scene("", "pipeline a like papr\npipeline b like paper without [blur]\n"
                              "pipeline c without [edge_loss] {\n  edge_loss\n}\n"))
    r = CliRunner().invoke(main, ["check", str(bad)])
    assert r.exit_code == 1 and "Traceback" not in r.output
    assert re.search(r"bad\.wd:18:17: error\[E104\]: unknown pipeline 'papr'.*", r.stderr), r.stderr
    assert "'blur' is not a stage of pipeline 'paper'" in r.stderr
    assert "'without' leaves stages out of the pipeline 'like' names: it needs 'like'" in r.stderr


def test_a_small_sigma_on_a_declared_covariance_is_w163():
    extra = "pipeline small {\n  calibration_error sigma 0.01\n}\n"
    _, warnings = compile_text(_scene(COVARIANCE, extra))
    (w,) = [w for w in warnings if w.code == "W163"]
    assert (w.span.line, w.span.col) == (20, 27)  # at the sigma
    assert "the draws have 0.01 times its standard deviations" in w.message and "sigma 1" in w.hint
    _, warnings = compile_text(_scene(COVARIANCE, extra.replace("0.01", "0.5")))  # not far below 1
    assert not [w for w in warnings if w.code == "W163"]
    info = COVARIANCE.replace("covariance", "information")  # an information matrix: the paper's own setting
    _, warnings = compile_text(_scene(info, extra))
    assert not [w for w in warnings if w.code == "W163"]
