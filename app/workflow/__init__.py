"""The application workflow: archive, search, confirm, view - what the interfaces call.

The REST routes (:mod:`app.api`), the 3D view (:mod:`app.viewer`) and the
command line (:mod:`app.cli`) are thin layers over these modules; none of
them imports another, and nothing here imports FastAPI or viser.

* :mod:`.context` - :class:`AppContext`, built once at start-up (archive,
  catalogue and index, compute pool, access policy, view state);
* :mod:`.archive` - uploads, sequences, the operator's pattern versions;
* :mod:`.search` - prepare / compute / store a search, candidates, sky view;
* :mod:`.confirm` - confirmations and their CCSDS APM/AEM;
* :mod:`.view` - the selection the console and the 3D view share;
* :mod:`.files` - the same pipeline on telemetry files (``solve``, ``extract``);
* :mod:`.text` - which characters operator names, comments and reasons may hold;
* :mod:`.documents` - every document the program emits or stores (one serializer);
* :mod:`.errors` - what the workflow refuses, by kind (the API maps kinds to statuses).
"""

__all__ = ["AppContext", "build_context"]


def __getattr__(name: str):
    """``AppContext`` and ``build_context`` on first use: a worker process imports only
    :mod:`app.workflow.compute` and should not pay for the whole context (~0.6 s of imports)."""
    if name in __all__:
        from app.workflow import context

        return getattr(context, name)
    raise AttributeError(f"module 'app.workflow' has no attribute {name!r}")
