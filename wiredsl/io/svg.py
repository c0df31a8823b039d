"""Stage 5b: one SVG a pose, in the paper's layouts (Figures 3, 4 and 9).

Every figure has a fixed width (1000 units, one column), whatever the world's shape: camera
panes with pixel axes, a top-view map fitted into a fixed box with metre axes, a scale bar,
object names and the cameras' fields of view, a legend of exactly the colours and markers
drawn, and a caption (scene, pose, pipeline, seed, trial, visibility). Each feature carries a
`<title>` tooltip naming its source.

Hand-written (a few f-strings) so that the output is small, fast and byte-identical for the
same input; coordinates are rounded to 0.01 units.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from html import escape

import numpy as np

from wiredsl.engine import geometry
from wiredsl.engine.simulate import PoseResult, View
from wiredsl.engine.world import World
from wiredsl.files import printable_path, require_finite
from wiredsl.scene import Scene

LAYOUTS = ("overlay", "side-by-side", "visibility")
WIDTH = 1000  # the figure's width: one column
MARGIN = 14
GAP = 26  # between cells
AX_L = 50  # room for the left tick labels and axis name
AX_B = 36  # room for the bottom tick labels and axis name
TITLE = 24  # a cell's title line
FONT = 14  # titles, caption, legend
SMALL = 12  # tick labels, object names
STROKE = 1.6  # features
SANS = 'font-family="DejaVu Sans, Arial, Helvetica, sans-serif"'

# camera panes: colour by what the vision system extracts
KIND_COLOURS = {"line": "#1f4e79", "polyline": "#1f4e79", "ellipse": "#2e7d32", "silhouette": "#b35900",
                "corner": "#c62828", "contour": "#6d4c41"}
KIND_LABELS = {"#1f4e79": "line, polyline", "#2e7d32": "ellipse", "#b35900": "silhouette", "#c62828": "corner",
               "#6d4c41": "contour (a mesh's smooth outline)"}
IDEAL = "#b0b0b0"  # the ideal features beneath the disturbed ones
HIDDEN = "#d81b60"  # features that view-dependency hides
# top view: colour by object; the largest (the room) is drawn first in grey, so that what lies on its
# lines (a door in a wall) is drawn over it in its own colour. A scheme of its own: none of these is near a
# feature kind's colour in the camera panes, a field of view's or another mark's (tests/test_figures.py)
ROOM = "#8d8d8d"
PALETTE = ("#0288d1", "#7cb342", "#f9a825", "#7e57c2", "#546e7a", "#827717", "#3949ab", "#ec407a")
MAX_PLACEMENT_KEYS = len(PALETTE)  # placements the legend names; past them (colours come round again) "and N more"
FOV = {"left": "#00897b", "right": "#7b1fa2"}
MESH, MESH_POINT, NEAREST, PATH, ROBOT = "#90caf9", "#64b5f6", "#ef6c00", "#9e9e9e", "#000000"


def _f(x: float) -> str:
    if not math.isfinite(x):
        require_finite(float(x), "an SVG coordinate")  # refuses it, saying why
    s = f"{x:.2f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _pts(points) -> str:
    if isinstance(points, np.ndarray):  # Python floats format several times faster than numpy scalars
        points = points.tolist()
    return " ".join(f"{_f(x)},{_f(y)}" for x, y in points)


def _text(x: float, y: float, s: str, size: int = FONT, anchor: str = "start", extra: str = "") -> str:
    a = "" if anchor == "start" else f' text-anchor="{anchor}"'
    return f'<text x="{_f(x)}" y="{_f(y)}" {SANS} font-size="{size}"{a}{extra}>{escape(s)}</text>'


@dataclass(frozen=True)
class Info:
    """What the caption says about the run."""

    pipeline: str | None = None
    seed: int | None = None
    trial: int | None = None
    visibility: str = "scene"
    layout: str = "overlay"


@dataclass
class Keys:
    """The legend: every colour and marker drawn, in the order first drawn, grouped."""

    entries: dict[tuple[str, str], tuple[str, str]] = field(default_factory=dict)  # (group, colour) -> (label, mark)
    more: dict[str, tuple[int, str]] = field(default_factory=dict)  # group -> (items not listed, what they are)

    def use(self, group: str, colour: str, label: str, mark: str = "line") -> str:
        self.entries.setdefault((group, colour), (label, mark))
        return colour

    def one_more(self, group: str, what: str) -> None:
        """An item drawn but not listed (its colour already means another): the legend says how many."""
        self.more[group] = (self.more.get(group, (0, what))[0] + 1, what)


@dataclass
class Pane:
    """A camera pane: its title and layers drawn bottom to top: (view, style) with style ideal/kind/hidden."""

    title: str
    layers: list[tuple[View, str]]


# --------------------------------------------------------------------------- axes

def nice_step(span: float, target: int = 6) -> float:
    """A 1-2-5 step giving about `target` ticks over `span`."""
    raw = span / max(target, 1)
    mag = 10 ** math.floor(math.log10(raw))
    return next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw * 0.999)


def _ticks(lo: float, hi: float, step: float) -> list[float]:
    first = math.ceil(lo / step - 1e-9)
    return [k * step for k in range(first, math.floor(hi / step + 1e-9) + 1)]


def _axes(x0, y0, w, h, xr, yr, xname, yname, y_down: bool, grid: bool) -> list[str]:
    """Frame, ticks and tick labels of a plot box at (x0, y0) of size w x h showing ranges xr, yr."""
    out = []
    sx = w / (xr[1] - xr[0])
    sy = h / (yr[1] - yr[0])
    for v in _ticks(*xr, nice_step(xr[1] - xr[0], max(2, round(w / 75)))):
        X = x0 + (v - xr[0]) * sx
        if grid:
            out.append(f'<line class="axis" x1="{_f(X)}" y1="{_f(y0)}" x2="{_f(X)}" y2="{_f(y0 + h)}" '
                       'stroke="#ececec" stroke-width="1"/>')
        out.append(f'<line class="axis" x1="{_f(X)}" y1="{_f(y0 + h)}" x2="{_f(X)}" y2="{_f(y0 + h + 5)}" '
                   'stroke="#333333" stroke-width="1.2"/>')
        out.append(_text(X, y0 + h + 17, f"{v:g}", SMALL, "middle"))
    for v in _ticks(*yr, nice_step(yr[1] - yr[0], max(2, round(h / 60)))):
        Y = y0 + (v - yr[0]) * sy if y_down else y0 + h - (v - yr[0]) * sy
        if grid:
            out.append(f'<line class="axis" x1="{_f(x0)}" y1="{_f(Y)}" x2="{_f(x0 + w)}" y2="{_f(Y)}" '
                       'stroke="#ececec" stroke-width="1"/>')
        out.append(f'<line class="axis" x1="{_f(x0 - 5)}" y1="{_f(Y)}" x2="{_f(x0)}" y2="{_f(Y)}" '
                   'stroke="#333333" stroke-width="1.2"/>')
        out.append(_text(x0 - 8, Y + 4, f"{v:g}", SMALL, "end"))
    out.append(_text(x0 + w, y0 + h + 32, xname, SMALL, "end"))
    out.append(_text(x0 - 38, y0, yname, SMALL, "end", f' transform="rotate(-90 {_f(x0 - 38)} {_f(y0)})"'))
    out.append(f'<rect class="axis" x="{_f(x0)}" y="{_f(y0)}" width="{_f(w)}" height="{_f(h)}" fill="none" '
               'stroke="#333333" stroke-width="1.2"/>')
    return out


# --------------------------------------------------------------------------- camera panes

def _tooltip(world: World, f, note: str) -> str:
    parts = [world.feature_ids[f.fid]]
    if f.segment >= 0:
        parts.append(f"segment {f.segment}")
    if f.fragment >= 0:
        parts.append(f"fragment {f.fragment}")
    if f.clipped:
        parts.append("clipped")
    return f"<title>{escape(', '.join(parts))} ({note})</title>"


def _pane(pane: Pane, world: World, x: float, y: float, w: float, clip: str, keys: Keys) -> tuple[list[str], float]:
    """A camera pane in a cell at (x, y) of width w: title, image frame, pixel axes, features; its height."""
    cam = pane.layers[0][0].camera
    pw = w - AX_L
    s = pw / cam.width
    ph = cam.height * s
    X0, Y0 = x + AX_L, y + TITLE
    out = [_text(x, y + 16, pane.title),
           f'<rect class="axis" x="{_f(X0)}" y="{_f(Y0)}" width="{_f(pw)}" height="{_f(ph)}" fill="#fafafa"/>',
           f'<clipPath id="{clip}"><rect x="{_f(X0)}" y="{_f(Y0)}" width="{_f(pw)}" height="{_f(ph)}"/></clipPath>',
           f'<g clip-path="url(#{clip})">']
    for view, style in pane.layers:
        for f in view.features:
            if f.kind == "conic":  # the analytic form of an ellipse already drawn as its polyline
                continue
            kind = world.feature_kind[f.fid]
            if style == "ideal":
                colour, note = keys.use("camera panes", IDEAL, "ideal (no effects)"), "ideal"
            elif style == "hidden":
                colour, note = keys.use("camera panes", HIDDEN, "hidden by view-dependency", "dash"), "hidden"
            else:
                colour = KIND_COLOURS.get(kind, "#000000")
                colour = keys.use("camera panes", colour, KIND_LABELS.get(colour, kind),
                                  "circle" if kind == "corner" else "line")
                note = style if style != "kind" else "shown"
            tip = _tooltip(world, f, note)
            P = (f.points * s + np.array((X0, Y0), f.points.dtype)).tolist()  # as X0 + x * s, Y0 + y * s
            dash = ' stroke-dasharray="6 4"' if style == "hidden" else ""
            if f.kind == "corner":
                dash = ' stroke-dasharray="3 2"' if dash else ""
                out.append(f'<circle class="feature" cx="{_f(P[0][0])}" cy="{_f(P[0][1])}" r="4.5" fill="none" '
                           f'stroke="{colour}" stroke-width="{STROKE}"{dash}>{tip}</circle>')
            else:
                tag = "polygon" if f.closed and len(P) > 2 else "polyline"
                out.append(f'<{tag} class="feature" points="{_pts(P)}" fill="none" stroke="{colour}" '
                           f'stroke-width="{STROKE}" stroke-linejoin="round"{dash}>{tip}</{tag}>')
    out.append("</g>")
    out += _axes(X0, Y0, pw, ph, (0, cam.width), (0, cam.height), "u (px)", "v (px)", y_down=True, grid=False)
    return out, TITLE + ph + AX_B


# --------------------------------------------------------------------------- top view

def _placement_of(world: World) -> list[str]:
    return [fid.split(".", 1)[0] for fid in world.feature_ids]


def _footprints(world: World) -> dict[str, list[np.ndarray]]:
    """Per placement, its features' outlines seen from above: (k, 2) world xy polylines."""
    owner = _placement_of(world)
    out: dict[str, list[np.ndarray]] = {}
    for seg, fid in zip(world.lines, world.line_fid, strict=True):
        out.setdefault(owner[fid], []).append(seg[:, :2])
    ring = np.linspace(0, 2 * math.pi, 73)
    for e, fid in enumerate(world.ell_fid):
        t = np.linspace(world.ell_arc[e, 0], world.ell_arc[e, 1], 73) if not world.ell_full[e] else ring
        pts = world.ell_c[e, :2] + np.cos(t)[:, None] * world.ell_U[e, :2] + np.sin(t)[:, None] * world.ell_V[e, :2]
        out.setdefault(owner[fid], []).append(pts)
    for fid, cont in world.contours:  # a smooth mesh surface: its outline seen from high above (far above its
        ends = cont.ends.reshape(-1, 3)  # own size too: from inside a sphere of 1e7 m nothing is an outline)
        above = ends.mean(axis=0) + (0.0, 0.0, max(1e6, 1e3 * float(np.ptp(ends, axis=0).max())))
        outline = cont.ends[cont.seen_from(above)][:, :, :2]
        if len(outline):
            out.setdefault(owner[fid], []).extend(outline)
    return out


