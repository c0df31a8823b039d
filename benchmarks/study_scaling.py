"""Study scaling: the lab's Sobol' `sources` study enlarged to 4,608 points (`design sobol points 512`), run by
local processes with 1, 2, ... N workers; the speed-up over 1 worker and the efficiency (speed-up / workers).

    python benchmarks/study_scaling.py [--points 512] [--workers 1,2] [--repeat 1]

Each run is a new process (benchmarks/_study.py) timing run_study alone (the workers' start included). Runs are
interleaved (1, 2, ..., 1, 2, ...) and the best of each count kept, so that the machine's other load hits every
count alike; the load average is printed beside the figures, and so is what the machine itself offered at that
moment: N processes of pure-Python work against one (study_speed.machine_speedup). On a bigger machine pass
--workers 1,2,4,8,16: the efficiency is printed the same way.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))


def machine(workers: int, n: int = 4_000_000) -> float:
    """N processes of pure-Python work against one, now: the parallelism the machine offers."""
    import multiprocessing
    import time
    from concurrent.futures import ProcessPoolExecutor

    from study_speed import burn

    t = time.perf_counter()
    burn(n)
    one = time.perf_counter() - t
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        list(pool.map(burn, [1] * workers))
        t = time.perf_counter()
        list(pool.map(burn, [n] * workers))
        many = time.perf_counter() - t
    return workers * one / many


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=512, help="Sobol' base samples n: n (7 + 2) design points")
    ap.add_argument("--workers", default="1,2", help="worker counts, comma-separated")
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args()
    from _cli import load
    from study_speed import _timed_study

    counts = [int(w) for w in args.workers.split(",")]
    print(f"machine: {os.cpu_count()} cores; {load()} before")
    best: dict[int, float] = {}
    cpu: dict[int, float] = {}
    offered: dict[int, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        _timed_study(ROOT, Path(tmp) / "warm", limit=4)  # numba's caches filled
        for _ in range(args.repeat):
            for w in counts:
                got = _timed_study(ROOT, Path(tmp) / f"w{w}", full=True, executor="processes", workers=w,
                                   points=args.points)
                best[w] = min(got["wall"], best.get(w, float("inf")))
                cpu[w] = min(got["cpu"] + got["cpu_workers"], cpu.get(w, float("inf")))
                offered[w] = max(machine(w) if w > 1 else 1.0, offered.get(w, 0.0))
                print(f"  {w} workers: {got['wall']:7.1f} s wall, {got['cpu']:6.1f} s CPU in the study's process + "
                      f"{got['cpu_workers']:6.1f} s in its workers ({load()})", flush=True)
    points = 9 * args.points
    print(f"study: lab sources, {points} points x 2 trials x 3 poses (pgh, stereo3d), processes; best of {args.repeat}")
    print("wall clock (what a quiet machine with that many free cores shows; a loaded one shows its load):")
    base = best[counts[0]] * counts[0]
    for w in counts:
        speedup = base / best[w]
        print(f"  {w:3d} workers: {best[w]:7.1f} s  {points / best[w]:7.1f} points/s  speed-up {speedup:5.2f}x  "
              f"efficiency {speedup / w:5.2f}  (the machine offered {offered[w]:.2f}x of pure-Python work: "
              f"{speedup / offered[w]:.0%} of it reached)")
    print("CPU time, the study's process and its workers together (load-independent: the work that parallelism adds;"
          " efficiency = CPU of the first count / CPU of this one, the wall efficiency on idle cores when every "
          "worker is busy to the end):")
    for w in counts:
        print(f"  {w:3d} workers: {cpu[w]:7.1f} CPU-s  {points / cpu[w]:7.1f} points per CPU-second  "
              f"CPU efficiency {cpu[counts[0]] / cpu[w]:5.2f}")
    print(f"machine: {load()} after (target: efficiency >= 0.8 from 1 to the machine's cores)")


if __name__ == "__main__":
    main()
