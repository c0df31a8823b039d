"""Every trial's view at once: the ideal views as ImageSets, and the raw strokes re-projected through each trial's
perturbed camera (calibration error), then cut to the image. Geometry only: the stages that disturb the sets are
run by `wiredsl.montecarlo`.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence

import numpy as np

from wiredsl.engine import geometry
from wiredsl.engine import imageset as im
from wiredsl.engine.simulate import ImageFeature, View
from wiredsl.engine.world import World

CULL = 0.25  # raw strokes wholly beyond the image grown by this fraction of its size are not re-projected


def to_imageset(view: View, world: World) -> im.ImageSet:
    """The ideal features of one view as an ImageSet of one trial (conics are left out)."""
    strokes = [f for f in view.features if f.kind in ("line", "polyline")]
    corners = [f for f in view.features if f.kind == "corner"]
    counts = [len(f.points) for f in strokes]
    kind = [im.ELLIPSE if world.feature_kind[f.fid] == "ellipse" else im.STRAIGHT if f.kind == "line" else im.CURVE
            for f in strokes]
    z = np.zeros(len(strokes), dtype=int)
    return im.ImageSet(
        pts=np.concatenate([f.points for f in strokes]) if strokes else np.zeros((0, 2)),
        start=np.concatenate([[0], np.cumsum(counts)]).astype(int),
        fid=np.array([f.fid for f in strokes], dtype=int), segment=np.array([f.segment for f in strokes], dtype=int),
        fragment=np.array([f.fragment for f in strokes], dtype=int), kind=np.array(kind, dtype=int),
        clipped=np.array([f.clipped for f in strokes], dtype=bool),
        closed=np.array([f.closed for f in strokes], dtype=bool), trial=z,
        corners=np.array([f.points[0] for f in corners]).reshape(-1, 2),
        corner_fid=np.array([f.fid for f in corners], dtype=int), corner_trial=np.zeros(len(corners), dtype=int),
        occluded=np.array([f.occluded for f in strokes], dtype=bool))


def concat_trials(sets: list[im.ImageSet]) -> im.ImageSet:
    """One ImageSet from per-trial ones (trial k gets batch index k)."""
    offsets = np.cumsum([0] + [len(s.pts) for s in sets])
    start = np.concatenate([s.start[:-1] + o for s, o in zip(sets, offsets, strict=False)] + [[offsets[-1]]])
    cat = lambda name: np.concatenate([getattr(s, name) for s in sets])  # noqa: E731
    return im.ImageSet(
        pts=np.concatenate([s.pts for s in sets]), start=start.astype(int), fid=cat("fid"), segment=cat("segment"),
        fragment=cat("fragment"), kind=cat("kind"), clipped=cat("clipped"), closed=cat("closed"),
        trial=np.concatenate([np.full(s.n_strokes, k) for k, s in enumerate(sets)]).astype(int),
        corners=np.concatenate([s.corners for s in sets]).reshape(-1, 2), corner_fid=cat("corner_fid"),
        corner_trial=np.concatenate([np.full(len(s.corners), k) for k, s in enumerate(sets)]).astype(int),
        occluded=cat("occluded"))


def features_of(s: im.ImageSet, k: int) -> list[ImageFeature]:
    """Batch trial k's disturbed features, with fragments numbered per (feature, segment)."""
    out: list[ImageFeature] = []
    idx = np.flatnonzero(s.trial == k)
    pieces: Counter = Counter()
    groups = Counter((int(s.fid[i]), int(s.segment[i])) for i in idx)
    for i in idx:
        key = (int(s.fid[i]), int(s.segment[i]))
        cut = s.fragment[i] >= 0 or groups[key] > 1
        frag = pieces[key] if cut else -1
        pieces[key] += 1
        pts = s.pts[s.start[i]:s.start[i + 1]]
        kind = "line" if s.kind[i] == im.STRAIGHT and len(pts) == 2 else "polyline"
        out.append(ImageFeature(int(s.fid[i]), kind, pts, int(s.segment[i]), bool(s.clipped[i]), bool(s.closed[i]),
                                fragment=frag, occluded=bool(s.occluded[i])))
    for i in np.flatnonzero(s.corner_trial == k):
        out.append(ImageFeature(int(s.corner_fid[i]), "corner", s.corners[i][None, :]))
    return out


