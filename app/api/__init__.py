"""The REST API (issue 4): FastAPI over the archive, extraction and identification.

``build_context`` opens what the server needs once; ``create_app(context)``
makes the application.  Modules: ``context`` (start-up state), ``app``
(factory), ``routes`` (HTTP), ``service`` (what the endpoints do),
``schemas`` (request bodies), ``security`` (bearer tokens), ``errors``
(the ``{"detail": ...}`` error shape).
"""

from app.api.app import create_app
from app.api.context import AppContext, build_context

__all__ = ["AppContext", "build_context", "create_app"]
