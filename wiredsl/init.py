"""`wiredsl init`: a starter project (a scene, a study, a CI script) or a plug-in package template.

The templates are strings here, filled by `str.format`-free substitution of `{{name}}`, `{{package}}`,
`{{effect}}`, `{{measure}}`, `{{detector}}` and `{{version}}`, so braces in the files themselves need no
escaping. The project is written into a temporary folder beside the target and renamed into place: a failure
leaves nothing behind.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from pathlib import Path

NAME = re.compile(r"^[a-z][a-z0-9_]{0,39}$")  # a scene name, a Python package and part of an entry point name


class InitError(ValueError):
    """A project that cannot be written (a bad name, an existing folder): a message for the user, exit 1."""


def package_name(name: str) -> str:
    """The Python package (and scene) name of a project name: lower case, '-' as '_'; refused if not an
    identifier of at most 40 characters."""
    import keyword

    package = name.replace("-", "_")
    if not NAME.fullmatch(package):  # (match's `$` also matches before a final newline)
        raise InitError(f"{name!r} is not a usable name: lower-case letters, digits, '_' or '-', starting with a "
                        "letter, at most 40 characters (it names the scene and the Python package)")
    if keyword.iskeyword(package):  # `import class` does not compile
        raise InitError(f"{name!r} is a Python keyword, which cannot name the Python package: choose another name")
    return package


# The world of both templates' scenes: a crate, the camera and the rig, view-points and a path.
WORLD = """\
wiredsl 1
scene {{package}}

# One model: a crate, in its own frame (metres).
model crate {
  polyline top closed through (0, 0, 0.5) (0.6, 0, 0.5) (0.6, 0.4, 0.5) (0, 0.4, 0.5)
  line edge_a from (0, 0, 0) to (0, 0, 0.5)
  line edge_b from (0.6, 0, 0) to (0.6, 0, 0.5)
  corner top_a at (0, 0, 0.5) joins top edge_a
  corner top_b at (0.6, 0, 0.5) joins top edge_b
  face front through (0, 0, 0) (0.6, 0, 0) (0.6, 0, 0.5) (0, 0, 0.5)
}
place crate as crate1 at (2.8m, 0.3m, 0) rotate z -90deg

# The camera (replace with `read "calib/your_file.yaml"`) and the rig on the robot.
camera eye {
  focal 6mm
  pixel 0.01mm
  size (640px, 480px)
  k 0.02
}

rig head {
  left eye at (0.1m, 0.06m, 0.8m) looking (1, 0, -0.1)
  right eye at (0.1m, -0.06m, 0.8m) looking (1, 0, -0.1)
}

viewpoints floor {
  grid from (0, -1m) to (2m, 1m) spacing 1m
  visibility auto
}

# The robot's path (or `read "trajectory.txt"` with a `body`).
path approach {
  straight from (0.2m, 0) to (1.8m, 0) step 0.4m
}

"""

# The starter scene: the world, then a pipeline and a study of the built-in effects.
SCENE = WORLD + """\
# What your detector does to the ideal image, in data-flow order.
pipeline detector default {
  edge_loss fraction 29%
  lateral_shift range 3px
  corner_loss keep 90%
}