def raw_template(view: View, world: World) -> tuple[im.ImageSet, np.ndarray, np.ndarray]:
    """The ideal view's strokes before image clipping as one trial's ImageSet (vertices not yet
    projected), with their world points (N, 3) and the corners' world points (C, 3).

    Strokes whose nominal image lies wholly beyond the image grown by CULL of its size on one side are
    left out: no calibration draw of a plausible rig brings them in, and re-projecting them is about half
    the work of a calibrated trial in the lab."""
    raw = view.raw
    counts = np.array([len(r.world) for r in raw], dtype=int)
    W = np.concatenate([r.world for r in raw]) if raw else np.zeros((0, 3))
    kinds = np.array([im.STRAIGHT if r.kind == "line" else
                      im.ELLIPSE if world.feature_kind[r.fid] == "ellipse" else im.CURVE for r in raw], dtype=int)
    cw = view.corner_world if view.corner_world is not None else np.zeros((0, 3))
    cf = view.corner_fid if view.corner_fid is not None else np.zeros(0, dtype=int)
    z = np.zeros(len(raw), dtype=int)
    template = im.ImageSet(
        pts=np.zeros((len(W), 2)), start=np.concatenate([[0], np.cumsum(counts)]).astype(int),
        fid=np.array([r.fid for r in raw], dtype=int), segment=np.array([r.segment for r in raw], dtype=int),
        fragment=np.array([r.fragment for r in raw], dtype=int), kind=kinds,
        clipped=np.array([r.clipped for r in raw], dtype=bool),
        closed=np.array([r.closed for r in raw], dtype=bool), trial=z, corners=np.zeros((len(cw), 2)),
        corner_fid=np.asarray(cf, dtype=int), corner_trial=np.zeros(len(cw), dtype=int),
        occluded=np.array([r.occluded for r in raw], dtype=bool))
    W = np.asarray(W, dtype=float).reshape(-1, 3)
    cam = view.camera
    table = geometry.camera_table(cam)
    nominal = np.array([[table[k] for k in geometry.CAMERA_ROW]], dtype=float)
    uv, _ = project_trials(W, np.asarray(view.R_cw, float)[None], np.asarray(view.t_cw, float)[None], nominal,
                           np.array([table["limit"]]))  # invalid vertices at 0: kept
    mx, my = CULL * cam.width, CULL * cam.height
    outside = np.zeros(template.n_strokes, dtype=bool)
    for cond in (uv[:, 0] < -mx, uv[:, 0] > cam.width + mx, uv[:, 1] < -my, uv[:, 1] > cam.height + my):
        all_far = np.logical_and.reduceat(cond, template.start[:-1]) if len(W) else np.zeros(0, bool)
        outside |= all_far & (template.counts > 0)
    far = np.repeat(outside, template.counts)
    return template.take(~outside), W[~far], np.asarray(cw, dtype=float).reshape(-1, 3)


