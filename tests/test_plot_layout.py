"""Issue 35, item 9: plots whose text was clipped or overlapping. Each figure is drawn and its texts' extents
measured: inside the figure, and the ones that overlapped apart."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("matplotlib")


def _boxes(fig, texts):
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    return [t.get_window_extent(r) for t in texts if t.get_text()]


def _inside(fig, box) -> bool:
    W, H = fig.bbox.width, fig.bbox.height
    return box.x0 >= -0.5 and box.y0 >= -0.5 and box.x1 <= W + 0.5 and box.y1 <= H + 0.5


def _table(factors):
    from wiredsl.io.features import SceneRef
    from wiredsl.study import report

    rows = [report.Row(point=i, values={f: float(v) for f in factors}, measure="survival", statistic="features",
                       n=8, n_values=8, mean=0.9 - 0.1 * i, sem=0.02, q05=0, q25=0, q50=0, q75=0, q95=0)
            for i, v in enumerate([0.0, 0.5, 1.0])]
    return report.StudyTable(tool_version="0", scene=SceneRef(name="x", file="x.wd", sha256="0" * 64),
                             study="s", design="grid", factors=factors, seed=0, trials=8, rows=rows)


def test_a_study_plot_over_calibration_sigma_keeps_its_x_label_inside(tmp_path, monkeypatch):
    """Was: the label of calibration_error.sigma cut at the right edge."""
    from wiredsl.scene import MeasureUse, Study
    from wiredsl.study import plots

    plt = plots._pyplot()
    figures = []
    monkeypatch.setattr(plt, "close", figures.append)
    for factors in (["calibration_error.sigma"], ["lateral_shift.range", "calibration_error.sigma"]):
        study = Study(name="s", factors=[{"stage": f.split(".")[0], "param": f.split(".")[1],
                                          "values": [0, 0.5, 1]} for f in factors],
                      measures=[MeasureUse(name="survival")])
        plots.write_all(_table(factors), study, tmp_path)
    assert figures
    for fig in figures:
        texts = [ax.xaxis.label for ax in fig.axes] + [ax.yaxis.label for ax in fig.axes] + [fig._suptitle]
        for box in _boxes(fig, texts):
            assert _inside(fig, box), (box, fig.bbox)


def test_a_grids_one_valued_factor_is_held_in_the_title_not_drawn(tmp_path, monkeypatch):
    """The lab's speed study holds both readouts at 30 ms: a factor of one value gets no panel and no legend
    entry (each was a dot, and every line's label repeated it), and the title says where it is held."""
    from wiredsl.scene import MeasureUse, Study
    from wiredsl.study import plots

    plt = plots._pyplot()
    figures = []
    monkeypatch.setattr(plt, "close", figures.append)
    table = _table(["lateral_shift.range"])
    table = table.model_copy(update={"factors": ["lateral_shift.range", "camera.cam.readout"], "rows": [
        r.model_copy(update={"values": {**r.values, "camera.cam.readout": 0.03}}) for r in table.rows]})
    study = Study(name="s", factors=[{"stage": "lateral_shift", "param": "range", "values": [0, 0.5, 1]},
                                     {"stage": "camera.cam", "param": "readout", "values": [0.03]}],
                  measures=[MeasureUse(name="survival")])
    plots.write_all(table, study, tmp_path)
    (fig,) = figures
    drawn = [ax for ax in fig.axes if ax.axison]
    assert [ax.xaxis.label.get_text().rsplit("\n", 1)[-1] for ax in drawn] == ["lateral_shift.range"]
    assert drawn[0].get_legend() is None
    assert fig._suptitle.get_text().endswith("\nheld at camera.cam.readout=0.03 s")
    assert all(_inside(fig, b) for b in _boxes(fig, [fig._suptitle]))


def _sobol_table():
    from wiredsl.io.features import SceneRef
    from wiredsl.study import report

    sobol = [report.SobolIndex(measure="m", statistic="s", factor=f, first_order=v, total_order=v + 0.1,
                               first_order_ci=(v - 0.1, v + 0.1), total_order_ci=(v, 1.2))
             for f, v in (("lateral_shift.range", 0.68), ("calibration_error.sigma", 0.2))]
    return report.StudyTable(tool_version="0", scene=SceneRef(name="x", file="x.wd", sha256="0" * 64),
                             study="sources", design="sobol", factors=["lateral_shift.range",
                                                                      "calibration_error.sigma"],
                             seed=0, trials=1, rows=[], sobol=sobol)


def test_sobol_titles_apart():
    """Was: the figure's title over the first subplot's title (an index cut at the top limit, annotated)."""
    from wiredsl.study import plots

    plt = plots._pyplot()
    for n in (1, 4, 13):  # 13: the lab's Sobol' study, whose title ran into the second subplot's
        fig = plots.sobol_figure(plt, _sobol_table(), [("m", "s")] * n)
        sup, *titles = _boxes(fig, [fig._suptitle] + [ax.title for ax in fig.axes if ax.axison])
        assert titles and all(not sup.overlaps(t) for t in titles)
        assert all(_inside(fig, b) for b in [sup, *titles])
        plt.close(fig)


def test_the_prediction_plots_ticks_do_not_run_together(tmp_path, monkeypatch):
    """Was: "0.70750.71000.7125" on a narrow range's CDF axis."""
    from wiredsl.verify import predict

    rng = np.random.default_rng(0)  # 0.700 to 0.715: matplotlib's default ticks were 0.6975, 0.7000, ... 0.7175
    real = [{"frame": k, "side": "left", "value": float(0.7 + 0.0149 * rng.random())} for k in range(12)]
    sims = [list(0.7 + 0.0149 * rng.random(20)) for _ in real]
    comparison = {"edge_fraction": {"real": real, "simulated": [v for s in sims for v in s], "_per_image": sims,
                                    "label": "verified fraction", "unit": "",
                                    "ks": {"statistic": 0.2, "p": 0.5}, "mann_whitney": {"p": 0.5}}}
    from wiredsl.study.plots import _pyplot

    plt = _pyplot()
    figures = []
    monkeypatch.setattr(plt, "close", figures.append)
    predict.plot(comparison, tmp_path / "p.png", "caption")
    (fig,) = figures
    cdf = fig.axes[1]
    boxes = _boxes(fig, cdf.get_xticklabels())
    assert len(boxes) >= 3
    boxes.sort(key=lambda b: b.x0)
    assert all(a.x1 < b.x0 for a, b in zip(boxes[:-1], boxes[1:], strict=True)), [(b.x0, b.x1) for b in boxes]