# How much of the view survives as edges shift further?
study shift {
  pipeline detector
  vary lateral_shift.range values [0, 2px, 4px]
  trials 8
  seed 1
  measure survival
}
"""

GITIGNORE = """\
# wiredsl's outputs (build, study), virtual environments, caches
build/
.venv/
__pycache__/
*.pyc
*.egg-info/
"""

CI_SCRIPT = """\
#!/usr/bin/env bash
# Checks every scene, compiles each and validates it against wiredsl's schema, then runs the scene and its study
# and validates what they wrote. Run it locally (`bash ci.sh`) or from CI (.github/workflows/wiredsl.yml).
set -euo pipefail
cd "$(dirname "$0")"
wiredsl check scenes/*.wd
# the canonical layout (docs: the language reference): a scene written by hand fails here until `wiredsl fmt
# scenes/*.wd` rewrites it so (long statements continued with a trailing backslash)
wiredsl fmt --check scenes/*.wd || { echo "ci.sh: run 'wiredsl fmt scenes/*.wd' to format the scenes" >&2; exit 1; }
mkdir -p build/ci
for f in scenes/*.wd; do
  wiredsl compile "$f" -o "build/ci/$(basename "$f" .wd).json"
done
wiredsl validate build/ci/*.json
wiredsl build scenes/{{package}}.wd -o build/ci/run --seed 1 --trials 4 --format jsonl --no-svg
wiredsl validate build/ci/run/features.jsonl build/ci/run/manifest.json
wiredsl study scenes/{{package}}.wd shift -o build/ci/study --executor inprocess --no-plots
wiredsl validate build/ci/study/table.json build/ci/study/manifest.json
echo "ci.sh: all checks passed"
"""

WORKFLOW = """\
# GitHub Actions: the project's checks (ci.sh) on every push. Set the repository variable WIREDSL to what pip
# installs wiredsl from: a git URL (git+https://...@v{{version}}) or a path; wiredsl is not on PyPI.
name: wiredsl
on: [push, pull_request]
jobs:
  check:
    runs-on: ubuntu-latest
    steps:
      - uses: actions/checkout@v4
      - uses: actions/setup-python@v5
        with:
          python-version: "3.11"
      - run: test -n "${{ vars.WIREDSL }}" || { echo "set the repository variable WIREDSL (see above)"; exit 1; }
      - run: pip install "${{ vars.WIREDSL }}"
      - run: bash ci.sh
"""

PROJECT_README = """\
# {{name}}

A wiredsl project: `scenes/{{package}}.wd` is a scene with one model, a stereo rig, a path, a detector's
pipeline and a study.

```sh
wiredsl check scenes/{{package}}.wd        # every problem, with file, line and column
wiredsl build scenes/{{package}}.wd        # build/{{package}}/: features.json, manifest.json, an SVG a pose
wiredsl study scenes/{{package}}.wd shift  # build/{{package}}-shift/: the study's table and plots
bash ci.sh                                 # what CI runs (.github/workflows/wiredsl.yml)
```

The study's plots need matplotlib (`pip install '.[plot]'` in wiredsl's checkout); without it, give `--no-plots`.
"""

# --- the plug-in package ---------------------------------------------------------------------------------------

PLUGIN_PYPROJECT = """\
[build-system]
requires = ["hatchling>=1.21"]
build-backend = "hatchling.build"

[project]
name = "{{name}}"
version = "0.1.0"
description = "wiredsl plug-in: {{effect}} (an uncertainty source), {{measure}} (a measure), {{detector}} (a detector)"
requires-python = ">=3.11"
dependencies = ["wiredsl>={{version}}", "numpy>=1.26"]

[project.optional-dependencies]
# fast: the effect's compiled kernel (numba), used by wiredsl's kernel engine; without it the numpy code runs.
fast = ["numba>=0.59"]
# test: wiredsl's images and plot extras too (OpenCV, matplotlib), for `wiredsl verify` with the detector.
test = ["pytest>=8", "wiredsl[images,plot]"]

# wiredsl finds plug-ins by these groups; the name on the left is the name scenes use, and must equal the
# class's `name`.
[project.entry-points."wiredsl.effects"]
{{effect}} = "{{package}}.effect:CornerNoise"

[project.entry-points."wiredsl.measures"]
{{measure}} = "{{package}}.measure:CornerError"

[project.entry-points."wiredsl.detectors"]
{{detector}} = "{{package}}.detect:SobelEdges"

[tool.hatch.build.targets.wheel]
packages = ["src/{{package}}"]

[tool.pytest.ini_options]
testpaths = ["tests"]
"""

PLUGIN_INIT = '''\
"""{{name}}: a wiredsl plug-in. The effect `{{effect}}` (effect.py, its numba kernel in kernel.py), the
measure `{{measure}}` (measure.py) and the detector `{{detector}}` (detect.py), found by wiredsl through the entry
points in pyproject.toml."""
'''

PLUGIN_EFFECT = '''\
"""Corner localisation noise: each detected corner moves by an isotropic Gaussian of standard deviation `sigma`
pixels on each axis. Your detector's own noise model goes here.

This is the numpy reference, which wiredsl's numpy engine runs. kernel.py is the same stage compiled with numba
(optional): the kernel engine runs it when numba is installed, and the tests hold it to this code.
"""

from __future__ import annotations

import numpy as np

from wiredsl.effects.base import Effect, KernelStage, Params, param
from wiredsl.engine import imageset as im


class CornerNoiseParams(Params):
    # param(default, unit kind, doc, bounds): the kind ("length", "angle", "image", "number", "fraction") makes
    # the language convert units (`sigma 0.5px`) and check the bounds (E110).
    sigma: float = param(0.5, "image", "standard deviation of each corner coordinate", ge=0, le=1000)


class CornerNoise(Effect):
    name = "{{effect}}"  # the entry point's name
    acts_on = "corner detection"  # where it runs in a real system (sets the data-flow order check, W161)
    Params = CornerNoiseParams
    doc = __doc__
    # the compiled stage: "module:function", its Params fields in order, its statistics row's columns
    kernel = KernelStage("{{package}}.kernel:stage", ("sigma",), (("count", "add"), ("sum_sq", "add")))

    # Methods are class methods: wiredsl never makes an instance.
    @classmethod
    def is_identity(cls, p: CornerNoiseParams) -> bool:
        return p.sigma == 0  # the stage is skipped

    @classmethod
    def disturb(cls, p: CornerNoiseParams, s: im.ImageSet, ctx) -> im.ImageSet:
        # s holds every trial of a batch: strokes (pts, start, fid, kind, ...) and corners (corners, corner_fid,
        # corner_trial). Draw only with ctx.draws: keyed by (seed, stage, trial, pose, camera), so a trial's
        # values depend on nothing else. per_item=2, normal=True: normals 2c and 2c + 1 of corner c's trial key.
        move = p.sigma * ctx.draws(cls.name, s.corner_trial, per_item=2, normal=True)
        ctx.stats.add(cls.name, count=len(move), sum_sq=float((move * move).sum()))
        return im.replace(s, corners=s.corners + move)  # a new ImageSet of the same layout

    @classmethod
    def report(cls, p: CornerNoiseParams, stats) -> dict:
        """What the run manifest records for the stage: the measured RMS against the declared sigma."""
        s = stats.sums[cls.name]
        rms = float(np.sqrt(s["sum_sq"] / (2 * s["count"]))) if s["count"] else None
        return {"rms_per_axis_px": {"declared": p.sigma, "measured": rms}}
'''

PLUGIN_KERNEL = '''\
"""The compiled stage of `{{effect}}` (numba), named by its KernelStage; imported only when a run uses wiredsl's
kernel engine, so importing the effect does not import numba. One trial's view in, the same arrays out."""

from numba import njit

from wiredsl.engine.kernel import _normal_pair


@njit(cache=True)
def stage(pts, start, meta, corners, cfid, key, params, epipole, right, stats):
    sigma = params[0]
    out = corners.copy()
    for c in range(len(corners)):
        gx, gy = _normal_pair(key, c)  # normals 2c and 2c + 1 of the trial's key: what ctx.draws gives corner c
        out[c, 0] = corners[c, 0] + sigma * gx
        out[c, 1] = corners[c, 1] + sigma * gy
        stats[0] += 1
        stats[1] += (sigma * gx) ** 2 + (sigma * gy) ** 2
    return pts, start, meta, out, cfid
'''

PLUGIN_MEASURE = '''\
"""Corner error: per trial, the RMS distance in pixels between each disturbed corner and the ideal image of the
same corner (both cameras), over the corners that were kept; and how many were kept. Your recognition or SLAM
front end goes here, fed the disturbed features.
"""

from __future__ import annotations

import numpy as np

from wiredsl.measures.base import Measure, Params


class CornerErrorParams(Params):
    """No parameters (declare them with wiredsl.measures.base.param, as an effect does)."""


class CornerError(Measure):
    name = "{{measure}}"
    Params = CornerErrorParams
    statistics = ("rms_error", "kept")
    weights = {"rms_error": "kept"}  # a study averages rms_error over trials weighted by kept
    units = {"rms_error": "px", "kept": "count"}
    doc = __doc__

    @classmethod
    def measure(cls, p, prepared, pose, disturbed: dict, n_trials: int) -> dict:
        # pose: the ideal PoseResult (pose.left / pose.right: View with .features, each with .fid, .kind and
        # .points); disturbed[side]: the batch's disturbed ImageSet, trials numbered 0..n_trials-1.
        sum_sq, kept = np.zeros(n_trials), np.zeros(n_trials)
        for side, s in disturbed.items():
            view = getattr(pose, side)
            ideal = {f.fid: f.points[0] for f in view.features if f.kind == "corner"}
            if not ideal or not len(s.corners):
                continue
            known = np.isin(s.corner_fid, list(ideal))
            where = np.array([ideal.get(int(f), (np.nan, np.nan)) for f in s.corner_fid]).reshape(-1, 2)
            d2 = ((s.corners - where) ** 2).sum(axis=1)
            sum_sq += np.bincount(s.corner_trial[known], weights=d2[known], minlength=n_trials)
            kept += np.bincount(s.corner_trial[known], minlength=n_trials)
        rms = np.sqrt(np.divide(sum_sq, kept, out=np.zeros(n_trials), where=kept > 0))
        return {"rms_error": rms, "kept": kept}
'''

# The plug-in template's scene: the same world, its effect in a pipeline and its measure in a study.
PLUGIN_SCENE = WORLD + """\
# The plug-in's effect in a pipeline, and its measure in a study.
pipeline detector default {
  {{effect}} sigma 0.5px
}

study noise {
  pipeline detector
  vary {{effect}}.sigma values [0, 1px, 2px]
  trials 8
  seed 1
  measure {{measure}}
}
"""

PLUGIN_DETECTOR = '''\
"""Sobel edges, in numpy alone: smooth, take the Sobel gradient, keep the pixels whose gradient magnitude is a
maximum along the gradient's direction (non-maximum suppression) and above a threshold. Your detector goes here.

`wiredsl verify --detector {{detector}}` runs it on your images; the verification wants the edge map and the
grey-level gradient over the whole image (it finds each edge's sub-pixel position from the magnitudes across it).
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from wiredsl.verify.detectors import Detection, Detector, DetectorParams


class SobelParams(DetectorParams):
    # every field needs a default; `--param threshold=20` sets one on the command line
    threshold: float = Field(10.0, ge=0, description="weakest gradient kept (grey levels a pixel)")
    blur: float = Field(1.0, ge=0, le=20, description="Gaussian smoothing first, its sigma in px (0: none)")


def smoothed(image: np.ndarray, sigma: float) -> np.ndarray:
    """The image convolved with a Gaussian of `sigma` px (rows, then columns; the border pixels repeated)."""
    out = image.astype(np.float64)
    if sigma == 0:
        return out
    r = int(np.ceil(3 * sigma))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    for axis in (0, 1):
        padded = np.pad(out, [(r, r) if a == axis else (0, 0) for a in (0, 1)], mode="edge")
        n = out.shape[axis]
        out = sum(w * padded.take(np.arange(i, i + n), axis=axis) for i, w in enumerate(k))
    return out


def sobel(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Sobel gradient (gx along columns, gy along rows), divided by 8: grey levels a pixel."""
    p = np.pad(image, 1, mode="edge")
    dx = p[:, 2:] - p[:, :-2]  # central differences, then smoothed across by (1, 2, 1)
    dy = p[2:, :] - p[:-2, :]
    gx = (dx[:-2] + 2 * dx[1:-1] + dx[2:]) / 8
    gy = (dy[:, :-2] + 2 * dy[:, 1:-1] + dy[:, 2:]) / 8
    return gx, gy


def thinned(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Non-maximum suppression: a pixel whose magnitude is larger than its neighbour behind it and no smaller
    than the one ahead, along the gradient rounded to one of four directions (0, 45, 90, 135 deg)."""
    m = np.hypot(gx, gy)
    p = np.pad(m, 1)
    h, w = m.shape
    ahead = {d: p[1 + d[1]:1 + d[1] + h, 1 + d[0]:1 + d[0] + w] for d in ((1, 0), (1, 1), (0, 1), (-1, 1))}
    behind = {d: p[1 - d[1]:1 - d[1] + h, 1 - d[0]:1 - d[0] + w] for d in ahead}
    sector = np.round(np.degrees(np.arctan2(gy, gx)) / 45).astype(int) % 4  # 0: along x, 1: 45 deg, ...
    keep = np.zeros(m.shape, bool)
    for s, d in enumerate(ahead):
        keep |= (sector == s) & (m > behind[d]) & (m >= ahead[d])
    return keep


class SobelEdges(Detector):
    name = "{{detector}}"  # the entry point's name
    doc = "Sobel gradient edges thinned along the gradient and thresholded (numpy only)."
    Params = SobelParams
    finds = "edges"  # what the verification tests: "edges" or "corners"

    @classmethod
    def detect(cls, image: np.ndarray, p: SobelParams) -> Detection:
        # image: (height, width) uint8, grey; pixel (i, j)'s centre is the point x = i, y = j
        gx, gy = sobel(smoothed(image, p.blur))
        edges = thinned(gx, gy) & (np.hypot(gx, gy) > p.threshold)
        return Detection(edges=edges, gx=gx.astype(np.float32), gy=gy.astype(np.float32))
'''

PLUGIN_TESTS = '''\
"""The plug-in's own tests: wiredsl finds it, a scene uses it, the effect draws what it declares, the kernel
gives what the numpy code gives, the measure measures what the effect did, and the detector finds drawn edges
where they were drawn, nothing in a flat image, and runs in `wiredsl verify`."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import wiredsl

SCENE = Path(__file__).resolve().parent.parent / "scenes" / "demo.wd"


def wiredsl_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "wiredsl", *args], capture_output=True, text=True)


def test_wiredsl_finds_the_three_entry_points():
    out = wiredsl_cli("plugins")
    assert out.returncode == 0, out.stderr
    lines = {tuple(line.split("\\t")[:2]): line for line in out.stdout.splitlines()}
    assert lines[("effect", "{{effect}}")].endswith("ok"), out.stdout
    assert lines[("measure", "{{measure}}")].endswith("ok"), out.stdout
    assert lines[("detector", "{{detector}}")].endswith("ok"), out.stdout


def test_the_scene_checks_and_a_bad_parameter_is_a_diagnostic(tmp_path):
    assert wiredsl_cli("check", str(SCENE)).returncode == 0
    bad = tmp_path / "bad.wd"
    bad.write_text(SCENE.read_text().replace("{{effect}} sigma 0.5px", "{{effect}} sigma -1px"))
    out = wiredsl_cli("check", str(bad))
    assert out.returncode == 1 and "E110" in out.stderr and "Traceback" not in out.stderr, out.stderr


def corner_moves(engine: str = "numpy", trials: int = 400) -> np.ndarray:
    """Disturbed minus ideal corner positions (matched by camera and feature) over many trials of the demo's
    pipeline (sigma 0.5 px)."""
    scene = wiredsl.compile(SCENE)
    moves = []
    for batch in wiredsl.simulate(scene, trials=trials, seed=3, poses=[2, 3], engine=engine):
        for pose, disturbed, _ in batch.disturbed:
            for side, s in disturbed.items():
                ideal = {f.fid: f.points[0] for f in getattr(pose, side).features if f.kind == "corner"}
                moves += [c - ideal[int(f)] for c, f in zip(s.corners, s.corner_fid, strict=True)]
    return np.array(moves)


def test_the_effect_moves_corners_by_its_sigma():
    """The standard deviation of the moves over 400 trials matches sigma to a few standard errors."""
    moves = corner_moves()
    assert len(moves) > 1000
    sd = moves.std(axis=0)
    assert np.all(np.abs(sd - 0.5) < 0.5 * 4 / np.sqrt(2 * len(moves))), sd
    assert np.all(np.abs(moves.mean(axis=0)) < 0.5 * 4 / np.sqrt(len(moves)))


def test_the_same_seed_gives_the_same_corners():
    a, b = corner_moves(trials=20), corner_moves(trials=20)
    assert np.array_equal(a, b)


def test_the_kernel_gives_what_the_numpy_code_gives():
    pytest.importorskip("numba")
    numpy_moves, kernel_moves = corner_moves("numpy", 50), corner_moves("kernel", 50)
    assert numpy_moves.shape == kernel_moves.shape
    assert np.abs(numpy_moves - kernel_moves).max() < 1e-9


def test_the_measure_reads_the_effects_sigma():
    """With 2D Gaussian moves of sigma per axis, the RMS distance is sigma * sqrt(2)."""
    from {{package}}.measure import CornerError

    scene = wiredsl.compile(SCENE)
    params = CornerError.Params()
    rms, kept = [], []
    for batch in wiredsl.simulate(scene, trials=300, seed=5, poses=[2, 3]):
        for pose, disturbed, _ in batch.disturbed:
            out = CornerError.measure(params, None, pose, disturbed, batch.n_trials)
            assert set(out) == set(CornerError.statistics)
            rms.append(out["rms_error"])
            kept.append(out["kept"])
    rms, kept = np.concatenate(rms), np.concatenate(kept)
    assert kept.sum() > 1000
    mean_sq = (rms**2 * kept).sum() / kept.sum()
    assert abs(np.sqrt(mean_sq) - 0.5 * np.sqrt(2)) < 0.03, np.sqrt(mean_sq)


def step_image(x0: float, angle: float, shape=(48, 64), dark=30.0, light=128.0) -> np.ndarray:
    """A straight step edge through (x0, rows / 2), `angle` degrees from the vertical, light on the side of its
    normal (cos angle, sin angle); each pixel's grey is the share of its area on either side (16 x 16 samples a
    pixel), rounded to 8 bits, as a camera sees an object's boundary."""
    a = np.radians(angle)
    sub = (np.arange(16) + 0.5) / 16 - 0.5
    y, x = np.mgrid[0:shape[0], 0:shape[1]]
    xs = x[..., None, None] + sub[None, None, None, :]
    ys = y[..., None, None] + sub[None, None, :, None]
    light_share = (((xs - x0) * np.cos(a) + (ys - shape[0] / 2) * np.sin(a)) > 0).mean(axis=(2, 3))
    return np.round(dark + (light - dark) * light_share).astype(np.uint8)


@pytest.mark.parametrize("angle", [0.0, 10.0, 30.0, -40.0])
@pytest.mark.parametrize("x0", [20.0, 20.25, 20.5, 20.8])
def test_the_detector_finds_a_drawn_step_edge_within_a_pixel(x0, angle):
    """Every edge pixel (3 px from the border) lies within a pixel of the drawn edge, every row crossing it has
    one, and its gradient points across the edge, towards the light side."""
    from {{package}}.detect import SobelEdges

    image = step_image(x0, angle)
    found = SobelEdges.detect(image, SobelEdges.Params())
    a = np.radians(angle)
    y, x = np.nonzero(found.edges[3:-3, 3:-3])
    y, x = y + 3, x + 3
    distance = (x - x0) * np.cos(a) + (y - image.shape[0] / 2) * np.sin(a)
    assert len(x) and np.abs(distance).max() <= 1.0, np.abs(distance).max()
    assert set(y) == set(range(3, image.shape[0] - 3))  # the edge is whole: one pixel or more a row
    gx, gy = found.gx[y, x], found.gy[y, x]
    assert np.all((gx * np.cos(a) + gy * np.sin(a)) > 0.95 * np.hypot(gx, gy))


def test_a_flat_image_gives_no_edges_even_with_sensor_noise():
    from {{package}}.detect import SobelEdges

    flat = np.full((48, 64), 128, np.uint8)
    assert not SobelEdges.detect(flat, SobelEdges.Params()).edges.any()
    noisy = np.clip(np.round(128 + np.random.default_rng(1).normal(0, 2, (480, 640))), 0, 255).astype(np.uint8)
    assert not SobelEdges.detect(noisy, SobelEdges.Params()).edges.any()  # 2 grey levels of noise: under 10


def test_wiredsl_verify_runs_the_detector_on_rendered_images(tmp_path):
    """The demo scene's five left views, drawn by wiredsl.io.render (blur 1 px, noise 2 grey levels) and
    verified with the detector: nearly every sample of the crate's edges has an edge where the scene puts it.
    A threshold above every gradient finds none."""
    from wiredsl.io import render

    scene = wiredsl.compile(SCENE)
    render.write(tmp_path / "frames", scene, look=render.Look(blur=1.0, noise=2.0), cameras="left", seed=1)
    images = str(tmp_path / "frames" / "left_*.png")
    out = wiredsl_cli("verify", str(SCENE), "--images", images, "--detector", "{{detector}}", "-o",
                      str(tmp_path / "v"))
    assert out.returncode == 0, out.stderr
    doc = json.loads((tmp_path / "v" / "verification.json").read_text())
    assert [d["name"] for d in doc["detectors"]] == ["{{detector}}"]
    (crate,) = doc["objects"]
    assert crate["images"] == 5 and crate["verified_fraction"] > 0.95, crate
    offsets = [r["offset_mean_px"] for r in doc["rows"] if r["kind"] == "edge" and r["offset_mean_px"] is not None]
    assert len(offsets) >= 20 and np.median(np.abs(offsets)) < 0.5, offsets
    out = wiredsl_cli("verify", str(SCENE), "--images", images, "--detector", "{{detector}}", "--param",
                      "threshold=1000", "-o", str(tmp_path / "none"))
    assert out.returncode == 0, out.stderr
    (crate,) = json.loads((tmp_path / "none" / "verification.json").read_text())["objects"]
    assert crate["verified_fraction"] == 0, crate


def test_a_study_over_the_effect_reports_the_measure(tmp_path):
    out = wiredsl_cli("study", str(SCENE), "noise", "-o", str(tmp_path / "study"), "--executor", "inprocess",
                      "--no-plots")
    assert out.returncode == 0, out.stderr
    table = json.loads((tmp_path / "study" / "table.json").read_text())
    text = json.dumps(table)
    assert "rms_error" in text and "{{effect}}.sigma" in text
'''

PLUGIN_README = """\
# {{name}}

A wiredsl plug-in package: the uncertainty source `{{effect}}` (src/{{package}}/effect.py, with an optional
numba kernel in kernel.py), the measure `{{measure}}` (src/{{package}}/measure.py) and the edge detector
`{{detector}}` (src/{{package}}/detect.py, numpy only), declared as entry points in pyproject.toml. Once
installed, scenes name the effect and the measure like built-ins: `wiredsl check` validates their parameters,
`wiredsl reference` lists them, a study can `vary {{effect}}.sigma` and `measure {{measure}}`; and `wiredsl
verify --detector {{detector}}` runs the detector on your images.

```sh
pip install -e '.[test]'        # add [fast] for the compiled kernel (numba)
wiredsl plugins                 # the three names, "ok"
pytest                          # the plug-in's own tests
wiredsl study scenes/demo.wd noise
wiredsl render scenes/demo.wd -o build/frames --cameras left --blur 1 --noise 2
wiredsl verify scenes/demo.wd --images 'build/frames/left_*.png' --detector {{detector}} -o build/verify
```
"""

STARTER = {"scenes/{{package}}.wd": SCENE, ".gitignore": GITIGNORE, "ci.sh": CI_SCRIPT,
           ".github/workflows/wiredsl.yml": WORKFLOW, "README.md": PROJECT_README}
PLUGIN = {"pyproject.toml": PLUGIN_PYPROJECT, "README.md": PLUGIN_README, ".gitignore": GITIGNORE,
          "src/{{package}}/__init__.py": PLUGIN_INIT, "src/{{package}}/effect.py": PLUGIN_EFFECT,
          "src/{{package}}/kernel.py": PLUGIN_KERNEL, "src/{{package}}/measure.py": PLUGIN_MEASURE,
          "src/{{package}}/detect.py": PLUGIN_DETECTOR,
          "scenes/demo.wd": PLUGIN_SCENE, "tests/test_{{package}}.py": PLUGIN_TESTS}


def fill(text: str, values: dict[str, str]) -> str:
    for key, value in values.items():
        text = text.replace("{{" + key + "}}", value)
    return text


def files(name: str, plugin: bool = False) -> dict[str, str]:
    """The project's files, relative path -> text."""
    from wiredsl import __version__

    package = package_name(name)
    values = {"name": name, "package": package, "effect": f"{package}_noise", "measure": f"{package}_error",
              "detector": f"{package}_edges", "version": __version__}
    return {fill(path, values): fill(text, values) for path, text in (PLUGIN if plugin else STARTER).items()}


def create(name: str, parent: Path = Path("."), plugin: bool = False) -> Path:
    """Write the project into parent/name (which must not exist, or be an empty folder); the path written."""
    content = files(name, plugin)
    target = Path(parent) / name
    if target.is_symlink() or (target.exists() and (not target.is_dir() or any(target.iterdir()))):
        raise InitError(f"{target} already exists and is not an empty folder: choose another name or remove it")
    if not target.parent.is_dir():
        raise InitError(f"{target.parent} is not a folder")
    tmp = Path(tempfile.mkdtemp(prefix=f".{name}.", dir=target.parent))
    try:
        for rel, text in content.items():
            path = tmp / rel
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text, encoding="utf-8")
            if rel.endswith(".sh"):
                path.chmod(0o755)
        tmp.chmod(0o777 & ~_umask())
        if target.exists():
            target.rmdir()
        os.rename(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
