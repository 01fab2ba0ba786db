"""Defects of the operator trial: text limits counted in characters, control characters in names and
comments refused, re-uploads of the same sequence in other bytes named, truth files skipped with a word.

The command-line ``upload`` checks live in test_hardening_api.py, beside its live server.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys

import pytest
from fastapi.testclient import TestClient

from app.api import create_app
from app.bench.server import REPO
from app.cli import main as cli_main
from app.cli.upload import summary_line
from app.storage import Storage
from app.workflow import AppContext
from app.workflow.access import TokenConfigError, parse_token_file, parse_token_list


@pytest.fixture
def api(tmp_path, sky):
    ctx = AppContext(storage=Storage.open(tmp_path / "trial.sqlite3"), sky=sky)
    yield TestClient(create_app(ctx)), ctx
    ctx.close()


@pytest.fixture
def stored(api, sample_dir) -> int:
    """The archive id of one uploaded sample."""
    client, _ = api
    r = client.post("/api/sequences", content=(sample_dir / "01-clean.json").read_bytes(),
                    headers={"Content-Type": "application/json"})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _problems(response) -> list[dict]:
    assert response.status_code == 422, response.text
    return response.json()["problems"]


# ---------------------------------------------------------------------------
# Item 1: a text field's length limit is said in characters
# ---------------------------------------------------------------------------

def test_confirm_says_operator_and_comment_limits_in_characters(api):
    client, _ = api
    r = client.post("/api/sequences/1/confirm", json={"rank": 1, "operator": "o" * 5000, "comment": "c" * 3000,
                                                      "override_reason": "r" * 2001})
    assert _problems(r) == [
        {"location": "body.operator", "message": "String should have at most 100 characters"},
        {"location": "body.comment", "message": "String should have at most 2000 characters"},
        {"location": "body.override_reason", "message": "String should have at most 2000 characters"}]


@pytest.mark.parametrize("method, path, body, location, limit", [
    ("POST", "/api/sequences/1/reject", {"reason": "r" * 2001, "operator": "ann"}, "body.reason", 2000),
    ("POST", "/api/sequences/1/reject", {"reason": "r", "operator": "o" * 101}, "body.operator", 100),
    ("PUT", "/api/sequences/1/pattern", {"operator": "o" * 101}, "body.operator", 100),
    ("POST", "/api/sequences/1/pattern/reset", {"operator": "o" * 101}, "body.operator", 100),
    ("POST", "/api/spacecraft/sat/calibrate", {"operator": "o" * 101}, "body.operator", 100),
    ("GET", "/api/sequences?search=" + "s" * 129, None, "query.search", 128),
    ("GET", "/api/sequences?spacecraft=" + "s" * 129, None, "query.spacecraft", 128),
    ("GET", "/api/attitudes/aem?spacecraft=" + "s" * 129, None, "query.spacecraft", 128),
    ("GET", "/api/spacecraft/" + "s" * 129 + "/camera", None, "path.name", 128),
])
def test_every_text_limit_is_said_in_characters(api, method, path, body, location, limit):
    client, _ = api
    r = client.request(method, path, json=body)
    assert _problems(r) == [{"location": location, "message": f"String should have at most {limit} characters"}]


def test_an_empty_spacecraft_name_is_said_in_characters(api):
    client, _ = api
    r = client.get("/api/attitudes/aem?spacecraft=")
    assert _problems(r) == [{"location": "query.spacecraft", "message": "String should have at least 1 character"}]


def test_the_nul_refusal_still_holds_with_the_limits(api):
    client, _ = api
    r = client.post("/api/sequences/1/reject", json={"reason": "x\x00", "operator": "ann"})
    assert _problems(r) == [{"location": "body.reason", "message": "must not contain a NUL character (U+0000)"}]
    assert _problems(client.get("/api/sequences?search=a%00")) == [
        {"location": "query.search", "message": "must not contain a NUL character (U+0000)"}]


# ---------------------------------------------------------------------------
# Item 2: control characters and bidirectional controls in names, comments and reasons
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("name, code, kind", [
    ("ann\x1b[31mroot", "U+001B", "control character"),
    ("ann\nbob", "U+000A", "control character"),
    ("ann\tbob", "U+0009", "control character"),
    ("ann\x7f", "U+007F", "control character"),
    ("ann\x9b2J", "U+009B", "control character"),
    ("ann\u202egnp.exe", "U+202E", "bidirectional control"),
    ("\u2066ann\u2069", "U+2066", "bidirectional control"),
])
def test_operator_names_with_control_characters_are_refused_at_the_field(api, stored, name, code, kind):
    client, _ = api
    r = client.post(f"/api/sequences/{stored}/reject", json={"reason": "no stars", "operator": name})
    assert _problems(r) == [{"location": "body.operator",
                             "message": f"must not contain the {kind} {code} (an operator name is one line of "
                                        "plain text)"}]
    assert client.get(f"/api/sequences/{stored}").json()["status"] == "new"  # nothing was recorded


@pytest.mark.parametrize("method, path, body", [
    ("PUT", "/api/sequences/{sid}/pattern", {"operator": "a\x1bb"}),
    ("POST", "/api/sequences/{sid}/pattern/reset", {"operator": "a\x1bb"}),
    ("POST", "/api/sequences/{sid}/confirm", {"rank": 1, "operator": "a\x1bb"}),
    ("POST", "/api/spacecraft/sat/calibrate", {"operator": "a\x1bb"}),
])
def test_every_operator_field_refuses_control_characters(api, stored, method, path, body):
    client, _ = api
    r = client.request(method, path.format(sid=stored), json=body)
    assert _problems(r) == [{"location": "body.operator",
                             "message": "must not contain the control character U+001B (an operator name is one "
                                        "line of plain text)"}]


@pytest.mark.parametrize("field, text, code, kind", [
    ("comment", "fine\x1b[2J", "U+001B", "control character"),
    ("comment", "ok\x0bthen", "U+000B", "control character"),
    ("override_reason", "best \u202bis wrong", "U+202B", "bidirectional control"),
])
def test_comments_refuse_control_characters_but_line_breaks_and_tabs(api, stored, field, text, code, kind):
    client, _ = api
    r = client.post(f"/api/sequences/{stored}/confirm", json={"rank": 1, "operator": "ann", field: text})
    assert _problems(r) == [{"location": f"body.{field}",
                             "message": f"must not contain the {kind} {code} (line breaks and tabs are allowed)"}]


def test_windows_and_old_mac_line_breaks_in_a_reason_are_kept_as_plain_newlines(api, stored):
    """A text field on Windows (or a pasted mail) sends CRLF: the same reason, not a refused one."""
    client, _ = api
    r = client.post(f"/api/sequences/{stored}/reject", json={"reason": "no stars:\r\n- ghosts\r- hot pixels",
                                                             "operator": "ann"})
    assert r.status_code == 201, r.text
    assert r.json()["reason"] == "no stars:\n- ghosts\n- hot pixels"


def test_a_reason_with_line_breaks_and_tabs_is_kept_as_written(api, stored):
    client, _ = api
    reason = "no stars:\n\t- cloud of ghosts\n\t- hot pixels"
    r = client.post(f"/api/sequences/{stored}/reject", json={"reason": reason, "operator": "ann"})
    assert r.status_code == 201, r.text
    assert r.json()["reason"] == reason
    r = client.post(f"/api/sequences/{stored}/reject", json={"reason": "x\u2067y", "operator": "ann",
                                                             "supersede": True})
    assert _problems(r) == [{"location": "body.reason", "message": "must not contain the bidirectional control "
                                                                  "U+2067 (line breaks and tabs are allowed)"}]


@pytest.mark.parametrize("name", ["Zoë Ångström", "山田 太郎", "Ана", "ann 🚀", "José-María O'Neill", "עדי"])
def test_plain_unicode_operator_names_are_accepted_and_kept(api, stored, name):
    client, _ = api
    r = client.post(f"/api/sequences/{stored}/reject", json={"reason": "clouded \u00e9t\u00e9 ✓", "operator": name})
    assert r.status_code == 201, r.text
    assert r.json()["operator"] == name and r.json()["reason"] == "clouded \u00e9t\u00e9 ✓"
    r = client.put(f"/api/sequences/{stored}/pattern", json={"operator": name})
    assert r.status_code == 200, r.text
    assert r.json()["operator"] == name


def test_token_operator_names_with_control_characters_are_refused():
    with pytest.raises(TokenConfigError) as refused:
        parse_token_list("t1=ann,t2=bob\x1b]0;owned\x07")
    assert str(refused.value) == ("STARID_TOKENS item 2: the operator name must not contain the control character "
                                  "U+001B (an operator name is one line of plain text)")
    with pytest.raises(TokenConfigError) as refused:
        parse_token_file("t1 Ann\nt2 eve\u202etxt.exe\n", "tokens.txt")
    assert str(refused.value) == ("tokens.txt line 2: the operator name must not contain the bidirectional control "
                                  "U+202E (an operator name is one line of plain text)")
    assert parse_token_list("t1=Zoë Ångström,t2=山田") == {"t1": "Zoë Ångström", "t2": "山田"}


def test_token_operator_names_are_as_long_as_the_api_allows():
    """The API refuses operator names over 100 characters; a token's name is held to the same."""
    assert parse_token_list("t1=" + "a" * 100) == {"t1": "a" * 100}
    with pytest.raises(TokenConfigError) as refused:
        parse_token_list("t1=" + "a" * 101)
    assert str(refused.value) == "STARID_TOKENS item 1: the operator name must be at most 100 characters, got 101"


