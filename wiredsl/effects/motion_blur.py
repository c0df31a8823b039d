"""Motion blur: what an edge detector does with an edge smeared by the image motion over the exposure.

A camera that declares `exposure` on a path with times is open from -exposure/2 to +exposure/2 about the pose's
time, while the robot moves with its velocities at the pose (engine/motion.py). Each feature point's image motion
over the exposure is the difference of its images at the two ends: the point's arc-length fraction along its
feature's ideal image at the pose's time (nearest point; features keyed by id and segment) taken on the
feature's images as the robot at -exposure/2 and +exposure/2 sees it (exact at a straight feature's ends, the
affine approximation between them). Its length and its angle to the edge (0: along, 90 deg: across) give, by
bilinear interpolation of the measured table `LOSS` / `SHIFT` (benchmarks/blur_magnitudes.py: render-then-verify
with Canny at its defaults; longer blur takes the table's longest), the probability that the point is lost and
the range of its lateral shift and the scatter of its position (each less the table's row without blur: what the
still edge's detection has, which the other stages model):

- loss: one uniform u per stroke; the stroke keeps the parts where loss(point) <= u (linear between vertices), so
  that a stroke of one blur is lost whole with that probability and a stroke whose blur grows along it loses
  its more blurred end;
- shift: one more uniform v per stroke; each point moves along its normal by range(point) (2 v - 1);
- scatter: each vertex moves by sigma(point) times a 2D standard normal (stream APPROX_STREAM), before the cut (a
  cut's new ends are interpolated between moved vertices).

`scale` multiplies both (1: the table as measured). Views whose camera has no exposure, and scenes without
motion, pass unchanged (nothing is drawn or projected for them).
"""

from __future__ import annotations

import numpy as np

from wiredsl.effects.base import Context, Effect, Params, Stats, param
from wiredsl.engine import imageset as im

# The measured table: benchmarks/blur_magnitudes.py (seed 39, its defaults), whose output is the table in
# docs/tutorials/path.md (docs/reproduce.py block blur-table): fitted edge_loss.fraction and lateral_shift.range
# (px) by blur length (rows, px) and angle to the edge (columns, deg).
TABLE_LENGTHS = (0.0, 4.0, 8.0, 10.0)
TABLE_ANGLES = (0.0, 45.0, 90.0)
LOSS = ((0, 0, 0),
        (0, 0, 0),
        (0, 0, 0.5377),
        (0, 0.0032, 0.682))
SHIFT = ((0.0014, 0.0014, 0.0014),
         (0.0013, 0.0312, 0.1858),
         (0.0013, 0.3049, 0),
         (0.0013, 0, 0))
SIGMA = ((0.0011, 0.0011, 0.0011),  # approx_error.sigma (px): the fitted end points' scatter, per axis
         (0.0012, 0, 0.032),
         (0.0012, 0, 1.3804),
         (0.0011, 0.2657, 2.5307))
APPROX_STREAM = "motion_blur.fitting"  # the per-vertex normals' draws (the stage's own key: per-stroke uniforms)


class MotionBlurParams(Params):
    scale: float = param(1.0, "number", "multiplies the measured loss and shift (1: Canny at its defaults, as "
                         "benchmarks/blur_magnitudes.py measured them)", ge=0, le=10)


class MotionBlur(Effect):
    name = "motion_blur"
    acts_on = "edges"
    Params = MotionBlurParams
    doc = __doc__

    @classmethod
    def is_identity(cls, p: MotionBlurParams) -> bool:
        return p.scale == 0

    @classmethod
    def disturb(cls, p: MotionBlurParams, s: im.ImageSet, ctx: Context) -> im.ImageSet:
        cams, which = ctx.view_cameras(s.trial)
        exposure = np.array([getattr(c, "exposure", 0.0) for c in cams])[which] if len(s.trial) else np.zeros(0)
        if ctx.moved is None or not (exposure > 0).any():
            return s
        motion = image_motion(s, ctx, exposure)
        tangent = _tangents(s)
        length = np.hypot(motion[:, 0], motion[:, 1])
        across = np.abs(motion[:, 0] * tangent[:, 1] - motion[:, 1] * tangent[:, 0])
        along = np.abs(motion[:, 0] * tangent[:, 0] + motion[:, 1] * tangent[:, 1])
        angle = np.degrees(np.arctan2(across, along))
        loss = np.clip(p.scale * excess(LOSS, length, angle), 0.0, 1.0)
        rng = p.scale * excess(SHIFT, length, angle)
        sigma = p.scale * excess(SIGMA, length, angle)
        u = ctx.draws(cls.name, s.trial, per_item=2)
        stroke = s.vertex_stroke()
        d = rng * (2 * u[stroke, 1] - 1)
        normals = np.column_stack([-tangent[:, 1], tangent[:, 0]])
        scatter = sigma[:, None] * ctx.draws(APPROX_STREAM, s.trial[stroke], 2, normal=True)
        shifted = im.replace(s, pts=s.pts + d[:, None] * normals + scatter)
        out = keep_below(shifted, loss, u[:, 0])
        _, L = im.arc_lengths(shifted)
        ctx.add(cls.name, s.trial, total_length=L, count=np.ones(s.n_strokes, dtype=int),
                sum_motion=np.bincount(stroke, weights=length, minlength=s.n_strokes) / np.maximum(s.counts, 1))
        ctx.add(cls.name, out.trial, kept_length=im.arc_lengths(out)[1])
        ctx.add(cls.name, s.trial, vertices=s.counts,
                sum_abs=np.bincount(stroke, weights=np.abs(d), minlength=s.n_strokes))
        ctx.stats.peak(cls.name, max_motion=length.max(initial=0.0), max_abs=np.abs(d).max(initial=0.0))
        return out

    @classmethod
    def report(cls, p: MotionBlurParams, stats: Stats) -> dict:
        s, m = stats.sums[cls.name], stats.maxima[cls.name]
        removed = 1 - s["kept_length"] / s["total_length"] if s["total_length"] else 0.0
        return {"removed_length_fraction": {"measured": removed},
                "mean_image_motion_px": {"measured": s["sum_motion"] / max(s["count"], 1)},
                "max_image_motion_px": {"measured": m["max_motion"]},
                "mean_abs_shift_px": {"measured": s["sum_abs"] / max(s["vertices"], 1)},
                "max_abs_shift_px": {"measured": m["max_abs"]}}


