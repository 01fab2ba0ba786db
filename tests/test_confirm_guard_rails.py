"""Guard rails before a confirmation, "no valid attitude", supersede and the work queue (issue 13), through
the REST API with FastAPI's TestClient.

The facts checked come from the archive and the samples' truth: which
candidate is the true attitude (rank 1 of the identified samples, within
0.1 deg of the truth), that the Earth sample has no match, and what the
audit trail holds after each step.
"""

from __future__ import annotations

import json
import sqlite3
from datetime import datetime, timedelta

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.api import create_app
from app.attitude import angle_between, rotation_from_radec_roll
from app.storage import Storage
from app.workflow import AppContext
from app.workflow.documents import SearchResult
from kvn_reader import parse_kvn


@pytest.fixture(scope="module")
def env(tmp_path_factory, sky, sample_dir):
    """(client, context, {sample name: sequence id}) with 02 (identified), 05 (no match), 06 and 01, and a
    copy of 01 made ambiguous by keeping its four brightest tracks (``"ambiguous"``: four stars fit, but not
    beyond doubt; three fit too many places to be credible at all), uploaded and searched."""
    ctx = AppContext(storage=Storage.open(tmp_path_factory.mktemp("guard") / "guard.sqlite3"), sky=sky)
    client = TestClient(create_app(ctx))
    ids = {}
    for name in ("02-ghosts-hot-pixels.json", "05-earth.json", "06-sparse.json", "01-clean.json"):
        r = client.post("/api/sequences", content=(sample_dir / name).read_bytes())
        assert r.status_code == 201, r.text
        ids[name] = r.json()["id"]
    copy = json.loads((sample_dir / "01-clean.json").read_text())
    copy["sequence_id"] += "-four-stars"
    r = client.post("/api/sequences", content=json.dumps(copy).encode())
    assert r.status_code == 201, r.text
    ids["ambiguous"] = four = r.json()["id"]
    points = client.get(f"/api/sequences/{four}").json()["pattern"]["points"]
    brightest = [p["track"] for p in sorted(points, key=lambda p: -(p["brightness"] or 0))][:4]
    assert client.put(f"/api/sequences/{four}/pattern", json={"include_tracks": brightest}).status_code == 200
    for sid in ids.values():
        assert client.post(f"/api/sequences/{sid}/search", json={}).status_code == 200
    yield client, ctx, ids
    ctx.close()


def _truth(sample_dir, name):
    return json.loads((sample_dir / f"{name.rsplit('.', 1)[0]}.truth.json").read_text())


def _attitude_count(client) -> int:
    return client.get("/api/attitudes").json()["total"]


def test_review_says_which_candidate_is_credible_and_why_the_others_are_not(env, sample_dir):
    client, _, ids = env
    sid = ids["02-ghosts-hot-pixels.json"]
    search = client.get(f"/api/sequences/{sid}").json()["search"]
    review = client.get(f"/api/sequences/{sid}/review").json()
    assert review["search_status"] == search["status"] == "identified" and not review["stale"]
    verdicts = {v["rank"]: v for v in review["candidates"]}
    assert set(verdicts) == {c["rank"] for c in search["candidates"]}
    # Rank 1 is the truth and the only credible one.
    truth = _truth(sample_dir, "02-ghosts-hot-pixels.json")
    best = search["candidates"][0]
    error = np.degrees(angle_between(np.array(best["rotation_matrix"])[2],
                                     rotation_from_radec_roll(*truth["radec_roll_deg"][search["reference_snapshot"]])[2]))
    assert error < 0.1
    assert verdicts[1]["credible"] and verdicts[1]["reasons"] == []
    assert verdicts[1]["deviation_gap_arcsec"] == 0 and verdicts[1]["separation_from_best_deg"] == 0
    for c in search["candidates"][1:]:
        v = verdicts[c["rank"]]
        assert not v["credible"]
        text = " | ".join(v["reasons"])
        assert "not the best candidate" in text
        if c["false_match_probability"] > 1e-6:
            assert "above the 'identified' threshold" in text
        if c["n_matched"] < 4:
            assert f"few matches: {c['n_matched']} of" in text
        assert v["deviation_gap_arcsec"] == pytest.approx(c["deviation_arcsec"] - best["deviation_arcsec"], abs=0.1)
        assert v["odds_vs_best"] > 0  # likelier to be chance than rank 1


