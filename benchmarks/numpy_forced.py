"""What a stage without a compiled kernel costs under `--engine auto`: the whole pipeline then runs on numpy.

On scenes/lab.wd's `paper` pipeline plus one numpy-only stage (a corner jitter, as a first plug-in would be),
the CPU time of a batch of trials on: (a) the compiled kernel without that stage, (b) the numpy path without it,
(c) the numpy path with it (what `auto` runs today), and the numpy-only stage alone on the kernel's output, which
is what a mixed pipeline (compiled stages compiled, only the plug-in's stage on numpy) would add to (a), less the
conversions between the two layouts. Prints the ratios that `wiredsl.run.NUMPY_COST` quotes.

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

import numpy as np  # noqa: E402

from wiredsl.effects.base import Context, Effect, Params, Stats, param  # noqa: E402
from wiredsl.engine import imageset as im  # noqa: E402
from wiredsl.engine.montecarlo import Run  # noqa: E402
from wiredsl.engine.simulate import Options  # noqa: E402
from wiredsl.engine.world import build_world  # noqa: E402
from wiredsl.language.compile import compile_file  # noqa: E402


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
    forced = run_of("auto", True)
    assert not forced.uses_kernel()
    c = cpu(go(forced))
    outs = [out for _, out in kernel.batches(trials)]

    def stage_alone():
        for out in outs:
            for result, sets, _ in out:
                for side, s in sets.items():
                    ctx = Context(pose=result.index, side=side, trials=np.arange(s.trial.max(initial=0) + 1), seed=1,
                                  stats=Stats())
                    Jitter.apply(Jitter.Params(), s, ctx)

    d = cpu(stage_alone)
    n = len(trials)
    print(f"{n} trials of the lab, CPU s: kernel {a:.2f}, numpy {b:.2f}, numpy + the numpy-only stage {c:.2f}, "
          f"that stage alone on the kernel's output {d:.3f}")
    print(f"auto with a numpy-only stage costs {c / a:.1f}x the kernel; a mixed pipeline would cost about "
          f"{(a + d) / a:.2f}x (kernel + the stage), i.e. {c / (a + d):.1f}x less than today")


if __name__ == "__main__":
    main()
