"""Frame previews (issue 15 item 5): kept at upload, append-only on both backends, served with their overlay.

The overlay's positions are checked against the stored sources and against the image itself: the
light of each bright star in the PNG, mapped back through the stated scale, lies within
0.5 px x scale of the detection.
"""

from __future__ import annotations

import io
import sqlite3

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image

from app.api import create_app
from app.camera import CAMERAS, Camera
from app.simulate import frames_fits_bytes, simulate_frames
from app.storage import MAX_PREVIEW_PNG_BYTES, Storage, UnknownSequence
from app.workflow import AppContext
from app.workflow import frames as framing
from app.workflow.frames import (PREVIEW_MAX_WIDTH, block_mean, encode_png, preview_scale, render_preview,
                                 stretch_to_8bit)

CAMERA = CAMERAS["tubsat-752x582-20deg"]
#: A 2 Mpx camera: previews at scale 2 (816 x 612).
WIDE = Camera(width=1632, height=1224, focal_length_px=round(816 / np.tan(np.radians(10.0)), 1), cx=815.5, cy=611.5,
              name="wide-1632x1224-20deg", mag_limit=5.5)


def png_bytes(width: int, height: int, value: int = 40) -> bytes:
    stream = io.BytesIO()
    Image.fromarray(np.full((height, width), value, dtype=np.uint8), mode="L").save(stream, format="PNG")
    return stream.getvalue()


