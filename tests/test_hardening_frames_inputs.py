"""Hostile-input trial of the frames path (issue 15): what it found, each answered where the user can fix it.

1. a sidecar naming a built-in camera of another size than the frames (its optics are in its own
   pixels: stored with the wrong geometry, or refused at detected blobs instead of the sidecar);
2. a frames body between the drain limit (64 MiB) and the frames' own limit (128 MiB) refused 413
   with a message stating the frames' limit, which the body was below;
3. a 32-bit float TIFF frame refused with an internal message (a read-only pixel buffer);
4. ``GET /api/sequences/{id}/frames`` of a spot list: an empty list, as the route documents.

The frames are drawn here (a few Gaussian stars on a noisy sky), not rendered from the catalogue:
what is checked is how they are read and where problems are located, not identification.
"""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image

from app.api import create_app
from app.api.routes import common
from app.api.routes.frames import MULTIPART_OVERHEAD
from app.frames.detect import detect
from app.frames.images import read_frames
from app.storage import Storage
from app.workflow import AppContext

TIME = "2024-03-12T21:04:10.000Z"
#: (x, y) of the stars drawn into the test frames; inside the smallest frame used (400 x 400).
STARS = [(60.0, 80.0), (210.3, 150.6), (330.0, 300.2), (120.5, 350.0)]


@pytest.fixture
def api(tmp_path, sky):
    ctx = AppContext(storage=Storage.open(tmp_path / "frames-inputs.sqlite3"), sky=sky)
    yield TestClient(create_app(ctx))
    ctx.close()


def _sky(width: int, height: int, seed: int = 7) -> np.ndarray:
    """A float frame: sky 200 +- 10 and the :data:`STARS` (Gaussian, sigma 1.2 px, peak ~3000 above the sky)."""
    rng = np.random.default_rng(seed)
    frame = rng.normal(200.0, 10.0, (height, width))
    rows, cols = np.mgrid[0:height, 0:width]
    for x, y in STARS:
        frame += 3000.0 * np.exp(-((cols - x) ** 2 + (rows - y) ** 2) / (2 * 1.2 ** 2))
    return frame


def _png(frame: np.ndarray) -> bytes:
    stream = io.BytesIO()
    Image.fromarray(np.clip(frame, 0, 65535).astype(np.uint16)).save(stream, format="PNG")
    return stream.getvalue()


def _float_tiff(frame: np.ndarray) -> bytes:
    """A 32-bit float greyscale TIFF (SampleFormat 3), as Pillow writes mode ``F``."""
    stream = io.BytesIO()
    Image.fromarray(frame.astype(np.float32), mode="F").save(stream, format="TIFF")
    return stream.getvalue()


def _post(client, name: str, data: bytes, camera, media_type: str = "image/png"):
    sidecar = {"format": "tubsat-frames/1", "camera": camera, "frames": [{"file": name, "time": TIME}]}
    return client.post("/api/frames", files=[("files", (name, data, media_type)),
                                             ("sidecar", ("frames.json", json.dumps(sidecar), "application/json"))])


def _stored(client) -> int:
    return client.get("/api/sequences").json()["total"]


# ---------------------------------------------------------------------------
# 1. A named camera is checked against the frames' size, like a camera object
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("name, size", [("narrow-1024x1024-12deg", "1024 x 1024"),
                                        ("tubsat-752x582-20deg", "752 x 582")])
def test_a_named_camera_of_another_size_is_refused_at_the_sidecar(api, name, size):
    """Was: the 1024 x 1024 camera stored for 1000 x 1000 frames (201, wrong geometry), and the 752 x 582 one
    refused at detected blobs (``snapshots[0].sources[1].x``), which the user never wrote."""
    r = _post(api, "a.png", _png(_sky(1000, 1000)), name)
    assert r.status_code == 422, r.text
    assert r.json()["problems"] == [{"location": "sidecar.camera",
                                     "message": f"{name} is {size}, but the frames are 1000 x 1000"}]
    assert _stored(api) == 0


def test_a_named_camera_of_the_frames_size_is_used(api):
    r = _post(api, "a.png", _png(_sky(752, 582)), "tubsat-752x582-20deg")
    assert r.status_code == 201, r.text
    assert r.json()["sequence"]["camera"]["name"] == "tubsat-752x582-20deg"


def test_an_unknown_camera_name_is_still_located_at_the_sidecar(api):
    r = _post(api, "a.png", _png(_sky(752, 582)), "no-such-camera")
    assert r.status_code == 422, r.text
    [problem] = r.json()["problems"]
    assert problem["location"] == "sidecar.camera" and "unknown camera 'no-such-camera'" in problem["message"]


# ---------------------------------------------------------------------------
# 2. The frames' own size limit is what counts (and what the 413 states)
# ---------------------------------------------------------------------------

@pytest.fixture
def small_limits(monkeypatch):
    """The real limits scaled down 1024 times: drain limit 64 KiB, frames limit 128 KiB (bytes of files)."""
    monkeypatch.setattr(common, "DRAIN_LIMIT_BYTES", 64 * 1024)
    monkeypatch.setenv("STARID_FRAMES_MAX_BYTES", str(128 * 1024))
    return 128 * 1024


def test_a_frames_body_above_the_drain_limit_and_within_its_own_limit_is_read(api, small_limits):
    """Was: refused 413 "larger than the limit of 134217728 bytes" for bodies of 64 to 128 MiB."""
    frame = _png(_sky(300, 300))  # noise hardly compresses: ~86 kB
    assert common.DRAIN_LIMIT_BYTES < len(frame) < small_limits, len(frame)
    r = _post(api, "a.png", frame, {"width": 300, "height": 300, "focal_length_px": 850.0,
                                    "cx": 149.5, "cy": 149.5})
    assert r.status_code == 201, r.text


