"""Optional bearer-token authentication for every route but /healthz.

A pure ASGI middleware (not a dependency) so unknown paths, /docs and /openapi.json are
covered too and an unauthenticated caller learns nothing, not even which routes exist.
The key is compared with ``hmac.compare_digest`` and never logged.

Open without the key: ``/healthz`` and the web page's static files (``/``, ``/favicon.ico`` and
``/ui/...``: HTML, script, style sheet and icon that hold no data; the page asks the user for the key and
sends it with every API call like any other client).
"""

from __future__ import annotations

import hmac

from starlette.datastructures import Headers
from starlette.types import ASGIApp, Receive, Scope, Send

from service.errors import error_response

OPEN_PATHS = frozenset({"/healthz"})
PAGE_PATHS = frozenset({"/", "/favicon.ico"})
PAGE_PREFIXES = ("/ui/",)
"""The web page's files: open to GET and HEAD only."""


class BearerAuthMiddleware:
    def __init__(self, app: ASGIApp, *, api_key: str):
        self.app = app
        self._key = api_key.encode()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path = scope.get("path", "")
        if scope["type"] != "http" or path in OPEN_PATHS or (
                scope.get("method") in ("GET", "HEAD") and (path in PAGE_PATHS or path.startswith(PAGE_PREFIXES))):
            await self.app(scope, receive, send)
            return
        header = Headers(scope=scope).get("authorization", "")
        scheme, _, token = header.partition(" ")
        if scheme.lower() == "bearer" and hmac.compare_digest(token.strip().encode(), self._key):
            await self.app(scope, receive, send)
            return
        problem = "missing Authorization header" if not header else "invalid API key"
        response = error_response(
            401, "unauthorized",
            f"{problem}: send 'Authorization: Bearer <key>' (the ROGUENERF_API_KEY of the server)",
            headers={"WWW-Authenticate": 'Bearer realm="roguenerf"'},
        )
        await response(scope, receive, send)
