"""``/v1/jobs/{id}/report/``: the job's HTML reports, browsable.

Browsers cannot send bearer tokens, so ``links.report`` carries a key derived from the owner's
token; the first page sets it as a cookie scoped to this job's reports, which the pages'
relative links (frames, images, meshes) then carry. A bearer token works too.
"""
from __future__ import annotations

import hmac
import mimetypes
from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import RedirectResponse, StreamingResponse
from fastapi.security import HTTPAuthorizationCredentials

from ..deps import SettingsDep, StorageDep, StoreDep, bearer, get_owner, report_key
from ..errors import ApiError, documented

router = APIRouter(prefix="/v1/jobs", tags=["reports"])
COOKIE = "prox_report"


@router.get("/{job_id}/report", include_in_schema=False)
def report_root(job_id: str, request: Request) -> RedirectResponse:
    query = f"?{request.url.query}" if request.url.query else ""
    return RedirectResponse(f"{request.url.path}/{query}")


@router.get("/{job_id}/report/{path:path}", response_class=StreamingResponse,
            responses=documented(401, 404, 409, 422, 503),
            summary="The job's HTML reports: open links.report in a browser")
def report_file(job_id: str, path: str, request: Request, settings: SettingsDep,
                store: StoreDep, storage: StorageDep,
                credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
                key: Annotated[str | None, Query(description="links.report's key")] = None
                ) -> StreamingResponse:
    presented = key or request.cookies.get(COOKIE)
    if presented is None and credentials is None:
        raise ApiError(401, "open the job's links.report URL, or send a bearer token",
                       headers={"WWW-Authenticate": "Bearer"})
    record = store.get(job_id)
    expected = report_key(settings, record["owner"], job_id) if record is not None else None
    valid = (presented is not None and expected is not None
             and hmac.compare_digest(presented.encode(), expected.encode()))
    if not valid:  # a wrong key reads as an unknown job: ids are not disclosed
        owner = get_owner(settings, credentials) if credentials is not None else None
        if record is None or owner != record["owner"]:
            raise ApiError(404, f"no job {job_id}")
    if record["status"] != "finished" or not record["options"]["report"]:
        raise ApiError(409, f"job {job_id} has no report (status {record['status']})")
    name = path + "index.html" if path == "" or path.endswith("/") else path
    try:
        size = storage.size(f"jobs/{job_id}/results/{name}")
    except ValueError:
        size = None
    if size is None:
        raise ApiError(404, f"no {name} in the report of job {job_id}")
    response = StreamingResponse(storage.chunks(f"jobs/{job_id}/results/{name}"),
                                 media_type=mimetypes.guess_type(name)[0]
                                 or "application/octet-stream",
                                 headers={"Content-Length": str(size)})
    if key is not None and valid:
        response.set_cookie(COOKIE, key, path=f"/v1/jobs/{job_id}/report/", max_age=86400,
                            httponly=True, samesite="strict")
    return response
