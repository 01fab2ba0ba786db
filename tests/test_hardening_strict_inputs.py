"""Hostile-input trial, strict inputs: guard rails not crossed by strings, a search id that is no search of
the sequence, digits of other scripts in CSV telemetry, leap seconds and dates that do not exist.

What is checked is the API's and the format's contract (docs/cli-and-api.md "REST API",
docs/formats.md): JSON's own booleans and integers in request bodies (pydantic's
lax mode took "yes" as true and true as the rank 1), ISO 8601 times in the AEM
export's range (a number was read as a Unix time), a located 422 saying the
truth about a foreign ``search_id``, plain ASCII decimals in CSV cells, and the
reason a time is refused.  Every refusal also leaves the archive as it was.
"""

from __future__ import annotations

import json

import pytest
from fastapi.testclient import TestClient

from app.api import create_app
from app.storage import Storage
from app.telemetry import TelemetryError, parse_telemetry
from app.workflow import AppContext

CSV_HEAD = "# sequence_id: strict\n# camera: tubsat-752x582-20deg\nsnapshot,time,x,y,brightness\n"
CAMERA = {"width": 752, "height": 582, "focal_length_px": 2132.4, "cx": 375.5, "cy": 290.5}
SESSION = "strict-inputs"


@pytest.fixture(scope="module")
def env(tmp_path_factory, sky, sample_dir):
    """(client, ids): ``confirmed`` (02, searched by tf then bright pairs, rank 1 of the latest confirmed),
    ``open`` (01, searched, no verdict), ``unsearched`` (03, uploaded only), and ``older_search`` (the tf
    search of ``confirmed``, which the bright-pair search replaced)."""
    ctx = AppContext(storage=Storage.open(tmp_path_factory.mktemp("strict") / "strict.sqlite3"), sky=sky)
    client = TestClient(create_app(ctx))
    ids = {}
    for key, name in (("confirmed", "02-ghosts-hot-pixels.json"), ("open", "01-clean.json"),
                      ("unsearched", "03-jupiter.json")):
        r = client.post("/api/sequences", content=(sample_dir / name).read_bytes())
        assert r.status_code == 201, r.text
        ids[key] = r.json()["id"]
    older = client.post(f"/api/sequences/{ids['confirmed']}/search", json={"method": "tf"})
    assert older.status_code == 200, older.text
    ids["older_search"] = older.json()["search_id"]
    for key in ("confirmed", "open"):
        r = client.post(f"/api/sequences/{ids[key]}/search", json={})
        assert r.status_code == 200 and r.json()["status"] == "identified", r.text
    r = client.post(f"/api/sequences/{ids['confirmed']}/confirm",
                    json={"rank": 1, "operator": "ann", "search_id": _latest_search(client, ids["confirmed"])})
    assert r.status_code == 201, r.text
    yield client, ids
    ctx.close()


def _latest_search(client, seq_id: int) -> int:
    return client.get(f"/api/sequences/{seq_id}").json()["search"]["search_id"]


def _verdicts(client, seq_id: int) -> tuple:
    """What a refused request must leave unchanged: the sequence's verdict, audit trail and pattern."""
    review = client.get(f"/api/sequences/{seq_id}/review").json()
    detail = client.get(f"/api/sequences/{seq_id}").json()
    return (review["confirmation"], review["rejection"], len(review["audit"]), detail["status"],
            detail["pattern"]["version"], client.get("/api/attitudes").json()["total"])


def _problem(r) -> dict:
    assert r.status_code == 422, r.text
    problems = r.json()["problems"]
    assert len(problems) == 1, problems
    return problems[0]


# ---------------------------------------------------------------------------
# 1. Flags, ranks, ids and numbers of request bodies are JSON's own
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("value, shown", [("yes", "a string ('yes')"), ("on", "a string ('on')"),
                                          ("t", "a string ('t')"), ("1", "a string ('1')"),
                                          ("true", "a string ('true')"), (1, "1"), (None, "null")])
def test_supersede_of_a_confirmation_is_a_json_boolean(env, value, shown):
    client, ids = env
    sid = ids["confirmed"]
    before = _verdicts(client, sid)
    r = client.post(f"/api/sequences/{sid}/confirm",
                    json={"rank": 2, "operator": "eve", "override_reason": "testing the guard rail",
                          "supersede": value})
    assert _problem(r) == {"location": "body.supersede", "message": f"must be true or false, got {shown}"}
    assert "body.supersede" in r.json()["detail"]
    assert _verdicts(client, sid) == before  # no superseding record


