"""Every command-line speed and memory script in one sitting, for the README's "Speed through the command line":
the machine, its load before and after, and each script's own output, for this checkout and (--against REF)
for another commit run alternately beside it, so that both see the same machine.

    python benchmarks/cli_report.py [--against main] [--quick]

The scripts: cold_start.py, cli_ideal_view.py, cli_trials.py, big_scene.py --memory-only and memory_npz.py
(100,000 trials; --quick runs 10,000) through the command line, then throughput.py and vs_opencv.py
in-process. --against REF checks REF out into a temporary git worktree and runs the same scripts there (its
own benchmarks, its own wiredsl on PYTHONPATH, the same Python).
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def scripts(quick: bool) -> list[list[str]]:
    return [["cold_start.py"], ["cli_ideal_view.py"], ["cli_trials.py"], ["big_scene.py", "--memory-only"],
            ["memory_npz.py", "--trials", "10000" if quick else "100000"], ["throughput.py"], ["vs_opencv.py"]]


def commit(tree: Path) -> str:
    return subprocess.run(["git", "-C", str(tree), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True, check=True).stdout.strip()


def run_script(tree: Path, script: list[str]) -> str:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, str(tree / "benchmarks" / script[0]), *script[1:]], cwd=tree, env=env,
                          capture_output=True, text=True)
    took = time.perf_counter() - t0
    if proc.returncode != 0:
        return f"FAILED ({proc.returncode}) after {took:.0f} s:\n{proc.stderr[-2000:]}"
    return proc.stdout.rstrip() + f"\n({took:.0f} s wall for the script)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", default=None, help="another commit to measure beside this checkout")
    ap.add_argument("--quick", action="store_true", help="10,000 trials in memory_npz.py instead of 100,000")
    args = ap.parse_args()
    import numpy

    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"numpy {numpy.__version__}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    print("uptime before: load average " + " ".join(f"{x:.2f}" for x in os.getloadavg()))
    trees = [("this checkout", ROOT)]
    with tempfile.TemporaryDirectory() as tmp:
        if args.against:
            other = Path(tmp) / "against"
            subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(other), args.against],
                           check=True)
            trees.append((args.against, other))
        try:
            print("trees: " + "; ".join(f"{name} at {commit(tree)}" for name, tree in trees))
            for script in scripts(args.quick):
                for name, tree in trees:
                    print(f"\n## {' '.join(script)} ({name}, {commit(tree)})", flush=True)
                    print(run_script(tree, script), flush=True)
        finally:
            if args.against:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(other)], check=False)
    print("\nuptime after: load average " + " ".join(f"{x:.2f}" for x in os.getloadavg()))


if __name__ == "__main__":
    main()
