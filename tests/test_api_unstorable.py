"""A NUL character anywhere a client can send text: refused at its field with 422 on both backends.

PostgreSQL's text cannot hold U+0000 (SQLite can), so without a check at the
boundary the same request was stored on SQLite and answered 500 on
PostgreSQL.  The refusal is the same on both, names the field, and stores
nothing.
"""

from __future__ import annotations

import json

import pytest
from fastapi.testclient import TestClient

from app.api import create_app
from app.config import Settings
from app.storage import Storage
from app.workflow import AppContext


@pytest.fixture
def client(archive_url, sky):
    ctx = AppContext(storage=Storage.open(archive_url), sky=sky, settings=Settings(search_timeout_s=10.0))
    yield TestClient(create_app(ctx))
    ctx.close()


def _sample(sample_dir) -> dict:
    return json.loads((sample_dir / "01-clean.json").read_text())


def _total(client) -> int:
    return client.get("/api/sequences").json()["total"]


def test_nul_in_telemetry_text_is_refused_at_its_field(client, sample_dir):
    doc = _sample(sample_dir)
    doc["sequence_id"] = "pass\x00one"
    r = client.post("/api/sequences", content=json.dumps(doc), headers={"Content-Type": "application/json"})
    assert r.status_code == 422, r.text
    assert "sequence_id" in json.dumps(r.json()["problems"])
    assert _total(client) == 0


def test_nul_in_operator_text_is_refused_and_nothing_is_confirmed(client, sample_dir):
    doc = _sample(sample_dir)
    up = client.post("/api/sequences", content=json.dumps(doc), headers={"Content-Type": "application/json"})
    assert up.status_code in (200, 201), up.text
    seq = up.json()["id"]
    search = client.post(f"/api/sequences/{seq}/search", json={})
    assert search.status_code == 200, search.text
    r = client.post(f"/api/sequences/{seq}/confirm", json={"search_id": search.json()["search_id"], "rank": 1,
                                                           "operator": "ann\x00", "comment": "ok"})
    assert r.status_code == 422, r.text
    assert "operator" in json.dumps(r.json()["problems"])
    r = client.post(f"/api/sequences/{seq}/confirm", json={"search_id": search.json()["search_id"], "rank": 1,
                                                           "operator": "ann", "comment": "a\x00b"})
    assert r.status_code == 422, r.text
    assert "comment" in json.dumps(r.json()["problems"])
    assert client.get("/api/attitudes").json()["total"] == 0


def test_nul_in_a_query_parameter_is_refused_at_its_parameter(client):
    r = client.get("/api/sequences", params={"spacecraft": "sat\x00"})
    assert r.status_code == 422, r.text
    assert r.json()["problems"][0]["location"] == "query.spacecraft"
    r = client.get("/api/attitudes/aem", params={"spacecraft": "\x00"})
    assert r.status_code == 422, r.text


def test_a_value_the_backend_refuses_is_a_located_422_not_a_500(client, monkeypatch):
    """The backstop: a write the database refuses that no field check caught is a 422, never a 500."""
    from app.storage import UnstorableValue
    from app.workflow import queue

    def refuse(*args, **kwargs):
        raise UnstorableValue("the archive cannot store this value: invalid byte sequence 0x00")

    monkeypatch.setattr(queue, "list_sequences", refuse)
    r = client.get("/api/sequences")
    assert r.status_code == 422, r.text
    assert r.json()["detail"].endswith("nothing was stored")
    assert r.json()["problems"] == [{"location": "request",
                                     "message": "the archive cannot store this value: invalid byte sequence 0x00"}]
