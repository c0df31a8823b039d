"""Where shards run: in this process, in local processes on every core, or on a Dask cluster.

Every executor calls the same spawn-safe function, `shards.run_chunk`, on chunks of consecutive shards
(a point's shards together, so a worker sets each point up once); it returns the shards' arrays, and the
caller hears of each finished shard (in whatever order) with its arrays, and journals them. A worker
process imports, loads the kernel and prepares the measures once per study (`shards._setup` keeps them),
not once per shard or chunk.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Sequence

import numpy as np

from wiredsl import check_stop, clear_stops, exception_chain, install_hint, pending_stop, signal_stop
from wiredsl.study.shards import Job, run_chunk, warm_kernel

EXECUTORS = ("processes", "inprocess", "dask")
Done = Callable[[Job, dict[str, np.ndarray]], None]
CHUNKS_PER_WORKER = 8  # chunks a worker gets, at least: the last chunks finish close together
CHUNK_TRIALS = 1024  # trials a chunk holds, at most: results come back (and are journalled) as they go


def chunks(jobs: Sequence[Job], workers: int) -> list[list[Job]]:
    """Consecutive jobs grouped into chunks of about equal trials, CHUNKS_PER_WORKER a worker or more."""
    total = sum(j.shard.hi - j.shard.lo for j in jobs)
    target = max(1, min(CHUNK_TRIALS, -(-total // (max(workers, 1) * CHUNKS_PER_WORKER))))
    out: list[list[Job]] = []
    size = target
    for job in jobs:
        if size >= target:
            out.append([])
            size = 0
        out[-1].append(job)
        size += job.shard.hi - job.shard.lo
    return out


def execute(jobs: Sequence[Job], executor: str, done: Done, workers: int | None = None,
            scheduler: str | None = None) -> None:
    """Run every job, calling done(job, arrays) as each finishes."""
    if not jobs:
        return
    with _terminable() as stopping:
        def journalled(job: Job, arrays: dict[str, np.ndarray]) -> None:
            done(job, arrays)
            stopping()  # a SIGTERM that compiled code swallowed stops the study here, between shards

        _execute(jobs, executor, journalled, workers, scheduler)
        stopping()


@contextlib.contextmanager
def _terminable():
    """SIGTERM unwinds like Ctrl-C: workers are shut down and the finished shards stay (exit status 143).

    The handler raises where the signal lands. Landing inside a callback from compiled code (numba calls back
    into Python to unpickle), the exit comes out wrapped in a SystemError, or not at all if the callback's
    caller drops it; so the context re-raises the SystemExit found in the chain, and yields a check that
    raises it between shards if it went missing."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield check_stop  # the command line's handler (cli_base) notes its signal the same way
        return

    def stop(signum, frame):
        exc = SystemExit(128 + signum)
        exc.signal_unwinding = True  # not a plug-in's SystemExit (wiredsl.plugins.call lets it through)
        raise signal_stop(exc)

    clear_stops()
    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield check_stop
    except Exception as exc:  # the SystemExit wrapped by the compiled code it landed in
        received = pending_stop()
        if received is not None and any(e is received for e in exception_chain(exc)):
            raise received from None
        raise
    finally:
        signal.signal(signal.SIGTERM, previous)
        clear_stops()


def _execute(jobs: Sequence[Job], executor: str, done: Done, workers: int | None, scheduler: str | None) -> None:
    if executor == "inprocess":
        for chunk in chunks(jobs, 1):
            for job, (_, arrays) in zip(chunk, run_chunk(chunk), strict=True):
                done(job, arrays)
    elif executor == "processes":
        _processes(jobs, done, workers or os.cpu_count() or 1)
    elif executor == "dask":
        _dask(jobs, done, scheduler)
    else:
        raise ValueError(f"unknown executor {executor!r} (one of {', '.join(EXECUTORS)})")


def _processes(jobs: Sequence[Job], done: Done, workers: int) -> None:
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    # fork would copy the parent's threads and locks; a fork server is started clean, imports the engine once
    # and forks every worker from it, ready (spawn would import it again in each worker)
    method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
    ctx = multiprocessing.get_context(method)
    if method == "forkserver":
        # numba and the compiled measures too (skipped without the `fast` extra): imported once, not per worker
        ctx.set_forkserver_preload(["wiredsl.study.shards", "wiredsl.measures", "threadpoolctl", "numba",
                                    "scipy.linalg", "wiredsl.engine.kernel", "wiredsl.measures.pgh_kernel",
                                    "wiredsl.measures.stereo3d_kernel"])  # missing ones are skipped
    warm_kernel(jobs[0])
    parts = chunks(jobs, workers)
    with ProcessPoolExecutor(max_workers=min(workers, len(parts)), mp_context=ctx) as pool:
        futures = {pool.submit(run_chunk, chunk): chunk for chunk in parts}
        try:
            for f in as_completed(futures):
                for job, (_, arrays) in zip(futures[f], f.result(), strict=True):
                    done(job, arrays)
        except BaseException:  # the shards running finish and are written; the rest are not started
            pool.shutdown(wait=True, cancel_futures=True)
            raise


def _dask(jobs: Sequence[Job], done: Done, scheduler: str | None) -> None:
    try:
        from distributed import Client, as_completed
    except ImportError as exc:
        raise RuntimeError(f"the dask executor needs Dask distributed: {install_hint('dask')}") from exc
    if not scheduler:
        raise ValueError("the dask executor needs --scheduler ADDRESS (e.g. tcp://host:8786)")
    with Client(scheduler) as client:
        n = sum(w.get("nthreads", 1) for w in client.scheduler_info().get("workers", {}).values()) or 1
        parts = chunks(jobs, n)
        futures = client.map(run_chunk, parts, pure=False)
        chunk_of = {f.key: chunk for f, chunk in zip(futures, parts, strict=True)}
        try:
            for f in as_completed(futures):
                for job, (_, arrays) in zip(chunk_of[f.key], f.result(), strict=True):
                    done(job, arrays)
        except BaseException:
            client.cancel(futures)
            raise
