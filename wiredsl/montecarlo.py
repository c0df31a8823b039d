"""Monte-Carlo trials: a pipeline's stages applied to the projected features, batch by batch.

Only the stages the chosen pipeline lists run, and a stage whose parameters
change nothing is skipped. Work that only an absent stage needs is never done:
the calibration matrix is decomposed only for `calibration_error`, epipoles are
computed only for `stereo_mismatch`, the right camera is projected only when
asked for. `Run.trace` counts what ran, for tests and for the manifest.

Trials are packed along the stroke axis of an ImageSet, so every stage works on
a whole batch of trials at once. Without calibration error the ideal projection
is shared by all trials; with it, each trial projects its own perturbed rig
(engine/trials.py). Above the effects it runs (and their plug-ins' guards), below
the faces that set a run up (run.py).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from wiredsl import check_stop
from wiredsl.diagnostics import Diagnostic, WiredslError
from wiredsl.effects import BUILTIN, REGISTRY
from wiredsl.effects import calibration_error as calib
from wiredsl.effects.base import CAMERA_INDEX, Context, PackedContext, Stats, stream_key
from wiredsl.engine import geometry
from wiredsl.engine import imageset as im
from wiredsl.engine.simulate import (
    Options,
    PoseResult,
    require_buildable,
    simulate,
    visibility_masks,
)
from wiredsl.engine.trials import (
    concat_trials,
    cut_to_image,
    projected,
    raw_template,
    reproject,
    robot_pose,
    to_imageset,
    trial_cameras,
    trial_rolling,
    view_maker,
)
from wiredsl.engine.world import World
from wiredsl.plugins import params_dump, params_of
from wiredsl.scene import Scene

BATCH = 256  # trials per batch at most: bounds memory whatever the number of trials
BATCH_BYTES = 32 * 2**20  # what one batch may hold (kernel output and the writer's copies), about
# bytes a trial holds per vertex and per stroke of its views, measured (peak RSS of 1,000 `paper` trials of the
# lab and of benchmarks/big_scene.py's 10x lab at several batch sizes): the writer's rows weigh on the strokes
VERTEX_BYTES, STROKE_BYTES = 16, 512
# vertex-trials (trials times a trial's vertices, `Run.trial_size`) from which the compiled kernel pays for loading
# numba and the cached kernel (some 0.15 s of CPU more than the numpy path's start, with the console entry's exit
# without teardown) against the numpy path: where `build --format npz` of the two cross in the lab, between 50 and
# 75 trials of its 2,675 vertices (best of 3 each, 2026-11-23)
KERNEL_PAYS = 200_000


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
    _templates: dict = field(default_factory=dict)  # per (pose, side, raw?): the view's packed strokes, once a run
    _kernel_rows: dict = field(default_factory=dict)  # the kernel's constant inputs: stage rows, templates' meta
    _visible: tuple | None = None
    exact_calibration: bool = False  # project each trial's perturbed rig from scratch (slow reference)
    point: int | None = None  # a study's design point: one more component of every draw's key
    design_point: int | None = None  # the study's design point this run is, for messages (None: as `point`)
    engine: str = "auto"  # "kernel" (compiled, numba), "numpy" (the readable reference), "auto": kernel if installed
    pack: bool = True  # numpy path, built-in stages: all views of a batch in one set (False: a view at a time)

    @classmethod
    def create(cls, scene: Scene, world: World, pipeline, seed: int, options: Options,
               point: int | None = None, need_path: bool = True) -> Run:
        require_buildable(scene, need_path)
        stages = []
        listed = pipeline.stages if pipeline is not None else []
        for g, st in enumerate(listed):
            effect = REGISTRY[st.effect]
            params = params_of("effect", effect, REGISTRY, st.params)
            if effect.name in BUILTIN:
                identity = effect.is_identity(params)
            else:  # an installed plug-in's answer: guarded, and it must be a plain truth value
                identity = plugin_call(effect, "is_identity()", effect.is_identity, params,
                                       where=f"stage {g + 1} of {len(listed)}")
                if not isinstance(identity, (bool, np.bool_)):
                    from wiredsl.plugins import failure

                    raise failure("effect", effect.name, REGISTRY, f"is_identity() returned a {type(identity).__name__}"
                                  ", not True or False", f"stage {g + 1} of {len(listed)}")
            if not identity:
                stages.append((effect, params))
        return cls(scene, world, stages, seed, options, point=point)

    def share_projection(self, base: Run) -> None:
        """Take `base`'s ideal projection, visibility, epipoles and views' templates (a run of the same scene and
        options): no stage changes them. An optimisation only: what `base` has not computed is computed when
        needed (the templates into `base`'s table, for the next run that shares it)."""
        for name in ("_ideal", "_visible"):
            if getattr(base, name) is not None:
                setattr(self, name, getattr(base, name))
        self._epipoles = base._epipoles
        if self._ideal is base._ideal:  # templates are made from the ideal views
            self._templates = base._templates

    @property
    def path_s(self) -> np.ndarray | None:
        """Distance along the scene's path at each pose (m), for the stages whose draws persist along it."""
        if "path_s" not in self._kernel_rows:
            from wiredsl.effects.variation import path_coordinate

            self._kernel_rows["path_s"] = path_coordinate(self.scene.path)
        return self._kernel_rows["path_s"]

    @property
    def calibration(self):
        return next(((e, p) for e, p in self.stages if e.name == "calibration_error"), None)

    @property
    def image_stages(self):
        return [(e, p) for e, p in self.stages if e.name != "calibration_error"]

    def where_point(self) -> int | None:
        """The design point messages name: the study's point, whether or not its draws are keyed by it."""
        return self.design_point if self.design_point is not None else self.point

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
            self.stats.samples["calibration_error.order"] = [c.order]
        return self._sampler

    def project(self, scene: Scene) -> list[PoseResult]:
        self.trace["project"] += 1
        self.trace["project:right"] += self.options.right
        if self._visible is None:  # view-points see from the nominal rig: once per run
            self._visible = visibility_masks(self.scene, self.world, self.options)
        return simulate(scene, self.options, self.world, self._visible)

    def moved_views(self):
        """Context.moved of this run: {pose index: ideal PoseResult} as the robot sees tau s after each pose,
        computed once per tau (effects.motion_blur); None when no camera exposes over time."""
        from wiredsl.effects import motion_blur

        if not motion_blur.exposed(self.scene):
            return None
        cache = self.__dict__.setdefault("_moved", {})

        def at(tau: float) -> dict:
            if tau not in cache:
                cache[tau] = {r.index: r for r in (self.ideal() if tau == 0 else
                                                   self.project(motion_blur.scene_at(self.scene, tau)))}
            return cache[tau]

        return at

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

    def batches(self, trials: Sequence[int], size: int | None = None
                ) -> Iterator[tuple[Sequence[int], list[tuple[PoseResult, dict]]]]:
        """For each batch of trials: per pose, the ideal result and {side: disturbed ImageSet of the batch}.

        `trials` is any sequence (a range for a run: nothing is built for the trials not yet reached), and
        each trial's output is the same whichever trials share its batch. `size`: trials a batch (default:
        `batch_size()`, sized to the scene).
        """
        size = size or self.batch_size()
        for lo in range(0, len(trials), size):
            check_stop()  # a SIGINT or SIGTERM dropped by the compiled code it landed in stops the run here
            batch = trials[lo:lo + size]
            yield batch, self._batch(batch)

    def batch_size(self) -> int:
        """Trials a batch: the largest power of two up to BATCH whose trials' strokes fit in BATCH_BYTES, so
        that memory stays bounded in a scene with many features in view (one trial at least)."""
        vertices, strokes = self.trial_size()
        fits = BATCH_BYTES // max(VERTEX_BYTES * vertices + STROKE_BYTES * strokes, 1)
        return int(min(BATCH, 2 ** int(np.log2(fits)) if fits >= 1 else 1))

    def trial_size(self) -> tuple[int, int]:
        """The vertices and strokes of a trial's views before the stages (the templates the stages start from)."""
        raw = self.sampler() is not None and not self.exact_calibration
        vertices = strokes = 0
        for result in self.ideal():
            for side in ("left", "right"):
                if getattr(result, side) is not None:
                    template = self.template(result, side, raw=raw)[0]
                    vertices, strokes = vertices + len(template.pts), strokes + template.n_strokes
        return vertices, strokes

    def kernel_pays(self, trials: int) -> bool:
        """Whether the compiled kernel would run `trials` trials, and pays for loading numba: KERNEL_PAYS
        vertex-trials at least (an `auto` engine's choice for a run of known size)."""
        return self.uses_kernel() and trials * self.trial_size()[0] >= KERNEL_PAYS

    def jittered(self) -> bool:
        """Whether the rig's sync has a jitter the trials draw (on a path with times): then every trial's views
        are re-projected, the right camera's at the trial's own offset."""
        rig, path = self.scene.rig, self.scene.path
        return rig is not None and rig.jitter > 0 and path is not None and path.times is not None

    def calibration_draws(self, batch: Sequence[int]) -> np.ndarray:
        """The batch's calibration perturbations (T, m), each checked: a draw that leaves a camera without a
        positive pixel scale (f ax, f ay), or one over calib.SCALE_LIMIT times the nominal, or anything not
        finite, is refused and redrawn (the next attempt of the same key), and counted."""
        return self.calibration_rigs(batch)[0]

    def calibration_rigs(self, batch: Sequence[int]) -> tuple[np.ndarray, dict]:
        """`calibration_draws` and the batch's perturbed rigs (`calib.perturbed_rigs`), built once a batch: the
        rigs that checked the draws are the rigs the batch projects with (a redrawn trial's rows replaced)."""
        sampler = self.sampler()
        order = self.scene.rig.calibration.order
        trials = np.asarray(batch, dtype=np.int64)
        phis = calib.draws(sampler, trials, self.seed, self.point)
        rigs = calib.checked_rigs(self.scene, phis, order)
        bad = ~calib.sensible(self.scene, phis, order, rigs)
        refused = int(bad.sum())
        for attempt in range(1, calib.ATTEMPTS):
            if not bad.any():
                break
            redo = np.flatnonzero(bad)
            phis[redo] = calib.draws(sampler, trials[redo], self.seed, self.point, attempt)
            again = calib.checked_rigs(self.scene, phis[redo], order)
            calib.splice_rigs(rigs, redo, again)
            bad[redo] = ~calib.sensible(self.scene, phis[redo], order, again)
            refused += int(bad.sum())
        if bad.any():
            raise WiredslError([Diagnostic(
                "error", "E161", f"calibration_error: {calib.ATTEMPTS} draws in a row for trial {int(trials[bad][0])} "
                "give a camera a pixel scale (f ax, f ay) that is not positive or over "
                f"{calib.SCALE_LIMIT:g} times the nominal: the calibration uncertainty is too large for the cameras",
                None)])
        if refused and not any(w.startswith("calibration draws refused") for w in self.warnings):
            self.warnings.append("calibration draws refused and redrawn (a camera's pixel scale not positive or "
                                 "implausibly large): counted in the manifest as refused_draws")
        calib.CalibrationError.record(self.stats, phis, refused)
        return phis, rigs

    def compiled_stages(self) -> list:
        """The image stages the compiled kernel runs (when `uses_kernel`): the leading ones that have a kernel;
        from the first that has none (an installed plug-in's, say) on, the stages run on numpy, on the kernel's
        output (the same keyed draws: the engines agree to rounding)."""
        return self.image_stages[:kernel_prefix([e for e, _ in self.image_stages])]

    def uses_kernel(self) -> bool:
        """Whether batches run in the compiled kernel: never for the from-scratch calibration reference, nor when
        a stage has no compiled kernel (an installed plug-in's, say): then the whole pipeline runs on numpy."""
        return not self.exact_calibration and kernel_runs([e for e, _ in self.stages], self.engine)

    def observe(self, result: PoseResult, trials: Sequence[int]) -> tuple[PoseResult, dict, dict]:
        """One ideal view (a path pose, or any pose projected with `Run.project_pose`) through the stages,
        for the given trials: (result, {side: disturbed ImageSet}, views), as `batches` gives each pose.

        The draws are keyed by `result.index`, so a path pose gives exactly what `batches` gives it; nothing is
        kept for a result that is not one of the run's ideal poses (a closed loop's poses do not pile up)."""
        if self.exact_calibration:
            raise ValueError("observe() re-projects the ideal strokes; exact_calibration projects whole runs")
        keep = self.scene.path is not None and any(r is result for r in self.ideal())
        return self._batch(trials, [result], keep)[0]

    def _batch(self, batch: Sequence[int], results: list[PoseResult] | None = None, keep: bool = True):
        sampler = self.sampler()
        per_trial = rigs = None
        base = nominal = self.ideal() if results is None else results
        kernel = self.uses_kernel()
        compiled = self.compiled_stages() if kernel else []
        keys = self._view_keys(batch, base, compiled) if kernel else None
        if sampler is not None:
            order = self.scene.rig.calibration.order
            phis, checked = self.calibration_rigs(batch)
            if self.exact_calibration:  # each trial's rig projected from scratch: the reference
                per_trial = [self.project(calib.perturb(self.scene, phi, order)) for phi in phis]
                base = per_trial[0]
            else:
                self.trace["reproject"] += 1
                rigs = checked
        jitter = self.jittered() and per_trial is None
        if jitter and rigs is None:  # the nominal rig, every trial re-projected at its own offset
            rigs = calib.perturbed_rigs(self.scene, np.zeros((len(batch), 0)), [])
        out = []
        # the exposures' ends are known for the path's own poses (a pose projected with `project_pose` has none)
        ideal = self.ideal() if self.scene.path is not None else []
        moved = self.moved_views() if all(any(r is p for p in ideal) for r in nominal) else None
        # the numpy path with built-in stages only: every view's trials packed in one set, each stage run once
        packed = [] if self.pack and not kernel and all(e.name in BUILTIN for e, _ in self.image_stages) else None
        for j, result in enumerate(base):
            disturbed = {}
            views = {"left": None, "right": None}
            if jitter:  # the right camera's robot pose at each trial's drawn offset (a path pose's only)
                from wiredsl.engine import motion

                on_path = 0 <= result.index < len(self.scene.path.poses) and result.pose == self.scene.path.pose(
                    result.index)
                rigs["right"]["robots"] = motion.jittered_robots(self.scene, result.index, batch, self.seed,
                                                                 self.point) if on_path else None
            for side in ("left", "right"):
                if getattr(result, side) is None:
                    continue
                if kernel:  # the leading stages that have a compiled kernel, in it; the rest below, on numpy
                    for effect, _ in compiled:
                        self.trace[effect.name] += 1
                    sets, views[side] = self._kernel_view(result, side, keys[j, CAMERA_INDEX[side]],
                                                          rigs[side] if rigs else None, keep)
                elif per_trial is not None:
                    sets = concat_trials([to_imageset(getattr(r[j], side), self.world) for r in per_trial])
                    views[side] = [getattr(r[j], side) for r in per_trial]
                elif rigs is not None:
                    template = self.template(result, side, raw=True, keep=keep)
                    if packed is not None:  # cut to the image below, with the other views
                        sets, ok, views[side] = projected(getattr(result, side), self.world, rigs[side], result.pose,
                                                          side, template)
                        packed.append((result, side, sets, disturbed, ok, rigs[side]["camera"],
                                       getattr(nominal[j], side).camera))
                        continue
                    sets, views[side] = reproject(getattr(result, side), self.world, rigs[side], result.pose, side,
                                                  template)
                else:
                    sets = self.template(result, side, raw=False, keep=keep)[0].repeat_trials(len(batch))
                if packed is not None:
                    packed.append((result, side, sets, disturbed, None, None, getattr(nominal[j], side).camera))
                    continue
                ctx = Context(pose=result.index, side=side, trials=np.asarray(batch), seed=self.seed,
                              stats=self.stats, epipole=lambda r=result, s=side: self.epipole(r.pose, s),
                              point=self.point, camera=getattr(nominal[j], side).camera,  # as the fast path's
                              path_s=self.path_s, moved=moved)
                for effect, params in self.image_stages[len(compiled):]:
                    self.trace[effect.name] += 1
                    if effect.name in BUILTIN:
                        sets = effect.apply(params, sets, ctx)
                    else:  # an installed plug-in: what it raises or returns is checked, and blamed on its package
                        sets = plugin_apply(effect, params, sets, ctx, len(self.world.feature_ids),
                                            self._stage_of(effect), self.where_point())
                disturbed[side] = sets
            out.append((result, disturbed, views))
        if packed:
            self._packed_stages(batch, packed)
        return out

    def _packed_stages(self, batch: Sequence[int], views: list) -> None:
        """The image stages (built-in effects) on many views' trials at once: [(result, side, ImageSet of the
        batch, the result's dict of disturbed sets, which vertices are imaged or None, the perturbed camera or
        None, the view's nominal camera)], each set put in its dict. With a camera, the set is the re-projection
        before its cuts (`projected`), cut here (`cut_to_image`). The same draws, outputs and statistics as one
        view at a time (`PackedContext`), with a stage's Python paid once, not once a view."""
        T = len(batch)
        for effect, _ in self.image_stages:
            self.trace[effect.name] += len(views)
        ideal = self.ideal() if self.scene.path is not None else []
        moved = self.moved_views() if all(any(v[0] is p for p in ideal) for v in views) else None
        poses = np.array([v[0].index for v in views], dtype=np.int64)
        cameras = np.array([CAMERA_INDEX[v[1]] for v in views], dtype=np.int64)
        epipoles = []

        def view_epipoles():  # as each view's stage would ask for it: once a view, in order
            if not epipoles:
                epipoles.append(np.array([self.epipole(v[0].pose, v[1]) for v in views]))
            return epipoles[0]

        ctx = PackedContext(pose=-1, side="", trials=np.tile(np.asarray(batch, dtype=np.int64), len(views)),
                            seed=self.seed, stats=self.stats, point=self.point, per_view=T,
                            poses=np.repeat(poses, T), cameras=np.repeat(cameras, T), view_epipoles=view_epipoles,
                            cameras_of_views=[v[6] for v in views], path_s=self.path_s, moved=moved)
        sets = im.concat([v[2] for v in views], T)
        if views[0][4] is not None:  # re-projected: cut to each view's image
            sizes = {(v[5].width, v[5].height) for v in views}
            width, height = sizes.pop() if len(sizes) == 1 else \
                (np.repeat([float(v[5].width) for v in views], T), np.repeat([float(v[5].height) for v in views], T))
            sets = cut_to_image(sets, np.concatenate([v[4] for v in views]), width, height)
        for effect, params in self.image_stages:
            sets = effect.apply(params, sets, ctx)
        for (_, side, _, disturbed, *_), s in zip(views, im.split(sets, len(views), T), strict=True):
            disturbed[side] = s

    def _stage_of(self, effect) -> str:
        """'stage G of N' for an effect of the pipeline (as the scene lists its stages that run)."""
        g = next(i for i, (e, _) in enumerate(self.stages) if e is effect)
        return f"stage {g + 1} of {len(self.stages)}"

    def template(self, result: PoseResult, side: str, raw: bool, keep: bool = True
                 ) -> tuple[im.ImageSet, np.ndarray, np.ndarray]:
        """One view's strokes as a trial's ImageSet: raw (before clipping, with world points, for
        re-projection) or ideal; built once a run (`keep`), or each time."""
        key = (result.index, side, raw)
        if key in self._templates and keep:
            return self._templates[key]
        view = getattr(result, side)
        made = raw_template(view, self.world) if raw else \
            (to_imageset(view, self.world), np.zeros((0, 3)), np.zeros((0, 3)))
        if keep:
            self._templates[key] = made
        return made

    def _view_keys(self, batch: Sequence[int], results: list[PoseResult], stages: list) -> np.ndarray:
        """The image stages' keys for every view of `results` (pose j, camera c) and trial of the batch:
        (poses, 2, stages, trials), one stream_key call a stage (the same keys as one call a view)."""
        poses = np.array([r.index for r in results], dtype=np.int64)[:, None, None]
        cameras = np.array([CAMERA_INDEX["left"], CAMERA_INDEX["right"]])[None, :, None]
        trials = np.asarray(batch, dtype=np.int64)[None, None, :]
        keys = np.empty((len(results), 2, len(stages), len(batch)), dtype=np.uint64)
        for g, (effect, params) in enumerate(stages):
            keys[:, :, g] = stream_key(effect.name, trials, -1 if _path_keyed(effect, params) else poses,
                                       -1 if _rig_keyed(effect) else cameras, self.seed, self.point)
        return keys

    def _kernel_view(self, result: PoseResult, side: str, keys: np.ndarray, rig: dict | None, keep: bool = True):
        """One view of a batch in the compiled kernel, its keys (stages, trials) from `_view_keys`: the same
        stages and draws as the numpy path."""
        from wiredsl.engine import kernel as kn

        view = getattr(result, side)
        T = keys.shape[1]
        raw = rig is not None
        template, W, CW = self.template(result, side, raw=raw, keep=keep)
        if raw:
            R_cw, t_cw, cams, folds = trial_cameras(rig, robot_pose(view, result.pose))
            cam, view_of = rig["camera"], view_maker(rig, R_cw, t_cw, side)
        else:
            cams = np.zeros((T, len(geometry.CAMERA_ROW)))
            R_cw, t_cw, folds = np.zeros((T, 3, 3)), np.zeros((T, 3)), np.zeros(T)
            cam, view_of = view.camera, None
        if "stages" not in self._kernel_rows:  # constant a run
            self._kernel_rows["stages"] = stage_rows(self.compiled_stages(), self.path_s)
            self._kernel_rows["plugins"] = load_plugin_kernels(self.compiled_stages(), self._stage_of)
        functions, params, zero = self._kernel_rows["stages"]
        params = at_pose(self.compiled_stages(), params, result.index)
        stats = zero.copy()
        meta = self._kernel_rows.get((result.index, side, raw)) if keep else None
        if meta is None:
            meta = np.column_stack([template.fid, template.segment, template.fragment, template.kind, template.clipped,
                                    template.closed, template.occluded]).astype(np.int64).reshape(-1, 7)
            if keep:
                self._kernel_rows[(result.index, side, raw)] = meta
        stages = self.compiled_stages()
        epipole = self.epipole(result.pose, side) if any(e.kernel.epipole for e, _ in stages) else np.zeros(3)
        args = (template.pts, template.start, meta, template.corners, template.corner_fid, W, CW, R_cw, t_cw, cams,
                folds, cam.width, cam.height, raw, functions, params, keys, epipole, side == "right", stats,
                tuple(e.kernel.camera for e, _ in stages), self._camera_row(result, side, keep),
                tuple(e.kernel.workspace for e, _ in stages), trial_rolling(view, rig) if raw else None)
        plugins = self._kernel_rows["plugins"]
        if not plugins:
            pts, start, m, trial, corners, cfid, ctrial = kn.run_view(*args)
        else:  # numba's typing of a plug-in's function happens here, at the first call: its failure is the plug-in's
            trials = f"pose {result.index}, camera {side}, the batch of {T} trials"
            effect, stage = plugins[0]
            pts, start, m, trial, corners, cfid, ctrial = plugin_call(
                effect, "its compiled kernel (" + ", ".join(e.kernel.function for e, _ in plugins) + ")", kn.run_view,
                *args, where=f"{stage}, {trials}")
        for (effect, _), row in zip(stages, stats, strict=True):
            kn.record(effect.name, effect.kernel.stats, row, self.stats)
        s = im.ImageSet(pts=pts, start=start, fid=m[:, 0], segment=m[:, 1], fragment=m[:, 2], kind=m[:, 3],
                        clipped=m[:, 4].astype(bool), closed=m[:, 5].astype(bool), trial=trial, corners=corners,
                        corner_fid=cfid, corner_trial=ctrial, occluded=m[:, 6].astype(bool))
        return s, view_of

    def _camera_row(self, result: PoseResult, side: str, keep: bool) -> np.ndarray:
        """`camera_row` of an ideal view's camera, kept with the templates (shared by the runs of a study's points:
        its lens limit alone cost a tenth of a small point's batch)."""
        if not keep:
            return camera_row(getattr(result, side).camera)
        key = ("camera_row", result.index, side)
        if key not in self._templates:
            self._templates[key] = camera_row(getattr(result, side).camera)
        return self._templates[key]

    def engines(self) -> dict[str, str]:
        """Which engine ran each stage (calibration_error's draws are numpy's on both: they set the cameras)."""
        compiled = {e.name for e, _ in self.compiled_stages()} if self.uses_kernel() else set()
        return {e.name: "kernel" if e.name in compiled else "numpy" for e, _ in self.stages}

    def manifest(self) -> dict:
        return {
            "stages": [{"effect": e.name, "params": params_dump(p), "measured": self._report(e, p)}
                       for e, p in self.stages],
            "ran": dict(sorted(self.trace.items())),
            "engine": "kernel" if self.uses_kernel() else "numpy",
            "engines": self.engines(),
            "warnings": self.warnings,
        }


    def _report(self, effect, params) -> dict:
        """A stage's `report` for the manifest; an installed plug-in's guarded and checked (a dict of JSON values,
        numbers finite)."""
        if effect.name in BUILTIN:
            return effect.report(params, self.stats)
        got = plugin_call(effect, "report()", effect.report, params, self.stats, where=self._stage_of(effect))
        problem = json_problem(got, top=True)
        if problem is not None:
            from wiredsl.plugins import failure

            raise failure("effect", effect.name, REGISTRY, f"report() returned {problem}", self._stage_of(effect))
        return got


MAX_JSON_DEPTH = 8


def json_problem(value, top: bool = False, depth: int = 0) -> str | None:
    """What keeps a plug-in's value out of a JSON manifest (not a dict at the top; a key not a string; a number
    not finite; a type JSON has not), or None."""
    import math

    if top and not isinstance(value, dict):
        return f"a {type(value).__name__}, not a dict"
    if depth > MAX_JSON_DEPTH:
        return f"values nested deeper than {MAX_JSON_DEPTH}"
    if isinstance(value, dict):
        if any(not isinstance(k, str) for k in value):
            return "a dict whose keys are not all strings"
        return next((p for v in value.values() if (p := json_problem(v, depth=depth + 1)) is not None), None)
    if isinstance(value, (list, tuple)):
        return next((p for v in value if (p := json_problem(v, depth=depth + 1)) is not None), None)
    if isinstance(value, (bool, np.bool_, str, int, np.integer)) or value is None:
        return None
    if isinstance(value, (float, np.floating)):
        return None if math.isfinite(value) else f"the non-finite number {value}"
    return f"a {type(value).__name__} (not a JSON value)"


def plugin_call(effect, doing: str, fn, *args, where=None):
    """A call into an installed effect's code, through the one guard (`wiredsl.plugins.call`)."""
    from wiredsl.plugins import call

    return call("effect", effect.name, REGISTRY, doing, fn, *args, where=where)


def load_plugin_kernels(stages, stage_of) -> list:
    """Import the compiled functions of the installed effects among `stages`, each through the guard (a kernel
    module that does not import, or lacks its function, is its package's error, E181); returns [(effect, 'stage G
    of N')] of those effects."""
    import importlib

    out = []
    for effect, _ in stages:
        if effect.name in BUILTIN:
            continue
        for function in filter(None, (effect.kernel.function, effect.kernel.workspace)):
            module, _, name = function.partition(":")

            def load(module=module, name=name):
                fn = getattr(importlib.import_module(module), name)
                if not callable(fn):
                    raise TypeError(f"{module}:{name} is a {type(fn).__name__}, not a function")
                return fn

            plugin_call(effect, f"loading its kernel {function}", load, where=stage_of(effect))
        out.append((effect, stage_of(effect)))
    return out


def camera_row(cam) -> np.ndarray:
    """A camera as a compiled stage sees it (KernelStage.camera): width, height, then geometry.CAMERA_ROW."""
    table = geometry.camera_table(cam)
    return np.array([cam.width, cam.height, *(table[k] for k in geometry.CAMERA_ROW)], dtype=np.float64)


def kernel_prefix(image_effects: list) -> int:
    """How many leading image stages have a compiled kernel (those the kernel runs)."""
    return next((g for g, e in enumerate(image_effects) if e.kernel is None), len(image_effects))


def kernel_runs(effects: list, engine: str) -> bool:
    """Whether a pipeline of these effects runs (partly) in the compiled kernel under `engine`: not on "numpy",
    not without stages, not when neither its first image stage has a kernel nor it re-projects calibration draws
    (the kernel would do nothing), and under "auto" where numba is installed."""
    image = [e for e in effects if e.name != "calibration_error"]
    if engine == "numpy" or not effects or (image and not kernel_prefix(image) and len(image) == len(effects)):
        return False
    if engine == "kernel":
        return True
    import importlib.util

    return importlib.util.find_spec("numba") is not None


def stage_engines(effects: list, engine: str) -> dict[str, str]:
    """The engine each of these effects runs on (calibration_error's draws are numpy's on both)."""
    image = [e for e in effects if e.name != "calibration_error"]
    compiled = {e.name for e in image[:kernel_prefix(image)]} if kernel_runs(effects, engine) else set()
    return {e.name: "kernel" if e.name in compiled else "numpy" for e in effects}


def stage_rows(stages, path_s: np.ndarray | None = None) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    """The compiled kernel's view of image stages [(effect, params)]: their functions (KernelStage.function), a
    row of parameters each (KernelStage.params in order, zero-padded) and a zeroed statistics row each. A stage
    keyed along the path (`_path_keyed`) has its row go on with a pose slot (-1; set a view at a time by
    `at_pose`) and the path's rho table (`variation.persistence` of `path_s`, its distance at each pose)."""
    from wiredsl.effects import variation

    functions = tuple(e.kernel.function for e, _ in stages)
    rows = []
    for e, p in stages:
        row = [float(getattr(p, name)) for name in e.kernel.params]
        if _path_keyed(e, p):
            row += [-1.0, *variation.persistence(path_s, p.correlation).tolist()]
        rows.append(row)
    params = np.zeros((len(stages), max([3] + [len(r) for r in rows])))
    for g, row in enumerate(rows):
        params[g, :len(row)] = row
    return functions, params, np.zeros((len(stages), max([6] + [len(e.kernel.stats) for e, _ in stages])))


def kernel_apply(effect, params, s: im.ImageSet, ctx: Context) -> im.ImageSet:
    """One stage on any ImageSet in the compiled kernel, trial by trial: what `effect.apply` gives on the numpy
    path, with the same keyed draws (so tests run hand-made inputs through both engines)."""
    from wiredsl.engine import kernel as kn

    if effect.is_identity(params):
        return s
    if effect.kernel is None:
        raise ValueError(f"effect '{effect.name}' has no compiled kernel")
    functions, row, _ = stage_rows([(effect, params)], ctx.path_s)
    row = at_pose([(effect, params)], row, ctx.pose)
    epipole = ctx.epipole() if effect.kernel.epipole and ctx.epipole else np.zeros(3)
    parts = []
    for k, t in enumerate(np.asarray(ctx.trials, dtype=np.int64)):
        one = s.take(s.trial == k).take_corners(s.corner_trial == k)
        meta = np.column_stack([one.fid, one.segment, one.fragment, one.kind, one.clipped, one.closed,
                                one.occluded]).astype(np.int64).reshape(-1, 7)
        keys = stream_key(effect.name, np.array([t]), -1 if _path_keyed(effect, params) else ctx.pose,
                          -1 if _rig_keyed(effect) else CAMERA_INDEX[ctx.side], ctx.seed, ctx.point)
        _, _, stats = stage_rows([(effect, params)])
        z3 = np.zeros((0, 3))
        pts, start, m, _, corners, cfid, _ = kn.run_view(
            one.pts, one.start, meta, one.corners, one.corner_fid, z3, z3, np.zeros((1, 3, 3)), np.zeros((1, 3)),
            np.zeros((1, len(geometry.CAMERA_ROW))), np.zeros(1), 0.0, 0.0, False, functions, row, keys.reshape(1, 1),
            epipole, ctx.side == "right", stats, (effect.kernel.camera,),
            camera_row(ctx.camera) if ctx.camera is not None else None, (effect.kernel.workspace,))
        kn.record(effect.name, effect.kernel.stats, stats[0], ctx.stats)
        parts.append(im.ImageSet(pts=pts, start=start, fid=m[:, 0], segment=m[:, 1], fragment=m[:, 2],
                                 kind=m[:, 3], clipped=m[:, 4].astype(bool), closed=m[:, 5].astype(bool),
                                 trial=np.zeros(len(m), dtype=int), corners=corners, corner_fid=cfid,
                                 corner_trial=np.zeros(len(corners), dtype=int), occluded=m[:, 6].astype(bool)))
    return concat_trials(parts) if parts else s


MAX_PIXEL = 1e9  # a plug-in's coordinates beyond this many pixels are refused: no image is that large, and
# squares of such numbers (lengths, errors) stay finite downstream, so no later stage is blamed for them
INTEGER_FIELDS = ("start", "fid", "segment", "fragment", "kind", "trial", "corner_fid", "corner_trial")
FLAG_FIELDS = ("clipped", "closed", "occluded")


def plugin_apply(effect, params, sets: im.ImageSet, ctx: Context, n_features: int, stage: str,
                 design_point: int | None = None) -> im.ImageSet:
    """An installed effect's stage, its failures and its output's defects reported against its package (E181),
    naming the stage, pose, camera and trials; what it returns is checked and made canonical (float64 points,
    int64 numbers, bool flags) before anything else reads it."""
    from wiredsl.plugins import failure

    trials = np.asarray(ctx.trials)
    span = f"trials {trials.min()}..{trials.max()}" if len(trials) > 1 else f"trial {trials[0]}" if len(trials) else ""
    at = design_point if design_point is not None else ctx.point
    where = f"{stage}, pose {ctx.pose}, camera {ctx.side}, {span}" + (f", design point {at}" if at is not None else "")
    out = plugin_call(effect, "disturb()", effect.apply, params, sets, ctx, where=where)
    checked, problem, trial = plugin_imageset(out, len(trials), n_features)
    if problem is not None:
        if trial is not None:
            where = f"{stage}, pose {ctx.pose}, camera {ctx.side}, trial {int(trials[trial])}"
        raise failure("effect", effect.name, REGISTRY, f"returned {problem}", where)
    return checked


def plugin_imageset(s, n_trials: int, n_features: int) -> tuple[im.ImageSet | None, str | None, int | None]:
    """A plug-in's ImageSet checked: (the set in canonical dtypes, None, None), or (None, what is wrong, the batch
    index of the first trial it is wrong in, if one)."""
    problem = imageset_problem(s, n_trials)
    if problem is not None:
        return None, problem, None
    a = {name: np.asarray(getattr(s, name)) for name in ("pts", "corners", *INTEGER_FIELDS, *FLAG_FIELDS)}
    for name in ("pts", "corners"):
        if a[name].dtype.kind not in "fiu":
            return None, f"{name} of dtype {a[name].dtype}, not real numbers (float64)", None
    for name in INTEGER_FIELDS:
        if a[name].dtype.kind not in "iu":
            return None, f"{name} of dtype {a[name].dtype}, not integers (int64)", None
    for name in FLAG_FIELDS:
        if a[name].dtype.kind not in "biu" or (len(a[name]) and not np.isin(a[name], (0, 1)).all()):
            return None, f"{name} of dtype {a[name].dtype} or values other than True and False", None
    counts = np.diff(a["start"])
    pts_trial = np.repeat(a["trial"], counts)

    def first(bad: np.ndarray, trial_of: np.ndarray) -> int | None:
        return int(trial_of[np.argmax(bad)]) if bad.any() else None

    checks = (
        (counts < 2, a["trial"], "a stroke of fewer than two points (a stroke is a polyline: two points at least)"),
        ((a["fid"] < 0) | (a["fid"] >= n_features), a["trial"],
         f"stroke feature ids (fid) outside 0..{n_features - 1}"),
        ((a["corner_fid"] < 0) | (a["corner_fid"] >= n_features), a["corner_trial"],
         f"corner feature ids (corner_fid) outside 0..{n_features - 1}"),
        (~np.isin(a["kind"], (im.STRAIGHT, im.CURVE, im.ELLIPSE)), a["trial"],
         "a stroke kind other than 0 (straight), 1 (curve) or 2 (ellipse)"),
        ((a["segment"] < -1) | (a["fragment"] < -1), a["trial"], "a segment or fragment number below -1"),
        (~np.isfinite(a["pts"]).all(axis=1), pts_trial, "non-finite coordinates"),
        (~np.isfinite(a["corners"]).all(axis=1), a["corner_trial"], "non-finite corner coordinates"),
        ((np.abs(a["pts"]) > MAX_PIXEL).any(axis=1), pts_trial, f"coordinates beyond {MAX_PIXEL:g} px"),
        ((np.abs(a["corners"]) > MAX_PIXEL).any(axis=1), a["corner_trial"], f"corners beyond {MAX_PIXEL:g} px"),
    )
    for bad, trial_of, what in checks:
        if bad.any():
            return None, what, first(bad, trial_of)
    as_int = {name: a[name].astype(np.int64) for name in INTEGER_FIELDS}
    as_int.update({name: a[name].astype(bool) for name in FLAG_FIELDS})
    return im.ImageSet(pts=a["pts"].astype(np.float64).reshape(-1, 2), corners=a["corners"].astype(np.float64)
                       .reshape(-1, 2), **as_int), None, None


def imageset_problem(s, n_trials: int) -> str | None:
    """What is wrong with an ImageSet a stage returned (shapes, offsets, trials, finiteness), or None."""
    if not isinstance(s, im.ImageSet):
        return f"a {type(s).__name__}, not an ImageSet"
    try:
        pts, start, corners = np.asarray(s.pts), np.asarray(s.start), np.asarray(s.corners)
    except (TypeError, ValueError) as exc:  # ragged lists, say
        return f"arrays numpy cannot read ({exc})"
    for name, a in (("points", pts), ("corners", corners)):
        if a.dtype.kind not in "fiu":
            return f"{name} of dtype {a.dtype}, not real numbers (float64)"
    if start.ndim != 1 or start.dtype.kind not in "iu":
        return f"stroke offsets (start) of dtype {start.dtype} and shape {start.shape}, not (strokes + 1,) integers"
    n = len(start) - 1
    if pts.ndim != 2 or pts.shape[1:] != (2,) or corners.ndim != 2 or corners.shape[1:] != (2,):
        return f"points of shape {pts.shape} and corners of shape {corners.shape}, not (n, 2)"
    if n < 0 or start[0] != 0 or start[-1] != len(pts) or np.any(np.diff(start) < 0):
        return "stroke offsets (start) that do not cover its points in order"
    per_stroke = ("fid", "segment", "fragment", "kind", "clipped", "closed", "trial", "occluded")
    bad = [f for f in per_stroke if np.ndim(getattr(s, f)) != 1 or len(getattr(s, f)) != n]
    bad += [f for f in ("corner_fid", "corner_trial") if np.ndim(getattr(s, f)) != 1
            or len(getattr(s, f)) != len(corners)]
    if bad:
        return "arrays of the wrong length: " + ", ".join(bad)
    for name in ("trial", "corner_trial"):
        t = np.asarray(getattr(s, name))
        if t.dtype.kind not in "iu":
            return f"{name} of dtype {t.dtype}, not integers (int64)"
        if len(t) and (t.min() < 0 or t.max() >= n_trials):
            return f"{name} values outside 0..{n_trials - 1}"
    return None


def at_pose(stages, params: np.ndarray, pose: int) -> np.ndarray:
    """The kernel's parameter rows (`stage_rows`) for a view of pose `pose`: its index in the pose slot of every
    stage keyed along the path (a copy; the rows themselves when there is none)."""
    marked = [(g, len(e.kernel.params)) for g, (e, p) in enumerate(stages) if _path_keyed(e, p)]
    if not marked:
        return params
    params = params.copy()
    for g, slot in marked:
        params[g, slot] = pose
    return params


def _path_keyed(effect, params) -> bool:
    """Whether the stage's draws persist along the path (KernelStage.path and a correlation above 0): its key is
    then made without the pose (wiredsl.effects.variation)."""
    from wiredsl.effects import variation

    return effect.kernel is not None and effect.kernel.path and variation.along_path(params)


def _rig_keyed(effect) -> bool:
    """Whether the stage draws with the rig's key in both views (KernelStage.rig)."""
    return effect.kernel is not None and effect.kernel.rig
