"""Whether ``cell serve`` can listen on the line's OPC UA endpoint, checked before the service starts
(and by ``cell doctor``), without loading the OPC UA server."""

from __future__ import annotations

from urllib.parse import urlsplit

from cell.line.config import LineConfig
from drivers.errors import ConfigError
from drivers.hosts import listen_problem


def check_endpoint(line: LineConfig | None) -> None:
    """Whether this machine can listen on the line's OPC UA endpoint now (nothing to check without one):
    ``ConfigError`` in one line for a port in use or a host that is not this machine's, before the
    service starts."""
    if line is None or line.opcua is None:
        return
    endpoint = line.opcua.endpoint
    parts = urlsplit(endpoint)
    problem = listen_problem(parts.hostname, parts.port)
    if problem is not None:
        raise ConfigError(f"cannot listen on {endpoint}: {problem}", field="line.opcua.endpoint")
