"""What the workflow refuses, by kind: the interfaces translate each kind into their own terms.

The API maps :class:`NotFound` to 404, :class:`Conflict` to 409,
:class:`Invalid` to 422 (with located ``problems``), :class:`TooLarge` to 413
and :class:`Busy` to 503; the CLI and the 3D view show the message.
Nothing here knows about HTTP.
"""

from __future__ import annotations


class WorkflowError(Exception):
    """An expected refusal with a sentence a person understands."""

    def __init__(self, detail: str, problems: list[dict] | None = None) -> None:
        super().__init__(detail)
        self.detail = detail
        #: Located problems ``[{"location": ..., "message": ...}]`` (Invalid only).
        self.problems = problems


class NotFound(WorkflowError):
    """The sequence, search, candidate or attitude named does not exist."""


class Conflict(WorkflowError):
    """The request is well formed but the archive's state does not allow it (e.g. no search yet)."""


class Invalid(WorkflowError):
    """A value of the request is wrong; ``problems`` locate it."""

    def __init__(self, detail: str, location: str = "body", message: str | None = None,
                 problems: list[dict] | None = None) -> None:
        super().__init__(detail, problems or [{"location": location, "message": message or detail}])


class TooLarge(WorkflowError):
    """An upload above the size limit."""


class Busy(WorkflowError):
    """The work did not finish within its time-out; the request may be tried again."""
