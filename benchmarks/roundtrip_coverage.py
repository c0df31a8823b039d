"""The round trip's coverage (issue 34): random settings of the effects injected into generated scenes, drawn by
`wiredsl render` with blur and noise varied, detected (Canny, and Harris where there are corners), verified and
fitted; for each fitted parameter, the share of settings whose 95% interval holds the injected value, and with
nothing injected (a parameter left at 0 in about a third of the settings), the share whose interval holds 0.

    python benchmarks/roundtrip_coverage.py [--settings 40] [--seed 2034]

Scenes: tests/data/verify/fence.wd (isolated lines and corner marks: step edges 12 px wide, no faces) and
tests/data/verify/cylinders.wd (four cylinders: ellipses whole and half hidden, silhouettes; no faces, whose
outlines are edges no pipeline disturbs, and 4 px step edges), alternately. A setting's draws are keyed by
the run's seed and its index: the same arguments print the same table. tests/test_verify_roundtrip.py runs a
few settings of it.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCENES = {"fence": "tests/data/verify/fence.wd", "cylinders": "tests/data/verify/cylinders.wd"}
EDGE_KEYS = ("edge_loss.fraction", "lateral_shift.range", "approx_error.sigma")
CORNER_KEYS = ("corner_loss.keep", "corner_error.sigma", "corner_mismatch.fraction")
OFF = 1 / 3  # the share of settings in which each edge parameter is left at 0 (nothing injected)


def setting(rng, scene: str) -> tuple[dict, float, float, int]:
    """(injected values by parameter, blur px, noise grey levels, render seed) of one setting."""
    shift_top = 3.0 if scene == "fence" else 1.5  # the cylinders' bands are 4 px wide: shifts stay inside them
    truth = {"edge_loss.fraction": rng.uniform(0.1, 0.4), "lateral_shift.range": rng.uniform(0.5, shift_top),
             "approx_error.sigma": rng.uniform(0.1, 0.6)}
    for key in EDGE_KEYS:
        if rng.random() < OFF:
            truth[key] = 0.0
    if scene == "fence":
        truth |= {"corner_loss.keep": rng.uniform(0.6, 0.95), "corner_mismatch.fraction": rng.uniform(0.05, 0.3),
                  "corner_mismatch.radius": rng.uniform(6, 10), "corner_error.sigma": rng.uniform(0.3, 1.0)}
    return truth, float(rng.uniform(0.6, 1.5)), float(rng.uniform(0, 4)), int(rng.integers(1 << 30))


def run_setting(i: int, scene: str, truth: dict, blur: float, noise: float, seed: int, folder: Path) -> dict:
    """{parameter: (injected, fitted, lo, hi)} of one setting."""
    sys.path.insert(0, str(ROOT))
    import wiredsl
    from wiredsl.io import render
    from wiredsl.scene import Pipeline, Stage
    from wiredsl.verify import command

    stages = [Stage(effect="edge_loss", params={"fraction": truth["edge_loss.fraction"]}),
              Stage(effect="lateral_shift", params={"range": truth["lateral_shift.range"]}),
              Stage(effect="approx_error", params={"sigma": truth["approx_error.sigma"]})]
    if scene == "fence":
        stages += [Stage(effect="corner_loss", params={"keep": truth["corner_loss.keep"]}),
                   Stage(effect="corner_error", params={"sigma": truth["corner_error.sigma"]}),
                   Stage(effect="corner_mismatch", params={"fraction": truth["corner_mismatch.fraction"],
                                                           "radius": truth["corner_mismatch.radius"]})]
        look = render.Look(blur=blur, noise=noise, edges="step", width=12, faces="none", corners="mark",
                           background=190, ink=70, mark=8)
        detectors = ["canny", "harris"]
    else:
        look = render.Look(blur=blur, noise=noise, edges="step", width=4, faces="none")
        detectors = ["canny"]
    path = str(ROOT / SCENES[scene])
    render.write(folder / "img", wiredsl.compile(path), pipeline=Pipeline(name="injected", stages=stages),
                 seed=seed, look=look)
    req = command.Request(path, [(str(folder / "img" / "*.png"), None)], detectors, fit=True, seed=i)
    fit = command.run(req, folder / "out").fit
    out = {}
    for key in EDGE_KEYS + (CORNER_KEYS if scene == "fence" else ()):
        e = fit.get(key)
        out[key] = (truth[key], e.value, e.lo, e.hi)
    return out


def held(row) -> bool:
    t, _, lo, hi = row
    return lo is not None and hi is not None and lo - 1e-12 <= t <= hi + 1e-12


def coverage(n: int, seed: int, scenes=("fence", "cylinders"), progress=None) -> list[dict]:
    """Every setting's rows: {scene, blur, noise, rows {parameter: (injected, fitted, lo, hi)}}."""
    results = []
    with tempfile.TemporaryDirectory() as d:
        for i in range(n):
            scene = scenes[i % len(scenes)]
            rng = np.random.default_rng([seed, i])
            truth, blur, noise, rseed = setting(rng, scene)
            rows = run_setting(i, scene, truth, blur, noise, rseed, Path(d) / f"s{i}")
            results.append({"scene": scene, "blur": blur, "noise": noise, "rows": rows})
            if progress is not None:
                progress(i, results[-1])
    return results


def table(results: list[dict]) -> str:
    keys = list(dict.fromkeys(k for r in results for k in r["rows"]))
    lines = ["| parameter | settings | interval holds the injected value | of them injected 0: interval holds 0 |",
             "|---|---|---|---|"]
    for key in keys:
        rows = [r["rows"][key] for r in results if key in r["rows"]]
        zero = [row for row in rows if row[0] == 0]
        z = f"{sum(map(held, zero))}/{len(zero)}" if zero else "-"
        lines.append(f"| {key} | {len(rows)} | {sum(map(held, rows))}/{len(rows)} "
                     f"({100 * sum(map(held, rows)) / len(rows):.0f}%) | {z} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--settings", type=int, default=40)
    ap.add_argument("--seed", type=int, default=2034)
    args = ap.parse_args()

    def show(i, r):
        misses = [f"{k} {t:.3g} not in [{lo}, {hi}] (fitted {v})" for k, (t, v, lo, hi) in r["rows"].items()
                  if not held((t, v, lo, hi))]
        print(f"setting {i} {r['scene']} blur {r['blur']:.2f} noise {r['noise']:.1f}: "
              + ("; ".join(misses) or "all held"), file=sys.stderr, flush=True)

    results = coverage(args.settings, args.seed, progress=show)
    print(table(results))


if __name__ == "__main__":
    main()
