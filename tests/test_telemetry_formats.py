"""The `tubsat-snapshots/1` JSON and CSV forms: parsing, validation errors, round trips.

Each error class of issue 2 (item 2) has a test that checks both *where*
(the problem's location) and *why* (words from its message).
"""

from __future__ import annotations

import copy
import json
import re
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest

from app.camera import CAMERAS, Camera
from app.config import MAX_SNAPSHOTS, MAX_SOURCES_PER_SNAPSHOT, Settings
from app.telemetry import (Problem, Sequence, Snapshot, TelemetryError, dump_csv, dump_json,
                           load_telemetry_file, parse_telemetry)
from app.telemetry import formats
from app.telemetry.errors import MAX_PROBLEMS

UTC = timezone.utc
CAMERA_BLOCK = {"width": 752, "height": 582, "focal_length_px": 2132.4, "cx": 375.5, "cy": 290.5}


def valid_doc() -> dict:
    """The issue's example, grown to three snapshots (one without sources)."""
    return {
        "format": "tubsat-snapshots/1",
        "sequence_id": "A-0427",
        "spacecraft": "TUBSAT-A",
        "camera": dict(CAMERA_BLOCK),
        "snapshots": [
            {"index": 0, "time": "1994-03-12T21:04:10.000Z",
             "sources": [{"x": 16.0, "y": 334.0, "brightness": 255.0},
                         {"x": 700.25, "y": 12.5, "brightness": 80.0}]},
            {"index": 1, "time": "1994-03-12T21:04:10.500Z",
             "sources": [{"x": 17.0, "y": 333.0, "brightness": 250.0}]},
            {"index": 2, "time": "1994-03-12T21:04:11.000Z", "sources": []},
        ],
    }


def parse_doc(doc, **kwargs) -> Sequence:
    return parse_telemetry(json.dumps(doc), **kwargs)


def problems_of(data, **kwargs) -> list[Problem]:
    """Parse data that must be invalid; return the problems found."""
    with pytest.raises(TelemetryError) as info:
        if isinstance(data, dict):
            parse_doc(data, **kwargs)
        else:
            parse_telemetry(data, **kwargs)
    return info.value.problems


def assert_problem(problems: list[Problem], location: str, *words: str) -> None:
    """Some problem is at ``location`` and its message holds every word."""
    at = [p for p in problems if p.location == location]
    assert at, f"no problem at {location!r}; got {problems}"
    assert any(all(w.lower() in p.message.lower() for w in words) for p in at), \
        f"no problem at {location!r} mentions {words}; got {at}"


def assert_same_sequence(a: Sequence, b: Sequence) -> None:
    assert a.sequence_id == b.sequence_id
    assert a.spacecraft == b.spacecraft
    assert a.camera == b.camera
    assert a.velocity_km_s == b.velocity_km_s
    assert len(a.snapshots) == len(b.snapshots)
    for s, t in zip(a.snapshots, b.snapshots):
        assert s.index == t.index
        assert s.time == t.time
        assert s.xy.dtype == t.xy.dtype == np.float64
        assert s.xy.shape == t.xy.shape
        np.testing.assert_array_equal(s.xy, t.xy)
        np.testing.assert_array_equal(s.brightness, t.brightness)


def random_sequence(rng: np.random.Generator, camera: Camera, n_snapshots: int) -> Sequence:
    """A sequence with awkward floats (full precision, sub-ms times) on the sensor."""
    start = datetime(1994, 3, 12, 21, 4, 10, tzinfo=UTC)
    offsets = np.cumsum(rng.integers(1, 10**6, n_snapshots))
    snaps = []
    for i, micro in enumerate(offsets):
        n = int(rng.integers(0, 12))
        xy = np.column_stack([rng.uniform(-0.5, camera.width - 0.5, n),
                              rng.uniform(-0.5, camera.height - 0.5, n)])
        snaps.append(Snapshot(index=int(i * 3 + 1), time=start + timedelta(microseconds=int(micro)),
                              xy=xy, brightness=rng.exponential(100.0, n)))
    return Sequence(sequence_id="R-1", spacecraft="TUBSAT-B", camera=camera, snapshots=tuple(snaps),
                    velocity_km_s=(7.1, -0.25, 1e-3))


