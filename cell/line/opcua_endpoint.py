"""Whether ``cell serve`` can listen on the line's OPC UA endpoint, checked before the service starts
(and by ``cell doctor``), without loading the OPC UA server."""

from __future__ import annotations

from dataclasses import dataclass
from urllib.parse import urlsplit

from cell.line.config import LineConfig
from drivers.errors import ConfigError
from drivers.hosts import listen_problem

ENDPOINT_FIELD = "line.opcua.endpoint"
"""The cell file's setting that names the endpoint."""


@dataclass(frozen=True)
class EndpointProblem:
    """Why the line's OPC UA ``endpoint`` cannot be listened on: its ``host`` and ``port`` and ``reason``,
    :func:`drivers.hosts.listen_problem`'s words (``cell doctor`` picks its fix by them, as given, rather
    than cut from a message that may hold more colons: an IPv6 host, a name's own words)."""

    endpoint: str
    host: str
    port: int
    reason: str

    def __str__(self) -> str:
        return f"cannot listen on {self.endpoint}: {self.reason}"


def endpoint_problem(line: LineConfig | None) -> EndpointProblem | None:
    """Why this machine cannot listen on the line's OPC UA endpoint now (a port in use, a host that is not
    this machine's), or None when it can or there is none."""
    if line is None or line.opcua is None:
        return None
    endpoint = line.opcua.endpoint
    parts = urlsplit(endpoint)
    assert parts.hostname is not None and parts.port is not None  # OPCUAConfig's check
    reason = listen_problem(parts.hostname, parts.port)
    return None if reason is None else EndpointProblem(endpoint, parts.hostname, parts.port, reason)


def check_endpoint(line: LineConfig | None) -> None:
    """Whether this machine can listen on the line's OPC UA endpoint now (nothing to check without one):
    ``ConfigError`` in one line for a port in use or a host that is not this machine's, before the
    service starts."""
    problem = endpoint_problem(line)
    if problem is not None:
        raise ConfigError(str(problem), field=ENDPOINT_FIELD)
