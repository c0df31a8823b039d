"""Round trip of the spreads between images and the correlation along a path (issue 34, item 2).

    python benchmarks/variation_roundtrip.py [SETTINGS] [SEED]

Each setting draws an edge loss, a lateral shift range and a corner keep, each with a spread between views
(zero in about a third of the settings, so that the "nothing injected, nothing found" half is tested too), and
a correlation along the path (0, or 0.1-0.4 m); renders the fence (tests/data/verify/fence.wd) along a straight
path of FRAMES poses 5 cm apart with blur and noise varied (wiredsl render's step edges), verifies it with Canny
and Harris, fits (`verify --fit`), and checks whether each fitted 95% interval holds the injected value. Prints
the coverage table: per parameter, the settings whose interval holds the injected spread, and of the settings
with none injected, those where none was found (the interval reaches 0). Defaults: 40 settings, seed 2026.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

FRAMES = 16
STAGES = ("edge_loss", "lateral_shift", "corner_loss")


def scene_text(frames: int = FRAMES) -> str:
    """The fence, walked straight at it in `frames` poses 5 cm apart."""
    text = (ROOT / "tests/data/verify/fence.wd").read_text()
    head, _, rest = text.partition("path walk {")
    _, _, tail = rest.partition("}")
    return head + f"path walk {{\n  straight from (0, 0) to ({0.05 * (frames - 1):.2f}, 0) step 0.05m\n}}" + tail


def setting(rng: np.random.Generator) -> dict:
    """Injected values: {stage: (value, spread, correlation)}, blur, noise, seed."""
    corr = 0.0 if rng.random() < 0.3 else float(rng.uniform(0.1, 0.4))
    none = rng.random() < 0.35
    f = float(rng.uniform(0.15, 0.35))
    r = float(rng.uniform(1.0, 3.0))
    k = float(rng.uniform(0.65, 0.9))
    return {"edge_loss": (f, 0.0 if none else float(rng.uniform(0.03, 0.08)), corr),
            "lateral_shift": (r, 0.0 if none else float(rng.uniform(0.2, 0.6)), corr),
            "corner_loss": (k, 0.0 if none else float(rng.uniform(0.04, 0.1)), corr),
            "blur": float(rng.uniform(0.6, 1.4)), "noise": float(rng.uniform(0, 3)),
            "seed": int(rng.integers(1 << 30))}


def run_setting(s: dict, folder: Path, index: int) -> dict:
    """The fitted spreads and correlations: {stage: (Estimate of spread, Estimate of correlation)}."""
    import wiredsl
    from wiredsl.io import render
    from wiredsl.scene import Pipeline, Stage
    from wiredsl.verify import command

    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "fence_path.wd"
    path.write_text(scene_text())
    scene = wiredsl.compile(str(path))
    keys = {"edge_loss": "fraction", "lateral_shift": "range", "corner_loss": "keep"}
    pipe = Pipeline(name="injected", stages=[
        Stage(effect=st, params={keys[st]: s[st][0], "spread": s[st][1], "correlation": s[st][2]})
        for st in STAGES])
    look = render.Look(blur=s["blur"], noise=s["noise"], edges="step", width=12, faces="none", corners="mark",
                       background=190, ink=70, mark=8)
    render.write(folder / "img", scene, pipeline=pipe, seed=s["seed"], look=look)
    req = command.Request(str(path), [(str(folder / "img" / "*.png"), None)], ["canny", "harris"], fit=True,
                          seed=index)
    fit = command.run(req, folder / "out").fit
    return {st: (fit.get(f"{st}.spread"), fit.get(f"{st}.correlation")) for st in STAGES}


def covers(e, truth: float) -> bool:
    return e.value is not None and e.lo is not None and e.lo - 1e-12 <= truth <= e.hi + 1e-12


def main(settings: int = 40, seed: int = 2026) -> dict:
    rng = np.random.default_rng(seed)
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for i in range(settings):
            s = setting(rng)
            got = run_setting(s, Path(d) / f"s{i}", i)
            rows.append((s, got))
            line = "; ".join(f"{st} spread {s[st][1]:.3g} -> {_fmt(got[st][0])}" for st in STAGES)
            print(f"setting {i}: corr {s['edge_loss'][2]:.2f} m; {line}", file=sys.stderr, flush=True)
    table = {}
    print("| parameter | injected > 0: interval holds it | none injected: none found | correlation > 0: "
          "interval holds it |")
    print("|---|---|---|---|")
    for st in STAGES:
        some = [(s, g) for s, g in rows if s[st][1] > 0]
        none = [(s, g) for s, g in rows if s[st][1] == 0]
        held = sum(covers(g[st][0], s[st][1]) for s, g in some)
        clean = sum(g[st][0].value is None or (g[st][0].lo or 0) <= 0 for s, g in none)
        cor = [(s, g) for s, g in some if s[st][2] > 0 and g[st][1].value is not None]
        cheld = sum(covers(g[st][1], s[st][2]) for s, g in cor)
        table[st] = {"held": held, "of": len(some), "clean": clean, "of_none": len(none), "corr_held": cheld,
                     "corr_of": len(cor)}
        print(f"| {st}.spread | {held} of {len(some)} | {clean} of {len(none)} | {cheld} of {len(cor)} |")
    return table


def _fmt(e) -> str:
    return "n/a" if e.value is None else f"{e.value:.3g} [{e.lo:.3g}, {e.hi:.3g}]"


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:3]))