def _eye(view: View) -> np.ndarray:
    return -view.R_cw.T @ view.t_cw


def _fov_rays(view: View) -> np.ndarray:
    """World xy directions through the image's left edge, centre column and right edge (at cy; a fisheye's
    reach no farther than its lens limit, past 90 deg when it is wider)."""
    cam = view.camera
    us = np.linspace(0.0, cam.width, 17)
    xd = (us - cam.cx) / (cam.f * cam.ax)
    if cam.distortion != "radtan":  # an angle-bounded lens: its own unprojection, no farther than its limit
        limit = geometry.lens_limit(cam)
        rays, ok = geometry.pixels_to_rays(np.column_stack([us, np.full_like(us, cam.cy)]), cam)
        th = np.where(ok, np.arctan2(np.abs(rays[:, 0]), rays[:, 2]), limit)
        rays = np.column_stack([np.sign(xd) * np.sin(th), np.zeros_like(us), np.cos(th)])
    else:
        rays = np.column_stack([xd, np.zeros_like(us), np.ones_like(us)])
    d = rays @ view.R_cw  # camera to world: R_cw.T @ ray for each row
    d = d[:, :2]
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


@dataclass
class TopView:
    """The parts of the top view that are the same for every pose of a run (one scene, world and box): drawn
    once, then each pose adds its fields of view, nearest view-point and robot."""

    m: Callable[[np.ndarray], np.ndarray]  # world xy (n, 2) -> SVG coordinates (n, 2)
    reach: float  # metres: a field of view's fan reaches past the box
    head: list[str]  # title, box, axes, the clipped group's start
    mesh: list[str]  # the view-point mesh's triangles
    points: list[str]  # the view-points
    objects: list[tuple[str, str, list[str]]]  # (placement, colour, its outlines), largest first
    path: str
    labels: list[str]  # the placements' names (drawn over the rest)
    tail: list[str]  # the scale bar and the frame


