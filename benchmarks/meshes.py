"""What `mesh read` costs: real CAD parts (compile cold and from the features' cache, a view with exact
visibility, peak memory against occlusion.BUDGET), then importing a mesh (read, features, scene nodes) and exact hidden
lines per view on
a scene with it, at several sizes of mesh, each size in its own process (so its peak RSS is its own).
Times are CPU times of the one process (OMP_NUM_THREADS=1): a shared machine slows wall time, not these.

The mesh is a sphere (every triangle an occluder, its outline a contour of each view) behind which stands
scenes/meshes.wd's crate; the robot's 3 poses x 2 cameras are the views.

    OMP_NUM_THREADS=1 python benchmarks/meshes.py
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from helpers import EYE_RIG  # noqa: E402  (the tests' stereo pair: one rig, written once)

SIZES = (1, 4, 16, 64)  # a uv sphere of (40 x 40) k: about 6,300 k triangles

SCENE = """wiredsl 1
model ball {{
  mesh read "ball.stl"
}}
model crate {{
  mesh read "{root}/scenes/meshes/crate.obj" scale 0.001 up y
}}
place ball as ball1 at (2.5m, 0, 0.6m)
place crate as crate1 at (3.6m, 0, 0)
""" + EYE_RIG.replace("{", "{{").replace("}", "}}") + """path approach {{
  straight from (0, 0) to (1m, 0) step 0.5m
}}
"""


def one(k: int) -> dict:
    import trimesh

    from wiredsl.engine.simulate import Options, simulate, visibility_masks
    from wiredsl.engine.world import build_world
    from wiredsl.language.compile import compile_file

    n = int(40 * k ** 0.5)
    ball = trimesh.creation.uv_sphere(radius=0.5, count=(n, n))
    with tempfile.TemporaryDirectory() as tmp:
        ball.export(Path(tmp) / "ball.stl")
        path = Path(tmp) / "s.wd"
        path.write_text(SCENE.format(root=Path.cwd().as_posix()))
        os.environ["XDG_CACHE_HOME"] = tmp  # a first read: the mesh cache (io/mesh.py) starts empty
        t0 = time.process_time()
        scene, _, _ = compile_file(path)
        t_import = time.process_time() - t0
    world = build_world(scene)
    o = Options(visibility="exact")
    masks = visibility_masks(scene, world, o)
    best = float("inf")
    for _ in range(3):
        t0 = time.process_time()
        results = simulate(scene, o, world, masks)
        best = min(best, time.process_time() - t0)
    views = 2 * len(results)
    contour = sum(1 for r in results for f in r.left.features if world.feature_kind[f.fid] == "contour")
    return {"triangles": len(ball.faces), "import_s": t_import, "view_ms": 1000 * best / views,
            "contour_edges_left": contour // len(results),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


PARTS = (("counter.stl", "units mm origin centre", "(2.0m, 0, 0.1m)"),  # 83,750 triangles
         ("cycloidal.ply", "scale 0.2 origin centre", "(2.0m, 0, 0.3m)"))  # 43,368, 244 non-manifold edges


def part(name: str, clauses: str, at: str) -> dict:
    """A real CAD part of tests/meshes/ (unpacked): compile cold and from the features' cache, then one view
    (the left camera at the first pose) with exact visibility; peak RSS against the occlusion budget."""
    import gzip

    from wiredsl.engine import occlusion
    from wiredsl.engine.simulate import Options, simulate, visibility_masks
    from wiredsl.engine.world import build_world
    from wiredsl.language.compile import compile_file

    root = Path(__file__).resolve().parent.parent
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / name).write_bytes(gzip.open(root / "tests" / "meshes" / f"{name}.gz").read())
        text = SCENE.replace('mesh read "ball.stl"', f'mesh read "{name}" {clauses}').replace(
            "at (2.5m, 0, 0.6m)", f"at {at}").format(root=root.as_posix())
        crate = f'model crate {{\n  mesh read "{root.as_posix()}/scenes/meshes/crate.obj" scale 0.001 up y\n}}\n'
        text = text.replace(crate, "").replace("place crate as crate1 at (3.6m, 0, 0)\n", "")
        path = Path(tmp) / "s.wd"
        path.write_text(text)
        os.environ["XDG_CACHE_HOME"] = tmp
        t0 = time.process_time()
        scene, _, _ = compile_file(path)
        cold = time.process_time() - t0
        t0 = time.process_time()
        scene, _, _ = compile_file(path)
        cached = time.process_time() - t0
    scene = scene.model_copy(update={"path": scene.path.model_copy(update={"poses": scene.path.poses[:1]})})
    world = build_world(scene)
    o = Options(visibility="exact", right=False)
    masks = visibility_masks(scene, world, o)
    t0 = time.process_time()
    results = simulate(scene, o, world, masks)
    view = time.process_time() - t0
    return {"name": name, "triangles": len(world.triangles), "cold_s": cold, "cached_s": cached, "view_s": view,
            "features": len(results[0].left.features), "budget_mb": occlusion.BUDGET / 2**20,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--one":
        print(json.dumps(one(int(sys.argv[2]))))
        return
    if len(sys.argv) == 3 and sys.argv[1] == "--part":
        print(json.dumps(part(*PARTS[int(sys.argv[2])])))
        return
    print("real CAD parts (tests/meshes/), one view with --visibility exact, one core, each in its own process:")
    print(f"{'part':>14} {'occluding tris':>14} {'compile cold (s)':>16} {'cached (s)':>10} {'view CPU (s)':>12}"
          f" {'features':>8} {'peak RSS (MB)':>13} {'budget (MB)':>11}")
    for k in range(len(PARTS)):
        out = subprocess.run([sys.executable, __file__, "--part", str(k)], capture_output=True, text=True, check=True)
        r = json.loads(out.stdout.splitlines()[-1])
        print(f"{r['name']:>14} {r['triangles']:>14,} {r['cold_s']:>16.2f} {r['cached_s']:>10.2f} {r['view_s']:>12.1f}"
              f" {r['features']:>8} {r['peak_rss_mb']:>13.0f} {r['budget_mb']:>11.0f}")
    print("sphere mesh + crate, exact hidden lines, one core (each size in its own process):")
    print(f"{'triangles':>10} {'import (s)':>11} {'per view (ms)':>14} {'contour edges':>14} {'peak RSS (MB)':>14}")
    for k in SIZES:
        out = subprocess.run([sys.executable, __file__, "--one", str(k)], capture_output=True, text=True, check=True)
        r = json.loads(out.stdout.splitlines()[-1])
        print(f"{r['triangles']:>10,} {r['import_s']:>11.2f} {r['view_ms']:>14.1f} {r['contour_edges_left']:>14}"
              f" {r['peak_rss_mb']:>14.0f}")


if __name__ == "__main__":
    main()
