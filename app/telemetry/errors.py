"""The one error every telemetry entry point raises for bad input.

A :class:`TelemetryError` carries a list of :class:`Problem` objects, each
saying *where* (a path such as ``snapshots[3].sources[2].x``, a CSV cell such
as ``line 14, column "x"``, or ``file`` for whole-file problems) and *why*.
Parsers collect as many problems as practical (up to :data:`MAX_PROBLEMS`)
before raising, so a user can fix a file in one pass.

``TelemetryError`` subclasses :class:`ValueError` so callers that only know
"bad value" still catch it; the CLI and the REST API use :meth:`to_dict`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

#: Problems kept per error; beyond this the file is broken enough that more
#: detail would only hide the first, most useful messages.
MAX_PROBLEMS = 50


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a telemetry file: where, and why."""

    location: str
    message: str

    def __str__(self) -> str:
        return f"{self.location}: {self.message}"

    def to_dict(self) -> dict:
        return {"location": self.location, "message": self.message}


class TelemetryError(ValueError):
    """Invalid telemetry: one or more :class:`Problem` s.

    ``truncated`` is True when more than :data:`MAX_PROBLEMS` problems were
    found and the rest were dropped.  :attr:`noun` names what was invalid in
    the message ("invalid telemetry: ...").
    """

    noun = "telemetry"

    def __init__(self, problems: list[Problem] | Problem, *, filename: str | None = None,
                 truncated: bool = False):
        if isinstance(problems, Problem):
            problems = [problems]
        problems = list(problems)
        if not problems:
            raise ValueError("a TelemetryError needs at least one problem")
        self.problems: list[Problem] = problems[:MAX_PROBLEMS]
        self.truncated = truncated or len(problems) > MAX_PROBLEMS
        self.filename = filename
        super().__init__(self.summary)

    def __reduce__(self):
        # Pickled whole, problems and all: a compute worker's error reaches the server as it was raised.
        return type(self), (self.problems,), {"filename": self.filename, "truncated": self.truncated}

    @classmethod
    def at(cls, location: str, message: str, *, filename: str | None = None) -> TelemetryError:
        """An error with a single problem."""
        return cls([Problem(location, message)], filename=filename)

    @property
    def summary(self) -> str:
        """One line: which file and how many problems (the first, if only one)."""
        where = f"{self.filename}: " if self.filename else ""
        if len(self.problems) == 1 and not self.truncated:
            return f"{where}invalid {self.noun}: {self.problems[0]}"
        more = "+" if self.truncated else ""
        return f"{where}invalid {self.noun}: {len(self.problems)}{more} problems"

    def __str__(self) -> str:
        if len(self.problems) == 1 and not self.truncated:
            return self.summary
        lines = [self.summary + ":"] + [f"  {p}" for p in self.problems]
        if self.truncated:
            lines.append(f"  ... (only the first {MAX_PROBLEMS} problems are shown)")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """JSON-ready form: ``{"message": str, "problems": [{"location", "message"}, ...]}``."""
        return {"message": self.summary, "problems": [p.to_dict() for p in self.problems]}


class ImageError(TelemetryError):
    """An image, or a pass of images, that cannot be read or assembled into a sequence
    (:mod:`app.frames`): "invalid image: ..." where the user sent no telemetry."""

    noun = "image"


@dataclass
class ProblemCollector:
    """Accumulates problems while a parser keeps going past the first one.

    Not shared between parses: each call of a parser makes its own.
    """

    problems: list[Problem] = field(default_factory=list)
    truncated: bool = False
    #: Whether camera values are held to the physical bounds of a star camera (off only for text an
    #: archive accepted under earlier bounds: see :func:`app.telemetry.formats.parse_telemetry`).
    physical_bounds: bool = True

    def add(self, location: str, message: str) -> None:
        if len(self.problems) >= MAX_PROBLEMS:
            self.truncated = True
            return
        self.problems.append(Problem(location, message))

    @property
    def full(self) -> bool:
        """True once no more problems will be kept; parsers may stop early."""
        return self.truncated

    def __bool__(self) -> bool:
        return bool(self.problems)

    def raise_if_any(self, filename: str | None = None, error: type[TelemetryError] = TelemetryError) -> None:
        if self.problems:
            raise error(self.problems, filename=filename, truncated=self.truncated)
