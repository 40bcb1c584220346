"""The campaign engine: many independent runs, each kept in a record the moment it ends.

A :class:`Job` is one run: a key, a folder inside the campaign's and a function of that folder
that returns the run's result (a JSON-able dict). :meth:`Campaign.run` skips every job whose
folder already holds a finished record (``run_record.json`` with status ``ok``), hands the others
to an executor and writes each record as its result arrives, so an interrupted campaign started
again redoes only what had not finished. A run that raises is recorded as ``failed`` with its
error (and its traceback in ``error.txt`` beside it); a run whose worker died more often than the
cluster allows is recorded as ``lost``. Neither stops the others.

Executors: :class:`SerialExecutor` runs the jobs one after another in this process (a baseline,
and where no cluster is wanted); :class:`sitl.campaign.cluster.DaskExecutor` runs them on a Dask
cluster. Both call :func:`execute` for a job, and both report ``started`` (to count the running
jobs) and ``done`` to the campaign.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import time
import traceback
from collections.abc import Callable, Mapping
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

__all__ = ["Job", "Campaign", "CampaignResult", "SerialExecutor", "execute", "RECORD_FILE", "STATUSES", "TOPIC",
           "lost_payload"]

log = logging.getLogger(__name__)

RECORD_FILE = "run_record.json"
#: the Dask event topic on which a worker announces that a run started
TOPIC = "sitl-campaign"
#: ``ok``: the run finished (a crash of the flight is a metric, not a failure); ``failed``: it
#: raised; ``lost``: its worker died more often than the cluster's bound on retries
STATUSES = ("ok", "failed", "lost")


@dataclass(frozen=True)
class Job:
    """One run: ``fn(out_dir, *args)`` returns its result; ``folder`` is relative to the
    campaign's; ``columns`` are its key columns in the results table."""

    key: str
    folder: Path
    fn: Callable[..., dict]
    args: tuple = ()
    columns: Mapping[str, Any] = field(default_factory=dict)


def _worker_name() -> str:
    """The Dask worker running this (its name when it has one, else its address), or the host."""
    try:
        from distributed import get_worker

        worker = get_worker()
    except (ImportError, ValueError):
        return f"{socket.gethostname()}:{os.getpid()}"
    name = str(worker.name)
    return name if name and name != worker.address else worker.address


def execute(job: Job, root: str, announce: Callable[[dict], None] | None = None) -> dict:
    """Run ``job`` into ``root/job.folder`` and return its payload: ``key``, ``status`` (``ok``
    or ``failed``), ``result``, ``error``, ``wall_s``, ``worker``, ``host``, ``pid`` and
    ``attempt`` (an id of this attempt). ``announce`` is told when the run starts (with the
    same ``attempt``) (default: the Dask worker's event log, topic
    :data:`TOPIC`, when running on one)."""
    worker = _worker_name()
    attempt = f"{socket.gethostname()}:{os.getpid()}:{time.time_ns()}"
    start = {"event": "started", "key": job.key, "worker": worker, "attempt": attempt}
    if announce is not None:
        announce(start)
    else:
        try:
            from distributed import get_worker

            get_worker().log_event(TOPIC, start)
        except (ImportError, ValueError):
            pass
    out = Path(root) / job.folder
    out.mkdir(parents=True, exist_ok=True)
    (out / "error.txt").unlink(missing_ok=True)
    t0 = time.perf_counter()
    status, result, error = "ok", None, None
    try:
        result = job.fn(out, *job.args)
    except Exception as exc:  # the run's failure is its record's, not the campaign's
        status, error = "failed", f"{type(exc).__name__}: {exc}"
        (out / "error.txt").write_text(traceback.format_exc())
    return {"key": job.key, "status": status, "result": result, "error": error, "wall_s": time.perf_counter() - t0,
            "worker": worker, "host": socket.gethostname(), "pid": os.getpid(), "attempt": attempt}


def lost_payload(job: Job, reason: str, status: str = "lost") -> dict:
    """The payload of a run the cluster could not fly: its worker died more often than allowed
    (``lost``), or the task itself could not run (``failed``, e.g. the package missing there)."""
    return {"key": job.key, "status": status, "result": None, "error": reason, "wall_s": None, "worker": None,
            "host": None, "pid": None, "attempt": None}


class SerialExecutor:
    """The jobs one after another in this process."""

    name = "serial"

    def run(self, jobs: list[Job], worker_root: str, started: Callable[[dict], None],
            done: Callable[[Job, dict, int], None]) -> None:
        for job in jobs:
            done(job, execute(job, worker_root, started), 1)


