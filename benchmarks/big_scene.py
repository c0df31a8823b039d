"""A scene k times the lab (k copies of every placement of scenes/lab.wd, spread over the room), generated
here: the ideal build's time against its feature count for k = 1, 2, 5, 10 (target: growth at most
linear), and the peak resident memory of 1,000 `paper` trials of the 10x scene streamed to npz through the
command line, measured as that child process's peak RSS (target: < 250 MB).

    OMP_NUM_THREADS=1 python benchmarks/big_scene.py [--scales 1 2 5 10] [--trials 1000] [--rounds 3]
    python benchmarks/big_scene.py --memory-only   # the 10x scene's trials alone
"""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, os.path.dirname(__file__))

from _cli import lab_folder, load, wiredsl  # noqa: E402

PLACE = re.compile(r"^place (\w+) as (\w+)(?: at \(([^)]*)\))?(.*)$")


def scaled_lab(k: int) -> str:
    """scenes/lab.wd with k copies of every placement, each copy shifted by up to about a metre."""
    out = []
    for line in Path("scenes/lab.wd").read_text(encoding="utf-8").splitlines():
        m = PLACE.match(line)
        if not m:
            out.append(line)
            continue
        model, name, at, rest = m.groups()
        x, y, z = (at or "0m, 0m, 0").split(",")
        for j in range(k):
            # a spiral of offsets: copies overlap little and stay around the room
            r, a = 0.35 * math.sqrt(j), 2.4 * j
            dx, dy = r * math.cos(a), r * math.sin(a)
            out.append(f"place {model} as {name}{'' if j == 0 else f'_{j}'} at "
                       f"({_m(x) + dx:.4f}m, {_m(y) + dy:.4f}m, {z.strip()}){rest}")
    return "\n".join(out) + "\n"


def _m(text: str) -> float:
    text = text.strip()
    return float(text[:-1]) if text.endswith("m") else float(text)


def ideal_build(path: Path) -> tuple[float, float, float, int, int]:
    """Seconds to compile, build the world, compute the view-point lists and project every pose (best of
    rounds), as (visibility, projection, total) and the world's and the views' feature counts."""
    from wiredsl.engine.simulate import Options, simulate, visibility_masks
    from wiredsl.engine.world import build_world
    from wiredsl.language.compile import compile_file

    t0 = time.perf_counter()
    scene, _, _ = compile_file(str(path))
    world = build_world(scene)
    t1 = time.perf_counter()
    vis = visibility_masks(scene, world, Options())
    t2 = time.perf_counter()
    results = simulate(scene, Options(), world, vis)
    t3 = time.perf_counter()
    emitted = sum(len(v.features) for r in results for v in (r.left, r.right) if v is not None)
    return t2 - t1, t3 - t2, t3 - t0, world.n_features, emitted


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scales", type=int, nargs="+", default=[1, 2, 5, 10])
    ap.add_argument("--trials", type=int, default=1000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--memory-only", action="store_true", help="only the trials of the largest scene")
    args = ap.parse_args()
    print(load())
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        lab_folder(folder)
        print("| scale | world features | features in the views | view-point lists (s) | projection (s) | "
              "whole ideal build (s) | ms per emitted feature |")
        print("|---|---|---|---|---|---|---|")
        base = None
        for k in [] if args.memory_only else args.scales:
            path = folder / f"lab_x{k}.wd"
            path.write_text(scaled_lab(k), encoding="utf-8")
            best = min((ideal_build(path) for _ in range(args.rounds)), key=lambda r: r[2])
            vis, proj, total, n_world, n_emitted = best
            per = 1e3 * total / n_emitted
            base = base or per
            print(f"| {k}x | {n_world:,} | {n_emitted:,} | {vis:.3f} | {proj:.3f} | {total:.3f} | "
                  f"{per:.3f} ({per / base:.2f}x the 1x figure) |")
        big = folder / f"lab_x{max(args.scales)}.wd"
        big.write_text(scaled_lab(max(args.scales)), encoding="utf-8")
        child = wiredsl("build", str(big), "--pipeline", "paper", "--trials", str(args.trials), "--format", "npz",
                        "--seed", "1", "--no-svg", "-o", str(folder / "out"))
        print(f"\n{args.trials:,} 'paper' trials of the {max(args.scales)}x scene to npz: {child.cpu:.1f} s CPU "
              f"({child.wall:.0f} s wall), peak RSS {child.rss:.0f} MiB = {child.rss * 1.048576:.0f} MB "
              "(target < 250 MB)")
    print(load())


if __name__ == "__main__":
    main()