def top_view(scene: Scene, world: World, x: float, y: float, w: float, h: float) -> TopView:
    """The static top view (north up) in a fixed box: objects, view-point mesh, path, labels."""
    foot = _footprints(world)
    pts = [p for polys in foot.values() for p in polys]
    if scene.viewpoints is not None:
        pts.append(np.array(scene.viewpoints.points, dtype=float))
    pts.append(np.array(scene.path.poses, dtype=float)[:, :2])
    allp = np.concatenate(pts)
    lo, hi = allp.min(0), allp.max(0)
    pad = 0.06 * max(hi - lo) + 0.3  # room for the robot, its tail and the labels
    lo, hi = lo - pad, hi + pad
    bw, bh = w - AX_L, h - TITLE - AX_B
    s = min(bw / (hi[0] - lo[0]), bh / (hi[1] - lo[1]))
    cx, cy = (lo + hi) / 2
    xr = (cx - bw / 2 / s, cx + bw / 2 / s)  # the world x, y ranges the whole box shows
    yr = (cy - bh / 2 / s, cy + bh / 2 / s)
    X0, Y0 = x + AX_L, y + TITLE

    def m(p):
        p = np.atleast_2d(p)
        return np.column_stack([X0 + (p[:, 0] - xr[0]) * s, Y0 + (yr[1] - p[:, 1]) * s])

    head = [_text(x, y + 16, "top view (x east, y north)"),
            f'<rect class="axis" x="{_f(X0)}" y="{_f(Y0)}" width="{_f(bw)}" height="{_f(bh)}" fill="#ffffff"/>',
            f'<clipPath id="clip-map"><rect x="{_f(X0)}" y="{_f(Y0)}" width="{_f(bw)}" height="{_f(bh)}"/></clipPath>']
    head += _axes(X0, Y0, bw, bh, xr, yr, "x (m)", "y (m)", y_down=False, grid=True)[:-1]  # frame drawn last
    head.append('<g clip-path="url(#clip-map)">')
    reach = float(np.hypot(*(np.array([xr[1] - xr[0], yr[1] - yr[0]]))))
    vp = scene.viewpoints
    mesh, points = [], []
    if vp is not None:
        P = m(np.array(vp.points, dtype=float))
        for a, b, c in vp.triangles:
            mesh.append(f'<polygon class="map" points="{_pts(P[[a, b, c]])}" fill="none" stroke="{MESH}" '
                        'stroke-width="1.3"/>')
        for name, p in zip(vp.names, P, strict=True):
            points.append(f'<circle class="map" cx="{_f(p[0])}" cy="{_f(p[1])}" r="2.5" fill="{MESH_POINT}">'
                          f"<title>view-point {escape(name)}</title></circle>")
    # objects, largest first, so that what lies on the room's lines is drawn over them
    def area(name):
        q = np.concatenate(foot[name])
        return float(np.prod(q.max(0) - q.min(0) + 1e-3))

    names = [p.name for p in scene.placements if p.name in foot]
    order = sorted(names, key=lambda n: (-area(n), names.index(n)))
    room = order[0] if order and area(order[0]) > 0.25 * (hi[0] - lo[0]) * (hi[1] - lo[1]) else None
    colour_of = {}
    k = 0
    for n in names:
        if n == room:
            colour_of[n] = ROOM
        else:
            colour_of[n] = PALETTE[k % len(PALETTE)]
            k += 1
    labels: list[tuple[float, float, str, str, str]] = []
    placed: list[tuple[float, float, float, float]] = []
    objects = []
    for n in order:
        colour = colour_of[n]
        width = 3.0 if n == room else 2.0
        objects.append((n, colour, [f'<polyline class="map" points="{_pts(m(poly))}" fill="none" stroke="{colour}" '
                                    f'stroke-width="{width}" stroke-linecap="round"><title>{escape(n)}</title>'
                                    "</polyline>" for poly in foot[n]]))
        q = m(np.concatenate(foot[n]))
        qlo, qhi = q.min(0), q.max(0)
        mid = (qlo + qhi) / 2
        if n == room:  # above its top-left corner, off the objects inside
            tries = [(qlo[0], qlo[1] - 6, "start")]
        else:  # above, below, right, left of the outline: the first that overlaps no earlier name
            tries = [(mid[0], qlo[1] - 6, "middle"), (mid[0], qhi[1] + 15, "middle"),
                     (qhi[0] + 5, mid[1] + 4, "start"), (qlo[0] - 5, mid[1] + 4, "end")]
        label = _place_label(n, colour, tries, placed, (X0, Y0, X0 + bw, Y0 + bh))
        if label is None and n == room:  # the room's name is kept, where it goes: it is placed first
            label = (*tries[0], n, colour)
        if label is not None:
            labels.append(label)
    path = (f'<polyline class="map" points="{_pts(m(np.array(scene.path.poses, dtype=float)[:, :2]))}" '
            f'fill="none" stroke="{PATH}" stroke-width="1.6" stroke-dasharray="6 4"/>')
    texts = []
    for tx, ty, anchor, n, colour in labels:  # a white halo beneath (paint-order is not drawn everywhere)
        texts.append(_text(tx, ty, n, SMALL, anchor, ' class="axis" fill="#ffffff" stroke="#ffffff" stroke-width="4" '
                           'stroke-linejoin="round" font-weight="bold"'))
        texts.append(_text(tx, ty, n, SMALL, anchor, f' class="label" fill="{colour}" font-weight="bold"'))
    tail = _scale_bar(X0 + bw, Y0 - 8, s, bw)  # in the title line: it hides nothing
    tail.append(f'<rect class="axis" x="{_f(X0)}" y="{_f(Y0)}" width="{_f(bw)}" height="{_f(bh)}" fill="none" '
                'stroke="#333333" stroke-width="1.2"/>')
    return TopView(m, reach, head, mesh, points, objects, path, texts, tail)


