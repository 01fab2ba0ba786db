"""POST /api/frames (issue 15): a pass of frames becomes an archived sequence; bad images give located 422s."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from astropy.io import fits
from fastapi.testclient import TestClient

from app.api import create_app
from app.attitude import angle_between
from app.camera import CAMERAS
from app.simulate import frame_png_bytes, frames_fits_bytes, frames_sidecar, simulate_frames
from app.storage import Storage
from app.workflow import AppContext

CAMERA = CAMERAS["tubsat-752x582-20deg"]


@pytest.fixture(scope="module")
def api(tmp_path_factory, sky):
    ctx = AppContext(storage=Storage.open(tmp_path_factory.mktemp("frames") / "api.sqlite3"), sky=sky)
    yield TestClient(create_app(ctx))
    ctx.close()


@pytest.fixture(scope="module")
def rendered():
    return simulate_frames(np.random.default_rng(404), CAMERA, n_frames=4, trail=True)


def _fits_upload(frames, times, **fields):
    data = frames_fits_bytes(frames, times, camera=CAMERA, spacecraft="API-SAT")
    return {"files": [("files", ("pass.fits", data, "application/fits"))], "data": fields}


def test_a_fits_pass_is_stored_once_as_an_ordinary_sequence_and_identified(api, rendered):
    frames, times, truth = rendered
    r = api.post("/api/frames", **_fits_upload(frames, times, sequence_id="api-pass"))
    assert r.status_code == 201, r.text
    doc = r.json()
    assert doc["created"] and doc["sequence"]["sequence_id"] == "api-pass" and doc["sequence"]["n_snapshots"] == 4
    again = api.post("/api/frames", **_fits_upload(frames, times, sequence_id="api-pass"))
    assert again.status_code == 200 and again.json()["id"] == doc["id"]
    detail = api.get(f"/api/sequences/{doc['id']}").json()
    block = detail["telemetry"]["frames"]
    assert block["format"] == "tubsat-frames/1" and len(block["content_sha256"]) == 64
    assert block["frames"][0]["file"] == "pass.fits" and block["detector"].startswith("sep ")
    search = api.post(f"/api/sequences/{doc['id']}/search", json={"method": "bright_pair"})
    assert search.status_code == 200, search.text
    result = search.json()
    assert result["status"] == "identified"
    R = np.asarray(truth["rotation_matrices"][detail["extraction"]["reference_snapshot"]])
    best = np.asarray(result["candidates"][0]["rotation_matrix"])
    assert np.degrees(angle_between(best[2], R[2])) < 0.1
    hot = api.get("/api/frames/hot-pixels", params={"spacecraft": "API-SAT", "sensor": "752x582"})
    assert hot.status_code == 200
    truth_hot = {(s["x"], s["y"]) for s in truth["frame_sources"][0] if s["kind"] == "hot_pixel"}
    assert {tuple(p) for p in hot.json()["hot_pixels"]} == {(int(x), int(y)) for x, y in truth_hot}
    assert [v["version"] for v in hot.json()["history"]] == [1]


def test_a_pass_can_ask_to_be_searched_right_away(tmp_path, sky, rendered):
    """As ``POST /api/sequences?search=true``: the new pass is searched after the answer (the console's
    "search new uploads automatically"); the same frames again are not searched twice."""
    frames, times, _ = rendered
    ctx = AppContext(storage=Storage.open(tmp_path / "auto.sqlite3"), sky=sky)
    try:
        client = TestClient(create_app(ctx))
        upload = _fits_upload(frames, times, sequence_id="auto-pass")
        r = client.post("/api/frames", params={"search": "true"}, **upload)  # TestClient runs the background task
        assert r.status_code == 201, r.text
        seq_id = r.json()["id"]
        detail = client.get(f"/api/sequences/{seq_id}").json()
        assert detail["status"] == "identified" and detail["search"]["method"] == "bright_pair"
        again = client.post("/api/frames", params={"search": "true"}, **upload)
        assert again.status_code == 200 and again.json()["id"] == seq_id
        assert client.get(f"/api/sequences/{seq_id}").json()["search"]["search_id"] == detail["search"]["search_id"]
        plain = client.post("/api/frames", **_fits_upload(frames[:3], times[:3], sequence_id="plain-pass"))
        assert plain.status_code == 201 and client.get(f"/api/sequences/{plain.json()['id']}").json()["search"] is None
        # The same frames again, asking for the search: stored (200) but never searched, so searched now.
        late = client.post("/api/frames", params={"search": "true"},
                           **_fits_upload(frames[:3], times[:3], sequence_id="plain-pass"))
        assert late.status_code == 200 and late.json()["id"] == plain.json()["id"]
        assert client.get(f"/api/sequences/{plain.json()['id']}").json()["search"]["method"] == "bright_pair"
    finally:
        ctx.close()


def test_a_png_set_with_its_sidecar_is_one_sequence(api, rendered):
    frames, times, _ = rendered
    names = [f"f{i}.png" for i in range(4)]
    sidecar = json.dumps(frames_sidecar(names, times, CAMERA, sequence_id="png-pass", spacecraft="API-SAT"))
    files = [("files", (n, frame_png_bytes(f), "image/png")) for n, f in zip(names, frames)]
    files.append(("sidecar", ("frames.json", sidecar.encode(), "application/json")))
    r = api.post("/api/frames", files=files)
    assert r.status_code == 201, r.text
    assert r.json()["sequence"]["sequence_id"] == "png-pass"
    history = api.get("/api/frames/hot-pixels", params={"spacecraft": "API-SAT", "sensor": "752x582"}).json()
    assert [v["version"] for v in history["history"]] == [1, 2] and history["frames"] == 8


def _cube() -> bytes:
    stream = io.BytesIO()
    fits.PrimaryHDU(np.zeros((2, 32, 32), np.int16)).writeto(stream)
    return stream.getvalue()


# An image that cannot be read is said to be one ("invalid image: ..."), not invalid telemetry: the user sent none.
@pytest.mark.parametrize("files, data, location, said", [
    ([("files", ("x.png", b"no image here", "image/png"))], {"fov_deg": "20"}, "x.png",
     "invalid image: x.png: not a readable image"),
    ([("files", ("cube.fits", _cube(), "application/fits"))], {"fov_deg": "20"}, "cube.fits[0]",
     "invalid image: cube.fits[0]: 3-D image"),
    ([("files", ("t.png", frame_png_bytes(np.zeros((64, 64), np.uint16)), "image/png"))],
     {"fov_deg": "20", "time": "yesterday"}, "body.time",
     "time: not an ISO 8601 time"),
    ([("files", ("t.png", frame_png_bytes(np.zeros((64, 64), np.uint16)), "image/png")),
      ("sidecar", ("s.json", b"{not json", "application/json"))], {}, "sidecar",
     "invalid image: sidecar: not valid JSON"),
    ([("files", ("t.png", frame_png_bytes(np.zeros((64, 64), np.uint16)), "image/png")),
      ("sidecar", ("s.json", b"", "application/json"))], {}, "sidecar",
     "invalid image: sidecar: the file is empty"),
    ([("files", ("t.png", frame_png_bytes(np.zeros((64, 64), np.uint16)), "image/png"))], {"fov_deg": "abc"},
     "body.fov_deg", "fov_deg must be a number"),
    ([("sidecar", ("s.json", b"{}", "application/json"))], {}, "body.files", "no frames"),
    ([("files", ("t.png", frame_png_bytes(np.zeros((64, 64), np.uint16)), "image/png"))],
     {"fov_deg": "20", "spacecraft": "sat\x00one"}, "body.spacecraft",
     "spacecraft contains control characters"),
])
def test_bad_uploads_give_located_422s(api, files, data, location, said):
    r = api.post("/api/frames", files=files, data=data)
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["detail"] and any(p["location"] == location for p in body["problems"]), body
    assert body["detail"].startswith(said), body["detail"]


def test_no_optics_is_stored_with_the_field_of_view_unknown_and_not_multipart_is_refused(api, rendered):
    frames, times, _ = rendered
    png = frame_png_bytes(frames[0])
    sidecar = json.dumps({"frames": [{"file": "a.png", "time": "2024-01-01T00:00:00Z"}]}).encode()
    r = api.post("/api/frames", files=[("files", ("a.png", png, "image/png")), ("sidecar", ("s.json", sidecar))])
    assert r.status_code == 201  # issue 26: the identification searches the field of view
    stored = api.get(f"/api/sequences/{r.json()['id']}").json()
    assert stored["camera"]["focal_length_unknown"] is True, stored["camera"]
    r = api.post("/api/frames", content=png, headers={"Content-Type": "image/png"})
    assert r.status_code == 415


def test_work_is_bounded_in_pixels_and_time(api, rendered, monkeypatch):
    frames, times, _ = rendered
    monkeypatch.setenv("STARID_FRAMES_MAX_DECODED_PIXELS", "100000")  # over the detection budget: binned
    r = api.post("/api/frames", **_fits_upload(frames, times, sequence_id="too-big"))
    assert r.status_code == 422 and r.json()["problems"][0]["location"] == "pass.fits[1]"
    assert "at most 100000" in r.json()["problems"][0]["message"]
    monkeypatch.delenv("STARID_FRAMES_MAX_DECODED_PIXELS")
    monkeypatch.setenv("STARID_FRAMES_TIMEOUT_S", "0")
    r = api.post("/api/frames", **_fits_upload(frames, times, sequence_id="too-slow"))
    assert r.status_code == 503 and ("longer than 0 s" in r.json()["detail"] or "time-out" in r.json()["detail"])
