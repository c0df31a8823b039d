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
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from wiredsl.engine.montecarlo import Run
from wiredsl.engine.simulate import Options
from wiredsl.engine.world import World, build_world
from wiredsl.io.files import write_atomic
from wiredsl.measures import BUILTIN, REGISTRY
from wiredsl.plugins import call, failure, params_of
from wiredsl.run import start
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


def options(study: Study) -> Options:
    return Options(poses=tuple(study.poses) if study.poses is not None else None)


def point_run(scene: Scene, world: World, study: Study, point: int, values, opts: Options | None = None,
              base: Run | None = None) -> Run:
    """The Run of one design point: its pipeline substituted, every draw keyed by the point's index too.

    `base` (a run of the same scene and options) lends its ideal projection and visibility, which no
    pipeline parameter changes.
    """
    values = np.asarray(values, dtype=float)
    lend = None if design.varies_scene(study) else base  # a point that varies the cameras projects its own
    return start(design.scene_at(scene, study, values), design.pipeline_at(scene, study, values), seed=study.seed,
                 options=opts or options(study), world=world, point=point, base=lend)


_WORKER: dict = {}  # per process: digest -> (world, base run, prepared); (digest, point) -> (run, prepared)


def compute(job: Job) -> dict[str, np.ndarray]:
    """One shard's per-trial values: {"measure.statistic": (n_poses, n_trials)}."""
    from wiredsl.language.compile_study import measure_registry

    registry = job.registry if job.registry is not None else measure_registry()
    study, scene = job.study, job.scene
    if job.digest not in _WORKER:
        world = build_world(scene)
        _WORKER.clear()  # one study at a time per worker
        base = start(scene, None, options=options(study), world=world)
        base.ideal()
        # a measure's reference data come from the ideal scene, which no pipeline parameter changes:
        # prepared once per study (with the run of no stages), unless the study varies the cameras
        _WORKER[job.digest] = (world, base, None if design.varies_scene(study) else _prepare(study, registry, base))
    world, base, prepared = _WORKER[job.digest]
    key = (job.digest, job.shard.point)
    if key not in _WORKER:
        for old in [k for k in _WORKER if isinstance(k, tuple)]:  # a point's shards come together: keep one
            del _WORKER[old]
        run = point_run(scene, world, study, job.shard.point, job.values, base=base)
        _WORKER[key] = (run, prepared if prepared is not None else _prepare(study, registry, run))
    run, prepared = _WORKER[key]
    return measure_batches(run, prepared, list(range(job.shard.lo, job.shard.hi)))


def _prepare(study: Study, registry: dict, run: Run) -> list:
    out = []
    for m in study.measures:
        measure = registry[m.name]
        params = params_of("measure", measure, REGISTRY, m.params)
        out.append((measure, params, _guarded(measure, "prepare()", measure.prepare, params, run,
                                              where=f"design point {run.point}" if run.point is not None else None)))
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
    parts: dict[str, list[list[np.ndarray]]] = {}
    for batch, batch_out in run.batches(trials):
        for j, (result, disturbed, _views) in enumerate(batch_out):
            pose, sets = read_only(result), {side: read_only(v) for side, v in disturbed.items()}
            for measure, params, prep in prepared:
                where = f"pose {result.index}, trials {batch[0]}..{batch[-1]}" + (
                    f", design point {run.point}" if run.point is not None else "")
                got = _guarded(measure, "measure()", measure.measure, params, prep, pose, sets, len(batch),
                               where=where)
                values = statistics_of(measure, got, len(batch))
                if isinstance(values, str):
                    raise failure("measure", measure.name, REGISTRY, values, where)
                for stat, v in values.items():
                    rows = parts.setdefault(f"{measure.name}.{stat}", [])
                    if len(rows) <= j:
                        rows.append([])
                    rows[j].append(v)
    return {k: np.stack([np.concatenate(r) for r in rows]) for k, rows in parts.items()}


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


def run_job(job: Job) -> tuple[Shard, dict[str, np.ndarray]]:
    """Compute one shard (the function every executor calls, through `run_chunk`); returns it and its arrays,
    which the study's process appends to its journal."""
    return job.shard, compute(job)


def run_chunk(jobs: list[Job]) -> list[tuple[Shard, dict[str, np.ndarray]]]:
    """Compute a chunk of shards in one worker call (one message each way, the scene and study pickled once),
    with BLAS on one thread: a study's workers take one core each, and a matrix product's sums then do not
    depend on how many threads the machine offered (a table is the same on every machine)."""
    with one_blas_thread():
        return [run_job(job) for job in jobs]


@contextlib.contextmanager
def one_blas_thread():
    """BLAS limited to one thread inside (threadpoolctl, from `wiredsl[fast]`); as it is without threadpoolctl."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        yield
        return
    with threadpool_limits(limits=1, user_api="blas"):
        yield
