"""Search methods over REST: triangle features, tracking from a prior or from the last
confirmation, search reuse, and the sequence fit carried into the APM/AEM."""

from __future__ import annotations

import json

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.api import create_app
from app.workflow import AppContext
from app.attitude import angle_between
from kvn_reader import parse_kvn
from app.storage import Storage


@pytest.fixture()
def api(tmp_path, sky):
    ctx = AppContext(storage=Storage.open(tmp_path / "methods.sqlite3"), sky=sky)
    yield TestClient(create_app(ctx))
    ctx.close()


def _upload(api, sample_dir, name):
    r = api.post("/api/sequences", files={"file": (name, (sample_dir / name).read_bytes(), "application/json")})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _truth_boresight_error_deg(sample_dir, name, candidate, reference):
    truth = json.loads((sample_dir / name.replace(".json", ".truth.json")).read_text())
    R_true = np.asarray(truth["rotation_matrices"][reference])
    return float(np.degrees(angle_between(np.asarray(candidate["rotation_matrix"])[2], R_true[2])))


def test_triangle_feature_search_finds_the_truth(api, sample_dir):
    seq = _upload(api, sample_dir, "09-wide-30deg.json")
    doc = api.post(f"/api/sequences/{seq}/search", json={"method": "tf"}).json()
    assert doc["method"] == "tf" and doc["candidates"]
    assert _truth_boresight_error_deg(sample_dir, "09-wide-30deg.json", doc["candidates"][0],
                                      doc["reference_snapshot"]) < 0.1


def test_tracking_from_a_given_prior_and_from_the_last_confirmation(api, sample_dir):
    name = "04-big-dipper.json"
    truth = json.loads((sample_dir / "04-big-dipper.truth.json").read_text())
    seq = _upload(api, sample_dir, name)
    # No prior and nothing confirmed for this spacecraft: a clear 422.
    r = api.post(f"/api/sequences/{seq}/search", json={"method": "tracking"})
    assert r.status_code == 422 and "prior" in r.json()["detail"]
    ra, dec, roll = truth["radec_roll_deg"][8]
    r = api.post(f"/api/sequences/{seq}/search",
                 json={"method": "tracking", "prior": {"ra_deg": (ra + 0.6) % 360, "dec_deg": dec - 0.4,
                                                      "roll_deg": roll + 0.5, "sigma_deg": 1.0}})
    assert r.status_code == 200, r.text
    doc = r.json()
    assert doc["status"] == "identified"
    best = doc["candidates"][0]
    assert _truth_boresight_error_deg(sample_dir, name, best, doc["reference_snapshot"]) < 0.05
    assert any(m["name"] == "Dubhe" for m in best["matches"])
    # Confirm it; the APM states the uncertainty and the rate, the AEM has every snapshot.
    confirmed = api.post(f"/api/sequences/{seq}/confirm", json={"rank": 1, "operator": "tester"}).json()
    apm = api.get(f"/api/attitudes/{confirmed['id']}/apm").text
    assert "1-sigma uncertainty" in apm and "Body rate" in apm
    aem = parse_kvn(api.get(f"/api/sequences/{seq}/aem").text)
    lines = [line for seg in aem["segments"] for line in seg["data"]["lines"]]
    assert len(lines) == 16  # the fitted rate gives every snapshot an attitude
    # The same sky seen again (another file of this spacecraft): tracking without a prior
    # starts from the confirmed attitude, propagated with its fitted rate.
    other = json.loads((sample_dir / name).read_text())
    other["sequence_id"] = "04-big-dipper-again"
    r = api.post("/api/sequences", content=json.dumps(other).encode(), headers={"Content-Type": "application/json"})
    assert r.status_code == 201
    doc = api.post(f"/api/sequences/{r.json()['id']}/search", json={"method": "tracking"}).json()
    assert doc["status"] == "identified"
    assert _truth_boresight_error_deg(sample_dir, name, doc["candidates"][0], doc["reference_snapshot"]) < 0.05


def test_repeated_search_is_reused_until_the_pattern_changes(api, sample_dir):
    seq = _upload(api, sample_dir, "01-clean.json")
    first = api.post(f"/api/sequences/{seq}/search").json()
    again = api.post(f"/api/sequences/{seq}/search").json()
    assert again["search_id"] == first["search_id"] and again["reused"] is True and first["reused"] is False
    assert again["candidates"] == first["candidates"]
    other_count = api.post(f"/api/sequences/{seq}/search", json={"max_candidates": 2}).json()
    assert other_count["reused"] is False and len(other_count["candidates"]) <= 2
    track = first["pattern"][0]["track"]
    assert api.put(f"/api/sequences/{seq}/pattern", json={"exclude_tracks": [track]}).status_code == 200
    edited = api.post(f"/api/sequences/{seq}/search", json={"max_candidates": 2}).json()
    assert edited["reused"] is False and all(p["track"] != track for p in edited["pattern"])


def test_candidates_carry_the_sequence_fit(api, sample_dir):
    seq = _upload(api, sample_dir, "10-narrow-12deg-ghosts.json")
    truth = json.loads((sample_dir / "10-narrow-12deg-ghosts.truth.json").read_text())
    best = api.post(f"/api/sequences/{seq}/search").json()["candidates"][0]
    fit = best["sequence_fit"]
    rate_err = np.degrees(np.asarray(truth["body_rate_rad_s"])) - np.asarray(fit["rate_deg_s"])
    assert np.all(np.abs(rate_err) <= 4 * np.asarray(fit["rate_sigma_deg_s"]))
    assert fit["snapshots_used"] >= 12