def scene_at(scene, tau: float):
    """The scene with every pose of its path moved `tau` seconds along its own motion (motion.robot_at), its
    times kept (a rolling shutter and a sync act about each moved pose as about the pose)."""
    from wiredsl.engine import motion

    path = scene.path
    v, w = motion.velocities_of(path)
    transforms = [np.reshape(motion.robot_at(path.pose(i), v[i], w[i], tau), (3, 4)).tolist()
                  for i in range(len(path.poses))]
    return scene.model_copy(update={"path": path.model_copy(update={"transforms": transforms})})


def exposed(scene) -> bool:
    """Whether a camera of the scene's rig exposes over time on a path with times."""
    if scene.rig is None or scene.path is None or scene.path.times is None:
        return False
    return any(scene.camera(getattr(scene.rig, s).camera).exposure > 0 for s in ("left", "right"))


def excess(table, length: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """table_at less the table's value without blur, at least 0."""
    return np.maximum(table_at(table, length, angle) - table_at(table, np.zeros(1), np.zeros(1)), 0.0)


def table_at(table, length: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of a (TABLE_LENGTHS x TABLE_ANGLES) table at blur lengths (px) and angles (deg),
    each clamped to the table's range."""
    T = np.asarray(table, dtype=float)
    Ls, As = np.asarray(TABLE_LENGTHS), np.asarray(TABLE_ANGLES)
    x = np.clip(length, Ls[0], Ls[-1])
    y = np.clip(angle, As[0], As[-1])
    i = np.clip(np.searchsorted(Ls, x, side="right") - 1, 0, len(Ls) - 2)
    j = np.clip(np.searchsorted(As, y, side="right") - 1, 0, len(As) - 2)
    tx = (x - Ls[i]) / (Ls[i + 1] - Ls[i])
    ty = (y - As[j]) / (As[j + 1] - As[j])
    return ((1 - tx) * (1 - ty) * T[i, j] + tx * (1 - ty) * T[i + 1, j] + (1 - tx) * ty * T[i, j + 1]
            + tx * ty * T[i + 1, j + 1])


def _tangents(s: im.ImageSet) -> np.ndarray:
    """Unit tangents (N, 2) at the vertices: imageset.vertex_normals turned back by 90 deg."""
    n = im.vertex_normals(s)
    return np.column_stack([n[:, 1], -n[:, 0]])


def image_motion(s: im.ImageSet, ctx: Context, exposure: np.ndarray) -> np.ndarray:
    """Each vertex's image motion over its view's exposure (N, 2) px (zero where the camera has none, or where the
    vertex's feature is not seen at either end of the exposure): see the module's docstring."""
    stroke = s.vertex_stroke()
    right = ctx.right(s.trial)
    poses = ctx.poses[s.trial] if getattr(ctx, "poses", None) is not None else np.full(s.n_strokes, ctx.pose)
    out = np.zeros((len(s.pts), 2))
    views = {}
    for k in np.flatnonzero(exposure > 0):
        views.setdefault((int(poses[k]), bool(right[k]), float(exposure[k])), []).append(k)
    for (pose, is_right, e), strokes in views.items():
        side = "right" if is_right else "left"
        centre, early, late = (_polylines(ctx.moved(tau), pose, side) for tau in (0.0, -e / 2, e / 2))
        strokes = np.asarray(strokes)
        vertex = np.flatnonzero(np.isin(stroke, strokes))
        keys = list(zip(s.fid[stroke[vertex]].tolist(), s.segment[stroke[vertex]].tolist(), strict=True))
        by_key: dict = {}
        for v, key in zip(vertex, keys, strict=True):
            by_key.setdefault(key, []).append(v)
        for key, vs in by_key.items():
            if key not in centre or (key not in early and key not in late):
                continue
            lam = _fraction(centre[key], s.pts[vs])
            a = _at(early[key], lam) if key in early else None
            b = _at(late[key], lam) if key in late else None
            c = _at(centre[key], lam)
            out[vs] = (b - a) if a is not None and b is not None else 2 * ((b if b is not None else c) -
                                                                              (a if a is not None else c))
    return out


def _polylines(results: dict, pose: int, side: str) -> dict:
    """{(feature id, segment): its image polyline (k, 2)} of a view, a feature's pieces joined in order."""
    r = results.get(pose)
    view = getattr(r, side, None) if r is not None else None
    out: dict = {}
    for f in (view.features if view is not None else ()):
        if f.kind in ("line", "polyline") and len(f.points) >= 2:
            pts = np.vstack([f.points, f.points[:1]]) if f.closed else np.asarray(f.points, float)
            key = (f.fid, f.segment)
            out[key] = np.vstack([out[key], pts]) if key in out else pts
    return out


def _arc(Q: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(Q, axis=0).T))])


