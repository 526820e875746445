"""FastAPI dependencies: the settings, job store and storage of the running app, and the
caller's identity from its bearer token."""
from __future__ import annotations

import hashlib
import hmac
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from .errors import ApiError
from .jobs import JobStore
from .settings import Settings
from .storage import Storage

bearer = HTTPBearer(auto_error=False, description="an API token configured by the operator")


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_store(request: Request) -> JobStore:
    return request.app.state.store


def get_storage(request: Request) -> Storage:
    return request.app.state.storage


def get_owner(settings: Annotated[Settings, Depends(get_settings)],
              credentials: Annotated[HTTPAuthorizationCredentials | None,
                                     Depends(bearer)]) -> str:
    """The token's owner name; 401 without a valid bearer token."""
    if credentials is None:
        raise ApiError(401, "missing bearer token (send 'Authorization: Bearer <token>')",
                       headers={"WWW-Authenticate": "Bearer"})
    presented = credentials.credentials.encode()
    for token, owner in settings.tokens.items():
        if hmac.compare_digest(presented, token.encode()):
            return owner
    raise ApiError(401, "invalid API token", headers={"WWW-Authenticate": "Bearer"})


def report_key(settings: Settings, owner: str, job_id: str) -> str | None:
    """A browser-friendly key to one job's report pages, derived from its owner's token (so
    the token itself never appears in a URL); changes when the token does, and is None
    once the owner has no token."""
    tokens = [t for t, o in settings.tokens.items() if o == owner]
    if not tokens:
        return None
    return hmac.new(min(tokens).encode(), f"report:{job_id}".encode(),
                    hashlib.sha256).hexdigest()[:32]


SettingsDep = Annotated[Settings, Depends(get_settings)]
StoreDep = Annotated[JobStore, Depends(get_store)]
StorageDep = Annotated[Storage, Depends(get_storage)]
OwnerDep = Annotated[str, Depends(get_owner)]
