"""RFC 9457 problem+json for every error, and the request-body size limit."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.errors import ServiceError, WorkerUnavailable, internal_error

log = logging.getLogger(__name__)

PROBLEM_JSON = "application/problem+json"


def problem(
    status: int,
    slug: str,
    title: str,
    detail: str,
    *,
    instance: str | None = None,
    headers: dict[str, str] | None = None,
    **extra: Any,
) -> JSONResponse:
    body: dict[str, Any] = {
        "type": f"urn:covslam:problem:{slug}",
        "title": title,
        "status": status,
        "detail": detail,
    }
    if instance is not None:
        body["instance"] = instance
    body.update({k: v for k, v in extra.items() if v is not None})
    return JSONResponse(body, status_code=status, media_type=PROBLEM_JSON, headers=headers)


def _loc(loc: tuple[Any, ...]) -> str:
    parts = [p for p in loc if p not in ("body", "query", "path", "header")]
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or ".".join(str(p) for p in loc)


def service_problem(request: Request, exc: ServiceError) -> JSONResponse:
    """The answer to a ServiceError."""
    headers: dict[str, str] = dict(getattr(exc, "headers", None) or {})
    if exc.status >= 500:
        headers["Connection"] = "close"  # the server is in doubt: a fresh connection
    return problem(
        exc.status,
        exc.slug,
        exc.title,
        exc.detail,
        instance=request.url.path,
        headers=headers or None,
        **exc.extra,
    )


def unavailable_problem(request: Request, exc: WorkerUnavailable) -> JSONResponse:
    """The answer to a WorkerUnavailable: 503 with Retry-After."""
    return problem(
        503,
        "worker-unavailable",
        "Worker unavailable",
        exc.detail,
        instance=request.url.path,
        headers={"Retry-After": str(exc.retry_after_s)},
    )


def install(app: FastAPI) -> None:
    """Exception handlers that answer problem+json."""

    @app.exception_handler(ServiceError)
    async def _service(request: Request, exc: ServiceError) -> JSONResponse:
        return service_problem(request, exc)

    @app.exception_handler(WorkerUnavailable)
    async def _unavailable(request: Request, exc: WorkerUnavailable) -> JSONResponse:
        return unavailable_problem(request, exc)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = exc.errors()
        if errors and errors[0].get("type") == "json_invalid":
            ctx = errors[0].get("ctx") or {}
            return problem(
                400,
                "malformed-body",
                "Malformed body",
                f"body: malformed JSON: {ctx.get('error', errors[0].get('msg'))}",
                instance=request.url.path,
            )
        parts = [f"{_loc(tuple(e['loc']))}: {e['msg']}" for e in errors]
        first = _loc(tuple(errors[0]["loc"])) if errors else None
        return problem(
            422,
            "invalid-request",
            "Invalid request",
            "; ".join(parts),
            instance=request.url.path,
            field=first,
            errors=[{"field": _loc(tuple(e["loc"])), "message": e["msg"]} for e in errors],
        )

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        titles = {
            400: "Malformed body",
            404: "Not found",
            405: "Method not allowed",
            413: "Body too large",
        }
        return problem(
            exc.status_code,
            "http-" + str(exc.status_code),
            titles.get(exc.status_code, "HTTP error"),
            str(exc.detail),
            instance=request.url.path,
        )

    @app.exception_handler(RecursionError)
    async def _too_deep(request: Request, exc: RecursionError) -> JSONResponse:
        # A JSON body nested deeper than the parser's recursion limit (handled here, not
        # as a 500: the server is fine).
        return await _service(request, internal_error(exc))

    @app.exception_handler(Exception)
    async def _internal(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error on %s", request.url.path)
        return await _service(request, internal_error(exc))


_PROBLEM_REF = {"$ref": "#/components/schemas/Problem"}


def declare_problem_responses(schema: dict[str, Any]) -> None:
    """Every 4xx/5xx response of the OpenAPI document is application/problem+json with
    the Problem schema (FastAPI's own 422 model included: its handler answers Problem)."""
    for operations in schema.get("paths", {}).values():
        for operation in operations.values():
            for code, response in operation.get("responses", {}).items():
                if str(code)[0] in "45":
                    response["content"] = {PROBLEM_JSON: {"schema": _PROBLEM_REF}}
    components = schema.get("components", {}).get("schemas", {})
    for unused in ("HTTPValidationError", "ValidationError"):
        components.pop(unused, None)


class _TooLarge(Exception):
    pass


class BodyLimit:
    """ASGI middleware: 413 problem+json for bodies over the limit (imports and multipart
    image frames have their own)."""

    def __init__(
        self,
        app: ASGIApp,
        *,
        max_bytes: int,
        max_import_bytes: int,
        max_image_frame_bytes: int | None = None,
    ) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.max_import_bytes = max_import_bytes
        self.max_image_frame_bytes = max_image_frame_bytes or max_bytes

    def _limit(self, scope: Scope) -> int:
        path: str = scope["path"]
        if path == "/v1/maps/import":
            return self.max_import_bytes
        if path.endswith("/frames"):
            for name, value in scope.get("headers", ()):
                if name == b"content-type" and value.lower().startswith(b"multipart/"):
                    return self.max_image_frame_bytes
        return self.max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] not in ("POST", "PUT", "PATCH"):
            await self.app(scope, receive, send)
            return
        limit = self._limit(scope)
        for name, value in scope.get("headers", ()):
            if name == b"content-length" and value.isdigit() and int(value) > limit:
                await self._reject(scope, send, limit, int(value))
                return
        seen = 0
        started = False

        async def limited_receive() -> Message:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    raise _TooLarge
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except _TooLarge:
            if not started:
                await self._reject(scope, send, limit, None)

    @staticmethod
    async def _reject(scope: Scope, send: Send, limit: int, size: int | None) -> None:
        got = f"{size} bytes" if size is not None else "more"
        response = problem(
            413,
            "body-too-large",
            "Body too large",
            f"body: {got} exceeds the limit of {limit} bytes for {scope['path']}",
            instance=scope["path"],
        )
        await response(scope, _noop_receive, send)


async def _noop_receive() -> Message:
    return {"type": "http.disconnect"}
