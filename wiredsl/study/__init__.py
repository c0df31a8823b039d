"""`wiredsl study`: a declared sensitivity study run shard by shard and reported as a tidy table.

design.py (points, seeds, pipelines, Sobol' indices) -> shards.py (one (point, trials) unit of
work) -> executors.py (where shards run) -> journal.py (where finished shards are kept) -> report.py
(table, manifest) -> plots.py.
"""

from __future__ import annotations

import functools
import hashlib
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from wiredsl import __version__
from wiredsl.files import write_atomic
from wiredsl.io.emit import to_json
from wiredsl.scene import Scene, Study
from wiredsl.study import design, journal, report, shards
from wiredsl.study.executors import EXECUTORS, execute

__all__ = ["EXECUTORS", "digest", "jobs", "run_study"]


def digest(scene: Scene, study: Study, plugins: list[dict] | None = None) -> str:
    """Identity of a study's results: the scene (less its file name and studies), the study, the tool, and each
    installed plug-in it uses (`plugins_used`: package, version and a hash of its files)."""
    body = {"scene": scene.model_dump(mode="json", exclude={"source", "studies"}),
            "study": study.model_dump(mode="json"), "wiredsl": __version__,
            "plugins": plugins if plugins is not None else plugins_used(scene, study)}
    if not body["plugins"]:
        del body["plugins"]  # (a study without plug-ins keeps the digest it always had)
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def plugins_used(scene: Scene, study: Study) -> list[dict]:
    """The installed plug-ins a study runs (its pipeline's and factors' effects, its measures), each as
    `wiredsl.plugins.fingerprint` gives it (kind, name, package, version, sha256 of its files)."""
    from wiredsl.effects import BUILTIN as EFFECTS
    from wiredsl.effects import REGISTRY as effects
    from wiredsl.measures import BUILTIN as MEASURES
    from wiredsl.measures import REGISTRY as measures
    from wiredsl.plugins import fingerprint

    base = scene.pipeline(study.pipeline) if study.pipeline else None
    names = [s.effect for s in (base.stages if base else [])] + [f.stage for f in study.factors
                                                                 if not f.stage.startswith("camera.")
                                                                 and f.stage not in design.SCENE_FACTORS]
    used = [fingerprint("effect", n, effects) for n in dict.fromkeys(names) if n not in EFFECTS]
    return used + [fingerprint("measure", m.name, measures)
                   for m in {m.name: m for m in study.measures}.values() if m.name not in MEASURES]


def engines(scene: Scene, study: Study, X: np.ndarray) -> dict[str, str]:
    """The engine each stage of the study's pipeline runs on (a study's runs use `--engine auto`)."""
    from wiredsl.effects import REGISTRY as effects
    from wiredsl.montecarlo import stage_engines

    stages = design.pipeline_at(scene, study, X[0]).stages if len(X) else []
    return stage_engines([effects[s.effect] for s in stages], "auto")


def jobs(scene: Scene, study: Study, folder: str | Path, registry: dict | None = None,
         shard_trials: int = shards.SHARD_TRIALS, plugins: list[dict] | None = None
         ) -> tuple[np.ndarray, list[shards.Job]]:
    """The design matrix and every shard's job, in (point, trials) order."""
    X = design.matrix(study)
    key = digest(scene, study, plugins)
    return X, [shards.Job(scene, study, key, tuple(float(v) for v in X[s.point]), s, str(folder), registry)
               for s in shards.shards(len(X), study.trials, shard_trials)]


