"""How well `--visibility auto` foresees what exact hidden lines cost (run.exact_seconds, issue 37).

For each of 12 scenes (the lab and the example scenes, uv spheres of 6k to 101k triangles behind a crate, and the real
parts of tests/meshes/: the ADIS16480 housing, the bunny scan, the cycloidal gear and the counter, placed as
benchmarks/meshes.py places them), one view with --visibility exact (the left camera at the first pose, after one
warm-up view), each scene in its own process: its counts, its CPU, the estimate and their ratio. `--fit` refits
run.py's coefficients to these views (non-negative least squares on relative errors) and prints them, with each
scene's ratio when it is left out of the fit. CPU times of the process (OMP_NUM_THREADS=1).

    OMP_NUM_THREADS=1 python benchmarks/visibility_cost.py [--fit]
"""

from __future__ import annotations

import gzip
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

SCENES = ("file:scenes/lab.wd", "file:scenes/meshes.wd", "file:scenes/handheld.wd", "file:scenes/fisheye.wd",
          "file:tests/data/table_box_cup.wd", "sphere:1", "sphere:4", "sphere:16", "part:adis16480.stl",
          "part:bunny.ply", "part:cycloidal.ply", "part:counter.stl")
PARTS = {"counter.stl": ("units mm origin centre", "(2.0m, 0, 0.1m)"),
         "cycloidal.ply": ("scale 0.2 origin centre", "(2.0m, 0, 0.3m)"),
         "adis16480.stl": ("scale 4 origin centre", "(1.2m, 0, 0.3m)"),
         "bunny.ply": ("scale 2 origin centre", "(2.0m, 0, 0.3m)")}


def view(path: Path) -> dict:
    """The counts of the scene's world and the CPU of one exact view."""
    from wiredsl import run as runs
    from wiredsl.engine.simulate import Options, simulate, visibility_masks
    from wiredsl.engine.world import build_world
    from wiredsl.language.compile import compile_file

    scene = compile_file(path)[0]
    scene = scene.model_copy(update={"path": scene.path.model_copy(update={"poses": scene.path.poses[:1]})})
    w = build_world(scene)
    o = Options(visibility="exact", right=False)
    masks = visibility_masks(scene, w, o)
    simulate(scene, o, w, masks)  # warm: numpy's and the grids' first calls
    t0 = time.process_time()
    simulate(scene, o, w, masks)
    return {"T": len(w.triangles), "L": len(w.lines), "C": len(w.ell_c) + len(w.sil_pair), "S": len(w.sil_pair),
            "cpu": time.process_time() - t0, "estimate": runs.exact_seconds(w, 1)}


def one(spec: str) -> dict:
    import meshes  # benchmarks/meshes.py: its scene of a mesh before the tests' stereo pair

    kind, arg = spec.split(":", 1)
    if kind == "file":
        return view(ROOT / arg)
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["XDG_CACHE_HOME"] = tmp
        text = meshes.SCENE.format(root=ROOT.as_posix())
        if kind == "part":
            clauses, at = PARTS[arg]
            (Path(tmp) / arg).write_bytes(gzip.open(ROOT / "tests" / "meshes" / f"{arg}.gz").read())
            text = text.replace('mesh read "ball.stl"', f'mesh read "{arg}" {clauses}').replace(
                "at (2.5m, 0, 0.6m)", f"at {at}")
        else:
            import trimesh

            n = int(40 * int(arg) ** 0.5)
            trimesh.creation.uv_sphere(radius=0.5, count=(n, n)).export(Path(tmp) / "ball.stl")
        (Path(tmp) / "s.wd").write_text(text)
        return view(Path(tmp) / "s.wd")


def refit(rows: list[dict]) -> None:
    import numpy as np
    from scipy.optimize import nnls

    X = np.array([[1, r["T"], r["L"] * r["T"] ** 0.5, r["C"] * r["T"] ** 0.5, r["C"] * r["S"]] for r in rows], float)
    y = np.array([r["cpu"] for r in rows])
    c, _ = nnls(X / y[:, None], np.ones(len(y)))
    print("fitted EXACT_VIEW, EXACT_TRIANGLE, EXACT_SEGMENT, EXACT_CURVE, EXACT_CURVE_SURFACE =",
          ", ".join(f"{v:.2g}" for v in c))
    print("fitted / CPU:", " ".join(f"{v:.2f}" for v in X @ c / y))
    out = []
    for i in range(len(y)):
        k = np.arange(len(y)) != i
        ck, _ = nnls(X[k] / y[k, None], np.ones(k.sum()))
        out.append(X[i] @ ck / y[i])
    print("left out of the fit, fitted / CPU:", " ".join(f"{v:.2f}" for v in out))


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--one":
        print(json.dumps(one(sys.argv[2])))
        return
    print(f"{'scene':>28} {'tris T':>7} {'segs L':>6} {'curves C':>8} {'surfs S':>7} {'view CPU s':>10}"
          f" {'estimate s':>10} {'est/CPU':>7}")
    rows = []
    for spec in SCENES:
        out = subprocess.run([sys.executable, __file__, "--one", spec], capture_output=True, text=True, check=True,
                             cwd=ROOT)
        r = json.loads(out.stdout.splitlines()[-1])
        rows.append(r)
        print(f"{spec.split(':', 1)[1]:>28} {r['T']:>7,} {r['L']:>6,} {r['C']:>8,} {r['S']:>7,} {r['cpu']:>10.3f}"
              f" {r['estimate']:>10.3f} {r['estimate'] / r['cpu']:>7.2f}", flush=True)
    if "--fit" in sys.argv:
        refit(rows)


if __name__ == "__main__":
    main()
