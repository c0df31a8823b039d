"""The one place that sets up a Monte-Carlo run: pipeline choice, seed resolution, `Run.create`.

Every face starts its runs here: `wiredsl build`, `wiredsl export-calibration`, a study's shards and the
public Python API (`wiredsl.simulate`, `wiredsl.Simulator`). The faces only parse their options and call.
(io/render.py, below, draws trial 0 of a given pipeline and seed on numpy: it calls `Run.create` as `start` would.)
"""

from __future__ import annotations

import dataclasses
import secrets
from dataclasses import dataclass

from wiredsl import install_hint
from wiredsl.engine.simulate import Options
from wiredsl.engine.world import World, build_world
from wiredsl.io import viewdep
from wiredsl.montecarlo import Run
from wiredsl.scene import Pipeline, Scene

ENGINES = ("auto", "kernel", "numpy")


class RunSetupError(ValueError):
    """A run's options do not fit the scene (an unknown pipeline, a pose off the path, ...).

    `option` names the command-line option at fault, for the command line's message.
    """

    def __init__(self, message: str, option: str | None = None):
        super().__init__(message)
        self.option = option


@dataclass(frozen=True)
class PipelineChoice:
    pipeline: Pipeline | None
    note: str | None = None  # said to the user when the choice is not obvious


def choose_pipeline(scene: Scene, name: str | None = None, no_effects: bool = False) -> PipelineChoice:
    """The named pipeline, else the scene's default (marked, or the only one); None: the ideal projection."""
    if no_effects:
        return PipelineChoice(None)
    if name is not None:
        pipeline = scene.pipeline(name)
        if pipeline is None:
            names = ", ".join([p.name for p in scene.pipelines] + ["the built-in paper"] * (
                not any(p.name == "paper" for p in scene.pipelines)))
            ideal = "; --no-effects draws the ideal projection" if name.lower() in ("none", "ideal") else ""
            raise RunSetupError(f"no pipeline '{name}' in {scene.source} (it has: {names}){ideal}", "--pipeline")
        return PipelineChoice(pipeline)
    pipeline = scene.pipeline()
    if pipeline is None and scene.pipelines:
        return PipelineChoice(None, "no pipeline is marked default; building the ideal projection (choose one "
                                    "with --pipeline: " + ", ".join(p.name for p in scene.pipelines) + ")")
    return PipelineChoice(pipeline)


# --visibility auto (the default of `build`, `study`, `export`, the API and the Gymnasium environment): where a
# scene has faces (hand-written or a mesh's) and the view-points' lists would be computed (`visibility auto`, or no
# view-points), exact hidden lines when affordable, else the lists with W129. The cost of a view, in CPU seconds, from
# the world's counts: T occluding triangles, L line segments (lines and polylines' pieces), C curves (ellipses and
# silhouette generators, sampled) and S ruled surfaces (the silhouettes' sides):
#     EXACT_VIEW + EXACT_TRIANGLE T + EXACT_SEGMENT L sqrt(T) + EXACT_CURVE C sqrt(T) + EXACT_CURVE_SURFACE C S
# (a segment or a curve meets the triangles in its grid cells, about sqrt(T) of them on a part; a curve's samples
# meet every surface). Fitted by `python benchmarks/visibility_cost.py --fit` to one view of 12 scenes (the lab,
# the example scenes, uv spheres of 6k to 101k triangles, the ADIS housing, the bunny, the cycloidal gear and the
# counter), 2026-12-03, loaded 2-core machine: every scene's estimate within 0.83-1.12 of its CPU, left out of the
# fit within 0.76-1.62 (the old cost, 4e-4 s a triangle, was 0.4x the gear's and 330x a 407k-triangle sphere's).
EXACT_VIEW, EXACT_TRIANGLE, EXACT_SEGMENT, EXACT_CURVE, EXACT_CURVE_SURFACE = 0.015, 1.8e-6, 6.4e-6, 6.3e-5, 1.9e-4
AUTO_EXACT_SECONDS = 60.0  # the estimated CPU up to which auto removes hidden lines exactly