def _map(scene: Scene, world: World, result: PoseResult, x: float, y: float, w: float, h: float,
         keys: Keys, views: dict | None = None) -> list[str]:
    """Top view (north up) in a fixed box: objects, view-point mesh, path, fields of view, robot. `views`
    keeps the static part (TopView) of each box drawn, for the next pose."""
    box = (x, y, w, h)
    tv = views.get(box) if views is not None else None
    if tv is None:
        tv = top_view(scene, world, *box)
        if views is not None:
            views[box] = tv
    m = tv.m
    out = list(tv.head)
    # fields of view: a fan from each camera out past the box
    for side, view in [("left", result.left)] + ([("right", result.right)] if result.right is not None else []):
        colour = keys.use("top view", FOV[side], f"{side} camera's field of view", "wedge")
        e = _eye(view)[:2]
        fan = np.vstack([e, e + tv.reach * _fov_rays(view), e])
        out.append(f'<polygon class="map" points="{_pts(m(fan))}" fill="{colour}" fill-opacity="0.08" '
                   f'stroke="{colour}" stroke-width="1.5" stroke-dasharray="5 3">'
                   f"<title>{side} camera ({escape(view.camera.name)}): field of view</title></polygon>")
    vp = scene.viewpoints
    if vp is not None:
        keys.use("top view", MESH, f"view-point mesh '{vp.name}'")
        out += tv.mesh
        keys.use("top view", MESH_POINT, "view-point", "dot")
        out += tv.points
    for n, colour, outlines in tv.objects:
        if ("top view", colour) in keys.entries:  # a colour come round again: named on the map, counted here
            keys.one_more("top view", "placements (colours repeat)")
        else:
            keys.use("top view", colour, n)
        out += outlines
    keys.use("top view", PATH, f"path '{scene.path.name}'", "dash")
    out.append(tv.path)
    if vp is not None and result.viewpoint is not None:
        p = m(np.array(vp.points[vp.names.index(result.viewpoint)], dtype=float))[0]
        ring = keys.use("top view", NEAREST, "nearest view-point", "ring")
        out.append(f'<circle class="map" cx="{_f(p[0])}" cy="{_f(p[1])}" r="7" fill="none" stroke="{ring}" '
                   f'stroke-width="2.2"><title>nearest view-point {escape(result.viewpoint)}</title></circle>')
    px, py, heading = geometry.floor_pose(result.pose)
    tail = m(np.array([[px, py], [px - 0.4 * math.cos(heading), py - 0.4 * math.sin(heading)]]))
    robot = keys.use("top view", ROBOT, "robot (dot) and its tail", "robot")
    out.append(f'<polyline class="map" points="{_pts(tail)}" fill="none" stroke="{robot}" stroke-width="2.6"/>')
    out.append(f'<circle class="map" cx="{_f(tail[0, 0])}" cy="{_f(tail[0, 1])}" r="5" fill="{robot}">'
               f"<title>robot at pose {result.index}</title></circle>")
    out += tv.labels
    out.append("</g>")
    out += tv.tail
    return out


