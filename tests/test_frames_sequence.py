"""Frames of one pass -> one Sequence that identifies (issue 15), from the library and from the command line."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from app.attitude import angle_between
from app.camera import CAMERAS
from app.frames import frames_to_sequence, parse_sidecar
from app.identification import solve_sequence
from app.simulate import frame_png_bytes, frames_fits_bytes, frames_sidecar, simulate_frames, true_optics, write_frames
from app.telemetry.errors import TelemetryError

REPO = Path(__file__).resolve().parent.parent
CAMERA = CAMERAS["tubsat-752x582-20deg"]


@pytest.fixture(scope="module")
def rendered():
    """Four frames, a trail in one, the true focal length 3 % off the declared one and 1 % distortion."""
    true_camera = true_optics(CAMERA, focal_error=0.03, k1=0.1)
    frames, times, truth = simulate_frames(np.random.default_rng(77), CAMERA, n_frames=4, trail=True,
                                           true_camera=true_camera, sequence_id="pass-77")
    return frames, times, truth


def _boresight_error_deg(solved, truth) -> float:
    candidate = solved.solution.candidates[0]
    R_true = np.asarray(truth["rotation_matrices"][solved.extraction.reference])
    return float(np.degrees(angle_between(np.asarray(candidate.rotation_matrix)[2], R_true[2])))


def test_a_multi_extension_fits_is_one_sequence_that_identifies(rendered, sky):
    frames, times, truth = rendered
    data = frames_fits_bytes(frames, times, camera=CAMERA, sequence_id="pass-77", spacecraft="SIM-1")
    result = frames_to_sequence([("pass-77.fits", data)])
    sequence = result.sequence
    assert (sequence.sequence_id, sequence.spacecraft, len(sequence.snapshots)) == ("pass-77", "SIM-1", 4)
    assert [s.time for s in sequence.snapshots] == times
    assert sequence.extra["frames"]["content_sha256"] == result.frames_sha256
    solved = solve_sequence(sequence, sky)
    assert solved.solution.status == "identified"
    assert _boresight_error_deg(solved, truth) < 0.1


def test_a_png_set_with_a_field_of_view_is_one_sequence_that_identifies(rendered, sky):
    frames, times, truth = rendered
    names = [f"img-{i}.png" for i in range(len(frames))]
    sidecar = frames_sidecar(names, times, CAMERA, sequence_id="png-77")
    del sidecar["camera"]
    true_fov = true_optics(CAMERA, focal_error=0.03).fov_deg[0]
    sidecar["fov_deg"] = true_fov * 1.04  # the field of view known to 4 %
    files = [(n, frame_png_bytes(f)) for n, f in reversed(list(zip(names, frames)))]  # any order
    sequence = frames_to_sequence(files, sidecar=parse_sidecar(json.dumps(sidecar))).sequence
    assert [s.time for s in sequence.snapshots] == times
    solved = solve_sequence(sequence, sky)
    assert solved.solution.status == "identified"
    assert _boresight_error_deg(solved, truth) < 0.1


@pytest.mark.parametrize("change, location", [
    (lambda s: s["frames"].pop(), "img-3.png.time"),
    (lambda s: s["frames"][1].update(time="yesterday"), "sidecar.frames[1].time"),
    (lambda s: s.update(fov_deg=500), "sidecar.fov_deg"),
    (lambda s: s["camera"].update(width=640), "sidecar.camera.width"),
    (lambda s: s["camera"].update(focal_length_px=-3.0), "sidecar.camera.focal_length_px"),
    (lambda s: s["frames"].append({"file": "missing.png", "time": "2024-01-01T00:00:00Z"}), "sidecar.frames"),
    (lambda s: s["frames"][2].update(time=s["frames"][1]["time"]), ".time"),
])
def test_sidecar_and_time_problems_are_located(rendered, change, location):
    frames, times, _ = rendered
    names = [f"img-{i}.png" for i in range(len(frames))]
    sidecar = frames_sidecar(names, times, CAMERA)
    change(sidecar)
    with pytest.raises(TelemetryError) as err:
        frames_to_sequence([(n, frame_png_bytes(f)) for n, f in zip(names, frames)],
                           sidecar=parse_sidecar(json.dumps(sidecar)))
    assert any(location in p.location for p in err.value.problems), err.value.problems


def test_frames_of_different_sizes_are_refused(rendered):
    frames, times, _ = rendered
    names = ["a.png", "b.png"]
    sidecar = parse_sidecar(json.dumps(frames_sidecar(names, times[:2], CAMERA)))
    with pytest.raises(TelemetryError) as err:
        frames_to_sequence([("a.png", frame_png_bytes(frames[0])), ("b.png", frame_png_bytes(frames[1][:-10]))],
                           sidecar=sidecar)
    assert err.value.problems[0].location == "b.png" and "one camera" in err.value.problems[0].message


def _cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "app", *args], cwd=REPO, capture_output=True, text=True, timeout=300)


def test_the_command_line_solves_fits_files_and_folders_and_says_invalid_for_bad_images(tmp_path):
    write_frames(tmp_path, 1, 5, "narrow-1024x1024-12deg", form="fits", name="fits-pass")
    write_frames(tmp_path, 1, 6, "liebe-576x604-30deg", form="png", name="png-pass", trail=True)
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")
    bad_folder = tmp_path / "bad-folder"
    bad_folder.mkdir()
    (bad_folder / "a.png").write_bytes((tmp_path / "png-pass" / "frame-00.png").read_bytes())
    (bad_folder / "frames.json").write_text('{"frames": [{"file": "a.png", "time": "not a time"}]}')
    run = _cli("solve", "--json", str(tmp_path / "fits-pass.fits"), str(tmp_path / "png-pass"),
               str(tmp_path / "broken.png"), str(bad_folder))
    assert run.returncode == 2, run.stderr[-2000:]
    assert "Traceback" not in run.stderr
    docs = [json.loads(line) for line in run.stdout.splitlines()]
    assert [d["status"] for d in docs] == ["identified", "identified", "invalid", "invalid"]
    for doc, name in zip(docs[:2], ("fits-pass", "png-pass")):
        truth = json.loads((tmp_path / f"{name}.truth.json").read_text())
        R = np.asarray(truth["rotation_matrices"][doc["reference_snapshot"]])
        error = np.degrees(angle_between(np.asarray(doc["candidates"][0]["rotation_matrix"])[2], R[2]))
        assert error < 0.1
    assert docs[2]["error"].startswith(f"{tmp_path / 'broken.png'}: invalid image: broken.png: not a readable image")
    # A sidecar found beside the images (not given) is named in its problems: a user who never wrote one asks which.
    assert docs[3]["error"].startswith(f"{bad_folder}: invalid image: frames.json.frames[0].time")
    (tmp_path / "alone.png").write_bytes((tmp_path / "png-pass" / "frame-00.png").read_bytes())
    (tmp_path / "alone.frames.json").write_bytes(b"")
    empty = _cli("solve", "--json", str(tmp_path / "alone.png"))
    said = json.loads(empty.stdout)["error"]
    assert said == f"{tmp_path / 'alone.png'}: invalid image: alone.frames.json: the file is empty"
    extract = _cli("extract", "--json", str(tmp_path / "fits-pass.fits"))
    assert extract.returncode == 0 and json.loads(extract.stdout)["status"] == "ok"


def test_a_frame_with_too_few_star_like_sources_says_what_it_saw_and_why_they_were_set_aside():
    """An overcast sky (nothing stands out of its noise) and two broad glows with one hot pixel (detected, and set
    aside as extended and as a hot pixel): the frames block says so in words an operator reads as "nothing like a
    star here", beside the search's "the pattern has 0 point(s)"; a frame with stars says nothing of the kind."""
    import io
    import re

    from PIL import Image

    def png(pixels) -> bytes:
        out = io.BytesIO()
        Image.fromarray(np.clip(pixels, 0, 255).astype(np.uint8)).save(out, format="PNG")
        return out.getvalue()

    y, x = np.mgrid[0:300, 0:400]
    rng = np.random.default_rng(3)
    overcast = 40.0 + rng.normal(0, 2, x.shape)
    glows = 20.0 + rng.normal(0, 2, x.shape)
    for cx, cy in ((100, 150), (280, 100)):
        glows += 150 * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * 25.0 ** 2))
    glows[60, 60] = 250  # one pixel alone: a hot pixel

    def notes(name, pixels):
        sequence = frames_to_sequence([(name, png(pixels))], fov_deg=20.0).sequence
        assert sequence.snapshots[0].n_sources == 0
        return [n for n in sequence.extra["frames"].get("notes", []) if "star-like" in n]

    assert notes("overcast.png", overcast) == [
        "overcast.png: no star-like source (nothing stands out of the sky's noise); a pattern needs at least 3"]
    (said,) = notes("glows.png", glows)
    found = re.fullmatch(r"glows\.png: no star-like source \((\d+) blob\(s\) detected, set aside as "
                         r"extended \((\d+)\), hot_pixel \(1\)\); a pattern needs at least 3", said)
    assert found, said
    blobs, extended = int(found[1]), int(found[2])
    assert blobs >= 3 and extended == blobs - 1  # each glow one blob or more, every one set aside
    pass_of_two = frames_to_sequence([("a.png", png(overcast)), ("b.png", png(overcast[::-1]))], fov_deg=20.0)
    assert [n for n in pass_of_two.sequence.extra["frames"]["notes"] if "star-like" in n] == [
        "a.png: no star-like source (nothing stands out of the sky's noise); a pattern needs at least 3; 1 other "
        "frame(s) kept fewer than 3 too"]
    starry = frames_to_sequence([("stars.png", frame_png_bytes(simulate_frames(np.random.default_rng(5), CAMERA,
                                                                                n_frames=1)[0][0]))], fov_deg=20.0)
    assert not [n for n in starry.sequence.extra["frames"].get("notes", []) if "star-like" in n]
