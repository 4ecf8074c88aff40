"""``/docs`` without the internet: Swagger UI's JavaScript, CSS and icon come from the app.

FastAPI's own ``/docs`` page loads them from a CDN, so it is blank on a machine with no
internet. The files ship in the ``swagger-ui-bundle-v2`` package (Swagger UI 5, Apache-2.0,
kept by the connexion maintainers; import name ``swagger_ui_bundle``) and are served here
under ``/docs/assets/``. ReDoc has no such package, so ``/redoc`` is not offered.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse
from starlette.staticfiles import StaticFiles

ASSETS = "/docs/assets"
ASSET_FILES = ("swagger-ui-bundle.js", "swagger-ui.css", "favicon-32x32.png")
"""What the page references; each must exist in the package (checked at start-up)."""


def swagger_ui_dir() -> Path:
    import swagger_ui_bundle

    folder = Path(str(swagger_ui_bundle.swagger_ui_path))
    missing = [name for name in ASSET_FILES if not (folder / name).is_file()]
    if missing:
        raise RuntimeError(f"swagger-ui-bundle-v2 lacks {', '.join(missing)} in {folder}; reinstall it")
    return folder


def install_docs(app: FastAPI) -> None:
    """Serve ``/docs`` (Swagger UI), its assets and its OAuth2 redirect page from the app.
    Create the app with ``docs_url=None, redoc_url=None``."""
    folder = swagger_ui_dir()
    app.mount(ASSETS, StaticFiles(directory=folder), name="swagger-ui-assets")

    @app.get("/docs", include_in_schema=False)
    def swagger_ui() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url, title=f"{app.title} - API docs",
            swagger_js_url=f"{ASSETS}/swagger-ui-bundle.js", swagger_css_url=f"{ASSETS}/swagger-ui.css",
            swagger_favicon_url=f"{ASSETS}/favicon-32x32.png", oauth2_redirect_url="/docs/oauth2-redirect",
        )

    @app.get("/docs/oauth2-redirect", include_in_schema=False)
    def swagger_ui_redirect() -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()
