"""The public Python API: compile a scene, run its Monte-Carlo trials, observe any pose in a closed loop.

    import wiredsl

    scene = wiredsl.compile("scenes/lab.wd")
    for batch in wiredsl.simulate(scene, trials=1000, seed=7):
        batch["pts"], batch["strokes"]        # the npz members of one batch (io/layout.py)
        batch.records()                       # what wiredsl.load gives for these trials

    sim = wiredsl.Simulator(scene, seed=7)
    seen = sim.observe((1.0, 0.5, 0.3), trial=0, step=12)   # any robot pose, draws keyed by step

Every name here is exported from `wiredsl` itself (lazily: importing wiredsl loads none of this).
"""

from __future__ import annotations

import math
import os
from collections import OrderedDict
from collections.abc import Iterator, Sequence

import numpy as np

from wiredsl import DEFAULT_VISIBILITY, VISIBILITIES
from wiredsl.diagnostics import Diagnostic, WiredslError
from wiredsl.effects.base import Effect
from wiredsl.measures.base import Measure
from wiredsl.plugins import PluginError
from wiredsl.scene import Pipeline, Scene

__all__ = ["Batch", "CameraAt", "CompileError", "CompileWarning", "Effect", "Measure", "PluginError", "Simulator",
           "compile", "simulate"]


class CompileError(WiredslError):
    """A scene that does not compile: `diagnostics` are what `wiredsl check` reports, and str(err) renders
    them as `check` prints them (file:line:column, the source line, a caret)."""

    def __init__(self, diagnostics: Sequence[Diagnostic], sources: dict[str, str] | None = None):
        super().__init__(diagnostics)
        self.sources = sources if sources is not None else {}

    def __str__(self) -> str:
        from wiredsl.diagnostics import read_sources, render

        return render(self.diagnostics, {**read_sources(self.diagnostics), **self.sources}).rstrip("\n")


class CompileWarning(UserWarning):
    """A warning `wiredsl check` would print about a scene that compiles."""


def compile(source: str | os.PathLike) -> Scene:  # noqa: A001 - the stage's name, as in the README's flow
    """The compiled scene of a file (a path: os.PathLike, or a str ending in `.wd` without a line break) or of
    scene text (any other str; its includes are found from the current folder).

    Raises CompileError with every diagnostic; warnings are issued as CompileWarning.
    """
    import warnings

    from wiredsl.language import ast
    from wiredsl.language.compile import compile_program

    if not isinstance(source, (str, os.PathLike)):
        raise TypeError(f"compile takes scene text (str) or a path (os.PathLike), not {type(source).__name__}")
    is_path = isinstance(source, os.PathLike) or (isinstance(source, str) and "\n" not in source
                                                   and source.endswith(".wd"))
    text = None if is_path else str(source)
    try:
        program = ast.load(source, None) if is_path else ast.load("<string>", text)
        scene, diags = compile_program(program)
    except WiredslError as err:
        raise CompileError(err.diagnostics, {"<string>": text} if text is not None else None) from None
    for d in diags:
        warnings.warn(CompileWarning(str(CompileError([d], program.sources))), stacklevel=_user_level())
    return scene


def _user_level() -> int:
    """The stacklevel, for a warning issued by this function's caller, of the first frame outside wiredsl: a
    warning of a scene compiled through wiredsl.gym is the user's call's, not a line of wiredsl's own code."""
    import sys

    package = os.path.dirname(os.path.abspath(__file__)) + os.sep
    frame, level = sys._getframe(1), 1  # level 1: the caller, which issues the warning
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(package):
        frame, level = frame.f_back, level + 1
    return level


