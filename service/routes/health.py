"""``/healthz``: is the API up, can it reach Redis, and are workers listening?"""
from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse
from redis.exceptions import RedisError
from rq import Worker

from ..deps import StoreDep
from ..schemas import Health

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health,
            responses={503: {"model": Health, "description": "Redis down or no worker"}})
def healthz(store: StoreDep) -> JSONResponse:
    try:
        store.redis.ping()
        workers = len(Worker.all(queue=store.queue))
        health = Health(status="ok" if workers else "degraded", api="ok", redis="ok",
                        workers=workers, queued=store.queue.count)
    except RedisError:  # its message names Redis's host and port: not for anyone to read
        health = Health(status="degraded", api="ok", redis="unreachable", workers=0,
                        queued=None)
    return JSONResponse(health.model_dump(), status_code=200 if health.status == "ok" else 503)
