"""Small helpers shared by the tests."""

from __future__ import annotations

import contextlib
import math
import sys
from pathlib import Path

import numpy as np

from wiredsl import plugins
from wiredsl.diagnostics import WiredslError
from wiredsl.engine import conics
from wiredsl.language.ast import Program, parse_text
from wiredsl.language.compile import compile_program

# The six faces of the 1 m box at the origin, as statements of a model block (hidden lines known by construction).
BOX_FACES = """
  face south through (0, 0, 0) (1, 0, 0) (1, 0, 1) (0, 0, 1)
  face north through (0, 1, 0) (1, 1, 0) (1, 1, 1) (0, 1, 1)
  face west through (0, 0, 0) (0, 1, 0) (0, 1, 1) (0, 0, 1)
  face east through (1, 0, 0) (1, 1, 0) (1, 1, 1) (1, 0, 1)
  face bottom through (0, 0, 0) (1, 0, 0) (1, 1, 0) (0, 1, 0)
  face top through (0, 0, 1) (1, 0, 1) (1, 1, 1) (0, 1, 1)
"""


# A stereo pair of 640 x 480 cameras 0.8 m up, 10 cm apart, looking along x and a little down.
EYE_RIG = """camera eye {
  focal 4mm
  pixel 0.008mm
  size (640px, 480px)
}
rig pair {
  left eye at (0, 0.05m, 0.8m) looking (1, 0, -0.15)
  right eye at (0, -0.05m, 0.8m) looking (1, 0, -0.15)
}
"""


def compile_text(text: str, path: str = "t.wd"):
    """Compile a one-file scene from text; returns (scene, warnings)."""
    file = parse_text(text, path)
    program = Program(file, files={path: file}, statements=list(file.statements))
    return compile_program(program)


def camera_scene(camera: str, right: str = "right c at (0, -0.06, 1) looking (1, 0, 0)", more: str = "") -> str:
    """A scene of one line seen by a rig whose left camera is `camera c { <camera> }` at (0, 0.06, 1), looking
    along x; `right` mounts its right camera, `more` adds statements (another camera) before the rig. The set-up
    of the calibration-file tests: `camera` is typically a `read "<file>"` statement."""
    return ("wiredsl 1\nmodel m {\n  line a from (2, -0.5, 0.3) to (2, 0.5, 1.8)\n}\nplace m as p\n"
            f"camera c {{\n  {camera}\n}}\n{more}"
            f"rig r {{\n  left c at (0, 0.06, 1) looking (1, 0, 0)\n  {right}\n}}\npath run {{ pose (0, 0) }}\n")


def errors_of(text: str) -> list[str]:
    """'line:col: CODE message' of every error a text produces."""
    try:
        compile_text(text)
    except WiredslError as err:
        return [f"{d.span.line}:{d.span.col}: {d.code} {d.message}" for d in err.diagnostics if d.severity == "error"]
    return []


def circle(centre, normal, radius):
    """(centre, U, V) of a circle: points centre + cos(t) U + sin(t) V."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    helper = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(n, helper)
    u /= np.linalg.norm(u)
    return np.asarray(centre, float), radius * u, radius * np.cross(n, u)


def out_of_range(field) -> list[float]:
    """Values just outside a pydantic field's declared bounds (ge, gt, le, lt): each must be refused."""
    bad = []
    for m in field.metadata:
        for attr, delta in (("ge", -1), ("gt", 0), ("le", 1), ("lt", 0)):
            v = getattr(m, attr, None)
            if v is not None:
                bad.append(v + delta * max(abs(v), 1.0) if delta else v)
    return bad


def silhouette_segments(ca, Ua, Va, cb, Ub, Vb, arc_a=None, arc_b=None):
    """Camera-frame 3D segments (start on a, end on b) of the visible sides between two ellipses."""
    full_a, full_b = np.array([arc_a is None]), np.array([arc_b is None])
    arcs_a = np.array([arc_a if arc_a is not None else (0.0, 2 * math.pi)], dtype=float)
    arcs_b = np.array([arc_b if arc_b is not None else (0.0, 2 * math.pi)], dtype=float)
    _, A, B = conics.silhouette_segments_batch(*(np.asarray(x, dtype=float)[None] for x in (ca, Ua, Va, cb, Ub, Vb)),
                                               arcs_a, full_a, arcs_b, full_b)
    return list(zip(A, B, strict=True))


