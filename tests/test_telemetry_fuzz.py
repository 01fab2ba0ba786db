"""Property tests: no input, however broken, raises anything but TelemetryError.

Whatever parses must satisfy the Sequence invariants (finite coordinates on
the sensor, non-negative brightness, unique indices, strictly increasing UTC
times, limits respected) and survive a dump/parse round trip unchanged.
"""

from __future__ import annotations

import copy
import json
import math
from datetime import datetime, timedelta, timezone

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from app.camera import CAMERAS, Camera
from app.config import MAX_SNAPSHOTS, MAX_SOURCES_PER_SNAPSHOT
from app.telemetry import Sequence, TelemetryError, dump_csv, dump_json, parse_telemetry

FAST = settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
UTC = timezone.utc
CSV_HEADER = "snapshot,time,x,y,brightness"


# =============================================================================
# the oracle: what any returned Sequence must satisfy
# =============================================================================
def assert_sequence_invariants(seq: Sequence) -> None:
    assert isinstance(seq, Sequence)
    assert isinstance(seq.sequence_id, str) and 0 < len(seq.sequence_id) <= 128
    cam = seq.camera
    assert isinstance(cam, Camera)
    assert isinstance(cam.width, int) and isinstance(cam.height, int)
    assert 1 <= cam.width <= 100_000 and 1 <= cam.height <= 100_000
    assert math.isfinite(cam.focal_length_px) and cam.focal_length_px > 0
    assert all(math.isfinite(v) for v in (cam.cx, cam.cy, cam.k1, cam.k2))
    assert abs(cam.k1) <= 10 and abs(cam.k2) <= 10
    assert 1 <= len(seq.snapshots) <= MAX_SNAPSHOTS
    indices = [s.index for s in seq.snapshots]
    assert len(set(indices)) == len(indices) and all(isinstance(i, int) and i >= 0 for i in indices)
    times = [s.time for s in seq.snapshots]
    assert all(t.utcoffset() == timedelta(0) for t in times)
    assert all(a < b for a, b in zip(times, times[1:]))
    for snap in seq.snapshots:
        n = snap.n_sources
        assert n <= MAX_SOURCES_PER_SNAPSHOT
        assert snap.xy.shape == (n, 2) and snap.xy.dtype == np.float64
        assert snap.brightness.shape == (n,) and snap.brightness.dtype == np.float64
        assert np.all(np.isfinite(snap.xy)) and np.all(np.isfinite(snap.brightness))
        assert np.all(snap.brightness >= 0)
        assert np.all(snap.xy >= -0.5)
        assert np.all(snap.xy[:, 0] <= cam.width - 0.5) and np.all(snap.xy[:, 1] <= cam.height - 0.5)
    if seq.velocity_km_s is not None:
        assert len(seq.velocity_km_s) == 3 and math.hypot(*seq.velocity_km_s) < 100
    # Whatever was accepted can be written and read back unchanged.
    again = parse_telemetry(dump_json(seq))
    assert dump_json(again) == dump_json(seq)
    assert dump_csv(parse_telemetry(dump_csv(seq))) == dump_csv(seq)


def assert_error_is_presentable(err: TelemetryError) -> None:
    """The documented error: problems, a printable message, a JSON-ready dict."""
    assert 1 <= len(err.problems) <= 50
    text = str(err)
    text.encode("utf-8")  # printable on any UTF-8 console
    json.dumps(err.to_dict()).encode("utf-8")
    for problem in err.problems:
        assert problem.location and problem.message


def parse_or_error(data, **kwargs) -> Sequence | TelemetryError:
    """Parse; any exception other than TelemetryError fails the test."""
    try:
        seq = parse_telemetry(data, **kwargs)
    except TelemetryError as err:
        assert_error_is_presentable(err)
        return err
    assert_sequence_invariants(seq)
    return seq


# =============================================================================
# (a) arbitrary input
# =============================================================================
@FAST
@given(st.binary(max_size=400))
def test_arbitrary_bytes(data):
    parse_or_error(data)


@FAST
@given(st.text(max_size=300))
def test_arbitrary_text(data):
    parse_or_error(data)


@FAST
@given(st.sampled_from(["{", "[", CSV_HEADER + "\n", "# camera: tubsat-752x582-20deg\n" + CSV_HEADER + "\n0,"]),
       st.text(alphabet=st.sampled_from(list('{}[]",:0123456789.eE-+ \nabcxyzNaInfity#=')), max_size=200))