class Progress:
    """Points done, trials/s and the estimated time left, on stderr at most once a second."""

    def __init__(self, total: list[shards.Job], echo: Callable[[str], None] | None):
        self.echo = echo
        self.left = dict.fromkeys((j.shard.point for j in total), 0)  # shards still to run, per point
        self.todo_trials = 0
        self.points = len(self.left)
        self.started = time.perf_counter()
        self.last = 0.0
        self.trials = 0
        self.first: tuple[float, int] | None = None  # (time, trials) at the first shard: the rate is from there

    def pending(self, job: shards.Job) -> None:
        self.left[job.shard.point] += 1
        self.todo_trials += job.shard.hi - job.shard.lo

    def __call__(self, shard: shards.Shard, trials: int) -> None:
        self.left[shard.point] -= 1
        self.trials += trials
        now = time.perf_counter()
        if self.echo is not None and (now - self.last >= 1.0 or self.trials == self.todo_trials):
            self.last = now
            done = sum(v == 0 for v in self.left.values())
            head = f"study: {done}/{self.points} points, {self.trials}/{self.todo_trials} trials"
            if self.first is None:  # the first shard carries the start-up (workers, compiling): no rate from it
                self.first = (now, self.trials)
                if self.trials < self.todo_trials:
                    self.echo(f"{head}, measuring the rate")
                    return
            t0, n0 = self.first
            rate = (self.trials - n0) / (now - t0) if now > t0 and self.trials > n0 else \
                self.trials / max(now - self.started, 1e-9)
            eta = (self.todo_trials - self.trials) / rate if rate > 0 else float("inf")
            shown = f"{rate:,.0f}" if rate >= 10 else f"{rate:.2g}"  # a slow study's rate is not "0"
            self.echo(f"{head}, {shown} trials/s, ETA {eta:,.0f} s")


def _stored(all_jobs: list[shards.Job], folder: Path) -> dict[str, dict[str, np.ndarray]]:
    """The study's shards already done: those its journals hold whole, and the shard files an earlier
    version wrote (one file a shard; read, never written any more)."""
    stored = journal.replay(folder, {shards.key(j) for j in all_jobs})
    if any((folder / "shards").glob("*.npz")):
        for j in all_jobs:
            if shards.key(j) not in stored and (arrays := shards.read(j)) is not None:
                stored[shards.key(j)] = arrays
    return stored


def run_study(scene: Scene, study: Study, folder: str | Path, executor: str = "processes", workers: int | None = None,
              scheduler: str | None = None, registry: dict | None = None, echo: Callable[[str], None] | None = None,
              shard_trials: int = shards.SHARD_TRIALS, limit: int | None = None, fresh: bool = False,
              program=None) -> report.StudyTable | None:
    """Run what is not yet done of a study into `folder`, then write table.csv, table.json and
    manifest.json there. `limit` stops after that many new shards (no table): an interrupted run. `fresh`
    recomputes every shard, whatever is there. `program` (the compiled program) places W129 in the file."""
    from wiredsl.io import emit
    from wiredsl.language.compile_study import measure_registry

    folder = Path(folder)
    if registry is None:  # resolved here, and sent to the workers with each job
        registry = {m.name: measure_registry()[m.name] for m in study.measures}
    for stale in (folder / "shards").glob(".*.tmp"):  # a shard being written when a run was killed
        stale.unlink(missing_ok=True)
    used = plugins_used(scene, study)
    X, all_jobs = jobs(scene, study, folder, registry, shard_trials, used)
    if fresh:  # what an earlier run stored is set aside whole: its journals and any shard files
        for old in [*journal.files(folder), *(folder / "shards").glob("*.npz")]:
            old.unlink(missing_ok=True)
    stored = _stored(all_jobs, folder)
    todo = [j for j in all_jobs if shards.key(j) not in stored]
    record = folder / PLUGINS_RECORD  # written before any shard, so that an interrupted run's are known too
    changed = plugins_changed(record if record.is_file() else folder / "manifest.json", used)
    if echo is not None and changed and len(todo) > 0:
        echo(f"study {study.name}: plug-ins changed since the last run ({changed}): their shards are recomputed")
    if todo and (used or record.is_file()):
        write_atomic(record, json.dumps({"plugins": used}, indent=1) + "\n")
    forced = numpy_forced(scene, study, X)

    @functools.cache
    def chosen():  # the one visibility of every point (shards.visibility), decided once
        from wiredsl.engine.world import build_world

        return shards.visibility(study, scene, build_world(scene))

    if echo is not None and forced and todo:
        echo(forced)
    progress = Progress(all_jobs, echo)
    if limit is not None:
        todo = todo[:limit]
    for j in todo:
        progress.pending(j)
    if echo is not None:
        echo(f"study {study.name}: {len(X)} points x {study.trials} trials in {len(all_jobs)} shards, "
             f"{len(all_jobs) - len(todo)} done before; executor {executor}")
        if todo:  # the one visibility of every point (shards.visibility), when it keeps hidden lines
            choice = chosen()
            if choice.warning is not None:
                from wiredsl.run import w129_span

                echo(f"{w129_span(program, scene)}: warning[W129]: {choice.warning}")
    if todo:
        with journal.Writer(folder) as out:
            def finished(job: shards.Job, arrays: dict[str, np.ndarray]) -> None:
                out.append(shards.key(job), arrays)
                stored[shards.key(job)] = arrays
                progress(job.shard, job.shard.hi - job.shard.lo)

            execute(todo, executor, finished, workers, scheduler)
    if limit is not None:
        return None
    per_point: list[dict[str, list[np.ndarray]]] = [{} for _ in range(len(X))]
    for j in all_jobs:
        arrays = stored.get(shards.key(j))
        if arrays is None:
            raise RuntimeError(f"shard {j.shard.name} is missing after its run")
        for name, V in arrays.items():
            per_point[j.shard.point].setdefault(name, []).append(V)
    measures = {m.name: registry[m.name] for m in study.measures}
    order = [f"{name}.{s}" for name, m in measures.items() for s in m.statistics]
    weights = {f"{name}.{s}": f"{name}.{w}" for name, m in measures.items()
               for s, w in (getattr(m, "weights", None) or {}).items()}
    merged = [{k: np.concatenate(p[k], axis=1) for k in order if k in p} for p in per_point]
    rows = report.rows(study, X, merged, weights)
    ref = emit.scene_ref(scene)
    table = report.StudyTable(tool_version=__version__, scene=ref, study=study.name, design=study.design,
                              factors=[f.label for f in study.factors], seed=study.seed, trials=study.trials,
                              rows=rows, sobol=report.sobol(study, rows))
    write_atomic(folder / "table.csv", report.to_csv(table))
    write_atomic(folder / "table.json", to_json(table))
    if table.sobol:
        write_atomic(folder / "sobol.csv", report.sobol_csv(table))
    write_atomic(folder / "manifest.json", to_json(report.manifest(ref, study, all_jobs[0].digest, X, shard_trials,
                                                                   used, engines(scene, study, X),
                                                                   chosen().mode)))
    return table


