"""Request bodies of the API (pydantic): their limits are the API's input contract.

Unknown fields are refused (``extra="forbid"``) so that a typo such as
``"exclude_track"`` is an error rather than an edit silently ignored.
Responses are the documents of :mod:`app.workflow.documents`.
"""

from __future__ import annotations

import math
import re
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, StringConstraints, WrapValidator

from app.identification import METHODS
from app.telemetry.formats import describe_value
from app.timefmt import ISO_EXAMPLE, parse_iso_time
from app.workflow.documents import ManualPointDefinition, PatternDefinition
from app.workflow.search import PriorRequest
from app.workflow.text import MAX_COMMENT, MAX_OPERATOR, NUL_MESSAGE, comment_problem, operator_name_problem
from app.workflow.view_state import SESSION_PATTERN

#: Largest list an edit may carry (a sequence has at most 64 x 64 sources).
MAX_LIST = 4096
#: Ids and ranks fit a 64-bit database integer.
MAX_ID = 2**63 - 1
#: Longest spacecraft name and search term.
MAX_NAME = 128


def _without_nul(text: str | None) -> str | None:
    if text is not None and "\x00" in text:
        raise ValueError(NUL_MESSAGE)
    return text


def _operator_name(text: str | None) -> str | None:
    problem = None if text is None else operator_name_problem(text)
    if problem:
        raise ValueError(problem)
    return text


def _comment(text: str | None) -> str | None:
    # CRLF and CR line breaks are kept as LF: a Windows text field or a pasted mail sends the same comment.
    text = None if text is None else text.replace("\r\n", "\n").replace("\r", "\n")
    problem = None if text is None else comment_problem(text)
    if problem:
        raise ValueError(problem)
    return text


# Free text a client sends.  U+0000 is refused everywhere: PostgreSQL's text cannot hold it and SQLite
# can; refusing it here gives the same located 422 on both backends instead of a stored row on one and a
# failed write on the other.  What an audit record keeps (names, comments, reasons) refuses control and
# bidirectional control characters too (app.workflow.text says which and why).
#
# Each length limit is a StringConstraints inside the type, before the validator: a Field(max_length=...)
# beside an AfterValidator is checked after it as a generic length, and pydantic then words it for a list
# ("Value should have at most 100 items after validation") instead of "String should have at most 100
# characters".  As a query or path parameter write ``Annotated[ShortText, Query(...)]`` without a length
# in Query: with ``= Query(...)`` as the default FastAPI drops the validator.

#: An operator's name (audit records): one line of plain text, at most MAX_OPERATOR characters.
OperatorName = Annotated[str, StringConstraints(max_length=MAX_OPERATOR), AfterValidator(_operator_name)]
#: A comment or an override reason: lines of text (newline and tab allowed), at most MAX_COMMENT characters.
Comment = Annotated[str, StringConstraints(max_length=MAX_COMMENT), AfterValidator(_comment)]
#: The reason of a "no valid attitude" verdict: as a comment, and not empty.
Reason = Annotated[str, StringConstraints(min_length=1, max_length=MAX_COMMENT), AfterValidator(_comment)]
#: A search term or a spacecraft filter: any character but U+0000, at most MAX_NAME characters.
ShortText = Annotated[str, StringConstraints(max_length=MAX_NAME), AfterValidator(_without_nul)]
#: A spacecraft's name as its telemetry files give it: 1 to MAX_NAME characters, any but U+0000.
SpacecraftName = Annotated[str, StringConstraints(min_length=1, max_length=MAX_NAME), AfterValidator(_without_nul)]

# Numbers and flags of a body must be JSON's own.  pydantic's lax mode takes "yes", "on", "t" and "1" as
# true, true and " 1 " as the integer 1, and "1.5" as a number: a guard rail (supersede, the rank confirmed,
# the search looked at) must not be crossed by a string or a boolean.  ``Strict()`` would do as much in
# pydantic's words ("Input should be a valid boolean"); these validators say what came instead, in the
# telemetry format's words ("must be an integer, got 1.0": app.telemetry.formats.describe_value), and keep
# the field's type and limits for the OpenAPI description.  A float with an integral value (1.0) is refused
# as an id or rank, as in the telemetry format: no client that counts writes 1.0, and a float id is a sign
# of arithmetic gone wrong (2**53 + 1 as a float is another id).