def test_arbitrary_text_behind_a_plausible_start(start, rest):
    parse_or_error(start + rest, filename="fuzz.txt")


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=8),
    lambda children: st.lists(children, max_size=3) | st.dictionaries(st.text(max_size=5), children, max_size=3),
    max_leaves=10,
)


@FAST
@given(json_values)
def test_arbitrary_json_values(value):
    parse_or_error(json.dumps(value))
    if isinstance(value, dict):
        parse_or_error(json.dumps({"sequence_id": "F", "snapshots": [value]}))


# =============================================================================
# (b) mutations of valid documents
# =============================================================================
@st.composite
def valid_documents(draw) -> dict:
    """A valid JSON document: a named or explicit camera, 1..4 snapshots."""
    name = draw(st.sampled_from(sorted(CAMERAS)))
    camera = CAMERAS[name]
    block = name if draw(st.booleans()) else {k: v for k, v in camera.to_dict().items() if k != "name"}
    start = datetime(1990, 1, 1, tzinfo=UTC) + timedelta(seconds=draw(st.integers(0, 10**9)))
    snapshots = []
    time, index = start, draw(st.integers(0, 5))
    for _ in range(draw(st.integers(1, 4))):
        time += timedelta(milliseconds=draw(st.integers(1, 10**6)))
        n = draw(st.integers(0, 4))
        sources = [{"x": draw(st.floats(-0.5, camera.width - 0.5)),
                    "y": draw(st.floats(-0.5, camera.height - 0.5)),
                    "brightness": draw(st.floats(0, 1e6))} for _ in range(n)]
        index += draw(st.integers(1, 3))
        snapshots.append({"index": index, "time": time.isoformat(), "sources": sources})
    return {"format": "tubsat-snapshots/1", "sequence_id": "S-1", "spacecraft": "TUBSAT-A",
            "camera": block, "snapshots": snapshots}


def leaf_paths(node, path=()):
    """Paths to every scalar of a JSON tree."""
    if isinstance(node, dict):
        for key, child in node.items():
            yield from leaf_paths(child, path + (key,))
    elif isinstance(node, list):
        for i, child in enumerate(node):
            yield from leaf_paths(child, path + (i,))
    else:
        yield path


def node_paths(node, path=()):
    """Paths to every node (objects, arrays, scalars) below the root."""
    if path:
        yield path
    children = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else []
    for key, child in children:
        yield from node_paths(child, path + (key,))


def location_of(path) -> str:
    """('snapshots', 0, 'sources', 1, 'x') -> 'snapshots[0].sources[1].x'"""
    text = ""
    for part in path:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else part)
    return text


def set_at(doc, path, value) -> None:
    for key in path[:-1]:
        doc = doc[key]
    # A copy: st.just() hands out the same object every time, and a later edit
    # of this document must not change what the next example draws.
    doc[path[-1]] = copy.deepcopy(value)


def delete_at(doc, path) -> None:
    for key in path[:-1]:
        doc = doc[key]
    del doc[path[-1]]


garbage = st.one_of(
    st.none(), st.booleans(), st.integers(-10**30, 10**30), st.floats(), st.text(max_size=10),
    st.just([[[[[[{"a": [1, {"b": None}]}]]]]]]), st.just({"x": {"y": {"z": []}}}),
    st.just(10**400), st.just(1e308), st.just(-1e308), st.just("1994-03-12T21:04:10Z"),
)


