"""`--fov-deg` on the command line (issue 15): the optics of image inputs for `extract`, `solve` and `upload`.

A rendered pass whose FITS headers hold no optics (no FOCALLEN/XPIXSZ, no sidecar) cannot be read
without it and solves with it; a bad value is refused at the option, and a spot-list file given with
it is that file's error (it carries its own camera) while the batch goes on.
"""

from __future__ import annotations

import json
import socket
import threading
import time

import numpy as np
import pytest

from app.attitude import angle_between
from app.camera import CAMERAS
from app.cli import main as cli_main
from app.simulate import frames_fits_bytes, simulate_frames

CAMERA = CAMERAS["tubsat-752x582-20deg"]
#: The field of view an operator would give: the declared one, 3 % off (known to +-5 %).
FOV = CAMERA.fov_deg[0] * 1.03


@pytest.fixture(scope="module")
def bare_pass(tmp_path_factory):
    """A FITS pass of 4 rendered frames without any optics in its headers, and its truth."""
    frames, times, truth = simulate_frames(np.random.default_rng(1515), CAMERA, n_frames=4, sequence_id="bare")
    folder = tmp_path_factory.mktemp("fov")
    path = folder / "bare.fits"
    path.write_bytes(frames_fits_bytes(frames, times, camera=None, spacecraft="FOV-SAT"))
    return path, truth


@pytest.fixture
def session_sky(monkeypatch, sky):
    """`solve` builds its Sky(); hand it the session's."""
    monkeypatch.setattr("app.identification.Sky", lambda: sky)
    return sky


def _lines(out: str) -> list[dict]:
    return [json.loads(line) for line in out.splitlines() if line.strip()]


def test_a_pass_without_optics_solves_by_searching_the_field_of_view_and_with_fov_deg(bare_pass, session_sky,
                                                                                    capsys):
    path, truth = bare_pass
    assert cli_main(["solve", "--json", str(path)]) == 0  # issue 26: no optics, the field of view searched
    doc, = _lines(capsys.readouterr().out)
    assert doc["status"] == "identified"
    best = doc["candidates"][0]
    assert abs(best["fov_deg"] / CAMERA.fov_deg[0] - 1) < 0.005, best["fov_deg"]
    R = np.asarray(truth["rotation_matrices"][doc["reference_snapshot"]])
    assert np.degrees(angle_between(np.asarray(best["rotation_matrix"])[2], R[2])) < 0.1
    assert any("field of view was not given" in note for note in doc["notes"])

    assert cli_main(["solve", "--json", "--fov-deg", f"{FOV:.4f}", str(path)]) == 0
    doc, = _lines(capsys.readouterr().out)
    assert doc["status"] == "identified"
    R = np.asarray(truth["rotation_matrices"][doc["reference_snapshot"]])
    best = np.asarray(doc["candidates"][0]["rotation_matrix"])
    assert np.degrees(angle_between(best[2], R[2])) < 0.1


def test_extract_takes_fov_deg_too(bare_pass, capsys):
    path, _ = bare_pass
    assert cli_main(["extract", "--json", str(path)]) == 0  # no optics: extracted through a nominal camera
    assert _lines(capsys.readouterr().out)[0]["status"] == "ok"
    assert cli_main(["extract", "--json", "--fov-deg", str(FOV), str(path)]) == 0
    doc, = _lines(capsys.readouterr().out)
    assert doc["status"] == "ok" and len(doc["tracks"]) >= 5


def test_a_spot_list_with_fov_deg_is_that_files_error_and_the_batch_goes_on(bare_pass, sample_dir, session_sky,
                                                                            capsys):
    path, _ = bare_pass
    spot_list = sample_dir / "01-clean.json"
    assert cli_main(["solve", "--json", "--fov-deg", str(FOV), str(spot_list), str(path)]) == 2
    spot, image = _lines(capsys.readouterr().out)
    assert spot["status"] == "invalid" and image["status"] == "identified"
    assert spot["error"].startswith(f"{spot_list}: ") and "--fov-deg" in spot["error"]
    assert "spot list carries its own camera" in spot["error"] and "\n" not in spot["error"]
    assert cli_main(["extract", "--fov-deg", str(FOV), str(spot_list)]) == 2
    assert "spot list carries its own camera" in capsys.readouterr().out
    assert cli_main(["extract", str(spot_list)]) == 0  # without it, as before
    capsys.readouterr()


@pytest.mark.parametrize("command", ["solve", "extract", "upload"])
@pytest.mark.parametrize("value", ["500", "0", "-20", "abc", "nan", "inf", "0.05"])
def test_a_bad_fov_deg_is_refused_at_the_option(command, value, bare_pass, capsys):
    path, _ = bare_pass
    extra = ["--server", "http://127.0.0.1:9"] if command == "upload" else []
    with pytest.raises(SystemExit) as exited:
        cli_main([command, str(path), *extra, f"--fov-deg={value}"])
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert f"argument --fov-deg: must be a number from 0.1 to 120 degrees, got '{value}'" in err
    assert "Traceback" not in err


