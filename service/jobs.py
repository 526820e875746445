"""Job records in Redis and their state machine, shared by the API and the workers.

A job is a Redis hash ``prox:job:<id>``; each owner has a sorted set of job ids by creation
time, and ``prox:running`` holds the ids of running jobs for the reaper. RQ only carries the
work: each attempt is an RQ job ``<id>-<attempt>`` calling :func:`worker.tasks.run_job`.
Every transition is a compare-and-set on the record (status and attempt), so a cancelled job
or a superseded attempt can never be overwritten by a late worker, and several API replicas
can reap at once.
"""
from __future__ import annotations

import dataclasses
import json
import time
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

from redis import Redis
from redis.exceptions import WatchError
from rq import Queue
from rq.exceptions import InvalidJobOperation, NoSuchJobError
from rq.job import Job

from prox_engine.config import FitConfig, load_config

from .settings import Settings

QUEUED, RUNNING, FINISHED, FAILED, CANCELLED = "queued", "running", "finished", "failed", \
    "cancelled"
TERMINAL = (FINISHED, FAILED, CANCELLED)
_JSON_FIELDS = ("options", "recordings", "timings", "errors")
_NUMBER_FIELDS = ("attempt", "runs", "frames_total", "frames_done", "frames_failed",
                  "upload_bytes", "created_at", "started_at", "finished_at", "heartbeat_at")


@dataclass(frozen=True)
class JobOptions:
    """What the user asked for: the configuration, frames per recording, mode, reports, and
    a baseline configuration to compare with."""

    config: str = "prox"
    frames: int | None = None
    sequence: bool = False
    report: bool = True  # HTML reports with renders
    render_every: int = 1  # render every k-th frame in the reports
    model: str = "anny"  # or "smplx", from the operator's PROX_MODEL_DIR
    gender: str = "neutral"
    genders: dict[str, str] | None = None  # per recording
    hand_pca: int = 12
    baseline: str | None = None  # a configuration also fitted, for the reports' comparison
    batch: int = 1  # frames of a recording fitted together (single-frame mode)

    def fit_config(self, model_dir: Path | None, name: str | None = None) -> FitConfig:
        """The fitting configuration (``name``, default the job's) with this job's body
        model; PROX's ``body_segments/`` and VPoser's ``vposer_v1_0/`` are used when the
        operator's model folder has them."""
        extras = {name: model_dir / name if model_dir and (model_dir / name).is_dir() else None
                  for name in ("body_segments", "vposer_v1_0")}
        return dataclasses.replace(
            load_config(name or self.config, self.model), batch_size=self.batch,
            model=self.model,
            gender=self.gender,
            hand_pca=self.hand_pca, model_path=str(model_dir) if model_dir else None,
            body_segments=str(extras["body_segments"]) if extras["body_segments"] else None,
            vposer_path=str(extras["vposer_v1_0"]) if extras["vposer_v1_0"] else None)

    def gender_of(self, recording: str) -> str:
        return (self.genders or {}).get(recording, self.gender)


def _encode(fields: dict) -> dict[str, str]:
    return {k: json.dumps(v) if k in _JSON_FIELDS else ("" if v is None else str(v))
            for k, v in fields.items()}


def _decode(raw: dict[str, str]) -> dict:
    record: dict = {}
    for key, value in raw.items():
        if key in _JSON_FIELDS:
            record[key] = json.loads(value)
        elif key in _NUMBER_FIELDS:
            record[key] = float(value) if "." in value else int(value) if value else None
        else:
            record[key] = value or None
    return record