@pytest.mark.parametrize("value", ["yes", "on", 1])
def test_supersede_of_no_valid_attitude_is_a_json_boolean(env, value):
    client, ids = env
    sid = ids["confirmed"]
    before = _verdicts(client, sid)
    r = client.post(f"/api/sequences/{sid}/reject", json={"reason": "all wrong", "operator": "eve", "supersede": value})
    assert _problem(r)["location"] == "body.supersede"
    assert _verdicts(client, sid) == before


@pytest.mark.parametrize("value, shown", [(True, "true"), ("  1 ", "a string ('  1 ')"), ("1", "a string ('1')"),
                                          (1.0, "1.0")])
def test_the_rank_confirmed_is_a_json_integer(env, value, shown):
    # 1.0 is refused too, as in the telemetry format: no client that counts writes it, and a float id or
    # rank means arithmetic went wrong somewhere (2**53 + 1 as a float is another number).
    client, ids = env
    sid = ids["open"]
    before = _verdicts(client, sid)
    r = client.post(f"/api/sequences/{sid}/confirm", json={"rank": value, "operator": "eve"})
    assert _problem(r) == {"location": "body.rank", "message": f"must be an integer, got {shown}"}
    assert _verdicts(client, sid) == before


@pytest.mark.parametrize("method, path, body, location, message", [
    ("POST", "/api/sequences/{open}/confirm", {"rank": 1, "operator": "eve", "search_id": "1"},
     "body.search_id", "must be an integer, got a string ('1')"),
    ("PUT", "/api/sequences/{confirmed}/pattern", {"exclude_tracks": [True]},
     "body.exclude_tracks[0]", "must be an integer, got true"),
    ("PUT", "/api/sequences/{confirmed}/pattern", {"include_tracks": [0, "1"]},
     "body.include_tracks[1]", "must be an integer, got a string ('1')"),
    ("PUT", "/api/sequences/{confirmed}/pattern", {"manual_points": [{"snapshot": "0", "x": 10, "y": 20}]},
     "body.manual_points[0].snapshot", "must be an integer, got a string ('0')"),
    ("PUT", "/api/sequences/{confirmed}/pattern", {"manual_points": [{"snapshot": 0, "x": True, "y": 20}]},
     "body.manual_points[0].x", "must be a number, got true"),
    ("POST", "/api/sequences/{confirmed}/search", {"max_candidates": "3"},
     "body.max_candidates", "must be an integer, got a string ('3')"),
    ("POST", "/api/sequences/{confirmed}/search",
     {"method": "tracking", "prior": {"ra_deg": "10", "dec_deg": 0, "roll_deg": 0}},
     "body.prior.ra_deg", "must be a number, got a string ('10')"),
    ("PUT", f"/api/view?session={SESSION}", {"sequence": "1"}, "body.sequence", "must be an integer, got a string ('1')"),
    ("PUT", f"/api/view?session={SESSION}", {"rank": True}, "body.rank", "must be an integer, got true"),
    ("PUT", f"/api/view?session={SESSION}", {"mag": "5"}, "body.mag", "must be a number, got a string ('5')"),
])
def test_ids_counts_and_numbers_of_every_body_are_json_numbers(env, method, path, body, location, message):
    client, ids = env
    url = path.format(**ids)
    before = {sid: _verdicts(client, sid) for sid in (ids["confirmed"], ids["open"])}
    searches = {sid: _latest_search(client, sid) for sid in (ids["confirmed"], ids["open"])}
    view = client.get(f"/api/view?session={SESSION}").json()
    r = client.request(method, url, json=body)
    assert _problem(r) == {"location": location, "message": message}
    assert {sid: _verdicts(client, sid) for sid in before} == before
    assert {sid: _latest_search(client, sid) for sid in searches} == searches
    assert client.get(f"/api/view?session={SESSION}").json()["revision"] == view["revision"]


def test_json_booleans_and_integers_still_work(env):
    client, ids = env
    sid = ids["confirmed"]
    current = client.get(f"/api/sequences/{sid}/review").json()["confirmation"]
    again = client.post(f"/api/sequences/{sid}/confirm",
                        json={"rank": 1, "operator": "bob", "supersede": False, "search_id": current["search_id"]})
    assert again.status_code == 200 and again.json()["id"] == current["id"]
    r = client.put(f"/api/view?session={SESSION}", json={"sequence": sid, "rank": 1, "mag": 5})
    assert r.status_code == 200 and (r.json()["sequence"], r.json()["rank"], r.json()["mag"]) == (sid, 1, 5.0)


