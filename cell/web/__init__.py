"""The operator's page: static files that ``cell serve`` serves at ``/`` (``cell.api.routes.page``).

``static/index.html`` loads ``static/js/main.js``, plain ES modules with no build step, which talk to
``/api/v1`` with the key the operator logs in with. three.js is vendored under ``static/vendor/three``
(its version and how to update it: ``static/vendor/three/VERSION``).
"""

from __future__ import annotations

from pathlib import Path

STATIC_DIR = Path(__file__).resolve().parent / "static"
INDEX_HTML = STATIC_DIR / "index.html"