def _place_label(name: str, colour: str, tries, placed: list, box) -> tuple[float, float, str, str, str] | None:
    """The first candidate position whose text lies in the box and clear of the names placed so far; None (the
    name left off, its outline's tooltip still has it) when every one would overlap another name."""
    w = 0.66 * SMALL * len(name)  # bold sans: about 0.66 em a character

    def rect(x, y, anchor):
        x0 = x - {"start": 0.0, "middle": w / 2, "end": w}[anchor]
        return x0, y - 0.8 * SMALL, x0 + w, y + 0.25 * SMALL

    def free(r):
        inside = r[0] >= box[0] and r[1] >= box[1] and r[2] <= box[2] and r[3] <= box[3]
        return inside and all(r[2] < q[0] or q[2] < r[0] or r[3] < q[1] or q[3] < r[1] for q in placed)

    found = next((t for t in tries if free(rect(*t))), None)
    if found is None:
        return None
    x, y, anchor = found
    placed.append(rect(x, y, anchor))
    return x, y, anchor, name, colour


def _scale_bar(right: float, base: float, s: float, bw: float) -> list[str]:
    """A bar of a round length ending at `right`, its label to its left, on the line y = `base`."""
    length = nice_step(bw / s, 6)
    x0 = right - length * s
    return [f'<polyline class="axis" points="{_f(x0)},{_f(base - 6)} {_f(x0)},{_f(base)} {_f(right)},{_f(base)} '
            f'{_f(right)},{_f(base - 6)}" fill="none" stroke="#000000" stroke-width="2"/>',
            _text(x0 - 6, base, f"{length:g} m", SMALL, "end")]


