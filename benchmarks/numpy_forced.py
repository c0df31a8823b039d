"""What a stage without a compiled kernel costs under `--engine auto`: the whole pipeline then runs on numpy.

On scenes/lab.wd's `paper` pipeline plus one numpy-only stage (a corner jitter, as a first plug-in would be),
the CPU time of a batch of trials on: (a) the compiled kernel without that stage, (b) the numpy path without it,
(c) the numpy path with it (what `auto` ran before mixed pipelines), and (d) the mixed pipeline `auto` runs now:
the leading stages with a compiled kernel in it, the numpy-only stage and those after it on numpy. Prints the
ratios that `wiredsl.run.NUMPY_COST` quotes.

    OMP_NUM_THREADS=1 python benchmarks/numpy_forced.py [--trials 1024]

Times are the process's CPU time (one thread), best of three.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "1")


from wiredsl.effects.base import Effect, Params, param  # noqa: E402
from wiredsl.engine import imageset as im  # noqa: E402
from wiredsl.engine.simulate import Options  # noqa: E402
from wiredsl.engine.world import build_world  # noqa: E402
from wiredsl.language.compile import compile_file  # noqa: E402
from wiredsl.montecarlo import Run  # noqa: E402


class JitterParams(Params):
    sigma: float = param(0.5, "image", "corner noise", ge=0)


class Jitter(Effect):
    name = "bench_jitter"
    acts_on = "corner detection"
    Params = JitterParams
    doc = "normal corner noise (numpy only)"

    @classmethod
    def is_identity(cls, p):
        return p.sigma == 0

    @classmethod
    def disturb(cls, p, s, ctx):
        return im.replace(s, corners=s.corners + p.sigma * ctx.draws(cls.name, s.corner_trial, 2, normal=True))


def cpu(fn, repeats: int = 3) -> float:
    best = float("inf")
    for _ in range(repeats):
        t = time.process_time()
        fn()
        best = min(best, time.process_time() - t)
    return best


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=1024)
    trials = list(range(ap.parse_args().trials))
    scene = compile_file("scenes/lab.wd")[0]
    world = build_world(scene)

    def run_of(engine: str, extra: bool) -> Run:
        run = Run.create(scene, world, scene.pipeline("paper"), 1, Options())
        run.engine = engine
        if extra:
            run.stages.append((Jitter, Jitter.Params()))
        run.ideal()
        return run

    def go(run):
        return lambda: [None for _ in run.batches(trials)]

    kernel = run_of("kernel", False)
    go(kernel)()  # compile or load the kernel first
    a = cpu(go(kernel))
    b = cpu(go(run_of("numpy", False)))
    c = cpu(go(run_of("numpy", True)))  # the whole pipeline on numpy: what `auto` ran before mixed pipelines
    mixed = run_of("auto", True)
    assert mixed.uses_kernel() and len(mixed.compiled_stages()) < len(mixed.image_stages)
    go(mixed)()
    d = cpu(go(mixed))
    n = len(trials)
    print(f"{n} trials of the lab, CPU s: kernel {a:.2f}, numpy {b:.2f}; with the numpy-only stage: all on numpy "
          f"{c:.2f}, mixed (kernel up to it, numpy from it on) {d:.2f}")
    print(f"a numpy-only stage costs {c / a:.1f}x the kernel on numpy alone, {d / a:.1f}x mixed "
          f"({c / d:.1f}x less)")


if __name__ == "__main__":
    main()
