"""Shards: one (design point, trial range) of a study, computed alone and written as one file.

A shard's values depend only on the scene, the study, the point and the trials, never on which
worker ran it or when, so a study's table is the same whatever the executor and however often it
was interrupted. A shard file carries its key and a checksum of its arrays; a rerun skips a shard
whose file has the expected key and checksum, and recomputes any other.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from wiredsl import DEFAULT_VISIBILITY
from wiredsl.engine import imageset as im
from wiredsl.engine.simulate import Options
from wiredsl.engine.world import World, build_world
from wiredsl.files import write_atomic
from wiredsl.measures import BUILTIN, REGISTRY
from wiredsl.montecarlo import Run
from wiredsl.plugins import call, failure, params_of
from wiredsl.run import VisibilityChoice, resolve_visibility, start
from wiredsl.scene import Scene, Study
from wiredsl.study import design

SHARD_TRIALS = 256  # trials a shard: one engine batch (the kernel's per-batch costs amortised); points spread work


@dataclass(frozen=True)
class Shard:
    point: int
    lo: int  # first trial
    hi: int  # one past the last trial

    @property
    def name(self) -> str:
        return f"p{self.point:05d}_t{self.lo:07d}-{self.hi:07d}"


@dataclass(frozen=True)
class Job:
    """Everything a worker needs to compute one shard (picklable, for processes and Dask)."""

    scene: Scene
    study: Study
    digest: str  # of the scene and the study: a shard from another study is never reused
    values: tuple[float, ...]  # the point's factor values
    shard: Shard
    folder: str
    registry: dict | None  # measure name -> class; None: the installed measures


def shards(n_points: int, trials: int, size: int = SHARD_TRIALS) -> list[Shard]:
    return [Shard(p, lo, min(lo + size, trials)) for p in range(n_points) for lo in range(0, trials, size)]


def options(study: Study, scene: Scene, world: World) -> Options:
    """The projection's options of every run of a study: its poses, and one visibility for all its points."""
    return Options(poses=tuple(study.poses) if study.poses is not None else None,
                   visibility=visibility(study, scene, world).mode)


def visibility(study: Study, scene: Scene, world: World) -> VisibilityChoice:
    """wiredsl.DEFAULT_VISIBILITY ("auto") decided once for the whole study, from what it projects: its poses x 2
    cameras, times its design points when a factor varies the cameras (each point then projects its own; else
    the points share one projection, whatever their number). Every point uses the same mode, so that the points
    compare: a Sobol' study that varies the cameras over thousands of points is usually over the budget and
    keeps the view-points' lists (warning W129, said when the study starts)."""
    poses = len(study.poses) if study.poses is not None else len(scene.path.poses) if scene.path is not None else 0
    points = len(design.matrix(study)) if design.varies_scene(study) else 1
    return resolve_visibility(scene, world, DEFAULT_VISIBILITY, poses * 2 * points,
                              "fewer poses in the study's `poses` (or, when a factor varies the cameras, fewer "
                              "points) make exact hidden lines affordable")


def point_run(scene: Scene, world: World, study: Study, point: int, values, opts: Options | None = None,
              base: Run | None = None) -> Run:
    """The Run of one design point: its pipeline substituted, every draw keyed by the point's index too
    (`draws independent`), or by the trial alone, the same at every point (`draws common`).

    `base` (a run of the same scene and options) lends its ideal projection and visibility, which no
    pipeline parameter changes.
    """
    values = np.asarray(values, dtype=float)
    lend = None if design.varies_scene(study) else base  # a point that varies the cameras projects its own
    run = start(design.scene_at(scene, study, values), design.pipeline_at(scene, study, values), seed=study.seed,
                 options=opts or options(study, scene, world), world=world,
                 point=None if study.draws == "common" else point, base=lend)
    run.design_point = point  # (messages name it under common draws too)
    return run


def warm_kernel(job: Job) -> None:
    """Compile the compiled kernel's loop of the built-in stages in this process, once, if the study's points run
    it (or load it from numba's cache): its worker processes then load it from the cache instead of each compiling
    it at once, and "compiling" is said once, by the study's own process. (A plug-in's loop is compiled where its
    failure is reported as the plug-in's: in the workers.)"""
    scene = job.scene
    run = point_run(scene, build_world(scene), job.study, job.shard.point, job.values)
    if not run.uses_kernel():
        return
    from wiredsl.engine import kernel

    stages = tuple((e.kernel.function, e.kernel.camera, e.kernel.workspace) for e, _ in run.compiled_stages())
    if kernel.stage_table(stages) == kernel.builtin_table():
        kernel.warm()


