"""The archive workflow's invariants: the stored extraction is authoritative, stored documents parse back
into the objects they came from, old archives migrate, and the CLI and the API say the same thing."""

from __future__ import annotations

import json
import sqlite3
import subprocess
import sys

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.api import create_app
from app.extraction import extract
from app.storage import MIGRATIONS, Storage
from app.telemetry.formats import load_telemetry_file
from app.workflow import AppContext, archive
from app.workflow.documents import ExtractionDocument, SearchResult
from app.workflow.errors import Conflict

SAMPLES = ("01-clean.json", "02-ghosts-hot-pixels.json", "06-sparse.json", "07-single.json", "08-csv.csv",
           "05-earth.json")


def _assert_same_extraction(a, b):
    assert a.reference == b.reference and a.noise_px == b.noise_px and a.notes == b.notes
    assert [t.tolist() for t in a.track_of_source] == [t.tolist() for t in b.track_of_source]
    assert a.rejection == b.rejection
    np.testing.assert_array_equal(a.motion, b.motion)
    assert len(a.tracks) == len(b.tracks)
    for s, t in zip(a.tracks, b.tracks):
        assert s.id == t.id and s.mean_brightness == t.mean_brightness
        np.testing.assert_array_equal(s.snapshots, t.snapshots)
        np.testing.assert_array_equal(s.source_indices, t.source_indices)
        np.testing.assert_array_equal(s.xy, t.xy)
    for name in ("pattern", "seed_pattern"):
        p, q = getattr(a, name), getattr(b, name)
        for field in ("track_ids", "xy", "vectors", "brightness", "sightings", "sigma_px"):
            np.testing.assert_array_equal(getattr(p, field), getattr(q, field), err_msg=f"{name}.{field}")


@pytest.mark.parametrize("name", SAMPLES)
def test_stored_extraction_equals_the_recomputed_one(sample_dir, name):
    sequence = load_telemetry_file(sample_dir / name)
    computed = extract(sequence)
    stored = json.loads(json.dumps(ExtractionDocument.of(computed).model_dump(mode="json"), allow_nan=False))
    _assert_same_extraction(ExtractionDocument.model_validate(stored).to_extraction(sequence), computed)


@pytest.fixture()
def api(tmp_path, sky):
    ctx = AppContext(storage=Storage.open(tmp_path / "archive.sqlite3"), sky=sky)
    yield TestClient(create_app(ctx)), ctx
    ctx.close()


def test_loading_a_sequence_reads_its_stored_extraction_and_never_extracts_again(api, sample_dir, monkeypatch):
    client, ctx = api
    seq = client.post("/api/sequences", files={"file": ("02.json", (sample_dir / "02-ghosts-hot-pixels.json")
                                                           .read_bytes())}).json()["id"]
    stored_doc = ctx.storage.get_sequence(seq).extraction
    ctx.cache = type(ctx.cache)()  # as after a restart

    def no_extraction(*_args, **_kwargs):
        raise AssertionError("extraction ran again on a stored sequence")

    monkeypatch.setattr(archive, "extract", no_extraction)
    detail = client.get(f"/api/sequences/{seq}").json()
    assert detail["extraction"] == stored_doc
    assert client.post(f"/api/sequences/{seq}/search").json()["status"] == "identified"


def _store_without_version(ctx, sample_dir, sources_override=None):
    """An upload stored as versions before 1 stored it: the extraction document without version or motion."""
    path = sample_dir / "01-clean.json"
    sequence = load_telemetry_file(path)
    doc = ExtractionDocument.of(extract(sequence)).model_dump(mode="json")
    del doc["version"], doc["motion"]
    if sources_override is not None:
        doc["sources"] = sources_override(doc["sources"])
    row, _ = ctx.storage.add_sequence(raw_text=path.read_text(), filename=path.name, sequence_id="old",
                                      camera=sequence.camera.to_dict(), n_snapshots=len(sequence.snapshots),
                                      extraction=doc)
    return row


def test_an_old_extraction_is_used_when_extraction_still_numbers_its_tracks_alike(api, sample_dir):
    _, ctx = api
    row = _store_without_version(ctx, sample_dir)
    item = archive.loaded(ctx, ctx.storage.get_sequence(row.id))
    assert ExtractionDocument.of(item.extraction).sources == row.extraction["sources"]


def test_an_old_extraction_numbered_differently_is_refused_not_renumbered(api, sample_dir):
    client, ctx = api

    def swap_first_two_tracks(sources):
        swap = {0: 1, 1: 0}
        return [[swap.get(t, t) if t is not None else None for t in per] for per in sources]

    row = _store_without_version(ctx, sample_dir, swap_first_two_tracks)
    with pytest.raises(Conflict, match="track numbers"):
        archive.loaded(ctx, ctx.storage.get_sequence(row.id))
    r = client.get(f"/api/sequences/{row.id}")
    assert r.status_code == 409 and "track numbers" in r.json()["detail"]