def preview(snapshot: int, *, width: int = 752, height: int = 582, scale: int = 1, png: bytes | None = None,
            overlay: dict | None = None) -> dict:
    iw, ih = -(-width // scale), -(-height // scale)
    return {"snapshot": snapshot, "width": width, "height": height, "scale": scale, "image_width": iw,
            "image_height": ih, "png": png if png is not None else png_bytes(iw, ih, 10 + snapshot),
            "overlay": overlay if overlay is not None else
            {"detections": [{"source": 0, "x": 1.25, "y": 2.5, "brightness": 100.0, "flags": []}],
             "rejected": [{"x": 5.0, "y": 6.0, "reason": "elongated"}], "rejected_total": 1,
             "hot_pixels": [[3, 4]], "hot_pixels_total": 1}}


def raw_write_refused(url: str, sql: str) -> bool:
    """True when the database itself refuses ``sql`` (the append-only triggers)."""
    if url.startswith("postgresql"):
        import psycopg

        with psycopg.connect(url, autocommit=True) as conn:
            try:
                conn.execute(sql)
            except psycopg.Error as exc:
                return "append-only" in str(exc)
        return False
    conn = sqlite3.connect(url)
    try:
        conn.execute(sql)
        conn.commit()
    except sqlite3.DatabaseError as exc:
        return "append-only" in str(exc)
    finally:
        conn.close()
    return False


# ---------------------------------------------------------------------------
# Storage, on both backends
# ---------------------------------------------------------------------------

def test_previews_round_trip_and_are_append_only(archive_url):
    with Storage.open(archive_url) as store:
        row, _ = store.add_sequence(raw_text='{"format": "tubsat-snapshots/1"}', n_snapshots=3)
        assert store.frame_previews(row.id) == [] and store.frame_preview(row.id, 0) is None
        first = [preview(1), preview(0, overlay={"detections": [], "rejected": [], "hot_pixels": []})]
        assert store.add_frame_previews(row.id, first) == 2
        listed = store.frame_previews(row.id)
        assert [p.snapshot for p in listed] == [0, 1] and all(p.png is None for p in listed)
        assert listed[1].overlay == first[0]["overlay"] and listed[1].created_at.tzinfo is not None
        assert (listed[1].width, listed[1].height, listed[1].scale, listed[1].image_width) == (752, 582, 1, 752)
        one = store.frame_preview(row.id, 1)
        assert one.png == first[0]["png"] and Image.open(io.BytesIO(one.png)).size == (752, 582)
        # The first preview of a snapshot stays; another is not stored, the new snapshot is.
        assert store.add_frame_previews(row.id, [preview(1, png=png_bytes(752, 582, 200)), preview(2)]) == 1
        assert store.frame_preview(row.id, 1).png == first[0]["png"]
        assert [p.snapshot for p in store.frame_previews(row.id)] == [0, 1, 2]
        with pytest.raises(UnknownSequence):
            store.add_frame_previews(row.id + 100, [preview(0)])
    target = archive_url
    assert raw_write_refused(target, "UPDATE frame_previews SET scale = 2")
    assert raw_write_refused(target, "DELETE FROM frame_previews")
    if target.startswith("postgresql"):
        assert raw_write_refused(target, "TRUNCATE frame_previews")


def test_previews_that_are_not_previews_are_refused_whole(archive_url):
    with Storage.open(archive_url) as store:
        row, _ = store.add_sequence(raw_text='{"format": "tubsat-snapshots/1", "id": 2}', n_snapshots=2)
        too_big = b"\x89PNG\r\n\x1a\n" + bytes(MAX_PREVIEW_PNG_BYTES)
        for bad in (preview(1, png=b"GIF89a..."), preview(1, png=too_big), preview(1, scale=2, png=png_bytes(10, 10)) |
                    {"image_width": 10}, preview(-1), {"snapshot": 1}):
            with pytest.raises(ValueError):
                store.add_frame_previews(row.id, [preview(0), bad])
        with pytest.raises(ValueError, match="same snapshot"):
            store.add_frame_previews(row.id, [preview(0), preview(0)])
        assert store.frame_previews(row.id) == []  # one transaction: nothing of a refused set is kept


# ---------------------------------------------------------------------------
# Rendering
# ---------------------------------------------------------------------------

def test_the_scale_brings_any_frame_to_1024_pixels_or_less():
    assert [preview_scale(w) for w in (1, 752, 1024, 1025, 1632, 2048, 2049, 4096)] == [1, 1, 1, 2, 2, 2, 3, 4]
    for width in (5, 1023, 1025, 3000, 4097):
        assert -(-width // preview_scale(width)) <= PREVIEW_MAX_WIDTH
    pixels = np.arange(7 * 5, dtype=float).reshape(5, 7)
    means = block_mean(pixels, 2)
    assert means.shape == (3, 4)
    assert means[0, 0] == pixels[:2, :2].mean() and means[2, 3] == pixels[4, 6]  # cut blocks: the pixels inside
    assert means[1, 3] == pixels[2:4, 6].mean()


def test_a_preview_larger_than_the_limit_is_made_again_at_twice_the_scale(monkeypatch):
    noise = np.random.default_rng(5).lognormal(0.0, 2.5, (600, 1000)).astype(np.float32)
    full = len(encode_png(stretch_to_8bit(noise)))
    monkeypatch.setattr(framing, "MAX_PREVIEW_PNG_BYTES", full - 1)  # the full-size PNG is one byte too many
    made = render_preview(noise, 0, {"detections": []})
    assert made.scale == 2 and (made.image_width, made.image_height) == (500, 300)
    assert len(made.png) < full
    assert Image.open(io.BytesIO(made.png)).size == (500, 300)
    monkeypatch.setattr(framing, "MAX_PREVIEW_PNG_BYTES", 10)  # nothing fits: no preview rather than a huge one
    assert render_preview(noise, 0, {"detections": []}) is None


# ---------------------------------------------------------------------------
# The API
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def api(tmp_path_factory, sky):
    ctx = AppContext(storage=Storage.open(tmp_path_factory.mktemp("previews") / "api.sqlite3"), sky=sky)
    yield TestClient(create_app(ctx))
    ctx.close()


def _upload(api, camera: Camera, seed: int, n_frames: int, sequence_id: str) -> tuple[dict, dict]:
    frames, times, truth = simulate_frames(np.random.default_rng(seed), camera, n_frames=n_frames, trail=True)
    data = frames_fits_bytes(frames, times, camera=camera, spacecraft=f"PREVIEW-{camera.width}")
    r = api.post("/api/frames", files=[("files", ("pass.fits", data, "application/fits"))],
                 data={"sequence_id": sequence_id})
    assert r.status_code == 201, r.text
    return r.json(), truth


def _light_near(image: np.ndarray, u: float, v: float, half: int = 3) -> tuple[float, float] | None:
    """Centroid (image pixels) of the light above the local median in a (2 half + 1)^2 box around (u, v)."""
    iu, iv = int(round(u)), int(round(v))
    h, w = image.shape
    if not (half <= iu < w - half and half <= iv < h - half):
        return None
    box = image[iv - half: iv + half + 1, iu - half: iu + half + 1].astype(float)
    light = np.clip(box - np.median(box), 0, None)
    light[light < 0.5 * light.max()] = 0.0  # the core: a neighbour's wing or the noise do not pull it
    if light.sum() <= 0:
        return None
    jj, ii = np.mgrid[-half: half + 1, -half: half + 1]
    return iu + float((light * ii).sum() / light.sum()), iv + float((light * jj).sum() / light.sum())


@pytest.mark.parametrize("camera,seed", [(CAMERA, 71), (WIDE, 72)], ids=["752px-scale1", "1632px-scale2"])
def test_the_frames_are_listed_with_their_overlay_and_the_images_agree_with_it(api, camera, seed):
    doc, truth = _upload(api, camera, seed, 3, f"previews-{camera.width}")
    seq_id = doc["id"]
    detail = api.get(f"/api/sequences/{seq_id}").json()
    listed = api.get(f"/api/sequences/{seq_id}/frames")
    assert listed.status_code == 200
    body = listed.json()
    assert body["sequence"] == seq_id and body["max_png_bytes"] == MAX_PREVIEW_PNG_BYTES
    frames = body["frames"]
    assert [f["snapshot"] for f in frames] == [0, 1, 2]
    scale = -(-camera.width // PREVIEW_MAX_WIDTH)
    reasons = set()
    checked = 0
    for f, snapshot in zip(frames, detail["telemetry"]["snapshots"]):
        assert (f["width"], f["height"], f["scale"]) == (camera.width, camera.height, scale)
        assert f["url"] == f"/api/sequences/{seq_id}/frames/{f['snapshot']}.png"
        r = api.get(f["url"])
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        assert len(r.content) <= MAX_PREVIEW_PNG_BYTES
        image = Image.open(io.BytesIO(r.content))
        assert image.mode == "L" and image.size == (f["image_width"], f["image_height"])
        assert image.size == (-(-camera.width // scale), -(-camera.height // scale))
        pixels = np.asarray(image)
        # Every source of the snapshot is a detection of the overlay, at its position.
        overlay = f["overlay"]
        sources = snapshot["sources"]
        assert [d["source"] for d in overlay["detections"]] == list(range(len(sources)))
        for d, s in zip(overlay["detections"], sources):
            assert abs(d["x"] - s["x"]) < 1e-3 and abs(d["y"] - s["y"]) < 1e-3
        # ... and where the image shows its light: the brightest unsaturated sources, mapped through the scale.
        bright = sorted((d for d in overlay["detections"] if not d["flags"]), key=lambda d: -d["brightness"])[:4]
        for d in bright:
            u, v = (d["x"] + 0.5) / scale - 0.5, (d["y"] + 0.5) / scale - 0.5
            found = _light_near(pixels, u, v)
            if found is None:
                continue
            x_img, y_img = (found[0] + 0.5) * scale - 0.5, (found[1] + 0.5) * scale - 0.5
            assert abs(x_img - d["x"]) <= 0.5 * scale and abs(y_img - d["y"]) <= 0.5 * scale, (d, x_img, y_img)
            checked += 1
        reasons |= {b["reason"] for b in overlay["rejected"]}
        assert overlay["rejected_total"] >= len(overlay["rejected"])
        assert overlay["hot_pixels_total"] == len(overlay["hot_pixels"])
    assert checked >= 6
    assert any("elongated" in reason for reason in reasons)  # the satellite trail
    assert any("hot_pixel" in reason for reason in reasons)  # the camera's hot pixels, not yet mapped
    # The same frames again: the stored sequence, its previews once.
    _upload_again = api.get(f"/api/sequences/{seq_id}/frames").json()
    assert len(_upload_again["frames"]) == 3


def test_hot_pixels_of_the_map_are_in_the_overlay(api):
    """A camera whose map knows its hot pixels (3 passes of 3 frames): the fourth pass lists them."""
    for k in range(3):
        _upload(api, CAMERA, 300 + k, 3, f"hot-{k}")
    doc, truth = _upload(api, CAMERA, 310, 3, "hot-after")
    overlay = api.get(f"/api/sequences/{doc['id']}/frames").json()["frames"][0]["overlay"]
    hot_truth = {(int(s["x"]), int(s["y"])) for s in truth["frame_sources"][0] if s["kind"] == "hot_pixel"}
    assert hot_truth and hot_truth <= {tuple(p) for p in overlay["hot_pixels"]}


def test_sequences_without_frames_say_so(api, sample_dir):
    text = (sample_dir / "01-clean.json").read_bytes()
    up = api.post("/api/sequences", content=text, headers={"Content-Type": "application/json"})
    assert up.status_code in (200, 201), up.text
    seq_id = up.json()["id"]
    assert api.get(f"/api/sequences/{seq_id}/frames").json()["frames"] == []
    missing = api.get(f"/api/sequences/{seq_id}/frames/0.png")
    assert missing.status_code == 404 and "spot list" in missing.json()["detail"]
    assert api.get("/api/sequences/999999/frames").status_code == 404
    assert api.get("/api/sequences/999999/frames/0.png").status_code == 404
    assert api.get(f"/api/sequences/{seq_id}/frames/-1.png").status_code == 422
    assert api.get(f"/api/sequences/{seq_id}/frames/x.png").status_code == 422


def test_a_snapshot_without_a_preview_is_a_404_naming_the_range(api):
    doc, _ = _upload(api, CAMERA, 81, 2, "two-frames")
    r = api.get(f"/api/sequences/{doc['id']}/frames/5.png")
    assert r.status_code == 404 and "snapshots 0 to 1" in r.json()["detail"]
