"""CCSDS Attitude Data Messages, ADM 2.0 (CCSDS 504.0-B-2, January 2024), KVN form.

Three writers (a reader for the tests is in tests/kvn_reader.py, and the
tests also read every message with the independent ``ccsds-ndm-py``):

* :func:`apm_kvn` - an Attitude Parameter Message: one attitude at one epoch.
* :func:`aem_kvn` - an Attitude Ephemeris Message: one attitude per epoch
  (here: one per snapshot of a confirmed sequence).
* :func:`acm_kvn` - an Attitude Comprehensive Message (section 5): the
  attitude states of every snapshot with the body rate, the covariance of the
  determined attitude, and how it was determined (method, sensors): the
  standard slots for what the APM can only carry in comments.

Keywords, their order and the blocks follow the standard's tables 3-1..3-3
(APM) and 4-2..4-4 (AEM); only version 2.0 keywords are written.  In 2.0 the
APM has no META_START/META_STOP and no Q_DIR, the AEM has no ATTITUDE_DIR and
no QUATERNION_TYPE: the quaternion always goes from REF_FRAME_A to
REF_FRAME_B and its scalar part QC is always written last (APM ``Q1 Q2 Q3 QC``
block, AEM data line ``EPOCH Q1 Q2 Q3 QC``).

Frames and the direction of the quaternion
------------------------------------------
REF_FRAME_A = ``ICRF``; REF_FRAME_B = :data:`CAMERA_FRAME` (``SENSOR_1``, a
spacecraft-body frame name of the SANA registry that annex B3 points to).
``SENSOR_1`` is *our camera frame*: +x along increasing pixel column, +y along
increasing pixel row, +z the boresight (see :mod:`app.camera`).  It is not the
spacecraft body frame: the camera's mounting on the bus is not known here.

Annex F2 defines the quaternion "from frame A to frame B" as the rotation
that carries the basis vectors of A onto those of B, and gives the matrix
that transforms coordinates, ``X_B = M_BA(q) X_A``.  With A = ICRF and
B = camera, ``M_BA`` is exactly this project's ``rotation_matrix`` R
(``v_cam = R @ v_icrs``).  Our messages therefore describe ICRF -> camera.

Careful: the project's scalar-last quaternion (:func:`app.attitude.quaternion_from_rotation`,
scipy's convention) is the quaternion whose *active* rotation matrix is R,
while the standard's ``M_BA(q)`` is the transpose of the active matrix of q.
So the file holds the conjugate: ``(Q1, Q2, Q3, QC) = (-x, -y, -z, w)`` of
the project's ``[x, y, z, w]``.  :func:`ccsds_quaternion_from_rotation` and
:func:`rotation_from_ccsds_quaternion` implement annex F2 directly so that
this never has to be remembered by callers: the writers take the project's
quaternion and convert.
"""

from __future__ import annotations

import math
import re
import textwrap
import unicodedata
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone

import numpy as np

#: REF_FRAME_A of every message we write: the International Celestial Reference Frame.
ICRF = "ICRF"
#: REF_FRAME_B: our camera frame (+x column, +y row, +z boresight); see the module docstring.
CAMERA_FRAME = "SENSOR_1"
#: Times in our messages are UTC (annex B2 value).
TIME_SYSTEM = "UTC"
#: Longest line the standard allows in an APM or AEM (6.6.1), line terminator excluded.
MAX_LINE_LENGTH = 254

_APM_VERSION_KEYWORD = "CCSDS_APM_VERS"
_AEM_VERSION_KEYWORD = "CCSDS_AEM_VERS"
_ACM_VERSION_KEYWORD = "CCSDS_ACM_VERS"
#: AD_METHOD values of the ACM's attitude determination block.
AD_METHODS = ("EKF", "TRIAD", "QUEST", "BATCH", "Q_METHOD", "FILTER_SMOOTHER")
_VERSION = "2.0"


class KvnError(ValueError):
    """Malformed input to a writer, or a KVN text that does not follow ADM 2.0."""


# ---------------------------------------------------------------------------
# Quaternions (annex F2)
# ---------------------------------------------------------------------------

