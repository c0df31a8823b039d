"""What hidden-line removal (--visibility exact) costs per view against the paper's rule and no occlusion,
measured in the same run on scenes/lab.wd's 14 views (best of 5 passes each, interleaved).

    OMP_NUM_THREADS=1 python benchmarks/hidden_lines.py
"""

from __future__ import annotations

import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

from wiredsl.engine.simulate import Options, simulate, visibility_masks  # noqa: E402
from wiredsl.engine.world import build_world  # noqa: E402
from wiredsl.language.compile import compile_file  # noqa: E402

MODES = ("all", "scene", "exact")


def main() -> None:
    scene, _, _ = compile_file("scenes/lab.wd")
    world = build_world(scene)
    best = dict.fromkeys(MODES, float("inf"))
    views = 0
    for _ in range(5):
        for mode in MODES:  # interleaved, so load on a shared machine hits every mode alike
            o = Options(visibility=mode)
            t0 = time.perf_counter()
            results = simulate(scene, o, world, visibility_masks(scene, world, o))
            best[mode] = min(best[mode], time.perf_counter() - t0)
            views = 2 * len(results)
    print(f"scenes/lab.wd, {views} views, per view (best of 5, visibility lists included):")
    for mode in MODES:
        ratio = best[mode] / best["scene"]
        print(f"  --visibility {mode:5s} {1000 * best[mode] / views:7.1f} ms  ({ratio:.2f}x scene)")


if __name__ == "__main__":
    main()
