"""The console's 3D view (issue 5) and the view state it shares with the browser console.

* :mod:`app.viewer.state` - the shared selection (sequence, rank, magnitude limit);
  no third-party imports, the API context holds one.
* :mod:`app.viewer.scene` - the geometry of the 3D scene as numpy functions.
* :mod:`app.viewer.server` - the viser server (imported only when the view starts).
"""

from app.viewer.state import ViewState, ViewStateStore


def start_viewer(context, port: int):
    """Start the 3D view for ``context`` on 127.0.0.1:``port`` or the next free port; None if it cannot start."""
    from app.viewer.server import start_viewer as start

    return start(context, port)


__all__ = ["ViewState", "ViewStateStore", "start_viewer"]
