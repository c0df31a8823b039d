"""Peak memory and time of a 100,000-trial `paper` run streaming to npz (targets: under 1 GiB peak RSS,
well under two minutes), measured as the child process's peak resident set size and wall time.

    python benchmarks/memory_npz.py [--trials 100000] [--pipeline paper] [--engine kernel]

On a shared machine, `--trials 10000` and the printed extrapolation (time is linear in trials: batches of
256 are independent; memory does not grow with trials) give the figure in a tenth of the time.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=100_000)
    ap.add_argument("--pipeline", default="paper")
    ap.add_argument("--engine", default="kernel", choices=["kernel", "numpy"])
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as out:
        # compile or load the kernel once first, so that the timed run is the run (the cache is on disk)
        subprocess.run([sys.executable, "-m", "wiredsl", "build", "scenes/lab.wd", "--pipeline", args.pipeline,
                        "--trials", "2", "--format", "npz", "--engine", args.engine, "-o", out + "/warm"], check=True)
        t0 = time.perf_counter()
        c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        subprocess.run([sys.executable, "-m", "wiredsl", "build", "scenes/lab.wd", "--pipeline", args.pipeline,
                        "--trials", str(args.trials), "--format", "npz", "--seed", "1", "--engine", args.engine,
                        "-o", out + "/run"], check=True)
        seconds = time.perf_counter() - t0
        c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        size = os.path.getsize(os.path.join(out, "run", "features.npz"))
    cpu = (c1.ru_utime + c1.ru_stime) - (c0.ru_utime + c0.ru_stime)
    peak = c1.ru_maxrss / 1024  # KiB on Linux: the largest child, i.e. the timed run
    print(f"{args.trials:,} trials of '{args.pipeline}' ({args.engine}) to npz: {seconds:.1f} s wall, {cpu:.1f} s CPU, "
          f"{size / 2**30:.2f} GiB written, peak RSS {peak:.0f} MiB (target < 1024 MiB)")
    if args.trials < 100_000:
        k = 100_000 / args.trials
        print(f"extrapolated to 100,000 trials: {seconds * k:.0f} s wall, {cpu * k:.0f} s CPU "
              f"(target well under 120 s), {size * k / 2**30:.1f} GiB written")


if __name__ == "__main__":
    main()
