"""The FastAPI application: ``create_app(settings)``; models and stores load in the lifespan.

``uvicorn --factory service.app:create_app`` serves it with settings from ``ROGUENERF_*``.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import threading
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, Response
from starlette.middleware.cors import CORSMiddleware
from starlette.staticfiles import StaticFiles

from jobs.data import bundled_checkpoint, open_data
from jobs.queue import JobQueue
from roguenerf import native
from service.auth import BearerAuthMiddleware
from service.docs import install_docs
from service.errors import error_response, install_error_handlers
from service.routers import checkpoints, enhance, health, jobs, paths, scenes, views
from service.settings import Settings
from service.state import EnhancerCache, Services

log = logging.getLogger("roguenerf.service")

UI_DIR = Path(__file__).resolve().parent / "ui"
"""The web page (static HTML/JS/CSS, no build step): served at ``/`` and ``/ui/``."""

UI_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' blob:; media-src 'self' blob:; "
                               "connect-src 'self'; "
                               "style-src 'self'; script-src 'self'; object-src 'none'; "
                               "base-uri 'none'; form-action 'none'; frame-ancestors 'none'",
    "Referrer-Policy": "no-referrer",
    "X-Content-Type-Options": "nosniff",
    "Cache-Control": "no-cache",
}
"""The page may load and contact only this origin (the browser enforces it)."""

FORM_LIMITS = {"max_files": 4, "max_fields": 16, "max_part_size": 1 << 20}
"""Multipart: at most archive + checkpoint or render + depth files; small text fields."""

DESCRIPTION = """
Enhance radiance-field renders with RoGUENeRF (ECCV 2024).

1. `POST /scenes` a zipped scene folder (optionally with an enhancer checkpoint).
2. `POST /enhance` novel renders with their depth and camera; get the enhanced PNG.
3. `POST /scenes/{id}/finetune` to adapt the enhancer to the scene; poll `GET /jobs/{id}`.
   When the job succeeds its checkpoint becomes the scene's active one.

Errors are `{"error": {"code": ..., "message": ...}}`. With `ROGUENERF_API_KEY` set, every
route but `/healthz` needs `Authorization: Bearer <key>`.
"""


def _load_default_model(settings: Settings):
    """The default enhancer for scenes registered without a checkpoint (None when absent)."""
    from roguenerf import load_checkpoint

    if settings.default_checkpoint:
        path = Path(settings.default_checkpoint)
        if not path.is_file():
            raise FileNotFoundError(f"ROGUENERF_DEFAULT_CHECKPOINT={path}: file not found")
    else:
        path = bundled_checkpoint()
        if path is None:
            log.warning("no bundled default checkpoint: scenes need their own checkpoint or a fine-tune")
            return None
    model, _ = load_checkpoint(path)
    log.info("default checkpoint loaded from %s", path)
    return model


def _open(settings: Settings) -> Services:
    layout, store = open_data(settings)
    from roguenerf import (
        SceneEnhancer,  # noqa: F401  (torch's import cost belongs to startup, not the first request)
        runtime,
    )

    log.info("runtime: %s", runtime.configure())

    return Services(
        settings=settings,
        layout=layout,
        store=store,
        queue=JobQueue(settings),
        enhancers=EnhancerCache(settings, layout, _load_default_model(settings)),
        enhance_slots=asyncio.Semaphore(settings.enhance_concurrency),
    )


@asynccontextmanager
async def lifespan(app: FastAPI):
    settings: Settings = app.state.settings
    services = await run_in_threadpool(_open, settings)
    services.extras["loop"] = asyncio.get_running_loop()
    # The fused CPU kernels compile on first use (about 3 s, then cached): do it now, beside
    # the serving, so that the first enhancement does not wait for the compiler.
    threading.Thread(target=native.library, name="roguenerf-native-build", daemon=True).start()
    app.state.services = services
    log.info("roguenerf service ready: data_dir=%s queue=%s", settings.data_dir, services.queue.backend)
    try:
        yield
    finally:
        services.store.db.close()


class RoGUENeRFApp(FastAPI):
    """FastAPI with a declared-size check in front of everything.

    FastAPI's ``max_body_size`` counts the bytes actually received (so chunked bodies
    without Content-Length are cut off at the limit too, answered through our 413 handler),
    but a too-large *declared* Content-Length makes Starlette replace whatever response the
    app sends with a plain-text 413. Refusing those up front keeps the JSON error format and
    spares reading a body that will be refused anyway.
    """

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] == "http":
            limit = self.state.settings.max_body_bytes
            for name, value in scope.get("headers", ()):
                if name == b"content-length":
                    try:
                        declared = int(value)
                    except ValueError:
                        declared = -1
                    if declared > limit or declared < 0:
                        problem = (f"request body of {declared} bytes is larger than the allowed {limit}"
                                   if declared > limit else f"invalid Content-Length {value!r}")
                        status, code = (413, "payload_too_large") if declared > limit else (400, "bad_request")
                        response = error_response(status, code, problem, headers={"Connection": "close"})
                        await response(scope, receive, send)
                        return
        await super().__call__(scope, receive, send)


class _UiFiles(StaticFiles):
    """The page's assets with the same security headers as the page."""

    def file_response(self, *args, **kwargs):
        response = super().file_response(*args, **kwargs)
        response.headers.update(UI_HEADERS)
        return response