def test_the_hot_pixel_map_refuses_a_nul_in_the_spacecraft_name(api):
    client, _ = api
    r = client.get("/api/frames/hot-pixels", params={"spacecraft": "SAT\x00", "sensor": "752x582"})
    assert r.status_code == 422
    assert r.json()["problems"] == [{"location": "query.spacecraft", "message": "must not contain a NUL character (U+0000)"}]


def test_serve_refuses_a_token_file_with_a_control_character_in_a_name(tmp_path):
    """The command-line path of an operator name: ``serve`` reads them from STARID_TOKENS(_FILE)."""
    tokens = tmp_path / "tokens"
    tokens.write_text("secret-1 ann\nsecret-2 mallory\x1b[8m\n", encoding="utf-8")
    with socket.socket() as probe:  # a free port: serve binds it before reading the tokens
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    env = {**os.environ, "STARID_TOKENS_FILE": str(tokens), "STARID_TOKENS": ""}
    done = subprocess.run([sys.executable, "-m", "app", "serve", "--port", str(port),
                           "--db", str(tmp_path / "x.sqlite3"), "--no-viewer"],
                          cwd=REPO, capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    assert done.stderr.strip() == ("serve: STARID_TOKENS_FILE line 2: the operator name must not contain the "
                                   "control character U+001B (an operator name is one line of plain text)")


# ---------------------------------------------------------------------------
# Item 3: the same sequence uploaded again in other bytes is stored, and named
# ---------------------------------------------------------------------------

def _post(client, data: bytes, content_type="application/json"):
    return client.post("/api/sequences", content=data, headers={"Content-Type": content_type})


def test_an_upload_of_a_stored_sequence_in_other_bytes_names_the_other_uploads(api, sample_dir):
    client, _ = api
    data = (sample_dir / "01-clean.json").read_bytes()
    first = _post(client, data)
    assert first.status_code == 201
    assert first.json()["same_sequence_id_as"] == [] and first.json()["note"] is None
    crlf = _post(client, data.replace(b"\n", b"\r\n"))
    assert crlf.status_code == 201  # dedupe stays by exact content: a second sequence...
    assert crlf.json()["sequence"]["sequence_id"] == first.json()["sequence"]["sequence_id"]
    assert crlf.json()["same_sequence_id_as"] == [first.json()["id"]]  # ...and it says so
    assert crlf.json()["note"] == (f"another stored upload (#{first.json()['id']}) has the same spacecraft and "
                                   "sequence id; its telemetry differs in bytes (line endings, byte-order mark or "
                                   "content)")
    bom = _post(client, b"\xef\xbb\xbf" + data)
    assert bom.status_code == 201, bom.text
    ids = [first.json()["id"], crlf.json()["id"]]
    assert bom.json()["same_sequence_id_as"] == ids
    assert bom.json()["note"] == (f"other stored uploads (#{ids[0]}, #{ids[1]}) have the same spacecraft and "
                                  "sequence id; their telemetry differs in bytes (line endings, byte-order mark or "
                                  "content)")
    again = _post(client, data)  # the very same bytes: the stored sequence, and the others still named
    assert again.status_code == 200 and again.json()["id"] == ids[0]
    assert again.json()["same_sequence_id_as"] == [ids[1], bom.json()["id"]]
    other = _post(client, (sample_dir / "02-ghosts-hot-pixels.json").read_bytes())
    assert other.json()["same_sequence_id_as"] == [] and other.json()["note"] is None
    assert client.get("/api/sequences").json()["total"] == 4  # digests and the unique key are unchanged


def test_the_upload_document_describes_the_new_fields(api):
    client, _ = api
    schema = client.get("/openapi.json").json()["components"]["schemas"]["UploadDocument"]
    assert schema["properties"]["same_sequence_id_as"]["items"]["type"] == "integer"
    assert "spacecraft and sequence id" in schema["properties"]["same_sequence_id_as"]["description"]
    assert "note" in schema["properties"]


def test_storage_finds_the_uploads_of_a_spacecraft_and_sequence_id(archive_url):
    with Storage.open(archive_url) as storage:
        a, _ = storage.add_sequence(raw_text="a", sequence_id="pass-1", spacecraft="SAT-1", filename="a.json")
        b, _ = storage.add_sequence(raw_text="a\r\n", sequence_id="pass-1", spacecraft="SAT-1")
        storage.add_sequence(raw_text="c", sequence_id="pass-1", spacecraft="SAT-2")
        storage.add_sequence(raw_text="d", sequence_id="pass-2", spacecraft="SAT-1")
        n1, _ = storage.add_sequence(raw_text="e", sequence_id="pass-1", spacecraft=None)
        n2, _ = storage.add_sequence(raw_text="f", sequence_id="pass-1", spacecraft=None)
        assert storage.same_sequence_uploads("SAT-1", "pass-1") == [(a.id, "a.json"), (b.id, None)]
        assert storage.same_sequence_uploads("SAT-1", "pass-1", other_than=a.id) == [(b.id, None)]
        # No spacecraft matches no spacecraft.
        assert storage.same_sequence_uploads(None, "pass-1") == [(n1.id, None), (n2.id, None)]
        assert storage.same_sequence_uploads("SAT-3", "pass-1") == []


# ---------------------------------------------------------------------------
# Item 4: truth files left out of a folder are counted (upload: see test_hardening_api.py)
# ---------------------------------------------------------------------------

def test_batch_says_how_many_truth_files_it_left_out(tmp_path, sample_dir, capsys):
    folder = tmp_path / "truth-only"
    folder.mkdir()
    for name in ("01-clean.truth.json", "08-csv.truth.json"):
        (folder / name).write_bytes((sample_dir / name).read_bytes())
    status = cli_main(["batch", str(folder), "--out", str(tmp_path / "out.jsonl")])
    assert status == 2  # nothing to process: refused before any cluster starts
    assert capsys.readouterr().err.splitlines() == [
        "batch: left out 2 truth files (*.truth.json): the simulator's answers, not telemetry",
        "batch: no .json or .csv files found"]
    # Named one by one, as a shell glob such as sample_telemetry/*.json names them: the same (they had been
    # sent as telemetry, and reported invalid).
    status = cli_main(["batch", *(str(p) for p in sorted(folder.iterdir())), "--out", str(tmp_path / "out.jsonl")])
    assert status == 2
    assert capsys.readouterr().err.splitlines() == [
        "batch: left out 2 truth files (*.truth.json): the simulator's answers, not telemetry",
        "batch: no .json or .csv files found"]


def test_the_upload_line_carries_the_servers_note():
    doc = {"id": 9, "sequence": {"sequence_id": "p"}, "note": "another stored upload (#8) has ..."}
    assert summary_line("b.json", 201, doc) == ("b.json: created id=9 sequence_id=p\n"
                                                "  note: another stored upload (#8) has ...")
    assert summary_line("b.json", 200, {**doc, "note": None}) == "b.json: duplicate id=9 sequence_id=p"


def test_a_console_names_its_operator_in_its_view_session(api):
    """What the 3D view confirms under: the console's name, held to the operator-name rule."""
    client, _ = api
    r = client.put("/api/view", params={"session": "tab-1"}, json={"operator": "Vera"})
    assert r.status_code == 200 and r.json()["operator"] == "Vera"
    r = client.put("/api/view", params={"session": "tab-1"}, json={"operator": "eve\x1b[2J"})
    assert _problems(r) == [{"location": "body.operator", "message": "must not contain the control character "
                                                                    "U+001B (an operator name is one line of plain text)"}]
    assert client.get("/api/view", params={"session": "tab-1"}).json()["operator"] == "Vera"