def test_a_non_credible_candidate_needs_a_reason_and_keeps_it(env):
    client, _, ids = env
    sid = ids["02-ghosts-hot-pixels.json"]
    before = _attitude_count(client)
    refused = client.post(f"/api/sequences/{sid}/confirm", json={"rank": 2, "operator": "ann"})
    assert refused.status_code == 409
    assert "not the credible best" in refused.json()["detail"] and "override_reason" in refused.json()["detail"]
    assert _attitude_count(client) == before  # nothing stored
    assert client.get(f"/api/sequences/{sid}").json()["status"] == "identified"
    assert client.get(f"/api/sequences/{sid}/review").json()["audit"] == []

    reason = "rank 1 is a known reflection; the flight dynamics team confirmed rank 2"
    r = client.post(f"/api/sequences/{sid}/confirm",
                    json={"rank": 2, "operator": "ann", "override_reason": f"  {reason} "})
    assert r.status_code == 201, r.text
    stored = r.json()
    assert stored["rank"] == 2 and stored["override_reason"] == reason
    assert any("not the best candidate" in text for text in stored["overridden"])
    apm = client.get(stored["apm_url"]).text
    # Comments are wrapped between words at the KVN line length: read them back as one text.
    comments = " ".join(line[len("COMMENT "):] for line in apm.splitlines() if line.startswith("COMMENT "))
    assert "operator override" in comments and reason in comments
    # ... and so do the AEM (the bulk export's segments are its text) and the ACM: whoever reads one alone sees it.
    for url in (stored["aem_url"], stored["apm_url"].replace("/apm", "/acm")):
        text = client.get(url).text
        said = " ".join(line[len("COMMENT "):] for line in text.splitlines() if line.strip().startswith("COMMENT "))
        assert "operator override" in said and reason in said, url
    assert _attitude_count(client) == before + 1
    audit = client.get(f"/api/sequences/{sid}/review").json()["audit"]
    assert [(e["kind"], e["id"], e["reason"], e["current"]) for e in audit] == [("confirmed", stored["id"], reason, True)]


def test_confirming_the_same_again_is_one_record_and_a_change_needs_supersede(env):
    client, _, ids = env
    sid = ids["02-ghosts-hot-pixels.json"]
    current = client.get(f"/api/sequences/{sid}/review").json()["confirmation"]
    count = _attitude_count(client)
    again = client.post(f"/api/sequences/{sid}/confirm", json={"rank": current["rank"], "operator": "bob"})
    assert again.status_code == 200 and again.json()["id"] == current["id"] and again.json()["operator"] == "ann"
    assert _attitude_count(client) == count

    other = client.post(f"/api/sequences/{sid}/confirm", json={"rank": 1, "operator": "bob"})
    assert other.status_code == 409
    assert f"attitude #{current['id']}" in other.json()["detail"] and "supersede" in other.json()["detail"]
    assert _attitude_count(client) == count

    new = client.post(f"/api/sequences/{sid}/confirm", json={"rank": 1, "operator": "bob", "supersede": True})
    assert new.status_code == 201 and new.json()["override_reason"] is None and new.json()["overridden"] == []
    old = client.get(f"/api/attitudes/{current['id']}").json()
    assert old["superseded_by"] == new.json()["id"] and not old["current"]


def test_a_stale_or_replaced_search_is_not_confirmed_silently(env):
    client, _, ids = env
    sid = ids["01-clean.json"]
    detail = client.get(f"/api/sequences/{sid}").json()
    search_id = detail["search"]["search_id"]
    # Another console takes a track out: the search on screen is now older than the pattern.
    track = detail["pattern"]["points"][0]["track"]
    assert client.put(f"/api/sequences/{sid}/pattern", json={"exclude_tracks": [track]}).status_code == 200
    review = client.get(f"/api/sequences/{sid}/review").json()
    assert review["stale"] and not review["candidates"][0]["credible"]
    assert review["candidates"][0]["reasons"][0].startswith("stale: the pattern changed since this search")
    refused = client.post(f"/api/sequences/{sid}/confirm", json={"rank": 1, "operator": "ann", "search_id": search_id})
    assert refused.status_code == 409 and "stale" in refused.json()["detail"]
    # A new search replaces the one the operator looked at: naming the old one is refused.
    new = client.post(f"/api/sequences/{sid}/search", json={}).json()
    assert new["search_id"] != search_id
    replaced = client.post(f"/api/sequences/{sid}/confirm", json={"rank": 1, "operator": "ann", "search_id": search_id})
    assert replaced.status_code == 409 and f"search {new['search_id']}" in replaced.json()["detail"]
    ok = client.post(f"/api/sequences/{sid}/confirm",
                     json={"rank": 1, "operator": "ann", "search_id": new["search_id"]})
    assert ok.status_code == 201, ok.text
    assert client.get(f"/api/sequences/{sid}/review").json()["confirmation"]["search_id"] == new["search_id"]


