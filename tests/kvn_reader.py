"""A small reader of CCSDS ADM 2.0 APM and AEM messages in KVN, for the tests.

It reads what :mod:`app.ccsds` writes back into plain Python values, checking
the layout of the standard's tables (CCSDS 504.0-B-2), so the tests can
assert what a message says without trusting the writer.  (A second,
fully independent parser, ``ccsds-ndm-py``, checks the messages in
``test_ccsds_independent.py``.)
"""

from __future__ import annotations

import re
from datetime import datetime, timedelta, timezone

from app.ccsds import _AEM_VERSION_KEYWORD, _APM_VERSION_KEYWORD, MAX_LINE_LENGTH, KvnError

_APM_HEADER = ("CLASSIFICATION", "CREATION_DATE", "ORIGINATOR", "MESSAGE_ID")
_APM_METADATA = ("OBJECT_NAME", "OBJECT_ID", "CENTER_NAME", "TIME_SYSTEM")
_AEM_METADATA = ("OBJECT_NAME", "OBJECT_ID", "CENTER_NAME", "REF_FRAME_A", "REF_FRAME_B",
                 "TIME_SYSTEM", "START_TIME", "USEABLE_START_TIME", "USEABLE_STOP_TIME",
                 "STOP_TIME", "ATTITUDE_TYPE", "EULER_ROT_SEQ", "ANGVEL_FRAME",
                 "INTERPOLATION_METHOD", "INTERPOLATION_DEGREE")
_APM_BLOCKS = {"QUAT", "EULER", "ANGVEL", "SPIN", "INERTIA", "MAN"}
_REAL = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")
_EPOCH = re.compile(r"^(\d{4})-(?:(\d{2})-(\d{2})|(\d{3}))T(\d{2}):(\d{2}):(\d{2})(\.\d+)?Z?$")


def parse_epoch(text: str) -> datetime:
    """A 6.8.9 time tag (calendar or day-of-year form) as an aware UTC datetime.

    Fractions beyond microseconds are truncated; a leap second (ss = 60) is
    refused because datetime cannot represent it.
    """
    m = _EPOCH.match(text.strip())
    if not m:
        raise KvnError(f"not a CCSDS epoch: {text!r}")
    year, month, day, doy, hh, mm, ss, frac = m.groups()
    micro = int((frac[1:] + "000000")[:6]) if frac else 0
    try:
        if doy is not None:
            base = datetime(int(year), 1, 1, tzinfo=timezone.utc) + timedelta(days=int(doy) - 1)
            if base.year != int(year):
                raise ValueError("day of year out of range")
            return base.replace(hour=int(hh), minute=int(mm), second=int(ss), microsecond=micro)
        return datetime(int(year), int(month), int(day), int(hh), int(mm), int(ss), micro,
                        tzinfo=timezone.utc)
    except ValueError as exc:
        raise KvnError(f"not a valid epoch: {text!r} ({exc})") from None


def _number(text: str, where: str) -> float:
    value = re.sub(r"\s*\[[^\]]*\]\s*$", "", text).strip()  # drop optional "[unit]" (6.9.1)
    if not _REAL.match(value):
        raise KvnError(f"{where}: not a number: {text!r}")
    return float(value)


def _tokens(text: str) -> list[tuple[int, str, str | None]]:
    """(line number, keyword, value) for each non-blank line; value None for markers/data."""
    out = []
    for number, raw in enumerate(re.split(r"\r\n|\n\r|\r|\n", text), start=1):
        if len(raw) > MAX_LINE_LENGTH:
            raise KvnError(f"line {number}: longer than {MAX_LINE_LENGTH} characters")
        if any(not (32 <= ord(ch) < 127) for ch in raw):
            raise KvnError(f"line {number}: characters other than printable ASCII")
        line = raw.strip()
        if not line:
            continue
        if line == "COMMENT" or line.startswith("COMMENT "):
            out.append((number, "COMMENT", line[len("COMMENT"):].strip()))
        elif "=" in line:
            keyword, value = (part.strip() for part in line.split("=", 1))
            if not re.fullmatch(r"[A-Z0-9_]+", keyword):
                raise KvnError(f"line {number}: keyword {keyword!r} is not upper case without blanks")
            if not value:
                raise KvnError(f"line {number}: {keyword} has an empty value")
            out.append((number, keyword, value))
        else:
            out.append((number, line, None))
    if not out:
        raise KvnError("empty message")
    return out


