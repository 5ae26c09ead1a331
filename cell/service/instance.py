"""Which service answers on a port: each start of a cell's service draws a random id, writes it into its
data dir and answers it on ``/healthz``, so that ``cell doctor``, given the same data dir, tells the ports
this cell's running service holds from another program's (another cell's service included, one of the
same name too). The id says nothing of the cell; a stale file, left by a service that ended, matches no
answer."""

from __future__ import annotations

import secrets
from pathlib import Path

from drivers.atomic_file import write_text_atomic

INSTANCE_FILE = "service.instance"
"""The file in the data dir that holds the id of the service's latest start."""


def new_instance(data_dir: Path) -> str:
    """A new id (16 hex digits), written to ``data_dir``/:data:`INSTANCE_FILE`."""
    instance = secrets.token_hex(8)
    write_text_atomic(data_dir / INSTANCE_FILE, instance + "\n")
    return instance


def instance_of(data_dir: Path) -> str | None:
    """The id written by the latest start of the service of ``data_dir``; None when there is none, or it
    cannot be read."""
    try:
        return (data_dir / INSTANCE_FILE).read_text().strip() or None
    except OSError:
        return None