def test_no_match_is_rejected_with_a_reason_and_a_rejection_is_a_verdict(env):
    client, ctx, ids = env
    sid = ids["05-earth.json"]
    review = client.get(f"/api/sequences/{sid}/review").json()
    assert review["search_status"] == "no_match"
    assert all(not v["credible"] for v in review["candidates"])
    assert any("no match" in text for text in review["candidates"][0]["reasons"])
    refused = client.post(f"/api/sequences/{sid}/confirm", json={"rank": 1, "operator": "ann"})
    assert refused.status_code == 409 and "no match" in refused.json()["detail"]

    missing = client.post(f"/api/sequences/{sid}/reject", json={"reason": "   ", "operator": "ann"})
    assert missing.status_code == 422 and missing.json()["problems"][0]["location"] == "body.reason"
    assert client.post(f"/api/sequences/{sid}/reject", json={"reason": "x"}).status_code == 422  # no operator
    reason = "the Earth fills the field: clouds and glints, no star"
    r = client.post(f"/api/sequences/{sid}/reject", json={"reason": reason, "operator": "ann"})
    assert r.status_code == 201, r.text
    rejection = r.json()
    assert rejection["reason"] == reason and rejection["current"] and rejection["search_id"] == review["search_id"]
    assert client.get(f"/api/sequences/{sid}").json()["status"] == "rejected"
    assert client.get("/api/sequences", params={"status": "rejected"}).json()["items"][0]["id"] == sid
    aem = client.get(f"/api/sequences/{sid}/aem")
    assert aem.status_code == 404 and "no valid attitude" in aem.json()["detail"]
    again = client.post(f"/api/sequences/{sid}/reject", json={"reason": "again", "operator": "bob"})
    assert again.status_code == 200 and again.json()["id"] == rejection["id"]  # one verdict, one record

    # Confirming over a rejection: explicit supersede, and the override reason for a no-match candidate.
    assert client.post(f"/api/sequences/{sid}/confirm", json={"rank": 1, "operator": "bob",
                                                              "override_reason": "test"}).status_code == 409
    c = client.post(f"/api/sequences/{sid}/confirm", json={"rank": 1, "operator": "bob", "supersede": True,
                                                           "override_reason": "a cloud pattern test"})
    assert c.status_code == 201 and c.json()["replaces_rejection"] == rejection["id"]
    assert client.get(f"/api/sequences/{sid}").json()["status"] == "confirmed"
    # ... and withdrawing that confirmation again: the confirmation is no longer current anywhere.
    assert client.post(f"/api/sequences/{sid}/reject", json={"reason": "no", "operator": "cy"}).status_code == 409
    w = client.post(f"/api/sequences/{sid}/reject", json={"reason": "really no star", "operator": "cy",
                                                          "supersede": True})
    assert w.status_code == 201 and w.json()["replaces_confirmation"] == c.json()["id"]
    withdrawn = client.get(f"/api/attitudes/{c.json()['id']}").json()
    assert not withdrawn["current"] and withdrawn["withdrawn_by"] == w.json()["id"] and withdrawn["superseded_by"] is None
    assert ctx.storage.current_confirmation(sid) is None
    audit = client.get(f"/api/sequences/{sid}/review").json()["audit"]
    assert [(e["kind"], e["current"]) for e in audit] == [("rejected", False), ("confirmed", False), ("rejected", True)]

    # The append-only guard holds for rejections too.
    raw = sqlite3.connect(ctx.storage.path)
    for sql in ("UPDATE rejections SET reason = 'edited'", "DELETE FROM rejections",
                "UPDATE confirmations SET override_reason = 'edited'"):
        with pytest.raises(sqlite3.DatabaseError):
            raw.execute(sql)
    raw.close()