def test_a_stored_extraction_cannot_be_changed(api, sample_dir):
    client, ctx = api
    seq = client.post("/api/sequences", files={"file": ("01.json", (sample_dir / "01-clean.json").read_bytes())}
                      ).json()["id"]
    raw = sqlite3.connect(ctx.storage.path)
    with pytest.raises(sqlite3.DatabaseError, match="never changed"):
        raw.execute("UPDATE sequences SET extraction_json = '{}' WHERE id = ?", (seq,))
    raw.close()


def test_a_search_result_parses_back_into_the_document_it_was_stored_from(api, sample_dir):
    client, ctx = api
    seq = client.post("/api/sequences", files={"file": ("03.json", (sample_dir / "03-jupiter.json").read_bytes())}
                      ).json()["id"]
    answered = client.post(f"/api/sequences/{seq}/search").json()
    parsed = SearchResult.model_validate(ctx.storage.latest_search(seq).result)
    assert parsed.model_dump(mode="json") == {k: answered[k] for k in SearchResult.model_fields}
    best = parsed.candidates[0]
    np.testing.assert_allclose(best.rotation @ best.rotation.T, np.eye(3), atol=1e-9)
    assert any(p.name == "jupiter" for p in best.planets)


def test_version_1_archive_migrates_with_the_confirmation_epoch_and_rate_as_columns(tmp_path):
    path = tmp_path / "v1.sqlite3"
    conn = sqlite3.connect(path)
    conn.execute("CREATE TABLE schema_version (version INTEGER PRIMARY KEY, applied_at TEXT NOT NULL)")
    for statement in MIGRATIONS[0]:
        conn.execute(statement)
    conn.execute("INSERT INTO schema_version VALUES (1, '2026-01-01T00:00:00.000000+00:00')")
    conn.execute("INSERT INTO sequences (id, content_sha256, raw_text, uploaded_at) VALUES "
                 "(1, 'x', '{}', '2026-01-01T00:00:00.000000+00:00')")
    apm = ("CCSDS_APM_VERS = 2.0\nCREATION_DATE = 2026-01-02T00:00:00.000000\nORIGINATOR = T\n"
           "OBJECT_NAME = S\nOBJECT_ID = Q\nTIME_SYSTEM = UTC\nEPOCH = 2025-07-04T12:34:56.789000\n")
    candidate = {"sequence_fit": {"rate_deg_s": [0.1, -0.2, 0.3]}}
    for cid, cand in ((1, candidate), (2, {})):
        conn.execute("INSERT INTO confirmations (id, seq_id, rank, operator, confirmed_at, quaternion_json, "
                     "rotation_matrix_json, ra_deg, dec_deg, roll_deg, pattern_json, candidate_json, apm_text) "
                     "VALUES (?, 1, 1, 'op', '2026-01-02T00:00:00.000000+00:00', '[0,0,0,1]', "
                     "'[[1,0,0],[0,1,0],[0,0,1]]', 0, 0, 0, '{}', ?, ?)", (cid, json.dumps(cand), apm))
    conn.commit()
    conn.close()
    with Storage.open(path) as store:
        first, second = store.get_confirmation(1), store.get_confirmation(2)
        assert first.epoch.isoformat() == "2025-07-04T12:34:56.789000+00:00"
        assert first.rate_deg_s == [0.1, -0.2, 0.3] and second.rate_deg_s is None
        assert store.health()["schema_version"] == len(MIGRATIONS)
    raw = sqlite3.connect(path)
    with pytest.raises(sqlite3.DatabaseError, match="append-only"):
        raw.execute("UPDATE confirmations SET epoch = NULL WHERE id = 1")
    raw.close()


def test_the_cli_and_the_api_give_the_same_candidate_document(api, sample_dir):
    client, _ = api
    path = sample_dir / "04-big-dipper.json"
    seq = client.post("/api/sequences", files={"file": (path.name, path.read_bytes())}).json()["id"]
    from_api = client.post(f"/api/sequences/{seq}/search").json()["candidates"]
    run = subprocess.run([sys.executable, "-m", "app", "solve", "--json", str(path)], capture_output=True,
                         text=True, timeout=120)
    from_cli = json.loads(run.stdout)["candidates"]
    assert from_cli and [c["rank"] for c in from_cli] == [c["rank"] for c in from_api]
    for a, b in zip(from_cli, from_api):
        assert set(a) == set(b)
        assert a == b
