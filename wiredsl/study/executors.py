"""Where shards run: in this process, in local processes on every core, or on a Dask cluster.

Every executor calls the same spawn-safe function, `shards.run_job`, which writes its shard's
file; the caller hears of each finished shard (in whatever order) and reads the files at the end.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Sequence

from wiredsl.study.shards import Job, Shard, run_job

EXECUTORS = ("processes", "inprocess", "dask")
Done = Callable[[Shard, int], None]


def execute(jobs: Sequence[Job], executor: str, done: Done, workers: int | None = None,
            scheduler: str | None = None) -> None:
    """Run every job, calling done(shard, trials) as each finishes."""
    if not jobs:
        return
    with _terminable():
        _execute(jobs, executor, done, workers, scheduler)


@contextlib.contextmanager
def _terminable():
    """SIGTERM unwinds like Ctrl-C: workers are shut down and the finished shards stay (exit status 143)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield
        return

    def stop(signum, frame):
        exc = SystemExit(128 + signum)
        exc.signal_unwinding = True  # not a plug-in's SystemExit (wiredsl.plugins.call lets it through)
        raise exc

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _execute(jobs: Sequence[Job], executor: str, done: Done, workers: int | None, scheduler: str | None) -> None:
    if executor == "inprocess":
        for job in jobs:
            done(*run_job(job))
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
        ctx.set_forkserver_preload(["wiredsl.study.shards", "wiredsl.measures"])  # missing ones are skipped
    with ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=ctx) as pool:
        futures = [pool.submit(run_job, job) for job in jobs]
        try:
            for f in as_completed(futures):
                done(*f.result())
        except BaseException:  # the shards running finish and are written; the rest are not started
            pool.shutdown(wait=True, cancel_futures=True)
            raise


def _dask(jobs: Sequence[Job], done: Done, scheduler: str | None) -> None:
    try:
        from distributed import Client, as_completed
    except ImportError as exc:
        raise RuntimeError("the dask executor needs Dask distributed: pip install 'wiredsl[dask]'") from exc
    if not scheduler:
        raise ValueError("the dask executor needs --scheduler ADDRESS (e.g. tcp://host:8786)")
    with Client(scheduler) as client:
        futures = client.map(run_job, list(jobs), pure=False)
        try:
            for f in as_completed(futures):
                done(*f.result())
        except BaseException:
            client.cancel(futures)
            raise