@dataclass(frozen=True)
class VisibilityChoice:
    mode: str  # "exact" or "scene"
    warning: str | None = None  # why faces that hide something do not hide it in this build (W129)
    seconds: float = 0.0  # the estimated CPU of exact visibility


REMEDY_CLI = "`--visibility exact` changes the answer (fewer poses with --pose also make it affordable)"


def exact_seconds(world: World, views: int) -> float:
    """The estimated CPU of exact hidden lines for `views` views of `world` (the model above)."""
    T, L = len(world.triangles), len(world.lines)
    C, S = len(world.ell_c) + len(world.sil_pair), len(world.sil_pair)
    root = T ** 0.5
    return views * (EXACT_VIEW + EXACT_TRIANGLE * T + (EXACT_SEGMENT * L + EXACT_CURVE * C) * root
                    + EXACT_CURVE_SURFACE * C * S)


def choose_visibility(scene: Scene, world: World, views: int, remedy: str = REMEDY_CLI) -> VisibilityChoice:
    """What `--visibility auto` means for this scene and number of views (poses x cameras, times the trials when
    each trial projects afresh): exact when the scene has faces (World.triangles: hand-written faces or a mesh's)
    and either no view-points or view-points whose lists are computed (`visibility auto`: whole-feature lists draw
    the parts of a feature behind a face), and the estimate is at most AUTO_EXACT_SECONDS; else the view-points'
    lists (`scene`), with a warning when exact was wanted, ending with `remedy`: what the caller (command line, API
    or study) can do about it. Authored or read lists (`visibility authored` / `file`) are the author's: kept."""
    triangles = len(world.triangles)
    vp = scene.viewpoints
    wanted = triangles > 0 and (vp is None or vp.visibility == "auto")
    seconds = exact_seconds(world, views)
    if not wanted:
        return VisibilityChoice("scene")
    if seconds <= AUTO_EXACT_SECONDS:
        return VisibilityChoice("exact", seconds=seconds)
    shown = "every feature whole" if vp is None else "the view-points' lists of whole features"
    return VisibilityChoice("scene", f"hidden lines are not removed: {views:,} view{'s' * (views != 1)} x "
                            f"{triangles:,} occluding triangles would take about {seconds:,.0f} s of CPU with exact "
                            f"visibility (over {AUTO_EXACT_SECONDS:.0f} s), so {shown} are drawn, hidden parts "
                            f"too; {remedy}", seconds)


def resolve_visibility(scene: Scene, world: World, visibility: str, views: int, remedy: str = REMEDY_CLI
                       ) -> VisibilityChoice:
    """The projection's mode for `visibility` (one of wiredsl.VISIBILITIES): "auto" as `choose_visibility` for
    `views` views (`remedy` ends its warning); the others as given."""
    if visibility == "auto":
        return choose_visibility(scene, world, views, remedy)
    return VisibilityChoice(visibility)


def w129_span(program, scene: Scene):
    """Where W129 points: the first `mesh read` (a mesh's triangles are what make exact costly), else the
    `viewpoints` statement (whose lists are drawn instead), else the file's start."""
    from wiredsl.diagnostics import Span

    if getattr(program, "mesh_reports", None):
        return program.mesh_reports[0][0]
    stmt = next((s for s in getattr(program, "statements", ()) if s.keyword == "viewpoints"), None)
    return stmt.keyword_span if stmt is not None else Span(scene.source, 1, 1, 1, 1)


def exact_cost_note(scene: Scene, world: World, views: int) -> str | None:
    """For a scene with faces: the estimated CPU of exact visibility for `views` views and what
    `--visibility auto` chooses (`wiredsl check`'s note); None without faces."""
    if not len(world.triangles):
        return None
    choice = choose_visibility(scene, world, views)
    triangles = len(world.triangles)
    seconds = exact_seconds(world, views)
    if choice.mode == "exact":
        why = "exact hidden lines"
    elif choice.warning is not None:
        why = f"the view-points' lists, with warning W129 (over {AUTO_EXACT_SECONDS:.0f} s)"
    else:
        why = f"the view-points' lists (the scene's `visibility` is {scene.viewpoints.visibility}, not auto)"
    return (f"exact visibility: {views:,} view{'s' * (views != 1)} x {triangles:,} occluding triangles, about "
            f"{seconds:,.1f} s of CPU; `--visibility auto` (the default) uses {why}")


