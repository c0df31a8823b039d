"""Stage 4: the ideal projection of a compiled scene, pose by pose, camera by camera.

For every pose of the path the rig is placed on the robot; each camera images
the features visible from there (the nearest view-point's list, or an exact
per-camera computation). Everything is clipped in 3D to the near plane and to
the radius where distortion folds before projection, and to the image
rectangle [0, width] x [0, height] after it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import gc
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from wiredsl.diagnostics import Diagnostic, Span, WiredslError
from wiredsl.engine import conics, geometry, occlusion, visibility
from wiredsl.engine.world import World, build_world
from wiredsl.scene import Camera, Scene

DEFAULT_TOLERANCE = 0.1  # px: largest deviation of an emitted polyline from the true image curve


@dataclass(frozen=True)
class Options:
    tolerance: float = DEFAULT_TOLERANCE
    visibility: str = "scene"  # "scene" (the mesh's lists), "exact" (per camera and pose), "all"
    poses: tuple[int, ...] | None = None  # None: every pose
    right: bool = True  # project the right camera too
    viewdep: dict | None = field(default=None, compare=False)  # a view-dependency file's lists (io/viewdep.py)


@dataclass
class ImageFeature:
    fid: int
    kind: str  # line | polyline | conic | corner
    points: np.ndarray  # (k, 2) pixels; a corner has k = 1
    segment: int = -1
    clipped: bool = False
    closed: bool = False
    conic: tuple | None = None  # (centre (2,), axes (2,), angle, arc or None)
    fragment: int = -1  # piece number after a stage cut the feature, -1 when whole
    occluded: bool = False  # a visible part of a feature that occlusion cut (--visibility exact)


@dataclass
class Raw:
    """A stroke before image clipping: the world points its vertices image, for re-projection."""

    fid: int
    segment: int
    kind: str  # "line" (straight in the image), "polyline"
    closed: bool
    clipped: bool  # already cut in 3D (near plane, fold)
    world: np.ndarray  # (k, 3)
    fragment: int = -1  # part number when occlusion cut the feature
    occluded: bool = False


@dataclass
class View:
    camera: Camera
    R_cw: np.ndarray
    t_cw: np.ndarray
    features: list[ImageFeature] = field(default_factory=list)
    # the strokes before image clipping: a projection gives a sequence that makes them when first read
    raw: Sequence[Raw] = field(default_factory=list)
    corner_world: np.ndarray | None = None  # (C, 3) the corners in front of the camera, before image clipping
    corner_fid: np.ndarray | None = None
    # a moving robot's camera (engine/motion.py): the robot's pose at the camera's own time (None: the pose's),
    # and its rolling shutter (readout, height, robot origin, v, w), or None
    robot: tuple | None = None
    rolling: tuple | None = None


@dataclass
class PoseResult:
    index: int
    pose: tuple[float, ...]  # see geometry.world_from_robot: (x, y, heading), or [R | t] row-major
    viewpoint: str | None
    left: View
    right: View | None


def simulate(scene: Scene, options: Options = Options(), world: World | None = None,
             visible: tuple | None = None) -> list[PoseResult]:
    """Project every selected pose of the scene's path; the ideal (undisturbed) feature sets.

    `visible` is `visibility_masks(...)` computed beforehand (e.g. once for many trials).
    """
    require_buildable(scene)
    world = world or build_world(scene)
    chosen = range(len(scene.path.poses)) if options.poses is None else options.poses
    vp_names, masks = visible if visible is not None else visibility_masks(scene, world, options)
    # --visibility exact: hidden lines removed, features cut at occlusion boundaries (occlusion.py)
    occluders = occlusion.Occluders.of_world(world) if options.visibility == "exact" else None
    sides = ("left", "right") if options.right else ("left",)
    specs = []  # (pose index, side, camera, R_cw, t_cw, mask) of every view, projected together
    motions = []  # each view's (robot pose at its time, rolling shutter), or None (engine/motion.py)
    moves = scene.path.times is not None and (scene.rig.sync != 0 or any(
        scene.camera(getattr(scene.rig, side).camera).readout > 0 for side in sides))
    if moves:
        from wiredsl.engine import motion
    for i in chosen:
        pose = scene.path.pose(i)
        sees = motion.view_motions(scene, i) if moves else {}
        for side in sides:
            mount = getattr(scene.rig, side)
            m = sees.get(side)
            R_cw, t_cw = geometry.camera_from_world(pose if m is None else m[0], mount.rotation, mount.position)
            specs.append((i, side, scene.camera(mount.camera), R_cw, t_cw, masks[(i, side)]))
            motions.append(m)
    views = []
    if specs:
        _, _, cams, Rs, ts, ms = zip(*specs, strict=True)
        views = project_views(world, list(cams), list(Rs), list(ts), list(ms), options.tolerance, occluders,
                              motions if moves else None)
    by_key = {(i, side): v for (i, side, *_), v in zip(specs, views, strict=True)}
    return [PoseResult(i, scene.path.pose(i), vp_names.get(i), by_key[(i, "left")],
                       by_key.get((i, "right"))) for i in chosen]


def project_pose(scene: Scene, world: World, pose, index: int, options: Options = Options(),
                 lists: dict[int, np.ndarray] | None = None, occluders: occlusion.Occluders | None = None
                 ) -> PoseResult:
    """The ideal views of the rig at any robot pose (x, y, heading, or a 6-DoF [R | t]), numbered `index`.

    What is visible follows the scene's visibility mode as for a path pose: the nearest view-point's list
    (`lists` keeps the view-point masks computed across calls), or, with options.visibility "exact", the
    occluders (`occluders`: Occluders.of_world, computed once by the caller), or everything.
    """
    require_buildable(scene, path=False)  # the pose is given
    pose = tuple(float(v) for v in pose)
    vp, name = scene.viewpoints, None
    if vp is None or vp.visibility == "all" or options.visibility in ("all", "exact"):
        mask = world.mask(None)
    else:
        at = geometry.floor_pose(pose)[:2]  # a 6-DoF pose's floor position, as for a path read from a file
        k = int(visibility.nearest_viewpoint(np.array(vp.points, dtype=float), np.array([at]))[0])
        lists = {} if lists is None else lists
        if k not in lists:
            lists.update(viewpoint_lists(scene, world, [k], options.viewdep))
        mask, name = lists[k], vp.names[k]
    if options.visibility == "exact" and occluders is None:
        occluders = occlusion.Occluders.of_world(world)
    sides = ("left", "right") if options.right else ("left",)
    cams, Rs, ts = [], [], []
    for side in sides:
        mount = getattr(scene.rig, side)
        R_cw, t_cw = geometry.camera_from_world(pose, mount.rotation, mount.position)
        cams.append(scene.camera(mount.camera))
        Rs.append(R_cw)
        ts.append(t_cw)
    views = project_views(world, cams, Rs, ts, [mask] * len(sides), options.tolerance,
                          occluders if options.visibility == "exact" else None)
    return PoseResult(index, pose, name, views[0], views[1] if options.right else None)


def require_buildable(scene: Scene, path: bool = True) -> None:
    """A scene needs a rig, and a path unless its poses come from elsewhere (the API's Simulator)."""
    if scene.rig is None or (path and scene.path is None):
        missing = "a rig" if scene.rig is None else "a path"
        start = Span(scene.source, 1, 1, 1, 1)  # the scene has no statement to point at: its file's start
        raise WiredslError([Diagnostic("error", "E102", f"scene '{scene.name}' needs {missing} to be built", start)])


def visibility_masks(scene: Scene, world: World, options: Options):
    """Per (pose, camera side) feature masks, and the view-point used for each pose."""
    poses = np.array(scene.path.poses, dtype=float)
    chosen = range(len(poses)) if options.poses is None else options.poses
    everything = world.mask(None)
    names: dict[int, str] = {}
    masks: dict[tuple[int, str], np.ndarray] = {}
    vp = scene.viewpoints
    if vp is None or vp.visibility == "all" or options.visibility in ("all", "exact"):  # exact: occlusion.py cuts
        for i in chosen:
            masks[(i, "left")] = masks[(i, "right")] = everything
        return names, masks
    points = np.array(vp.points, dtype=float)
    nearest = visibility.nearest_viewpoint(points, poses[list(chosen), :2]) if len(list(chosen)) else []
    lists = viewpoint_lists(scene, world, sorted(set(int(k) for k in nearest)), options.viewdep)
    for i, k in zip(chosen, nearest, strict=True):
        names[i] = vp.names[k]
        masks[(i, "left")] = masks[(i, "right")] = lists[int(k)]
    return names, masks


def viewpoint_lists(scene: Scene, world: World, which: list[int], viewdep: dict | None = None
                    ) -> dict[int, np.ndarray]:
    """Visibility masks of the given view-point indices, from wherever the scene says they come (`viewdep`:
    the view-dependency file's lists, `wiredsl.io.viewdep.read`, for view-points with `visibility file`)."""
    vp = scene.viewpoints
    if vp.visibility == "authored":
        return {k: world.mask(set(vp.visible.get(vp.names[k], []))) for k in which}
    if vp.visibility == "file":
        if viewdep is None:
            raise ValueError(f"scene '{scene.name}': the view-points' file {vp.file} was not read "
                             "(wiredsl.io.viewdep.of_scene, as wiredsl.run.start does)")
        data = viewdep
        return {k: world.mask(set(data.get(vp.names[k], []))) for k in which}
    eyes = visibility.viewpoint_eyes(scene)[which]
    vis = visibility.visible_features(world, eyes)
    return {k: vis[j] for j, k in enumerate(which)}


# --------------------------------------------------------------------------- projection
#
# All views (poses x cameras) are projected together, in packed arrays: the straight 3D segments
# (lines, polyline segments, silhouette generators) of every view, then the ellipses, then the
# corners. Curves (segments under distortion, ellipse arcs) are sampled adaptively all at once,
# cut to the image all at once, and each end cut at the image border is moved onto the true curve.
# The only Python loops run per view (a 3x3 transform each) or per emitted feature (the objects).

def project_view(world: World, cam: Camera, R_cw: np.ndarray, t_cw: np.ndarray, mask: np.ndarray,
                 tol: float = DEFAULT_TOLERANCE, occluders: occlusion.Occluders | None = None) -> View:
    """What one camera sees of the features in `mask` (only their unoccluded parts, given occluders)."""
    return project_views(world, [cam], [R_cw], [t_cw], [mask], tol, occluders)[0]


def project_views(world: World, cams: list[Camera], R_cw: list, t_cw: list, masks: list,
                  tol: float = DEFAULT_TOLERANCE, occluders: occlusion.Occluders | None = None,
                  motions: list | None = None) -> list[View]:
    """What each camera sees of the features in its mask, for many views (camera, pose) at once.

    With occluders (--visibility exact), each view keeps only the unoccluded parts (occlusion.py). `motions`:
    each view's (robot pose at the camera's time, rolling shutter or None) or None (`motion.view_motions`); a
    rolling shutter's view images every point from the camera's pose at its row's time, its lines as curves.
    """
    with gc_paused():
        return _project_views(world, cams, R_cw, t_cw, masks, tol, occluders, motions)


@contextlib.contextmanager
def gc_paused():
    """Python's cyclic garbage collector paused while the engine makes its many small objects (features,
    strokes, dump records; none in a reference cycle). Left running, it walks every object of the process
    each time enough of them have been made: about a third of a long path's projection in a fresh process."""
    paused = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if paused:
            gc.enable()


def _project_views(world: World, cams: list[Camera], R_cw: list, t_cw: list, masks: list, tol: float,
                   occluders: occlusion.Occluders | None, motions: list | None = None) -> list[View]:
    views = [View(c, np.asarray(R, float), np.asarray(t, float)) for c, R, t in zip(cams, R_cw, t_cw, strict=True)]
    if not views:
        return views
    cam = _camera_table(cams)
    if motions is not None:
        for v, m in zip(views, motions, strict=True):
            if m is not None:
                v.robot, v.rolling = m
        rolling = np.array([v.rolling is not None for v in views])
        if rolling.any():  # its lines are curves, sampled and cut on the rolling-shutter image
            cam["rolling"], cam["views"] = rolling, views
            cam["distorted"] = cam["distorted"] | rolling
    masks = np.asarray(masks, dtype=bool).reshape(len(views), -1)
    out = _Emitted(views, frozenset(fid for fid, _ in world.contours))
    eyes = None if occluders is None else [  # pixels a radian: what is too small to keep
        occluders.seen_from(v.R_cw, v.t_cw, v.camera.f * max(v.camera.ax, v.camera.ay)) for v in views]
    ellipses = _ellipses_cam(world, views)
    seg = _straight_segments(world, views, cam, masks, eyes, ellipses)
    ell = _ellipse_intervals(world, views, cam, masks, eyes, ellipses)
    _emit_lines(seg, views, cam, out)
    # every curve of every view sampled together: segments under distortion, then ellipse arcs
    curved = np.flatnonzero(seg.keep & cam["distorted"][seg.vid])
    curves = _Curves(cam, np.concatenate([seg.vid[curved], ell.vid[ell.owner]]),
                     np.concatenate([seg.A[curved], ell.c[ell.owner]]),
                     np.concatenate([seg.D[curved], ell.U[ell.owner]]),
                     np.concatenate([np.zeros((len(curved), 3)), ell.V[ell.owner]]),
                     np.arange(len(curved) + len(ell.owner)) < len(curved))
    try:
        cid, ts, bounds, uv = curves.sample(np.concatenate([seg.t0[curved], ell.lo]),
                                            np.concatenate([seg.t1[curved], ell.hi]), tol,
                                            np.where(curves.line, 2, 16))
    except geometry.TooManyVertices as exc:
        raise _too_many(exc, tol) from None
    P = curves.points(cid, ts)
    world_pts = functools.cache(lambda: out.to_world(P, curves.view[cid]))  # for the raw strokes, when read
    n_seg = len(curved)
    # a segment's curve is one run; an ellipse arc splits into runs inside the fold radius
    seg_runs = np.stack([bounds[:n_seg], bounds[1:n_seg + 1]], axis=1)
    ell_runs, ell_run_meta = _fold_runs(ell, cam, cid, ts, P, bounds, n_seg)
    runs = np.concatenate([seg_runs, ell_runs])
    pieces = curves.clip(cid, ts, uv, runs)
    _emit_curved_segments(seg, curved, seg_runs, pieces, world_pts, out)
    _emit_ellipses(ell, cam, ell_runs, ell_run_meta, pieces, n_seg, world_pts, out)
    _emit_corners(world, views, cam, masks, out, eyes)
    out.deliver()
    if eyes is not None:  # parts also cut by the image border get their own numbers (occlusion.py)
        for v in views:
            occlusion.number_parts(v.features)
    return views


def _too_many(exc: geometry.TooManyVertices, tol: float) -> WiredslError:
    what = "one curve" if exc.curve >= 0 else "the projection of all views"
    return WiredslError([Diagnostic(
        "error", "E151", f"{what} would need more than {exc.limit:,} polyline vertices at a tolerance of {tol:g} px",
        None, "use a larger --tolerance; the camera model is only meaningful to about 1e-6 px")])


class _Emitted:
    """Features and raw strokes as they are produced, delivered to the views in a stable order."""

    def __init__(self, views: list[View], chained: frozenset = frozenset()):
        self.views = views
        self.chained = chained  # fids whose pieces of one segment join end to end (contours)
        self.features: list[tuple[tuple, ImageFeature]] = []
        self.raw: list = []  # functions giving [(key, Raw)]: called the first time a view's strokes are read

    def to_world(self, P_cam: np.ndarray, vid: np.ndarray) -> np.ndarray:
        """Camera-frame points (m, 3) of views vid (m,) back in the world frame, one transform a view."""
        out = np.empty_like(P_cam)
        # vid comes in a few sorted runs (segments, then ellipses): one transform a block of equal views
        cuts = np.flatnonzero(vid[1:] != vid[:-1]) + 1
        starts, ends = np.concatenate([[0], cuts]).tolist(), np.concatenate([cuts, [len(vid)]]).tolist()
        for a, b, k in zip(starts, ends, vid[starts].tolist(), strict=True) if len(vid) else ():
            out[a:b] = (P_cam[a:b] - self.views[k].t_cw) @ self.views[k].R_cw
        return out

    def deliver(self) -> None:
        for key, f in sorted(self.features, key=lambda kf: kf[0]):
            self.views[key[0]].features.append(f)
        if self.chained:
            for v in self.views:
                v.features = _joined(v.features, self.chained)
        strokes = _RawStrokes(self.raw, len(self.views), self.chained)
        for k, v in enumerate(self.views):
            v.raw = _Strokes(strokes, k)


def _joined(items: list, chained: frozenset, points: str = "points") -> list:
    """Consecutive strokes (ImageFeature or Raw) of a chained feature and one segment whose ends meet, joined
    into one polyline (closed when it comes back to its start uncut); other items as they are."""
    out = []
    for f in items:
        prev = out[-1] if out else None
        if (f.fid in chained and f.kind in ("line", "polyline") and prev is not None and prev.fid == f.fid
                and prev.kind in ("line", "polyline") and prev.segment == f.segment and not prev.closed
                and np.array_equal(getattr(prev, points)[-1], getattr(f, points)[0])):
            P = np.concatenate([getattr(prev, points), getattr(f, points)[1:]])
            prev = out[-1] = dataclasses.replace(prev, kind="polyline", clipped=prev.clipped or f.clipped,
                                                 occluded=prev.occluded or f.occluded,
                                                 fragment=prev.fragment if prev.fragment >= 0 else f.fragment)
            setattr(prev, points, P)
            if not prev.clipped and len(P) > 3 and np.array_equal(P[0], P[-1]):
                prev.closed = True
        else:
            out.append(f)
    return out


class _RawStrokes:
    """The raw strokes of views projected together, made for all of them the first time any view's are read
    (the Monte-Carlo engines read them; a plain build, which writes the clipped features, never does)."""

    def __init__(self, makers: list, n_views: int, chained: frozenset = frozenset()):
        self.makers, self.n_views, self.lists, self.chained = makers, n_views, None, chained

    def of(self, k: int) -> list[Raw]:
        if self.lists is None:
            lists = [[] for _ in range(self.n_views)]
            with gc_paused():
                for key, r in sorted((kr for make in self.makers for kr in make()), key=lambda kr: kr[0]):
                    lists[key[0]].append(r)
            if self.chained:
                lists = [_joined(x, self.chained, "world") for x in lists]
            self.lists, self.makers = lists, None
        return self.lists[k]


class _Strokes(Sequence):
    """One view's raw strokes, a sequence of Raw made when first read (`_RawStrokes`)."""

    def __init__(self, strokes: _RawStrokes, k: int):
        self._strokes, self._k = strokes, k

    def __getitem__(self, i):
        return self._strokes.of(self._k)[i]

    def __len__(self) -> int:
        return len(self._strokes.of(self._k))

    def __iter__(self):
        return iter(self._strokes.of(self._k))

    def __eq__(self, other) -> bool:
        return isinstance(other, Sequence) and list(self) == list(other)

    def __repr__(self) -> str:
        return repr(self._strokes.of(self._k))

    def __reduce__(self):  # pickled (a study's worker) as the plain list
        return list, (list(self),)


def _camera_table(cams: list[Camera]) -> dict[str, np.ndarray]:
    """Per-view camera parameters as arrays (V,), with the lens model and limit (`geometry.lens_limit`), and
    whether lines are curves in the image."""
    distinct = {id(c): c for c in cams}  # the views of a path share a few Camera objects
    row = {k: {**geometry.camera_table(c), "width": float(c.width), "height": float(c.height),
               "distorted": geometry.is_distorted(c)} for k, c in distinct.items()}
    rows = [row[id(c)] for c in cams]
    table = {k: np.array([r[k] for r in rows]) for k in rows[0]}
    # each distinct set of camera numbers once, as scalars: points are projected a camera at a time
    numbers = np.column_stack([table[k] for k in _CAMERA]).astype(float)
    # the same bits, not just equal values (0.0 and -0.0 apart): the same doubles as a column a point
    _, first, which = np.unique(numbers.view(np.int64), axis=0, return_index=True, return_inverse=True)
    table["camera"] = which.reshape(-1)
    table["cameras"] = [dict(zip(_CAMERA, numbers[i].tolist(), strict=True)) for i in first.tolist()]
    return table


_CAMERA = (*geometry.CAMERA_KEYS, "model")  # the numbers geometry.project needs


def _pixels(P: np.ndarray, cam: dict, v: np.ndarray) -> np.ndarray:
    """Camera-frame points (m, 3) the cameras of views v (m,) image -> pixels (m, 2).

    A pixel beyond float range (a focal length of 1e300 px) is inf: such points count as outside the image;
    a radtan point that rounding at huge distances left at z <= 0 is NaN (outside every image).
    Each distinct camera projects its points with its numbers as scalars, which gives the same doubles as
    one projection with a column of numbers a point, in less time.
    """
    cameras = cam["cameras"]
    if len(cameras) == 1:
        out = geometry.project(P, cameras[0])
    else:
        which = cam["camera"][v]
        out = np.empty((len(P), 2))
        for k in np.flatnonzero(np.bincount(which, minlength=len(cameras))).tolist():
            rows = np.flatnonzero(which == k)
            out[rows] = geometry.project(P[rows], cameras[k])
    if "rolling" in cam:
        _rolling(P, cam, v, out)
    return out


def _rolling(P: np.ndarray, cam: dict, v: np.ndarray, out: np.ndarray) -> None:
    """The pixels `out` (m, 2) of camera-frame points P (m, 3) of views v (m,) re-made where the view has a rolling
    shutter: each point imaged from the camera's pose at its row's time (`motion.rolling_pixels`)."""
    from wiredsl.engine import motion

    for k in np.unique(v[cam["rolling"][v]]).tolist():
        rows = np.flatnonzero(v == k)
        view = cam["views"][k]
        R, t = view.R_cw, view.t_cw
        g = cam["cameras"][int(cam["camera"][k])]
        readout, height, robot, vel, w = view.rolling
        out[rows] = motion.rolling_pixels((P[rows] - t) @ R, lambda X, R=R, t=t, g=g: geometry.project(X @ R.T + t, g),
                                          readout, height, robot, vel, w)


def _ellipses_cam(world: World, views: list[View]):
    """Every ellipse in every view's camera frame: centres, U and V, each (V, m, 3)."""
    c = np.stack([world.ell_c @ v.R_cw.T + v.t_cw for v in views])
    U = np.stack([world.ell_U @ v.R_cw.T for v in views])
    V = np.stack([world.ell_V @ v.R_cw.T for v in views])
    return c, U, V


def silhouettes_cam(world: World, mask: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray):
    """Camera-frame contour generators of one view's visible silhouettes: (A, B, fid, side)."""
    _, A, B, fid, side = silhouettes_cams(world, [View(None, R_cw, t_cw)], np.asarray(mask, bool)[None])
    return A, B, fid, side


def silhouettes_cams(world: World, views: list[View], masks: np.ndarray, ellipses: tuple | None = None):
    """Camera-frame contour generators of the visible silhouettes of every view (`ellipses`: their
    `_ellipses_cam`, when the caller has them).

    Returns (view, A, B, fid, side): the two sides of a silhouette are numbered by where they
    appear, left to right in the image, for stable indices.
    """
    vv, ss = np.nonzero(masks[:, world.sil_fid]) if len(world.sil_fid) else (np.zeros(0, int),) * 2
    z3 = np.zeros((0, 3))
    if len(vv) == 0:
        return np.zeros(0, int), z3, z3, np.zeros(0, int), np.zeros(0, int)
    c, U, V = _ellipses_cam(world, views) if ellipses is None else ellipses
    a, b = world.sil_pair[ss, 0], world.sil_pair[ss, 1]
    full = world.ell_full
    o, A, B = conics.silhouette_segments_batch(c[vv, a], U[vv, a], V[vv, a], c[vv, b], U[vv, b], V[vv, b],
                                               world.ell_arc[a], full[a], world.ell_arc[b], full[b])
    with np.errstate(divide="ignore", invalid="ignore"):
        key = np.where(A[:, 2] > 0, A[:, 0] / np.where(A[:, 2] > 0, A[:, 2], 1.0), np.inf)
    order = np.lexsort((key, o))
    o, A, B = o[order], A[order], B[order]
    first = np.searchsorted(o, o)
    return vv[o], A, B, world.sil_fid[ss[o]], np.arange(len(o)) - first


@dataclass
class _Segments:
    """Straight 3D segments of every view (camera frame), clipped to the near plane and the fold cone."""

    vid: np.ndarray
    A: np.ndarray
    D: np.ndarray
    fid: np.ndarray
    seg: np.ndarray
    t0: np.ndarray
    t1: np.ndarray
    keep: np.ndarray
    cut3d: np.ndarray
    piece: np.ndarray  # part index when occlusion cut the segment, else -1
    hid: np.ndarray  # occlusion cut it


def _straight_segments(world: World, views: list[View], cam: dict, masks: np.ndarray, eyes, ellipses: tuple
                       ) -> _Segments:
    """Lines, polyline segments and silhouette sides of every view, in that order within a view."""
    sv, sA, sB, sfid, sside = silhouettes_cams(world, views, masks, ellipses)
    (sv, sA, sB, sfid, sside), own = _with_contours(world, views, masks, (sv, sA, sB, sfid, sside))
    lv, ll = np.nonzero(masks[:, world.line_fid]) if len(world.line_fid) else (np.zeros(0, int),) * 2
    R = np.stack([v.R_cw for v in views])
    t = np.stack([v.t_cw for v in views])
    ends = np.einsum("vij,lkj->vlki", R, world.lines)[lv, ll] + t[lv, None]  # (n, 2, 3) camera frame
    # within a view: its lines and polyline segments, then its silhouette sides
    vid = np.concatenate([lv, sv])
    order = np.argsort(vid, kind="stable")
    vid = vid[order]
    A = np.concatenate([ends[:, 0], sA])[order]
    B = np.concatenate([ends[:, 1], sB])[order]
    fid = np.concatenate([world.line_fid[ll], sfid])[order]
    seg = np.concatenate([world.line_segment[ll], sside])[order]
    own = tuple(np.concatenate([np.zeros(len(ll), x.dtype), x])[order] for x in own)  # a line: no own surface
    rows, t0, t1 = geometry.clip_segments_lens(A, B, cam["model"][vid], cam["limit"][vid])
    vid, A, B, fid, seg = vid[rows], A[rows], B[rows], fid[rows], seg[rows]  # a fisheye may cut one in parts
    own = tuple(x[rows] for x in own)
    keep = np.ones(len(rows), dtype=bool)
    fid, seg = fid.astype(int), seg.astype(int)
    cut3d = (t0 > 0) | (t1 < 1)
    piece, hid = np.full(len(A), -1), np.zeros(len(A), dtype=bool)
    if eyes is not None:  # --visibility exact: one row per unoccluded part, view by view (occlusion.py)
        parts = []
        for k, eye in enumerate(eyes):
            m = np.flatnonzero(vid == k)
            r, u0, u1, pc, hd = occlusion.split_segments(eye, A[m], B[m], t0[m], t1[m], keep[m],
                                                         tuple(x[m] for x in own))
            parts.append((m[r], u0, u1, pc, hd))
        rows, u0, u1, piece, hid = (np.concatenate(x) for x in zip(*parts, strict=True))
        rows = rows.astype(int)
        cut3d = ((u0 > 0) & (u0 == t0[rows])) | ((u1 < 1) & (u1 == t1[rows]))  # the near plane, not occlusion
        vid, A, B, fid, seg, t0, t1 = vid[rows], A[rows], B[rows], fid[rows], seg[rows], u0, u1
        keep = np.ones(len(rows), dtype=bool)
    return _Segments(vid, A, B - A, fid, seg, t0, t1, keep, cut3d, piece.astype(int), hid.astype(bool))


def _with_contours(world: World, views: list[View], masks: np.ndarray, sil: tuple) -> tuple[tuple, tuple]:
    """The silhouette sides and the occluding-contour edges of smooth mesh surfaces (engine/mesh.py) of
    every view: (view, A, B, fid, segment), camera frame; a contour's edges come chained end to end, its
    segment the chain's number in the view (`_Emitted.deliver` joins each chain's pieces into polylines).
    And (first, end, reach) a row: a contour edge's own surface (its triangles [first, end) of World.triangles)
    and how far before the edge that surface must be to hide it (`Contours`; a silhouette side: none)."""
    n = len(sil[0])
    own = [(np.zeros(n, int), np.zeros(n, int), np.zeros(n))]
    if not world.contours:
        return sil, own[0]
    parts = [sil]
    for k, v in enumerate(views):
        eye = -v.R_cw.T @ v.t_cw  # the camera's centre in the world
        for fid, cont in world.contours:
            if masks[k, fid]:
                e, chain, back = cont.chains(np.flatnonzero(cont.seen_from(eye)))
                P = cont.ends[e] @ v.R_cw.T + v.t_cw
                P = np.where(back[:, None, None], P[:, ::-1], P)
                parts.append((np.full(len(e), k), P[:, 0], P[:, 1], np.full(len(e), fid), chain))
                own.append((np.full(len(e), cont.own[0]), np.full(len(e), cont.own[1]), cont.reach[e]))
    return (tuple(np.concatenate(x) for x in zip(*parts, strict=True)),
            tuple(np.concatenate(x) for x in zip(*own, strict=True)))


def _emit_lines(s: _Segments, views: list[View], cam: dict, out: _Emitted) -> None:
    """Segments of undistorted views: straight in the image too, clipped exactly."""
    idx = np.flatnonzero(s.keep & ~cam["distorted"][s.vid])
    if len(idx) == 0:
        return
    vid = s.vid[idx]
    Pa, Pb = s.A[idx] + s.t0[idx, None] * s.D[idx], s.A[idx] + s.t1[idx, None] * s.D[idx]
    fid, seg, cut3d, vl = s.fid[idx].tolist(), s.seg[idx].tolist(), s.cut3d[idx].tolist(), vid.tolist()
    piece, hid = s.piece[idx].tolist(), s.hid[idx].tolist()

    def strokes():
        Wa, Wb = out.to_world(Pa, vid), out.to_world(Pb, vid)
        return [((vl[j], 0, i), Raw(fid[j], seg[j], "line", False, cut3d[j], np.stack([Wa[j], Wb[j]]), piece[j],
                                    hid[j])) for j, i in enumerate(idx.tolist())]

    out.raw.append(strokes)
    a, b = _pixels(Pa, cam, vid), _pixels(Pb, cam, vid)
    finite = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
    a, b = np.where(finite[:, None], a, 0.0), np.where(finite[:, None], b, 0.0)
    r0, r1, ok = geometry.clip_segments_rect(a, b, cam["width"][vid], cam["height"][vid])
    d = b - a
    ok &= finite & (np.hypot(d[:, 0], d[:, 1]) * (r1 - r0) > 1e-9)  # a line seen end-on has no image
    for j in np.flatnonzero(ok & (r1 > r0)).tolist():
        pts = np.stack([a[j] + r0[j] * d[j], a[j] + r1[j] * d[j]])
        cut = bool(cut3d[j] or r0[j] > 0 or r1[j] < 1)
        out.features.append(((vl[j], 0, int(idx[j]), 0), ImageFeature(fid[j], "line", pts, seg[j], cut,
                                                                      fragment=piece[j], occluded=hid[j])))


def _emit_curved_segments(s: _Segments, curved: np.ndarray, runs: np.ndarray, pieces, world_pts, out: _Emitted):
    """Segments of distorted views: adaptive polylines (curve k of the sampling is segment curved[k])."""
    vl, fid, seg, cut3d, piece, hid = (x[curved].tolist() for x in (s.vid, s.fid, s.seg, s.cut3d, s.piece, s.hid))
    cl = curved.tolist()

    def strokes():
        W = world_pts()
        return [((vl[k], 0, cl[k]), Raw(fid[k], seg[k], "polyline", False, cut3d[k], W[b0:b1], piece[k], hid[k]))
                for k, (b0, b1) in enumerate(runs.tolist())]

    out.raw.append(strokes)
    for n, (k, pts, cut) in enumerate(pieces):
        if k < len(cl):
            out.features.append(((vl[k], 0, cl[k], n),
                                 ImageFeature(fid[k], "polyline", pts, seg[k], bool(cut or cut3d[k]),
                                              fragment=piece[k], occluded=hid[k])))


class _Curves:
    """Curves P(t) = base + X cos t + Y sin t (ellipses) or base + t X (lines, Y = 0), camera frame."""

    def __init__(self, cam: dict, view: np.ndarray, base: np.ndarray, X: np.ndarray, Y: np.ndarray,
                 line: np.ndarray):
        self.cam, self.view, self.line = cam, view, line
        # the coordinates apart (3, n): gathering and combining contiguous rows costs less than (n, 3) rows
        self.base, self.X, self.Y = (np.ascontiguousarray(np.asarray(a, float).T) for a in (base, X, Y))
        # points are evaluated a group at a time: one camera (its numbers as scalars) and one kind (lines
        # without cosines)
        self.group = 2 * cam["camera"][view] + line
        self.n_groups = 2 * len(cam["cameras"])

    def _groups(self, c: np.ndarray) -> list:
        """[(group, rows of c in it, or None for all of c)] for the groups of curves c."""
        g = self.group.take(c)
        present = np.flatnonzero(np.bincount(g, minlength=self.n_groups)).tolist()
        if len(present) == 1:
            return [(present[0], None)]
        return [(k, np.flatnonzero(g == k)) for k in present]

    def _xyz(self, c: np.ndarray, t: np.ndarray, line: bool) -> np.ndarray:
        """Points (3, m) of curves c (m,), all lines or all ellipses, at parameters t (m,)."""
        take = functools.partial(np.take, indices=c, axis=1)  # np.take: several times faster than [:, c]
        if line:  # (base + t X) + 0 Y, Y = 0: adding 0.0 turns a -0.0 into 0.0, as the sum with 0 Y does
            return take(self.base) + t * take(self.X) + 0.0
        return take(self.base) + np.cos(t) * take(self.X) + np.sin(t) * take(self.Y)

    def points(self, c: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Points (m, 3) of curves c (m,) at parameters t (m,)."""
        out = np.empty((3, len(c)))
        for k, rows in self._groups(c):
            if rows is None:
                out = self._xyz(c, t, bool(k & 1))
            else:
                out[:, rows] = self._xyz(c.take(rows), t.take(rows), bool(k & 1))
        return np.ascontiguousarray(out.T)

    def pixels(self, c: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Pixels (m, 2) of curves c (m,) at parameters t (m,)."""
        out = np.empty((len(c), 2))
        for k, rows in self._groups(c):
            cc, tt = (c, t) if rows is None else (c.take(rows), t.take(rows))
            X, Y, Z = self._xyz(cc, tt, bool(k & 1))
            at = slice(None) if rows is None else rows
            out[at, 0], out[at, 1] = geometry.project_xyz(X, Y, Z, self.cam["cameras"][k >> 1])
        if "rolling" in self.cam:
            rows = np.flatnonzero(self.cam["rolling"][self.view[c]])
            if len(rows):
                sub = np.empty((len(rows), 2))
                _rolling(self.points(c[rows], t[rows]), self.cam, self.view[c[rows]], sub)
                out[rows] = sub
        return out

    def sample(self, t0: np.ndarray, t1: np.ndarray, tol: float, start):
        """(cid, t, bounds, pixels) of `geometry.adaptive_samples_packed`."""
        image = (self.cam["width"][self.view], self.cam["height"][self.view])
        return geometry.adaptive_samples_packed(self.pixels, t0, t1, tol, start, image=image, points=True)

    def clip(self, cid: np.ndarray, ts: np.ndarray, uv: np.ndarray, runs: np.ndarray) -> list:
        """Cut the polylines of sample runs (R, 2) [first, end) to the image (the samples' pixels uv (m, 2));
        ends cut at the border lie on the curve. Returns [(run, pixels (k, 2), cut)] in run order."""
        cam = self.cam
        keep = runs[:, 1] > runs[:, 0]
        runs = runs[keep]
        sizes = runs[:, 1] - runs[:, 0]
        take = geometry._ranges(runs[:, 0], sizes)
        c, t = cid[take], ts[take]
        uv = uv[take]
        start = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
        run_of = np.flatnonzero(keep)
        v = self.view[c[start[:-1]]]
        r = geometry.clip_polylines_rect(uv, start, cam["width"][v], cam["height"][v])
        pts = r["pts"]
        ends = np.flatnonzero(r["end"] > 0)
        if len(ends):
            j = r["seg"][ends]
            pts[ends] = self._on_border(c[j], t[j], t[j + 1], r["at"][ends], r["side"][ends], pts[ends])
        src, bounds, cut = run_of[r["src"]].tolist(), r["start"].tolist(), r["cut"].tolist()
        return [(src[k], pts[bounds[k]:bounds[k + 1]], cut[k]) for k in range(len(src))]

    def _on_border(self, c, ta, tb, at, side, chord_pts) -> np.ndarray:
        """Where the curve crosses the border `side` between parameters ta and tb (Illinois regula falsi).

        Falls back to the chord's crossing where the curve's end values do not bracket the border.
        """
        axis = np.where(side < 2, 0, 1)
        v = self.view[c]
        level = np.select([side == 1, side == 3], [self.cam["width"][v], self.cam["height"][v]], 0.0)
        rows = np.arange(len(c))

        def g(t):
            return self.pixels(c, t)[rows, axis] - level

        ga, gb = g(ta), g(tb)
        ok = np.isfinite(ga) & np.isfinite(gb) & (np.sign(ga) != np.sign(gb))
        a, b, fa, fb = ta.copy(), tb.copy(), ga.copy(), gb.copy()
        last = np.zeros(len(c), dtype=int)
        x = ta + at * (tb - ta)
        for _ in range(100):
            fx = g(x)
            done = ~ok | (np.abs(fx) <= 1e-10) | (np.abs(b - a) <= 1e-15 * np.maximum(np.abs(a), 1.0))
            if done.all():
                break
            left = np.sign(fx) == np.sign(fa)  # the root lies in [x, b]
            a, fa, b, fb = np.where(left, x, a), np.where(left, fx, fa), np.where(left, b, x), np.where(left, fb, fx)
            # Illinois: halve the weight of an end kept twice in a row, so convergence stays superlinear
            fb = np.where(left & (last == 1), fb / 2, fb)
            fa = np.where(~left & (last == -1), fa / 2, fa)
            last = np.where(left, 1, -1)
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                x_new = (a * fb - b * fa) / (fb - fa)
            x_new = np.where(np.isfinite(x_new) & (x_new >= np.minimum(a, b)) & (x_new <= np.maximum(a, b)),
                             x_new, 0.5 * (a + b))
            x = np.where(done, x, x_new)
        p = self.pixels(c, x)
        p[rows, axis] = np.where(ok, level, p[rows, axis])  # exactly on the border (within 1e-10 px already)
        return np.where(ok[:, None] & np.isfinite(p).all(axis=1)[:, None], p, chord_pts)


def _front_intervals(cz, Az, Bz, arc):
    """Parts of each ellipse's arc [t0, t1] where cz + Az cos t + Bz sin t > NEAR.

    For n ellipses (arrays (n,), arc (n, 2)): (owner (k,), lo (k,), hi (k,)), in order.
    """
    t0, t1 = arc[:, 0], arc[:, 1]
    R = np.hypot(Az, Bz)
    level = geometry.NEAR - cz
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ratio = level / np.where(R > 0, R, 1e-300)
    flat = (R <= 1e-15 * np.maximum(np.abs(cz), 1.0)) | (ratio <= -1)
    flat_in = flat & ((level < 0) | (ratio <= -1))
    phi = np.arctan2(Bz, Az)
    alpha = np.arccos(np.clip(ratio, -1.0, 1.0))
    # visible where |t - phi| < alpha (mod 2 pi); intersect with [t0, t1]
    k0 = np.floor((t0 - phi - alpha) / (2 * math.pi))
    ks = k0[:, None] + np.arange(3)[None, :]
    lo = phi[:, None] - alpha[:, None] + 2 * math.pi * ks
    hi = phi[:, None] + alpha[:, None] + 2 * math.pi * ks
    a, b = np.maximum(lo, t0[:, None]), np.minimum(hi, t1[:, None])
    ok = (~flat & (ratio < 1))[:, None] & (b > a)
    ok = np.concatenate([flat_in[:, None], ok], axis=1)
    a = np.concatenate([t0[:, None], a], axis=1)
    b = np.concatenate([t1[:, None], b], axis=1)
    owner, col = np.nonzero(ok)
    return owner, a[owner, col], b[owner, col]


LENS_SAMPLES = 256  # samples of an ellipse arc where a fisheye's visible parts are sought (then bisected)


def _lens_intervals(c, U, V, arc, limit, n: int = LENS_SAMPLES):
    """Parts of each ellipse's arc that a fisheye images: theta < limit and at least NEAR from the centre.

    The arc is sampled at n + 1 points and each change of side bisected to 1e-15 of the arc, so a part
    narrower than 1/n of the arc may be missed. For E ellipses: (owner (k,), lo (k,), hi (k,)), in order.
    """
    E = len(c)
    if E == 0:
        return np.zeros(0, int), np.zeros(0), np.zeros(0)
    cos_lim = np.cos(limit)

    def h(e, t):  # > 0 where imaged
        P = c[e] + np.cos(t)[:, None] * U[e] + np.sin(t)[:, None] * V[e]
        r = np.sqrt((P * P).sum(axis=1))
        return np.minimum(P[:, 2] - r * cos_lim[e], r - geometry.NEAR)

    T = arc[:, :1] + (arc[:, 1] - arc[:, 0])[:, None] * np.linspace(0.0, 1.0, n + 1)[None, :]
    T[:, 0], T[:, -1] = arc[:, 0], arc[:, 1]
    H = h(np.repeat(np.arange(E), n + 1), T.ravel()).reshape(E, n + 1)
    pos = H > 0
    ce, cj = np.nonzero(pos[:, :-1] != pos[:, 1:])
    a, b, in_a = T[ce, cj], T[ce, cj + 1], pos[ce, cj]
    for _ in range(64):
        m = 0.5 * (a + b)
        same = (h(ce, m) > 0) == in_a
        a, b = np.where(same, m, a), np.where(same, b, m)
    # a part starts at the arc's start or where it enters; ends where it leaves or at the arc's end
    s_e = np.concatenate([np.flatnonzero(pos[:, 0]), ce[~in_a]])
    s_t = np.concatenate([arc[pos[:, 0], 0], b[~in_a]])
    e_e = np.concatenate([ce[in_a], np.flatnonzero(pos[:, -1])])
    e_t = np.concatenate([a[in_a], arc[pos[:, -1], 1]])
    so, eo = np.lexsort((s_t, s_e)), np.lexsort((e_t, e_e))
    return s_e[so], s_t[so], e_t[eo]


@dataclass
class _Ellipses:
    """The visible ellipses of every view (camera frame) and their arcs in front of the near plane."""

    vid: np.ndarray  # (E,) view of each
    c: np.ndarray
    U: np.ndarray
    V: np.ndarray
    arc: np.ndarray
    full: np.ndarray
    fid: np.ndarray
    owner: np.ndarray  # (I,) the ellipse of each interval in front
    lo: np.ndarray
    hi: np.ndarray
    whole: np.ndarray  # (E,) the whole arc is in front (one interval, equal to the arc)
    hid: np.ndarray  # (E,) occlusion cut it (--visibility exact)


def _ellipse_intervals(world: World, views: list[View], cam: dict, masks: np.ndarray, eyes, ellipses: tuple
                       ) -> _Ellipses:
    """The visible ellipses of every view (`ellipses`: `_ellipses_cam`) and their arcs in front."""
    vv, ee = np.nonzero(masks[:, world.ell_fid]) if len(world.ell_fid) else (np.zeros(0, int),) * 2
    c, U, V = (x[vv, ee] for x in ellipses)
    arc = world.ell_arc[ee]
    fish = cam["model"][vv] != geometry.RADTAN  # an angle-bounded lens
    rad = np.flatnonzero(~fish)
    owner, lo, hi = _front_intervals(c[rad, 2], U[rad, 2], V[rad, 2], arc[rad])
    if fish.any():  # the parts a fisheye images (its region is not bounded by a plane)
        fe = np.flatnonzero(fish)
        fo, flo, fhi = _lens_intervals(c[fe], U[fe], V[fe], arc[fe], cam["limit"][vv[fe]])
        owner, lo, hi = np.concatenate([rad[owner], fe[fo]]), np.concatenate([lo, flo]), np.concatenate([hi, fhi])
        order = np.lexsort((lo, owner))
        owner, lo, hi = owner[order], lo[order], hi[order]
    else:
        owner = rad[owner]
    whole = np.zeros(len(vv), dtype=bool)
    one = np.flatnonzero(np.bincount(owner, minlength=len(vv)) == 1)
    first = np.searchsorted(owner, one)
    whole[one] = (lo[first] == arc[one, 0]) & (hi[first] == arc[one, 1])
    full = world.ell_full[ee]
    hid = np.zeros(len(vv), dtype=bool)
    if eyes is not None:  # --visibility exact: the unoccluded arcs, view by view (occlusion.py)
        parts = [(np.zeros(0, int), np.zeros(0), np.zeros(0))]
        for k, eye in enumerate(eyes):
            mine = np.flatnonzero(vv == k)  # the view's ellipses (vv is sorted) and their arcs
            if len(mine) == 0:
                continue
            at = np.flatnonzero((owner >= mine[0]) & (owner <= mine[-1]))
            o, a, b, hid[mine] = occlusion.split_arcs(eye, c[mine], U[mine], V[mine], owner[at] - mine[0], lo[at],
                                                      hi[at], full[mine])
            parts.append((o + mine[0], a, b))
        owner, lo, hi = (np.concatenate(x) for x in zip(*parts, strict=True))
        owner = owner.astype(int)
    return _Ellipses(vv, c, U, V, arc, full, world.ell_fid[ee], owner, lo, hi, whole, hid)


def _fold_runs(ell: _Ellipses, cam: dict, cid, ts, P, bounds, n_seg: int):
    """Runs [first, end) of each ellipse interval's samples inside the fold radius (radtan), with (interval,
    raw closed, raw clipped, any sample cut of its ellipse) for each run."""
    lo = bounds[n_seg]
    icid = cid[lo:] - n_seg  # interval of each ellipse sample
    Pe = P[lo:]
    n_int = len(ell.owner)
    e_of = ell.owner[icid]
    v_of = ell.vid[e_of]
    # a fisheye's intervals are exact already (their ends lie on its limit); a radtan's are cut at the fold
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        inside = (cam["model"][v_of] != geometry.RADTAN) | (np.hypot(Pe[:, 0] / Pe[:, 2], Pe[:, 1] / Pe[:, 2])
                                               < cam["limit"][v_of])
    first = np.zeros(len(icid), dtype=bool)
    first[bounds[n_seg:-1] - lo] = True
    last = np.zeros(len(icid), dtype=bool)
    last[bounds[n_seg + 1:] - lo - 1] = True
    prev_in = np.concatenate([[False], inside[:-1]])
    next_in = np.concatenate([inside[1:], [False]])
    begin = np.flatnonzero(inside & (first | ~prev_in))
    end = np.flatnonzero(inside & (last | ~next_in)) + 1
    run_int = icid[begin]
    all_in = np.bincount(icid, weights=~inside, minlength=n_int) == 0
    runs_per_int = np.bincount(run_int, minlength=n_int)
    e = ell.owner[run_int]
    closed = ell.full[e] & ell.whole[e] & ~ell.hid[e] & (runs_per_int[run_int] == 1) & all_in[run_int]
    clipped = ~(ell.whole[e] & all_in[run_int])
    any_cut = ~ell.whole | (np.bincount(e_of, weights=~inside, minlength=len(ell.vid)) > 0)
    return np.stack([begin + lo, end + lo], axis=1).reshape(-1, 2), (run_int, closed, clipped, any_cut)


def _emit_ellipses(ell: _Ellipses, cam: dict, runs, meta, pieces, n_seg: int, world_pts, out: _Emitted) -> None:
    """Ellipse polylines (runs n_seg... of the pieces), and a conic where the image is an exact ellipse."""
    run_int, closed, clipped, any_cut = meta
    run_e = ell.owner[run_int]
    vl, fl, el = ell.vid[run_e].tolist(), ell.fid[run_e].tolist(), run_e.tolist()
    raw_part = np.where(ell.hid[run_e], occlusion._rank(run_e), -1).tolist()  # runs of an ellipse are adjacent

    def strokes():
        W = world_pts()
        return [((vl[k], 1, el[k], k), Raw(fl[k], -1, "polyline", bool(closed[k]), bool(clipped[k]), W[b0:b1],
                                           raw_part[k], bool(ell.hid[el[k]])))
                for k, (b0, b1) in enumerate(runs.tolist())]

    out.raw.append(strokes)
    mine = [(r - n_seg, pts, cut) for r, pts, cut in pieces if r >= n_seg]
    piece_e = np.array([run_e[r] for r, _, _ in mine], dtype=int)
    n_pieces = np.bincount(piece_e, minlength=len(ell.vid))
    piece_cut = np.bincount(piece_e, weights=[cut for _, _, cut in mine], minlength=len(ell.vid)) > 0
    one_uncut = ell.full & ell.whole & ~ell.hid & (n_pieces == 1) & ~piece_cut
    part = occlusion._rank(piece_e).tolist()  # pieces of an ellipse are adjacent
    for n, (r, pts, cut) in enumerate(mine):
        e = int(piece_e[n])
        hid = bool(ell.hid[e])
        out.features.append(((vl[r], 1, e, n), ImageFeature(fl[r], "polyline", pts, -1, bool(cut or any_cut[e]),
                                                            bool(one_uncut[e]), fragment=part[n] if hid else -1,
                                                            occluded=hid)))
    # conics: exact ellipse images (no distortion, wholly in front, not cut by occlusion), when some of it
    # is in the image
    sel = np.flatnonzero(~cam["distorted"][ell.vid] & ell.whole & ~ell.hid & (n_pieces > 0))
    if len(sel) == 0:
        return
    g = {k: cam[k][ell.vid[sel]] for k in ("f", "ax", "ay", "cx", "cy")}
    K = np.zeros((len(sel), 3, 3))
    K[:, 0, 0], K[:, 0, 2], K[:, 1, 1], K[:, 1, 2], K[:, 2, 2] = g["f"] * g["ax"], g["cx"], g["f"] * g["ay"], g["cy"], 1
    H = K @ conics.homography(ell.c[sel], ell.U[sel], ell.V[sel])
    ok, centre, axes, angle = conics.image_ellipses(H)
    for j in np.flatnonzero(ok).tolist():
        e = int(sel[j])
        arc_img = None if ell.full[e] else _image_arc(H[j], centre[j], axes[j], angle[j], tuple(ell.arc[e]))
        out.features.append(((int(ell.vid[e]), 1, e, len(mine)),
                             ImageFeature(int(ell.fid[e]), "conic", centre[j][None, :], -1, bool(piece_cut[e]),
                                          bool(ell.full[e]), (centre[j], axes[j], float(angle[j]), arc_img))))


def _emit_corners(world: World, views: list[View], cam: dict, masks: np.ndarray, out: _Emitted, eyes=None) -> None:
    """Corner points of every view; each view also keeps its corners in front of it for re-projection."""
    cv, cc = np.nonzero(masks[:, world.corner_fid]) if len(world.corner_fid) else (np.zeros(0, int),) * 2
    if len(cv) == 0:
        return
    R = np.stack([v.R_cw for v in views])
    t = np.stack([v.t_cw for v in views])
    P = np.einsum("vij,cj->vci", R, world.corners)[cv, cc] + t[cv]
    ok = geometry.visible(P, cam["model"][cv], cam["limit"][cv])
    if eyes is not None:  # --visibility exact (occlusion.py)
        for k, eye in enumerate(eyes):
            m = np.flatnonzero(cv == k)
            ok[m] &= ~eye.hidden(P[m])
    uv = _pixels(np.where(ok[:, None], P, np.array([0.0, 0.0, 1.0])), cam, cv)
    front = np.flatnonzero(ok)  # cv is sorted: one split gives every view its corners in front
    cuts = np.searchsorted(cv[front], np.arange(1, len(views)))
    for v, rows in zip(views, np.split(cc[front], cuts), strict=True):
        v.corner_world, v.corner_fid = world.corners[rows], world.corner_fid[rows]
    with np.errstate(invalid="ignore"):
        ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= cam["width"][cv]) & (uv[:, 1] >= 0) & (uv[:, 1] <= cam["height"][cv])
    shown = np.flatnonzero(ok)
    for j, k, f in zip(shown.tolist(), cv[shown].tolist(), world.corner_fid[cc[shown]].tolist(), strict=True):
        out.features.append(((k, 2, j, 0), ImageFeature(f, "corner", uv[j][None, :])))


def _image_arc(H, centre, axes, angle, arc) -> tuple[float, float]:
    """The section's range in the image ellipse's own parameter s (centre + A cos s e1 + B sin s e2)."""
    e1 = np.array([math.cos(angle), math.sin(angle)])
    e2 = np.array([-e1[1], e1[0]])

    def s_of(t):
        p = H @ np.array([math.cos(t), math.sin(t), 1.0])
        q = p[:2] / p[2] - centre
        return math.atan2(q @ e2 / axes[1], q @ e1 / axes[0])

    t0, t1 = arc
    s0, s1, sm = s_of(t0), s_of(t1), s_of((t0 + t1) / 2)
    forward = (sm - s0) % (2 * math.pi) <= (s1 - s0) % (2 * math.pi)
    if not forward:
        s0, s1 = s1, s0
    span = (s1 - s0) % (2 * math.pi)
    return s0, s0 + span
