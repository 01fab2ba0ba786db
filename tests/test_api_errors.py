"""Every error code of the API, its {"detail": ...} shape, and a schema-driven fuzz run (no 5xx)."""

from __future__ import annotations

import json
import re
from urllib.parse import quote

import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings as hyp_settings, strategies as st

from app.api import create_app
from app.workflow import AppContext
from app.workflow.access import AccessPolicy, TokenConfigError, load_tokens, parse_token_file
from app.config import Settings
from app.storage import Storage

LIMIT = 20_000  # bytes: the samples are ~8-12 kB, so 413 is easy to provoke


@pytest.fixture(scope="module")
def env(tmp_path_factory, sky, sample_dir):
    ctx = AppContext(storage=Storage.open(tmp_path_factory.mktemp("errors") / "e.sqlite3"), sky=sky,
                     settings=Settings(max_upload_bytes=LIMIT, search_timeout_s=2.0))
    client = TestClient(create_app(ctx))
    sid = client.post("/api/sequences", content=(sample_dir / "02-ghosts-hot-pixels.json").read_bytes(),
                      headers={"Content-Type": "application/json"}).json()["id"]
    yield client, sid
    ctx.close()


def _error(r, status):
    assert r.status_code == status, r.text
    doc = r.json()
    assert isinstance(doc["detail"], str) and len(doc["detail"]) > 10
    return doc


