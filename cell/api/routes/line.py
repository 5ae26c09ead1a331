"""The packing line over REST: its PackML state, commands, unit mode and recorded transitions.

The same state machine answers OPC UA and the robot's digital I/O (``cell.line``); a command that is not
valid now answers 409 with the reason, the state unchanged.
"""

from __future__ import annotations

import logging
from dataclasses import asdict
from typing import Annotated, Any, TypeVar

from fastapi import APIRouter, Query, Request, Response
from pydantic import TypeAdapter

from cell.api.auth import KeyFirstRoute, Liner, ModeSwitcher, Reader
from cell.api.deps import Bulk, Service
from cell.api.schemas import (
    LineCommandIn,
    LineCommandOut,
    LineDioInputIn,
    LineDioOut,
    LineModeIn,
    LineOut,
    LineTransitionOut,
)
from cell.line.controller import LineController
from cell.line.dio import DigitalIOHandshake
from cell.line.packml import Command, State, UnitMode
from cell.service.manager import CellService
from drivers.errors import ServiceError

log = logging.getLogger("cell.line")
router = APIRouter(prefix="/api/v1/line", tags=["line"], route_class=KeyFirstRoute)
ROW_ID_MAX = 2**63 - 1
"""The largest row id a store holds (SQL's BIGINT, SQLite's INTEGER); a larger one overflowed it, a 500."""
E = TypeVar("E", Command, UnitMode)
TRANSITIONS = TypeAdapter(list[LineTransitionOut])


def _line(cell: CellService) -> LineController:
    if cell.line is None:
        raise ServiceError(f"cell {cell.name} has no packing line (no line: section in its cell file)",
                           reason="not found")
    return cell.line


def _dio(cell: CellService) -> DigitalIOHandshake:
    _line(cell)
    if cell.dio is None:
        raise ServiceError(f"cell {cell.name}'s line has no digital-I/O handshake (no line.dio in its cell "
                           "file)", reason="not found")
    return cell.dio


def _levels(dio: DigitalIOHandshake) -> dict[str, Any]:
    return asdict(dio.levels())


def _member(kind: type[E], value: str | int, field: str) -> E:
    """``value`` as a member of ``kind``, by name (any case) or number; ``ServiceError`` naming them."""
    try:
        return kind(value) if isinstance(value, int) else kind[value.strip().upper()]
    except (KeyError, ValueError):
        names = ", ".join(f"{m.name.lower()} {m.value}" for m in kind)
        raise ServiceError(f"unknown {field} {value!r}; one of: {names}", reason="invalid",
                           field=field) from None


@router.get("", response_model=LineOut)
async def get_line(cell: Service, _: Reader) -> dict[str, Any]:
    """State and unit mode, the part id, the cycle's job, counters, last stop reason and last result."""
    return _line(cell).snapshot().as_dict()


@router.post("/command", response_model=LineCommandOut)
async def post_command(cell: Service, body: LineCommandIn, key: Liner) -> dict[str, Any]:
    """A PackML command; ``part_id``, when the command is accepted, sets the part the next Start scans."""
    line = _line(cell)
    command = _member(Command, body.command, "command")
    message = await line.command(command, f"REST (key {key.name})", part_id=body.part_id)
    return {"message": message, "line": line.snapshot().as_dict()}


@router.post("/mode", response_model=LineCommandOut)
async def post_mode(cell: Service, body: LineModeIn, key: ModeSwitcher) -> dict[str, Any]:
    """Switch the unit mode: Production (the line starts scans, operator jobs are refused) or Manual (the
    operator's). Only in Stopped, Idle or Aborted."""
    line = _line(cell)
    message = await line.set_mode(_member(UnitMode, body.mode, "mode"), f"REST (key {key.name})")
    return {"message": message, "line": line.snapshot().as_dict()}


@router.get("/dio", response_model=LineDioOut)
async def get_dio(cell: Service, _: Reader) -> dict[str, Any]:
    """The digital-I/O handshake's signals: each wired input as the handshake counts it (debounced), each
    output as last written, and whether the link is connected."""
    return _levels(_dio(cell))


@router.put("/dio/inputs/{name}", response_model=LineDioOut)
async def put_dio_input(cell: Service, name: str, body: LineDioInputIn, key: Liner) -> dict[str, Any]:
    """Drive a wired input (``trigger_input``, ``reset_input``) of a sim cell's simulated UR5e high or
    low, as a PLC's wire would; the handshake counts the new level after its debounce filter (``GET
    /api/v1/line/dio`` shows when). A real UR5e's inputs are the PLC's wires: 409."""
    dio = _dio(cell)
    simulated = dio.simulated
    if simulated is None:
        raise ServiceError("the inputs of a real UR5e are its wires from the PLC: only a sim cell's "
                           "simulated inputs can be set", reason="conflict")
    pins = {signal.name: signal.pin for signal in dio.levels().inputs}
    if name not in pins:
        raise ServiceError(f"no wired input {name!r}; this cell's: {', '.join(pins)}", reason="not found")
    simulated.set_input(pins[name], body.level)
    log.info("line: simulated digital input %s (DI%d) set %s by REST (key %s)", name, pins[name],
             "high" if body.level else "low", key.name)
    return _levels(dio)


@router.get("/history", response_model=list[LineTransitionOut])
async def get_history(request: Request, cell: Service, bulk: Bulk, _: Reader,
                      limit: Annotated[int, Query(ge=1, le=1000)] = 100,
                      before_id: Annotated[int | None, Query(ge=1, le=ROW_ID_MAX)] = None) -> Response:
    """Recorded transitions, newest first; ``before_id`` pages back."""
    line = _line(cell)
    await line.written()

    def page() -> bytes:  # 1000 transitions are 65-330 ms of Python: a bulk answer (cell.api.bulk)
        return TRANSITIONS.dump_json([
            LineTransitionOut(id=row_id, at=t.at, from_state=t.from_state,
                              from_name=State(t.from_state).label, to_state=t.to_state,
                              to_name=State(t.to_state).label, mode=t.mode, cause=t.cause)
            for row_id, t in line.transitions(limit, before_id)])

    return await bulk.answer(request, page)