def rotation_from_ccsds_quaternion(q1: float, q2: float, q3: float, qc: float) -> np.ndarray:
    """Annex F2's ``M_BA``: the matrix with ``X_B = M_BA @ X_A`` for the quaternion A -> B.

    Written out term by term as in the standard (not via a library) so that
    the tests check our files against the standard's own formula.
    """
    n = math.sqrt(q1 * q1 + q2 * q2 + q3 * q3 + qc * qc)
    q1, q2, q3, qc = q1 / n, q2 / n, q3 / n, qc / n
    return np.array([
        [q1 * q1 - q2 * q2 - q3 * q3 + qc * qc, 2 * (q1 * q2 + q3 * qc), 2 * (q1 * q3 - q2 * qc)],
        [2 * (q1 * q2 - q3 * qc), -q1 * q1 + q2 * q2 - q3 * q3 + qc * qc, 2 * (q2 * q3 + q1 * qc)],
        [2 * (q1 * q3 + q2 * qc), 2 * (q2 * q3 - q1 * qc), -q1 * q1 - q2 * q2 + q3 * q3 + qc * qc],
    ])


def ccsds_quaternion_from_project(quaternion_xyzw: Sequence[float]) -> tuple[float, float, float, float]:
    """(Q1, Q2, Q3, QC) of the file from the project's scalar-last quaternion of R.

    The project's ``[x, y, z, w]`` has active matrix R; the standard's M_BA is
    the transpose of the active matrix, so the file's quaternion is the
    conjugate ``(-x, -y, -z, w)``.  The input is normalised; it must be
    finite and of unit norm to 1e-6 (anything else is a caller's bug).
    """
    q = np.asarray(quaternion_xyzw, dtype=float)
    if q.shape != (4,) or not np.all(np.isfinite(q)):
        raise KvnError("a quaternion needs four finite numbers [x, y, z, w]")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > 1e-6:
        raise KvnError(f"quaternion is not of unit norm (|q| = {norm:.9g})")
    x, y, z, w = q / norm
    if w < 0:  # same rotation, conventional sign: scalar part >= 0
        x, y, z, w = -x, -y, -z, -w
    return (float(-x), float(-y), float(-z), float(w))


def ccsds_quaternion_from_rotation(rotation_matrix: np.ndarray) -> tuple[float, float, float, float]:
    """(Q1, Q2, Q3, QC) with ``M_BA(q) = rotation_matrix``, QC >= 0 (Shepperd's method)."""
    m = np.asarray(rotation_matrix, dtype=float)
    # Invert the F2 matrix: the trace gives QC, the antisymmetric part the
    # vector part; pick the largest diagonal term for numerical stability.
    t = np.trace(m)
    candidates = [t, m[0, 0], m[1, 1], m[2, 2]]
    k = int(np.argmax(candidates))
    if k == 0:
        qc = 0.5 * math.sqrt(max(1.0 + t, 0.0))
        q1 = (m[1, 2] - m[2, 1]) / (4 * qc)
        q2 = (m[2, 0] - m[0, 2]) / (4 * qc)
        q3 = (m[0, 1] - m[1, 0]) / (4 * qc)
    elif k == 1:
        q1 = 0.5 * math.sqrt(max(1.0 + 2 * m[0, 0] - t, 0.0))
        qc = (m[1, 2] - m[2, 1]) / (4 * q1)
        q2 = (m[0, 1] + m[1, 0]) / (4 * q1)
        q3 = (m[0, 2] + m[2, 0]) / (4 * q1)
    elif k == 2:
        q2 = 0.5 * math.sqrt(max(1.0 + 2 * m[1, 1] - t, 0.0))
        qc = (m[2, 0] - m[0, 2]) / (4 * q2)
        q1 = (m[0, 1] + m[1, 0]) / (4 * q2)
        q3 = (m[1, 2] + m[2, 1]) / (4 * q2)
    else:
        q3 = 0.5 * math.sqrt(max(1.0 + 2 * m[2, 2] - t, 0.0))
        qc = (m[0, 1] - m[1, 0]) / (4 * q3)
        q1 = (m[0, 2] + m[2, 0]) / (4 * q3)
        q2 = (m[1, 2] + m[2, 1]) / (4 * q3)
    q = np.array([q1, q2, q3, qc])
    q /= np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return tuple(float(v) for v in q)


