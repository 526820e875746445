"""API errors: every 4xx/5xx answer is JSON with a ``detail`` message, and ``file`` and
``problem`` when a file of the upload is at fault."""
from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException


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


def upload_too_large(limit: int) -> ApiError:
    return ApiError(413, f"upload larger than the limit of {limit >> 20} MB")


def install_handlers(app: FastAPI, max_upload_bytes: int) -> None:
    @app.exception_handler(ApiError)
    async def api_error(request: Request, exc: ApiError) -> Response:
        return exc.response()

    @app.exception_handler(HTTPException)
    async def http_error(request: Request, exc: HTTPException) -> Response:
        if exc.status_code == 413:  # the body limit: say what the limit is
            return upload_too_large(max_upload_bytes).response()
        return await http_exception_handler(request, exc)
