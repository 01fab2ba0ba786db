"""REST API happy paths with FastAPI's TestClient, checked against the samples' truth files."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.api import create_app
from app.workflow import AppContext
from app.workflow.access import AccessPolicy
from app.attitude import angle_between, rotation_from_radec_roll
from app.ccsds import rotation_from_ccsds_quaternion
from kvn_reader import parse_epoch, parse_kvn
from app.config import Settings
from app.storage import Storage


def _client(tmp_path, sky, **context_args) -> tuple[TestClient, AppContext]:
    ctx = AppContext(storage=Storage.open(tmp_path / "api.sqlite3"), sky=sky, **context_args)
    return TestClient(create_app(ctx)), ctx


@pytest.fixture(scope="module")
def api(tmp_path_factory, sky):
    client, ctx = _client(tmp_path_factory.mktemp("api"), sky)
    yield client
    ctx.close()


@pytest.fixture(scope="module")
def uploaded(api, sample_dir):
    """Ids of the samples this module uses, uploaded once (multipart, raw JSON and raw CSV)."""
    ids = {}
    for name in ("01-clean.json", "02-ghosts-hot-pixels.json", "03-jupiter.json"):
        r = api.post("/api/sequences", files={"file": (name, (sample_dir / name).read_bytes(), "application/json")})
        assert r.status_code == 201, r.text
        ids[name] = r.json()["id"]
    r = api.post("/api/sequences?filename=08-csv.csv", content=(sample_dir / "08-csv.csv").read_bytes(),
                 headers={"Content-Type": "text/csv"})
    assert r.status_code == 201, r.text
    ids["08-csv.csv"] = r.json()["id"]
    return ids


def _truth(sample_dir, name):
    return json.loads((sample_dir / f"{name.rsplit('.', 1)[0]}.truth.json").read_text())


def _boresight_error_deg(R, truth_radec):
    return float(np.degrees(angle_between(np.asarray(R)[2], rotation_from_radec_roll(*truth_radec)[2])))


def test_health_reports_database_and_index(api, sky):
    doc = api.get("/api/health").json()
    assert doc["status"] == "ok"
    assert doc["db"]["ok"] and doc["db"]["journal_mode"] == "wal"
    assert "path" not in doc["db"]
    assert doc["index"] == {"loaded": True, "stars": sky.index.n_stars, "pairs": sky.index.n_pairs,
                            "mag_limit": sky.index.mag_limit}
    assert doc["search_workers"].endswith("threads")  # a test's own Sky: searches stay in-process


def test_upload_returns_extraction_matching_the_file_and_truth(api, uploaded, sample_dir):
    sample = json.loads((sample_dir / "02-ghosts-hot-pixels.json").read_text())
    truth = _truth(sample_dir, "02-ghosts-hot-pixels.json")
    r = api.post("/api/sequences", content=(sample_dir / "02-ghosts-hot-pixels.json").read_bytes(),
                 headers={"Content-Type": "application/json"})
    assert r.status_code == 200  # same content again: the stored sequence
    doc = r.json()
    assert doc["id"] == uploaded["02-ghosts-hot-pixels.json"] and doc["created"] is False
    ex = doc["extraction"]
    assert [len(s) for s in ex["sources"]] == [len(s["sources"]) for s in sample["snapshots"]]
    # Every hot pixel and nearly every ghost of the truth is rejected; stars are mostly tracked.
    kinds = [[src["kind"] for src in snap] for snap in truth["sources"]]
    flat = [(k, t) for ks, ts in zip(kinds, ex["sources"]) for k, t in zip(ks, ts)]
    assert all(t is None for k, t in flat if k == "hot_pixel")
    stars = [t for k, t in flat if k == "star"]
    assert sum(t is not None for t in stars) >= 0.9 * len(stars)
    assert doc["pattern"]["version"] == 1 and doc["pattern"]["kind"] == "automatic"
    assert len(doc["pattern"]["points"]) == len(ex["pattern"])


def test_csv_upload_and_listing_with_filters(api, uploaded):
    r = api.get(f"/api/sequences/{uploaded['08-csv.csv']}")
    assert r.status_code == 200
    assert r.json()["sequence_id"] == "08-csv" and r.json()["n_snapshots"] == 16
    page = api.get("/api/sequences", params={"limit": 2}).json()
    assert page["total"] == 4 and len(page["items"]) == 2
    assert page["items"][0]["id"] > page["items"][1]["id"]  # newest first
    rest = api.get("/api/sequences", params={"limit": 2, "offset": 2}).json()["items"]
    assert {s["id"] for s in page["items"] + rest} == set(uploaded.values())
    spacecraft = page["items"][0]["spacecraft"]
    filtered = api.get("/api/sequences", params={"spacecraft": spacecraft}).json()
    assert filtered["total"] >= 1 and all(s["spacecraft"] == spacecraft for s in filtered["items"])
    assert api.get("/api/sequences", params={"spacecraft": "no such craft"}).json()["total"] == 0


def test_sequence_detail_holds_the_telemetry(api, uploaded, sample_dir):
    doc = api.get(f"/api/sequences/{uploaded['01-clean.json']}").json()
    sample = json.loads((sample_dir / "01-clean.json").read_text())
    assert len(doc["telemetry"]["snapshots"]) == len(sample["snapshots"])
    first = doc["telemetry"]["snapshots"][0]["sources"][0]
    assert first["x"] == pytest.approx(sample["snapshots"][0]["sources"][0]["x"])
    assert doc["pattern"]["definition"] == {"exclude_tracks": [], "include_tracks": None, "manual_points": []}


def test_pattern_edit_manual_point_and_reset(api, uploaded):
    sid = uploaded["02-ghosts-hot-pixels.json"]
    automatic = api.get(f"/api/sequences/{sid}").json()["pattern"]
    tracks = [p["track"] for p in automatic["points"]]
    out = tracks[0]
    ref = automatic["reference_snapshot"]
    r = api.put(f"/api/sequences/{sid}/pattern",
                json={"exclude_tracks": [out], "include_tracks": None,
                      "manual_points": [{"snapshot": ref, "x": 100.5, "y": 200.25}], "operator": "ann"})
    assert r.status_code == 200, r.text
    edited = r.json()
    assert edited["kind"] == "edit" and edited["operator"] == "ann"
    assert edited["version"] == automatic["version"] + 1
    assert [p["track"] for p in edited["points"]] == tracks[1:] + [None]
    # A point picked in the reference snapshot stays where it was picked.
    assert edited["points"][-1]["x"] == pytest.approx(100.5, abs=1e-3)
    assert edited["points"][-1]["y"] == pytest.approx(200.25, abs=1e-3)
    # The sky view names a hand-picked point by its place among the hand-picked points, as the pattern's
    # errors do ("manual point 0"), not by its row in the pattern (after every tracked point).
    assert api.post(f"/api/sequences/{sid}/search").status_code == 200
    sky_points = api.get(f"/api/sequences/{sid}/candidates/1").json()["sky"]["pattern_points"]
    assert [(p["track"], p["hand"]) for p in sky_points] == [(t, None) for t in tracks[1:]] + [(None, 0)]
    r = api.post(f"/api/sequences/{sid}/pattern/reset", json={"operator": "bob"})
    assert r.status_code == 200
    reset = r.json()
    assert reset["kind"] == "reset" and reset["version"] == edited["version"] + 1
    assert reset["points"] == automatic["points"]


def test_search_identifies_clean_sequence_within_truth(api, uploaded, sample_dir):
    sid = uploaded["01-clean.json"]
    r = api.post(f"/api/sequences/{sid}/search", json={"method": "bright_pair", "max_candidates": 3})
    assert r.status_code == 200, r.text
    doc = r.json()
    assert doc["status"] == "identified" and 1 <= len(doc["candidates"]) <= 3
    ref = doc["reference_snapshot"]
    truth = _truth(sample_dir, "01-clean.json")
    assert _boresight_error_deg(doc["candidates"][0]["rotation_matrix"], truth["radec_roll_deg"][ref]) < 0.1
    assert api.get(f"/api/sequences/{sid}").json()["status"] == "identified"
    # Matched stars are the truth's stars of the tracks they explain.
    sources = api.get(f"/api/sequences/{sid}").json()["extraction"]["sources"]
    truth_hip_of_track = {}
    for snap_tracks, snap_truth in zip(sources, truth["sources"]):
        for track, what in zip(snap_tracks, snap_truth):
            if track is not None:
                truth_hip_of_track[track] = what["hip"]
    matches = doc["candidates"][0]["matches"]
    assert len(matches) >= 5
    assert all(truth_hip_of_track[m["track"]] == m["hip"] for m in matches)


def test_a_focal_length_the_stars_contradict_is_a_member_of_the_stored_search(api, uploaded, tmp_path):
    """A camera 8 % longer than declared (5 % tolerance): the search finds nothing credible, and its
    document names the focal length the stars fit (the simulator's truth, to 0.5 %), as returned and as
    read back from the archive; a clean sample's search has none."""
    from app.cli import main as cli_main

    assert cli_main(["simulate", str(tmp_path), "--n", "1", "--seed", "5", "--scenario", "single",
                     "--focal-error", "0.08"]) == 0
    [path] = [p for p in tmp_path.glob("*.json") if not p.name.endswith(".truth.json")]
    true_focal = json.loads(path.with_name(path.stem + ".truth.json").read_text())["true_camera"]["focal_length_px"]
    r = api.post(f"/api/sequences?filename={path.name}", content=path.read_bytes(),
                 headers={"Content-Type": "application/json"})
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    searched = api.post(f"/api/sequences/{sid}/search").json()
    assert searched["status"] != "identified"
    found = searched["focal_length_contradiction"]
    assert found["focal_length_px"] == pytest.approx(true_focal, rel=0.005)
    assert found["offset"] == pytest.approx(found["focal_length_px"] / found["declared_focal_length_px"] - 1, abs=1e-6)
    assert f"{found['focal_length_px']:.1f} px" in found["note"] and "outside its tolerance" in found["note"]
    assert not any("bright triangles fit" in note for note in searched["notes"])  # said once, there
    assert api.get(f"/api/sequences/{sid}").json()["search"]["focal_length_contradiction"] == found
    clean = api.post(f"/api/sequences/{uploaded['01-clean.json']}/search").json()
    assert clean["status"] == "identified" and clean["focal_length_contradiction"] is None


def test_candidate_sky_section_puts_stars_on_their_sources(api, uploaded, sample_dir):
    sid = uploaded["01-clean.json"]
    if api.get(f"/api/sequences/{sid}").json()["search"] is None:
        api.post(f"/api/sequences/{sid}/search")
    r = api.get(f"/api/sequences/{sid}/candidates/1", params={"mag": 5.5})
    assert r.status_code == 200, r.text
    doc = r.json()
    sky = doc["sky"]
    ref = doc["reference_snapshot"]
    sample = json.loads((sample_dir / "01-clean.json").read_text())
    truth = _truth(sample_dir, "01-clean.json")
    by_hip = {s["hip"]: s for s in sky["stars"]}
    # Independent check: each true star source of the reference snapshot lies where the view draws its star.
    checked = 0
    for src, what in zip(sample["snapshots"][ref]["sources"], truth["sources"][ref]):
        if what["kind"] == "star" and what["hip"] in by_hip:
            star = by_hip[what["hip"]]
            assert star["on_sensor"]
            assert np.hypot(star["x"] - src["x"], star["y"] - src["y"]) < 3.0
            checked += 1
    assert checked >= 5
    assert all(s["mag"] <= 5.5 or s["matched"] for s in sky["stars"])
    x0, x1, y0, y1 = (sky["bounds"][k] for k in ("x_min", "x_max", "y_min", "y_max"))
    assert all(x0 <= s["x"] <= x1 and y0 <= s["y"] <= y1 for s in sky["stars"])
    assert any(not s["on_sensor"] for s in sky["stars"])  # the 20% margin shows stars around the field
    # Residual vectors go from each matched point to its star and are small for the right attitude.
    matched = [p for p in sky["pattern_points"] if p["hip"] is not None]
    assert len(matched) == len(doc["candidate"]["matches"])
    for p in matched:
        assert p["star_x"] == pytest.approx(p["x"] + p["residual_x"], abs=0.02)
        assert np.hypot(p["residual_x"], p["residual_y"]) < 2.0
        assert by_hip[p["hip"]]["pattern_index"] == p["index"]
    edge = sky["generating_edge"]
    points = doc["candidate"]["generating_edge"]
    assert edge["pattern_indices"] == points
    assert [s["hip"] for s in edge["stars"]] == doc["candidate"]["generating_pair_hip"]
    assert {s["constellation"] for s in sky["stars"]} >= {sky["center"]["constellation"]}
    assert sum(c["n_stars"] for c in sky["constellations"]) == len(sky["stars"])
    fainter = api.get(f"/api/sequences/{sid}/candidates/1", params={"mag": 6.5}).json()["sky"]["stars"]
    assert len(fainter) > len(sky["stars"])


def test_planet_is_labelled_in_the_sky_section(api, uploaded):
    sid = uploaded["03-jupiter.json"]
    doc = api.post(f"/api/sequences/{sid}/search").json()
    assert doc["candidates"], doc
    best = doc["candidates"][0]
    assert [p["name"] for p in best["planets"]] == ["jupiter"]
    view = api.get(f"/api/sequences/{sid}/candidates/1").json()["sky"]
    jupiter = next(p for p in view["planets"] if p["name"] == "jupiter")
    point = view["pattern_points"][jupiter["pattern_index"]]
    assert point["planet"] == "jupiter"
    assert np.hypot(jupiter["x"] - point["x"], jupiter["y"] - point["y"]) < 3.0


def test_confirm_apm_aem_and_supersession(api, uploaded, sample_dir):
    sid = uploaded["01-clean.json"]
    search = api.post(f"/api/sequences/{sid}/search").json()
    best = search["candidates"][0]
    r = api.post(f"/api/sequences/{sid}/confirm", json={"rank": 1, "operator": "ann", "comment": "clear field"})
    assert r.status_code == 201, r.text
    first = r.json()
    assert first["operator"] == "ann" and first["comment"] == "clear field" and first["current"]
    assert api.get(f"/api/sequences/{sid}").json()["status"] == "confirmed"
    truth = _truth(sample_dir, "01-clean.json")
    ref = search["reference_snapshot"]
    assert _boresight_error_deg(first["rotation_matrix"], truth["radec_roll_deg"][ref]) < 0.1

    apm = api.get(first["apm_url"])
    assert apm.status_code == 200 and apm.headers["content-type"].startswith("text/plain")
    assert re.search(r'attachment; filename="[A-Za-z0-9._-]+\.apm"', apm.headers["content-disposition"])
    parsed = parse_kvn(apm.text)
    quat = parsed["data"]["blocks"][0]
    assert (quat["REF_FRAME_A"], quat["REF_FRAME_B"]) == ("ICRF", "SENSOR_1")
    R = rotation_from_ccsds_quaternion(quat["Q1"], quat["Q2"], quat["Q3"], quat["QC"])
    assert np.allclose(R, best["rotation_matrix"], atol=1e-8)
    assert parse_epoch(parsed["data"]["EPOCH"]) == parse_epoch(truth["times"][ref].rstrip("Z"))

    aem = api.get(f"/api/sequences/{sid}/aem")
    assert aem.status_code == 200 and ".aem" in aem.headers["content-disposition"]
    lines = parse_kvn(aem.text)["segments"][0]["data"]["lines"]
    assert len(lines) == 16  # the clean sequence links every snapshot
    truth_times = [parse_epoch(t.rstrip("Z")) for t in truth["times"]]
    for epoch, q1, q2, q3, qc in lines:
        i = truth_times.index(parse_epoch(epoch))
        Ri = rotation_from_ccsds_quaternion(q1, q2, q3, qc)
        assert _boresight_error_deg(Ri, truth["radec_roll_deg"][i]) < 0.1

    # The same candidate again is the same record (200); a new record needs an explicit supersede (issue 13).
    repeat = api.post(f"/api/sequences/{sid}/confirm", json={"rank": 1, "operator": "bob"})
    assert repeat.status_code == 200 and repeat.json()["id"] == first["id"]
    second = api.post(f"/api/sequences/{sid}/confirm", json={"rank": 1, "operator": "bob", "supersede": True}).json()
    assert second["id"] > first["id"]
    again = api.get(f"/api/attitudes/{first['id']}").json()
    assert again["superseded_by"] == second["id"] and not again["current"]
    assert api.get(first["apm_url"]).text == apm.text  # stored once, never re-rendered
    listing = api.get("/api/attitudes").json()
    assert [a["id"] for a in listing["items"][:2]] == [second["id"], first["id"]]
    assert "confirmed by bob" in api.get(f"/api/sequences/{sid}/aem").text  # the current confirmation
    # Each attitude's AEM is its own, superseded or not (its link once gave the sequence's current one).
    assert first["aem_url"] == f"/api/attitudes/{first['id']}/aem"
    assert api.get(first["aem_url"]).text == aem.text
    assert "confirmed by bob" in api.get(second["aem_url"]).text and api.get(second["aem_url"]).text != aem.text


def test_token_operator_wins_over_body_operator(tmp_path, sky, sample_dir):
    access = AccessPolicy.for_host("0.0.0.0", {"s3cret": "carol"})
    client, ctx = _client(tmp_path, sky, access=access, settings=Settings())
    try:
        data = (sample_dir / "01-clean.json").read_bytes()
        assert client.post("/api/sequences", content=data).status_code == 401
        auth = {"Authorization": "Bearer s3cret"}
        sid = client.post("/api/sequences", content=data, headers=auth).json()["id"]
        assert client.get(f"/api/sequences/{sid}").status_code == 200  # reads need no token
        assert client.post(f"/api/sequences/{sid}/search", headers=auth).status_code == 200
        r = client.post(f"/api/sequences/{sid}/confirm", json={"rank": 1, "operator": "mallory"}, headers=auth)
        assert r.status_code == 201 and r.json()["operator"] == "carol"
        edit = client.put(f"/api/sequences/{sid}/pattern", json={"operator": "mallory"}, headers=auth).json()
        assert edit["operator"] == "carol"
    finally:
        ctx.close()


def test_docs_page_uses_only_local_assets(api):
    html = api.get("/docs").text
    assert "/vendor/swagger-ui/swagger-ui-bundle.js" in html and "/openapi.json" in html
    assert not re.search(r"https?://", html.split("<body>")[0] + "".join(re.findall(r'src="[^"]*"', html)))
    assert api.get("/vendor/swagger-ui/swagger-ui-bundle.js").status_code == 200
    assert api.get("/vendor/swagger-ui/swagger-ui.css").status_code == 200
    assert api.get("/redoc").status_code == 404
