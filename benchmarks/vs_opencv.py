"""Per view, wiredsl against what a user would otherwise do: render the scene's projected lines into a
640 x 480 image and run OpenCV's Canny and probabilistic Hough transform to get segments back.
Both sides measured in the same run on scenes/lab.wd's 14 views (target: wiredsl >= 200x faster).

    OMP_NUM_THREADS=1 python benchmarks/vs_opencv.py   (needs opencv-python-headless, a test extra)
"""

from __future__ import annotations

import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from wiredsl.engine.montecarlo import Run  # noqa: E402
from wiredsl.engine.simulate import Options  # noqa: E402
from wiredsl.engine.world import build_world  # noqa: E402
from wiredsl.language.compile import compile_file  # noqa: E402

cv2.setNumThreads(1)


def main() -> None:
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

    reps = 20
    t0 = time.perf_counter()
    for _ in range(reps):
        segments = opencv_all()
    opencv_per_view = (time.perf_counter() - t0) / (reps * len(views))

    trials = 1024
    t0 = time.perf_counter()
    for _ in run.batches(list(range(trials))):
        pass
    ours_per_view = (time.perf_counter() - t0) / (trials * len(views))

    t0 = time.perf_counter()
    for _ in range(5):
        run.project(scene)
    ideal_per_view = (time.perf_counter() - t0) / (5 * len(views))

    print(f"scenes/lab.wd, {len(views)} views of 640 x 480; OpenCV finds {segments // reps} segments in all views")
    print(f"OpenCV render + Canny + HoughLinesP : {1e3 * opencv_per_view:8.3f} ms a view")
    print(f"wiredsl paper pipeline, batched     : {1e3 * ours_per_view:8.3f} ms a view (a trial's view)")
    print(f"wiredsl ideal projection alone      : {1e3 * ideal_per_view:8.3f} ms a view")
    print(f"speed-up, batched trials            : {opencv_per_view / ours_per_view:8.1f} x (target >= 200)")
    print(f"speed-up, one projection            : {opencv_per_view / ideal_per_view:8.1f} x")


if __name__ == "__main__":
    main()