_WORKER: dict = {}  # per process: digest -> (world, base run, prepared); (digest, point) -> (run, prepared)


def compute(job: Job) -> dict[str, np.ndarray]:
    """One shard's per-trial values: {"measure.statistic": (n_poses, n_trials)}."""
    run, prepared = _setup(job)
    return measure_batches(run, prepared, list(range(job.shard.lo, job.shard.hi)))


def compute_chunk(jobs: list[Job]) -> list[dict[str, np.ndarray]]:
    """`compute` of each job, the trials of consecutive design points measured together (`measure_points`)."""
    units = []
    for job in jobs:
        run, prepared = _setup(job)
        units.append((run, prepared, list(range(job.shard.lo, job.shard.hi))))
    return measure_points(units)


def _setup(job: Job) -> tuple[Run, list]:
    """The run of a job's design point and its measures' prepared data, kept per worker: the world, the run of
    no stages and (unless the study varies the cameras) the prepared measures once per study, a point's run
    once per point."""
    from wiredsl.language.compile_study import measure_registry

    registry = job.registry if job.registry is not None else measure_registry()
    study, scene = job.study, job.scene
    if job.digest not in _WORKER:
        world = build_world(scene)
        _WORKER.clear()  # one study at a time per worker
        opts = options(study, scene, world)
        base = start(scene, None, options=opts, world=world)
        base.ideal()
        # a measure's reference data come from the ideal scene, which no pipeline parameter changes:
        # prepared once per study (with the run of no stages), unless the study varies the cameras
        _WORKER[job.digest] = (world, opts, base,
                               None if design.varies_scene(study) else _prepare(study, registry, base))
    world, opts, base, prepared = _WORKER[job.digest]
    key = (job.digest, job.shard.point)
    if key not in _WORKER:
        for old in [k for k in _WORKER if isinstance(k, tuple)]:  # a point's shards come together: keep one
            del _WORKER[old]
        run = point_run(scene, world, study, job.shard.point, job.values, opts, base=base)
        _WORKER[key] = (run, prepared if prepared is not None else _prepare(study, registry, run))
    return _WORKER[key]


def _prepare(study: Study, registry: dict, run: Run) -> list:
    out = []
    for m in study.measures:
        measure = registry[m.name]
        params = params_of("measure", measure, REGISTRY, m.params)
        out.append((measure, params, _guarded(measure, "prepare()", measure.prepare, params, run,
                                              where=f"design point {run.where_point()}" if run.where_point() is not None
                                              else None)))
    return out


def _guarded(measure, doing: str, fn, *args, where=None):
    """A call into a measure's code: an installed measure's failure is its package's error (E181, naming where);
    a built-in's stays a bug."""
    if measure.name in BUILTIN:
        return fn(*args)
    return call("measure", measure.name, REGISTRY, doing, fn, *args, where=where)


MAX_STATISTIC = 1e150  # a statistic's magnitude at most: its sums of squares over a study stay finite


def measure_batches(run: Run, prepared, trials: list[int]) -> dict[str, np.ndarray]:
    """Every measure on every pose of the given trials: {"measure.statistic": (n_poses, n_trials)}.

    Each measure gets read-only views of the pose and the disturbed sets (one cannot change what another
    reads), and what an installed one returns is checked before anything reads it."""
    return measure_points([(run, prepared, trials)])[0]


def measure_points(units: list[tuple[Run, list, list[int]]]) -> list[dict[str, np.ndarray]]:
    """`measure_batches` of several design points' (run, prepared, trials), in order.

    Consecutive points that share their prepared measures and ideal poses (a study that does not vary the
    cameras) have their engine batches pooled, up to an engine batch's trials (`Run.batch_size`): a `pooled`
    measure is called once a pose for the whole pool, its disturbed sets concatenated with the trials renumbered
    0..n-1, and its values split back by point. Its values are each trial's own, so they are those of a call per
    point (a study's cost is then per trial, not per measure call). Other measures are called per batch.
    """
    parts: list[dict[str, list[list[np.ndarray]]]] = [{} for _ in units]
    pool: list[tuple[int, Run, list, Sequence[int], list]] = []  # (unit, run, prepared, batch, [(result, sets)])
    frozen: dict[int, tuple] = {}  # id(pose result) -> (result, its read-only view): poses shared by the pool

    def flush() -> None:
        if pool:
            _measure_pool(pool, parts, frozen)
            pool.clear()

    for u, (run, prepared, trials) in enumerate(units):
        for batch, batch_out in run.batches(trials):
            got = [(result, disturbed) for result, disturbed, _views in batch_out]
            if pool and not (pool[0][2] is prepared and _same_poses(pool[0][4], got)
                             and sum(len(b) for *_, b, _ in pool) + len(batch) <= run.batch_size()):
                flush()
            pool.append((u, run, prepared, batch, got))
    flush()
    return [{k: np.stack([np.concatenate(r) for r in rows]) for k, rows in p.items()} for p in parts]


