"""Throughput of the full `paper` pipeline on scenes/lab.wd with batched trials, in million feature-trials
per second on one core: the compiled kernel and the numpy path, next to a bare numpy kernel doing
projection plus three perturbations on the same number of features, measured in the same run (target:
the kernel >= 0.5x the bare numpy kernel, aim 1.0x). A pipeline of one cheap stage (corner_loss) is
measured too: it must cost visibly less than `paper`. Then the CPU a new process spends loading the cached
`paper` kernel, as the command line does: importing numba, then loading the composed loop and the functions it
calls (its first call), best of three.

    OMP_NUM_THREADS=1 python benchmarks/throughput.py [--trials 2048]

Times are the process's CPU time (one thread), not wall time: the machine is shared, and CPU time is
what one core spends whatever else runs beside it.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from wiredsl.engine.simulate import Options  # noqa: E402
from wiredsl.engine.world import build_world  # noqa: E402
from wiredsl.language.compile import compile_file  # noqa: E402
from wiredsl.montecarlo import Run  # noqa: E402
from wiredsl.scene import Pipeline  # noqa: E402


def wiredsl_rate(scene, world, pipeline, engine: str, trials: int) -> tuple[float, int]:
    run = Run.create(scene, world, pipeline, 1, Options())
    run.engine = engine
    ideal = run.ideal()  # the one-off projection and visibility are not per-trial work
    features = sum(len([f for f in v.features if f.kind != "conic"]) for r in ideal for v in (r.left, r.right))
    for _ in run.batches(range(8)):  # compile or load the kernel, warm the caches
        pass
    t0 = time.process_time()
    for _ in run.batches(range(trials)):
        pass
    seconds = time.process_time() - t0
    return features * trials / seconds, features


def numpy_rate(features: int, trials: int) -> float:
    """Projection of each feature's two end points, then lateral shift, approximation error and a length
    cut, on (trials, features) arrays: the least any implementation has to do."""
    rng = np.random.default_rng(0)
    ends = rng.uniform(-1, 1, size=(features, 2, 3)) + [0, 0, 4]
    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    R = np.eye(3)
    t0 = time.process_time()
    done = 0
    while done < trials:
        T = min(256, trials - done)
        Rt = R[None] + rng.normal(0, 1e-4, size=(T, 3, 3))  # per-trial camera
        P = np.einsum("tij,nej->tnei", Rt, ends)
        uv = (P @ K.T)[..., :2] / P[..., 2:3]
        d = uv[:, :, 1] - uv[:, :, 0]
        n = np.stack([-d[..., 1], d[..., 0]], -1) / np.linalg.norm(d, axis=-1, keepdims=True)
        uv = uv + rng.uniform(-3, 3, size=(T, features, 1, 1)) * n[:, :, None]  # lateral shift
        uv = uv + rng.normal(0, 0.15, size=uv.shape)  # approximation error
        cut = rng.random((T, features, 1)) * 0.71  # edge loss: keep 71% of the length
        uv = np.stack([uv[:, :, 0] + cut * d, uv[:, :, 0] + (cut + 0.29) * d], axis=2)
        done += T
    return features * trials / (time.process_time() - t0)


LOAD = """
import time
from wiredsl import cli
from wiredsl.effects import BUILTIN
from wiredsl.language.compile import compile_file
stages = [BUILTIN[s.effect].kernel for s in compile_file("scenes/lab.wd")[0].pipeline("paper").stages]
functions = tuple(k.function for k in stages if k is not None)
t0 = time.process_time()
import numba
getattr(cli, "_numba_without_blas", lambda: None)()  # as the command line loads it (where it does)
t1 = time.process_time()
from wiredsl.engine import kernel
kernel.warm(functions, tuple(k.camera for k in stages if k is not None),
            tuple(k.workspace for k in stages if k is not None))
print(t1 - t0, time.process_time() - t1)
"""


def kernel_load(repeat: int = 3) -> tuple[float, float]:
    """CPU seconds of a new process importing numba and loading the cached `paper` kernel (best of `repeat`)."""
    runs = []
    for _ in range(repeat):
        out = subprocess.run([sys.executable, "-c", LOAD], capture_output=True, text=True, check=True)
        runs.append(tuple(float(x) for x in out.stdout.split()))
    return min(runs, key=sum)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=2048)
    args = ap.parse_args()
    scene, _, _ = compile_file("scenes/lab.wd")
    world = build_world(scene)
    paper = scene.pipeline("paper")
    cheap = Pipeline(name="corners", stages=[s for s in paper.stages if s.effect == "corner_loss"])
    bare = numpy_rate(276, args.trials)
    kernel, features = wiredsl_rate(scene, world, paper, "kernel", args.trials)
    cheap_kernel, _ = wiredsl_rate(scene, world, cheap, "kernel", args.trials)
    reference, _ = wiredsl_rate(scene, world, paper, "numpy", max(args.trials // 8, 64))
    bare = (bare + numpy_rate(features, args.trials)) / 2  # before and after: the machine is shared
    print(f"scenes/lab.wd, {features} features a trial (7 poses x 2 cameras), {args.trials} trials, one core")
    print(f"bare numpy kernel                 : {bare / 1e6:7.3f} million feature-trials/s")
    print(f"wiredsl paper, compiled kernel    : {kernel / 1e6:7.3f}  = {kernel / bare:5.2f}x bare numpy "
          "(target >= 0.5x, aim 1.0x)")
    print(f"wiredsl paper, numpy path         : {reference / 1e6:7.3f}  = {reference / bare:5.2f}x bare numpy; "
          f"the kernel is {kernel / reference:.1f}x the numpy path")
    print(f"wiredsl corner_loss only, kernel  : {cheap_kernel / 1e6:7.3f}  = {cheap_kernel / kernel:5.1f}x the paper "
          "pipeline's rate")
    print(f"wiredsl paper, a trial in-process : {1e6 * features / kernel:7.1f} us of CPU (kernel and the Python "
          "around it)")
    numba_import, loading = kernel_load()
    print(f"loading the cached kernel         : {numba_import + loading:7.3f} s of CPU in a new process (importing "
          f"numba {numba_import:.3f}, the composed loop and its functions {loading:.3f})")


if __name__ == "__main__":
    main()