# ---------------------------------------------------------------------------
# Value formatting (section 6.8)
# ---------------------------------------------------------------------------

def format_epoch(t: datetime) -> str:
    """6.8.9 ``YYYY-MM-DDThh:mm:ss.dddddd`` in UTC; naive datetimes are refused."""
    if not isinstance(t, datetime) or t.tzinfo is None or t.utcoffset() is None:
        raise KvnError("epochs must be timezone-aware datetimes")
    return t.astimezone(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%f")


def format_quaternion_component(v: float) -> str:
    """Fixed point with 15 decimals: 16 digits, the most 6.8.4.1 allows, ~1e-15 resolution.

    "-0" is not a supported value (6.8.5), so a negative zero after rounding
    is written without its sign.
    """
    s = f"{v:.15f}"
    if s.startswith("-") and float(s) == 0.0:
        s = s[1:]
    return s


def _ascii_text(text: str, escape: bool = False) -> str:
    """Printable ASCII only (6.6.3): accents dropped; other characters become '?', or with ``escape`` (for
    comments) their Python escape (``\\u5f20``), so that an operator named in Chinese or Cyrillic stays
    that operator in the message (two names of '??' would be one), readable back with ``unicode_escape``."""
    out = []
    for ch in str(text):
        plain = "".join(c for c in unicodedata.normalize("NFKD", ch) if not unicodedata.combining(c))
        if plain and all(32 <= ord(c) < 127 for c in plain):  # ASCII, or a Latin letter with its accents
            out.append(plain)
        elif ch.isspace():
            out.append(" ")
        elif escape and unicodedata.category(ch)[0] in "LNPS":  # letters, digits, punctuation, symbols
            out.append(ch.encode("unicode_escape").decode("ascii"))
        else:  # control, format (bidirectional overrides) and unassigned characters say nothing
            out.append("?")
    return "".join(out)


def text_value(text: str, keyword: str) -> str:
    """A text value as 6.8.6/6.8.8 want it: printable ASCII, upper case, single blanks."""
    value = re.sub(r"\s+", " ", _ascii_text(text)).strip().upper()
    if not value:
        raise KvnError(f"{keyword} needs a non-empty value")
    if len(keyword) + 3 + len(value) > MAX_LINE_LENGTH:
        raise KvnError(f"{keyword} value is too long for a {MAX_LINE_LENGTH}-character line")
    return value


def comment_lines(comments: Iterable[str]) -> list[str]:
    """COMMENT lines (6.10.1): ASCII (other characters escaped, see :func:`_ascii_text`), one per input line,
    long ones wrapped between words at 254 characters (a word longer than a line is cut)."""
    width = MAX_LINE_LENGTH - len("COMMENT ")
    lines: list[str] = []
    for comment in comments:
        for part in _ascii_text(str(comment).replace("\r", "\n"), escape=True).split("\n"):
            part = part.rstrip()
            chunks = textwrap.wrap(part, width, break_on_hyphens=False) if len(part) > width else [part]
            lines.extend(f"COMMENT {chunk}".rstrip() for chunk in chunks)
    return lines


def _kv(keyword: str, value: str) -> str:
    return f"{keyword} = {value}"


def _header(version_keyword: str, *, originator: str, creation_date: datetime | None,
            message_id: str | None, header_comments: Iterable[str]) -> list[str]:
    """Tables 3-1 / 4-2: version, comments, CREATION_DATE, ORIGINATOR, MESSAGE_ID."""
    created = creation_date if creation_date is not None else datetime.now(timezone.utc)
    lines = [_kv(version_keyword, _VERSION)]
    lines += comment_lines(header_comments)
    lines.append(_kv("CREATION_DATE", format_epoch(created)))
    lines.append(_kv("ORIGINATOR", text_value(originator, "ORIGINATOR")))
    if message_id is not None:
        lines.append(_kv("MESSAGE_ID", text_value(message_id, "MESSAGE_ID")))
    return lines


def _finish(lines: list[str]) -> str:
    for line in lines:
        if len(line) > MAX_LINE_LENGTH:  # only reachable through a bug above
            raise KvnError(f"line longer than {MAX_LINE_LENGTH} characters: {line[:40]}...")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------
# Writers
# ---------------------------------------------------------------------------

def apm_kvn(*, epoch: datetime, quaternion_xyzw: Sequence[float], originator: str,
            object_name: str, object_id: str, ref_frame_a: str = ICRF,
            ref_frame_b: str = CAMERA_FRAME, center_name: str | None = "EARTH",
            comments: Iterable[str] = (), header_comments: Iterable[str] = (),
            quaternion_comments: Iterable[str] = (), message_id: str | None = None,
            creation_date: datetime | None = None) -> str:
    """An APM 2.0 in KVN holding one attitude quaternion at ``epoch``.

    ``quaternion_xyzw`` is the project's scalar-last quaternion of the
    ICRS -> camera rotation R (as :attr:`Candidate.quaternion`); the file gets
    the annex-F2 quaternion from ``ref_frame_a`` to ``ref_frame_b`` (its
    conjugate, see the module docstring), so ``M_BA(Q) = R``.

    Layout (tables 3-1, 3-2, 3-3; no META_START in an APM):
    header (CCSDS_APM_VERS, COMMENT*, CREATION_DATE, ORIGINATOR, MESSAGE_ID?),
    metadata (OBJECT_NAME, OBJECT_ID, CENTER_NAME?, TIME_SYSTEM),
    data (COMMENT*, EPOCH, QUAT_START, COMMENT*, REF_FRAME_A, REF_FRAME_B,
    Q1, Q2, Q3, QC, QUAT_STOP).  ``comments`` go before EPOCH (they describe
    the attitude: deviation, false-match probability, operator...).
    Output is deterministic for equal inputs when ``creation_date`` is given;
    without it the current UTC time is used.  Text values are upper-cased and
    reduced to ASCII as 6.6.3/6.8.6 require.  Raises :class:`KvnError`.
    """
    q1, q2, q3, qc = ccsds_quaternion_from_project(quaternion_xyzw)
    lines = _header(_APM_VERSION_KEYWORD, originator=originator, creation_date=creation_date,
                    message_id=message_id, header_comments=header_comments)
    lines.append("")
    lines.append(_kv("OBJECT_NAME", text_value(object_name, "OBJECT_NAME")))
    lines.append(_kv("OBJECT_ID", text_value(object_id, "OBJECT_ID")))
    if center_name is not None:
        lines.append(_kv("CENTER_NAME", text_value(center_name, "CENTER_NAME")))
    lines.append(_kv("TIME_SYSTEM", TIME_SYSTEM))
    lines.append("")
    lines += comment_lines(comments)
    lines.append(_kv("EPOCH", format_epoch(epoch)))
    lines.append("")
    lines.append("QUAT_START")
    lines += comment_lines(quaternion_comments)
    lines.append(_kv("REF_FRAME_A", text_value(ref_frame_a, "REF_FRAME_A")))
    lines.append(_kv("REF_FRAME_B", text_value(ref_frame_b, "REF_FRAME_B")))
    for keyword, value in zip(("Q1", "Q2", "Q3", "QC"), (q1, q2, q3, qc)):
        lines.append(_kv(keyword, format_quaternion_component(value)))
    lines.append("QUAT_STOP")
    return _finish(lines)


def aem_kvn(*, epochs: Sequence[datetime], quaternions_xyzw: Sequence[Sequence[float]],
            originator: str, object_name: str, object_id: str, ref_frame_a: str = ICRF,
            ref_frame_b: str = CAMERA_FRAME, center_name: str | None = "EARTH",
            comments: Iterable[str] = (), header_comments: Iterable[str] = (),
            data_comments: Iterable[str] = (), message_id: str | None = None,
            creation_date: datetime | None = None) -> str:
    """An AEM 2.0 in KVN: one segment, ATTITUDE_TYPE = QUATERNION, one line per epoch.

    Quaternions are the project's scalar-last quaternions of R, converted as
    in :func:`apm_kvn`; each data line is ``EPOCH Q1 Q2 Q3 QC`` (table 4-4).
    Epochs must be strictly increasing (4.2.4.8.1); START_TIME and STOP_TIME
    are the first and last epoch.  ``comments`` go at the start of the
    metadata (after META_START), ``data_comments`` right after DATA_START
    (6.10.3).  No INTERPOLATION_METHOD is given: the snapshots are the data.
    Raises :class:`KvnError`.
    """
    epochs = list(epochs)
    quats = list(quaternions_xyzw)
    if not epochs:
        raise KvnError("an AEM needs at least one epoch")
    if len(epochs) != len(quats):
        raise KvnError(f"{len(epochs)} epochs but {len(quats)} quaternions")
    stamps = [format_epoch(t) for t in epochs]
    for earlier, later in zip(epochs, epochs[1:]):
        if later - earlier <= timedelta(0):
            raise KvnError("AEM epochs must be strictly increasing")
    rows = [ccsds_quaternion_from_project(q) for q in quats]

    lines = _header(_AEM_VERSION_KEYWORD, originator=originator, creation_date=creation_date,
                    message_id=message_id, header_comments=header_comments)
    lines.append("")
    lines.append("META_START")
    lines += comment_lines(comments)
    lines.append(_kv("OBJECT_NAME", text_value(object_name, "OBJECT_NAME")))
    lines.append(_kv("OBJECT_ID", text_value(object_id, "OBJECT_ID")))
    if center_name is not None:
        lines.append(_kv("CENTER_NAME", text_value(center_name, "CENTER_NAME")))
    lines.append(_kv("REF_FRAME_A", text_value(ref_frame_a, "REF_FRAME_A")))
    lines.append(_kv("REF_FRAME_B", text_value(ref_frame_b, "REF_FRAME_B")))
    lines.append(_kv("TIME_SYSTEM", TIME_SYSTEM))
    lines.append(_kv("START_TIME", stamps[0]))
    lines.append(_kv("STOP_TIME", stamps[-1]))
    lines.append(_kv("ATTITUDE_TYPE", "QUATERNION"))
    lines.append("META_STOP")
    lines.append("")
    lines.append("DATA_START")
    lines += comment_lines(data_comments)
    for stamp, q in zip(stamps, rows):
        lines.append(" ".join([stamp, *(format_quaternion_component(v) for v in q)]))
    lines.append("DATA_STOP")
    return _finish(lines)


@dataclass(frozen=True)
class AcmSensor:
    """One sensor of an ACM's attitude determination block (SENSOR_START ... SENSOR_STOP)."""

    number: int
    used: str  # SENSOR_USED, e.g. STAR_TRACKER
    noise_stddev_deg: tuple[float, ...] = ()  # SENSOR_NOISE_STDDEV, deg
    frequency_hz: float | None = None  # SENSOR_FREQUENCY
    comments: tuple[str, ...] = ()


@dataclass(frozen=True)
class AcmDetermination:
    """An ACM's attitude determination block (AD_START ... AD_STOP)."""

    ad_id: str
    method: str  # one of AD_METHODS
    sensors: tuple[AcmSensor, ...]
    source: str | None = None  # ATTITUDE_SOURCE (free text)
    number_states: int | None = None
    attitude_states: str = "QUATERNION"
    cov_type: str | None = None  # "ANGLE" when the message has its covariance
    rate_states: str | None = None  # "ANGVEL" when the rate was estimated too
    comments: tuple[str, ...] = ()


def _real(value: float) -> str:
    """A real number as 6.8.4 allows (no "-0"), ten significant digits."""
    text = f"{float(value):.10g}"
    return text[1:] if text.startswith("-") and float(text) == 0.0 else text


def _seconds(t: datetime, t0: datetime) -> str:
    """``t`` as seconds after ``t0`` (the ACM's EPOCH_TZERO), to the microsecond."""
    delta = t - t0
    micro = (delta.days * 86400 + delta.seconds) * 1_000_000 + delta.microseconds
    return f"{micro // 1_000_000}.{micro % 1_000_000:06d}"


def acm_kvn(*, epochs: Sequence[datetime], quaternions_xyzw: Sequence[Sequence[float]], originator: str,
            object_name: str, rate_deg_s: Sequence[float] | None = None,
            covariance: tuple[datetime, Sequence[float]] | None = None,
            determination: AcmDetermination | None = None, ref_frame_a: str = ICRF,
            ref_frame_b: str = CAMERA_FRAME, center_name: str | None = "EARTH", att_id: str = "ATT_1",
            att_basis: str = "DETERMINED_GND", comments: Iterable[str] = (), header_comments: Iterable[str] = (),
            att_comments: Iterable[str] = (), cov_comments: Iterable[str] = (), message_id: str | None = None,
            creation_date: datetime | None = None) -> str:
    """An ACM 2.0 in KVN (CCSDS 504.0-B-2 section 5): one attitude state history, its covariance and
    its attitude determination.

    * Metadata (META_START ... META_STOP): OBJECT_NAME, CENTER_NAME,
      TIME_SYSTEM, EPOCH_TZERO (the first epoch; every time in the data is in
      seconds after it), ACM_DATA_ELEMENTS, START_TIME, STOP_TIME.
    * Attitude states (ATT_START ... ATT_STOP): ATT_ID, ATT_BASIS, ATT_BASIS_ID
      (the determination's AD_ID), REF_FRAME_A/B, NUMBER_STATES, ATT_TYPE =
      QUATERNION and, with ``rate_deg_s``, RATE_TYPE = ANGVEL; one line per
      epoch ``t Q1 Q2 Q3 QC [WX WY WZ]``.  The quaternions are the project's
      scalar-last quaternions of R converted as in :func:`apm_kvn`; the rate
      (deg/s) is the angular velocity of REF_FRAME_B relative to REF_FRAME_A in
      REF_FRAME_B's axes (this project's body rate in camera axes).
    * Covariance (COV_START ... COV_STOP), with ``covariance = (epoch,
      variances)``: COV_BASIS, COV_REF_FRAME = REF_FRAME_B, COV_TYPE = ANGLE,
      one line ``t VAR_X VAR_Y VAR_Z`` (deg**2, the attitude error about each
      axis of REF_FRAME_B).
    * Attitude determination (AD_START ... AD_STOP) from ``determination``.

    Epochs must be strictly increasing.  Output is deterministic for equal
    inputs when ``creation_date`` is given.  Raises :class:`KvnError`.
    """
    epochs = list(epochs)
    quats = list(quaternions_xyzw)
    if not epochs:
        raise KvnError("an ACM needs at least one attitude state")
    if len(epochs) != len(quats):
        raise KvnError(f"{len(epochs)} epochs but {len(quats)} quaternions")
    for earlier, later in zip(epochs, epochs[1:]):
        if later - earlier <= timedelta(0):
            raise KvnError("ACM epochs must be strictly increasing")
    rows = [ccsds_quaternion_from_project(q) for q in quats]
    rate = None if rate_deg_s is None else [float(w) for w in rate_deg_s]
    if rate is not None and (len(rate) != 3 or not all(map(math.isfinite, rate))):
        raise KvnError("the body rate needs three finite numbers (deg/s)")
    if determination is not None and determination.method not in AD_METHODS:
        raise KvnError(f"AD_METHOD must be one of {', '.join(AD_METHODS)}")
    t0 = epochs[0]
    frame_a, frame_b = text_value(ref_frame_a, "REF_FRAME_A"), text_value(ref_frame_b, "REF_FRAME_B")
    elements = ["ATT", *(["COV"] if covariance is not None else []), *(["AD"] if determination is not None else [])]

    lines = _header(_ACM_VERSION_KEYWORD, originator=originator, creation_date=creation_date,
                    message_id=message_id, header_comments=header_comments)
    lines += ["", "META_START"]
    lines += comment_lines(comments)
    lines.append(_kv("OBJECT_NAME", text_value(object_name, "OBJECT_NAME")))
    if center_name is not None:
        lines.append(_kv("CENTER_NAME", text_value(center_name, "CENTER_NAME")))
    lines.append(_kv("TIME_SYSTEM", TIME_SYSTEM))
    lines.append(_kv("EPOCH_TZERO", format_epoch(t0)))
    lines.append(_kv("ACM_DATA_ELEMENTS", " ".join(elements)))
    lines.append(_kv("START_TIME", format_epoch(epochs[0])))
    lines.append(_kv("STOP_TIME", format_epoch(epochs[-1])))
    lines.append("META_STOP")

    lines += ["", "ATT_START"]
    lines += comment_lines(att_comments)
    lines.append(_kv("ATT_ID", text_value(att_id, "ATT_ID")))
    lines.append(_kv("ATT_BASIS", text_value(att_basis, "ATT_BASIS")))
    if determination is not None:
        lines.append(_kv("ATT_BASIS_ID", text_value(determination.ad_id, "ATT_BASIS_ID")))
    lines.append(_kv("REF_FRAME_A", frame_a))
    lines.append(_kv("REF_FRAME_B", frame_b))
    lines.append(_kv("NUMBER_STATES", "4" if rate is None else "7"))
    lines.append(_kv("ATT_TYPE", "QUATERNION"))
    if rate is not None:
        lines.append(_kv("RATE_TYPE", "ANGVEL"))
    for t, q in zip(epochs, rows):
        values = [format_quaternion_component(v) for v in q] + ([_real(w) for w in rate] if rate is not None else [])
        lines.append(" ".join([_seconds(t, t0), *values]))
    lines.append("ATT_STOP")

    if covariance is not None:
        at, variances = covariance
        variances = [float(v) for v in variances]
        if len(variances) != 3 or not all(math.isfinite(v) and v >= 0 for v in variances):
            raise KvnError("an ANGLE covariance needs three finite variances (deg**2)")
        lines += ["", "COV_START"]
        lines += comment_lines(cov_comments)
        lines.append(_kv("COV_BASIS", text_value(att_basis, "COV_BASIS")))
        lines.append(_kv("COV_REF_FRAME", frame_b))
        lines.append(_kv("COV_TYPE", "ANGLE"))
        lines.append(" ".join([_seconds(at, t0), *(_real(v) for v in variances)]))
        lines.append("COV_STOP")

    if determination is not None:
        d = determination
        lines += ["", "AD_START"]
        lines += comment_lines(d.comments)
        lines.append(_kv("AD_ID", text_value(d.ad_id, "AD_ID")))
        lines.append(_kv("AD_METHOD", d.method))
        if d.source is not None:
            lines.append(_kv("ATTITUDE_SOURCE", text_value(d.source, "ATTITUDE_SOURCE")))
        if d.number_states is not None:
            lines.append(_kv("NUMBER_STATES", str(int(d.number_states))))
        lines.append(_kv("ATTITUDE_STATES", text_value(d.attitude_states, "ATTITUDE_STATES")))
        if d.cov_type is not None:
            lines.append(_kv("COV_TYPE", text_value(d.cov_type, "COV_TYPE")))
        lines.append(_kv("REF_FRAME_A", frame_a))
        lines.append(_kv("REF_FRAME_B", frame_b))
        if d.rate_states is not None:
            lines.append(_kv("RATE_STATES", text_value(d.rate_states, "RATE_STATES")))
        for sensor in d.sensors:
            lines.append("SENSOR_START")
            lines += comment_lines(sensor.comments)
            lines.append(_kv("SENSOR_NUMBER", str(int(sensor.number))))
            lines.append(_kv("SENSOR_USED", text_value(sensor.used, "SENSOR_USED")))
            if sensor.noise_stddev_deg:
                lines.append(_kv("SENSOR_NOISE_STDDEV", " ".join(_real(v) for v in sensor.noise_stddev_deg)))
            if sensor.frequency_hz is not None:
                lines.append(_kv("SENSOR_FREQUENCY", _real(sensor.frequency_hz)))
            lines.append("SENSOR_STOP")
        lines.append("AD_STOP")
    return _finish(lines)
