"""What `wiredsl verify` costs: CPU time of one 640x480 image with one detector (read, detect, verify), the
projection of its view apart, and the peak memory of a folder of 100 and of 1,000 images (streamed: it must
not grow with the number of images).

    python benchmarks/verify_speed.py [--images 1000]

The images are the fence scene (tests/data/verify/fence.wd) drawn through its `injected` pipeline by the
tests' drawing (tests/verify_drawing.py); OpenCV runs on one thread, as numpy does.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from _cli import load, wiredsl  # noqa: E402

FENCE = Path(__file__).resolve().parents[1] / "tests" / "data" / "verify" / "fence.wd"
REPEAT = 20


def per_image(folder: Path) -> None:
    import cv2
    import numpy as np

    import wiredsl as w
    from wiredsl.engine.simulate import Options, project_pose
    from wiredsl.engine.world import build_world
    from wiredsl.verify import detectors as D
    from wiredsl.verify import images as I
    from wiredsl.verify import verification as V

    cv2.setNumThreads(1)
    scene = w.compile(FENCE)
    world = build_world(scene)
    path = str(folder / "left_000.png")
    t = time.process_time()
    for _ in range(REPEAT):
        view = project_pose(scene, world, scene.path.pose(0), 0, Options(visibility="exact")).left
    project = (time.process_time() - t) / REPEAT
    print(f"projection of the view (hidden lines, {sum(f.kind != 'corner' for f in view.features)} strokes): "
          f"{1000 * project:.2f} ms CPU")
    print("\n| detector | read | detect | verify | total (one 640x480 image) |\n|---|---|---|---|---|")
    for name, det in D.BUILTIN.items():
        params = det.Params()
        times = np.zeros(3)
        for _ in range(REPEAT):
            t0 = time.process_time()
            img = I.read_grey(path, 640, 480)
            t1 = time.process_time()
            found = D.checked(det.detect(img, params), img.shape, name)
            t2 = time.process_time()
            V.verify_image(view, found, img.shape, V.Settings(), V.ImageResult(path, "left", "0", name,
                                                                                world.feature_ids))
            t3 = time.process_time()
            times += (t1 - t0, t2 - t1, t3 - t2)
        r, d, v = 1000 * times / REPEAT
        print(f"| {name} | {r:.2f} ms | {d:.2f} ms | {v:.2f} ms | {r + d + v:.2f} ms |")


def folder_memory(src: Path, n: int, work: Path) -> None:
    """Peak RSS of `wiredsl verify` over n images (copies of the ten drawn ones)."""
    imgs = work / f"n{n}"
    imgs.mkdir()
    files = sorted(src.glob("left_*.png"))
    for k in range(n):
        os.link(files[k % len(files)], imgs / f"left_{k:04d}.png")
    poses = work / f"poses{n}.txt"
    import numpy as np

    # every image at the scene's first left-camera pose (a TUM file of n identical poses)
    import wiredsl as w
    from wiredsl.engine.geometry import camera_from_world

    scene = w.compile(FENCE)
    R_cw, t_cw = camera_from_world(scene.path.pose(0), scene.rig.left.rotation, scene.rig.left.position)
    from scipy.spatial.transform import Rotation

    p, q = -R_cw.T @ t_cw, Rotation.from_matrix(R_cw.T).as_quat()
    poses.write_text("".join(f"{k} " + " ".join(f"{v:.12f}" for v in (*p, *q)) + "\n" for k in range(n)))
    c = wiredsl("verify", str(FENCE), "--images", str(imgs / "*.png"), "--poses", str(poses), "--match", "order",
                "--detector", "canny", "--fit", "-o", str(work / f"out{n}"))
    print(f"| {n:,} | {c.wall:.1f} s | {c.cpu:.1f} s | {1000 * c.cpu / n:.1f} ms | {c.rss:.0f} MiB |")
    assert np.isfinite(c.rss)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--images", type=int, default=1000, help="the larger folder (default 1000)")
    args = ap.parse_args()
    from verify_drawing import render_records

    import wiredsl as w

    print(load())
    with tempfile.TemporaryDirectory() as d:
        work = Path(d)
        batch = next(w.simulate(w.compile(FENCE), trials=1, seed=3, pipeline="injected", engine="numpy"))
        render_records(batch.records(), work / "img", blur=1.0, noise=2.0, seed=3)
        per_image(work / "img")
        print("\n| images (canny, --fit) | wall | CPU | CPU an image | peak RSS |\n|---|---|---|---|---|")
        for n in (100, args.images):
            folder_memory(work / "img", n, work)
    print(load())


if __name__ == "__main__":
    main()