# =============================================================================
# the happy path
# =============================================================================
def test_issue_example_parses_to_the_stated_values():
    seq = parse_doc(valid_doc())
    assert seq.sequence_id == "A-0427" and seq.spacecraft == "TUBSAT-A"
    assert seq.camera == Camera(752, 582, 2132.4, 375.5, 290.5)
    assert [s.index for s in seq.snapshots] == [0, 1, 2]
    assert seq.snapshots[0].time == datetime(1994, 3, 12, 21, 4, 10, tzinfo=UTC)
    assert seq.snapshots[1].time == datetime(1994, 3, 12, 21, 4, 10, 500000, tzinfo=UTC)
    np.testing.assert_array_equal(seq.snapshots[0].xy, [[16.0, 334.0], [700.25, 12.5]])
    np.testing.assert_array_equal(seq.snapshots[0].brightness, [255.0, 80.0])
    assert seq.snapshots[2].xy.shape == (0, 2) and seq.snapshots[2].brightness.shape == (0,)
    assert seq.velocity_km_s is None and seq.extra == {}


def test_times_with_offsets_become_utc_and_naive_times_are_utc():
    doc = valid_doc()
    doc["snapshots"][0]["time"] = "1994-03-12T23:04:10+02:00"   # = 21:04:10Z
    doc["snapshots"][1]["time"] = "1994-03-12T21:04:10.5"       # naive: UTC
    seq = parse_doc(doc)
    assert seq.snapshots[0].time == datetime(1994, 3, 12, 21, 4, 10, tzinfo=UTC)
    assert seq.snapshots[0].time.utcoffset() == timedelta(0)
    assert seq.snapshots[1].time == datetime(1994, 3, 12, 21, 4, 10, 500000, tzinfo=UTC)


def test_sensor_edges_are_inside():
    doc = valid_doc()
    doc["snapshots"][0]["sources"] = [{"x": -0.5, "y": -0.5, "brightness": 0},
                                      {"x": 751.5, "y": 581.5, "brightness": 0}]
    np.testing.assert_array_equal(parse_doc(doc).snapshots[0].xy, [[-0.5, -0.5], [751.5, 581.5]])


def test_camera_may_be_a_name_or_left_out():
    doc = valid_doc()
    doc["camera"] = "narrow-1024x1024-12deg"
    assert parse_doc(doc).camera == CAMERAS["narrow-1024x1024-12deg"]
    del doc["camera"]
    assert parse_doc(doc).camera == CAMERAS[Settings().default_camera]
    narrow = CAMERAS["narrow-1024x1024-12deg"]
    assert parse_doc(doc, default_camera=narrow).camera == narrow


def test_optional_camera_fields_and_velocity():
    doc = valid_doc()
    doc["camera"].update(k1=-0.02, k2=0.001, name="lab-cam.1", mag_limit=5.0)
    doc["velocity_km_s"] = [7.0, -1.5, 0.25]
    seq = parse_doc(doc)
    assert seq.camera == Camera(752, 582, 2132.4, 375.5, 290.5, k1=-0.02, k2=0.001,
                                name="lab-cam.1", mag_limit=5.0)
    assert seq.velocity_km_s == (7.0, -1.5, 0.25)


def test_unknown_top_level_keys_are_kept_and_written_back():
    doc = valid_doc()
    doc["ground_station"] = {"site": "Berlin", "antenna": [1, 2]}
    seq = parse_doc(doc)
    assert seq.extra == {"ground_station": {"site": "Berlin", "antenna": [1, 2]}}
    assert json.loads(dump_json(seq))["ground_station"] == {"site": "Berlin", "antenna": [1, 2]}


def test_sequence_id_comes_from_the_file_name_when_missing():
    doc = valid_doc()
    del doc["sequence_id"]
    assert parse_doc(doc, filename="uploads/B-0001.json").sequence_id == "B-0001"
    assert parse_doc(doc, filename="C:\\telemetry\\B-0002.json").sequence_id == "B-0002"
    assert_problem(problems_of(doc), "sequence_id", "missing")