def parse_kvn(text: str) -> dict:
    """Read an ADM 2.0 APM or AEM in KVN into plain Python values.

    Returns ``{"type": "APM"|"AEM", "version": str, "keywords": [...],
    "header": {...}, ...}`` where ``keywords`` lists every keyword, marker
    (``QUAT_START``...) and ``<DATA>`` line in file order, and section dicts
    map keywords to values with their comments under ``"COMMENT"``.

    * APM: ``"metadata"``, ``"data"`` = {"COMMENT", "EPOCH", "blocks": [{"block":
      "QUAT", "COMMENT": [...], "REF_FRAME_A": ..., "Q1": float, ...}]}.
    * AEM: ``"segments"`` = [{"metadata": {...}, "data": {"COMMENT": [...],
      "lines": [[epoch_str, float, ...], ...]}}].

    Epoch values are kept as strings (see :func:`parse_epoch`); values in
    quaternion, Euler, rate and inertia blocks become floats.  Raises
    :class:`KvnError` when the text does not follow the layout of the
    standard's tables (keyword in the wrong section, unknown keyword, missing
    mandatory keyword, block not closed...).
    """
    tokens = _tokens(text)
    number, keyword, version = tokens[0]
    if keyword == _APM_VERSION_KEYWORD:
        kind = "APM"
    elif keyword == _AEM_VERSION_KEYWORD:
        kind = "AEM"
    else:
        raise KvnError(f"line {number}: the first line must be CCSDS_APM_VERS or CCSDS_AEM_VERS")
    result: dict = {"type": kind, "version": version, "keywords": [keyword]}
    rest = _parse_header(tokens[1:], result)
    if kind == "APM":
        _parse_apm_body(rest, result)
    else:
        _parse_aem_body(rest, result)
    return result


def _parse_header(tokens, result) -> list:
    header, i = _take_section(tokens, 0, _APM_HEADER, result, ("CREATION_DATE", "ORIGINATOR"))
    result["header"] = header
    return tokens[i:]


def _take_section(tokens, i, allowed, result, mandatory) -> tuple[dict, int]:
    """Leading COMMENTs then keywords of ``allowed`` in table order."""
    section: dict = {"COMMENT": []}
    while i < len(tokens) and tokens[i][1] == "COMMENT":
        section["COMMENT"].append(tokens[i][2])
        result["keywords"].append("COMMENT")
        i += 1
    last = -1
    while i < len(tokens) and tokens[i][1] in allowed:
        number, keyword, value = tokens[i]
        position = allowed.index(keyword)
        if position <= last:
            raise KvnError(f"line {number}: {keyword} out of order or repeated")
        last = position
        section[keyword] = value
        result["keywords"].append(keyword)
        i += 1
    for keyword in mandatory:
        if keyword not in section:
            raise KvnError(f"section lacks mandatory {keyword}")
    return section, i


