"""API errors: every 4xx/5xx answer is JSON with a ``detail`` message, and ``file`` and
``problem`` when a file of the upload is at fault."""
from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel
from redis.exceptions import RedisError
from starlette.exceptions import HTTPException

RETRY_AFTER_S = 5  # what a client told the job store is down should wait


class ApiError(Exception):
    """An error answered as ``{"detail": ..., "file": ..., "problem": ...}``."""

    def __init__(self, status: int, detail: str, file: str | None = None,
                 headers: dict[str, str] | None = None) -> None:
        super().__init__(detail)
        self.status, self.detail, self.file, self.headers = status, detail, file, headers

    def body(self) -> dict:
        body: dict = {"detail": self.detail}
        if self.file is not None:
            body["file"] = self.file
            body["problem"] = self.detail.removeprefix(f"{self.file}: ")
        return body

    def response(self) -> JSONResponse:
        return JSONResponse(self.body(), status_code=self.status, headers=self.headers)


class ErrorBody(BaseModel):
    """What every error answer holds."""

    detail: str
    file: str | None = None  # the file of the upload at fault
    problem: str | None = None  # what is wrong with it


MEANING = {
    400: "the upload is not a valid, safe zip (a bad entry name, a link, encryption, ...)",
    401: "no bearer token, or one this service does not know",
    404: "no such job among the caller's (another owner's job reads the same)",
    409: "the job is not in a state that allows this (e.g. results of an unfinished job)",
    410: "the job's results are no longer in storage",
    413: "the upload, or what it decompresses to, is over a limit",
    422: "invalid options, or a dataset the engine cannot read (the file is named)",
    503: "the job store is unreachable; retry after the Retry-After header's seconds",
}


def documented(*statuses: int) -> dict[int | str, dict]:
    """OpenAPI ``responses`` entries for error statuses, all with :class:`ErrorBody`."""
    return {status: {"model": ErrorBody, "description": MEANING[status]}
            for status in statuses}


def upload_too_large(limit: int) -> ApiError:
    return ApiError(413, f"upload larger than the limit of {limit >> 20} MB")


def install_handlers(app: FastAPI, max_upload_bytes: int) -> None:
    @app.exception_handler(ApiError)
    async def api_error(request: Request, exc: ApiError) -> Response:
        return exc.response()

    @app.exception_handler(RequestValidationError)
    async def invalid_request(request: Request, exc: RequestValidationError) -> Response:
        problems = "; ".join(
            f"{'.'.join(str(part) for part in error['loc'])}: {error['msg']}"
            for error in exc.errors())
        return ApiError(422, f"invalid request ({problems})").response()

    @app.exception_handler(RedisError)
    async def store_down(request: Request, exc: RedisError) -> Response:
        return ApiError(503, "the job store is unreachable; try again shortly",
                        headers={"Retry-After": str(RETRY_AFTER_S)}).response()

    @app.exception_handler(HTTPException)
    async def http_error(request: Request, exc: HTTPException) -> Response:
        if exc.status_code == 413:  # the body limit: say what the limit is
            return upload_too_large(max_upload_bytes).response()
        return await http_exception_handler(request, exc)
