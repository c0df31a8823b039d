"""`wiredsl render`'s cost: CPU seconds a view, in-process (process start left out), best of 3.

    python benchmarks/render_speed.py

For each scene: the first view of a camera (its rays are solved once: undistortion on an 8 px grid and
splines) and the views after it, with and without faces, blur and noise.
"""

from __future__ import annotations

import time
from pathlib import Path

from wiredsl.io import render as rd
from wiredsl.language.compile import compile_file

ROOT = Path(__file__).resolve().parent.parent


def cpu(fn) -> float:
    best = float("inf")
    for _ in range(3):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best


def main() -> None:
    print(f"{'scene':12} {'image':>9} {'look':28} {'views':>5} {'CPU s':>7} {'s a view':>8}")
    for name, poses in (("lab", (0, 1, 2, 3)), ("box", (0, 1)), ("chessboard", (0, 1, 2, 3)), ("fisheye", (0,))):
        scene, _, _ = compile_file(ROOT / "scenes" / f"{name}.wd")
        cam = scene.camera(scene.rig.left.camera)
        for label, look in (("faces, step edges", rd.Look()),
                            ("faces, blur 1, noise 2", rd.Look(blur=1.0, noise=2.0)),
                            ("no faces", rd.Look(faces="none"))):
            n = 2 * len(poses)
            def views(scene=scene, poses=poses, look=look):
                return list(rd.render(scene, pipeline=None, seed=1, poses=poses, look=look))

            s = cpu(views)
            print(f"{name:12} {cam.width:>4}x{cam.height:<4} {label:28} {n:>5} {s:>7.2f} {s / n:>8.3f}")


if __name__ == "__main__":
    main()