def _json_boolean(value: Any, handler):
    if not isinstance(value, bool):
        raise ValueError(f"must be true or false, got {describe_value(value)}")
    return handler(value)


def _json_integer(value: Any, handler):
    if isinstance(value, float) and math.isfinite(value) and abs(value) > MAX_ID:
        # 1e20 is a float, but what is wrong first is its size: the API's words for it (app.api.errors).
        raise ValueError("the number is too large for an integer")
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"must be an integer, got {describe_value(value)}")
    return handler(value)


def _json_number(value: Any, handler):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"must be a number, got {describe_value(value)}")
    return handler(value)


#: A flag (JSON true or false only).
Flag = Annotated[bool, WrapValidator(_json_boolean)]
#: An archive id or a rank: a JSON integer from 1 that fits a 64-bit database integer.
DbId = Annotated[int, Field(ge=1, le=MAX_ID), WrapValidator(_json_integer)]
#: A track id as the extraction numbers them (0..tracks-1; bounded so nothing overflows).
TrackId = Annotated[int, Field(ge=0, le=1_000_000), WrapValidator(_json_integer)]
#: A snapshot's 0-based position in the file.
SnapshotPosition = Annotated[int, Field(ge=0, le=10_000), WrapValidator(_json_integer)]
#: How many candidates a search returns.
CandidateCount = Annotated[int, Field(ge=1, le=50), WrapValidator(_json_integer)]
#: A JSON number (an integer is one; a string or a boolean is not).  Its limits go in ``Field(...)`` as the
#: default, which pydantic applies inside the validator, so that OpenAPI shows them as minimum and maximum.
Number = Annotated[float, WrapValidator(_json_number)]

#: Text of a plain number: a Unix time or a date without separators, never read as a time here.
_NUMBER_TEXT = re.compile(r"[+-]?[0-9]+(?:\.[0-9]*)?")


def _iso_8601_time(value: Any) -> Any:
    """ISO 8601 text only: pydantic reads ``1582788491`` (and the text of it) as a Unix time, which a time
    range of an export must not silently become.  A datetime passes (a default or a Python caller)."""
    if isinstance(value, datetime):
        return value
    if not isinstance(value, str):
        raise ValueError(f"must be an ISO 8601 time such as {ISO_EXAMPLE}, got {describe_value(value)}")
    if _NUMBER_TEXT.fullmatch(value.strip()):
        raise ValueError(f"{value.strip()!r} is a number, not a time: give an ISO 8601 time such as {ISO_EXAMPLE} "
                         "(Unix times are not read)")
    return parse_iso_time(value.strip())


