"""Running `wiredsl` as the user does, from a new process: the child's wall time, CPU time and peak RSS.

Shared by the command-line benchmarks (cli_trials, cli_ideal_view, cold_start, big_scene, memory_npz). Each
figure comes from os.wait4 on that one child, so a run's peak RSS is its own, not the largest child's so far.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ENV = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}


@dataclass
class Child:
    wall: float  # seconds
    cpu: float  # user + system seconds
    rss: float  # peak resident set size, MiB


def run(args: list[str], quiet: bool = True, env: dict | None = None, cwd: str | None = None) -> Child:
    """Run `python args...` in a new process (one thread for BLAS and numba; `env` added to the environment; in
    `cwd`, whose wiredsl `-m` and `-c` import before an editable install's) and measure it."""
    t0 = time.perf_counter()
    out = subprocess.DEVNULL if quiet else None
    proc = subprocess.Popen([sys.executable, *args], env={**ENV, **(env or {})}, stdout=out, stderr=subprocess.PIPE,
                            cwd=cwd)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    err = proc.stderr.read().decode()
    proc.stderr.close()
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed ({proc.returncode}):\n{err}")
    return Child(wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024)


def wiredsl(*args: str) -> Child:
    return run(["-m", "wiredsl", *args])


def best(args: list[str], repeat: int, env: dict | None = None) -> Child:
    """The fastest of `repeat` runs by CPU time (the machine is shared: the least disturbed run), with the
    largest peak RSS seen."""
    runs = [run(args, env=env) for _ in range(repeat)]
    fastest = min(runs, key=lambda c: c.cpu)
    return Child(min(c.wall for c in runs), fastest.cpu, max(c.rss for c in runs))


def load() -> str:
    """The machine's load averages (1, 5, 15 minutes): the benchmarks print them before and after."""
    return "load average " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def lab_folder(folder: Path) -> None:
    """What a variant of scenes/lab.wd written into `folder` needs beside it: its models and calibration file."""
    shutil.copytree("scenes/models", folder / "models")
    shutil.copy("scenes/lab.info", folder / "lab.info")
