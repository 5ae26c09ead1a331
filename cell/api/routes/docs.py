"""The API's interactive documentation: Swagger UI at ``/docs``, its files under ``/static-offline-docs``
(``fastapi_offline``'s copy: a cell's PC often has no internet), no key needed (the page holds no data;
each call tried from it sends the key typed into it). The page and its files go out with the operator
page's security headers (:func:`cell.api.routes.page.security_headers`): only this service's scripts and
the page's own inline start of Swagger UI run, it connects only to this service, and no site may frame it.
Only the files the page loads are served (:data:`DOCS_FILE_NAMES`): the package's copy of ReDoc, a page
this service does not offer, answers 404. There is no OAuth2 redirect page: the API's keys are bearer
tokens, typed into Swagger UI's Authorize."""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse

from cell.api.routes.page import RevalidatedFiles, security_headers

DOCS_URL = "/docs"
DOCS_FILES_URL = "/static-offline-docs"
DOCS_FILES = Path(str(files("fastapi_offline").joinpath("static")))
DOCS_JS, DOCS_CSS, DOCS_ICON = "swagger-ui-bundle.js", "swagger-ui.css", "favicon.png"
DOCS_FILE_NAMES = frozenset({DOCS_JS, DOCS_CSS, DOCS_ICON})
"""The files of ``DOCS_FILES`` that the docs page loads, the only ones served (not its
``redoc.standalone.js``)."""
DOCS_IMAGES = "data: blob:"
"""Where the docs page's images may come from besides this service: Swagger UI's stylesheet draws its
icons from ``data:`` URLs, and "Try it out" shows an image answer (a job's plot) from a ``blob:`` URL."""


def add_docs(app: FastAPI) -> None:
    """Serve Swagger UI for ``app``'s OpenAPI schema at ``/docs`` and its files (:data:`DOCS_FILE_NAMES`)
    under ``/static-offline-docs``, each with the docs page's security headers."""
    assert app.openapi_url is not None
    at = DOCS_FILES_URL
    html = bytes(get_swagger_ui_html(
        openapi_url=app.openapi_url, title=f"{app.title} - Swagger UI", oauth2_redirect_url=None,
        swagger_js_url=f"{at}/{DOCS_JS}", swagger_css_url=f"{at}/{DOCS_CSS}",
        swagger_favicon_url=f"{at}/{DOCS_ICON}",
        # no badge from swagger.io's validator: the page connects to this service alone
        swagger_ui_parameters={"validatorUrl": None}).body).decode()
    headers = security_headers(html, images=DOCS_IMAGES)

    @app.api_route(DOCS_URL, methods=["GET", "HEAD"], include_in_schema=False)
    def docs() -> HTMLResponse:
        return HTMLResponse(html, headers=headers)

    app.mount(DOCS_FILES_URL, RevalidatedFiles(DOCS_FILES, lambda: headers, only=DOCS_FILE_NAMES),
              name="docs-files")