@pytest.mark.parametrize("query, location, words", [
    ("start=1582788491", "query.start", "'1582788491' is a number, not a time"),
    ("end=1582788491.5", "query.end", "'1582788491.5' is a number, not a time"),
    ("start=20200227", "query.start", "'20200227' is a number, not a time"),
    ("start=2020-02-30T00:00:00Z", "query.start", "the date 2020-02-30 does not exist (February 2020 has 29 days)"),
    ("start=yesterday", "query.start", "not an ISO 8601 time such as"),
])
def test_the_aem_time_range_is_iso_8601_never_a_number(env, query, location, words):
    client, _ = env
    r = client.get(f"/api/attitudes/aem?spacecraft=SIM-TUBSAT&{query}")
    problem = _problem(r)
    assert problem["location"] == location and words in problem["message"], problem


def test_the_aem_time_range_reads_iso_8601(env):
    client, _ = env
    for query in ("start=2020-02-27T07:00:00Z", "start=2020-02-27T07:00:00&end=2020-02-28",
                  "start=2020-02-27T08:00:00%2B01:00"):
        r = client.get(f"/api/attitudes/aem?spacecraft=SIM-TUBSAT&{query}")
        assert r.status_code == 200 and "CCSDS_AEM_VERS" in r.text, (query, r.text)
    assert client.get("/api/attitudes/aem?spacecraft=SIM-TUBSAT&start=2020-02-28T00:00:00Z").status_code == 404


# ---------------------------------------------------------------------------
# 2. A search id that is no search of the sequence says so
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("which", ["unknown", "another sequence's"])
def test_a_search_id_that_is_no_search_of_the_sequence_is_a_located_422(env, which):
    # 422, not 409: nothing in the archive replaced it, so no reload makes the request right.
    client, ids = env
    sid = ids["open"]
    search_id = 999999 if which == "unknown" else _latest_search(client, ids["confirmed"])
    before = _verdicts(client, sid)
    r = client.post(f"/api/sequences/{sid}/confirm", json={"rank": 1, "operator": "a", "search_id": search_id})
    expected = f"search {search_id} is not a search of sequence {sid} (its latest is {_latest_search(client, sid)})"
    assert _problem(r) == {"location": "body.search_id", "message": expected}
    assert r.json()["detail"] == expected and "replaced" not in r.text
    assert _verdicts(client, sid) == before


def test_a_search_id_on_a_sequence_never_searched(env):
    client, ids = env
    sid = ids["unsearched"]
    r = client.post(f"/api/sequences/{sid}/confirm", json={"rank": 1, "operator": "a", "search_id": ids["older_search"]})
    assert _problem(r)["message"] == (f"search {ids['older_search']} is not a search of sequence {sid} "
                                      "(it has not been searched yet)")


def test_an_older_search_of_the_sequence_is_still_a_409_replaced(env):
    client, ids = env
    sid = ids["confirmed"]
    before = _verdicts(client, sid)
    r = client.post(f"/api/sequences/{sid}/confirm",
                    json={"rank": 1, "operator": "a", "search_id": ids["older_search"], "supersede": True})
    assert r.status_code == 409, r.text
    assert (f"the candidates of search {ids['older_search']} were replaced by search "
            f"{_latest_search(client, sid)} of sequence {sid}") in r.json()["detail"]
    assert _verdicts(client, sid) == before


def test_an_unknown_sequence_is_still_a_404_with_a_search_id(env):
    client, _ = env
    r = client.post("/api/sequences/987654/confirm", json={"rank": 1, "operator": "a", "search_id": 1})
    assert r.status_code == 404, r.text


# ---------------------------------------------------------------------------
# 3. CSV numbers are plain ASCII decimals
# ---------------------------------------------------------------------------

def _csv_problems(text: str) -> list[dict]:
    with pytest.raises(TelemetryError) as err:
        parse_telemetry(text)
    return err.value.to_dict()["problems"]


def test_csv_digits_of_other_scripts_are_not_numbers():
    # Python's float() reads '٨٩' as 89.0 and '１２' as 12.0; the format's numbers are plain decimals.
    assert _csv_problems(CSV_HEAD + "0,2020-01-01T00:00:00Z,٨٩,٢,٣\n") == [
        {"location": 'line 4, column "x"', "message": "'٨٩' is not a plain decimal number (ASCII digits)"},
        {"location": 'line 4, column "y"', "message": "'٢' is not a plain decimal number (ASCII digits)"},
        {"location": 'line 4, column "brightness"', "message": "'٣' is not a plain decimal number (ASCII digits)"}]
    assert _csv_problems(CSV_HEAD + "0,2020-01-01T00:00:00Z,１２,2,3\n") == [
        {"location": 'line 4, column "x"', "message": "'１２' is not a plain decimal number (ASCII digits)"}]
    assert _csv_problems(CSV_HEAD + "٣,2020-01-01T00:00:00Z,12,2,3\n") == [
        {"location": 'line 4, column "snapshot"', "message": "'٣' is not a plain decimal number (ASCII digits)"}]
    assert _csv_problems(CSV_HEAD + "0,2020-01-01T00:00:00Z,1٢.5,2,3\n")[0]["message"] == (
        "'1٢.5' is not a plain decimal number (ASCII digits)")


