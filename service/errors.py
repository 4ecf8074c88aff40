"""One error format for every answer that is not a success.

``{"error": {"code": "...", "message": "..."}}`` (plus ``"details"`` for validation errors),
for our own errors, the library's input errors, FastAPI's validation errors and Starlette's
404/405/413.
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from jobs.layout import public_message
from roguenerf import CameraMismatchError, CheckpointError, InputError, RoGUENeRFError, SceneFormatError

log = logging.getLogger("roguenerf.service")

_STATUS_CODES = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    409: "conflict",
    413: "payload_too_large",
    415: "unsupported_media_type",
    422: "validation_error",
    429: "too_many_requests",
    503: "unavailable",
}


class ApiError(Exception):
    """Raise in a route: becomes ``status`` with ``{"error": {"code", "message"}}``."""

    def __init__(self, status: int, code: str, message: str, *, headers: dict | None = None):
        self.status = status
        self.code = code
        self.message = message
        self.headers = headers
        super().__init__(message)


def error_body(code: str, message: str, **extra) -> dict:
    return {"error": {"code": code, "message": message, **extra}}


def error_response(status: int, code: str, message: str, *, headers: dict | None = None,
                   **extra) -> JSONResponse:
    return JSONResponse(error_body(code, message, **extra), status_code=status, headers=headers)


def library_error(exc: RoGUENeRFError, *, root=None, root_name: str = "the scene") -> ApiError:
    """Map a library error raised by user input to a 4xx (or 413 for oversized images).

    ``root``: the uploaded folder the input came from; paths inside it are shown relative to it,
    the folder itself as ``root_name`` (the message handlers below also replace anything left
    under the data directory)."""
    from roguenerf import ImageTooLargeError

    message = str(exc) if root is None else public_message(str(exc), root=root, root_name=root_name)
    if isinstance(exc, ImageTooLargeError):
        return ApiError(413, "image_too_large", message)
    if isinstance(exc, SceneFormatError):
        return ApiError(422, "invalid_scene", message)
    if isinstance(exc, CheckpointError):
        return ApiError(422, "invalid_checkpoint", message)
    if isinstance(exc, CameraMismatchError):  # wrong_convention, wrong_scale, wrong_world, wrong_depth_type
        return ApiError(422, "field_geometry" if exc.cause == "geometry" else f"wrong_{exc.cause}", message)
    if isinstance(exc, InputError):
        return ApiError(422, "invalid_input", message)
    # Not the caller's input (e.g. the model produced NaN/inf): a server-side failure.
    log.error("library failure (answered 500): %s", exc)
    return ApiError(500, "enhance_failed", message)


def _public(request: Request, message: str) -> str:
    """Last line of defence: no server path under the data directory reaches a client."""
    settings = getattr(request.app.state, "settings", None)
    return message if settings is None else public_message(message, data_dir=settings.data_dir)


def _location(loc) -> str:
    parts = [str(p) for p in loc if p not in ("body",)]
    return ".".join(parts) or "body"


async def _api_error(request: Request, exc: ApiError) -> JSONResponse:
    return error_response(exc.status, exc.code, _public(request, exc.message), headers=exc.headers)


async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    code = _STATUS_CODES.get(exc.status_code, "http_error")
    message = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
    if exc.status_code == 404 and message == "Not Found":
        message = f"no route {request.method} {request.url.path}"
    elif exc.status_code == 413:
        limit = getattr(request.app.state, "settings", None)
        limit_txt = f" (limit {limit.max_body_bytes} bytes)" if limit is not None else ""
        message = f"request body too large{limit_txt}"
    return error_response(exc.status_code, code, message, headers=getattr(exc, "headers", None))


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    for e in exc.errors():
        if e.get("type") == "json_invalid":
            # FastAPI reports an unparseable body as a validation error whose "location" is the
            # character offset; it is a malformed request, not an invalid field.
            loc = e.get("loc", ())
            position = loc[1] if len(loc) > 1 and isinstance(loc[1], int) else None
            reason = (e.get("ctx") or {}).get("error") or e.get("msg", "JSON decode error")
            where = f" at character {position}" if position is not None else ""
            return error_response(400, "invalid_json", f"request body is not valid JSON: {reason}{where}",
                                  **({"position": position} if position is not None else {}))
    details = [
        {"field": _location(e.get("loc", ())), "message": e.get("msg", ""), "type": e.get("type", "")}
        for e in exc.errors()
    ]
    summary = "; ".join(f"{d['field']}: {d['message']}" for d in details[:5])
    return error_response(422, "validation_error", f"invalid request: {summary}", details=details)


async def _library_error(request: Request, exc: RoGUENeRFError) -> JSONResponse:
    mapped = library_error(exc)
    return error_response(mapped.status, mapped.code, _public(request, mapped.message))


async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unhandled error on %s %s", request.method, request.url.path)
    return error_response(500, "internal_error", "internal server error (logged on the server)")


def install_error_handlers(app: FastAPI) -> None:
    app.add_exception_handler(ApiError, _api_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(RoGUENeRFError, _library_error)
    app.add_exception_handler(Exception, _unexpected)


_DESCRIPTIONS = {
    400: ("malformed request (multipart syntax, too many parts or fields, a part too large, unparseable JSON, "
          "a bad cursor)"),
    401: "missing or wrong API key",
    404: "unknown id",
    409: "conflicts with the current state",
    413: "body or image too large",
    422: "invalid input",
    500: "the model failed on this input (e.g. non-finite output); logged on the server",
    503: "over capacity or a dependency is down; retry later",
}


def error_responses(*codes: int) -> dict:
    """OpenAPI ``responses=`` entries documenting the error body for these status codes."""
    from service.schemas import ErrorBody

    return {code: {"model": ErrorBody, "description": _DESCRIPTIONS.get(code, "error")} for code in codes}