def test_utf8_bom_and_bytes_are_accepted():
    text = json.dumps(valid_doc())
    assert parse_telemetry(("\ufeff" + text).encode("utf-8")).sequence_id == "A-0427"


# =============================================================================
# error classes of issue 2, item 2
# =============================================================================
@pytest.mark.parametrize("data, words", [
    ("hello world", ["neither JSON nor CSV"]),
    (b"", ["empty"]),
    ("   \n\t ", ["empty"]),
    ('{"sequence_id": "A", "snapshots": [}', ["not valid JSON", "line 1"]),
    ("[1, 2, 3]", ["top level must be a JSON object", "array"]),
    (b'{"sequence_id": "\xff\xfe"}', ["not valid UTF-8", "0xff"]),
    ("{" * 5000 + "}" * 5000, ["not valid JSON"]),  # keys missing: still JSON's message
    ('{"a":' * 30 + "1" + "}" * 30, ["nested deeper than 20"]),
    ('[' * 100000 + ']' * 100000, ["nested deeper"]),
])
def test_not_json_or_csv(data, words):
    assert_problem(problems_of(data), "file", *words)


def test_lone_surrogate_in_text_input():
    assert_problem(problems_of('{"a": "\ud800"}'), "file", "lone surrogate")


@pytest.mark.parametrize("path, value, location, words", [
    (("snapshots", 0, "sources", 1, "x"), "16", "snapshots[0].sources[1].x", ["must be a number", "string"]),
    (("snapshots", 0, "sources", 0, "y"), True, "snapshots[0].sources[0].y", ["must be a number", "true"]),
    (("snapshots", 1, "sources", 0, "brightness"), None, "snapshots[1].sources[0].brightness",
     ["must be a number", "null"]),
    (("snapshots", 1, "index"), 1.0, "snapshots[1].index", ["integer"]),
    (("snapshots", 1, "index"), False, "snapshots[1].index", ["integer", "false"]),
    (("snapshots", 1, "time"), 1994, "snapshots[1].time", ["ISO 8601"]),
    (("snapshots", 1, "time"), "yesterday", "snapshots[1].time", ["ISO 8601", "yesterday"]),
    (("snapshots", 1, "time"), "1850-01-01T00:00:00Z", "snapshots[1].time", ["1900"]),
    (("snapshots", 1, "sources"), {"x": 1}, "snapshots[1].sources", ["array", "object"]),
    (("snapshots", 1), [], "snapshots[1]", ["must be an object"]),
    (("snapshots",), {"0": {}}, "snapshots", ["array"]),
    (("camera", "width"), "752", "camera.width", ["integer", "string"]),
    (("camera", "height"), 0, "camera.height", ["1 to 100000"]),
    (("camera", "width"), 100001, "camera.width", ["1 to 100000"]),
    (("camera", "focal_length_px"), -5, "camera.focal_length_px", ["> 0"]),
    (("camera", "k1"), 11.0, "camera.k1", ["10"]),
    (("camera", "name"), "my camera", "camera.name", ["letters"]),
    (("camera",), 42, "camera", ["object or a camera name"]),
    (("camera",), "hubble", "camera", ["unknown camera", "tubsat-752x582-20deg"]),
    (("sequence_id",), "", "sequence_id", ["empty"]),
    (("sequence_id",), "x" * 129, "sequence_id", ["128"]),
    (("sequence_id",), "A\n0427", "sequence_id", ["control"]),
    (("spacecraft",), 7, "spacecraft", ["string"]),
    (("format",), "tubsat-snapshots/2", "format", ["unsupported format"]),
    (("velocity_km_s",), [1, 2], "velocity_km_s", ["3 numbers"]),
    (("velocity_km_s",), [100, 0, 0], "velocity_km_s", ["speed"]),
    (("velocity_km_s",), [1, "2", 3], "velocity_km_s[1]", ["number"]),
])
def test_wrong_types_and_values_in_json(path, value, location, words):
    doc = valid_doc()
    target = doc
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    assert_problem(problems_of(doc), location, *words)


