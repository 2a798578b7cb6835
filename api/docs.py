"""The API docs without a CDN: Swagger UI at /docs and ReDoc at /redoc.

Their JavaScript, CSS and icon are the copies that the `fastapi-offline` package ships
(`FastAPIOffline` builds the app with both pages pointing at them), served from
`DOCS_ASSETS` by this service, so the docs work on a site network with no way out.
ReDoc's bundle still asks for its maker's logo from a CDN (it hides the image when that
fails); `DocsPolicy` sends a Content-Security-Policy with both pages that keeps every
load on this origin, so the browser never makes that request.
"""

from __future__ import annotations

from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

DOCS_ASSETS = "/docs-assets"
"""URL prefix of the Swagger UI and ReDoc assets."""

DOC_PAGES = frozenset({"/docs", "/redoc"})

DOCS_CSP = "; ".join(
    [
        "default-src 'self'",
        "script-src 'self' 'unsafe-inline'",  # the page's inline SwaggerUIBundle({...}) call
        "style-src 'self' 'unsafe-inline'",  # ReDoc's styled-components
        "img-src 'self' data:",  # Swagger UI's inline SVG icons
        "worker-src 'self' blob:",  # ReDoc's search index
        "font-src 'self' data:",
    ]
)
"""Content-Security-Policy of the doc pages: nothing from another origin."""


class DocsPolicy:
    """ASGI middleware: the Content-Security-Policy header on the doc pages."""

    def __init__(self, app: ASGIApp, *, pages: frozenset[str] = DOC_PAGES) -> None:
        self.app = app
        self.pages = pages

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"] not in self.pages:
            await self.app(scope, receive, send)
            return

        async def send_with_policy(message: Message) -> None:
            if message["type"] == "http.response.start":
                MutableHeaders(scope=message)["Content-Security-Policy"] = DOCS_CSP
            await send(message)

        await self.app(scope, receive, send_with_policy)
