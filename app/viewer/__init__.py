"""The console's 3D view: a viser server drawing the view state the console shares.

* :mod:`app.viewer.scene` - the geometry of the 3D scene as numpy functions;
* :mod:`app.viewer.server` - the viser server (imported only when the view starts).

The shared selection itself is application state: :mod:`app.workflow.view`.
"""


def start_viewer(context, port: int):
    """Start the 3D view for ``context`` on 127.0.0.1:``port`` or the next free port; None if it cannot start."""
    from app.viewer.server import start_viewer as start

    return start(context, port)


__all__ = ["start_viewer"]