@functools.cache
def _icon_png() -> bytes:
    """The page's icon: 32x32 PNG, a white "R" on the header's blue (drawn once, no file)."""
    import io

    from PIL import Image, ImageDraw

    image = Image.new("RGB", (32, 32), (31, 78, 121))
    draw = ImageDraw.Draw(image)
    draw.line([(10, 26), (10, 6), (18, 6)], fill="white", width=4)
    draw.arc([(12, 6), (24, 18)], start=270, end=90, fill="white", width=4)
    draw.line([(10, 17), (18, 17), (24, 26)], fill="white", width=4)
    buf = io.BytesIO()
    image.save(buf, format="PNG")
    return buf.getvalue()


def _add_ui(app: FastAPI) -> None:
    """``/``: the web page; ``/ui/``: its script and style sheet. Both are public files with
    no data in them (no key needed to load them, see service/auth.py); everything the page
    shows comes from the API with the key the user types in."""

    @app.get("/", include_in_schema=False)
    async def web_page() -> FileResponse:
        return FileResponse(UI_DIR / "index.html", media_type="text/html", headers=UI_HEADERS)

    @app.get("/favicon.ico", include_in_schema=False)
    async def favicon() -> Response:
        # The page's <link rel="icon"> names it; browsers ask for it anyway (no 404 in their console).
        return Response(_icon_png(), media_type="image/png", headers=UI_HEADERS)

    app.mount("/ui", _UiFiles(directory=UI_DIR), name="ui")


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    app = RoGUENeRFApp(
        title="RoGUENeRF enhancement service",
        version=__import__("roguenerf").__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
        max_body_size=settings.max_body_bytes,
        form_limits=FORM_LIMITS,
        docs_url=None,  # served from the package by install_docs: FastAPI's page needs a CDN
        redoc_url=None,
    )
    app.state.settings = settings
    install_error_handlers(app)
    install_docs(app)
    for module in (health, scenes, views, checkpoints, enhance, jobs, paths):
        app.include_router(module.router)
    _add_ui(app)
    if settings.api_key is not None:
        app.add_middleware(BearerAuthMiddleware, api_key=settings.api_key.get_secret_value())
    if settings.cors_origins:
        # Added last, so outermost: preflights are answered before authentication.
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.cors_origins,
            allow_credentials=False,
            allow_methods=["GET", "POST", "PATCH", "DELETE"],
            allow_headers=["Authorization", "Content-Type", "Idempotency-Key"],
            expose_headers=["X-Enhance-Seconds", "X-Total-Seconds", "X-Neighbours",
                            "X-Enhance-Note", "X-Checkpoint-Version", "X-Pose-Refined", "X-Colour-Offset",
                            "X-Trust", "X-Neighbour-Agreement", "Location", "Retry-After"],
        )
    return app
