"""The service the routes call, taken from the app (opened in its lifespan)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from cell.service.manager import CellService


def service(request: Request) -> CellService:
    cell: CellService = request.app.state.service
    return cell


Service = Annotated[CellService, Depends(service)]