def trial_cameras(rig: dict, pose: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every trial's camera for one side at one pose: R_cw (T, 3, 3), t_cw (T, 3), intrinsics (T, 18) as
    geometry.CAMERA_ROW, and the lens limit (T,) (`geometry.lens_limit`)."""
    p = rig["params"]
    robots = rig.get("robots")  # each trial's robot pose (a jittered sync: motion.jittered_robots), or None
    R_wr, t_wr = geometry.world_from_robot(pose) if robots is None else robots
    R_wr = R_wr[None] if robots is None else R_wr
    R_wc = (R_wr[:, :, :, None] * rig["rotation"][:, None, :, :]).sum(axis=2)  # row by row: no BLAS
    t_wc = (rig["position"][:, None, :] * R_wr).sum(axis=2) + t_wr
    R_cw = np.ascontiguousarray(np.transpose(R_wc, (0, 2, 1)))
    t_cw = -(R_cw * t_wc[:, None, :]).sum(axis=2)
    if "cams" not in rig:  # the same at every pose: once a batch
        cam = rig["camera"]
        model = geometry.MODELS.index(cam.distortion)
        cams = rig["cams"] = np.column_stack([*(p[k] for k in geometry.CAMERA_KEYS),
                                              np.full(len(p["f"]), model)]).astype(float)
        if cam.distortion == "radtan" and not any(np.any(p[k]) for k in ("k3", "k4", "k5", "k6")):
            rig["folds"] = np.broadcast_to(geometry.fold_radius(p["k1"], p["k2"]), len(cams)).astype(float)
        else:
            lens = geometry.CAMERA_KEYS[5:]
            rig["folds"] = np.array([geometry.lens_limit(cam, **{k: float(p[k][i]) for k in lens})
                                     for i in range(len(cams))])
    return R_cw, t_cw, rig["cams"], rig["folds"]


def project_trials(X: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray, cams: np.ndarray, folds: np.ndarray,
                   rolling: tuple | None = None):
    """World points X (N, 3) seen by every trial's camera (rows of geometry.CAMERA_ROW, lens limits folds):
    pixels (T * N, 2) trial-major and whether each is valid (imaged by the near rule); invalid ones are 0.
    `rolling`: the view's rolling shutter (View.rolling), each point imaged from the camera's pose at its row's
    time (`motion.rolling_pixels`; valid as imaged at the camera's time 0).

    The arithmetic is the kernel's, term by term, without gathering a matrix per vertex."""
    def cam(X, i):
        return R_cw[:, i, 0, None] * X[..., 0] + R_cw[:, i, 1, None] * X[..., 1] \
            + R_cw[:, i, 2, None] * X[..., 2] + t_cw[:, i, None]

    P = np.stack([cam(X[None], 0), cam(X[None], 1), cam(X[None], 2)], axis=-1)
    g = {k: cams[:, i, None] for i, k in enumerate(geometry.CAMERA_ROW)}
    ok = geometry.visible(P, g["model"], folds[:, None])
    with np.errstate(over="ignore", invalid="ignore"):  # a huge k1 > 0 (no fold): pixels beyond any image
        if rolling is None:
            uv = geometry.project(np.where(ok[..., None], P, np.array([0.0, 0.0, 1.0])), g)
        else:
            from wiredsl.engine import motion

            def pixels(Xm):  # a point the moved camera does not image is not finite: invalid, as the kernel's
                Pm = np.stack([cam(Xm, 0), cam(Xm, 1), cam(Xm, 2)], axis=-1)
                seen = ok & geometry.visible(Pm, g["model"], folds[:, None])
                uv = geometry.project(np.where(seen[..., None], Pm, np.array([0.0, 0.0, 1.0])), g)
                return np.where(seen[..., None] | ~ok[..., None], uv, np.nan)

            uv = motion.rolling_pixels(np.broadcast_to(X[None], P.shape), pixels, *rolling)
    ok &= np.isfinite(uv).all(axis=-1)  # checked here: what overflowed is invalid, like a folded point
    uv = np.where(ok[..., None], uv, 0.0)
    return uv.reshape(-1, 2), ok.ravel()


def robot_pose(view: View, pose: tuple) -> tuple:
    """The robot's pose at the view's camera's own time (a stereo pair's sync, engine/motion.py): `pose`, the
    path pose's, unless the robot moved."""
    return pose if view.robot is None else view.robot


def trial_rolling(view: View, rig: dict) -> tuple | None:
    """The view's rolling shutter (View.rolling) for a batch's trials: with a jittered sync, each trial's robot
    origin (T, 1, 3) at its own offset (`trial_cameras`' robots)."""
    if view.rolling is None or rig.get("robots") is None:
        return view.rolling
    return (*view.rolling[:2], rig["robots"][1][:, None, :], *view.rolling[3:])


def reproject(view: View, world: World, rig: dict, pose: tuple, side: str, template: tuple | None = None):
    """Every trial's view under its perturbed camera, at once: the ideal view's strokes before image
    clipping (their world points) projected with per-trial parameters, then cut to the image.

    The strokes keep the ideal view's sampling and silhouette generators; vertices a perturbation takes
    behind the near plane or past the fold radius are cut away. Returns the ImageSet and
    a function giving trial k's View (its camera and pose) for the dump.
    """
    rep, ok, view_of = projected(view, world, rig, pose, side, template)
    cam = rig["camera"]
    return cut_to_image(rep, ok, cam.width, cam.height), view_of


def projected(view: View, world: World, rig: dict, pose: tuple, side: str, template: tuple | None = None):
    """`reproject` before its cuts: every trial's strokes projected (ImageSet), whether each vertex is imaged (N,),
    and the trials' views; the corners are already those within the image."""
    template, W, CW = template if template is not None else raw_template(view, world)
    R_cw, t_cw, cams, folds = trial_cameras(rig, robot_pose(view, pose))
    T = len(cams)
    rolling = trial_rolling(view, rig)
    uv, ok = project_trials(W, R_cw, t_cw, cams, folds, rolling)
    cam = rig["camera"]
    cuv, cok = project_trials(CW, R_cw, t_cw, cams, folds, rolling)
    cok &= (cuv[:, 0] >= 0) & (cuv[:, 0] <= cam.width) & (cuv[:, 1] >= 0) & (cuv[:, 1] <= cam.height)
    rep = im.replace(template.repeat_trials(T), pts=uv, corners=cuv).take_corners(cok)
    return rep, ok, view_maker(rig, R_cw, t_cw, side)


def cut_to_image(rep: im.ImageSet, ok: np.ndarray, width, height) -> im.ImageSet:
    """Projected strokes cut where a vertex is not imaged (`ok` False) and to the image [0, width] x [0, height]
    (numbers, or arrays by batch index when the set packs views of cameras of several sizes).

    A vertex the perturbation takes behind the near plane or past the fold (a stroke cut there in the ideal view)
    is cut away with its neighbours' span, as the ideal path cuts in 3D."""
    with np.errstate(over="ignore", invalid="ignore"):  # as the kernel: a huge distortion's far vertices measure
        rep = im.keep_vertex_runs(rep, ok)  # inf and are cut away, never reach the image
        if np.ndim(width):  # each vertex's image size
            width, height = (np.repeat(np.asarray(a)[rep.trial], rep.counts) for a in (width, height))
        return im.clip_rect(rep, width, height)


def view_maker(rig: dict, R_cw: np.ndarray, t_cw: np.ndarray, side: str) -> TrialViews:
    """Every trial's View (its perturbed camera and pose) for the dump."""
    return TrialViews(rig, R_cw, t_cw, side)


class TrialViews:
    """The perturbed cameras and poses of a batch's trials for one side: trial k's View by `views(k)`, and all
    of them as arrays (`cameras`, `poses`) for the npz writer, which needs no model a trial."""

    def __init__(self, rig: dict, R_cw: np.ndarray, t_cw: np.ndarray, side: str):
        self.rig, self.R_cw, self.t_cw, self.side = rig, R_cw, t_cw, side
        self.params, self.camera = rig["params"], rig["camera"]

    def __call__(self, k: int) -> View:
        cam = self.camera
        fields = {key: float(self.params[key][k]) for key in self.params}
        return View(cam.model_copy(update={**fields, "name": f"{cam.name}:{self.side}"}), self.R_cw[k], self.t_cw[k])

    def cameras(self, columns: Sequence[str], value: Callable) -> np.ndarray:
        """(T, len(columns)) float64: each trial's camera parameter of each column; an unperturbed one is
        `value(camera, column)` repeated. The same at every pose: made once a batch and side."""
        key = ("cameras", tuple(columns), value)
        if key not in self.rig:
            T = len(self.R_cw)
            self.rig[key] = np.column_stack([np.broadcast_to(np.asarray(self.params[c], dtype=np.float64), (T,))
                                             if c in self.params else np.full(T, float(value(self.camera, c)))
                                             for c in columns])
        return self.rig[key]

    def poses(self) -> np.ndarray:
        """(T, 12) float64: each trial's R_cw (row-major) and t_cw."""
        return np.concatenate([self.R_cw.reshape(-1, 9), self.t_cw.reshape(-1, 3)], axis=1)
