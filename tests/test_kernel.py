"""The compiled kernel against the numpy path (the readable reference): the same keyed draws give
identical discrete decisions (which strokes, fragments, vertices and corners survive, with their
metadata) and coordinates within 1e-9 px, on every buildable scene, over many trials, for the scene's
own pipelines and for every stage at the paper's values."""

from __future__ import annotations

import numpy as np
import pytest
from test_replay import SCENES, pipelines

from wiredsl.engine.montecarlo import Run
from wiredsl.engine.simulate import Options
from wiredsl.engine.world import build_world
from wiredsl.language.compile import compile_file

DISCRETE = ("start", "fid", "segment", "fragment", "kind", "clipped", "closed", "occluded", "trial", "corner_fid",
            "corner_trial")


def batches(run: Run, engine: str, trials) -> list:
    run.engine = engine
    return [out for _, out in run.batches(trials, 64)]


@pytest.mark.parametrize("path", SCENES)
def test_kernel_and_numpy_agree_on_every_scene_over_many_trials(path):
    scene, _, _ = compile_file(path)
    world = build_world(scene)
    for pipe in pipelines(scene):
        runs = {e: Run.create(scene, world, pipe, 99, Options()) for e in ("numpy", "kernel")}
        got = {e: batches(run, e, range(500, 692)) for e, run in runs.items()}
        assert runs["kernel"].uses_kernel() and not runs["numpy"].uses_kernel()
        worst, strokes = 0.0, 0
        for bn, bk in zip(got["numpy"], got["kernel"], strict=True):
            for (r, dn, _), (_, dk, _) in zip(bn, bk, strict=True):
                assert set(dn) == set(dk)
                for side, a in dn.items():
                    b = dk[side]
                    for name in DISCRETE:
                        assert np.array_equal(getattr(a, name), getattr(b, name)), (path, pipe.name, r.index, side,
                                                                                     name)
                    worst = max(worst, np.abs(a.pts - b.pts).max(initial=0),
                                np.abs(a.corners - b.corners).max(initial=0))
                    strokes += a.n_strokes
        assert strokes > 0 and worst < 1e-9, (path, pipe.name, worst)
        # the manifests' measured statistics agree too (sums in another order: to rounding)
        mn, mk = runs["numpy"].manifest(), runs["kernel"].manifest()
        assert mn["ran"] == mk["ran"]
        for sn, sk in zip(mn["stages"], mk["stages"], strict=True):
            assert sn["effect"] == sk["effect"]
            _close(sn["measured"], sk["measured"])


def _close(a, b):
    if isinstance(a, dict):
        assert set(a) == set(b)
        for k in a:
            _close(a[k], b[k])
    elif isinstance(a, float):
        assert b == pytest.approx(a, rel=1e-9, abs=1e-12)
    else:
        assert a == b
