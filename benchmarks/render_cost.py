"""The rates behind `render`'s cost estimate (wiredsl/io/render.py: RAY_TESTS_A_SECOND, PIXELS_A_SECOND):
each scene rendered (one pose, left camera), its estimate printed beside the CPU it took.

    PYTHONPATH=. python benchmarks/render_cost.py scenes/lab.wd scenes/fisheye.wd
"""

from __future__ import annotations

import sys
import time

import numpy as np

import wiredsl
from wiredsl.engine.world import build_world, surface_triangles
from wiredsl.io import render as rd


def main(paths: list[str]) -> None:
    for path in paths:
        scene = wiredsl.compile(path)
        world = build_world(scene)
        sil, _ = surface_triangles(world)
        tris = np.concatenate([world.triangles, sil]) if len(sil) else world.triangles
        look = rd.Look(boards=rd.scene_boards(scene))
        t0 = time.process_time()
        images = list(rd.render(scene, look=look, poses=[0], cameras="left", world=world, force=True))
        took = time.process_time() - t0
        from wiredsl.engine.simulate import Options
        from wiredsl.montecarlo import Run

        run = Run.create(scene, world, None, 0, Options(tolerance=rd.TOLERANCE, poses=[0], right=False))
        views = [r.left for r in run.ideal()]
        cost = rd.estimate(views, tris, look)
        print(f"{path}: {len(images)} image(s) {images[0].camera.width} x {images[0].camera.height}: "
              f"took {took:.2f} s CPU; estimate {cost.seconds:.2f} s ({cost.ray_tests:.3g} ray tests, "
              f"{cost.pixels:.3g} pixels), {cost.bytes / 1e9:.2f} GB")


if __name__ == "__main__":
    main(sys.argv[1:])
