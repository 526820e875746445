"""The FastAPI application: ``uvicorn service.app:app`` (configured by ``PROX_*``
environment variables, see :mod:`service.settings`)."""
from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from typing import AsyncIterator

from fastapi import FastAPI
from fastapi.concurrency import run_in_threadpool
from redis.exceptions import RedisError

from .errors import install_handlers
from .jobs import JobStore
from .limits import BodySizeLimit
from .routes import docs, health, jobs, reports
from .settings import Settings
from .storage import LocalStorage, Storage

log = logging.getLogger("prox.service")
ORPHAN_AGE_S = 600  # job files without a record are swept at start-up once this old


async def _reap_forever(store: JobStore, interval: float) -> None:
    """Recover jobs whose worker died (see :meth:`JobStore.reap`)."""
    while True:
        try:
            for job_id in await run_in_threadpool(store.reap):
                log.warning("job %s lost its worker; retried or failed", job_id)
        except Exception:  # noqa: BLE001 - Redis down: keep trying, /healthz reports it
            log.exception("reaping stale jobs failed")
        await asyncio.sleep(interval)


def sweep_orphans(store: JobStore, storage: Storage, older_than_s: float = ORPHAN_AGE_S
                  ) -> list[str]:
    """Delete the files of jobs that have no record (a submission cut off between storing
    its upload and recording the job), once they are ``older_than_s`` (younger ones may be
    a submission in flight on another API process); returns their ids."""
    removed = []
    for job_id, changed in storage.folders("jobs"):
        if time.time() - changed > older_than_s and store.get(job_id) is None:
            storage.delete_prefix(f"jobs/{job_id}")
            removed.append(job_id)
    return removed


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings.from_env()
    if not settings.tokens:
        raise RuntimeError("no API tokens configured: set PROX_API_TOKENS='name:token,...' "
                           "or PROX_TOKENS_FILE")

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        try:
            for job_id in await run_in_threadpool(sweep_orphans, app.state.store,
                                                  app.state.storage):
                log.warning("removed the files of job %s, which has no record", job_id)
        except RedisError:  # Redis down: the next start sweeps
            log.exception("sweeping orphaned job files failed")
        reaper = asyncio.create_task(_reap_forever(app.state.store, settings.reap_interval_s))
        yield
        reaper.cancel()

    app = FastAPI(title="prox", version="1", lifespan=lifespan, docs_url=None, redoc_url=None,
                  description="Fit 3D human bodies to OpenPose keypoints inside scanned "
                              "scenes (PROX). Submit a zip in the PROX layout, follow the "
                              "job, download the fitted meshes and parameters.")
    app.state.settings = settings
    app.state.store = JobStore(settings)
    app.state.storage = LocalStorage(settings.storage_dir)
    install_handlers(app, settings.max_upload_bytes)
    app.add_middleware(BodySizeLimit, limit=settings.max_upload_bytes)
    app.include_router(jobs.router)
    app.include_router(reports.router)
    app.include_router(health.router)
    docs.install(app)
    return app


def __getattr__(name: str) -> FastAPI:
    # ``service.app:app`` for uvicorn, built on first access so importing the module
    # (tests, tools) does not need a configured environment.
    if name == "app":
        globals()["app"] = create_app()
        return globals()["app"]
    raise AttributeError(name)
