"""`wiredsl verify --fit --predict` (issue 24, item 7): the fence scene drawn by `wiredsl render` with known
disturbances (25% edge loss, 3 px lateral shift, 80% corner keep, 20% corner mismatches within 8 px), detected
with Canny and Harris, fitted, and simulated with the fitted pipeline. The simulation must predict the real
(rendered and detected) measures: no two-sample test below p 0.01 (everything is seeded, so the p-values are
fixed numbers, between 0.28 and 0.92 when this was written). A pipeline without the lateral shift must be told
apart from the 3 px rendered, and an ideal simulation must triangulate the model's corners exactly."""

from __future__ import annotations

import json

import numpy as np
import pytest

import wiredsl
from wiredsl.scene import Pipeline, Stage
from wiredsl.verify import command, predict

pytest.importorskip("cv2")
pytest.importorskip("matplotlib")

FENCE = "tests/data/verify/fence.wd"
INJECTED = Pipeline(name="injected", stages=[
    Stage(effect="edge_loss", params={"fraction": 0.25}), Stage(effect="lateral_shift", params={"range": 3.0}),
    Stage(effect="corner_loss", params={"keep": 0.8}),
    Stage(effect="corner_mismatch", params={"fraction": 0.2, "radius": 8.0})])


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    from wiredsl.io import render

    folder = tmp_path_factory.mktemp("predict")
    look = render.Look(blur=1.0, noise=2.0, edges="step", width=12, faces="none", corners="mark", background=190,
                       ink=70, mark=8)
    render.write(folder / "img", wiredsl.compile(FENCE), pipeline=INJECTED, seed=3, look=look)
    return folder


def _run(folder, name, **kw):
    req = command.Request(FENCE, [(str(folder / "img" / "*.png"), None)], ["canny", "harris"], fit=True,
                          predict=True, trials=20, edge_loss="raw", seed=1, **kw)
    return command.run(req, folder / name)


def test_the_fitted_pipeline_predicts_the_rendered_detector(images):
    out = _run(images, "fitted")
    assert {"prediction.json", "prediction.png"} <= set(out.written)
    doc = json.loads((images / "fitted" / "prediction.json").read_text())
    for key, e in doc["measures"].items():
        assert len(e["real"]) == (5 if key in predict.PAIR else 10), key  # 5 stereo pairs
        assert len(e["simulated"]) >= 15 * len(e["real"]), key
        assert e["ks"]["p"] > 0.01 and e["mann_whitney"]["p"] > 0.01, (key, e["ks"], e["mann_whitney"])
        assert 0.2 < e["rank_mean"] < 0.8, key  # image by image, the real value is not beyond its trials
    v = doc["measures"]["verified_fraction"]
    assert abs(v["real_mean"] - v["simulated_mean"]) < 0.01
    assert abs(v["real_mean"] - 0.75 * 0.96) < 0.03  # the rendered loss, and Canny's own at the gaps' ends
    again = _run(images, "again")
    assert (images / "again" / "prediction.json").read_bytes() == (images / "fitted" / "prediction.json").read_bytes()
    assert again.prediction["offset_rms_px"]["real_mean"] == out.prediction["offset_rms_px"]["real_mean"]


def test_a_wrong_pipeline_is_told_apart(images):
    no_shift = Pipeline(name="no_shift", stages=[s for s in INJECTED.stages if s.effect != "lateral_shift"])
    e = _run(images, "no_shift", predict_pipeline=no_shift).prediction
    off = e["offset_rms_px"]
    assert off["simulated_mean"] < 0.3 < 1.0 < off["real_mean"]  # a 3 px uniform shift: RMS about 1.7 px
    assert off["ks"]["p"] < 1e-6 and off["mann_whitney"]["p"] < 1e-6
    assert off["rank_mean"] == 1.0  # every real image lies above all its trials
    # without the shift the simulated verification keeps what edge_loss kept (the injected 75%); the rendered
    # images, through Canny, lose its ~1 px at each end of each gap too, which the fitted (raw) loss absorbs
    assert abs(e["verified_fraction"]["simulated_mean"] - 0.75) < 0.01


def test_an_ideal_simulation_triangulates_the_model_corners(images):
    e = _run(images, "ideal", predict_pipeline=Pipeline(name="ideal", stages=[])).prediction
    for key in predict.PAIR:
        sim = np.array(e[key]["simulated"])
        assert len(sim) == 5 * 20 and sim.max() < 1e-6, key  # mm: DLT on exact projections recovers the corners
    assert e["verified_fraction"]["simulated_mean"] > 0.99
    assert e["corner_error_3d"]["ks"]["p"] < 1e-6  # the rendered mismatches are not there