class Batch:
    """Some trials of a run: `n_trials`, `trials` (their numbers), the npz members of one batch by name
    (`batch["pts"]`, without the bNNNNN_ prefix; float64 where the file has float32), and `records()`."""

    def __init__(self, trials: Sequence[int], arrays: dict[str, np.ndarray], feature_ids: list[str],
                 disturbed: list | None = None, kinds: dict[str, str] | None = None):
        self.trials = np.asarray(trials, dtype=np.int64)
        self.arrays = arrays
        self.feature_ids = feature_ids
        self.disturbed = disturbed  # per pose: (ideal PoseResult, {side: ImageSet}, views), for measures
        self.kinds = kinds  # "placement.feature" -> the kind its model declares (feature_kinds)

    @property
    def n_trials(self) -> int:
        return len(self.trials)

    def __getitem__(self, name: str) -> np.ndarray:
        return self.arrays[name]

    def keys(self):
        return self.arrays.keys()

    def records(self) -> list[dict]:
        """The feature records of these trials, as `wiredsl.load` gives them from the same run's dump."""
        from wiredsl.io.load import records

        return records({**self.arrays, "feature_ids": self.feature_ids})

    def select(self, placement: str | None = None, feature: str | None = None, kind: str | None = None,
               camera: str | None = None) -> list[dict]:
        """The records of the features chosen by placement name, model feature name and the kind the model
        declares them as (line, polyline, ellipse, silhouette, corner, surface: not their image kind, which
        says whether a line's image is straight or curved under distortion), and camera ("left", "right").
        A placement, feature or kind the scene does not have is a ValueError, never an empty list."""
        chosen = set(select_features(self.kinds or {}, placement, feature, kind))
        camera = None if camera is None else _choice("camera", camera, ("left", "right"))
        return [r for r in self.records() if r["source"] in chosen and camera in (None, r["camera"])]

    def __repr__(self) -> str:
        return f"Batch(trials {self.trials[0]}..{self.trials[-1]}, {len(self.arrays['strokes'])} strokes)"


MAX_SEED = 2**63 - 1  # as the command line's --seed
MAX_TRIAL = 2**31 - 1  # as its --trial (cli.MAX_TRIAL): npz numbers trials, and poses by step, in int32


