"""``create_app(context)``: the FastAPI application over an :class:`AppContext`.

The API lives under ``/api``, the OpenAPI description at ``/openapi.json``
and ``/docs`` (Swagger UI from ``static/vendor``: no CDN, so it works
offline), and the browser console (``static/``) at ``/``.  The context
is built by the caller (``python -m app serve`` or a test) and stays its
property: the application never opens or closes the archive itself.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

from app.api.errors import install_error_handlers
from app.api.routes import ROUTERS
from app.workflow import AppContext

#: The console's files, served at /.
STATIC_DIR = Path(__file__).resolve().parents[2] / "static"
#: Where the vendored Swagger UI is served (static/vendor/swagger-ui).
SWAGGER_UI = "/vendor/swagger-ui"


def create_app(context: AppContext, static_dir: Path | None = STATIC_DIR) -> FastAPI:
    app = FastAPI(title="Star pattern identification ground station",
                  description="Upload TUBSAT star-camera telemetry, edit the star pattern, identify it, "
                              "confirm an attitude and export it as CCSDS APM/AEM 2.0. Every error is "
                              '`{"detail": "..."}`; 422 responses add located `problems`.',
                  version="1.0", docs_url=None, redoc_url=None)
    app.state.context = context

    @app.get("/docs", include_in_schema=False)
    def docs() -> HTMLResponse:
        return get_swagger_ui_html(openapi_url=app.openapi_url, title=f"{app.title}: API",
                                   swagger_js_url=f"{SWAGGER_UI}/swagger-ui-bundle.js",
                                   swagger_css_url=f"{SWAGGER_UI}/swagger-ui.css",
                                   swagger_favicon_url=f"{SWAGGER_UI}/favicon-32x32.png")

    install_error_handlers(app)
    for router in ROUTERS:
        app.include_router(router)
    if static_dir is not None and Path(static_dir).is_dir():
        # Mounted last: the API routes take precedence over files.
        app.mount("/", StaticFiles(directory=static_dir, html=True), name="console")
    return app