def test_413_above_the_size_limit(env):
    client, _ = env
    big = b'{"format": "tubsat-snapshots/1", "pad": "' + b"x" * LIMIT + b'"}'
    doc = _error(client.post("/api/sequences", content=big, headers={"Content-Type": "application/json"}), 413)
    assert str(LIMIT) in doc["detail"]
    _error(client.post("/api/sequences", files={"file": ("big.json", big, "application/json")}), 413)

    def chunks():  # no Content-Length: the limit must hold while streaming
        for _ in range(LIMIT // 1000 + 2):
            yield b" " * 1000

    _error(client.post("/api/sequences", content=chunks(), headers={"Content-Type": "text/plain"}), 413)


def test_422_invalid_telemetry_has_located_problems(env, sample_dir):
    client, _ = env
    doc = json.loads((sample_dir / "01-clean.json").read_text())
    doc["snapshots"][0]["sources"][1]["x"] = 5000.0
    del doc["snapshots"][2]["time"]
    r = client.post("/api/sequences", files={"file": ("bad.json", json.dumps(doc).encode(), "application/json")})
    body = _error(r, 422)
    locations = [p["location"] for p in body["problems"]]
    assert "snapshots[0].sources[1].x" in locations
    assert any(loc.startswith("snapshots[2]") for loc in locations)
    for raw in (b"", b"\xff\xfe", b"snapshot,time,x,y,brightness\n1,yesterday,1,2,3\n"):
        assert client.post("/api/sequences", content=raw, headers={"Content-Type": "text/csv"}).status_code == 422
    _error(client.post("/api/sequences", files={"other": (None, "text")}), 422)


def test_422_an_image_or_no_body_sent_as_telemetry_is_said_to_be_one(env):
    """A PNG (or FITS) posted to the telemetry endpoint is named an image, with where images go (it read as
    'not valid UTF-8 text: byte 0x89 at offset 0'); a POST without any body is said to have none (it read as 'the
    file is empty'); an empty file sent as a file is still 'the file is empty'."""
    client, _ = env
    png = b"\x89PNG\r\n\x1a\n" + bytes(64)
    for r in (client.post("/api/sequences", files={"file": ("sky.png", png, "image/png")}),
              client.post("/api/sequences", content=b"SIMPLE  =                    T" + bytes(50),
                          headers={"Content-Type": "text/plain"})):
        doc = _error(r, 422)
        assert "an image (FITS, PNG, JPEG or TIFF), not telemetry: send images to POST /api/frames" in doc["detail"]
        assert doc["problems"] == [{"location": "body.file",
                                    "message": "an image, not telemetry: send it to POST /api/frames"}]
    assert _error(client.post("/api/sequences", files={"file": ("sky.png", png, "image/png")}), 422)[
        "detail"].startswith("sky.png: an image")
    doc = _error(client.post("/api/sequences"), 422)
    assert doc["detail"].startswith("the request has no body") and doc["problems"] == [
        {"location": "body", "message": "no body"}]
    doc = _error(client.post("/api/sequences", content=b"", headers={"Content-Type": "application/json"}), 422)
    assert "the file is empty" in doc["detail"]


def test_415_unsupported_media_type(env):
    client, _ = env
    _error(client.post("/api/sequences", content=b"<xml/>", headers={"Content-Type": "application/xml"}), 415)


def test_404_for_unknown_ids(env):
    client, sid = env
    missing = sid + 1000
    for method, url, kwargs in [
        ("get", f"/api/sequences/{missing}", {}),
        ("put", f"/api/sequences/{missing}/pattern", {"json": {}}),
        ("post", f"/api/sequences/{missing}/pattern/reset", {}),
        ("post", f"/api/sequences/{missing}/search", {}),
        ("get", f"/api/sequences/{missing}/candidates/1", {}),
        ("post", f"/api/sequences/{missing}/confirm", {"json": {"rank": 1, "operator": "x"}}),
        ("get", f"/api/sequences/{missing}/aem", {}),
        ("get", "/api/attitudes/987654", {}),
        ("get", "/api/attitudes/987654/apm", {}),
        ("get", "/api/no/such/endpoint", {}),
    ]:
        doc = _error(getattr(client, method)(url, **kwargs), 404)
        assert "987654" in doc["detail"] or str(missing) in doc["detail"] or "endpoint" in doc["detail"]


def test_409_confirm_without_search_or_rank_and_404_candidate(tmp_path, sky, sample_dir):
    ctx = AppContext(storage=Storage.open(tmp_path / "c.sqlite3"), sky=sky)
    client = TestClient(create_app(ctx))
    try:
        sid = client.post("/api/sequences", content=(sample_dir / "06-sparse.json").read_bytes()).json()["id"]
        assert "not been searched" in _error(
            client.post(f"/api/sequences/{sid}/confirm", json={"rank": 1, "operator": "x"}), 409)["detail"]
        _error(client.get(f"/api/sequences/{sid}/candidates/1"), 404)
        _error(client.get(f"/api/sequences/{sid}/aem"), 404)
        n = len(client.post(f"/api/sequences/{sid}/search").json()["candidates"])
        doc = _error(client.post(f"/api/sequences/{sid}/confirm", json={"rank": n + 1, "operator": "x"}), 409)
        assert f"rank {n + 1}" in doc["detail"]
        _error(client.get(f"/api/sequences/{sid}/candidates/{n + 1}"), 404)
        assert client.get("/api/attitudes").json()["total"] == 0  # nothing was stored by the refusals
    finally:
        ctx.close()


def test_422_bad_request_bodies_and_parameters(env):
    client, sid = env
    for body in ({"exclude_track": [1]}, {"include_tracks": [999]}, {"exclude_tracks": [-1]},
                 {"manual_points": [{"snapshot": 0, "x": 1e9, "y": 3}]},
                 {"manual_points": [{"snapshot": 99, "x": 10, "y": 10}]},
                 {"manual_points": [{"snapshot": 0, "x": "left"}]}):
        doc = _error(client.put(f"/api/sequences/{sid}/pattern", json=body), 422)
        assert doc["problems"] and all("location" in p and "message" in p for p in doc["problems"])
    doc = _error(client.put(f"/api/sequences/{sid}/pattern", content=b"{not json",
                            headers={"Content-Type": "application/json"}), 422)
    assert "JSON" in doc["detail"]
    # Located at the body, with the character FastAPI's offset names (it had read "body[0]", an item).
    doc = _error(client.post(f"/api/sequences/{sid}/search", content=b"garbage",
                             headers={"Content-Type": "application/json"}), 422)
    assert doc["problems"] == [{"location": "body", "message": "the body is not valid JSON (Expecting value at "
                                                                 "character 0)"}]
    doc = _error(client.post(f"/api/sequences/{sid}/confirm", content=b'{"rank": 1e20, "operator": "x"}',
                             headers={"Content-Type": "application/json"}), 422)
    assert doc["problems"] == [{"location": "body.rank", "message": "the number is too large for an integer"}]
    _error(client.put(f"/api/sequences/{sid}/pattern", content=b'{"manual_points": [{"snapshot": 0, "x": NaN, "y": 1}]}',
                      headers={"Content-Type": "application/json"}), 422)
    _error(client.post(f"/api/sequences/{sid}/search", json={"method": "guess"}), 422)
    _error(client.post(f"/api/sequences/{sid}/search", json={"max_candidates": 0}), 422)
    _error(client.post(f"/api/sequences/{sid}/confirm", json={"rank": 1}), 422)  # no operator anywhere
    _error(client.post(f"/api/sequences/{sid}/confirm", json={"rank": 0, "operator": "x"}), 422)
    _error(client.get("/api/sequences", params={"limit": 0}), 422)
    _error(client.get("/api/sequences", params={"status": "lost"}), 422)
    _error(client.get("/api/sequences/abc"), 422)
    _error(client.get(f"/api/sequences/{2**70}"), 422)
    _error(client.get(f"/api/sequences/{sid}/candidates/1", params={"mag": "bright"}), 422)
    # The stored pattern did not change through any of these.
    assert client.get(f"/api/sequences/{sid}").json()["pattern"]["version"] == 1


def test_401_writes_need_a_valid_token_off_loopback(tmp_path, sky, sample_dir):
    ctx = AppContext(storage=Storage.open(tmp_path / "t.sqlite3"), sky=sky,
                     access=AccessPolicy.for_host("192.0.2.10", {"tok": "dana"}))
    client = TestClient(create_app(ctx))
    try:
        data = (sample_dir / "01-clean.json").read_bytes()
        r = client.post("/api/sequences", content=data)
        assert _error(r, 401) and r.headers["www-authenticate"] == "Bearer"
        _error(client.post("/api/sequences", content=data, headers={"Authorization": "Bearer wrong"}), 401)
        _error(client.put("/api/sequences/1/pattern", json={}), 401)
        assert client.get("/api/sequences").status_code == 200
    finally:
        ctx.close()


def test_token_configuration():
    assert load_tokens("a1=alice, b2=bob") == {"a1": "alice", "b2": "bob"}
    assert parse_token_file("# comment\n\nt1 Ann Smith\nt2 bob\n") == {"t1": "Ann Smith", "t2": "bob"}
    with pytest.raises(TokenConfigError, match="non-loopback"):
        AccessPolicy.for_host("0.0.0.0", {})
    assert not AccessPolicy.for_host("127.0.0.1", {}).require_token
    assert not AccessPolicy.for_host("::1", {}).require_token
    with pytest.raises(TokenConfigError):
        load_tokens("justatoken")
    with pytest.raises(TokenConfigError, match="cannot read"):
        load_tokens("", "/nonexistent/tokens.txt")


# ---------------------------------------------------------------------------
# Schema-driven fuzzing: every operation of /openapi.json with generated
# parameters and bodies must never answer 5xx.
# ---------------------------------------------------------------------------

_json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-2**70, 2**70) | st.floats(allow_nan=False, allow_infinity=False) | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=10), inner, max_size=4),
    max_leaves=12)