def _fraction(Q: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Arc-length fraction (k,) along polyline Q (m, 2) of the points of Q nearest to points P (k, 2)."""
    arc = _arc(Q)
    a, d = Q[:-1], np.diff(Q, axis=0)
    dd = np.maximum((d * d).sum(axis=1), 1e-300)
    t = np.clip(((P[:, None, :] - a[None]) * d[None]).sum(axis=2) / dd, 0.0, 1.0)
    near = a[None] + t[..., None] * d[None]
    j = np.argmin(((P[:, None, :] - near) ** 2).sum(axis=2), axis=1)
    pos = arc[j] + t[np.arange(len(P)), j] * np.sqrt(dd[j])
    return pos / arc[-1] if arc[-1] > 0 else np.zeros(len(P))


def _at(Q: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Points at arc-length fractions lam along polyline Q."""
    arc = _arc(Q)
    target = lam * arc[-1]
    return np.column_stack([np.interp(target, arc, Q[:, 0]), np.interp(target, arc, Q[:, 1])])


def keep_below(s: im.ImageSet, loss: np.ndarray, u: np.ndarray) -> im.ImageSet:
    """The parts of the strokes where loss (N,) <= the stroke's u (S,), loss linear between vertices: a stroke kept
    everywhere is kept verbatim (closed ones too); one cut is cut along its vertices (a closed one once around,
    from its first vertex), its pieces numbered 0, 1, ... as fragments and flagged clipped."""
    stroke = s.vertex_stroke()
    g = loss - u[stroke]  # kept where g <= 0
    cut = np.bincount(stroke, weights=(g > 0).astype(float), minlength=s.n_strokes) > 0
    if not cut.any():
        return s
    s2 = im.unroll_closed(s, cut)  # the cut loops traversed twice: their first lap is once around
    k2 = s2.vertex_stroke()
    i2 = np.arange(len(s2.pts)) - s2.start[:-1][k2]
    g2 = g[s.start[:-1][k2] + i2 % np.maximum(s.counts[k2], 1)]
    arc, _ = im.arc_lengths(s2)
    lap = np.where(s.closed & cut, s.counts, s.counts - 1)  # a cut stroke's segments, once around
    seg = np.flatnonzero(cut[k2] & (i2 < lap[k2]))
    g0, g1 = g2[seg], g2[seg + 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        tc = np.where(g0 != g1, g0 / (g0 - g1), 0.0)
    t0 = np.where(g0 <= 0, 0.0, np.where(g1 <= 0, tc, 1.0))
    t1 = np.where(g0 <= 0, np.where(g1 <= 0, 1.0, tc), 1.0)
    ok = t1 > t0
    seg, t0, t1 = seg[ok], t0[ok], t1[ok]
    span = arc[seg + 1] - arc[seg]
    a, b, ks = arc[seg] + t0 * span, arc[seg] + t1 * span, k2[seg]
    # a piece continues the previous one when it starts where that one ended, in the same stroke
    new = np.ones(len(seg), dtype=bool)
    new[1:] = (ks[1:] != ks[:-1]) | (a[1:] > b[:-1] + 1e-12)
    first = np.flatnonzero(new)
    ra, rk = a[first], ks[first]
    rb = np.maximum.reduceat(b, first) if len(first) else b
    rfrag = np.arange(len(first)) - np.searchsorted(rk, rk)
    whole = np.flatnonzero(~cut)
    stroke_all = np.concatenate([whole, rk])
    a_all = np.concatenate([np.zeros(len(whole)), ra])
    b_all = np.concatenate([np.zeros(len(whole)), rb])
    is_whole = np.concatenate([np.ones(len(whole), dtype=bool), np.zeros(len(rk), dtype=bool)])
    frag = np.concatenate([s.fragment[whole], rfrag])
    order = np.lexsort((a_all, stroke_all))
    return im.keep_intervals(s2, stroke_all[order], a_all[order], b_all[order], frag[order],
                             closed=(is_whole & s.closed[stroke_all])[order], cut=~is_whole[order],
                             whole=is_whole[order])