def test_csv_header_numbers_are_ascii_too():
    text = ("# sequence_id: strict\n# camera: width=٧٥٢ height=582 focal_length_px=2132.4 cx=375.5 cy=290.5\n"
            "# velocity_km_s: ١ 2 3\nsnapshot,time,x,y,brightness\n0,2020-01-01T00:00:00Z,1,2,3\n")
    assert _csv_problems(text) == [
        {"location": "line 2, camera.width", "message": "'٧٥٢' is not a plain decimal number (ASCII digits)"},
        {"location": "line 3, velocity_km_s[0]", "message": "'١' is not a plain decimal number (ASCII digits)"}]


def test_ascii_csv_numbers_are_read_as_before():
    seq = parse_telemetry(CSV_HEAD + "0,2020-01-01T00:00:00Z,89,2.5,1.5e2\n")
    assert seq.snapshots[0].xy.tolist() == [[89.0, 2.5]] and seq.snapshots[0].brightness.tolist() == [150.0]


def test_an_upload_with_other_scripts_digits_is_a_422_and_stores_nothing(env):
    client, _ = env
    total = client.get("/api/sequences").json()["total"]
    r = client.post("/api/sequences", content=(CSV_HEAD + "0,2020-01-01T00:00:00Z,٨٩,2,3\n").encode(),
                    headers={"Content-Type": "text/csv"})
    assert r.status_code == 422, r.text
    assert r.json()["problems"] == [{"location": 'line 4, column "x"',
                                     "message": "'٨٩' is not a plain decimal number (ASCII digits)"}]
    assert client.get("/api/sequences").json()["total"] == total


# ---------------------------------------------------------------------------
# 4. Leap seconds and dates that do not exist are refused with their reason
# ---------------------------------------------------------------------------

def _json_doc(*times: str) -> str:
    sources = [{"x": 100.0, "y": 80.0, "brightness": 10.0}]
    return json.dumps({"format": "tubsat-snapshots/1", "sequence_id": "t", "camera": CAMERA,
                       "snapshots": [{"index": i, "time": t, "sources": sources} for i, t in enumerate(times)]})


def _json_problems(*times: str) -> list[dict]:
    with pytest.raises(TelemetryError) as err:
        parse_telemetry(_json_doc(*times))
    return err.value.to_dict()["problems"]


def test_a_leap_second_is_refused_saying_why():
    # Refused rather than moved to 23:59:59.999999 or 00:00:00: either misdates the snapshot by up to a
    # second, collides with its neighbour at 1 Hz, and skews the body rate fitted over the sequence.
    problems = _json_problems("2016-12-31T23:59:59.500Z", "2016-12-31T23:59:60.500Z", "2017-01-01T00:00:00.500Z")
    assert [p["location"] for p in problems] == ["snapshots[1].time"]
    message = problems[0]["message"]
    assert message.startswith("2016-12-31T23:59:60.500Z is a leap second, which is not supported")
    assert "body rate" in message and "not an ISO 8601 time" not in message
    csv_problems = _csv_problems(CSV_HEAD + "0,2016-12-31T23:59:60Z,1,2,3\n")
    assert csv_problems[0]["location"] == 'line 4, column "time"' and "leap second" in csv_problems[0]["message"]


@pytest.mark.parametrize("time, message", [
    ("2020-02-30T00:00:00Z", "the date 2020-02-30 does not exist (February 2020 has 29 days)"),
    ("2021-02-29T12:00:00Z", "the date 2021-02-29 does not exist (February 2021 has 28 days)"),
    ("2020-13-01T00:00:00Z", "the date 2020-13-01 does not exist (months run from 01 to 12)"),
    ("2020-01-01T25:00:00Z", "hour 25 does not exist (hours run from 00 to 23)"),
])
def test_a_date_or_hour_that_does_not_exist_says_so(time, message):
    assert _json_problems(time) == [{"location": "snapshots[0].time", "message": message}]


def test_times_that_are_not_iso_8601_keep_their_message():
    assert _json_problems("noon") == [{"location": "snapshots[0].time",
                                       "message": "not an ISO 8601 time such as 1994-03-12T21:04:10.000Z: "
                                                  "a string ('noon')"}]
    assert "ASCII digits" in _json_problems("٢٠٢٠-01-01T00:00:00Z")[0]["message"]
    assert parse_telemetry(_json_doc("2020-02-29T23:59:59.999Z")).snapshots[0].time.day == 29