class JobStore:
    """Job records, their transitions and the queue they are worked from."""

    def __init__(self, settings: Settings, redis: Redis | None = None) -> None:
        self.settings = settings
        self.redis = redis or Redis.from_url(settings.redis_url, decode_responses=True)
        # RQ pickles its payloads, so it needs a connection that does not decode.
        self.queue = Queue(settings.queue, connection=Redis.from_url(settings.redis_url))

    @staticmethod
    def _key(job_id: str) -> str:
        return f"prox:job:{job_id}"

    @staticmethod
    def _owner_key(owner: str) -> str:
        return f"prox:owner:{owner}"

    _RUNNING = "prox:running"

    # ------------------------------------------------------------------ reading
    def get(self, job_id: str) -> dict | None:
        raw = self.redis.hgetall(self._key(job_id))
        return _decode(raw) if raw else None

    def list(self, owner: str, offset: int, limit: int) -> tuple[list[dict], int]:
        """The owner's jobs, newest first, and how many there are."""
        key = self._owner_key(owner)
        ids = self.redis.zrevrange(key, offset, offset + limit - 1)
        records = [r for r in (self.get(i) for i in ids) if r is not None]
        return records, self.redis.zcard(key)

    # ------------------------------------------------------------------ API side
    def new_id(self) -> str:
        return uuid.uuid4().hex

    def create(self, job_id: str, owner: str, options: JobOptions,
               recordings: dict[str, list[str]], upload_bytes: int) -> dict:
        """Record a validated upload (already in storage) and queue its first attempt."""
        now = time.time()
        record = {
            "id": job_id, "owner": owner, "status": QUEUED, "options": asdict(options),
            "recordings": {r: len(f) for r, f in recordings.items()},
            "frames_total": sum(len(f) for f in recordings.values()), "frames_done": 0,
            "frames_failed": 0, "stage": None, "recording": None, "error": None,
            "errors": [], "timings": {}, "attempt": 1, "runs": 0,
            "upload_bytes": upload_bytes, "created_at": now, "started_at": None,
            "finished_at": None, "heartbeat_at": None, "worker": None,
        }
        with self.redis.pipeline() as pipe:
            pipe.hset(self._key(job_id), mapping=_encode(record))
            pipe.zadd(self._owner_key(owner), {job_id: now})
            pipe.execute()
        self._enqueue(job_id, 1, record["frames_total"])
        return record

    def cancel(self, job_id: str) -> dict | None:
        """Cancel a queued or running job; a running one stops at its next stage."""
        record = self._update(job_id, lambda r: r["status"] in (QUEUED, RUNNING),
                              {"status": CANCELLED, "finished_at": time.time(),
                               "stage": None})
        if record is not None:
            self.redis.srem(self._RUNNING, job_id)
            self._cancel_rq(job_id, record["attempt"])
        return record

    def delete(self, job_id: str) -> bool:
        """Forget a finished, failed or cancelled job (its files are the caller's)."""
        record = self.get(job_id)
        if record is None or record["status"] not in TERMINAL:
            return False
        with self.redis.pipeline() as pipe:
            pipe.delete(self._key(job_id))
            pipe.zrem(self._owner_key(record["owner"]), job_id)
            pipe.execute()
        return True

    def reap(self) -> list[str]:
        """Recover running jobs whose worker stopped heart-beating, and queued ones that a
        worker took from the queue but never started; returns their ids."""
        reaped = []
        deadline = time.time() - self.settings.stale_after_s
        for job_id in self.redis.smembers(self._RUNNING):
            record = self.get(job_id)
            if record is None or record["status"] != RUNNING:
                self.redis.srem(self._RUNNING, job_id)
            elif (record["heartbeat_at"] or 0) < deadline:
                silent = time.time() - (record["heartbeat_at"] or record["created_at"])
                if self.worker_lost(job_id, record["attempt"],
                                    f"its worker stopped responding ({silent:.0f} s without "
                                    "a heartbeat)"):
                    reaped.append(job_id)
        return reaped + self._reap_taken()

    def _reap_taken(self) -> list[str]:
        """Attempts that RQ handed to a worker (its intermediate list and started registry)
        whose records are still queued after ``stale_after_s``: the worker died, or Redis
        was killed, between taking the attempt and starting it, and nothing else would
        ever run the job. Each is first marked, then retried when the mark is that old."""
        reaped = []
        taken = {*self.queue.intermediate_queue.get_job_ids(),
                 *self.queue.started_job_registry.get_job_ids(cleanup=False)}
        for rq_id in taken:
            job_id, _, attempt = rq_id.rpartition("-")
            record = self.get(job_id)
            if (record is None or record["status"] != QUEUED
                    or str(record["attempt"]) != attempt):
                continue
            mark = f"prox:taken:{rq_id}"
            self.redis.set(mark, time.time(), nx=True, ex=10 * self.settings.stale_after_s)
            waited = time.time() - float(self.redis.get(mark) or time.time())
            if waited >= self.settings.stale_after_s and self.worker_lost(
                    job_id, record["attempt"],
                    f"a worker took it but never started it ({waited:.0f} s)"):
                reaped.append(job_id)
        return reaped

    # ------------------------------------------------------------------ worker side
    def start(self, job_id: str, attempt: int, worker: str) -> dict | None:
        """Claim an attempt; None when the job was cancelled or the attempt superseded."""
        now = time.time()
        record = self._update(
            job_id, lambda r: r["status"] == QUEUED and r["attempt"] == attempt,
            {"status": RUNNING, "started_at": now, "heartbeat_at": now, "worker": worker,
             "frames_done": 0, "frames_failed": 0},
            lambda pipe: (pipe.hincrby(self._key(job_id), "runs", 1),
                          pipe.sadd(self._RUNNING, job_id)))
        return record

    def progress(self, job_id: str, attempt: int, **fields: object) -> bool:
        """Heartbeat plus progress fields; False when the attempt should stop."""
        return self._update(job_id, self._is_current(attempt),
                            {**fields, "heartbeat_at": time.time()}) is not None

    def finish(self, job_id: str, attempt: int, **fields: object) -> bool:
        return self._end(job_id, attempt, FINISHED, {"error": None, **fields})

    def fail(self, job_id: str, attempt: int, error: str, **fields: object) -> bool:
        return self._end(job_id, attempt, FAILED, {"error": error, **fields})

    def worker_lost(self, job_id: str, attempt: int, reason: str) -> bool:
        """The attempt's worker died: queue the next attempt, or fail after the last."""
        if attempt < self.settings.max_attempts:
            record = self._update(
                job_id, lambda r: r["status"] in (QUEUED, RUNNING) and r["attempt"] == attempt,
                {"status": QUEUED, "attempt": attempt + 1, "stage": None, "worker": None,
                 "error": f"attempt {attempt} failed: {reason}; retrying"},
                lambda pipe: pipe.srem(self._RUNNING, job_id))
            if record is not None:
                self._enqueue(job_id, attempt + 1, record["frames_total"])
            return record is not None
        return self._end(job_id, attempt, FAILED,
                         {"error": f"{reason} (attempt {attempt} of "
                                   f"{self.settings.max_attempts})"},
                         statuses=(QUEUED, RUNNING))

    # ------------------------------------------------------------------ internals
    @staticmethod
    def _is_current(attempt: int) -> Callable[[dict], bool]:
        return lambda r: r["status"] == RUNNING and r["attempt"] == attempt

    def _end(self, job_id: str, attempt: int, status: str, fields: dict,
             statuses: tuple[str, ...] = (RUNNING,)) -> bool:
        return self._update(
            job_id, lambda r: r["status"] in statuses and r["attempt"] == attempt,
            {**fields, "status": status, "finished_at": time.time(), "stage": None},
            lambda pipe: pipe.srem(self._RUNNING, job_id)) is not None

    def _update(self, job_id: str, allowed: Callable[[dict], bool], changes: dict,
                also: Callable | None = None) -> dict | None:
        """Apply ``changes`` if ``allowed(record)``, atomically; the new record or None."""
        key = self._key(job_id)
        with self.redis.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(key)
                    raw = pipe.hgetall(key)
                    if not raw or not allowed(_decode(raw)):
                        return None
                    pipe.multi()
                    pipe.hset(key, mapping=_encode(changes))
                    if also is not None:
                        also(pipe)
                    pipe.execute()
                    return {**_decode(raw), **changes}
                except WatchError:
                    continue

    def _rq_id(self, job_id: str, attempt: int) -> str:
        return f"{job_id}-{attempt}"

    def _enqueue(self, job_id: str, attempt: int, frames: int) -> None:
        self.queue.enqueue(
            "worker.tasks.run_job", job_id, attempt, job_id=self._rq_id(job_id, attempt),
            job_timeout=self.settings.job_timeout_s + self.settings.seconds_per_frame_limit
            * frames, result_ttl=24 * 3600, failure_ttl=7 * 24 * 3600,
            description=f"prox job {job_id} attempt {attempt}")

    def _cancel_rq(self, job_id: str, attempt: int) -> None:
        try:
            rq_job = Job.fetch(self._rq_id(job_id, attempt), connection=self.queue.connection)
            if rq_job.get_status() == "queued":
                rq_job.cancel()
        except (NoSuchJobError, InvalidJobOperation):
            pass  # already taken or gone: the worker sees the cancelled record
