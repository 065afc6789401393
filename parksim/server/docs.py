"""``/docs`` served from this host: Swagger UI's files come from the swagger-ui-bundle-v2 package, not a CDN,
so the API page works without internet. ReDoc (CDN only) is not served."""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles
from swagger_ui_bundle import swagger_ui_path

__all__ = ["install_docs", "DOCS_ASSETS"]

DOCS_ASSETS = "/docs/assets"


def install_docs(app: FastAPI) -> None:
    """Swagger UI at ``/docs`` over ``app``'s OpenAPI schema, its JS, CSS and icon under ``DOCS_ASSETS``."""
    app.mount(DOCS_ASSETS, StaticFiles(directory=swagger_ui_path), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    def docs(request: Request) -> HTMLResponse:
        base = request.scope.get("root_path", "") + DOCS_ASSETS
        return get_swagger_ui_html(openapi_url=request.scope.get("root_path", "") + str(app.openapi_url),
                                   title=f"{app.title} - API", swagger_js_url=f"{base}/swagger-ui-bundle.js",
                                   swagger_css_url=f"{base}/swagger-ui.css",
                                   swagger_favicon_url=f"{base}/favicon-32x32.png",
                                   swagger_ui_parameters={"validatorUrl": None, "persistAuthorization": True})
