"""Who is asking: ``Authorization: Bearer KEY`` on every route but ``/healthz``.

A key is looked up in the service's in-memory key ring (``cell.service.keys.KeyRing``: a hash and a
dictionary lookup, never the database), then its role is checked against the route's permission. A
missing, unknown or revoked key answers 401, a role too low 403. The key never appears in a response or
a log.

The 401, and the 403 of a role that may not use the route, come before anything reads the request's body
(:class:`KeyFirstRoute`): FastAPI reads and parses a body before a route's dependencies run, so a client
with no key had a malformed body answered 422 (not the 401 it is owed) and could make the service read
and parse bodies for nothing, which slowed a STOP; a viewer's key held a connection for as long as it
took to send the body of a job it may not submit (300 of them made every STOP a 503), and a line key's
50 MB upload was read whole before its 403. The route's own dependency (``Require``) checks the key again
once the body is in: one revoked meanwhile is refused then.
"""

from __future__ import annotations

from collections.abc import Callable, Coroutine
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request, Response
from fastapi.dependencies.models import Dependant
from fastapi.responses import JSONResponse
from fastapi.routing import APIRoute
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from cell.service.keys import KeyRing, Permission, allowed
from cell.service.store import KeyRecord

_bearer = HTTPBearer(auto_error=False, description="an API key made by `cell keys create`")
Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
UNAUTHORIZED = "a valid API key is needed: Authorization: Bearer <key>"
CHALLENGE = {"WWW-Authenticate": "Bearer"}


def key_record(ring: KeyRing, credentials: HTTPAuthorizationCredentials | None) -> KeyRecord | None:
    """The active key's record for the request's credentials, or None (missing, unknown, revoked)."""
    return ring.authenticate(credentials.credentials) if credentials is not None else None


# What each permission lets a key do, in the 403's words ("an operator key may not drive the line").
# RECOVER guards both the arm's recovery and the queue's resume: a viewer's resume was told it "may not
# recover the arm", which reads as if the request had gone to the wrong place.
ACTIONS: dict[Permission, str] = {
    Permission.READ: "read the cell and its jobs", Permission.STOP: "stop", Permission.SUBMIT: "submit",
    Permission.CANCEL: "cancel a queued job", Permission.RECOVER: "recover the arm or resume the queue",
    Permission.UPLOAD: "upload an object", Permission.LINE: "drive the line",
    Permission.MODE: "switch the line's unit mode", Permission.KEYS: "manage keys",
    Permission.PURGE: "purge jobs", Permission.KEEP: "keep a job from retention",
}


def forbidden(role: str, action: str) -> HTTPException:
    """The 403 for a key of ``role`` asking to ``action``: "an operator key may not purge ..."."""
    article = "an" if role.startswith(tuple("aeiou")) else "a"
    return HTTPException(403, f"{article} {role} key may not {action}")


class Require:
    """A dependency that returns the caller's key record when its role has ``permission``; its permission
    is read by :class:`KeyFirstRoute`."""

    def __init__(self, permission: Permission) -> None:
        self.permission = permission

    async def __call__(self, request: Request, credentials: Credentials) -> KeyRecord:
        record = key_record(request.app.state.keys, credentials)
        if record is None:
            raise HTTPException(401, UNAUTHORIZED, headers=CHALLENGE)
        if not allowed(record.role, self.permission):
            raise forbidden(record.role, ACTIONS[self.permission])
        return record


Reader = Annotated[KeyRecord, Depends(Require(Permission.READ))]
Stopper = Annotated[KeyRecord, Depends(Require(Permission.STOP))]
Submitter = Annotated[KeyRecord, Depends(Require(Permission.SUBMIT))]
Canceller = Annotated[KeyRecord, Depends(Require(Permission.CANCEL))]
Recoverer = Annotated[KeyRecord, Depends(Require(Permission.RECOVER))]
Uploader = Annotated[KeyRecord, Depends(Require(Permission.UPLOAD))]
Liner = Annotated[KeyRecord, Depends(Require(Permission.LINE))]
ModeSwitcher = Annotated[KeyRecord, Depends(Require(Permission.MODE))]
Keeper = Annotated[KeyRecord, Depends(Require(Permission.KEEP))]
Purger = Annotated[KeyRecord, Depends(Require(Permission.PURGE))]


class KeyFirstRoute(APIRoute):
    """The route class of the API's routers: a route that checks a key (one whose dependencies include
    the ``Authorization: Bearer`` check) answers a request without a valid key 401, and one whose key's
    role lacks a permission the route's dependencies ``Require`` 403, before anything reads its body (the
    module docstring); a route that needs no key is left as it is."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()
        if not _checks_key(self.dependant):
            return handler
        permissions = sorted(_permissions(self.dependant))

        async def key_first(request: Request) -> Response:
            record = key_record(request.app.state.keys, await _bearer(request))
            if record is None:
                return JSONResponse({"detail": UNAUTHORIZED}, 401, headers=CHALLENGE)
            for permission in permissions:
                if not allowed(record.role, permission):
                    return JSONResponse({"detail": forbidden(record.role, ACTIONS[permission]).detail}, 403)
            return await handler(request)

        return key_first


def _checks_key(dependant: Dependant) -> bool:
    return dependant.call is _bearer or any(_checks_key(d) for d in dependant.dependencies)


def _permissions(dependant: Dependant) -> set[Permission]:
    """The permissions the route's dependencies ``Require``."""
    own = {dependant.call.permission} if isinstance(dependant.call, Require) else set()
    return own.union(*(_permissions(d) for d in dependant.dependencies))
