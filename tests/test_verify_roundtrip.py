"""The round trip (issue 24, item 5): a scene's features disturbed by the engine with known parameters, drawn
by `wiredsl render` (step edges with a band wider than the shifts, no faces, corner marks; blur and noise
varied) at 640 x 480, detected (Canny, Harris), verified and fitted. The fitted parameters must hold the injected ones
within their
95% intervals in at least 90% of 30 random settings (27 of 30), each parameter on its own."""

from __future__ import annotations

import numpy as np

import wiredsl
from wiredsl.io import render
from wiredsl.scene import Pipeline, Stage
from wiredsl.verify import command

FENCE = "tests/data/verify/fence.wd"
SETTINGS = 30
KEYS = ("edge_loss.fraction", "lateral_shift.range", "corner_loss.keep", "corner_error.sigma",
        "corner_mismatch.fraction")


def _setting(rng):
    truth = {"edge_loss.fraction": rng.uniform(0.1, 0.4), "lateral_shift.range": rng.uniform(0.5, 3.0),
             "corner_loss.keep": rng.uniform(0.6, 0.95), "corner_mismatch.fraction": rng.uniform(0.05, 0.3),
             "corner_mismatch.radius": rng.uniform(6, 10), "corner_error.sigma": rng.uniform(0.3, 1.0)}
    return truth, rng.uniform(0.6, 1.5), rng.uniform(0, 4), int(rng.integers(1 << 30))


def test_fitted_parameters_recover_the_injected_ones(tmp_path):
    scene = wiredsl.compile(FENCE)
    rng = np.random.default_rng(2024)
    hits = dict.fromkeys(KEYS, 0)
    misses = []
    for i in range(SETTINGS):
        truth, blur, noise, seed = _setting(rng)
        pipe = Pipeline(name="injected", stages=[
            Stage(effect="edge_loss", params={"fraction": truth["edge_loss.fraction"]}),
            Stage(effect="lateral_shift", params={"range": truth["lateral_shift.range"]}),
            Stage(effect="corner_loss", params={"keep": truth["corner_loss.keep"]}),
            Stage(effect="corner_error", params={"sigma": truth["corner_error.sigma"]}),
            Stage(effect="corner_mismatch", params={"fraction": truth["corner_mismatch.fraction"],
                                                    "radius": truth["corner_mismatch.radius"]})])
        folder = tmp_path / f"s{i}"
        look = render.Look(blur=blur, noise=noise, edges="step", width=12, faces="none", corners="mark",
                           background=190, ink=70, mark=8)
        render.write(folder / "img", scene, pipeline=pipe, seed=seed, look=look)
        req = command.Request(FENCE, [(str(folder / "img" / "*.png"), None)], ["canny", "harris"], fit=True, seed=i)
        fit = command.run(req, folder / "out").fit
        for key in KEYS:
            e = fit.get(key)
            ok = e.lo is not None and e.lo <= truth[key] <= e.hi
            hits[key] += ok
            if not ok:
                misses.append(f"setting {i} (blur {blur:.2f}, noise {noise:.1f}): {key} {truth[key]:.3f} not in "
                              f"[{e.lo}, {e.hi}] (fitted {e.value})")
    print("\n".join(misses))
    print({k: f"{v}/{SETTINGS}" for k, v in hits.items()})
    assert all(v >= 0.9 * SETTINGS for v in hits.values()), (hits, misses)


def test_the_coverage_harness_round_trips_ellipses_silhouettes_and_nothing_injected():
    """Issue 34 item 6, CI-sized: the first two settings of benchmarks/roundtrip_coverage.py (the fence with
    corners, and four cylinders: ellipses and silhouettes), each edge parameter injected or left at 0, rendered
    with blur and noise, verified and fitted. The fence's 95% intervals hold every injected value. The
    cylinders' do not yet all (measured at full size, 40 settings, in the script's table): there the fit is held
    to its measured closeness, edge loss within 0.03 and approx_error, injected at 0, under 0.15 px."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "roundtrip_coverage.py"
    spec = importlib.util.spec_from_file_location("roundtrip_coverage", path)
    rc = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(rc)
    fence, cylinders = rc.coverage(2, 2034)
    assert (fence["scene"], cylinders["scene"]) == ("fence", "cylinders")
    assert all(rc.held(row) for row in fence["rows"].values()), fence["rows"]
    t, v, _, _ = cylinders["rows"]["edge_loss.fraction"]
    assert abs(v - t) < 0.03, cylinders["rows"]
    t, v, _, _ = cylinders["rows"]["approx_error.sigma"]
    assert t == 0 and v < 0.15, cylinders["rows"]
    text = rc.table([fence, cylinders])
    assert all(k in text for k in rc.EDGE_KEYS + rc.CORNER_KEYS)
