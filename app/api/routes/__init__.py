"""The API's routers, one module per resource."""

from app.api.routes import attitudes, sequences, system, view

ROUTERS = (sequences.router, attitudes.router, system.router, view.router)