# ---------------------------------------------------------------------------
# upload --fov-deg against a real server
# ---------------------------------------------------------------------------

@pytest.fixture
def live_server(tmp_path, sky):
    """A real uvicorn server in a thread (loopback): its base URL."""
    import uvicorn

    from app.api import create_app
    from app.storage import Storage
    from app.workflow import AppContext

    ctx = AppContext(storage=Storage.open(tmp_path / "fov.sqlite3"), sky=sky)
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen(64)
    server = uvicorn.Server(uvicorn.Config(create_app(ctx), log_level="warning", log_config=None))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive(), "the test server did not start"
        time.sleep(0.02)
    yield f"http://127.0.0.1:{sock.getsockname()[1]}", ctx
    server.should_exit = True
    thread.join(10)
    sock.close()
    ctx.close()


def test_upload_sends_image_passes_with_fov_deg_and_refuses_spot_lists_with_it(live_server, bare_pass, sample_dir,
                                                                               capsys):
    url, ctx = live_server
    path, _ = bare_pass
    assert cli_main(["upload", str(path), "--server", url]) == 0  # no optics: stored, the field of view unknown
    assert f"{path}: created id=1" in capsys.readouterr().out
    assert ctx.storage.get_sequence(1).camera["focal_length_unknown"] is True

    spot_list = sample_dir / "01-clean.json"
    assert cli_main(["upload", str(spot_list), str(path), "--server", url, "--fov-deg", str(FOV)]) == 2
    spot, image, *_ = capsys.readouterr().out.splitlines()
    assert spot.startswith(f"{spot_list}: invalid (not sent): --fov-deg applies to image files")
    assert image.startswith(f"{path}: created id=2")
    row = ctx.storage.get_sequence(2)
    assert row.n_snapshots == 4 and row.spacecraft == "FOV-SAT"
    focal = (CAMERA.width / 2) / np.tan(np.radians(FOV) / 2)
    assert row.camera["focal_length_px"] == pytest.approx(focal, abs=0.01)
    assert "focal_length_unknown" not in row.camera
    assert ctx.storage.list_sequences(0, 10)[1] == 2  # the spot list was not sent


def test_upload_sends_a_folder_of_frames_as_one_pass_with_its_sidecar(live_server, tmp_path, capsys):
    from app.simulate import write_frames

    url, ctx = live_server
    write_frames(tmp_path / "in", 1, 9, "tubsat-752x582-20deg", form="png", name="png-pass", n_frames=3)
    folder = tmp_path / "in" / "png-pass"
    assert cli_main(["upload", str(folder), "--server", url]) == 0
    line, = capsys.readouterr().out.splitlines()
    assert line.startswith(f"{folder}: created id=1 sequence_id=png-pass")
    assert ctx.storage.get_sequence(1).n_snapshots == 3


def test_solve_prints_no_empty_table_for_an_image_without_stars_and_says_why(tmp_path, session_sky, capsys):
    """An overcast frame (noise only): the text answer says there is no candidate, instead of a table header with
    nothing under it, and the note says nothing stood out of the sky."""
    import io

    from PIL import Image

    out = io.BytesIO()
    Image.fromarray((40 + np.random.default_rng(4).normal(0, 2, (300, 400))).astype(np.uint8)).save(out, "PNG")
    path = tmp_path / "overcast.png"
    path.write_bytes(out.getvalue())
    assert cli_main(["solve", "--fov-deg", "20", str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"{path}: overcast  no_match  (attitudes at snapshot 0, the reference)"
    assert lines[1] == "  no candidate (the notes say why)"
    assert not any("RA deg" in line for line in lines)
    assert ("  note: overcast.png: no star-like source (nothing stands out of the sky's noise); a pattern needs at "
            "least 3") in lines


def test_the_field_of_view_line_says_where_the_search_began_only_when_one_was_given(bare_pass, session_sky, capsys):
    """The text answer's "field of view: ... fitted to the stars" adds "(one given is where the search began)" only
    when one was given (a photograph trial read it under a search that had none)."""
    path, _ = bare_pass
    assert cli_main(["solve", str(path)]) == 0
    (line,) = [x for x in capsys.readouterr().out.splitlines() if x.startswith("  field of view:")]
    assert line.endswith("fitted to the stars")
    assert cli_main(["solve", "--fov-deg", f"{FOV:.4f}", str(path)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [x for x in out if x.startswith("  field of view:")][0].endswith(
        "fitted to the stars (one given is where the search began)")