def _parse_apm_body(tokens, result) -> None:
    metadata, i = _take_section(tokens, 0, _APM_METADATA, result,
                                ("OBJECT_NAME", "OBJECT_ID", "TIME_SYSTEM"))
    result["metadata"] = metadata
    data, i = _take_section(tokens, i, ("EPOCH",), result, ("EPOCH",))
    data["blocks"] = []
    while i < len(tokens):
        number, marker, value = tokens[i]
        if value is not None or not marker.endswith("_START") or marker[:-6] not in _APM_BLOCKS:
            raise KvnError(f"line {number}: expected the start of an APM data block, got {marker!r}")
        name = marker[:-6]
        result["keywords"].append(marker)
        block: dict = {"block": name, "COMMENT": []}
        i += 1
        while i < len(tokens) and tokens[i][1] == "COMMENT":
            block["COMMENT"].append(tokens[i][2])
            result["keywords"].append("COMMENT")
            i += 1
        while i < len(tokens) and tokens[i][1] != f"{name}_STOP":
            number, keyword, value = tokens[i]
            if value is None or keyword == "COMMENT":
                raise KvnError(f"line {number}: {keyword!r} inside {name} block (comments only at its start)")
            if keyword in block:
                raise KvnError(f"line {number}: {keyword} repeated in {name} block")
            textual = keyword.startswith("REF_FRAME") or keyword.endswith("FRAME") \
                or keyword in ("EULER_ROT_SEQ", "MAN_EPOCH_START")
            block[keyword] = value if textual else _number(value, f"line {number}")
            result["keywords"].append(keyword)
            i += 1
        if i == len(tokens):
            raise KvnError(f"{name}_START without {name}_STOP")
        result["keywords"].append(f"{name}_STOP")
        i += 1
        if name == "QUAT":
            order = [k for k in block if k not in ("block", "COMMENT")]
            expected = ["REF_FRAME_A", "REF_FRAME_B", "Q1", "Q2", "Q3", "QC"]
            if order[:6] != expected:
                raise KvnError(f"QUAT block keywords {order} are not in the order {expected}")
        data["blocks"].append(block)
    if not data["blocks"]:
        raise KvnError("an APM needs at least one data block")
    result["data"] = data


def _parse_aem_body(tokens, result) -> None:
    segments = []
    i = 0
    while i < len(tokens):
        number, marker, value = tokens[i]
        if marker != "META_START" or value is not None:
            raise KvnError(f"line {number}: expected META_START, got {marker!r}")
        result["keywords"].append("META_START")
        metadata, i = _take_section(tokens, i + 1, _AEM_METADATA, result,
                                    ("OBJECT_NAME", "OBJECT_ID", "REF_FRAME_A", "REF_FRAME_B",
                                     "TIME_SYSTEM", "START_TIME", "STOP_TIME", "ATTITUDE_TYPE"))
        for expected in ("META_STOP", "DATA_START"):
            if i == len(tokens) or tokens[i][1] != expected or tokens[i][2] is not None:
                got = tokens[i][1] if i < len(tokens) else "end of text"
                raise KvnError(f"expected {expected}, got {got!r}")
            result["keywords"].append(expected)
            i += 1
        data: dict = {"COMMENT": [], "lines": []}
        while i < len(tokens) and tokens[i][1] == "COMMENT":
            data["COMMENT"].append(tokens[i][2])
            result["keywords"].append("COMMENT")
            i += 1
        n_values = {"QUATERNION": 4, "QUATERNION/DERIVATIVE": 8, "QUATERNION/ANGVEL": 7,
                    "EULER_ANGLE": 3, "EULER_ANGLE/DERIVATIVE": 6, "EULER_ANGLE/ANGVEL": 6,
                    "SPIN": 4, "SPIN/NUTATION": 7, "SPIN/NUTATION_MOM": 7}.get(metadata["ATTITUDE_TYPE"])
        if n_values is None:
            raise KvnError(f"unknown ATTITUDE_TYPE {metadata['ATTITUDE_TYPE']!r}")
        while i < len(tokens) and tokens[i][1] != "DATA_STOP":
            number, line, value = tokens[i]
            if value is not None:
                raise KvnError(f"line {number}: keyword {line} inside the data section")
            fields = line.split()
            if len(fields) != 1 + n_values:
                raise KvnError(f"line {number}: {len(fields) - 1} values, {n_values} expected")
            parse_epoch(fields[0])
            data["lines"].append([fields[0], *(_number(f, f"line {number}") for f in fields[1:])])
            result["keywords"].append("<DATA>")
            i += 1
        if i == len(tokens):
            raise KvnError("DATA_START without DATA_STOP")
        result["keywords"].append("DATA_STOP")
        i += 1
        segments.append({"metadata": metadata, "data": data})
    if not segments:
        raise KvnError("an AEM needs at least one segment")
    result["segments"] = segments
