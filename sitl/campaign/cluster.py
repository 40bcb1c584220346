"""Campaign runs on Dask ``distributed``: a local cluster, or one started elsewhere.

:func:`connect` gives a client: ``scheduler=None`` starts a :class:`distributed.LocalCluster` of
``workers`` processes with one thread each (a flight is single-threaded; one per core by
default), otherwise it joins the scheduler at ``tcp://HOST:PORT`` whose workers have this package
installed. :class:`DaskExecutor` submits a campaign's jobs there, one task per run.

A worker that dies (killed, out of memory, its machine gone) loses the run it was flying; the
scheduler gives that run to another worker, up to ``distributed.scheduler.allowed-failures``
deaths per run (the local cluster takes ``retries``; a scheduler started elsewhere reads it from
its own Dask configuration, e.g. ``DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES=2``). A run past
that bound is recorded ``lost``. The local cluster sends a worker only the run it flies
(``distributed.scheduler.worker-saturation`` 1.0; give a scheduler of your own the same, else a
worker's death also counts against the runs queued on it). Each attempt announces itself on the
scheduler's event log when it starts; a run's record counts them (``attempts``).
"""

from __future__ import annotations

import hashlib
import logging
import os
from collections.abc import Callable
from contextlib import contextmanager
from typing import Iterator

from .engine import TOPIC, Job, execute, lost_payload

__all__ = ["TOPIC", "DaskExecutor", "connect", "open_executor", "default_workers", "INSTALL_HINT"]

INSTALL_HINT = "install it with pip install 'aerial-skeleton-stack[campaign]' (part of [sim])"


def default_workers() -> int:
    """One worker per core this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


@contextmanager
def connect(scheduler: str | None = None, workers: int | None = None, retries: int = 2) -> Iterator:
    """A Dask client: on a new local cluster of ``workers`` single-threaded processes (``None``:
    :func:`default_workers`) that gives a run whose worker died to another up to ``retries``
    times, or on the scheduler at ``scheduler`` (``tcp://HOST:PORT``). Closes what it started."""
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError as exc:
        raise ImportError(f"Dask distributed is missing; {INSTALL_HINT}") from exc
    if retries < 0:
        raise ValueError(f"retries must be >= 0, got {retries}")
    for name in ("distributed", "bokeh", "tornado"):  # the cluster's own chatter: warnings and errors only
        logging.getLogger(name).setLevel(max(logging.WARNING, logging.getLogger(name).level))
    if scheduler is not None:
        with Client(scheduler, timeout=30) as client:
            yield client
        return
    n = workers or default_workers()
    if n < 1:
        raise ValueError(f"workers must be >= 1, got {n}")
    # worker-saturation 1: a worker holds only the run it flies, so its death costs no other run an attempt
    with dask.config.set({"distributed.scheduler.allowed-failures": retries,
                          "distributed.scheduler.worker-saturation": 1.0}):
        with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                          silence_logs=logging.ERROR) as cluster, Client(cluster) as client:
            yield client


class DaskExecutor:
    """A campaign's jobs as Dask tasks on ``client``'s cluster."""

    name = "dask"

    def __init__(self, client):
        self.client = client

    def run(self, jobs: list[Job], worker_root: str, started: Callable[[dict], None],
            done: Callable[[Job, dict, int], None]) -> None:
        from distributed import KilledWorker, as_completed

        attempts: dict[str, set[str]] = {}

        def on_event(event) -> None:
            msg = event[1] if isinstance(event, tuple) and len(event) == 2 else event
            if isinstance(msg, dict) and msg.get("event") == "started":
                attempts.setdefault(msg.get("key"), set()).add(msg.get("attempt"))
                started(msg)

        self.client.subscribe_topic(TOPIC, on_event)
        futures = {}
        for job in jobs:
            key = "sitl-run-" + hashlib.sha256(f"{worker_root}|{job.key}".encode()).hexdigest()[:24]
            futures[self.client.submit(execute, job, worker_root, key=key, pure=False, retries=0)] = job
        try:
            for future in as_completed(futures):
                job = futures[future]
                seen = attempts.get(job.key, set())
                if future.status == "finished":
                    payload = future.result()
                    done(job, payload, len(seen | {payload["attempt"]}))
                elif future.status == "error":  # not the run's own error (execute records those)
                    exc = future.exception()
                    if isinstance(exc, KeyboardInterrupt):  # Ctrl-C reached the workers too: not the run's
                        raise KeyboardInterrupt
                    reason = f"{type(exc).__name__}: {exc}"
                    if isinstance(exc, KilledWorker):  # every allowed death was an attempt, announced or not
                        done(job, lost_payload(job, reason), max(len(seen), exc.allowed_failures + 1))
                    else:  # e.g. the package missing on the worker
                        done(job, lost_payload(job, reason, "failed"), len(seen))
                future.release()
        finally:
            for future in futures:
                if not future.done():
                    future.cancel()
            self.client.unsubscribe_topic(TOPIC)


@contextmanager
def open_executor(scheduler: str | None = None, workers: int | None = None, serial: bool = False,
                  retries: int = 2) -> Iterator:
    """The executor a command line asks for: :class:`~sitl.campaign.engine.SerialExecutor` when
    ``serial``, else a :class:`DaskExecutor` on :func:`connect`'s client."""
    if serial:
        from .engine import SerialExecutor

        yield SerialExecutor()
        return
    with connect(scheduler, workers, retries) as client:
        yield DaskExecutor(client)