PLUGINS_RECORD = ".plugins.json"  # the plug-ins of the last run that computed shards in a study's folder


def plugins_changed(manifest: Path, used: list[dict]) -> str | None:
    """How the plug-ins of a study differ from those a record of its last run lists (its `.plugins.json`, or its
    manifest): "count: wdplug 0.3 -> 0.4", "count: wdplug 0.3, its files changed"; None when the same or unknown."""
    try:
        before = {(p["kind"], p["name"]): p for p in json.loads(manifest.read_text(encoding="utf-8"))["plugins"]}
    except (OSError, ValueError, KeyError, TypeError):
        return None
    now = {(p["kind"], p["name"]): p for p in used}
    said = []
    for key in sorted(set(before) | set(now)):
        a, b = before.get(key), now.get(key)
        if a == b:
            continue
        if a is None or b is None:
            said.append(f"{key[0]} '{key[1]}' {'added' if a is None else 'no longer used'}")
        elif (a.get("package"), a.get("version")) != (b["package"], b["version"]):
            said.append(f"{b['name']}: {a.get('package')} {a.get('version')} -> {b['package']} {b['version']}")
        else:
            said.append(f"{b['name']}: {b['package']} {b['version']}, its files changed")
    return "; ".join(said) or None


def numpy_forced(scene: Scene, study: Study, X: np.ndarray) -> str | None:
    """The line saying that a stage without a compiled kernel (and those after it) run on numpy, or None."""
    from wiredsl.effects import REGISTRY as effects
    from wiredsl.run import numpy_forced_line

    stages = design.pipeline_at(scene, study, X[0]).stages if len(X) else []
    return numpy_forced_line([effects[s.effect] for s in stages], "auto", "")  # a study has no --engine
