"""The API's routers, one module per resource."""

from app.api.routes import attitudes, frames, queue, sequences, spacecraft, system, timeline, view

ROUTERS = (sequences.router, attitudes.router, spacecraft.router, system.router, view.router,
           queue.router, frames.router, timeline.router)
