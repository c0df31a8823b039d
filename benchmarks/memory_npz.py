"""100,000 `paper` trials of scenes/lab.wd streamed to npz through the command line: CPU time and peak RSS,
against a tenth of the trials in the same run (targets: linear in trials, under 250 MB peak RSS).

    python benchmarks/memory_npz.py [--trials 100000] [--pipeline paper] [--engine kernel]

Each run is a new process (`wiredsl build ... --format npz`); its CPU time, wall time and peak RSS are its own
(os.wait4). Linear in trials: the CPU a trial of the full run against that of the tenth (each less the fixed
cost of a run, measured by a 2-trial build), and the same peak RSS.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile

sys.path.insert(0, os.path.dirname(__file__))

from _cli import load, wiredsl  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=100_000)
    ap.add_argument("--pipeline", default="paper")
    ap.add_argument("--engine", default="kernel", choices=["kernel", "numpy"])
    args = ap.parse_args()
    print(load())
    with tempfile.TemporaryDirectory() as out:
        def build(n: int):
            child = wiredsl("build", "scenes/lab.wd", "--pipeline", args.pipeline, "--trials", str(n), "--format",
                            "npz", "--seed", "1", "--engine", args.engine, "--no-svg", "--force", "-o", f"{out}/{n}")
            size = os.path.getsize(os.path.join(out, str(n), "features.npz"))
            return child, size

        fixed, _ = build(2)  # also compiles or loads the kernel's cache on disk
        tenth, _ = build(args.trials // 10)
        full, size = build(args.trials)
    per_full = (full.cpu - fixed.cpu) / (args.trials - 2)
    per_tenth = (tenth.cpu - fixed.cpu) / (args.trials // 10 - 2)
    print(f"2 trials (the fixed cost)  : {fixed.cpu:6.1f} s CPU, peak RSS {fixed.rss:.0f} MiB")
    print(f"{args.trials // 10:>7,} trials           : {tenth.cpu:6.1f} s CPU, peak RSS {tenth.rss:.0f} MiB, "
          f"{1e6 * per_tenth:.0f} us CPU a trial beyond the fixed cost")
    print(f"{args.trials:>7,} trials           : {full.cpu:6.1f} s CPU ({full.wall:.0f} s wall), peak RSS "
          f"{full.rss:.0f} MiB = {full.rss * 1.048576:.0f} MB (target < 250 MB), {size / 2**30:.2f} GiB written, "
          f"{1e6 * per_full:.0f} us CPU a trial = {per_full / per_tenth:.2f}x the tenth's (linear: 1.00)")
    print(load())


if __name__ == "__main__":
    main()
