"""`paper` trials to npz through the command line against the bare numpy kernel, in million feature-trials per
second of one core's CPU time, measured in the same run (target: >= 0.5x the bare numpy kernel).

    python benchmarks/cli_trials.py [--trials 2000] [--repeat 3]

`wiredsl build scenes/lab.wd --trials N --format npz` runs in a new process, as a user runs it: the figure
covers compiling the scene, loading the kernel, the trials, packing and writing the npz. The marginal rate
(the CPU of N trials less that of N/8, over the extra trials) leaves out the fixed cost of a run. The bare
numpy kernel is benchmarks/throughput.py's: projection of each feature's two end points plus three
perturbations on (trials, features) arrays, the least any implementation has to do; measured before and
after the builds, in this process (one thread).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(__file__))
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from _cli import best, load  # noqa: E402
from throughput import numpy_rate  # noqa: E402

FEATURES = 276  # the lab's strokes a trial (7 poses x 2 cameras), as throughput.py counts them


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=2000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    print(load())
    bare = numpy_rate(FEATURES, args.trials)
    small = max(args.trials // 8, 2)
    with tempfile.TemporaryDirectory() as out:
        def build(n: int):
            return best(["-m", "wiredsl", "build", "scenes/lab.wd", "--trials", str(n), "--format", "npz",
                         "--seed", "1", "--no-svg", "-o", f"{out}/n{n}"], args.repeat)
        build(2)  # the kernel's cache on disk
        few, many = build(small), build(args.trials)
    bare = (bare + numpy_rate(FEATURES, args.trials)) / 2  # before and after: the machine is shared
    whole = FEATURES * args.trials / many.cpu
    marginal = FEATURES * (args.trials - small) / max(many.cpu - few.cpu, 1e-9)
    print(f"bare numpy kernel                      : {bare / 1e6:6.3f} million feature-trials/s")
    print(f"wiredsl build, {args.trials} trials to npz  : {whole / 1e6:6.3f} = {whole / bare:5.2f}x bare numpy "
          f"(target >= 0.5x); {many.cpu:.2f} s CPU, {many.wall:.2f} s wall, peak RSS {many.rss:.0f} MiB")
    fixed = few.cpu - small * (many.cpu - few.cpu) / (args.trials - small)
    print(f"  marginal ({small} -> {args.trials} trials): {marginal / 1e6:6.3f} = {marginal / bare:5.2f}x bare numpy; "
          f"fixed cost of a run {fixed:.2f} s CPU")
    kernel, around, writer = split(args.trials)
    total = kernel + around + writer
    print(f"where a trial's CPU goes, in-process ({total:.0f} us a trial): compiled kernel {kernel:.0f} us "
          f"({kernel / total:.0%}), Python around it (keys, cameras, packing) {around:.0f} us ({around / total:.0%}), "
          f"npz writer {writer:.0f} us ({writer / total:.0%})")
    print(load())


def split(trials: int) -> tuple[float, float, float]:
    """Microseconds of CPU a lab trial spends in the compiled kernel, in the Python around it and in the npz
    writer, measured in this process (the kernel's calls timed one by one)."""
    from wiredsl.engine import kernel as kn
    from wiredsl.engine.montecarlo import Run
    from wiredsl.engine.simulate import Options
    from wiredsl.engine.world import build_world
    from wiredsl.io import emit
    from wiredsl.language.compile import compile_file

    inside = [0.0]
    run_view = kn.run_view

    def timed(*a):
        t = time.process_time()
        out = run_view(*a)
        inside[0] += time.process_time() - t
        return out

    scene, _, _ = compile_file("scenes/lab.wd")
    world = build_world(scene)
    run = Run.create(scene, world, scene.pipeline("paper"), 1, Options())
    run.engine = "kernel"
    run.ideal()
    list(run.batches(range(4)))  # load the kernel
    kn.run_view = timed
    batches = writing = 0.0
    with tempfile.TemporaryDirectory() as out:
        writer = emit.NpzStream(f"{out}/features.npz")
        it = iter(run.batches(range(trials)))
        while True:
            t0 = time.process_time()
            got = next(it, None)
            t1 = time.process_time()
            if got is None:
                break
            writer.write_batch(*got, run.world)
            batches, writing = batches + t1 - t0, writing + time.process_time() - t1
        writer.abort()
    kn.run_view = run_view
    return 1e6 * inside[0] / trials, 1e6 * (batches - inside[0]) / trials, 1e6 * writing / trials


if __name__ == "__main__":
    main()