def check_poses(scene: Scene, poses) -> tuple[int, ...] | None:
    """The chosen pose indices, sorted and unique (None: every pose); a pose off the path is refused."""
    if poses is None:
        return None
    chosen = tuple(sorted({int(p) for p in poses}))
    if scene.path is not None:
        n = len(scene.path.poses)
        for p in chosen:
            if not 0 <= p < n:
                raise RunSetupError(f"pose {p} is not in 0..{n - 1}", "--pose")
    return chosen or None


def check_engine(engine: str) -> str:
    """The engine, if it can run here: "kernel" needs numba installed."""
    if engine not in ENGINES:
        raise RunSetupError(f"engine {engine!r} is not one of {', '.join(ENGINES)}", "--engine")
    if engine == "kernel":
        import importlib.util

        if importlib.util.find_spec("numba") is None:
            raise RunSetupError(f"the compiled kernel needs numba: {install_hint('fast')}", "--engine")
    return engine


def start(scene: Scene, pipeline: Pipeline | str | None = None, *, seed: int | None = None,
          options: Options | None = None, world: World | None = None, point: int | None = None,
          engine: str = "auto", exact_calibration: bool = False, base: Run | None = None,
          need_path: bool = True) -> Run:
    """A Run of the scene through `pipeline` (a Pipeline, a pipeline's name, or None: no stages).

    `seed` None draws one at random when something random runs (kept in `run.seed`); an ideal run keeps 0,
    so its output is byte-identical whatever the seed. `base`, a run of the same scene and options, lends its
    ideal projection and visibility (which no stage changes). `need_path` False: poses come from the caller.
    """
    if isinstance(pipeline, str):
        pipeline = choose_pipeline(scene, pipeline).pipeline
    options = options if options is not None else Options()
    if options.viewdep is None:
        options = dataclasses.replace(options, viewdep=viewdep.of_scene(scene))
    run = Run.create(scene, world if world is not None else build_world(scene), pipeline,
                     seed if seed is not None else 0, options, point=point, need_path=need_path)
    if seed is None and run.stages:  # drawn only when something random runs, so ideal runs stay byte-identical
        run.seed = secrets.randbits(63)
    run.engine = check_engine(engine)
    if engine == "kernel" and run.stages and not exact_calibration and \
            len(run.compiled_stages()) < len(run.image_stages):
        lacking = ", ".join(e.name for e, _ in run.image_stages if e.kernel is None)
        first = run.image_stages[len(run.compiled_stages())][0].name
        run.warnings.append(f"the stages from {first} on run on numpy: no compiled kernel for {lacking}")
    run.exact_calibration = exact_calibration
    if base is not None:
        run.share_projection(base)
    return run


# CPU time of a pipeline whose stages from a numpy-only one on run on numpy, over the compiled kernel's, for the
# lab's `paper` pipeline with one cheap numpy-only stage at "corner detection" (benchmarks/numpy_forced.py, 512
# trials, 2026-11-26: 0.28 s against 0.20 s); the whole pipeline on numpy was 7.0x
NUMPY_COST = 1.4


def numpy_forced_line(effects: list, engine: str, remedy: str = ", or --engine numpy to choose numpy") -> str | None:
    """The one line said on stderr when, under `--engine auto` with numba installed, a stage without a compiled
    kernel (an installed plug-in's) makes it and the stages after it run on numpy; None otherwise. `remedy`
    ends it: what else the command can do (a study has no --engine: "")."""
    import importlib.util

    from wiredsl.montecarlo import kernel_prefix
    from wiredsl.plugins import Registry

    image = [e for e in effects if e.name != "calibration_error"]
    lacking = [e for e in image if e.kernel is None]
    if engine != "auto" or not lacking or importlib.util.find_spec("numba") is None:
        return None
    from wiredsl.effects import REGISTRY

    names = []
    for e in dict.fromkeys(lacking):
        origin = REGISTRY.origin(e.name) if isinstance(REGISTRY, Registry) else None
        names.append(f"'{e.name}'" + (f" ({origin.package} {origin.version})" if origin else ""))
    k = kernel_prefix(image)
    after = f"the stages from '{image[k].name}' on run on numpy" if k else "the whole pipeline runs on numpy"
    return (f"wiredsl: {', '.join(names)} {'has' if len(names) == 1 else 'have'} no compiled kernel, so {after}: "
            f"about {NUMPY_COST:g}x the CPU time of the kernel on the lab, up to 7x (the whole pipeline); give the "
            f"effect a KernelStage{remedy}")