def test_the_queue_puts_what_needs_an_operator_first(env):
    client, _, ids = env
    statuses = {s["id"]: s["status"] for s in client.get("/api/sequences").json()["items"]}
    assert statuses[ids["ambiguous"]] == "ambiguous", "the four-star pattern must leave an operator the choice"
    assert {"ambiguous", "rejected", "confirmed"} <= set(statuses.values())
    page = client.get("/api/sequences", params={"order": "queue"}).json()
    order = ["ambiguous", "no_match", "identified", "new", "rejected", "confirmed"]
    got = [order.index(s["status"]) for s in page["items"]]
    assert got == sorted(got) and page["items"][0]["id"] == ids["ambiguous"]
    # Search by sequence id, and a page larger than 8 when there is more.
    found = client.get("/api/sequences", params={"search": "EARTH"}).json()
    assert [s["id"] for s in found["items"]] == [ids["05-earth.json"]]
    assert client.get("/api/sequences", params={"search": f"#{ids['01-clean.json']}"}).json()["total"] == 1
    assert client.get("/api/sequences", params={"search": "%"}).json()["total"] == 0  # a literal %, no wildcard
    bad = client.get("/api/sequences", params={"order": "random"})
    assert bad.status_code == 422 and bad.json()["problems"][0]["location"] == "query.order"
    assert client.get("/api/spacecraft").json() == [{"name": "SIM-TUBSAT", "sequences": 5}]


def test_a_best_candidate_chance_explains_is_never_credible_whatever_the_status(env):
    """The review does not take a search's status on trust: a best candidate matching 2 of 10 points with a
    false-match probability of 1 (what tracking once called identified) needs the second step and a reason;
    one that explains every point of its pattern (tracking's two-point patterns) does not."""
    from app.workflow.review import candidate_verdicts

    client, _, ids = env
    search = SearchResult.model_validate(client.get(f"/api/sequences/{ids['02-ghosts-hot-pixels.json']}").json()["search"])
    assert search.status == "identified" and candidate_verdicts(search, search.pattern_version)[0].credible
    best = search.candidates[0]
    chance = search.model_copy(update={"candidates": [best.model_copy(update={
        "false_match_probability": 1.0, "n_matched": 2, "matches": best.matches[:2]})]})
    verdict = candidate_verdicts(chance, search.pattern_version)[0]
    assert not verdict.credible
    assert any("above the 'identified' threshold" in r for r in verdict.reasons)
    two_points = chance.model_copy(update={"pattern": chance.pattern[:2]})
    assert candidate_verdicts(two_points, search.pattern_version)[0].credible


def test_bulk_aem_holds_one_segment_per_confirmed_sequence_in_the_range(env):
    client, _, ids = env
    confirmed = [a for a in client.get("/api/attitudes").json()["items"] if a["current"]]
    assert len(confirmed) >= 2
    r = client.get("/api/attitudes/aem", params={"spacecraft": "SIM-TUBSAT"})
    assert r.status_code == 200 and ".aem" in r.headers["content-disposition"]
    parsed = parse_kvn(r.text)
    assert len(parsed["segments"]) == len(confirmed)
    # Each segment is its sequence's stored AEM segment, byte for byte.
    for a in confirmed:
        stored = client.get(a["aem_url"]).text
        assert stored[stored.index("META_START"):].rstrip("\n") in r.text
    # A range around one epoch holds that one only.
    first = min(datetime.fromisoformat(a["epoch"].replace("Z", "+00:00")) for a in confirmed)
    one = client.get("/api/attitudes/aem", params={"spacecraft": "SIM-TUBSAT", "start": first.isoformat(),
                                                   "end": (first + timedelta(seconds=1)).isoformat()})
    assert one.status_code == 200 and len(parse_kvn(one.text)["segments"]) == 1
    # The header says the range in words (it once read "Time range - to -" for no range).
    assert "COMMENT Time range: every confirmed attitude" in r.text
    assert "overlap" not in r.text  # their times are years apart
    assert "Time range: reference epochs from " in one.text and " to before " in one.text
    empty = client.get("/api/attitudes/aem", params={"spacecraft": "NOBODY"})
    assert empty.status_code == 404 and "NOBODY" in empty.json()["detail"]
    backwards = client.get("/api/attitudes/aem", params={"spacecraft": "SIM-TUBSAT", "start": "2001-01-02T00:00:00Z",
                                                         "end": "2001-01-01T00:00:00Z"})
    assert backwards.status_code == 422 and backwards.json()["problems"][0]["location"] == "query.end"
    assert client.get("/api/attitudes/aem", params={"spacecraft": "SIM-TUBSAT", "start": "yesterday"}).status_code == 422


