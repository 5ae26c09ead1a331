"""Who is asking: ``Authorization: Bearer KEY`` on every route but ``/healthz``.

A key is looked up in the service's in-memory key ring (``cell.service.keys.KeyRing``: a hash and a
dictionary lookup, never the database), then its role is checked against the route's permission. A
missing or unknown key answers 401, a role too low 403. The key never appears in a response or a log.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Annotated

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from cell.service.keys import KeyRing, Permission, allowed
from cell.service.store import KeyRecord

_bearer = HTTPBearer(auto_error=False, description="an API key made by `cell keys create`")
Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]


def forbidden(role: str, action: str) -> HTTPException:
    """The 403 for a key of ``role`` asking to ``action``: "an operator key may not purge ..."."""
    article = "an" if role.startswith(tuple("aeiou")) else "a"
    return HTTPException(403, f"{article} {role} key may not {action}")


def require(permission: Permission) -> Callable[..., Awaitable[KeyRecord]]:
    """A dependency that returns the caller's key record when its role has ``permission``."""

    async def check(request: Request, credentials: Credentials) -> KeyRecord:
        ring: KeyRing = request.app.state.keys
        record = ring.authenticate(credentials.credentials) if credentials is not None else None
        if record is None:
            raise HTTPException(401, "a valid API key is needed: Authorization: Bearer <key>",
                                headers={"WWW-Authenticate": "Bearer"})
        if not allowed(record.role, permission):
            raise forbidden(record.role, permission.value)
        return record

    return check


Reader = Annotated[KeyRecord, Depends(require(Permission.READ))]
Stopper = Annotated[KeyRecord, Depends(require(Permission.STOP))]
Submitter = Annotated[KeyRecord, Depends(require(Permission.SUBMIT))]
Canceller = Annotated[KeyRecord, Depends(require(Permission.CANCEL))]
Recoverer = Annotated[KeyRecord, Depends(require(Permission.RECOVER))]
Uploader = Annotated[KeyRecord, Depends(require(Permission.UPLOAD))]
Liner = Annotated[KeyRecord, Depends(require(Permission.LINE))]
ModeSwitcher = Annotated[KeyRecord, Depends(require(Permission.MODE))]
Keeper = Annotated[KeyRecord, Depends(require(Permission.KEEP))]
Purger = Annotated[KeyRecord, Depends(require(Permission.PURGE))]
