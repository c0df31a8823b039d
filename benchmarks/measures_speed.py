"""Time of each measure per trial against the Monte-Carlo trial itself, on scenes/lab.wd's `paper`
pipeline, measured in the same run (aim: the measures do not dominate a study's time).

Per measure: the one-off `prepare` (ideal references; for pgh also the view-point database) and
`measure` over the same batches the trials produced, as seconds per trial (all poses, both cameras)
and as a ratio to the trials' own time (wall); `prepare` also in CPU time. The load average is printed before and
after (docs/reference/measures.md quotes pgh's prepare).

    OMP_NUM_THREADS=1 python benchmarks/measures_speed.py [--trials 256] [--pgh-viewpoints N] [--numpy]

--numpy times pgh's numpy pair loop even when numba (the `fast` extra) is installed.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from wiredsl.engine.simulate import Options  # noqa: E402
from wiredsl.engine.world import build_world  # noqa: E402
from wiredsl.language.compile import compile_file  # noqa: E402
from wiredsl.measures import REGISTRY, pgh  # noqa: E402
from wiredsl.montecarlo import Run  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=256)
    ap.add_argument("--pgh-viewpoints", type=int, default=None, help="pgh's `viewpoints` (default: its own)")
    ap.add_argument("--numpy", action="store_true", help="pgh without its numba kernel")
    args = ap.parse_args()
    if args.numpy:
        pgh._KERNEL = False
    scene, _, _ = compile_file("scenes/lab.wd")
    world = build_world(scene)
    run = Run.create(scene, world, scene.pipeline("paper"), 1, Options())
    run.ideal()  # the one-off projection and visibility are not per-trial work
    t0 = time.perf_counter()
    batches = list(run.batches(list(range(args.trials))))
    trial_time = (time.perf_counter() - t0) / args.trials
    engine = "numpy" if args.numpy or pgh.kernel() is None else "numba"
    print(f"lab, pipeline 'paper', {args.trials} trials x {len(run.ideal())} poses x 2 cameras; pgh: {engine}")
    print("load average " + " ".join(f"{x:.2f}" for x in os.getloadavg()))
    print(f"{'':<10} {'prepare s':>10} {'CPU s':>7} {'ms/trial':>10} {'x trial time':>13}")
    print(f"{'trials':<10} {'':>10} {'':>7} {trial_time * 1e3:>10.2f} {1.0:>13.2f}")
    for name, m in REGISTRY.items():
        extra = {"viewpoints": args.pgh_viewpoints} if name == "pgh" and args.pgh_viewpoints is not None else {}
        p = m.Params(**extra)
        t0, c0 = time.perf_counter(), time.process_time()
        prep = m.prepare(p, run)
        prepare, prepare_cpu = time.perf_counter() - t0, time.process_time() - c0
        t0 = time.perf_counter()
        for batch, results in batches:
            for result, disturbed, _ in results:
                m.measure(p, prep, result, disturbed, len(batch))
        per = (time.perf_counter() - t0) / args.trials
        print(f"{name:<10} {prepare:>10.2f} {prepare_cpu:>7.2f} {per * 1e3:>10.2f} {per / trial_time:>13.2f}")
    print("load average " + " ".join(f"{x:.2f}" for x in os.getloadavg()))


if __name__ == "__main__":
    main()