def test_bulk_aem_warns_of_segments_of_one_spacecraft_that_overlap_in_time(tmp_path, sky, sample_dir):
    """02 and 04 were simulated for one spacecraft over the same 36 seconds, pointing at two constellations:
    confirmed both, their AEM says that one of them cannot be this spacecraft's at those times."""
    ctx = AppContext(storage=Storage.open(tmp_path / "overlap.sqlite3"), sky=sky)
    client = TestClient(create_app(ctx))
    try:
        attitudes = {}
        for name in ("02-ghosts-hot-pixels.json", "04-big-dipper.json"):
            sid = client.post("/api/sequences", content=(sample_dir / name).read_bytes()).json()["id"]
            assert client.post(f"/api/sequences/{sid}/search", json={}).json()["status"] == "identified"
            r = client.post(f"/api/sequences/{sid}/confirm", json={"rank": 1, "operator": "ann"})
            assert r.status_code in (200, 201), r.text
            attitudes[name.removesuffix(".json")] = r.json()["id"]
        text = client.get("/api/attitudes/aem", params={"spacecraft": "SIM-TUBSAT"}).text
        spans = [(seg["metadata"]["START_TIME"], seg["metadata"]["STOP_TIME"]) for seg in parse_kvn(text)["segments"]]
        assert spans[0] == spans[1]  # the same seconds
        warning = " ".join(line.removeprefix("COMMENT ") for line in text.split("META_START")[0].splitlines()
                           if line.startswith("COMMENT "))
        pair = [f"{name} (attitude {attitude})" for name, attitude in attitudes.items()]
        assert any(f"WARNING: the segments of sequences {a} and {b} overlap in time, from {spans[0][0]} to "
                   f"{spans[0][1]}: a spacecraft has one attitude at a time" in warning
                   for a, b in (pair, pair[::-1])), warning
    finally:
        ctx.close()


def test_each_console_session_keeps_its_own_view(env):
    client, ctx, ids = env
    a, b = ids["02-ghosts-hot-pixels.json"], ids["05-earth.json"]
    assert client.put("/api/view", params={"session": "tab-a"}, json={"sequence": a}).json()["sequence"] == a
    assert client.put("/api/view", params={"session": "tab-b"}, json={"sequence": b, "rank": 2}).json()["rank"] == 2
    doc_a = client.get("/api/view", params={"session": "tab-a"}).json()
    assert (doc_a["sequence"], doc_a["rank"], doc_a["session"]) == (a, 1, "tab-a")
    assert client.get("/api/view", params={"session": "tab-b"}).json()["sequence"] == b
    assert client.get("/api/view", params={"session": "never-written"}).json()["sequence"] is None
    # The 3D view draws the session of the console that opened it; requests without a session mean it.
    followed = client.put("/api/viewer", json={"session": "tab-b"}).json()
    assert followed["followed_by_3d"] and followed["sequence"] == b
    assert client.get("/api/view").json()["session"] == "tab-b"
    assert ctx.view.get().sequence == b  # what the 3D view reads
    assert not client.get("/api/view", params={"session": "tab-a"}).json()["followed_by_3d"]
    bad = client.get("/api/view", params={"session": "../etc"})
    assert bad.status_code == 422 and bad.json()["problems"][0]["location"] == "query.session"
    assert client.put("/api/viewer", json={"session": ""}).status_code == 422


def test_operator_endpoint_names_the_token_operator(tmp_path, sky):
    from app.workflow.access import AccessPolicy

    ctx = AppContext(storage=Storage.open(tmp_path / "op.sqlite3"), sky=sky,
                     access=AccessPolicy.for_host("0.0.0.0", {"tok-1": "carol"}))
    try:
        client = TestClient(create_app(ctx))
        assert client.get("/api/operator").json() == {"auth_required": True, "operator": None}
        me = client.get("/api/operator", headers={"Authorization": "Bearer tok-1"}).json()
        assert me == {"auth_required": True, "operator": "carol"}
        assert client.get("/api/operator", headers={"Authorization": "Bearer wrong"}).status_code == 401
    finally:
        ctx.close()