def test_the_shape_error_ignores_a_rigid_motion_and_sees_a_distortion():
    """Kabsch's residual: zero for the model moved rigidly (any rotation, any translation), the plain RMS's
    lower bound, the same under a rigid motion of the noisy points; a scaling (not rigid) is not fitted away."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    T = rng.uniform(-0.2, 0.2, (40, 3))
    for seed in range(20):
        rot = Rotation.random(random_state=seed)
        move = rng.normal(0, 0.5, 3)
        assert predict.shape_error_mm(rot.apply(T) + move, T) < 1e-9
        X = T + rng.normal(0, 1e-3, T.shape)
        shape = predict.shape_error_mm(X, T)
        assert shape <= predict._rms_mm(X - T) + 1e-12
        assert predict.shape_error_mm(rot.apply(X) + move, T) == pytest.approx(shape, rel=1e-9)
    assert predict.shape_error_mm(1.01 * T, T) == pytest.approx(0.01 * predict._rms_mm(T - T.mean(0)), rel=1e-6)
    assert predict.shape_error_mm(T[:2], T[:2]) is None
    line = np.outer(np.arange(5.0), [1.0, 2.0, 0.5])
    assert predict.shape_error_mm(line, line) is None


def test_the_command_line_predicts_with_a_named_pipeline_and_refuses_an_unknown_one(images):
    """`--predict-pipeline NAME` simulates the scene's pipeline instead of the fitted one (fence.wd's `injected`:
    the one the images were drawn with); a name the scene lacks is a usage error before any image is read."""
    from click.testing import CliRunner

    from wiredsl.cli import main

    args = ["verify", FENCE, "--images", str(images / "img" / "*.png"), "--detector", "canny", "--fit", "--predict",
            "--trials", "5"]
    r = CliRunner().invoke(main, [*args, "--predict-pipeline", "nosuch", "-o", str(images / "named_bad")])
    assert r.exit_code == 2 and "no pipeline 'nosuch' (it has: injected" in r.output, r.output
    assert not (images / "named_bad").exists()
    r = CliRunner().invoke(main, [*args, "--predict-pipeline", "injected", "-o", str(images / "named")])
    assert r.exit_code == 0, r.output
    doc = json.loads((images / "named" / "prediction.json").read_text())
    assert doc["pipeline"] == "injected" and [s["effect"] for s in doc["stages"]] == [
        "edge_loss", "lateral_shift", "corner_loss", "corner_mismatch"]
    r = CliRunner().invoke(main, ["verify", FENCE, "--images", "x.png", "--detector", "canny",
                                  "--predict-pipeline", "injected", "-o", str(images / "no_predict")])
    assert r.exit_code == 2 and "needs --predict" in r.output


def test_a_run_publishes_its_files_together_and_a_failed_one_leaves_the_folder_as_it_was(images, monkeypatch):
    """verify writes into a staging folder and moves its files into -o at the end: a failure in the fit leaves an
    earlier run's files byte for byte (no new table beside an old fit), and a run without --fit or --predict
    removes the earlier fit and prediction (stale beside its new table); other files in -o are left alone."""
    from wiredsl.verify import fit as fitting

    out = images / "staged"
    first = _run(images, "staged")  # --fit --predict
    (out / "notes.txt").write_text("mine")
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert {"fit.json", "prediction.json", "measured.wd", "verification.csv"} <= set(before)

    def broken(*a, **k):
        raise RuntimeError("the fit failed")

    monkeypatch.setattr(fitting, "fit", broken)
    canny = command.Request(FENCE, [(str(images / "img" / "*.png"), None)], ["canny"], fit=True, seed=1)
    with pytest.raises(RuntimeError, match="the fit failed"):  # (its table, Canny's alone, would differ)
        command.run(canny, out)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # nothing new, nothing left behind
    monkeypatch.undo()
    req = command.Request(FENCE, [(str(images / "img" / "*.png"), None)], ["canny", "harris"], seed=1)
    again = command.run(req, out)
    assert set(again.written) == {"verification.csv", "verification.json", "figure7.png"}
    assert {p.name for p in out.iterdir()} == {*again.written, "notes.txt"}
    assert first.written and (out / "notes.txt").read_text() == "mine"


def test_the_background_term_gives_whole_runs_offsets_uniform_over_the_band():
    """Issue 34: the fit's shift mixture takes a share of the fragments as edges the model does not name, offsets
    uniform over the band; the prediction simulates that share. Oracle: with share 1 each run's offsets are one
    value, and over many runs their RMS is the uniform's, (band + 0.5) / sqrt(3); share 0 changes nothing; the
    same key gives the same draws."""
    from wiredsl.verify import verification as ver

    n_runs, per = 4000, 6
    stroke = np.repeat(np.arange(n_runs), per)
    s = np.tile(np.arange(per, dtype=float), n_runs)
    sm = ver.Samples(np.zeros((len(s), 2)), np.tile([0.0, 1.0], (len(s), 1)), stroke, s, np.full(n_runs, per))
    verified = np.ones(len(s), bool)
    m = ver.EdgeMatch(verified, verified, np.zeros(len(s)))
    got = predict.with_background(sm, m, 1.0, 6.0, np.random.default_rng(1))
    per_run = got.offset.reshape(n_runs, per)
    assert np.all(per_run == per_run[:, :1])
    assert np.sqrt(np.mean(per_run[:, 0] ** 2)) == pytest.approx(6.5 / np.sqrt(3), rel=0.03)
    assert np.abs(per_run).max() <= 6.5
    assert np.array_equal(predict.with_background(sm, m, 0.0, 6.0, np.random.default_rng(1)).offset, m.offset)
    again = predict.with_background(sm, m, 0.3, 6.0, np.random.default_rng(7)).offset
    assert np.array_equal(again, predict.with_background(sm, m, 0.3, 6.0, np.random.default_rng(7)).offset)
    assert abs(np.mean(again.reshape(n_runs, per)[:, 0] != 0) - 0.3) < 0.03
