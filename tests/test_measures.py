"""The measures: a registry-wide battery (declared statistics, finite values, the perfect score on
ideal features, determinism, parameters out of range refused), and survival against the effects'
declared magnitudes."""

from __future__ import annotations

import numpy as np
import pydantic
import pytest
from helpers import compile_text, out_of_range

from wiredsl.engine.simulate import Options
from wiredsl.engine.world import build_world
from wiredsl.language.compile import compile_file
from wiredsl.measures import REGISTRY
from wiredsl.montecarlo import Run

LAB, _, _ = compile_file("scenes/lab.wd")
WORLD = build_world(LAB)
# what each measure reports for features exactly as projected
PERFECT = {"pgh": {"match": 1.0, "recognition": 1.0},
           "stereo3d": {"corner_error": 0.0, "outliers": 0.0},
           "survival": {"features": 1.0, "length": 1.0, "corners": 1.0}}


def pipeline(text: str):
    scene, _ = compile_text(f"wiredsl 1\npipeline p {{\n{text}\n}}\n")
    return scene.pipelines[0]


def run_measure(name: str, pipe, trials: int, poses=(1, 5), seed: int = 4, **params) -> list[dict]:
    m = REGISTRY[name]
    p = m.Params(**params)
    run = Run.create(LAB, WORLD, pipe, seed, Options(poses=poses))
    prep = m.prepare(p, run)
    out = []
    for batch, results in run.batches(list(range(trials))):
        for result, disturbed, _ in results:
            out.append(m.measure(p, prep, result, disturbed, len(batch)))
    return out


def test_every_measure_has_a_perfect_score_here():
    assert set(PERFECT) == set(REGISTRY)


@pytest.mark.parametrize("name", list(REGISTRY))
def test_declared_statistics_come_back_finite_one_per_trial(name):
    m = REGISTRY[name]
    assert set(m.weights) <= set(m.statistics) and set(m.weights.values()) <= set(m.statistics)
    for pipe in (LAB.pipeline("paper"), pipeline("edge_loss fraction 1\ncorner_loss keep 0")):
        for out in run_measure(name, pipe, 3):
            assert set(out) == set(m.statistics)
            for key, v in out.items():
                assert v.shape == (3,) and np.isfinite(v).all(), (key, v)


@pytest.mark.parametrize("name", list(REGISTRY))
def test_ideal_features_get_the_perfect_score(name):
    for out in run_measure(name, None, 2):
        for key, value in PERFECT[name].items():
            assert np.allclose(out[key], value, atol=1e-9), (key, out[key])


@pytest.mark.parametrize("name", list(REGISTRY))
def test_same_input_same_output(name):
    a = run_measure(name, LAB.pipeline("paper"), 2, poses=(3,))
    b = run_measure(name, LAB.pipeline("paper"), 2, poses=(3,))
    for x, y in zip(a, b, strict=True):
        assert all(np.array_equal(x[k], y[k]) for k in x)


@pytest.mark.parametrize("name", list(REGISTRY))
def test_out_of_range_parameters_are_refused(name):
    m = REGISTRY[name]
    m.Params()  # the defaults are in range
    for key, field in m.Params.model_fields.items():
        assert field.description and field.json_schema_extra["kind"]
        for value in out_of_range(field):
            with pytest.raises(pydantic.ValidationError):
                m.Params(**{key: value})
    with pytest.raises(pydantic.ValidationError):
        m.Params(no_such_parameter=1)


def test_survival_follows_the_declared_losses():
    out = run_measure("survival", pipeline("edge_loss fraction 30%\ncorner_loss keep 0.6"), 200, poses=(2,))[0]
    assert out["length"].mean() == pytest.approx(0.7, abs=0.005)  # edge loss removes exactly 30% of each
    assert out["features"].min() == 1.0  # ... as one gap: every feature keeps some part
    assert out["corners"].mean() == pytest.approx(0.6, abs=0.03)
    assert (out["ideal_corners"] > 0).all()


def test_when_everything_is_lost_the_placeholders_are_the_documented_ones():
    lost = pipeline("edge_loss fraction 1\ncorner_loss keep 0")
    for out in run_measure("pgh", lost, 2):
        assert all((v == 0).all() for k, v in out.items() if k != "viewpoint_cameras")
        assert (out["viewpoint_cameras"] > 0).all()  # a weight: the cameras that had a mesh to rank
    for out in run_measure("stereo3d", lost, 2):
        assert all((v == 0).all() for v in out.values())  # errors are 0 with weight (points) 0
    for out in run_measure("survival", lost, 2):
        assert (out["features"] == 0).all() and (out["length"] == 0).all() and (out["corners"] == 0).all()
        assert (out["ideal_features"] > 0).all()


def test_finite_from_anywhere_in_the_room_even_inside_furniture():
    """Random poses over the whole room (some inside the bins and the cabinet), every measure finite."""
    rng = np.random.default_rng(13)
    poses = [(float(x), float(y), float(h)) for x, y, h in
             zip(rng.uniform(-0.5, 6.5, 8), rng.uniform(-0.5, 5.5, 8), rng.uniform(-np.pi, np.pi, 8), strict=True)]
    poses += [(4.6, 3.2, 0.3), (5.2, 1.1, 2.0)]  # the bins' centres
    scene = LAB.model_copy(update={"path": LAB.path.model_copy(update={"poses": poses})})
    run = Run.create(scene, WORLD, LAB.pipeline("paper"), 2, Options(visibility="all"))
    for name, m in REGISTRY.items():
        p = m.Params(**({"viewpoints": 2} if name == "pgh" else {}))
        prep = m.prepare(p, run)
        for batch, results in run.batches([0, 1]):
            for result, disturbed, _ in results:
                out = m.measure(p, prep, result, disturbed, len(batch))
                assert all(v.shape == (2,) and np.isfinite(v).all() for v in out.values()), (name, result.pose)


def test_every_statistic_declares_its_unit():
    """Plots label their axes with them (stereo3d's errors are metres)."""
    for name, m in REGISTRY.items():
        assert set(m.units) == set(m.statistics), name
        assert set(m.units.values()) <= {"m", "px", "count", "fraction"}, name
    assert REGISTRY["stereo3d"].units["error_median"] == "m"
