"""Throughput of the full `paper` pipeline on scenes/lab.wd with batched trials, in feature-trials per
second on one core, next to a bare numpy kernel doing projection plus three perturbations on the same
features, measured in the same run (target: wiredsl >= 4 million/s, within 2x of bare numpy).

    OMP_NUM_THREADS=1 python benchmarks/throughput.py [--trials 2048]
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from wiredsl.engine.montecarlo import Run  # noqa: E402
from wiredsl.engine.simulate import Options  # noqa: E402
from wiredsl.engine.world import build_world  # noqa: E402
from wiredsl.language.compile import compile_file  # noqa: E402


def wiredsl_rate(trials: int) -> tuple[float, int]:
    scene, _, _ = compile_file("scenes/lab.wd")
    world = build_world(scene)
    run = Run.create(scene, world, scene.pipeline("paper"), 1, Options())
    ideal = run.ideal()  # the one-off projection and visibility are not per-trial work
    features = sum(len([f for f in v.features if f.kind != "conic"]) for r in ideal for v in (r.left, r.right))
    t0 = time.perf_counter()
    for _ in run.batches(list(range(trials))):
        pass
    seconds = time.perf_counter() - t0
    return features * trials / seconds, features


def numpy_rate(features: int, trials: int) -> float:
    """Projection of each feature's two end points, then lateral shift, approximation error and a length
    cut, on (trials, features) arrays: the least any implementation has to do."""
    rng = np.random.default_rng(0)
    ends = rng.uniform(-1, 1, size=(features, 2, 3)) + [0, 0, 4]
    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    R = np.eye(3)
    t0 = time.perf_counter()
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
    return features * trials / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=2048)
    args = ap.parse_args()
    ours, features = wiredsl_rate(args.trials)
    bare = numpy_rate(features, args.trials)
    print(f"scenes/lab.wd, paper pipeline, {features} features a trial (7 poses x 2 cameras), {args.trials} trials")
    print(f"wiredsl full pipeline : {ours / 1e6:8.3f} million feature-trials/s (target >= 4)")
    print(f"bare numpy kernel     : {bare / 1e6:8.3f} million feature-trials/s")
    print(f"ratio numpy / wiredsl : {bare / ours:8.1f} (target <= 2)")


if __name__ == "__main__":
    main()
