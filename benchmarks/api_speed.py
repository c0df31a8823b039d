"""The Python API's costs on scenes/lab.wd (`paper`): `wiredsl.simulate` against `wiredsl build --format npz`
for the same trials (target: simulate at most 1.10x build), and one `Simulator.observe` of both cameras
after the first call (target: at most 2 ms), by a path index and by an arbitrary robot pose.

    OMP_NUM_THREADS=1 python benchmarks/api_speed.py [--trials 2048]

Times are the process's CPU time (one thread): the machine is shared. Both sides run in this process after
one warm-up each (the kernel compiled or loaded, the ideal projection of the scene made), best of 3.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "1")

from click.testing import CliRunner  # noqa: E402

import wiredsl  # noqa: E402
from wiredsl.cli import main  # noqa: E402

LAB = "scenes/lab.wd"


def best(fn, repeat: int = 3) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        times.append(time.process_time() - t0)
    return min(times)


def main_() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=2048)
    args = ap.parse_args()
    scene = wiredsl.compile(LAB)
    with tempfile.TemporaryDirectory() as tmp:
        def build():
            r = CliRunner().invoke(main, ["build", LAB, "-o", f"{tmp}/out", "--no-svg", "--format", "npz",
                                          "--seed", "7", "--trials", str(args.trials), "--force"])
            assert r.exit_code == 0, r.output

        def simulate():
            for _ in wiredsl.simulate(scene, trials=args.trials, seed=7):
                pass

        build(), simulate()  # warm: kernel, caches
        t_build, t_sim = best(build), best(simulate)
    print(f"lab, paper, {args.trials} trials: build to npz {t_build:.2f} s (compile included), "
          f"simulate {t_sim:.2f} s: {t_sim / t_build:.2f}x build (target <= 1.10x)")
    sim = wiredsl.Simulator(scene, seed=7)
    sim.observe(3, trial=0)
    n = 200
    t0 = time.process_time()
    for k in range(n):
        sim.observe(3, trial=k)
    by_index = (time.process_time() - t0) / n * 1e3
    at = tuple(scene.path.poses[3])
    sim.observe(at, trial=0, step=3)
    t0 = time.process_time()
    for k in range(n):
        sim.observe(at, trial=k, step=1000 + k)
    by_pose = (time.process_time() - t0) / n * 1e3
    print(f"observe, both cameras, paper: {by_index:.2f} ms by path index (target <= 2 ms), "
          f"{by_pose:.2f} ms at an arbitrary pose (projected each call)")


if __name__ == "__main__":
    main_()
