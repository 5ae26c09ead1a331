"""The operator's page (``cell.web``): ``/`` and its files under ``/static``, no key needed (they hold
no data; every call the page makes sends the key). The page, and every file under ``/static``, is sent
with a Content-Security-Policy that lets it run only the scripts of this service and connect only to it
(:func:`security_headers`, which the API's docs page also goes out with: ``cell.api.routes.docs``)."""

from __future__ import annotations

import base64
import hashlib
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fastapi import APIRouter, FastAPI, Response
from starlette.staticfiles import StaticFiles

from cell.web import INDEX_HTML, STATIC_DIR

INLINE_SCRIPT = re.compile(r"<script(?![^>]*\bsrc=)[^>]*>(.*?)</script>", re.DOTALL)
"""A script written in the page (the page's import map, the docs page's start of Swagger UI), not loaded."""

router = APIRouter(include_in_schema=False)


def security_headers(html: str, images: str = "blob:") -> dict[str, str]:
    """The headers of the page ``html``: its CSP allows scripts from this origin and the page's inline
    scripts (each by its SHA-256: the operator page's import map), images from this origin and from
    ``images`` (the operator page's blob URLs: plots fetched with the key), connections to this origin
    alone, and no framing."""
    inline = [f"'sha256-{base64.b64encode(hashlib.sha256(m.encode()).digest()).decode()}'"
              for m in INLINE_SCRIPT.findall(html)]
    scripts = " ".join(("'self'", *inline))
    policy = "; ".join((
        "default-src 'self'", f"script-src {scripts}", "style-src 'self'",
        f"img-src 'self' {images}", "connect-src 'self'", "object-src 'none'", "base-uri 'none'",
        "form-action 'none'", "frame-ancestors 'none'"))
    return {"Content-Security-Policy": policy, "X-Content-Type-Options": "nosniff",
            "Referrer-Policy": "no-referrer", "Cache-Control": "no-cache"}


class RevalidatedFiles(StaticFiles):
    """Static files a browser revalidates at each load (ETag): a new version of the cell's software is
    picked up at once, never mixed with cached modules of the old one. Each goes out with the security
    headers ``headers()`` gives at that moment, those of the page the files belong to (for the operator's
    page, as ``/`` sends it: ``/static/index.html`` is the page itself, and was served without its policy,
    to be framed or to run what the policy keeps out, then with the import map's hash of the page the
    service started with, which an upgrade in place changes). ``only``: the names of the files served,
the others answering 404 as missing ones do (None: every file of ``directory``)."""

    def __init__(self, directory: Path, headers: Callable[[], dict[str, str]],
                 only: frozenset[str] | None = None) -> None:
        super().__init__(directory=directory)
        self._headers = headers
        self._only = only

    def lookup_path(self, path: str) -> tuple[str, os.stat_result | None]:
        if self._only is not None and path not in self._only:
            return "", None  # as StaticFiles answers a file it does not find: 404
        return super().lookup_path(path)

    def file_response(self, *args: Any, **kwargs: Any) -> Response:
        response = super().file_response(*args, **kwargs)
        response.headers.update(self._headers())
        return response


@router.api_route("/", methods=["GET", "HEAD"])
def index() -> Response:
    """The page; HEAD too, as uptime monitors send (the static files answer it already)."""
    html = INDEX_HTML.read_text()
    return Response(html, media_type="text/html; charset=utf-8", headers=security_headers(html))


def add_page(app: FastAPI) -> None:
    """Serve the page at ``/`` and its files at ``/static``."""
    app.include_router(router)
    # the page read at each file, a few kB from the page cache: an upgrade in place changes its policy
    app.mount("/static", RevalidatedFiles(STATIC_DIR, lambda: security_headers(INDEX_HTML.read_text())),
              name="static")