# --------------------------------------------------------------------------- legend, caption, layout

def _legend(keys: Keys, x: float, y: float, w: float) -> tuple[list[str], float]:
    """Swatch and label of every colour drawn, in two columns per group."""
    out = ['<g class="legend">', _text(x, y + 16, "legend")]
    row_h, col_w = 20, w / 2
    yy = y + TITLE + 8
    groups: dict[str, list[tuple[str, str, str]]] = {}
    for (group, colour), (label, mark) in keys.entries.items():
        groups.setdefault(group, []).append((colour, label, mark))
    for group, items in groups.items():
        out.append(_text(x, yy + 4, group, SMALL, extra=' font-style="italic"'))
        yy += row_h - 2
        rows = math.ceil(len(items) / 2)
        for i, (colour, label, mark) in enumerate(items):
            cx, cy = x + (i // rows) * col_w, yy + (i % rows) * row_h
            out.append(_swatch(cx, cy, colour, mark, label))
            out.append(_text(cx + 32, cy + 4, label, SMALL))
        yy += rows * row_h + 8
        if group in keys.more:
            count, what = keys.more[group]
            out.append(_text(x, yy + 4, f"and {count} more {what}", SMALL))
            yy += row_h
    out.append("</g>")
    return out, yy - y


def _swatch(x: float, y: float, colour: str, mark: str, label: str) -> str:
    attr = f'class="key" data-label="{escape(label)}"'
    if mark == "circle":
        return (f'<circle {attr} cx="{_f(x + 12)}" cy="{_f(y)}" r="4.5" fill="none" stroke="{colour}" '
                'stroke-width="1.6"/>')
    if mark == "ring":
        return (f'<circle {attr} cx="{_f(x + 12)}" cy="{_f(y)}" r="6" fill="none" stroke="{colour}" '
                'stroke-width="2.2"/>')
    if mark == "dot":
        return f'<circle {attr} cx="{_f(x + 12)}" cy="{_f(y)}" r="3" fill="{colour}" stroke="{colour}"/>'
    if mark == "wedge":
        return (f'<polygon {attr} points="{_f(x)},{_f(y)} {_f(x + 24)},{_f(y - 7)} {_f(x + 24)},{_f(y + 7)}" '
                f'fill="{colour}" fill-opacity="0.15" stroke="{colour}" stroke-width="1.5"/>')
    if mark == "robot":
        return (f'<g {attr}><line x1="{_f(x + 4)}" y1="{_f(y)}" x2="{_f(x + 20)}" y2="{_f(y)}" stroke="{colour}" '
                f'stroke-width="2.6"/><circle cx="{_f(x + 20)}" cy="{_f(y)}" r="5" fill="{colour}"/></g>')
    dash = ' stroke-dasharray="6 4"' if mark == "dash" else ""
    return (f'<line {attr} x1="{_f(x)}" y1="{_f(y)}" x2="{_f(x + 24)}" y2="{_f(y)}" stroke="{colour}" '
            f'stroke-width="2.4"{dash}/>')


def _metres(v: float) -> str:
    """v to the centimetre, without a sign on what rounds to zero ('-0.00')."""
    text = f"{v:.2f}"
    return "0.00" if text == "-0.00" else text


def _caption(scene: Scene, result: PoseResult, info: Info) -> list[str]:
    x, y, hd = geometry.floor_pose(result.pose)
    n = len(scene.path.poses)
    z = "" if len(result.pose) == 3 else f", z = {_metres(geometry.world_from_robot(result.pose)[1][2])} m"
    first = (f"{scene.name} ({scene.source}): pose {result.index} of 0..{n - 1} at x = {_metres(x)} m, "
             f"y = {_metres(y)} m{z}, "
             f"heading {math.degrees(hd):.1f} deg" + (f", nearest view-point {result.viewpoint}"
                                                      if result.viewpoint else ""))
    if info.layout == "visibility":  # Figure 4 compares the ideal world seen two ways
        return [first, f"ideal projections, visibility all against {info.visibility}; layout visibility"]
    run = ("ideal projection (no effects)" if info.pipeline is None else
           f"pipeline '{info.pipeline}', seed {info.seed}, trial {info.trial}")
    return [first, f"{run}; visibility {info.visibility}; layout {info.layout}"]


def _compose(scene: Scene, world: World, result: PoseResult, panes: list[Pane], info: Info,
             width: float = WIDTH, views: dict | None = None) -> str:
    """Cells two a row: the camera panes, then the top view and the legend; the caption beneath."""
    keys = Keys()
    cw = (width - 2 * MARGIN - GAP) / 2
    cells = [_pane(pane, world, 0.0, 0.0, cw, f"clip-pane{i}", keys) for i, pane in enumerate(panes)]
    map_h = max(cells[0][1], 380.0)
    cells.append((_map(scene, world, result, 0.0, 0.0, cw, map_h, keys, views), map_h))
    cells.append(_legend(keys, 0.0, 0.0, cw))  # last: it lists what the others drew
    body: list[str] = []
    y = MARGIN
    for r in range(0, len(cells), 2):
        row = cells[r:r + 2]
        for c, (parts, _) in enumerate(row):
            body.append(f'<g transform="translate({_f(MARGIN + c * (cw + GAP))},{_f(y)})">')
            body += parts
            body.append("</g>")
        y += max(h for _, h in row) + GAP / 2
    lines = _caption(scene, result, info)
    caption = [_text(MARGIN, y + 16 + 20 * k, s, FONT, extra=' class="caption"') for k, s in enumerate(lines)]
    height = y + 20 * len(lines) + 10
    head = [f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {_f(width)} {_f(height)}" '
            f'width="{_f(width)}" height="{_f(height)}">',
            f"<title>{escape(lines[0])}</title>",
            f'<rect x="0" y="0" width="{_f(width)}" height="{_f(height)}" fill="#ffffff"/>']
    return printable_path("\n".join(head + body + caption + ["</svg>"]) + "\n")


def _cam_title(scene: Scene, side: str, what: str = "") -> str:
    return f"{side} camera ({getattr(scene.rig, side).camera})" + (f": {what}" if what else "")


def _sides(result: PoseResult) -> list[tuple[str, View]]:
    return [("left", result.left)] + ([("right", result.right)] if result.right is not None else [])


def overlay(scene: Scene, world: World, result: PoseResult, ideal: PoseResult | None = None,
            info: Info = Info(), views: dict | None = None) -> str:
    """Figures 3 and 9 overlaid: each camera's (disturbed) features in colour over the ideal ones in grey."""
    panes = []
    for side, view in _sides(result):
        under = None if ideal is None else getattr(ideal, side)
        layers = ([(under, "ideal")] if under is not None else []) + [(view, "kind")]
        panes.append(Pane(_cam_title(scene, side), layers))
    return _compose(scene, world, result, panes, info, views=views)


def side_by_side(scene: Scene, world: World, result: PoseResult, ideal: PoseResult, info: Info = Info(),
                 views: dict | None = None) -> str:
    """Figure 9 side by side: each camera's original (ideal) world beside its disturbed one."""
    panes = []
    for side, view in _sides(result):
        panes.append(Pane(_cam_title(scene, side, "original"), [(getattr(ideal, side), "kind")]))
        panes.append(Pane(_cam_title(scene, side, f"disturbed ({info.pipeline})"), [(view, "disturbed")]))
    return _compose(scene, world, result, panes, info, views=views)


def visibility_pair(scene: Scene, world: World, without: PoseResult, with_: PoseResult, info: Info = Info(),
                    views: dict | None = None) -> str:
    """Figure 4: the left camera without view-dependency (what it hides dashed) and with it."""
    kept = {f.fid for f in with_.left.features}
    hidden = View(without.left.camera, without.left.R_cw, without.left.t_cw,
                  [f for f in without.left.features if f.fid not in kept])
    shown = View(without.left.camera, without.left.R_cw, without.left.t_cw,
                 [f for f in without.left.features if f.fid in kept])
    panes = [Pane(_cam_title(scene, "left", "without view-dependency"), [(shown, "kind"), (hidden, "hidden")]),
             Pane(_cam_title(scene, "left", f"with view-dependency ({info.visibility})"), [(with_.left, "kind")])]
    return _compose(scene, world, with_, panes, info, views=views)


def pose_figures(run, results: list[PoseResult], layout: str, info: Info) -> dict[str, str]:
    """File name -> SVG of every pose of one trial's results, in the chosen layout."""
    from dataclasses import replace

    from wiredsl.engine.simulate import simulate

    ideal = {r.index: r for r in run.ideal()} if run.stages else {}
    out: dict[str, str] = {}
    views: dict = {}  # the top view's static part, drawn once for all poses
    if layout == "visibility":
        everything = {r.index: r for r in simulate(run.scene, replace(run.options, visibility="all"), run.world)}
        for r in run.ideal():
            out[f"pose_{r.index:03d}.svg"] = visibility_pair(run.scene, run.world, everything[r.index], r, info, views)
        return out
    for r in results:
        if layout == "side-by-side":
            text = side_by_side(run.scene, run.world, r, ideal.get(r.index, r), info, views)
        else:
            text = overlay(run.scene, run.world, r, ideal.get(r.index), info, views)
        out[f"pose_{r.index:03d}.svg"] = text
    return out