_param_values = st.one_of(st.integers(-5, 5), st.integers(-2**70, 2**70), st.text(max_size=12),
                          st.floats(allow_nan=True, allow_infinity=True), st.just("1"))


def _operations(client):
    spec = client.get("/openapi.json").json()
    ops = []
    for path, methods in spec["paths"].items():
        for method, op in methods.items():
            ops.append((path, method, op))
    return ops


def _body_for(op, schema_fields, data):
    """A body built from the operation's schema (valid-ish fields with fuzzed values) or random JSON."""
    if data.draw(st.booleans()):
        return data.draw(_json_values)
    body = {}
    for name in schema_fields:
        if data.draw(st.booleans()):
            body[name] = data.draw(_json_values | st.integers(0, 20) | st.lists(st.integers(-3, 30), max_size=5))
    return body


def test_fuzz_openapi_operations_never_5xx(env):
    client, sid = env
    spec = client.get("/openapi.json").json()
    schemas = spec.get("components", {}).get("schemas", {})
    operations = _operations(client)
    assert len(operations) >= 12

    def fields_of(op):
        content = op.get("requestBody", {}).get("content", {}).get("application/json", {})
        ref = content.get("schema", {})
        ref = ref.get("$ref") or next((s.get("$ref") for s in ref.get("anyOf", []) if "$ref" in s), None)
        return list(schemas[ref.rsplit("/", 1)[1]]["properties"]) if ref else []

    @hyp_settings(max_examples=120, deadline=None, suppress_health_check=list(HealthCheck))
    @given(st.data())
    def run(data):
        path, method, op = data.draw(st.sampled_from(operations))
        url = path
        for name in re.findall(r"{(\w+)}", path):
            value = data.draw(st.one_of(st.just(sid), st.just(1), _param_values))
            url = url.replace("{" + name + "}", quote(str(value), safe="") or "0")
        params = {p["name"]: str(data.draw(_param_values)) for p in op.get("parameters", [])
                  if p["in"] == "query" and data.draw(st.booleans())}
        kwargs = {"params": params}
        if method in ("post", "put"):
            if path == "/api/sequences":
                kwargs["content"] = data.draw(st.binary(max_size=300))
                kwargs["headers"] = {"Content-Type": data.draw(st.sampled_from(
                    ["application/json", "text/csv", "text/plain", "multipart/form-data; boundary=x", "image/png"]))}
            else:
                kwargs["json"] = _body_for(op, fields_of(op), data)
        r = client.request(method.upper(), url, **kwargs)
        assert r.status_code < 500, (method, url, kwargs, r.status_code, r.text)
        if r.headers.get("content-type", "").startswith("application/json") and r.status_code >= 400:
            assert isinstance(r.json()["detail"], str)

    run()
