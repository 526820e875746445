"""FastAPI dependencies: the settings, job store and storage of the running app, and the
caller's identity from its bearer token."""
from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from .errors import ApiError
from .jobs import JobStore
from .settings import Settings
from .storage import Storage

_bearer = HTTPBearer(auto_error=False, description="an API token configured by the operator")


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_store(request: Request) -> JobStore:
    return request.app.state.store


def get_storage(request: Request) -> Storage:
    return request.app.state.storage


def get_owner(settings: Annotated[Settings, Depends(get_settings)],
              credentials: Annotated[HTTPAuthorizationCredentials | None,
                                     Depends(_bearer)]) -> str:
    """The token's owner name; 401 without a valid bearer token."""
    if credentials is None:
        raise ApiError(401, "missing bearer token (send 'Authorization: Bearer <token>')",
                       headers={"WWW-Authenticate": "Bearer"})
    presented = credentials.credentials.encode()
    for token, owner in settings.tokens.items():
        if hmac.compare_digest(presented, token.encode()):
            return owner
    raise ApiError(401, "invalid API token", headers={"WWW-Authenticate": "Bearer"})


SettingsDep = Annotated[Settings, Depends(get_settings)]
StoreDep = Annotated[JobStore, Depends(get_store)]
StorageDep = Annotated[Storage, Depends(get_storage)]
OwnerDep = Annotated[str, Depends(get_owner)]