def test_missing_and_unknown_fields_in_json():
    doc = valid_doc()
    del doc["snapshots"][0]["sources"][1]["brightness"]
    doc["snapshots"][1]["sources"][0]["mag"] = 3.0
    del doc["camera"]["cy"]
    doc["camera"]["focal_length"] = 2132.4
    del doc["snapshots"][2]["time"]
    problems = problems_of(doc)
    assert_problem(problems, "snapshots[0].sources[1].brightness", "missing")
    assert_problem(problems, "snapshots[1].sources[0].mag", "unknown source field")
    assert_problem(problems, "camera.cy", "missing")
    assert_problem(problems, "camera.focal_length", "unknown camera field")
    assert_problem(problems, "snapshots[2].time", "missing")
    del doc["snapshots"]
    assert_problem(problems_of(doc), "snapshots", "missing")


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity"])
def test_nan_and_infinity_in_json(token):
    text = json.dumps(valid_doc()).replace("700.25", token)
    assert_problem(problems_of(text), "snapshots[0].sources[1].x", token, "finite")


def test_overflowing_numbers_in_json():
    text = json.dumps(valid_doc()).replace("334.0", "1e999").replace("2132.4", "-1e400")
    problems = problems_of(text)
    assert_problem(problems, "snapshots[0].sources[0].y", "finite")
    assert_problem(problems, "camera.focal_length_px", "finite")
    huge_int = json.dumps(valid_doc()).replace('"index": 1', '"index": ' + "9" * 40)
    assert_problem(problems_of(huge_int), "snapshots[1].index", "0 to 2147483647", "huge")


def test_nan_inside_kept_unknown_field_is_rejected():
    text = json.dumps(valid_doc())[:-1] + ', "extra_info": {"list": [1, NaN]}}'
    assert_problem(problems_of(text), "extra_info.list[1]", "NaN")


@pytest.mark.parametrize("x, y, location, words", [
    (752.0, 10.0, "snapshots[0].sources[1].x", ["x = 752", "outside the sensor", "751.5"]),
    (10.0, 581.6, "snapshots[0].sources[1].y", ["y = 581.6", "outside the sensor"]),
    (-0.51, 10.0, "snapshots[0].sources[1].x", ["outside the sensor", "-0.5"]),
])
def test_coordinates_outside_the_sensor(x, y, location, words):
    doc = valid_doc()
    doc["snapshots"][0]["sources"][1].update(x=x, y=y)
    assert_problem(problems_of(doc), location, *words)


def test_negative_brightness():
    doc = valid_doc()
    doc["snapshots"][1]["sources"][0]["brightness"] = -1.5
    assert_problem(problems_of(doc), "snapshots[1].sources[0].brightness", ">= 0", "-1.5")


def test_times_not_increasing():
    doc = valid_doc()
    doc["snapshots"][1]["time"] = doc["snapshots"][0]["time"]          # equal
    doc["snapshots"][2]["time"] = "1994-03-12T21:04:09.000Z"           # earlier
    problems = problems_of(doc)
    assert_problem(problems, "snapshots[1].time", "strictly increase", "snapshots[0].time")
    assert_problem(problems, "snapshots[2].time", "strictly increase")
    # Same wall-clock text, but +01:00 makes it an hour *earlier* in UTC.
    doc = valid_doc()
    doc["snapshots"][1]["time"] = "1994-03-12T21:04:10.500+01:00"
    assert_problem(problems_of(doc), "snapshots[1].time", "strictly increase")


def test_duplicate_indices():
    doc = valid_doc()
    doc["snapshots"][2]["index"] = 0
    assert_problem(problems_of(doc), "snapshots[2].index", "duplicate snapshot index 0", "snapshots[0].index")


def test_duplicate_json_key():
    text = json.dumps(valid_doc())[:-1] + ', "sequence_id": "B"}'
    assert_problem(problems_of(text), "file", "duplicate key", "sequence_id")


