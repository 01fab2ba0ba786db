"""The API's routers, one module per resource."""

from app.api.routes import attitudes, sequences, spacecraft, system, view

ROUTERS = (sequences.router, attitudes.router, spacecraft.router, system.router, view.router)
