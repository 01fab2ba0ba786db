"""A camera's hot-pixel map applied to spot-list uploads of the same spacecraft and sensor size (issue 15).

Sources on a mapped hot pixel get extraction's ``hot_pixel`` verdict in place: they are never
tracks or pattern points, every other source keeps its place in the file's numbering, the stored
extraction records the map's version, and a reload reads that extraction back unchanged.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.api import create_app
from app.attitude import angle_between
from app.camera import CAMERAS
from app.extraction import HOT_PIXEL, extract
from app.frames import HotPixelMap
from app.simulate import simulate_sequence
from app.storage import Storage
from app.workflow import AppContext, archive

CAMERA = CAMERAS["tubsat-752x582-20deg"]
OTHER_SIZE = CAMERAS["liebe-576x604-30deg"]
SPACECRAFT = "HOT-S"
HOT = (200, 150)  # a mapped hot pixel
INSERT_AT = 3  # where the hot pixel's source goes in each snapshot's list (file order)


@pytest.fixture
def api(tmp_path, sky):
    ctx = AppContext(storage=Storage.open(tmp_path / "hot.sqlite3"), sky=sky)
    yield TestClient(create_app(ctx)), ctx
    ctx.close()


def _store_map(ctx, spacecraft=SPACECRAFT, sensor=CAMERA, pixels=(HOT, (600, 400))) -> int:
    """A map in which ``pixels`` are hot (seen in 5 of 5 frames), stored as the frames route stores it."""
    hot_map = HotPixelMap.empty(sensor.width, sensor.height).with_frames([list(pixels)] * 5)
    assert set(pixels) <= set(hot_map.hot)
    row = ctx.storage.add_hot_pixel_map(spacecraft, hot_map.sensor, map_doc=hot_map.to_json(), frames=hot_map.frames,
                                        hot_pixels=len(hot_map.hot), based_on=None)
    return row.version


def _with_hot_source(sequence, snapshots, spacecraft=SPACECRAFT, xy=HOT, brightness=230.0):
    """The sequence with a bright source at ``xy`` inserted at :data:`INSERT_AT` of the given snapshots."""
    out = []
    for i, snap in enumerate(sequence.snapshots):
        if i in snapshots:
            k = min(INSERT_AT, snap.n_sources)
            snap = dataclasses.replace(snap, xy=np.insert(np.asarray(snap.xy, float), k, xy, axis=0),
                                       brightness=np.insert(np.asarray(snap.brightness, float), k, brightness))
        out.append(snap)
    return dataclasses.replace(sequence, spacecraft=spacecraft, snapshots=tuple(out))


def _upload(client, sequence) -> dict:
    r = client.post("/api/sequences", files={"file": (f"{sequence.sequence_id}.json",
                                                      json.dumps(sequence.to_json_dict()).encode())})
    assert r.status_code == 201, r.text
    return r.json()


def _near(points, xy, tol=1.5) -> bool:
    return any(p["x"] is not None and abs(p["x"] - xy[0]) <= tol and abs(p["y"] - xy[1]) <= tol for p in points)


def _attitude_error_deg(client, seq_id, truth, reference) -> float:
    result = client.post(f"/api/sequences/{seq_id}/search", json={"method": "bright_pair"}).json()
    assert result["status"] == "identified", result
    R = np.asarray(truth["rotation_matrices"][reference])
    return float(np.degrees(angle_between(np.asarray(result["candidates"][0]["rotation_matrix"])[2], R[2])))


@pytest.fixture(scope="module")
def single():
    """One snapshot (nothing to track against: extraction alone takes every source as a star)."""
    sequence, truth = simulate_sequence(np.random.default_rng([15, 1]), CAMERA, "single")
    assert sequence.snapshots[0].n_sources > INSERT_AT + 4
    return sequence, truth


def test_a_source_on_a_mapped_hot_pixel_of_a_single_snapshot_is_hot_and_the_rest_keep_their_places(api, single):
    client, ctx = api
    version = _store_map(ctx)
    sequence, truth = single
    uploaded = _with_hot_source(sequence, {0})
    n = uploaded.snapshots[0].n_sources

    # Without the map (another spacecraft) extraction alone makes it a pattern point: what the map is for.
    alone = _upload(client, _with_hot_source(sequence, {0}, spacecraft="NO-MAP"))
    assert alone["extraction"]["rejected"][0][INSERT_AT] is None and _near(alone["pattern"]["points"], HOT)
    assert alone["extraction"]["hot_pixel_map"] is None

    doc = _upload(client, uploaded)
    extraction = doc["extraction"]
    assert extraction["hot_pixel_map"] == version
    assert len(extraction["sources"][0]) == n  # nothing removed: the file's numbering stands
    assert extraction["rejected"][0] == [HOT_PIXEL if k == INSERT_AT else None for k in range(n)]
    assert extraction["sources"][0][INSERT_AT] is None
    assert not _near(doc["pattern"]["points"], HOT) and not _near(extraction["pattern"], HOT)
    assert len(doc["pattern"]["points"]) == n - 1
    # every other source is its own track, at its own place in the file
    xy = uploaded.snapshots[0].xy
    tracks = {t["id"]: t for t in extraction["tracks"]}
    for k, track_id in enumerate(extraction["sources"][0]):
        if k != INSERT_AT:
            np.testing.assert_allclose(tracks[track_id]["xy"][0], xy[k], atol=1e-3)
    assert [t for t in extraction["sources"][0] if t is not None] == list(range(n - 1))  # in file order

    assert _attitude_error_deg(client, doc["id"], truth, 0) < 0.1


def test_a_hot_pixel_that_a_slow_sky_passes_for_a_star_is_marked_hot_by_the_map(api):
    """Two snapshots, the sky hardly moving: a source on the same pixel in both is kept as a track by
    extraction alone; the map makes it hot, and the other sources keep their verdicts."""
    client, ctx = api
    version = _store_map(ctx)
    sequence, _ = simulate_sequence(np.random.default_rng([16, 0]), CAMERA, "sparse", n_snapshots=2)
    uploaded = _with_hot_source(sequence, {0, 1})
    places = [min(INSERT_AT, s.n_sources) for s in sequence.snapshots]
    plain = extract(uploaded)
    assert all(plain.track_of_source[i][k] >= 0 for i, k in enumerate(places))  # taken for a star

    doc = _upload(client, uploaded)
    extraction = doc["extraction"]
    assert extraction["hot_pixel_map"] == version
    for i, k in enumerate(places):
        assert len(extraction["sources"][i]) == uploaded.snapshots[i].n_sources
        assert extraction["rejected"][i][k] == HOT_PIXEL and extraction["sources"][i][k] is None
        others = [r for j, r in enumerate(extraction["rejected"][i]) if j != k]
        assert others == [r for j, r in enumerate(plain.rejection[i]) if j != k]
    assert not _near(doc["pattern"]["points"], HOT)
    assert len(extraction["tracks"]) == len(plain.tracks) - 1


def test_a_moving_sequence_keeps_its_track_numbers(api):
    """In a moving sequence a hot pixel seen once is a ghost anyway: with the map it is hot, and every
    other source has exactly the track id it has without the map."""
    client, ctx = api
    _store_map(ctx)
    sequence, truth = simulate_sequence(np.random.default_rng([15, 2]), CAMERA, "clean", n_snapshots=6)
    uploaded = _with_hot_source(sequence, {2})
    plain = extract(uploaded)
    doc = _upload(client, uploaded)
    extraction = doc["extraction"]
    k = min(INSERT_AT, sequence.snapshots[2].n_sources)
    assert extraction["rejected"][2][k] == HOT_PIXEL and plain.rejection[2][k] == "ghost"
    assert extraction["sources"] == [[int(t) if t >= 0 else None for t in per] for per in plain.track_of_source]
    assert _attitude_error_deg(client, doc["id"], truth, extraction["reference_snapshot"]) < 0.1


def test_without_a_map_or_with_another_sensor_size_nothing_changes(api, single):
    client, ctx = api
    _store_map(ctx)
    sequence, _ = single
    for uploaded in (_with_hot_source(sequence, {0}, spacecraft="OTHER-SAT"),
                     _with_hot_source(dataclasses.replace(sequence, sequence_id="no-spacecraft"), {0},
                                      spacecraft=None)):
        doc = _upload(client, uploaded)
        assert doc["extraction"]["hot_pixel_map"] is None and HOT_PIXEL not in doc["extraction"]["rejected"][0]
    other, _ = simulate_sequence(np.random.default_rng([15, 3]), OTHER_SIZE, "single")
    doc = _upload(client, _with_hot_source(other, {0}))  # the same spacecraft, another camera
    assert doc["extraction"]["hot_pixel_map"] is None
    assert doc["extraction"]["rejected"][0][INSERT_AT] is None and _near(doc["pattern"]["points"], HOT)
    assert doc["extraction"] == json.loads(json.dumps(archive.ExtractionDocument.of(
        extract(archive.parse_upload(ctx, json.dumps(_with_hot_source(other, {0}).to_json_dict()).encode(),
                                     "x.json").sequence)).model_dump(mode="json")))


def test_a_reload_reads_the_stored_extraction_and_a_later_map_changes_nothing(api, single, monkeypatch):
    client, ctx = api
    version = _store_map(ctx)
    sequence, _ = single
    doc = _upload(client, _with_hot_source(sequence, {0}))
    stored = ctx.storage.get_sequence(doc["id"]).extraction
    before = archive.loaded(ctx, ctx.storage.get_sequence(doc["id"])).extraction
    # a newer map in which the pixel is no longer hot, and a restart: the stored extraction stands
    fresh = HotPixelMap.empty(CAMERA.width, CAMERA.height).with_frames([[(10, 10)]] * 5)
    ctx.storage.add_hot_pixel_map(SPACECRAFT, fresh.sensor, map_doc=fresh.to_json(), frames=fresh.frames,
                                  hot_pixels=1, based_on=version)
    ctx.cache = type(ctx.cache)()

    def no_extraction(*_args, **_kwargs):
        raise AssertionError("extraction ran again on a stored sequence")

    monkeypatch.setattr(archive, "extract", no_extraction)
    detail = client.get(f"/api/sequences/{doc['id']}").json()
    assert detail["extraction"] == stored and stored["hot_pixel_map"] == version
    after = archive.loaded(ctx, ctx.storage.get_sequence(doc["id"])).extraction
    assert after.rejection == before.rejection
    assert [t.tolist() for t in after.track_of_source] == [t.tolist() for t in before.track_of_source]
    np.testing.assert_array_equal(after.pattern.xy, before.pattern.xy)
    np.testing.assert_array_equal(after.pattern.track_ids, before.pattern.track_ids)
    assert client.post(f"/api/sequences/{doc['id']}/search").json()["status"] == "identified"


def test_an_extraction_made_with_the_known_hot_pixels_is_stored_as_it_is(api, single, monkeypatch):
    """The workflow's own path (parse_upload, extraction_job with known_hot, store_upload) extracts once;
    an extraction made without them is made again with them."""
    client, ctx = api
    version = _store_map(ctx)
    sequence, _ = single
    data = json.dumps(_with_hot_source(sequence, {0}).to_json_dict()).encode()
    upload = archive.parse_upload(ctx, data, "direct.json")
    assert upload.hot_pixel_map == version and upload.known_hot[0].tolist().count(True) == 1
    with_hot = archive.extraction_job(upload.sequence, upload.known_hot)
    assert archive.upload_extraction(upload, with_hot) is with_hot
    again = archive.upload_extraction(upload, archive.extraction_job(upload.sequence))
    assert again.rejection == with_hot.rejection
    calls = []
    monkeypatch.setattr(archive, "extract", lambda *a, **k: calls.append(1) or extract(*a, **k))
    doc = archive.store_upload(ctx, upload, with_hot)
    assert not calls and doc.extraction.hot_pixel_map == version
    assert doc.extraction.rejected[0][INSERT_AT] == HOT_PIXEL


def test_known_hot_must_fit_the_sequence_and_all_false_changes_nothing(single):
    sequence, _ = single
    n = sequence.snapshots[0].n_sources
    with pytest.raises(ValueError):
        extract(sequence, known_hot=[np.zeros(n + 1, bool)])
    with pytest.raises(ValueError):
        extract(sequence, known_hot=[])
    plain, flagged = extract(sequence), extract(sequence, known_hot=[np.zeros(n, bool)])
    assert plain.rejection == flagged.rejection and plain.notes == flagged.notes
    np.testing.assert_array_equal(plain.pattern.xy, flagged.pattern.xy)