# ----------------------------------------------------------------------------- plug-in packages, as pip leaves them

def dist_info(site: Path, name: str, version: str, entry_points: str) -> Path:
    """A distribution's `.dist-info` folder as pip leaves it in site-packages (METADATA, entry_points.txt), through
    which importlib.metadata finds the package's entry points; returns the folder."""
    info = site / f"{name.replace('-', '_')}-{version}.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n")
    (info / "entry_points.txt").write_text(entry_points)
    return info


def entry_points_text(groups: dict[str, dict[str, str]]) -> str:
    """pyproject.toml's [project.entry-points] tables as the lines of entry_points.txt."""
    return "".join(f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in eps.items()) + "\n"
                   for group, eps in groups.items())


def make_dist(site: Path, name: str, module: str, entry_points: str) -> Path:
    """A package `name` (its __init__.py the text `module`), version 0.3, installed into the folder `site`;
    returns `site`, the folder to put on sys.path."""
    (site / name).mkdir(parents=True)
    (site / name / "__init__.py").write_text(module)
    dist_info(site, name, "0.3", entry_points)
    return site


@contextlib.contextmanager
def plugins_on_path(monkeypatch, *folders: Path, modules: tuple[str, ...] = ()):
    """Plug-in packages installed in `folders` for the block: the folders put first on sys.path (the last named
    first), the plug-in registries rescanned on entering and on leaving, and the packages' modules (`modules`: their
    top-level names) taken out of sys.modules after, so that no other test sees them."""
    for folder in folders:
        monkeypatch.syspath_prepend(str(folder))
    plugins.rescan()
    try:
        yield
    finally:
        plugins.rescan()
        for m in [m for m in sys.modules if m.split(".")[0] in modules]:
            del sys.modules[m]


def fandisk_like(sag: float, at=(0.0, 0.0, 0.0)):
    """A 0.3 x 0.12 x 0.08 m block whose top bulges by `sag` (m) over its first half and is flat over the second,
    tessellated in 200 strips: the top-front and top-back creases are curved-then-flat chains of 200 edges that
    the mesh reader merges (MERGE_LATERAL) into nearly collinear lines; turned off the axes, so vertex merging
    puts the merged lines a fraction of a micron off their faces (the fandisk's defect). Its vertices in 4 rows of
    201 (bottom-front, top-front, top-back, bottom-back), then shifted by `at` (m): a trimesh.Trimesh."""
    import trimesh

    L, W, H, n = 0.3, 0.12, 0.08, 200
    x = np.linspace(0.0, L, n + 1)
    u = np.clip(x / (L / 2), 0.0, 1.0)
    z = H + sag * np.where(x < L / 2, np.sin(np.pi * u) ** 2, 0.0)
    ring = [np.column_stack([x, np.full_like(x, y), zz]) for y, zz in
            ((0.0, np.zeros_like(x)), (0.0, z), (W, z), (W, np.zeros_like(x)))]
    V = np.concatenate(ring)  # 4 rows of n + 1: bottom-front, top-front, top-back, bottom-back
    m = n + 1
    F = []
    for r in range(4):
        a, b = r * m, ((r + 1) % 4) * m
        for i in range(n):
            F += [(a + i, a + i + 1, b + i + 1), (a + i, b + i + 1, b + i)]
    for i in (0, n):  # the two ends
        F += [(i, m + i, 2 * m + i), (i, 2 * m + i, 3 * m + i)]
    mesh = trimesh.Trimesh(V, np.array(F), process=False)
    c, s = np.cos(0.5), np.sin(0.5)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    c, s = np.cos(0.2), np.sin(0.2)
    Rx = np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])
    mesh.vertices = mesh.vertices @ (Rx @ Rz).T + np.asarray(at, float)
    return mesh