def _integer(name: str, value, lo: int, hi: int) -> int:
    """`value` as an int in lo..hi, else a ValueError naming the argument (never a truncated 1.5, a bool, or
    numpy's OverflowError from deep inside the keyed draws)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= value <= hi:
        raise ValueError(f"{name} must be an integer in {lo}..{hi}, not {value!r}")
    return int(value)


def _choice(name: str, value, choices: tuple[str, ...]) -> str:
    if value not in choices:
        raise ValueError(f"{name} must be one of {', '.join(choices)}, not {value!r}")
    return value


def _poses(poses) -> list[int] | None:
    """Path pose indices as given (None: every pose); an empty list, a string or a 0.5 is refused."""
    if poses is None:
        return None
    if isinstance(poses, (str, bytes)) or not len(poses):
        raise ValueError(f"poses must be a non-empty list of path pose indices, not {poses!r}")
    return [_integer("poses must be path pose indices: each", p, 0, MAX_TRIAL) for p in poses]


def _scene(scene, where: str) -> Scene:
    """`scene` if it is a compiled Scene, else a TypeError saying how to get one (a path or text is not one)."""
    if isinstance(scene, Scene):
        return scene
    how = (f"compile it first: wiredsl.compile({scene!r})" if isinstance(scene, (str, os.PathLike))
           else "get one from wiredsl.compile(path or text) or wiredsl.load(path)")
    shown = repr(scene) if len(repr(scene)) <= 60 else repr(scene)[:60] + "..."
    raise TypeError(f"{where} takes a compiled Scene, not {type(scene).__name__} {shown}; {how}")


def _pipeline(scene: Scene, pipeline: Pipeline | str | None) -> Pipeline | None:
    from wiredsl.run import choose_pipeline

    return choose_pipeline(scene, pipeline).pipeline if not isinstance(pipeline, Pipeline) else pipeline


def simulate(scene: Scene, *, trials: int, seed: int, pipeline: Pipeline | str | None = None,
             poses: Sequence[int] | None = None, engine: str = "auto",
             visibility: str = DEFAULT_VISIBILITY) -> Iterator[Batch]:
    """The run's trials 0..trials-1, batch by batch (memory stays bounded however many trials).

    The same values as `wiredsl build --seed SEED --trials TRIALS --format npz` (whose file keeps float32
    pixels). `pipeline` is a pipeline's name or Pipeline (None: the scene's default, as build chooses it);
    `poses` the path pose indices (None: every pose); `visibility` as build's `--visibility` (the same
    default, wiredsl.DEFAULT_VISIBILITY: "auto" decides for the chosen poses x 2 cameras and warns W129, as a
    UserWarning, when it keeps hidden lines). A run without stages is the ideal projection: one batch of one
    trial, numbered 0, with the analytic conics, as build writes it.
    """
    from wiredsl import run as runs
    from wiredsl.engine.simulate import Options

    # the arguments are checked at the call, not at the first batch (simulate returns a generator)
    scene = _scene(scene, "simulate")
    trials, seed = _integer("trials", trials, 1, MAX_TRIAL + 1), _integer("seed", seed, 0, MAX_SEED)
    chosen = runs.check_poses(scene, _poses(poses))
    n_poses = len(chosen) if chosen else len(scene.path.poses) if scene.path is not None else 0
    world, mode = _visibility(scene, visibility, n_poses * 2)
    return _batches(scene, trials, seed, pipeline, Options(visibility=mode, poses=chosen), engine, world)


def _visibility(scene: Scene, visibility: str, views: int):
    """(world, the projection's mode) for the API's `visibility` (run.resolve_visibility); W129 as a warning."""
    import warnings

    from wiredsl import run as runs
    from wiredsl.engine.world import build_world

    world = build_world(scene)
    choice = runs.resolve_visibility(scene, world, _choice("visibility", visibility, VISIBILITIES), views,
                                     '`visibility="exact"` changes the answer (fewer poses also make it affordable)')
    if choice.warning is not None:
        warnings.warn(f"W129: {choice.warning}", UserWarning, stacklevel=_user_level())
    return world, choice.mode


def _batches(scene: Scene, trials: int, seed: int, pipeline, opts, engine: str, world=None, only: int | None = None
             ) -> Iterator[Batch]:
    """The run's batches of trials 0..trials-1 (`only`: trial `only` alone, the same draws); `engine="auto"`
    decides as build does for a run of `trials` trials (a trial alone: as its run)."""
    from wiredsl import run as runs
    from wiredsl.io.emit import batch_arrays, contours

    run = runs.start(scene, _pipeline(scene, pipeline), seed=seed, options=opts, engine=engine, world=world)
    if engine == "auto":
        runs.settle_auto_engine(run, trials)  # numpy for a small run, or a large one before the kernel is compiled
    ids, kinds = run.world.feature_ids, feature_kinds(scene)
    if not run.stages:
        out = [(r, {side: _ideal_set(run, r, side) for side in ("left", "right") if getattr(r, side) is not None},
                None) for r in run.ideal()]
        yield Batch([0], batch_arrays([0], out, contours(run.world), renumber=False), ids, out, kinds)
        return
    for batch, batch_out in run.batches(range(only, only + 1) if only is not None else range(trials)):
        yield Batch(batch, batch_arrays(batch, batch_out, contours(run.world)), ids, batch_out, kinds)


def _ideal_set(run, result, side: str):
    from wiredsl.engine.trials import to_imageset

    return to_imageset(getattr(result, side), run.world)


class Simulator:
    """One run of a scene for closed loops: `observe` any pose of the robot, trial by trial.

    Draws are keyed by (seed, stage, trial, step, camera), so `observe(i, trial=K)` is exactly what
    `build --seed S` gives pose i of trial K, and a controller that revisits a step sees the same draws.

    `engine="auto"` runs the compiled kernel when numba's cache has its loop for the pipeline's stages (a large
    `build`, or any run with `engine="kernel"`, compiles it once) and numpy otherwise: a one-trial view costs a few
    ms more on numpy, where a fresh install's first compile costs tens of seconds. Both give the same output.
    """

    def __init__(self, scene: Scene, seed: int, pipeline: Pipeline | str | None = None, *,
                 cameras: str = "both", visibility: str = DEFAULT_VISIBILITY, engine: str = "auto"):
        from wiredsl import run as runs
        from wiredsl.engine.simulate import Options

        self.scene = scene = _scene(scene, "Simulator")
        right = _choice("cameras", cameras, ("both", "left")) == "both"
        # "auto" decides for one pass over the path's poses (a single pose without a path)
        views = (len(scene.path.poses) if scene.path is not None else 1) * (2 if right else 1)
        world, mode = _visibility(scene, visibility, views)
        self.run = runs.start(scene, _pipeline(scene, pipeline), seed=_integer("seed", seed, 0, MAX_SEED),
                              options=Options(visibility=mode, right=right), engine=engine, need_path=False,
                              world=world)
        if engine == "auto" and self.run.uses_kernel() and not runs.kernel_compiled(self.run):
            self.run.engine = "numpy"  # a stream of one-trial views: the kernel once numba has it compiled
        self._lists: dict = {}  # view-point masks met so far
        self._occluders = None
        self._seen: OrderedDict = OrderedDict()  # (pose, trial, step) -> Batch: the last OBSERVED observations
        self._rigs: OrderedDict = OrderedDict()  # trial -> its perturbed rig (calibration_error's draw)
        self.kinds = feature_kinds(scene)

    @property
    def seed(self) -> int:
        return self.run.seed

    def observe(self, pose, trial: int = 0, step: int | None = None) -> Batch:
        """What the rig sees at `pose` in trial `trial`: a Batch of one trial (its arrays and `records()`).

        `pose` is a path pose index (then `step` defaults to it), a robot pose (x, y, heading) in metres and
        radians on the floor, or a 4x4 world-from-robot transform (planar: a turn about the vertical).
        `step` keys the draws (and numbers the pose in the output); an arbitrary pose needs one.
        """
        step = None if step is None else _integer("step", step, 0, MAX_TRIAL)
        trial = _integer("trial", trial, 0, MAX_TRIAL)
        key = (_pose_key(pose), trial, step)
        if key in self._seen:  # the same pose, trial and step again: the same draws, so the same batch
            self._seen.move_to_end(key)
            return self._seen[key]
        batch = self._observe(pose, trial, step)
        self._seen[key] = batch
        if len(self._seen) > OBSERVED:
            self._seen.popitem(last=False)
        return batch

    def _observe(self, pose, trial: int, step: int | None) -> Batch:
        from wiredsl.io.emit import batch_arrays, contours

        result, step = self._ideal(pose, step)
        trials = [trial]
        if self.run.stages:
            out = [self.run.observe(result, trials)]
        else:
            out = [(result, {side: _ideal_set(self.run, result, side) for side in ("left", "right")
                             if getattr(result, side) is not None}, None)]
        arrays = batch_arrays(trials, out, contours(self.run.world), renumber=bool(self.run.stages))
        return Batch(trials, arrays, self.run.world.feature_ids, out, self.kinds)

    def camera(self, pose, side: str = "left", trial: int | None = None) -> CameraAt:
        """The rig camera `side` with the robot at `pose`, as OpenCV takes it: K, distortion coefficients,
        R and t (camera from world) and the 3x4 projection P = K [R | t].

        trial None: the nominal camera, as the scene declares it. trial K: the camera trial K of this run
        saw, with calibration_error's draw applied (the same at every pose of the trial; nominal when the
        pipeline has no calibration_error). `pose` is a path pose index or any pose `observe` takes.
        """
        from wiredsl.engine import geometry

        side = _choice("side", side, ("left", "right"))
        engine_pose = self._engine_pose(pose)
        if trial is None or self.run.sampler() is None:
            if trial is not None:
                _integer("trial", trial, 0, MAX_TRIAL)
            mount = getattr(self.scene.rig, side)
            cam = self.scene.camera(mount.camera)
            values = {k: float(getattr(cam, k)) for k in geometry.CAMERA_KEYS}
            R, t = geometry.camera_from_world(engine_pose, mount.rotation, mount.position)
        else:
            from wiredsl.engine.trials import trial_cameras

            rig = self._trial_rig(_integer("trial", trial, 0, MAX_TRIAL))[side]
            cam = rig["camera"]
            R_cw, t_cw, cams, _ = trial_cameras(rig, engine_pose)
            values = dict(zip(geometry.CAMERA_KEYS, (float(v) for v in cams[0]), strict=False))
            R, t = R_cw[0], t_cw[0]
        return CameraAt.of(side, cam, values, R, t)

    def _trial_rig(self, trial: int) -> dict:
        from wiredsl.effects.calibration_error import perturbed_rigs

        if trial not in self._rigs:
            phis = self.run.calibration_draws([trial])
            self._rigs[trial] = perturbed_rigs(self.scene, phis, self.scene.rig.calibration.order)
            if len(self._rigs) > OBSERVED:
                self._rigs.popitem(last=False)
        return self._rigs[trial]

    def _engine_pose(self, pose) -> tuple[float, ...]:
        if isinstance(pose, (int, np.integer)) and not isinstance(pose, bool):
            if self.scene.path is None or not 0 <= pose < len(self.scene.path.poses):
                raise ValueError(f"pose {pose} is not a pose of the scene's path")
            return tuple(self.scene.path.pose(int(pose)))
        return robot_pose(pose)

    def select(self, placement: str | None = None, feature: str | None = None,
               kind: str | None = None) -> list[str]:
        """The feature ids ("placement.feature") chosen by placement, model feature name and declared kind (see
        `Batch.select`); a name or kind the scene does not have is a ValueError."""
        return select_features(self.kinds, placement, feature, kind)

    def _ideal(self, pose, step: int | None):
        import dataclasses

        from wiredsl.engine.simulate import project_pose

        if isinstance(pose, (int, np.integer)):
            if self.scene.path is None:
                raise ValueError(f"scene '{self.scene.name}' has no path: pass a robot pose (x, y, heading) or a "
                                 "4x4 transform, with step=N")
            ideal = self.run.ideal()
            if not 0 <= pose < len(ideal):
                raise ValueError(f"pose {pose} is not in 0..{len(ideal) - 1} (the path's poses)")
            result = ideal[int(pose)]
            if step is None or step == pose:
                return result, int(pose)
            pose = result.pose  # the path's pose, with the draws of another step
        if step is None:
            raise ValueError("an arbitrary pose needs step=N: the draws are keyed by it")
        xyh = robot_pose(pose)
        if self._occluders is None and self.run.options.visibility == "exact":
            from wiredsl.engine.occlusion import Occluders

            self._occluders = Occluders.of_world(self.run.world)
        result = project_pose(self.scene, self.run.world, xyh, int(step), self.run.options, self._lists,
                              self._occluders)
        return dataclasses.replace(result, index=int(step)), int(step)


OBSERVED = 64  # observations (and trial rigs) a Simulator keeps for a controller that asks again


def _pose_key(pose) -> tuple:
    """A hashable key of a pose as given: a path index, or its numbers exactly."""
    if isinstance(pose, (int, np.integer)) and not isinstance(pose, bool):
        return ("index", int(pose))
    a = np.asarray(pose, dtype=float)
    return ("pose", a.shape, a.tobytes())


MODEL_KINDS = {"lines": "line", "polylines": "polyline", "ellipses": "ellipse", "silhouettes": "silhouette",
               "corners": "corner", "surfaces": "surface"}


def feature_kinds(scene: Scene) -> dict[str, str]:
    """Every emitted feature of the scene, "placement.feature", with the kind its model declares it as."""
    models = {m.name: m for m in scene.models}
    out = {}
    for placement in scene.placements:
        model = models[placement.model]
        for attr, kind in MODEL_KINDS.items():
            for f in getattr(model, attr):
                out[f"{placement.name}.{f.name}"] = kind
    return out


def select_features(kinds: dict[str, str], placement: str | None = None, feature: str | None = None,
                    kind: str | None = None) -> list[str]:
    """The ids of `kinds` (feature_kinds) matching every criterion given; an unknown one is a ValueError that
    names what there is."""
    import difflib

    def known(what: str, value: str, choices: set[str]) -> None:
        if value not in choices:
            near = difflib.get_close_matches(value, sorted(choices), n=1)
            hint = f" (did you mean '{near[0]}'?)" if near else ""
            raise ValueError(f"no {what} '{value}' in the scene{hint}: {', '.join(sorted(choices))}")

    if placement is not None:
        known("placement", placement, {k.split(".", 1)[0] for k in kinds})
    if kind is not None:
        known("feature kind", kind, set(MODEL_KINDS.values()))
    chosen = [k for k, v in kinds.items() if (placement is None or k.split(".", 1)[0] == placement)
              and (kind is None or v == kind)]
    if feature is not None:
        known("feature" + (f" of placement '{placement}'" if placement else ""), feature,
              {k.split(".", 1)[1] for k in chosen} if chosen else {k.split(".", 1)[1] for k in kinds})
        chosen = [k for k in chosen if k.split(".", 1)[1] == feature]
    return chosen


class CameraAt:
    """A rig camera at a robot pose, in OpenCV's terms (numpy arrays, float64).

    `K` (3, 3); `dist` the distortion coefficients as OpenCV takes them: radtan (k1, k2, p1, p2, k3, k4, k5, k6)
    for cv2.projectPoints, equidistant (k1, k2, k3, k4) for cv2.fisheye.projectPoints (`model` says which);
    `R` (3, 3) and `t` (3,) with P_cam = R P_world + t (cv2.Rodrigues(R) is projectPoints' rvec, t its tvec);
    `P` (3, 4) = K [R | t], the projection of undistorted points; `size` (width, height) in pixels.
    """

    def __init__(self, side: str, model: str, K: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray,
                 size: tuple[int, int]):
        self.side, self.model, self.K, self.dist, self.R, self.t, self.size = side, model, K, dist, R, t, size

    @classmethod
    def of(cls, side: str, cam, v: dict[str, float], R: np.ndarray, t: np.ndarray) -> CameraAt:
        K = np.array([[v["f"] * v["ax"], 0.0, v["cx"]], [0.0, v["f"] * v["ay"], v["cy"]], [0.0, 0.0, 1.0]])
        keys = ("k1", "k2", "k3", "k4") if cam.distortion == "equidistant" else \
            ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
        return cls(side, cam.distortion, K, np.array([v[k] for k in keys]), np.array(R, dtype=float),
                   np.array(t, dtype=float), (int(cam.width), int(cam.height)))

    @property
    def P(self) -> np.ndarray:
        return self.K @ np.column_stack([self.R, self.t])

    def __repr__(self) -> str:
        return f"CameraAt({self.side}, {self.model}, f=({self.K[0, 0]:.6g}, {self.K[1, 1]:.6g}) px)"


PLANAR = 1e-9  # how far from a turn about the vertical a transform may be to be taken as a floor pose


def robot_pose(pose) -> tuple[float, ...]:
    """A robot pose as the engine takes it (geometry.world_from_robot): (x, y, heading) on the floor, given as
    such or as a transform that is a turn about the vertical; else the 12 numbers of a 6-DoF [R | t]. A
    transform is (4, 4), (3, 4) or its 12 numbers row-major (a trajectory path's pose)."""
    from wiredsl.language.statements import MAX_MAGNITUDE

    a = np.asarray(pose, dtype=float)
    if a.shape == (3,):
        shown = tuple(float(v) for v in a)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"pose {shown} is not finite")
        if np.abs(a[:2]).max() > MAX_MAGNITUDE:  # as a scene's lengths (E110): squares of it stay finite
            raise ValueError(f"pose {shown} is beyond {MAX_MAGNITUDE:g} m from the origin")
        return shown
    if a.shape not in ((4, 4), (3, 4), (12,)):
        raise ValueError(f"a pose is a path index, (x, y, heading) or a 4x4 transform, not shape {a.shape}")
    a = np.vstack([a.reshape(-1, 4), [0, 0, 0, 1]])[:4]
    R, t = a[:3, :3], a[:3, 3]
    if not np.all(np.isfinite(a)) or np.abs(a[3] - [0, 0, 0, 1]).max() > PLANAR \
            or np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise ValueError("a 4x4 pose must be a rigid transform (rotation and translation, last row 0 0 0 1)")
    if np.abs(t).max() > MAX_MAGNITUDE:
        raise ValueError(f"pose's translation {tuple(float(v) for v in t)} is beyond {MAX_MAGNITUDE:g} m")
    if abs(R[2, 2] - 1) > PLANAR or np.abs(R[2, :2]).max() > PLANAR or np.abs(R[:2, 2]).max() > PLANAR \
            or abs(t[2]) > PLANAR:
        return tuple(float(v) for v in a[:3].ravel())  # 6-DoF: height, roll and pitch
    return robot_pose((t[0], t[1], math.atan2(R[1, 0], R[0, 0])))
