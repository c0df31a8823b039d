"""Monte-Carlo trials: a pipeline's stages applied to the projected features, batch by batch.

Only the stages the chosen pipeline lists run, and a stage whose parameters
change nothing is skipped. Work that only an absent stage needs is never done:
the calibration matrix is decomposed only for `calibration_error`, epipoles are
computed only for `stereo_mismatch`, the right camera is projected only when
asked for. `Run.trace` counts what ran, for tests and for the manifest.

Trials are packed along the stroke axis of an ImageSet, so every stage works on
a whole batch of trials at once. Without calibration error the ideal projection
is shared by all trials; with it, each trial projects its own perturbed rig.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from wiredsl.effects import REGISTRY
from wiredsl.effects import calibration_error as calib
from wiredsl.effects.base import Context, Stats
from wiredsl.engine import geometry
from wiredsl.engine import imageset as im
from wiredsl.engine.simulate import (
    ImageFeature,
    Options,
    PoseResult,
    View,
    require_buildable,
    simulate,
    visibility_masks,
)
from wiredsl.engine.world import World
from wiredsl.scene import Scene

BATCH = 256  # trials per batch: bounds memory whatever the number of trials


@dataclass
class Run:
    scene: Scene
    world: World
    stages: list  # [(effect class, params)] that will run, in order
    seed: int
    options: Options
    trace: Counter = field(default_factory=Counter)
    stats: Stats = field(default_factory=Stats)
    warnings: list[str] = field(default_factory=list)
    _sampler: calib.Sampler | None = None
    _ideal: list[PoseResult] | None = None
    _epipoles: dict = field(default_factory=dict)
    _visible: tuple | None = None
    exact_calibration: bool = False  # project each trial's perturbed rig from scratch (slow reference)

    @classmethod
    def create(cls, scene: Scene, world: World, pipeline, seed: int, options: Options) -> Run:
        require_buildable(scene)
        stages = []
        for st in (pipeline.stages if pipeline is not None else []):
            effect = REGISTRY[st.effect]
            if not effect.is_identity(st.params):
                stages.append((effect, st.params))
        return cls(scene, world, stages, seed, options)

    @property
    def calibration(self):
        return next(((e, p) for e, p in self.stages if e.name == "calibration_error"), None)

    @property
    def image_stages(self):
        return [(e, p) for e, p in self.stages if e.name != "calibration_error"]

    def sampler(self) -> calib.Sampler | None:
        found = self.calibration
        if found is None or self.scene.rig.calibration is None:
            return None
        if self._sampler is None:
            self.trace["decompose"] += 1
            c = self.scene.rig.calibration
            self._sampler = calib.sampler(found[1], c.kind, c.matrix, c.order)
            if self._sampler.unconstrained:
                self.warnings.append("calibration leaves unconstrained directions (no perturbation there), led by: "
                                     + ", ".join(self._sampler.unconstrained))
            self.stats.samples["calibration_error.covariance"] = [self._sampler.covariance]
        return self._sampler

    def project(self, scene: Scene) -> list[PoseResult]:
        self.trace["project"] += 1
        self.trace["project:right"] += self.options.right
        if self._visible is None:  # view-points see from the nominal rig: once per run
            self._visible = visibility_masks(self.scene, self.world, self.options)
        return simulate(scene, self.options, self.world, self._visible)

    def ideal(self) -> list[PoseResult]:
        if self._ideal is None:
            self._ideal = self.project(self.scene)
        return self._ideal

    def epipole(self, pose: tuple, side: str) -> np.ndarray:
        """This camera's epipole (homogeneous pixels): the image of the other camera's centre."""
        key = (pose, side)
        if key not in self._epipoles:
            self.trace["epipole"] += 1
            rig = self.scene.rig
            me, other = (rig.left, rig.right) if side == "left" else (rig.right, rig.left)
            cam = self.scene.camera(me.camera)
            R_cw, t_cw = geometry.camera_from_world(pose, me.rotation, me.position)
            R_ow, t_ow = geometry.camera_from_world(pose, other.rotation, other.position)
            centre = -R_ow.T @ t_ow
            X = R_cw @ centre + t_cw
            K = np.array([[cam.f * cam.ax, 0, cam.cx], [0, cam.f * cam.ay, cam.cy], [0, 0, 1.0]])
            e = K @ X
            self._epipoles[key] = e / np.linalg.norm(e)
        return self._epipoles[key]

    def batches(self, trials: list[int]) -> Iterator[tuple[list[int], list[tuple[PoseResult, dict]]]]:
        """For each batch of trials: per pose, the ideal result and {side: disturbed ImageSet of the batch}."""
        for lo in range(0, len(trials), BATCH):
            batch = trials[lo:lo + BATCH]
            yield batch, self._batch(batch)

    def _batch(self, batch: list[int]):
        sampler = self.sampler()
        per_trial = rigs = None
        base = self.ideal()
        if sampler is not None:
            order = self.scene.rig.calibration.order
            phis = np.array([calib.draw(sampler, t, self.seed) for t in batch])
            self.stats.samples["calibration_error"].extend(phis)
            if self.exact_calibration:  # each trial's rig projected from scratch: the reference
                per_trial = [self.project(calib.perturb(self.scene, phi, order)) for phi in phis]
                base = per_trial[0]
            else:
                self.trace["reproject"] += 1
                rigs = calib.perturbed_rigs(self.scene, phis, order)
        out = []
        for j, result in enumerate(base):
            disturbed = {}
            views = {"left": None, "right": None}
            for side in ("left", "right"):
                if getattr(result, side) is None:
                    continue
                if per_trial is not None:
                    sets = concat_trials([to_imageset(getattr(r[j], side), self.world) for r in per_trial])
                    views[side] = [getattr(r[j], side) for r in per_trial]
                elif rigs is not None:
                    sets, views[side] = reproject(getattr(result, side), self.world, rigs[side], result.pose, side)
                else:
                    sets = to_imageset(getattr(result, side), self.world).repeat_trials(len(batch))
                ctx = Context(pose=result.index, side=side, trials=np.array(batch), seed=self.seed,
                              stats=self.stats, epipole=lambda r=result, s=side: self.epipole(r.pose, s))
                for effect, params in self.image_stages:
                    self.trace[effect.name] += 1
                    sets = effect.apply(params, sets, ctx)
                disturbed[side] = sets
            out.append((result, disturbed, views))
        return out

    def manifest(self) -> dict:
        return {
            "stages": [{"effect": e.name, "params": p.model_dump(), "measured": e.report(p, self.stats)}
                       for e, p in self.stages],
            "ran": dict(sorted(self.trace.items())),
            "warnings": self.warnings,
        }


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


def reproject(view: View, world: World, rig: dict, pose: tuple, side: str):
    """Every trial's view under its perturbed camera, at once: the ideal view's strokes before image
    clipping (their world points) projected with per-trial parameters, then cut to the image.

    The strokes keep the ideal view's sampling and silhouette generators; vertices a perturbation takes
    behind the near plane or past the fold radius are cut away. Returns the ImageSet and
    a function giving trial k's View (its camera and pose) for the dump.
    """
    p = rig["params"]
    T = len(p["f"])
    R_wr = geometry.rot_z(pose[2])
    R_wc = R_wr[None] @ rig["rotation"]
    t_wc = rig["position"] @ R_wr.T + np.array([pose[0], pose[1], 0.0])
    R_cw = np.transpose(R_wc, (0, 2, 1))
    t_cw = -np.einsum("tij,tj->ti", R_cw, t_wc)
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
    rep = template.repeat_trials(T)
    folds = np.array([geometry.fold_radius(k1, k2) for k1, k2 in zip(p["k1"], p["k2"], strict=True)])

    def project(points, trial):
        P = np.einsum("nij,nj->ni", R_cw[trial], points) + t_cw[trial]
        ok = P[:, 2] > geometry.NEAR
        xy = P[:, :2] / np.where(ok, P[:, 2], 1.0)[:, None]
        ok &= np.hypot(xy[:, 0], xy[:, 1]) < folds[trial]
        g = {k: p[k][trial] for k in p}
        uv = geometry.plane_to_pixels(geometry.distort(xy, g["k1"], g["k2"], g["p1"], g["p2"]),
                                      g["f"], g["ax"], g["ay"], g["cx"], g["cy"])
        return uv, ok

    uv, ok = project(np.tile(W, (T, 1)), np.repeat(rep.trial, rep.counts))
    # a vertex the perturbation takes behind the near plane or past the fold (a stroke cut there in the
    # ideal view) is cut away with its neighbours' span, as the ideal path cuts in 3D
    rep = im.keep_vertex_runs(im.replace(rep, pts=np.where(ok[:, None], uv, 0.0)), ok)
    cam = rig["camera"]
    rep = im.clip_rect(rep, cam.width, cam.height)
    cuv, cok = project(np.tile(cw, (T, 1)), rep.corner_trial)
    cok &= (cuv[:, 0] >= 0) & (cuv[:, 0] <= cam.width) & (cuv[:, 1] >= 0) & (cuv[:, 1] <= cam.height)
    rep = im.replace(rep, corners=cuv).take_corners(cok)

    def view_of(k: int) -> View:
        fields = {key: float(p[key][k]) for key in p}
        return View(cam.model_copy(update={**fields, "name": f"{cam.name}:{side}"}), R_cw[k], t_cw[k])

    return rep, view_of
