"""Who the caller is: the key's name, role and what it may do (the page offers only that)."""

from __future__ import annotations

from fastapi import APIRouter

from cell.api.auth import KeyFirstRoute, Reader
from cell.api.schemas import WhoAmIOut
from cell.service.keys import PERMISSIONS, Role

router = APIRouter(prefix="/api/v1", tags=["keys"], route_class=KeyFirstRoute)


@router.get("/whoami", response_model=WhoAmIOut)
async def whoami(key: Reader) -> WhoAmIOut:
    """The calling key: its name, role and permissions (any valid key; 401 for a wrong one)."""
    return WhoAmIOut(name=key.name, role=key.role,
                     permissions=sorted(p.value for p in PERMISSIONS[Role(key.role)]))