@dataclass
class CampaignResult:
    """What a campaign run did: every job's record (in the jobs' order; ``None`` for a job not
    finished, after an interrupt), and how many were ``skipped`` (finished before) and ``ran``."""

    records: list[dict | None]
    skipped: int
    ran: int
    wall_s: float

    def counts(self) -> dict[str, int]:
        out = {s: 0 for s in (*STATUSES, "not run")}
        for r in self.records:
            out[r["status"] if r else "not run"] += 1
        return out


class Campaign:
    """The jobs of one campaign folder ``root``. ``worker_root``: where the workers write the run
    folders (default ``root``; another path for workers on machines that do not share it)."""

    def __init__(self, root: Path, jobs: list[Job], worker_root: str | None = None):
        keys = [j.key for j in jobs]
        if len(set(keys)) != len(keys):
            raise ValueError("two jobs have the same key")
        folders = [j.folder for j in jobs]
        if len(set(folders)) != len(folders):
            raise ValueError("two jobs have the same folder")
        self.root = Path(root)
        self.jobs = jobs
        self.worker_root = str(worker_root or self.root.resolve())
        #: the records known so far by key: those finished before, then each as it is written by :meth:`run`
        self.records: dict[str, dict] = {}

    def record_path(self, job: Job) -> Path:
        return self.root / job.folder / RECORD_FILE

    def load_record(self, job: Job) -> dict | None:
        """The job's record on disk, if it is this job's (same key) and readable."""
        try:
            rec = json.loads(self.record_path(job).read_text())
        except (OSError, ValueError):
            return None
        return rec if isinstance(rec, dict) and rec.get("key") == job.key and rec.get("status") in STATUSES else None

    def finished(self) -> dict[str, dict]:
        """The records of the jobs that finished before (status ``ok``), by key."""
        out = {}
        for job in self.jobs:
            rec = self.load_record(job)
            if rec is not None and rec["status"] == "ok":
                out[job.key] = rec
        return out

    def _write_record(self, job: Job, payload: dict, attempts: int) -> dict:
        rec = {"key": job.key, "columns": dict(job.columns), "status": payload["status"], "attempts": attempts,
               "error": payload["error"], "wall_s": payload["wall_s"], "worker": payload["worker"],
               "host": payload["host"], "finished_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
               "result": payload["result"]}
        text = json.dumps(rec, indent=1, default=_jsonable)
        path = self.record_path(job)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(text)
        os.replace(tmp, path)
        return json.loads(text)  # what a resumed campaign will read: the same numbers

    def run(self, open_executor: Callable[[], AbstractContextManager], *,
            on_record: Callable[[dict], None] | None = None,
            progress: Callable[[dict], None] | None = None) -> CampaignResult:
        """Run the jobs not finished before on the executor ``open_executor()`` gives (a context
        manager, opened only when a job is left to run). ``on_record(record)`` after each
        record is written; ``progress(counts)`` with ``done``, ``running``, ``failed``, ``lost``,
        ``total`` whenever one changes. A ``KeyboardInterrupt`` stops the executor and propagates;
        the records written so far stay."""
        t0 = time.perf_counter()
        self.records = records = self.finished()
        skipped = len(records)
        todo = [j for j in self.jobs if j.key not in records]
        running: dict[str, str] = {}  # worker -> the run it started last (its start says the one before ended)
        counts = {"done": skipped, "running": 0, "failed": 0, "lost": 0, "total": len(self.jobs)}

        def tell():
            counts["running"] = len(running)
            if progress is not None:
                progress(dict(counts))

        def started(event: dict) -> None:
            if event.get("key") not in records:
                running[str(event.get("worker"))] = event.get("key")
                tell()

        def done(job: Job, payload: dict, attempts: int) -> None:
            rec = self._write_record(job, payload, attempts)
            records[job.key] = rec
            for worker in [w for w, key in running.items() if key == job.key]:
                del running[worker]
            counts["done"] += 1
            if rec["status"] != "ok":
                counts[rec["status"]] += 1
                log.warning("%s: %s (%s)", job.key, rec["status"], rec["error"])
            if on_record is not None:
                on_record(rec)
            tell()

        tell()
        if todo:
            with open_executor() as executor:
                executor.run(todo, self.worker_root, started, done)
        return CampaignResult(self.in_order(), skipped, len(records) - skipped, time.perf_counter() - t0)

    def in_order(self) -> list[dict | None]:
        """The known records in the jobs' order (``None``: not finished)."""
        return [self.records.get(j.key) for j in self.jobs]


def _jsonable(obj):
    """numpy scalars and arrays in a result, as JSON numbers and lists."""
    if hasattr(obj, "tolist"):
        return obj.tolist()
    raise TypeError(f"not JSON-able: {type(obj).__name__}")