def test_missing_camera_without_a_configured_default(monkeypatch):
    # An empty STARID_DEFAULT_CAMERA means: no default camera.
    monkeypatch.setattr(formats, "settings", lambda: Settings(default_camera=""))
    doc = valid_doc()
    del doc["camera"]
    assert_problem(problems_of(doc), "camera", "missing camera")
    csv_text = "# sequence_id: A\nsnapshot,time,x,y,brightness\n0,1994-03-12T21:04:10Z,1,2,3\n"
    assert_problem(problems_of(csv_text), "file", "missing camera")
    # An explicit default still works.
    assert parse_doc(doc, default_camera=CAMERAS["narrow-1024x1024-12deg"]).camera.width == 1024


def test_too_many_snapshots():
    doc = valid_doc()
    base = datetime(1994, 3, 12, tzinfo=UTC)
    doc["snapshots"] = [{"index": i, "time": (base + timedelta(seconds=i)).isoformat(), "sources": []}
                        for i in range(MAX_SNAPSHOTS + 1)]
    assert_problem(problems_of(doc), "snapshots", "65 snapshots", "at most 64")
    doc["snapshots"].pop()
    assert len(parse_doc(doc).snapshots) == MAX_SNAPSHOTS
    doc["snapshots"] = []
    assert_problem(problems_of(doc), "snapshots", "at least one")


def test_too_many_sources():
    doc = valid_doc()
    doc["snapshots"][1]["sources"] = [{"x": i, "y": 1, "brightness": 1}
                                      for i in range(MAX_SOURCES_PER_SNAPSHOT + 1)]
    assert_problem(problems_of(doc), "snapshots[1].sources", "65 sources", "at most 64")
    doc["snapshots"][1]["sources"].pop()
    assert parse_doc(doc).snapshots[1].n_sources == MAX_SOURCES_PER_SNAPSHOT


def test_file_larger_than_the_limit(tmp_path):
    text = json.dumps(valid_doc())
    size = len(text.encode())
    assert_problem(problems_of(text, max_bytes=size - 1), "file", f"{size} bytes", f"limit of {size - 1}")
    assert parse_telemetry(text, max_bytes=size).sequence_id == "A-0427"
    path = tmp_path / "big.json"
    path.write_text(text)
    with pytest.raises(TelemetryError) as info:
        load_telemetry_file(path, max_bytes=100)
    assert info.value.problems == [Problem("file", f"the file is {size} bytes, larger than the limit of 100 bytes")]
    assert info.value.filename == str(path)
    assert load_telemetry_file(path).sequence_id == "A-0427"


def test_operating_system_errors_are_telemetry_errors(tmp_path):
    for path in (tmp_path / "absent.json", tmp_path):
        with pytest.raises(TelemetryError) as info:
            load_telemetry_file(path)
        assert_problem(info.value.problems, "file", "cannot read the file")


def test_sequence_id_from_file_name_of_a_loaded_file(tmp_path):
    doc = valid_doc()
    del doc["sequence_id"]
    path = tmp_path / "A-0999.json"
    path.write_text(json.dumps(doc))
    assert load_telemetry_file(path).sequence_id == "A-0999"


# =============================================================================
# the error object
# =============================================================================
def test_all_problems_are_collected_and_reported():
    doc = valid_doc()
    doc["snapshots"][0]["sources"][0]["x"] = "a"
    doc["snapshots"][0]["sources"][1]["brightness"] = -1
    doc["camera"]["k2"] = 20
    with pytest.raises(TelemetryError) as info:
        parse_doc(doc, filename="A-0427.json")
    err = info.value
    assert isinstance(err, ValueError)
    assert [p.location for p in err.problems] == [
        "camera.k2", "snapshots[0].sources[0].x", "snapshots[0].sources[1].brightness"]
    text = str(err)
    assert text.splitlines()[0] == "A-0427.json: invalid telemetry: 3 problems:"
    assert "  snapshots[0].sources[1].brightness: brightness must be >= 0, got -1" in text.splitlines()
    as_dict = err.to_dict()
    assert as_dict["message"] == "A-0427.json: invalid telemetry: 3 problems"
    assert as_dict["problems"][0] == {"location": "camera.k2", "message": err.problems[0].message}
    json.dumps(as_dict)  # serialisable as is


