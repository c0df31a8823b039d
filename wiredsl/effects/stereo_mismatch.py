"""Stereo match error: features near-parallel to epipolar lines are lost, a few of the rest shift along them.

In both cameras, every part of a stroke whose direction is within `band` of the
epipolar line through it is removed (a straight segment as a whole; a curve
segment by segment, leaving fragments). Then, in the right image (the matched
one; the left is the reference), each remaining stroke is mismatched with
probability `fraction` and moves along its epipolar line by a uniform amount in
[-disparity, disparity]. The epipolar geometry is the nominal rig's (the one a
matcher would use), through its lenses: under a distorted lens the epipolar
lines are curves, and the direction at a point is the curve's tangent there.
"""

from __future__ import annotations

import math

import numpy as np

from wiredsl.effects.base import Context, Effect, KernelStage, Params, Stats, param
from wiredsl.engine import geometry
from wiredsl.engine import imageset as im


class StereoMismatchParams(Params):
    band: float = param(math.radians(5.0), "angle", "features within this angle of the epipolar line are dropped",
                        ge=0, le=math.pi / 2)
    fraction: float = param(0.01, "fraction", "fraction of remaining features mismatched", ge=0, le=1)
    disparity: float = param(20.0, "image", "disparity search range either side", ge=0, le=10000)


def epipolar_directions(points: np.ndarray, epipole: np.ndarray) -> np.ndarray:
    """Unit direction of the epipolar line through each point (n, 2), from a homogeneous epipole (3,), or one a
    point (n, 3)."""
    e = np.asarray(epipole)
    d = points * e[..., 2:] - e[..., :2]
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    return np.divide(d, norm, out=np.tile([1.0, 0.0], (len(d), 1)), where=norm > 0)


NUDGE = 1e-4  # the 3D step (a unit ray's length: 1e-4 rad) of the central differences of a lens's epipolar tangent


def epipolar_tangents(points: np.ndarray, epipole: np.ndarray, g: dict) -> np.ndarray:
    """Unit tangent of the epipolar curve through each point (n, 2) of a camera with numbers g (a camera table,
    `geometry.camera_table`) whose epipole (homogeneous, `Run.epipole`: K X for the other camera's centre X in
    this camera's frame) is given, (3,) or one a point (n, 3): the image of the point's epipolar plane under the
    lens. The pixel's unit ray d (`geometry.pixels_to_rays_newton`) moved NUDGE away from and towards the other
    camera's centre (along -X and X: within the plane), projected through the lens (`geometry.project_xyz`): the
    difference of the two images, central differences. Under a pinhole lens the direction `epipolar_directions`
    gives, whose sign it keeps. Where no ray or image is found, that pinhole direction. The compiled kernel's
    `_tangent` computes the same, term by term."""
    e = np.broadcast_to(np.asarray(epipole, dtype=float), (len(points), 3))
    x, y, z = geometry.pixels_to_rays_newton(points[:, 0], points[:, 1], g)
    Xx = (e[:, 0] - g["cx"] * e[:, 2]) / (g["f"] * g["ax"])  # K^-1 e: X up to a positive scale
    Xy = (e[:, 1] - g["cy"] * e[:, 2]) / (g["f"] * g["ay"])
    Xz = e[:, 2]
    step = NUDGE / np.sqrt(Xx * Xx + Xy * Xy + Xz * Xz)
    Xx, Xy, Xz = Xx * step, Xy * step, Xz * step
    ua, va = geometry.project_xyz(x - Xx, y - Xy, z - Xz, g)
    ub, vb = geometry.project_xyz(x + Xx, y + Xy, z + Xz, g)
    tx, ty = ua - ub, va - vb
    with np.errstate(invalid="ignore", over="ignore"):
        norm = np.sqrt(tx * tx + ty * ty)
        good = np.isfinite(norm) & (norm > 0)
        t = np.column_stack([tx, ty]) / np.where(good, norm, 1.0)[:, None]
    return np.where(good[:, None], t, epipolar_directions(points, e))


def epipolar_lines(mid: np.ndarray, epipole: np.ndarray, lens: tuple | None) -> tuple[np.ndarray, np.ndarray]:
    """The direction (lx, ly), (n,) each, not normalised, of the epipolar line or curve through points mid (n, 2):
    a pinhole's line from the epipole (homogeneous, (3,) or one a point (n, 3)); under a distorted lens (`lens`,
    from `lens_of`: camera tables, None for a pinhole, and each point's index into them) the curve's tangent,
    `epipolar_tangents`. A point at the epipole: the x axis, as epipolar_directions."""
    e = np.asarray(epipole)
    ex, ey, ew = e[..., 0], e[..., 1], e[..., 2]
    lx, ly = mid[:, 0] * ew - ex, mid[:, 1] * ew - ey
    at_epipole = (lx == 0) & (ly == 0)
    lx, ly = np.where(at_epipole, 1.0, lx), np.where(at_epipole, 0.0, ly)
    return _tangents_into(lx, ly, mid, e, lens)


