"""Configuration of the packing-line interface (the cell file's ``line:`` section).

A cell file without ``line:`` has no line: jobs come from operators only. With it, the service owns a
PackML state machine (:mod:`cell.line.controller`) that the REST trigger always reaches, and OPC UA and
the robot's digital I/O when their sections are given.
"""

from __future__ import annotations

from typing import Literal
from urllib.parse import urlsplit

from pydantic import Field, PositiveFloat, field_validator, model_validator

from drivers.config_base import StrictModel
from drivers.hosts import is_loopback

PART_ID_MAX = 64
"""Longest part id a line may send [characters]."""
PART_ID_PATTERN = r"^[\x20-\x7e]+$"
"""The characters of a part id: printable ASCII, space to ``~`` (it ends up in file names, logs and the
PLC's STRINGs, which need not hold any other)."""


class OPCUAConfig(StrictModel):
    """The OPC UA server (asyncua) that ``cell serve`` starts.

    ``endpoint`` ``opc.tcp://HOST:PORT/PATH``; ``security`` ``sign-and-encrypt`` (Basic256Sha256, the
    server's certificate generated into the data dir on first start, clients log in with the name and
    the secret of a ``line`` key) or ``none`` (no encryption, still a ``line`` key's name and secret),
    which only a loopback endpoint may use; ``namespace`` the URI of the cell's nodes."""

    endpoint: str
    security: Literal["sign-and-encrypt", "none"] = "sign-and-encrypt"
    namespace: str = "urn:cell:packml"

    @field_validator("endpoint")
    @classmethod
    def _opc_tcp(cls, endpoint: str) -> str:
        parts = urlsplit(endpoint)
        if parts.scheme != "opc.tcp" or not parts.hostname or parts.port is None:
            raise ValueError(f"expected opc.tcp://HOST:PORT/PATH, got {endpoint!r}")
        return endpoint

    @property
    def host(self) -> str:
        host = urlsplit(self.endpoint).hostname
        assert host is not None
        return host

    @model_validator(mode="after")
    def _plain_only_on_loopback(self) -> OPCUAConfig:
        if self.security == "none" and not is_loopback(self.host):
            raise ValueError(f"security 'none' sends the line key in clear text: only a loopback endpoint "
                             f"may use it, not {self.host}")
        return self


class DigitalIOConfig(StrictModel):
    """The robot's digital-I/O handshake (UR5e: the arm section's ``trigger_input``, ``busy_output`` and
    ``done_output``): a rising edge on the trigger in Idle is Start, busy is high in Execute, done is high
    in Complete until the PLC acknowledges, which is Reset: a held trigger by falling, a pulsed one by
    the next part's rising edge (Reset, then Start). Optionally the arm's ``reset_input`` (Clear in
    Aborted, else Reset), ``ready_output`` (Idle in Production) and ``fault_output`` (Held, or stopped
    for a reason the line did not command); ``docs/packml-opcua.md`` has the timing.

    ``debounce_s`` [s] how long the trigger must hold a new level before it counts (a relay or a
    photo-eye bounces for a few milliseconds; 20 ms is the usual PLC input filter); ``poll_hz`` how
    often the inputs are read; ``part_id`` what a trigger scans (a digital input carries no part id: in
    sim and dry-run cells this names the simulated feeder's part, on a real cell it is recorded; None:
    the part id the PLC set for the part over OPC UA or REST since the last Start, else
    ``part-<count>``)."""

    debounce_s: float = Field(default=0.02, ge=0.0, le=1.0)
    poll_hz: float = Field(default=200.0, gt=0.0, le=1000.0)
    part_id: str | None = Field(default=None, min_length=1, max_length=PART_ID_MAX, pattern=PART_ID_PATTERN)


class LineConfig(StrictModel):
    """``initial_mode``: the unit mode of a new line, at the service's first start with this cell's store; a
    restart keeps the mode the line was last in (a cell left in Manual does not come back in Production by
    itself), and the state is Stopped at every start; ``opcua``/``dio``: the ways in besides REST (None: not
    wired); ``max_time_s`` [s] a line scan's time budget (None: the scan section's)."""

    initial_mode: Literal["production", "manual"] = "production"
    opcua: OPCUAConfig | None = None
    dio: DigitalIOConfig | None = None
    max_time_s: PositiveFloat | None = None