def test_a_distortion_that_folds_the_image_over_before_the_corner_is_refused():
    """By hand, for the 752 x 582 sensor at f = 1000 px (its corner at r^2 = 0.2261): k1 = 1.8, k2 = -9
    stop ``r (1 + k1 r^2 + k2 r^4)`` increasing where ``1 + 5.4 u - 45 u^2 = 0``, u = r^2 = 0.2207, inside
    the sensor, though they move the corner by only -5.3 %; with k2 = -8 it turns back at u = 0.2394,
    beyond the corner, and the camera is kept."""
    doc = valid_doc()
    doc["camera"].update(focal_length_px=1000.0, k1=1.8, k2=-9.0)
    with pytest.raises(TelemetryError) as info:
        parse_doc(doc, filename="A-0427.json")
    (problem,) = info.value.problems
    assert problem.location == "camera.k1" and "fold the image over before the sensor corner" in problem.message
    doc["camera"]["k2"] = -8.0
    assert parse_doc(doc, filename="A-0427.json").camera.k2 == -8.0


def test_problems_are_capped():
    doc = valid_doc()
    doc["snapshots"][0]["sources"] = [{"x": "bad", "y": "bad", "brightness": 1}] * 60
    with pytest.raises(TelemetryError) as info:
        parse_doc(doc)
    assert len(info.value.problems) == MAX_PROBLEMS and info.value.truncated
    assert "only the first 50 problems" in str(info.value)


def test_single_problem_message_is_one_line():
    err = TelemetryError.at("file", "the file is empty", filename="x.csv")
    assert str(err) == "x.csv: invalid telemetry: file: the file is empty"
    assert err.to_dict() == {"message": "x.csv: invalid telemetry: file: the file is empty",
                             "problems": [{"location": "file", "message": "the file is empty"}]}


# =============================================================================
# CSV form
# =============================================================================
CSV_TEXT = """\
# format: tubsat-snapshots/1
# sequence_id: A-0427
# spacecraft: TUBSAT-A
# camera: width=752 height=582 focal_length_px=2132.4 cx=375.5 cy=290.5
snapshot,time,x,y,brightness
0,1994-03-12T21:04:10.000Z,16.0,334.0,255.0
0,1994-03-12T21:04:10.000Z,700.25,12.5,80
1,1994-03-12T21:04:10.500Z,17,333,250.0
2,1994-03-12T21:04:11.000Z,,,
"""


def test_csv_and_json_of_the_same_data_give_the_same_sequence():
    assert_same_sequence(parse_telemetry(CSV_TEXT), parse_doc(valid_doc()))


def test_csv_columns_in_any_order_extra_columns_ignored_crlf_and_comments():
    text = ("# sequence_id: A-0427\r\n# spacecraft: TUBSAT-A\r\n"
            "# camera: width=752, height=582, focal_length_px=2132.4, cx=375.5, cy=290.5\r\n"
            "# a free comment: ignored\r\n"
            "Brightness, X, y, flags, time, snapshot\r\n"
            "255.0,16.0,334.0,ok,1994-03-12T21:04:10.000Z,0\r\n"
            "\r\n# comment between rows\r\n"
            "80,700.25,12.5,,1994-03-12T21:04:10Z,0\r\n"
            "250,17,333,x,1994-03-12T21:04:10.500Z,1\r\n"
            ",,,,1994-03-12T21:04:11Z,2\r\n")
    assert_same_sequence(parse_telemetry(text), parse_doc(valid_doc()))


def test_csv_camera_by_name_or_default_and_velocity():
    body = "snapshot,time,x,y,brightness\n5,2001-01-01T00:00:00Z,1,2,3\n"
    seq = parse_telemetry("# camera: liebe-576x604-30deg\n# velocity_km_s: 7.5, 0, -1\n" + body,
                          filename="F-1.csv")
    assert seq.camera == CAMERAS["liebe-576x604-30deg"]
    assert seq.velocity_km_s == (7.5, 0.0, -1.0)
    assert seq.sequence_id == "F-1" and seq.spacecraft is None
    assert parse_telemetry(body, filename="F-1.csv").camera == CAMERAS[Settings().default_camera]