def curve_directions(points: np.ndarray, epipole: np.ndarray, lens: tuple | None) -> np.ndarray:
    """Unit directions (n, 2) of `epipolar_lines`: a pinhole's `epipolar_directions`, under a distorted lens the
    curve's tangent."""
    d = epipolar_directions(points, epipole)
    if lens is not None:
        _tangents_into(d[:, 0], d[:, 1], points, np.asarray(epipole), lens)
    return d


def _tangents_into(lx: np.ndarray, ly: np.ndarray, points: np.ndarray, e: np.ndarray, lens: tuple | None):
    """Put `epipolar_tangents` in lx, ly (n,) (views, in place) at the points under a distorted lens."""
    if lens is None:
        return lx, ly
    tables, which = lens
    for i, g in enumerate(tables):
        here = which == i
        if g is not None and here.any():
            t = epipolar_tangents(points[here], e[here] if e.ndim == 2 else e, g)
            lx[here], ly[here] = t[:, 0], t[:, 1]
    return lx, ly


def rows(lens: tuple | None, index: np.ndarray) -> tuple | None:
    """`lens_of`'s answer for the items `index` of its items."""
    return None if lens is None else (lens[0], lens[1][index])


def lens_of(ctx: Context, batch_index: np.ndarray) -> tuple | None:
    """What `epipolar_lines` needs of the items' views' nominal cameras: None when every one is a pinhole (or is
    not known: the band is the pinhole's, as it always was); else their camera tables (None for a pinhole) and
    each item's index into them, (n,)."""
    cameras, which = ctx.view_cameras(batch_index)
    tables = [geometry.camera_table(c) if c is not None and geometry.is_distorted(c) else None for c in cameras]
    return None if all(t is None for t in tables) else (tables, which)


def angle_to_epipolar(a: np.ndarray, b: np.ndarray, epipole: np.ndarray) -> np.ndarray:
    """Angle in [0, pi/2] between segments a->b (n, 2) and the epipolar line through their midpoints."""
    d = b - a
    e = epipolar_directions((a + b) / 2, epipole)
    return np.arctan2(np.abs(d[:, 0] * e[:, 1] - d[:, 1] * e[:, 0]), np.abs((d * e).sum(axis=1)))


def in_band(a: np.ndarray, b: np.ndarray, epipole: np.ndarray, band: float, lens: tuple | None = None
            ) -> np.ndarray:
    """Whether segments a->b (n, 2) are within `band` of the epipolar line (or curve, under a distorted `lens`:
    see `epipolar_lines`) through their midpoints: angle_to_epipolar <= band, decided as |cross| <= tan(band) |dot|
    (no atan2, no normalising). The epipole is homogeneous, (3,) or one a segment (n, 3)."""
    if band >= math.pi / 2:
        return np.ones(len(a), dtype=bool)
    lx, ly = epipolar_lines((a + b) / 2, epipole, lens)
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    return np.abs(dx * ly - dy * lx) <= math.tan(band) * np.abs(dx * lx + dy * ly)


class StereoMismatch(Effect):
    name = "stereo_mismatch"
    acts_on = "stereo"
    kernel = KernelStage("wiredsl.effects.stereo_mismatch_kernel:stage", ("band", "fraction", "disparity"),
                         (("length_in", "add"), ("length_after_band", "add"), ("right_strokes", "add"),
                                  ("shifted", "add"), ("max_shift", "peak")), epipole=True, camera=True,
                         workspace="wiredsl.effects.stereo_mismatch_kernel:workspace")
    Params = StereoMismatchParams
    doc = __doc__

    @classmethod
    def is_identity(cls, p: StereoMismatchParams) -> bool:
        return p.band == 0 and (p.fraction == 0 or p.disparity == 0)

    @classmethod
    def disturb(cls, p: StereoMismatchParams, s: im.ImageSet, ctx: Context) -> im.ImageSet:
        ctx.add(cls.name, s.trial, length_in=im.arc_lengths(s)[1])
        epipole = ctx.epipoles(s.trial)  # each stroke's view's, (strokes, 3)
        lens = lens_of(ctx, s.trial)  # None: pinhole views
        if p.band > 0 and s.n_strokes:
            s = _drop_band(s, epipole, p.band, lens)
            epipole, lens = ctx.epipoles(s.trial), lens_of(ctx, s.trial)
        ctx.add(cls.name, s.trial, length_after_band=im.arc_lengths(s)[1])
        right = np.flatnonzero(ctx.right(s.trial))  # the strokes of right views (all of a view's)
        if not len(right) or p.fraction == 0 or p.disparity == 0:
            return s
        draws = ctx.draws(cls.name, s.trial[right], 2)
        hit = draws[:, 0] < p.fraction
        shift = np.where(hit, p.disparity * (2 * draws[:, 1] - 1), 0.0)
        mid = np.add.reduceat(s.pts, s.start[:-1], axis=0)[right] / s.counts[right, None]
        direction = curve_directions(mid, epipole[right], rows(lens, right))
        move = np.repeat(shift[:, None] * direction, s.counts[right], axis=0)
        ctx.add(cls.name, s.trial[right], right_strokes=np.ones(len(hit), dtype=int), shifted=hit)
        ctx.stats.peak(cls.name, max_shift=np.abs(shift).max(initial=0.0))
        if len(right) == s.n_strokes:
            return im.replace(s, pts=s.pts + move)
        pts = s.pts.copy()
        vertices = np.repeat(np.isin(np.arange(s.n_strokes), right), s.counts)
        pts[vertices] += move
        return im.replace(s, pts=pts)

    @classmethod
    def report(cls, p: StereoMismatchParams, stats: Stats) -> dict:
        s = stats.sums[cls.name]
        return {"band_removed_length_fraction": {"measured": 1 - s["length_after_band"] / s["length_in"]
                                                 if s["length_in"] else None},
                "mismatch_rate": {"declared": p.fraction,
                                  "measured": s["shifted"] / s["right_strokes"] if s["right_strokes"] else None},
                "max_shift_px": {"declared_bound": p.disparity, "measured": stats.maxima[cls.name]["max_shift"]}}