#: A time of a query parameter: ISO 8601 (naive or with a zone, as written), never a number.
IsoTime = Annotated[datetime, BeforeValidator(_iso_8601_time)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ManualPoint(_Strict):
    """A point picked by hand in snapshot ``snapshot`` (0-based position in the file)."""

    snapshot: SnapshotPosition
    x: Number = Field(allow_inf_nan=False)
    y: Number = Field(allow_inf_nan=False)


class PatternEdit(_Strict):
    """The operator's pattern: tracks out, tracks in (null: every track), hand-picked points."""

    exclude_tracks: list[TrackId] = Field(default_factory=list, max_length=MAX_LIST)
    include_tracks: list[TrackId] | None = Field(default=None, max_length=MAX_LIST)
    manual_points: list[ManualPoint] = Field(default_factory=list, max_length=256)
    operator: OperatorName | None = None

    def location_of(self, field: str, key: int) -> str:
        """Where ``key`` (a track id, or a manual point's position) is in this request, for a located problem."""
        if field in ("exclude_tracks", "include_tracks"):
            values = getattr(self, field) or []
            if key in values:
                return f"body.{field}[{values.index(key)}]"
        elif field == "manual_points" and 0 <= key < len(self.manual_points):
            return f"body.manual_points[{key}]"
        return f"body.{field}"

    def definition(self) -> PatternDefinition:
        return PatternDefinition(
            exclude_tracks=sorted(set(self.exclude_tracks)),
            include_tracks=None if self.include_tracks is None else sorted(set(self.include_tracks)),
            manual_points=[ManualPointDefinition(**p.model_dump()) for p in self.manual_points])


class PatternReset(_Strict):
    operator: OperatorName | None = None


class PriorAttitude(_Strict):
    """A prior attitude for tracking: boresight RA/Dec, roll (docs/conventions.md) and its 1-sigma, degrees."""

    ra_deg: Number = Field(ge=0.0, lt=360.0, allow_inf_nan=False)
    dec_deg: Number = Field(ge=-90.0, le=90.0, allow_inf_nan=False)
    roll_deg: Number = Field(ge=-360.0, le=360.0, allow_inf_nan=False)
    sigma_deg: Number = Field(default=1.0, gt=0.0, le=10.0, allow_inf_nan=False)

    def request(self) -> PriorRequest:
        return PriorRequest(**self.model_dump())


class SearchRequest(_Strict):
    """``bright_pair`` (default) and ``tf`` search the whole sky; ``tracking`` matches near ``prior``, or
    near the newest confirmed attitude of the same spacecraft propagated with its rate."""

    method: Literal[tuple(METHODS)] = "bright_pair"  # type: ignore[valid-type]
    max_candidates: CandidateCount | None = None
    prior: PriorAttitude | None = None


class VerdictRef(_Strict):
    """A verdict of a sequence: a confirmed attitude or a "no valid attitude" record, by its id."""

    kind: Literal["attitude", "rejection"]
    id: DbId

    def key(self) -> tuple[str, int]:
        return self.kind, self.id


class ConfirmRequest(_Strict):
    """Confirm a candidate of the latest search.  ``override_reason``: needed (and kept in the audit record)
    for a candidate that is not the credible best; ``supersede``: replace the sequence's current verdict, and
    with ``replaces`` (the verdict the operator saw) only that one (409 when another came in between);
    ``search_id``: the search the operator looked at (refused if a newer one replaced it)."""

    rank: DbId
    operator: OperatorName | None = None
    comment: Comment | None = None
    override_reason: Comment | None = None
    supersede: Flag = False
    replaces: VerdictRef | None = None
    search_id: DbId | None = None


class RejectRequest(_Strict):
    """Record "no valid attitude" for a sequence, with the reason; ``supersede`` withdraws a confirmation (with
    ``replaces``, only the verdict named: see :class:`ConfirmRequest`)."""

    reason: Reason
    operator: OperatorName | None = None
    supersede: Flag = False
    replaces: VerdictRef | None = None


class ViewerFollow(_Strict):
    """The console session the 3D view should draw."""

    session: str = Field(pattern=SESSION_PATTERN, description="the console's session id")


class ViewEdit(_Strict):
    """A write to the shared view state: only the fields sent change; null clears one."""

    sequence: DbId | None = None
    rank: DbId | None = None
    mag: Number = Field(default=6.0, ge=-2.0, le=7.0, allow_inf_nan=False)
    #: The name typed in this console (null or blank: none): the 3D view's Confirm, drawing this session,
    #: confirms under it.
    operator: OperatorName | None = None

    def changes(self) -> dict:
        """The fields the client actually sent."""
        return {name: getattr(self, name) for name in self.model_fields_set}


class CalibrateRequest(_Strict):
    """Who calibrates, and which optical parameters to fit (default focal length, principal point, k1)."""

    operator: OperatorName | None = None
    parameters: list[Literal["f", "focal_length_px", "cx", "cy", "k1", "k2"]] | None = Field(
        default=None, min_length=1, max_length=6)