def test_an_upload_can_ask_to_be_searched_right_away(tmp_path, sky, sample_dir):
    ctx = AppContext(storage=Storage.open(tmp_path / "auto.sqlite3"), sky=sky)
    try:
        client = TestClient(create_app(ctx))
        # TestClient returns once the app is done, background task included.
        r = client.post("/api/sequences", params={"search": "true"},
                        content=(sample_dir / "04-big-dipper.json").read_bytes())
        assert r.status_code == 201 and r.json()["sequence"]["status"] == "new"
        detail = client.get(f"/api/sequences/{r.json()['id']}").json()
        assert detail["status"] == "identified" and detail["search"]["method"] == "bright_pair"
        plain = client.post("/api/sequences", content=(sample_dir / "06-sparse.json").read_bytes())
        assert client.get(f"/api/sequences/{plain.json()['id']}").json()["search"] is None
        # The same file again, now asking for the search: stored already (200) but never searched, so
        # it is searched now; a third time it keeps that search.
        again = client.post("/api/sequences", params={"search": "true"},
                            content=(sample_dir / "06-sparse.json").read_bytes())
        assert again.status_code == 200 and again.json()["id"] == plain.json()["id"]
        searched = client.get(f"/api/sequences/{plain.json()['id']}").json()["search"]
        assert searched is not None and searched["method"] == "bright_pair"
        client.post("/api/sequences", params={"search": "true"}, content=(sample_dir / "06-sparse.json").read_bytes())
        assert client.get(f"/api/sequences/{plain.json()['id']}").json()["search"]["search_id"] == searched["search_id"]
    finally:
        ctx.close()


def test_a_verdict_replaces_only_the_verdict_its_operator_saw(tmp_path, sky, sample_dir):
    """An operator trial: Alice had the step open to replace Bob's confirmation with rank 2; Bob meanwhile
    recorded "no valid attitude"; Alice's Supersede replaced Bob's rejection, which she never saw.  With
    ``replaces`` naming the verdict seen, a verdict given in between is refused (409) and kept."""
    ctx = AppContext(storage=Storage.open(tmp_path / "replaces.sqlite3"), sky=sky)
    client = TestClient(create_app(ctx))
    try:
        sid = client.post("/api/sequences", content=(sample_dir / "02-ghosts-hot-pixels.json").read_bytes()).json()["id"]
        search = client.post(f"/api/sequences/{sid}/search").json()
        url = f"/api/sequences/{sid}"
        nothing = client.post(f"{url}/confirm", json={"rank": 1, "operator": "bob", "supersede": True,
                                                      "replaces": {"kind": "attitude", "id": 1}})
        assert nothing.status_code == 422 and nothing.json()["problems"][0]["location"] == "body.replaces"
        bob = client.post(f"{url}/confirm", json={"rank": 1, "operator": "bob"}).json()
        seen = {"kind": "attitude", "id": bob["id"]}
        rejected = client.post(f"{url}/reject", json={"reason": "a ghost pattern", "operator": "bob", "supersede": True,
                                                      "replaces": seen})
        assert rejected.status_code == 201, rejected.text
        alice = client.post(f"{url}/confirm", json={"rank": 2, "operator": "alice", "supersede": True, "replaces": seen,
                                                    "override_reason": "rank 1 is a ghost", "search_id": search["search_id"]})
        assert alice.status_code == 409, alice.text
        assert alice.json()["detail"].startswith(f"another verdict came first: sequence {sid}'s verdict is now "
                                                 "'no valid attitude' recorded by bob at ")
        assert f"not attitude #{bob['id']}, named to be replaced" in alice.json()["detail"]
        again = client.post(f"{url}/reject", json={"reason": "clouds", "operator": "carl", "supersede": True,
                                                   "replaces": seen})
        assert again.status_code == 409
        review = client.get(f"{url}/review").json()
        assert review["rejection"]["id"] == rejected.json()["id"] and review["confirmation"] is None
        # Naming the verdict now current replaces it; without ``replaces``, supersede replaces whatever is current.
        now = {"kind": "rejection", "id": rejected.json()["id"]}
        assert client.post(f"{url}/confirm", json={"rank": 1, "operator": "alice", "supersede": True,
                                                   "replaces": now}).status_code == 201
        assert client.post(f"{url}/reject", json={"reason": "clouds", "operator": "carl",
                                                  "supersede": True}).status_code == 201
        assert [e["kind"] for e in client.get(f"{url}/review").json()["audit"]] == \
            ["confirmed", "rejected", "confirmed", "rejected"]
    finally:
        ctx.close()
