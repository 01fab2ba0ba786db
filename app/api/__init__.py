"""The REST API: thin FastAPI routes over the application workflow (:mod:`app.workflow`).

``create_app(context)`` makes the application over an
:class:`app.workflow.AppContext` that the caller built.  Modules: ``app``
(factory), ``routes`` (HTTP, one module per resource), ``schemas`` (request
bodies and their limits), ``errors`` (the ``{"detail": ...}`` error shape and
the mapping of workflow refusals to statuses).
"""

from app.api.app import create_app

__all__ = ["create_app"]
