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
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from wiredsl.engine.montecarlo import Run
from wiredsl.engine.simulate import Options
from wiredsl.engine.world import World, build_world
from wiredsl.io.files import write_atomic
from wiredsl.measures import BUILTIN, REGISTRY
from wiredsl.plugins import failure
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
        params = measure.Params(**m.params)
        with _blamed(measure):
            out.append((measure, params, measure.prepare(params, run)))
    return out


@contextlib.contextmanager
def _blamed(measure):
    """An installed measure's exception reported as its package's error (E181); a built-in's stays a bug."""
    try:
        yield
    except Exception as exc:
        if measure.name in BUILTIN:
            raise
        raise failure("measure", measure.name, REGISTRY, f"failed: {type(exc).__name__}: {exc}") from None


def measure_batches(run: Run, prepared, trials: list[int]) -> dict[str, np.ndarray]:
    """Every measure on every pose of the given trials: {"measure.statistic": (n_poses, n_trials)}."""
    parts: dict[str, list[list[np.ndarray]]] = {}
    for batch, batch_out in run.batches(trials):
        for j, (result, disturbed, _views) in enumerate(batch_out):
            for measure, params, prep in prepared:
                with _blamed(measure):
                    got = measure.measure(params, prep, result, disturbed, len(batch))
                for stat in measure.statistics:
                    with _blamed(measure):
                        v = np.asarray(got[stat], dtype=float) if isinstance(got, dict) and stat in got else None
                    if v is None or v.shape != (len(batch),) or not np.all(np.isfinite(v)):
                        what = "nothing" if v is None else f"shape {v.shape}" if v.shape != (len(batch),) \
                            else "non-finite values"
                        raise failure("measure", measure.name, REGISTRY,
                                      f"gave {what} for statistic '{stat}' ({len(batch)} trials: one finite "
                                      "value a trial)")
                    rows = parts.setdefault(f"{measure.name}.{stat}", [])
                    if len(rows) <= j:
                        rows.append([])
                    rows[j].append(v)
    return {k: np.stack([np.concatenate(r) for r in rows]) for k, rows in parts.items()}


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