def _drop_band(s: im.ImageSet, epipole: np.ndarray, band: float, lens: tuple | None = None) -> im.ImageSet:
    """Remove every stroke segment within `band` of its epipolar line (curve); keep the rest as fragments.
    `epipole`: each stroke's view's, (strokes, 3); `lens`: each stroke's view's lens (`lens_of`), None for pinholes.

    A closed stroke's segments include its closing one; its kept runs are taken once around the loop,
    a run through the loop's start being one piece; a loop that loses nothing stays whole and closed.
    """
    S = s.n_strokes
    first, last = s.start[:-1], s.start[1:] - 1
    loops = np.flatnonzero(s.closed & (s.counts > 1))
    closing_inside = np.zeros(S, dtype=bool)
    closing_inside[loops] = in_band(s.pts[last[loops]], s.pts[first[loops]], epipole[loops], band, rows(lens, loops))
    stroke_of = s.vertex_stroke()
    real = stroke_of[:-1] == stroke_of[1:] if len(s.pts) else np.zeros(0, bool)
    inside = in_band(s.pts[:-1], s.pts[1:], epipole[stroke_of[:-1]], band, rows(lens, stroke_of[:-1]))
    hit = np.bincount(stroke_of[:-1][real & inside], minlength=S) > 0 if len(s.pts) else np.zeros(S, bool)
    cut_loops = s.closed & (hit | closing_inside)
    intact = s.closed & ~cut_loops
    u = im.unroll_closed(s, cut_loops)  # a cut loop: twice round, of which one lap from a dropped segment is used
    stroke_of = u.vertex_stroke()
    pair_stroke = stroke_of[:-1]
    real = stroke_of[:-1] == stroke_of[1:]
    local = np.arange(len(u.pts) - 1) - u.start[pair_stroke]
    c = s.counts[pair_stroke]  # a loop's own number of segments
    # each pair's segment decided once, above: slot start[k] + i holds segment i of stroke k, a loop's last slot its
    # closing segment (the tangents under a distorted lens cost more than the rest of the band together)
    slot = np.append(inside, False)
    slot[last[loops]] = closing_inside[loops]
    inside = slot[s.start[pair_stroke] + np.where(cut_loops[pair_stroke], local % np.maximum(c, 1), local)]
    lap = real & inside & cut_loops[pair_stroke] & (local < c)
    p0 = np.full(S, np.iinfo(np.int64).max // 4)
    np.minimum.at(p0, pair_stroke[lap], local[lap])  # a cut loop's first dropped segment
    window = ~cut_loops[pair_stroke] | ((local > p0[pair_stroke]) & (local < p0[pair_stroke] + c))
    keep_pair = real & ~inside & window & ~intact[pair_stroke]
    arc, _ = im.arc_lengths(u)
    # runs of kept pairs within each stroke become fragments (vertex ranges [starts, ends])
    change = np.flatnonzero(np.diff(np.concatenate([[False], keep_pair, [False]]).astype(int)))
    starts, ends = change[::2], change[1::2]
    strokes = pair_stroke[starts]
    whole = (starts == u.start[strokes]) & (ends == u.start[strokes + 1] - 1)  # an open stroke that lost nothing
    strokes = np.concatenate([strokes, np.flatnonzero(intact)])
    lo = np.concatenate([arc[starts], np.zeros(intact.sum())])
    hi = np.concatenate([arc[ends], np.zeros(intact.sum())])
    whole = np.concatenate([whole, np.ones(intact.sum(), dtype=bool)])
    order = np.argsort(strokes, kind="stable")
    strokes, lo, hi, whole = strokes[order], lo[order], hi[order], whole[order]
    frag = np.where(whole, u.fragment[strokes], 0)  # fragments are numbered when the dump is written
    return im.keep_intervals(u, strokes, lo, hi, frag, closed=whole & s.closed[strokes], whole=whole)