@st.composite
def mutated_documents(draw) -> str:
    """A valid document after 1..3 random edits, serialised (maybe truncated)."""
    doc = draw(valid_documents())
    for _ in range(draw(st.integers(1, 3))):
        paths = list(node_paths(doc))
        kind = draw(st.sampled_from(["delete", "replace", "duplicate_snapshot", "swap_times", "nan"]))
        if kind == "delete" and paths:
            delete_at(doc, draw(st.sampled_from(paths)))
        elif kind == "replace" and paths:
            set_at(doc, draw(st.sampled_from(paths)), draw(garbage))
        elif kind == "duplicate_snapshot" and isinstance(doc.get("snapshots"), list) and doc["snapshots"]:
            doc["snapshots"].append(json.loads(json.dumps(draw(st.sampled_from(doc["snapshots"])))))
        elif kind == "swap_times" and isinstance(doc.get("snapshots"), list) and len(doc["snapshots"]) > 1:
            a, b = doc["snapshots"][0], doc["snapshots"][-1]
            if isinstance(a, dict) and isinstance(b, dict) and "time" in a and "time" in b:
                a["time"], b["time"] = b["time"], a["time"]
        elif kind == "nan":
            leaves = list(leaf_paths(doc))
            if leaves:
                set_at(doc, draw(st.sampled_from(leaves)), draw(st.sampled_from([math.nan, math.inf, -math.inf])))
    text = json.dumps(doc)  # allow_nan: writes NaN/Infinity tokens
    if draw(st.booleans()):
        text = text[: draw(st.integers(0, len(text)))]
    return text


@FAST
@given(mutated_documents())
def test_mutated_json_documents(text):
    parse_or_error(text)


@FAST
@given(valid_documents(), st.data())
def test_valid_documents_parse(doc, data):
    result = parse_or_error(json.dumps(doc))
    assert isinstance(result, Sequence), result
    assert [s.index for s in result.snapshots] == [s["index"] for s in doc["snapshots"]]
    for snap, raw in zip(result.snapshots, doc["snapshots"]):
        np.testing.assert_array_equal(snap.xy.reshape(-1), [v for s in raw["sources"] for v in (s["x"], s["y"])])


@FAST
@given(valid_documents(), st.data())
def test_any_non_finite_or_boolean_in_the_data_is_reported_where_it_is(doc, data):
    """Every number inside camera and snapshots is checked: NaN, +-Infinity
    and true/false there must be reported at exactly that path."""
    leaves = [p for p in leaf_paths(doc) if p[0] in ("camera", "snapshots") and p[-1] != "time"]
    if not leaves:
        return  # a named camera and no sources: nothing numeric but indices... which are leaves
    path = data.draw(st.sampled_from(leaves))
    set_at(doc, path, data.draw(st.sampled_from([math.nan, math.inf, -math.inf, True, False])))
    result = parse_or_error(json.dumps(doc))
    assert isinstance(result, TelemetryError)
    assert location_of(path) in [p.location for p in result.problems], (path, result.problems)


@st.composite
def mutated_csv(draw) -> str:
    """The CSV form of a valid document after line/cell edits."""
    doc = draw(valid_documents())
    lines = dump_csv(parse_telemetry(json.dumps(doc))).splitlines()
    for _ in range(draw(st.integers(1, 3))):
        i = draw(st.integers(0, len(lines) - 1))
        kind = draw(st.sampled_from(["delete", "duplicate", "swap", "cell", "insert"]))
        if kind == "delete" and len(lines) > 1:
            del lines[i]
        elif kind == "duplicate":
            lines.insert(i, lines[i])
        elif kind == "swap":
            j = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
        elif kind == "cell":
            cells = lines[i].split(",")
            k = draw(st.integers(0, len(cells) - 1))
            cells[k] = draw(st.sampled_from(["", "nan", "inf", "-1", "1e999", "abc", '"', "99999", "0"])
                            | st.text(max_size=6))
            lines[i] = ",".join(cells)
        elif kind == "insert":
            lines.insert(i, draw(st.text(max_size=20)))
    text = "\n".join(lines)
    if draw(st.booleans()):
        text = text[: draw(st.integers(0, len(text)))]
    return text


@FAST
@given(mutated_csv())
def test_mutated_csv_documents(text):
    parse_or_error(text)


def test_big_inputs_stay_fast_and_bounded():
    """Limits cut work short: 5000 snapshots or 10^5 rows are refused quickly."""
    base = datetime(2000, 1, 1, tzinfo=UTC)
    many = {"sequence_id": "B", "snapshots": [
        {"index": i, "time": (base + timedelta(seconds=i)).isoformat(), "sources": []} for i in range(5000)]}
    err = parse_or_error(json.dumps(many))
    assert [p.location for p in err.problems] == ["snapshots"]
    rows = "\n".join(f"0,2000-01-01T00:00:00Z,{i % 700},1,1" for i in range(100_000))
    err = parse_or_error("# sequence_id: B\n" + CSV_HEADER + "\n" + rows)
    assert [p.message for p in err.problems] == ["snapshot 0 has more than 64 sources"]