@pytest.mark.parametrize("row, location, words", [
    ("1,1994-03-12T21:04:10.500Z,abc,333,250", 'line 8, column "x"', ["must be a number", "abc"]),
    ("1,1994-03-12T21:04:10.500Z,17,nan,250", 'line 8, column "y"', ["nan", "finite"]),
    ("1,1994-03-12T21:04:10.500Z,17,333,-inf", 'line 8, column "brightness"', ["finite"]),
    ("1,1994-03-12T21:04:10.500Z,17,333,1e999", 'line 8, column "brightness"', ["finite"]),
    ("1,1994-03-12T21:04:10.500Z,17,333,-2", 'line 8, column "brightness"', [">= 0"]),
    ("1,1994-03-12T21:04:10.500Z,752,333,2", 'line 8, column "x"', ["outside the sensor"]),
    ("1,1994-03-12T21:04:10.500Z,17,,2", 'line 8, column "y"', ["missing value"]),
    ("1.5,1994-03-12T21:04:10.500Z,17,3,2", 'line 8, column "snapshot"', ["integer"]),
    ("-1,1994-03-12T21:04:10.500Z,17,3,2", 'line 8, column "snapshot"', ["0 to"]),
    ("1,noon,17,3,2", 'line 8, column "time"', ["ISO 8601"]),
    ("1,1994-03-12T21:04:10.500Z,17,3", "line 8", ["expected 5 fields", "got 4"]),
    ("1,1994-03-12T21:04:10.500Z,17,3,2,9", "line 8", ["expected 5 fields", "got 6"]),
    ('1,"1994-03-12T21:04:10.500Z,17,3,2', "line 8", ["5 fields"]),
    ("1,1994-03-12T21:04:10.000Z,17,333,250", 'line 8, column "time"', ["strictly increase"]),
    ("0,1994-03-12T21:04:10.500Z,17,333,250", 'line 8, column "time"', ["same time", "line 6"]),
])
def test_csv_row_errors(row, location, words):
    lines = CSV_TEXT.splitlines()
    lines[7] = row  # the row of snapshot 1 (line 8)
    assert_problem(problems_of("\n".join(lines)), location, *words)


def test_csv_duplicate_index_reported_once_as_not_contiguous():
    text = CSV_TEXT + "0,1994-03-12T21:04:12Z,1,1,1\n"
    assert_problem(problems_of(text), 'line 10, column "snapshot"', "contiguous", "line 6")


def test_csv_rows_of_a_snapshot_share_one_time():
    text = CSV_TEXT.replace("0,1994-03-12T21:04:10.000Z,700.25", "0,1994-03-12T21:04:10.001Z,700.25")
    assert_problem(problems_of(text), 'line 7, column "time"', "same time", "line 6")


def test_csv_empty_row_only_for_a_snapshot_without_sources():
    text = CSV_TEXT + "2,1994-03-12T21:04:11.000Z,1,2,3\n"
    assert_problem(problems_of(text), 'line 10, column "x"', "empty row")


@pytest.mark.parametrize("comment, location, words", [
    ("# camera: width=752 height=582 focal_length_px=0 cx=375.5 cy=290.5",
     "line 4, camera.focal_length_px", ["> 0"]),
    ("# camera: width=752.0 height=582 focal_length_px=2000 cx=375.5 cy=290.5",
     "line 4, camera.width", ["integer"]),
    ("# camera: width=752 height=582 focal_length_px=2000 cx=375.5", "line 4, camera.cy", ["missing"]),
    ("# camera: width=752 height=582 focal_length_px=2000 cx=375.5 cy=nan", "line 4, camera.cy", ["finite"]),
    ("# camera: width=752 height=582 focal=2000 cx=375.5 cy=290", "line 4, camera.focal", ["unknown"]),
    ("# camera: width=752 height 582", "line 4, camera", ["key=value"]),
    ("# camera: hubble", "line 4, camera", ["unknown camera"]),
])
def test_csv_camera_comment_errors(comment, location, words):
    text = CSV_TEXT.replace(CSV_TEXT.splitlines()[3], comment)
    assert_problem(problems_of(text), location, *words)