def _same_poses(a: list, b: list) -> bool:
    return len(a) == len(b) and all(x[0] is y[0] and x[1].keys() == y[1].keys() for x, y in zip(a, b, strict=True))


def _measure_pool(pool: list, parts: list[dict], frozen: dict) -> None:
    """Every measure on every pose of a pool of batches (one point's, or several points' sharing their poses)."""
    prepared = pool[0][2]
    sizes = [len(batch) for _, _, _, batch, _ in pool]
    ends = np.cumsum(sizes)[:-1]
    points = sorted({run.where_point() for _, run, _, _, _ in pool if run.where_point() is not None})
    for j in range(len(pool[0][4])):
        result = pool[0][4][j][0]
        if id(result) not in frozen:
            frozen[id(result)] = (result, read_only(result))
        pose = frozen[id(result)][1]
        sides = pool[0][4][j][1].keys()
        pooled = {side: read_only(_stack([entry[4][j][1][side] for entry in pool], sizes)) for side in sides} \
            if len(pool) > 1 else None
        for measure, params, prep in prepared:
            if pooled is not None and getattr(measure, "pooled", False):
                calls = [(pooled, sum(sizes), pool[0][3][0], pool[-1][3][-1], points)]
            else:
                calls = [({side: read_only(v) for side, v in entry[4][j][1].items()}, len(entry[3]), entry[3][0],
                          entry[3][-1], [entry[1].where_point()] if entry[1].where_point() is not None else [])
                         for entry in pool]
            values_of = []
            for sets, n, first, last, at in calls:
                where = f"pose {result.index}, trials {first}..{last}" + (
                    f", design point {at[0]}" if len(at) == 1 else f", design points {at[0]}..{at[-1]}" if at else "")
                got = _guarded(measure, "measure()", measure.measure, params, prep, pose, sets, n, where=where)
                values = statistics_of(measure, got, n)
                if isinstance(values, str):
                    raise failure("measure", measure.name, REGISTRY, values, where)
                values_of.append(values)
            if len(values_of) == 1 and len(pool) > 1:  # one pooled call: split by entry
                values_of = [{stat: v[lo:hi] for stat, v in values_of[0].items()}
                             for lo, hi in zip([0, *ends], [*ends, sum(sizes)], strict=True)]
            for (u, *_), values in zip(pool, values_of, strict=True):
                for stat, v in values.items():
                    rows = parts[u].setdefault(f"{measure.name}.{stat}", [])
                    if len(rows) <= j:
                        rows.append([])
                    rows[j].append(v)


def _stack(sets: list[im.ImageSet], sizes: list[int]) -> im.ImageSet:
    """One ImageSet of several batches' sets (of `sizes` trials each), their trials renumbered in order."""
    offsets = np.cumsum([0, *sizes[:-1]])
    vertex = np.cumsum([0] + [len(s.pts) for s in sets])
    cat = lambda name: np.concatenate([getattr(s, name) for s in sets])  # noqa: E731
    return im.ImageSet(
        pts=cat("pts").reshape(-1, 2),
        start=np.concatenate([s.start[:-1] + o for s, o in zip(sets, vertex, strict=False)] + [[vertex[-1]]]
                             ).astype(int),
        fid=cat("fid"), segment=cat("segment"), fragment=cat("fragment"), kind=cat("kind"), clipped=cat("clipped"),
        closed=cat("closed"), trial=np.concatenate([s.trial + o for s, o in zip(sets, offsets, strict=True)]),
        corners=cat("corners").reshape(-1, 2), corner_fid=cat("corner_fid"),
        corner_trial=np.concatenate([s.corner_trial + o for s, o in zip(sets, offsets, strict=True)]),
        occluded=cat("occluded"))


