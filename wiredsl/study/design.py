"""A study's design points, each point's seed and pipeline, and Sobol' indices of a space-filling design.

Space-filling designs (lhs, sobol) use Saltelli's pick-freeze layout so that first-order and total
Sobol' indices come out of the same runs: two base matrices A and B of n samples over the d factors
(the halves of one 2d-dimensional Sobol' or Latin hypercube sample), then AB_i = A with column i taken
from B. The design's points are the rows of A, B, AB_1, ..., AB_d, in that order: n (d + 2) points.
"""

from __future__ import annotations

import itertools
import warnings

import numpy as np

from wiredsl.effects import REGISTRY
from wiredsl.scene import Pipeline, Scene, Study


def matrix(study: Study) -> np.ndarray:
    """The design points, shape (n_points, n_factors), in the factors' SI units.

    A study without factors (a grid of none) has one point: the pipeline as declared."""
    d = len(study.factors)
    if study.design == "grid":
        points = list(itertools.product(*(f.values for f in study.factors)))  # no factors: one point, ()
        return np.array(points, dtype=float).reshape(len(points), d)
    n = study.points
    from scipy.stats import qmc

    if study.design == "sobol":
        with warnings.catch_warnings():  # scipy warns when n is not a power of 2: the balance is merely weaker
            warnings.simplefilter("ignore", UserWarning)
            u = qmc.Sobol(2 * d, scramble=True, rng=np.random.default_rng(study.design_seed)).random(n)
    else:
        u = qmc.LatinHypercube(2 * d, rng=np.random.default_rng(study.design_seed)).random(n)
    lo = np.array([f.low for f in study.factors])
    hi = np.array([f.high for f in study.factors])
    A, B = lo + u[:, :d] * (hi - lo), lo + u[:, d:] * (hi - lo)
    AB = [np.where(np.arange(d) == i, B, A) for i in range(d)]
    return np.concatenate([A, B, *AB])


def pipeline_at(scene: Scene, study: Study, values: np.ndarray) -> Pipeline:
    """The study's pipeline with one design point's values substituted; stages it lacks are inserted at
    their data-flow position, with default parameters for what the study does not vary."""
    base = scene.pipeline(study.pipeline) if study.pipeline else None
    stages = {s.effect: dict(s.params) for s in (base.stages if base else [])}
    order = [s.effect for s in (base.stages if base else [])]
    for f, v in zip(study.factors, values, strict=True):
        if f.stage.startswith("camera.") or f.stage in SCENE_FACTORS:
            continue
        if f.stage not in stages:
            stages[f.stage] = {}
            rank = REGISTRY[f.stage].flow_rank()
            at = next((i for i, name in enumerate(order) if REGISTRY[name].flow_rank() > rank), len(order))
            order.insert(at, f.stage)
        stages[f.stage][f.param] = float(v)
    return Pipeline(name=f"{study.name}", stages=[{"effect": e, "params": REGISTRY[e].Params(**stages[e]).model_dump()}
                                                  for e in order])


def sobol_indices(y: np.ndarray, n: int, d: int, seed: int = 0,
                  resamples: int = 199) -> dict[str, np.ndarray] | None:
    """First-order and total Sobol' indices of outputs y (n (d + 2) values in the design's order), with
    bootstrap 95% intervals: scipy.stats.sobol_indices (Saltelli 2010 first order, Jansen 1999 total).

    None when y does not vary over A and B (the indices divide by that variance: they are undefined).
    """
    from scipy.stats import sobol_indices as scipy_sobol

    y = np.asarray(y, dtype=float)
    f_A, f_B = y[:n][None], y[n:2 * n][None]
    base = y[:2 * n]
    if not np.ptp(base) > 1e-12 * np.abs(base).max(initial=0.0):
        return None
    f_AB = y[2 * n:].reshape(d, 1, n)
    if d == 1:  # scipy fails for one factor; a copy of it as a second factor leaves its indices as they are
        f_AB = np.concatenate([f_AB, f_AB])
    res = scipy_sobol(func={"f_A": f_A, "f_B": f_B, "f_AB": f_AB}, n=n, rng=np.random.default_rng(seed))
    out = {"first_order": np.atleast_1d(res.first_order)[:d], "total_order": np.atleast_1d(res.total_order)[:d]}
    if n >= 4 and resamples > 0:
        # scipy's SobolResult.bootstrap draws its resamples from numpy's global RandomState (it passes no rng on):
        # seeded here from `seed` and restored after, so that the intervals are the same on every run
        state = np.random.get_state()
        try:
            np.random.seed(seed)
            with warnings.catch_warnings():  # resamples of (nearly) constant values: NaN bounds, dropped by callers
                warnings.simplefilter("ignore", RuntimeWarning)
                ci = res.bootstrap(confidence_level=0.95, n_resamples=resamples)
        finally:
            np.random.set_state(state)
        out["first_order_ci"] = np.stack([np.atleast_1d(ci.first_order.confidence_interval.low),
                                          np.atleast_1d(ci.first_order.confidence_interval.high)])[:, :d]
        out["total_order_ci"] = np.stack([np.atleast_1d(ci.total_order.confidence_interval.low),
                                          np.atleast_1d(ci.total_order.confidence_interval.high)])[:, :d]
    return out


SCENE_FACTORS = ("path", "rig")  # `path.speed`, `rig.sync`: factors of the robot's motion, in the scene


def varies_scene(study: Study) -> bool:
    """True when a factor changes the scene itself (a camera, the path's speed, the rig's sync), not only the
    pipeline."""
    return any(f.stage.startswith("camera.") or f.stage in SCENE_FACTORS for f in study.factors)


def scene_at(scene: Scene, study: Study, values: np.ndarray) -> Scene:
    """The scene with one design point's camera factors substituted (`k` is TINA's: k1 = -k), and its motion's:
    `path.speed` times the written poses (each pose's distance along the path over the speed), `rig.sync` sets
    the offset."""
    updates: dict[str, dict[str, float]] = {}
    scene_updates: dict = {}
    for f, v in zip(study.factors, values, strict=True):
        if f.stage.startswith("camera."):
            name = f.stage.split(".", 1)[1]
            key, value = ("k1", -float(v)) if f.param == "k" else (f.param, float(v))
            updates.setdefault(name, {})[key] = value
        elif f.stage == "path":
            scene_updates["path"] = scene.path.timed(float(v))
        elif f.stage == "rig":
            scene_updates["rig"] = scene.rig.model_copy(update={"sync": float(v)})
    if updates:
        scene_updates["cameras"] = [c.model_copy(update=updates[c.name]) if c.name in updates else c
                                    for c in scene.cameras]
    return scene.model_copy(update=scene_updates) if scene_updates else scene