def test_csv_header_and_preamble_errors():
    assert_problem(problems_of("# sequence_id: A\n# sequence_id: B\nsnapshot,time,x,y,brightness\n"
                               "0,2000-01-01,1,1,1\n"), "line 2, sequence_id", "twice")
    assert_problem(problems_of("# sequence_id: A\nsnapshot,time,x,y\n0,2000-01-01,1,1\n"),
                   "line 2", "lacks", '"brightness"')
    assert_problem(problems_of("# sequence_id: A\nsnapshot,time,x,x,y,brightness\n"), "line 2", "repeats")
    assert_problem(problems_of("# sequence_id: A\n# only comments\n"), "file", "no CSV header")
    assert_problem(problems_of("# sequence_id: A\nsnapshot,time,x,y,brightness\n\n"), "file", "no snapshot rows")
    assert_problem(problems_of("# format: other/1\n" + CSV_TEXT.split("\n", 1)[1]), "line 1, format",
                   "unsupported format")


def test_csv_too_many_snapshots_and_sources():
    header = "# sequence_id: A\nsnapshot,time,x,y,brightness\n"
    rows = [f"{i},2000-01-{1 + i // 24:02d}T{i % 24:02d}:00:00Z,1,1,1" for i in range(MAX_SNAPSHOTS + 1)]
    assert_problem(problems_of(header + "\n".join(rows)), f'line {MAX_SNAPSHOTS + 3}, column "snapshot"',
                   "more than 64 snapshots")
    assert len(parse_telemetry(header + "\n".join(rows[:-1])).snapshots) == MAX_SNAPSHOTS
    rows = [f"0,2000-01-01T00:00:00Z,{i},1,1" for i in range(MAX_SOURCES_PER_SNAPSHOT + 1)]
    assert_problem(problems_of(header + "\n".join(rows)), f'line {MAX_SOURCES_PER_SNAPSHOT + 3}, column "x"',
                   "more than 64 sources")
    assert parse_telemetry(header + "\n".join(rows[:-1])).snapshots[0].n_sources == MAX_SOURCES_PER_SNAPSHOT


# =============================================================================
# round trips
# =============================================================================
@pytest.mark.parametrize("camera_name", list(CAMERAS))
def test_round_trip_json_and_csv(camera_name):
    rng = np.random.default_rng(len(camera_name))
    camera = CAMERAS[camera_name]
    seq = random_sequence(rng, camera, n_snapshots=16)
    from_json = parse_telemetry(dump_json(seq))
    from_csv = parse_telemetry(dump_csv(seq))
    assert_same_sequence(from_json, seq)
    assert_same_sequence(from_csv, seq)
    assert dump_json(from_json) == dump_json(seq) and dump_csv(from_csv) == dump_csv(seq)


def test_round_trip_keeps_distortion_and_unnamed_camera():
    camera = Camera(1024, 768, 1800.123456789, 511.7, 383.2, k1=-0.0123, k2=1e-5)
    seq = random_sequence(np.random.default_rng(7), camera, n_snapshots=3)
    seq = Sequence(seq.sequence_id, None, camera, seq.snapshots, None, {"note": "kept"})
    back = parse_telemetry(dump_json(seq))
    assert_same_sequence(back, seq)
    assert back.extra == {"note": "kept"}
    assert_same_sequence(parse_telemetry(dump_csv(seq)), seq)


def test_dumped_json_is_the_documented_form():
    doc = json.loads(dump_json(parse_doc(valid_doc())))
    expected = copy.deepcopy(valid_doc())
    assert doc == expected


def test_the_documented_examples_parse_to_the_same_sequence():
    """docs/formats.md: its JSON example and its CSV example are the same data."""
    doc_text = (Path(__file__).resolve().parents[1] / "docs" / "formats.md").read_text()
    blocks = re.findall(r"```(json|text)\n(.*?)```", doc_text, re.S)
    json_example = next(body for kind, body in blocks if kind == "json" and '"snapshots"' in body)
    csv_example = next(body for kind, body in blocks if kind == "text" and "snapshot,time" in body)
    from_json, from_csv = parse_telemetry(json_example), parse_telemetry(csv_example)
    assert_same_sequence(from_json, from_csv)
    assert from_json.velocity_km_s == (-3.91, 6.12, 1.07)
    assert [s.n_sources for s in from_json.snapshots] == [2, 1, 0]