def numpy_forced(run: Run, trials: int) -> str | None:
    """numpy_forced_line for a run of `trials` trials, said only where the kernel would have run (a run as large
    as `--engine auto` gives the kernel)."""
    from wiredsl.montecarlo import KERNEL_PAYS

    if run.exact_calibration or not run.stages or trials * run.trial_size()[0] < KERNEL_PAYS:
        return None
    return numpy_forced_line([e for e, _ in run.stages], run.engine)


# `--engine auto` when the compiled loop is not in numba's cache yet (a fresh install): numpy unless the run is large
# enough for compiling to pay for itself in this run (break-even, as a tiered JIT decides: the compile's CPU against
# the numpy engine's extra CPU over the kernel's). Measured on scenes/lab.wd's `paper` pipeline (2,263 vertices a
# trial as `build` projects it, hidden lines removed: `Run.trial_size`), 2026-12-02, the shared 2-core machine, one
# run each: the built-in loop's compile from an empty cache 43 s of CPU (`python -c "from wiredsl.engine import
# kernel; kernel.warm()"`: 40.7 s user + 2.3 s system), and `build --format npz` of 300 and 3,000 trials: numpy 2.8 s
# and 17.5 s, kernel 1.75 s and 3.6 s, so numpy's extra CPU is (17.5 - 2.8 - (3.6 - 1.75)) / 2,700 trials / 2,263
# vertices = 1.9e-6 s a vertex-trial. (A replay, `--trials N --trial K`, decides as its N-trial run.)
COMPILE_SECONDS = 43.0
NUMPY_EXTRA_SECONDS = 1.9e-6  # a vertex-trial
COLD_KERNEL_PAYS = COMPILE_SECONDS / NUMPY_EXTRA_SECONDS  # vertex-trials: some 10,000 trials of the lab's build


def kernel_compiled(run) -> bool:
    """Whether numba's cache holds the compiled loop of the run's kernel stages (`kernel.loop_cached`): running
    it loads it instead of compiling it."""
    from wiredsl.engine import kernel

    return kernel.loop_cached(tuple((e.kernel.function, e.kernel.camera, e.kernel.workspace)
                                    for e, _ in run.compiled_stages()))


def cold_kernel_line(run, trials: int) -> str | None:
    """Under `--engine auto`, for a run that would use the compiled kernel: when its loop is not in numba's cache
    yet (`kernel.loop_cached`) and the run is smaller than COLD_KERNEL_PAYS vertex-trials, set the run's engine to
    numpy (both engines give the same output) and return the one line said on stderr; else None (the kernel)."""
    if not run.uses_kernel():
        return None
    size = run.trial_size()[0]
    if trials * size >= COLD_KERNEL_PAYS or kernel_compiled(run):
        return None
    run.engine = "numpy"
    n = int(COLD_KERNEL_PAYS // max(size, 1)) + 1
    return (f"note: numpy engine for this run (the compiled kernel is not built yet, about {COMPILE_SECONDS:.0f} s "
            f"of CPU once: a run of {n:,} trials or more of this scene builds it, as does --engine kernel)")


def settle_auto_engine(run, trials: int) -> str | None:
    """What `engine="auto"` means for a run of `trials` trials (a replay's: its run's N), for build and the API
    alike: numpy where the kernel would not pay for loading numba (`Run.kernel_pays`) or, not compiled yet, for
    compiling its loop (`cold_kernel_line`, whose line it returns); else the kernel, as `run` has it."""
    if not run.uses_kernel():
        return None
    if not run.kernel_pays(trials):
        run.engine = "numpy"  # a small run: the kernel would not pay
        return None
    return cold_kernel_line(run, trials)
