"""What the study tutorial's two commands cost, run as its reader runs them (docs/tutorials/study.md): `wiredsl
study scenes/studies/lab_study.wd shift_calibration` (a 4 x 3 grid, 12 trials at 3 poses) and `... sources` (the
Sobol' design, 576 points x 2 trials x 3 poses), with their plots, on the default local processes.

    python benchmarks/study_tutorial.py [--repeat 1] [--study shift_calibration --study sources]

Each run is a new process (benchmarks/_cli.py) running the command as `python -m wiredsl` does, then stopping
multiprocessing's fork server (the parent of the workers, which reaps them), so that its CPU time (os.wait4:
user + system) holds the workers'; its wall time includes that stop. Best of `--repeat` by CPU, each into a new
folder (a study resumes from its folder). The numba caches are as the machine has them (a first run on a new
machine compiles the kernel once: see docs/performance.md). The load average is printed before and after: on a
shared machine the wall time is the figure that moves.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _cli import load, run  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FILE = ROOT / "scenes" / "studies" / "lab_study.wd"
# `python -m wiredsl ARGS`, then the fork server stopped (and so reaped, with the workers it reaped)
COMMAND = """
import sys
from multiprocessing import forkserver
from wiredsl.cli import main
try:
    main(sys.argv[1:], prog_name="wiredsl")
except SystemExit as exc:
    code = exc.code
finally:
    if getattr(forkserver._forkserver, "_forkserver_pid", None):
        forkserver._forkserver._stop()
sys.exit(code)
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--study", action="append", default=None)
    args = ap.parse_args()
    print(load(), f"cores {os.cpu_count()}")
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.study or ["shift_calibration", "sources"]:
            runs = [run(["-c", COMMAND, "study", str(FILE), name, "-o", f"{tmp}/{name}-{k}"])
                    for k in range(args.repeat)]
            child = min(runs, key=lambda c: c.cpu)
            print(f"study {name}\twall {child.wall:.1f} s\tCPU {child.cpu:.1f} s (its workers' included)")
    print(load())


if __name__ == "__main__":
    main()
