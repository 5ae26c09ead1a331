"""A write the service must not drop (a job's end, the line's state): tried again while the store does not
answer."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any

from cell.service.store.records import STORE_RETRY_S
from drivers.errors import StoreError


async def until_stored(write: Callable[[], object], what: str, shutting_down: Callable[[], bool],
                       log: logging.Logger, extra: dict[str, Any] | None = None) -> bool:
    """Run ``write`` (a store call) on a thread, again every ``STORE_RETRY_S`` while it raises
    ``StoreError``, logging ``what`` was not recorded once, and recorded once it was. Given up (False) only
    when ``shutting_down()`` says so after a failure: the next start settles what is left."""
    waited = False
    while True:
        try:
            await asyncio.to_thread(write)
        except StoreError as exc:
            if shutting_down():
                log.error("%s not recorded, the service shutting down: %s", what, exc, extra=extra)
                return False
            if not waited:
                log.warning("%s not recorded yet, again every %g s: %s", what, STORE_RETRY_S, exc,
                            extra=extra)
            waited = True
            await asyncio.sleep(STORE_RETRY_S)
            continue
        if waited:
            log.warning("%s recorded once the store answered", what, extra=extra)
        return True
