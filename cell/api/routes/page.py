"""The operator's page (``cell.web``): ``/`` and its files under ``/static``, no key needed (they hold
no data; every call the page makes sends the key). The page, and every file under ``/static``, is sent
with a Content-Security-Policy that lets it run only the scripts of this service and connect only to it."""

from __future__ import annotations

import base64
import hashlib
import re
from pathlib import Path
from typing import Any

from fastapi import APIRouter, FastAPI, Response
from starlette.staticfiles import StaticFiles

from cell.web import INDEX_HTML, STATIC_DIR

IMPORT_MAP = re.compile(r'<script type="importmap">(.*?)</script>', re.DOTALL)

router = APIRouter(include_in_schema=False)


def security_headers(html: str) -> dict[str, str]:
    """The page's headers: its CSP allows scripts from this origin and the page's import map (by its
    SHA-256, the one inline script), images from it and from blob URLs (plots fetched with the key),
    connections to it alone, and no framing."""
    inline = [f"'sha256-{base64.b64encode(hashlib.sha256(m.encode()).digest()).decode()}'"
              for m in IMPORT_MAP.findall(html)]
    scripts = " ".join(("'self'", *inline))
    policy = "; ".join((
        "default-src 'self'", f"script-src {scripts}", "style-src 'self'",
        "img-src 'self' blob:", "connect-src 'self'", "object-src 'none'", "base-uri 'none'",
        "form-action 'none'", "frame-ancestors 'none'"))
    return {"Content-Security-Policy": policy, "X-Content-Type-Options": "nosniff",
            "Referrer-Policy": "no-referrer", "Cache-Control": "no-cache"}


class _RevalidatedFiles(StaticFiles):
    """Static files a browser revalidates at each load (ETag): a new version of the cell's software is
    picked up at once, never mixed with cached modules of the old one. Each goes out with the security
    headers of the page ``page`` as it is now, as ``/`` sends it: ``/static/index.html`` is the page
    itself, and was served without its policy (to be framed, or to run what the policy keeps out), then
    with the import map's hash of the page the service started with, which an upgrade in place changes."""

    def __init__(self, directory: Path, page: Path) -> None:
        super().__init__(directory=directory)
        self._page = page

    def file_response(self, *args: Any, **kwargs: Any) -> Response:
        response = super().file_response(*args, **kwargs)
        response.headers.update(security_headers(self._page.read_text()))  # a few kB, from the page cache
        return response


@router.api_route("/", methods=["GET", "HEAD"])
def index() -> Response:
    """The page; HEAD too, as uptime monitors send (the static files answer it already)."""
    html = INDEX_HTML.read_text()
    return Response(html, media_type="text/html; charset=utf-8", headers=security_headers(html))


def add_page(app: FastAPI) -> None:
    """Serve the page at ``/`` and its files at ``/static``."""
    app.include_router(router)
    app.mount("/static", _RevalidatedFiles(STATIC_DIR, INDEX_HTML), name="static")