def test_a_frames_body_above_its_own_limit_is_413_stating_that_limit_and_its_setting(api, small_limits):
    """Beyond the frames' limit and the room kept for multipart framing: 413 naming the limit and its setting
    (a body within the framing room reaches the files' own check: 422 at ``files``)."""
    oversized = b"\0" * (small_limits + MULTIPART_OVERHEAD + 1)
    r = api.post("/api/frames", files=[("files", ("a.png", oversized, "image/png"))])
    assert r.status_code == 413, r.text
    detail = r.json()["detail"]
    assert f"the limit of {small_limits} bytes" in detail and "STARID_FRAMES_MAX_BYTES" in detail


def test_a_70_mb_frames_upload_is_not_refused_for_its_size(api):
    """The trial's case at full size, with the real limits: 70 MB of a file that is no image is read (the
    answer is about the file, located at it), not refused as larger than 128 MiB."""
    assert common.DRAIN_LIMIT_BYTES < 70_000_000 < 128 * 1024 * 1024
    r = api.post("/api/frames", files=[("files", ("big.png", b"\0" * 70_000_000, "image/png"))])
    assert r.status_code == 422, r.text[:300]
    assert r.json()["problems"][0]["location"] == "big.png"


# ---------------------------------------------------------------------------
# 3. 32-bit float TIFF frames are read
# ---------------------------------------------------------------------------

def test_a_float_tiff_frame_is_read_into_writable_float_pixels():
    frame = _sky(400, 400)
    [read] = list(read_frames(_float_tiff(frame), "a.tif"))
    assert read.bits == -32 and read.saturation is None
    assert read.pixels.dtype == np.float32 and read.pixels.flags.writeable
    assert np.array_equal(read.pixels, frame.astype(np.float32))


def test_detection_accepts_read_only_pixels():
    """A read-only array (a view of an image's buffer, ``np.frombuffer``) is the caller's to keep: detection
    works on it without writing into it."""
    pixels = _sky(400, 400).astype(np.float32)
    pixels.setflags(write=False)
    found = detect(pixels)
    assert len(found) >= len(STARS)


def test_a_float_tiff_frame_is_stored_with_its_stars(api):
    """Was: 422 "the background cannot be estimated (buffer source array is read-only)"."""
    r = _post(api, "a.tif", _float_tiff(_sky(752, 582)), "tubsat-752x582-20deg", media_type="image/tiff")
    assert r.status_code == 201, r.text
    detail = api.get(f"/api/sequences/{r.json()['id']}").json()["telemetry"]
    assert detail["frames"]["frames"][0]["bits"] == -32
    found = [(s["x"], s["y"]) for s in detail["snapshots"][0]["sources"]]
    for x, y in STARS:
        assert min(np.hypot(fx - x, fy - y) for fx, fy in found) < 0.2, (x, y, found)


# ---------------------------------------------------------------------------
# 4. The frames of a spot list: an empty list, as documented by the route
# ---------------------------------------------------------------------------

def test_the_frames_of_a_spot_list_are_an_empty_list_and_its_images_404(api, sample_dir):
    """The route (and FramePreviewsDocument) document an empty list for spot lists, and the console asks only
    for sequences uploaded as frames; only the image of a snapshot is 404, saying why."""
    up = api.post("/api/sequences", content=(sample_dir / "01-clean.json").read_bytes(),
                  headers={"Content-Type": "application/json"})
    assert up.status_code == 201, up.text
    seq_id = up.json()["id"]
    listed = api.get(f"/api/sequences/{seq_id}/frames")
    assert listed.status_code == 200 and listed.json()["frames"] == []
    image = api.get(f"/api/sequences/{seq_id}/frames/0.png")
    assert image.status_code == 404 and "spot list" in image.json()["detail"]
    summary = api.get("/openapi.json").json()["paths"]["/api/sequences/{seq_id}/frames"]["get"]["summary"]
    assert "an empty list for spot lists" in summary


# ---------------------------------------------------------------------------
# 5. A sidecar's time says why it is none, as the telemetry's does (app.timefmt)
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("time, said", [
    ("2016-12-31T23:59:60Z", "2016-12-31T23:59:60 is a leap second, which is not supported"),
    ("2020-02-30T00:00:00Z", "the date 2020-02-30 does not exist (February 2020 has 29 days)"),
    ("yesterday", "not an ISO 8601 time such as 1994-03-12T21:04:10.000Z: 'yesterday'")])
def test_a_sidecar_time_that_is_none_says_why(api, time, said):
    sidecar = {"format": "tubsat-frames/1", "camera": "tubsat-752x582-20deg",
               "frames": [{"file": "a.png", "time": time}]}
    r = api.post("/api/frames", files=[("files", ("a.png", _png(_sky(752, 582)), "image/png")),
                                       ("sidecar", ("frames.json", json.dumps(sidecar), "application/json"))])
    assert r.status_code == 422, r.text
    [problem] = r.json()["problems"]
    assert problem["location"] == "sidecar.frames[0].time" and problem["message"].startswith(said), problem


def test_a_sensor_size_is_written_in_ascii_digits(api):
    """The hot-pixel map's ``sensor`` (``752x582``): its pattern's ``\\d`` took the digits of any script."""
    r = api.get("/api/frames/hot-pixels", params={"spacecraft": "SAT", "sensor": "٧٥٢x٥٨٢"})
    assert r.status_code == 422 and r.json()["problems"][0]["location"] == "query.sensor", r.text
    assert api.get("/api/frames/hot-pixels", params={"spacecraft": "SAT", "sensor": "752x582"}).status_code != 422
