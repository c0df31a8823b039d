"""Stage 5b: one SVG a pose, like the paper's Figure 3: both camera images and a top-view map.

Hand-written (a few f-strings) so that the output is small, fast and byte-identical
for the same input; coordinates are rounded to 0.01 px.
"""

from __future__ import annotations

import math
from html import escape

import numpy as np

from wiredsl.engine.simulate import PoseResult, View
from wiredsl.engine.world import World
from wiredsl.io.files import require_finite
from wiredsl.scene import Scene

GAP = 20
MARGIN = 10
TITLE = 22
MAP_ASPECT = 4  # widest top view, in map heights
COLOURS = {"line": "#1f4e79", "polyline": "#1f4e79", "ellipse": "#2e7d32", "silhouette": "#b35900",
           "corner": "#c62828"}


def _f(x: float) -> str:
    if not math.isfinite(x):
        require_finite(float(x), "an SVG coordinate")  # refuses it, saying why
    s = f"{x:.2f}".rstrip("0").rstrip(".")
    return "0" if s == "-0" else s


def _poly(points, colour: str, width: float = 1.2, closed: bool = False, extra: str = "") -> str:
    pts = " ".join(f"{_f(x)},{_f(y)}" for x, y in points)
    tag = "polygon" if closed else "polyline"
    return f'<{tag} points="{pts}" fill="none" stroke="{colour}" stroke-width="{width}"{extra}/>'


def _pane(view: View, world: World, ox: float, oy: float, title: str, grey: bool = False,
          background: bool = True) -> list[str]:
    cam = view.camera
    out = [f'<g transform="translate({_f(ox)},{_f(oy)})">']
    if background:
        out += [f'<text x="0" y="-6" font-family="sans-serif" font-size="13">{escape(title)}</text>',
                f'<rect x="0" y="0" width="{cam.width}" height="{cam.height}" fill="#fafafa" stroke="#333"/>']
    for f in view.features:
        kind = world.feature_kind[f.fid]
        colour = "#9e9e9e" if grey else COLOURS.get(kind, "#000")
        if f.kind in ("line", "polyline"):
            out.append(_poly(f.points, colour, closed=f.closed and len(f.points) > 2))
        elif f.kind == "corner":
            x, y = f.points[0]
            out.append(f'<circle cx="{_f(x)}" cy="{_f(y)}" r="2.5" fill="none" stroke="{colour}" stroke-width="1.2"/>')
    out.append("</g>")
    return out


def _map(scene: Scene, world: World, result: PoseResult, ox: float, oy: float, height: float):
    """Top view (north up): object footprints, the view-point mesh, the path and the robot."""
    pts = [world.lines.reshape(-1, 3)[:, :2]] if len(world.lines) else []
    ring = np.linspace(0, 2 * math.pi, 49)
    ell = [world.ell_c[e, :2] + np.cos(ring)[:, None] * world.ell_U[e, :2] + np.sin(ring)[:, None] *
           world.ell_V[e, :2] for e in range(len(world.ell_c))]
    pts += ell
    if scene.viewpoints is not None:
        pts.append(np.array(scene.viewpoints.points))
    pts.append(np.array(scene.path.poses)[:, :2])
    allp = np.concatenate(pts)
    lo, hi = allp.min(0) - 0.5, allp.max(0) + 0.5  # room for the robot and its tail
    # Halves: a world spanning more than half the float range must not overflow its own extent. The map is
    # `height` tall, or MAP_ASPECT times as wide when the world is wider than that.
    half = np.maximum(hi / 2 - lo / 2, 1e-9)
    k = min(height / 2 / half[1], MAP_ASPECT * height / 2 / half[0])  # pixels per half-metre
    width, height = 2 * float(half[0] * k), 2 * float(half[1] * k)

    def m(p):
        p = np.atleast_2d(p)
        return np.column_stack([(p[:, 0] / 2 - lo[0] / 2) * 2 * k, (hi[1] / 2 - p[:, 1] / 2) * 2 * k])

    out = [f'<g transform="translate({_f(ox)},{_f(oy)})">',
           '<text x="0" y="-6" font-family="sans-serif" font-size="13">top view</text>',
           f'<rect x="0" y="0" width="{_f(width)}" height="{_f(height)}" fill="#ffffff" stroke="#333"/>']
    vp = scene.viewpoints
    if vp is not None:
        P = m(np.array(vp.points))
        for a, b, c in vp.triangles:
            out.append(_poly(P[[a, b, c]], "#90caf9", 0.6, closed=True))
        for p in P:
            out.append(f'<circle cx="{_f(p[0])}" cy="{_f(p[1])}" r="1.5" fill="#64b5f6"/>')
        if result.viewpoint is not None:
            p = P[vp.names.index(result.viewpoint)]
            out.append(f'<circle cx="{_f(p[0])}" cy="{_f(p[1])}" r="5" fill="none" stroke="#ef6c00" '
                       'stroke-width="2"/>')
    for seg in world.lines:
        out.append(_poly(m(seg[:, :2]), "#616161", 1.0))
    for e in ell:
        out.append(_poly(m(e), "#616161", 1.0))
    path = m(np.array(scene.path.poses)[:, :2])
    out.append(_poly(path, "#bdbdbd", 1.0, extra=' stroke-dasharray="4 3"'))
    x, y, heading = result.pose
    tail = m(np.array([[x, y], [x - 0.35 * math.cos(heading), y - 0.35 * math.sin(heading)]]))
    out.append(_poly(tail, "#000", 2.0))
    out.append(f'<circle cx="{_f(tail[0, 0])}" cy="{_f(tail[0, 1])}" r="4" fill="#000"/>')
    out.append("</g>")
    return out, width


def render(scene: Scene, world: World, result: PoseResult, underlay: PoseResult | None = None) -> str:
    """The SVG for one pose; `underlay` (e.g. the ideal features) is drawn grey beneath."""
    height = result.left.camera.height
    panes = [("left", result.left)] + ([("right", result.right)] if result.right is not None else [])
    under = [] if underlay is None else [underlay.left, underlay.right]
    body: list[str] = []
    x = MARGIN
    for i, (side, view) in enumerate(panes):
        title = f"{side}: {view.camera.name}"
        if under and under[i] is not None:  # the ideal features in grey beneath the disturbed ones
            body += _pane(under[i], world, x, MARGIN + TITLE, title, grey=True)
        body += _pane(view, world, x, MARGIN + TITLE, title, background=not under)
        x += view.camera.width + GAP
    map_parts, map_w = _map(scene, world, result, x, MARGIN + TITLE, height)
    body += map_parts
    total_w = x + map_w + MARGIN
    total_h = MARGIN + TITLE + height + MARGIN + 18
    x0, y0, hd = require_finite(tuple(float(v) for v in result.pose), "the pose")
    caption = (f"{scene.name}: pose {result.index} at ({x0:.2f} m, {y0:.2f} m), heading {math.degrees(hd):.1f} deg"
               + (f", view-point {result.viewpoint}" if result.viewpoint else ""))
    head = [f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {_f(total_w)} {_f(total_h)}" '
            f'width="{_f(total_w)}" height="{_f(total_h)}">',
            f'<text x="{MARGIN}" y="{_f(total_h - 6)}" font-family="sans-serif" font-size="12">{escape(caption)}'
            "</text>"]
    return "\n".join(head + body + ["</svg>"]) + "\n"
