"""Per view, wiredsl against what a user would otherwise do: render the scene's projected lines into a
640 x 480 image and run OpenCV's Canny and probabilistic Hough transform to get segments back.
Both sides measured in the same run on scenes/lab.wd's 14 views. Targets: batched Monte-Carlo trials
>= 200x faster than render + detect; one ideal projection <= 0.5 ms a view and >= 5x faster.
Each timing is the best of several rounds (the machines are shared).

    OMP_NUM_THREADS=1 python benchmarks/vs_opencv.py [--trials 1024] [--rounds 5]
    (needs opencv-python-headless, a test extra)
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from wiredsl.engine.simulate import Options, simulate  # noqa: E402
from wiredsl.engine.world import build_world  # noqa: E402
from wiredsl.language.compile import compile_file  # noqa: E402
from wiredsl.montecarlo import Run  # noqa: E402

cv2.setNumThreads(1)


def best(fn, rounds: int, reps: int) -> float:
    """Best mean time of fn over `rounds` rounds of `reps` calls."""
    times = []
    for _ in range(rounds):
        t0 = time.perf_counter()
        for _ in range(reps):
            fn()
        times.append((time.perf_counter() - t0) / reps)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=1024)
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    scene, _, _ = compile_file("scenes/lab.wd")
    world = build_world(scene)
    run = Run.create(scene, world, scene.pipeline("paper"), 1, Options())
    views = [v for r in run.ideal() for v in (r.left, r.right)]

    images = []
    for v in views:
        img = np.zeros((v.camera.height, v.camera.width), np.uint8)
        for f in v.features:
            if f.kind in ("line", "polyline"):
                cv2.polylines(img, [np.round(f.points).astype(np.int32)], False, 255, 1, cv2.LINE_AA)
        images.append(img)

    def opencv_all():
        found = 0
        for v, img in zip(views, images, strict=True):
            canvas = img.copy()  # rendering is part of the per-view cost: redraw each time
            canvas[:] = 0
            for f in v.features:
                if f.kind in ("line", "polyline"):
                    cv2.polylines(canvas, [np.round(f.points).astype(np.int32)], False, 255, 1, cv2.LINE_AA)
            edges = cv2.Canny(cv2.GaussianBlur(canvas, (3, 3), 0), 50, 150)
            lines = cv2.HoughLinesP(edges, 1, np.pi / 180, threshold=30, minLineLength=10, maxLineGap=3)
            found += 0 if lines is None else len(lines)
        return found

    opencv_per_view = best(opencv_all, args.rounds, 4) / len(views)
    segments = opencv_all()

    visible = run._visible  # the view-point lists, computed once a run like the trials do
    ideal_per_view = best(lambda: simulate(scene, Options(), world, visible), args.rounds, 10) / len(views)

    trials = list(range(args.trials))
    t0 = time.perf_counter()
    for _ in run.batches(trials):
        pass
    ours_per_view = (time.perf_counter() - t0) / (len(trials) * len(views))

    print(f"scenes/lab.wd, {len(views)} views of 640 x 480; OpenCV finds {segments} segments in all views")
    print(f"OpenCV render + Canny + HoughLinesP : {1e3 * opencv_per_view:8.3f} ms a view")
    print(f"wiredsl paper pipeline, batched     : {1e3 * ours_per_view:8.3f} ms a view (a trial's view)")
    print(f"wiredsl ideal projection alone      : {1e3 * ideal_per_view:8.3f} ms a view")
    print(f"speed-up, batched trials            : {opencv_per_view / ours_per_view:8.1f} x (target >= 200)")
    print(f"speed-up, one projection            : {opencv_per_view / ideal_per_view:8.1f} x (target >= 5, "
          f"and <= 0.5 ms a view)")


if __name__ == "__main__":
    main()
