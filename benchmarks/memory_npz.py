"""Peak memory of a 100,000-trial run streaming to npz (target: under 1 GiB), measured as the child
process's peak resident set size.

    python benchmarks/memory_npz.py [--trials 100000] [--pipeline paper]
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
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "wiredsl", "build", "scenes/lab.wd", "--pipeline", args.pipeline,
                        "--trials", str(args.trials), "--format", "npz", "--seed", "1", "-o", out], check=True)
        seconds = time.perf_counter() - t0
        size = os.path.getsize(os.path.join(out, "features.npz"))
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024  # KiB on Linux
    print(f"{args.trials:,} trials of '{args.pipeline}' to npz: {seconds:.0f} s, {size / 2**30:.2f} GiB written, "
          f"peak RSS {peak:.0f} MiB (target < 1024 MiB)")


if __name__ == "__main__":
    main()
