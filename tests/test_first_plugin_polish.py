"""The rough edges a first plug-in author hits (issue 23, item 6): hints for missing plug-ins, did-you-mean in
Python, dir(wiredsl), diagnostics in source order without knock-on errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from wiredsl.diagnostics import NOT_INSTALLED, WiredslError
from wiredsl.language import ast
from wiredsl.language.compile import compile_program

ROOT = Path(__file__).resolve().parent.parent
LAB = (ROOT / "scenes" / "lab.wd").read_text()


def compile_lab(text: str):
    """Compile text as if it were a file in scenes/ (so that the lab's includes are found)."""
    return compile_program(ast.load(str(ROOT / "scenes" / "edited.wd"), text))


def diagnostics_of(text: str):
    with pytest.raises(WiredslError) as err:
        compile_lab(text)
    return err.value.diagnostics


def test_an_unknown_stage_that_is_no_near_miss_hints_at_a_missing_plugin():
    (d,) = diagnostics_of(LAB.replace("pipeline edges {\n  edge_loss", "pipeline edges {\n  rolling_shutter speed 2"))
    assert d.code == "E100" and d.message == "unknown statement 'rolling_shutter' in a pipeline block"
    assert d.hint == NOT_INSTALLED and "wiredsl plugins" in d.hint


def test_a_near_miss_still_gets_did_you_mean_not_the_plugin_hint():
    (d,) = diagnostics_of(LAB.replace("pipeline edges {\n  edge_loss", "pipeline edges {\n  edge_los"))
    assert d.hint == "did you mean 'edge_loss'?"


STUDY = "study s {\n  pipeline edges\n  vary VARY values [0, 1]\n  trials 2\n  measure MEASURE\n}\n"


def test_an_unknown_measure_or_varied_stage_hints_at_a_missing_plugin():
    (d,) = diagnostics_of(LAB + STUDY.replace("VARY", "lateral_shift.range").replace("MEASURE", "essential"))
    assert d.message == "unknown measure 'essential'" and d.hint.startswith(NOT_INSTALLED + "; measures: ")
    (d,) = diagnostics_of(LAB + STUDY.replace("VARY", "rolling_shutter.speed").replace("MEASURE", "survival"))
    assert d.message == "unknown stage 'rolling_shutter'" and d.hint.startswith(NOT_INSTALLED + "; stages: ")


# --------------------------------------------------------------------------- did-you-mean from Python

def test_a_misspelt_effect_in_a_python_pipeline_says_what_it_may_have_meant():
    import wiredsl
    from wiredsl.scene import Pipeline

    lab = compile_lab(LAB)[0]
    bad = Pipeline(name="p", stages=[{"effect": "edge_los", "params": {}}])
    with pytest.raises(KeyError) as err:  # still a KeyError (a lookup), but one that says what it is
        next(wiredsl.simulate(lab, trials=1, seed=0, pipeline=bad))
    assert str(err.value) == "unknown effect 'edge_los': did you mean 'edge_loss'?"
    far = Pipeline(name="p", stages=[{"effect": "rolling_shutter", "params": {}}])
    with pytest.raises(KeyError, match="unknown effect 'rolling_shutter': maybe a plug-in .*; effects: "
                                       "calibration_error, edge_loss"):
        wiredsl.Simulator(lab, 0, far)


def test_a_misspelt_measure_name_from_python():
    from wiredsl.measures import REGISTRY

    with pytest.raises(KeyError) as err:
        REGISTRY["survivl"]
    assert str(err.value) == "unknown measure 'survivl': did you mean 'survival'?"
    assert REGISTRY.get("survivl") is None and "survivl" not in REGISTRY  # a Mapping still


def test_dir_of_wiredsl_lists_the_public_api_without_importing_it():
    import subprocess
    import sys

    code = "import sys, wiredsl; d = dir(wiredsl); print(sorted(set(wiredsl.__all__) - set(d)), 'numpy' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["[]", "False"]  # every public name, and nothing heavy imported to list them
    import wiredsl

    assert {"compile", "simulate", "Simulator", "load", "Measure", "Effect", "__version__"} <= set(dir(wiredsl))
    assert all(hasattr(wiredsl, name) for name in wiredsl.__all__)


# --------------------------------------------------------------------------- diagnostics in order, no knock-on

WORLD = "wiredsl 1\nmodel m {\n  line a from (2, -0.5, 0.3) to (2, 0.5, 1.8)\n}\nplace m as p\n"
RIG_AB = ("rig r {\n  left a at (0, 0.06, 1) looking (1, 0, 0)\n  right b at (0, -0.06, 1) looking (1, 0, 0)\n}\n"
          "path run { pose (0, 0) }\n")


def test_a_typo_in_a_camera_gives_no_knock_on_error_to_a_camera_declared_like_it():
    text = WORLD + "camera a {\n  focla 600px\n  size (640px, 480px)\n}\ncamera b like a {\n  k1 0.01\n}\n" + RIG_AB
    (d,) = diagnostics_of(text)  # was also "camera 'b' needs 'focal' (focal length)"
    assert (d.code, d.message, d.span.line) == ("E100", "unknown statement 'focla' in a camera block", 7)
    assert d.hint == "did you mean 'focal'?"


def test_a_camera_like_a_camera_that_truly_lacks_focal_still_needs_it():
    text = WORLD + "camera a {\n  size (640px, 480px)\n}\ncamera b like a {\n  k1 0.01\n}\n" + RIG_AB
    assert [d.message for d in diagnostics_of(text)] == ["camera 'a' needs 'focal' (focal length)",
                                                         "camera 'b' needs 'focal' (focal length)"]


def test_diagnostics_come_in_source_order(tmp_path):
    import json

    from click.testing import CliRunner

    from wiredsl.cli import main

    text = (WORLD + "camera a {\n  focal 600px\n  size (640px, 480px)\n  k1 zz\n}\nplace q as p2\n"
            + RIG_AB.replace("right b", "right a"))
    lines = [d.span.line for d in diagnostics_of(text)]
    assert lines == [9, 11]  # the camera's error was reported after the placement's (cameras resolve later)
    (tmp_path / "s.wd").write_text(text)
    r = CliRunner().invoke(main, ["check", str(tmp_path / "s.wd")])
    assert r.stderr.index(":9:6: error[E106]") < r.stderr.index(":11:7: error[E104]")
    r = CliRunner().invoke(main, ["check", "--diagnostics", "json", str(tmp_path / "s.wd")])
    assert [d["line"] for d in json.loads(r.stderr)["diagnostics"]] == [9, 11]


# --------------------------------------------------------------------------- a plug-in's default is its own

from test_plugins import installed  # noqa: E402,F401 - the wdplug distribution, as a fixture


def test_a_plugin_parameters_default_on_hover_does_not_claim_to_be_the_papers(installed):  # noqa: F811
    from wiredsl.language.statements import CONTEXTS
    from wiredsl.lsp import _clause_detail

    assert _clause_detail(CONTEXTS["pipeline"]["centre_noise"], "sigma") == "sigma (default 0.5 px)"
    assert _clause_detail(CONTEXTS["pipeline"]["lateral_shift"], "range") == "range (default 3 px, the paper's)"


# --------------------------------------------------------------------------- study plots

def _table(design="grid"):
    from wiredsl.io.features import SceneRef
    from wiredsl.study import report

    rows = []
    for i, x in enumerate([0.0, 0.002, 0.004]):
        for stat, mean, sem in (("features", [0.98, 0.6, 0.03][i], 0.05), ("ideal_features", 40.0, 1.0)):
            rows.append(report.Row(point=i, values={"lateral_shift.range": x}, measure="survival", statistic=stat,
                                   n=8, n_values=8, mean=mean, sem=sem, q05=0, q25=0, q50=0, q75=0, q95=0))
        rows.append(report.Row(point=i, values={"lateral_shift.range": x}, measure="stereo3d",
                               statistic="error_mean", n=8, n_values=8, mean=[0.001, 0.01, 0.02][i], sem=0.004,
                               q05=0, q25=0, q50=0, q75=0, q95=0))
    return report.StudyTable(tool_version="0", scene=SceneRef(name="x", file="x.wd", sha256="0" * 64),
                             study="shift", design=design, factors=["lateral_shift.range"], seed=0, trials=8,
                             rows=rows)


def test_study_plots_have_worded_titles_150_dpi_and_bands_inside_the_statistics_range(tmp_path, monkeypatch):
    from wiredsl.scene import MeasureUse, Study
    from wiredsl.study import plots

    assert plots.DPI == 150
    figures = {}
    plt = plots._pyplot()
    real = plt.close
    monkeypatch.setattr(plt, "close", lambda fig: figures.setdefault(fig._suptitle.get_text(), fig))
    study = Study(name="shift", pipeline="edges", factors=[{"stage": "lateral_shift", "param": "range",
                                                            "values": [0, 0.002, 0.004]}],
                  measures=[MeasureUse(name="survival"), MeasureUse(name="stereo3d")])
    written = plots.write_all(_table(), study, tmp_path)
    assert "plots/survival.features.png" in written
    from PIL import Image

    with Image.open(tmp_path / "survival.features.png") as im:  # 4.2 x 3.3 inches at 150 dpi
        assert abs(im.size[0] - 4.2 * 150) < 40 and abs(im.size[1] - 3.3 * 150) < 40
    titles = sorted(figures)
    assert "Survival: features (fraction)\nmean and 95% band, study shift (survival.features)" in titles
    assert "Stereo reconstruction error: error mean (m)\nmean and 95% band, study shift (stereo3d.error_mean)" \
        in titles
    for title, fig in figures.items():
        ax = fig.axes[0]
        assert ax.get_xlabel() == ("lateral shift: largest lateral shift either side (px)\n"
                                   "lateral_shift.range")
        ys = np.concatenate([p.get_paths()[0].vertices[:, 1] for p in ax.collections])
        lo, hi = {"features": (0, 1), "ideal_features": (0, np.inf), "error_mean": (0, np.inf)}[
            title.split("(")[-1].split(".")[-1].rstrip(")")]
        assert ys.min() >= lo and ys.max() <= hi, (title, ys.min(), ys.max())  # was 0.03 - 1.96 * 0.05 < 0
        real(fig)


def test_a_signed_statistic_keeps_its_band_below_zero():
    from wiredsl.study.plots import statistic_range

    assert statistic_range("m", [0.1, -0.2]) == (-np.inf, np.inf)
    assert statistic_range("m", [0.1, 0.2]) == (0, np.inf) and statistic_range("fraction", [2]) == (0, 1)
    assert statistic_range(None, [1.0]) == (-np.inf, np.inf)