def statistics_of(measure, got, n: int) -> dict[str, np.ndarray] | str:
    """A measure's answer checked: {statistic: (n,) float64}, or what is wrong with it (a dict of one finite real
    value a trial for each statistic, magnitudes up to MAX_STATISTIC, weights never negative)."""
    if not isinstance(got, Mapping):
        return f"returned a {type(got).__name__}, not a dict of statistics"
    out = {}
    counts = set((getattr(measure, "weights", None) or {}).values())
    for stat in measure.statistics:
        raw = np.asarray(got[stat]) if stat in got else None
        why = "nothing" if raw is None else f"dtype {raw.dtype}" if raw.dtype.kind not in "fiub" else \
            f"shape {raw.shape}" if raw.shape != (n,) else None
        v = raw.astype(np.float64) if why is None else None
        if why is None and not np.all(np.isfinite(v)):
            why = f"non-finite values (trial {int(np.argmax(~np.isfinite(v)))} of the batch)"
        elif why is None and np.abs(v).max(initial=0) > MAX_STATISTIC:
            why = f"values beyond {MAX_STATISTIC:g}"
        elif why is None and stat in counts and v.min(initial=0) < 0:
            why = "negative values for a statistic that weights another (a count)"
        if why is not None:
            return f"gave {why} for statistic '{stat}' ({n} trials: one finite real value a trial)"
        out[stat] = v
    return out


def read_only(x):
    """A view of an ImageSet or a PoseResult whose arrays cannot be written (numpy's writeable flag off)."""
    import dataclasses

    from wiredsl.engine import imageset as im
    from wiredsl.engine.simulate import PoseResult

    def frozen(a):
        if not isinstance(a, np.ndarray):
            return a
        v = a.view()
        v.flags.writeable = False
        return v

    if isinstance(x, im.ImageSet):
        return dataclasses.replace(x, **{f.name: frozen(getattr(x, f.name)) for f in dataclasses.fields(x)})
    if isinstance(x, PoseResult):
        def view(v):
            if v is None:
                return None
            feats = [dataclasses.replace(f, points=frozen(f.points)) for f in v.features]
            return dataclasses.replace(v, R_cw=frozen(v.R_cw), t_cw=frozen(v.t_cw), features=feats)

        return dataclasses.replace(x, left=view(x.left), right=view(x.right))
    return x


def span_of(trial: int, trials: int, size: int = SHARD_TRIALS) -> tuple[int, int]:
    """The trials of the shard that holds `trial`: a replay runs them as one batch, exactly as the study did
    (the engine also makes a trial independent of its batch; this keeps the replay so whatever the engine)."""
    lo = trial - trial % size
    return lo, min(lo + size, trials)


def key(job: Job) -> str:
    return json.dumps({"study": job.digest, "point": job.shard.point, "lo": job.shard.lo, "hi": job.shard.hi},
                      sort_keys=True)


def checksum(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name], dtype="<f8")
        h.update(name.encode() + b"\0" + repr(a.shape).encode() + b"\0" + a.tobytes())
    return h.hexdigest()


def path(job: Job) -> Path:
    return Path(job.folder) / "shards" / f"{job.shard.name}.npz"


def write(job: Job, arrays: dict[str, np.ndarray]) -> None:
    """The shard's file, atomically: its arrays, its key and their checksum."""
    buf = io.BytesIO()
    meta = json.dumps({"key": key(job), "checksum": checksum(arrays)})
    np.savez(buf, __meta__=np.array(meta), **arrays)
    write_atomic(path(job), buf.getvalue())


def read(job: Job) -> dict[str, np.ndarray] | None:
    """The shard's arrays if its file is there, whole, of this study and intact; else None."""
    p = path(job)
    if not p.is_file():
        return None
    try:
        with np.load(p, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        meta = json.loads(str(arrays.pop("__meta__")))
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, json.JSONDecodeError):
        return None
    if meta.get("key") != key(job) or meta.get("checksum") != checksum(arrays):
        return None
    return arrays


def run_chunk(jobs: list[Job]) -> list[tuple[Shard, dict[str, np.ndarray]]]:
    """Compute a chunk of shards in one worker call (one message each way, the scene and study pickled once; the
    trials of its consecutive points measured together, `compute_chunk`), with BLAS on one thread: a study's workers
    take one core each, and a matrix product's sums then do not depend on how many threads the machine offered (a
    table is the same on every machine)."""
    with one_blas_thread():
        return list(zip([job.shard for job in jobs], compute_chunk(jobs), strict=True))


@contextlib.contextmanager
def one_blas_thread():
    """BLAS limited to one thread inside (threadpoolctl, from `wiredsl[fast]`); as it is without threadpoolctl."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        yield
        return
    with contextlib.suppress(ImportError):  # numba's compiled measures (PGH's products) call scipy's own BLAS: it is
        import scipy.linalg.cython_blas  # noqa: F401  loaded now, so that the limit covers it (else 2 threads, other sums)
    with threadpool_limits(limits=1, user_api="blas"):
        yield
