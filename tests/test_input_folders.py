"""What a folder named on the command line holds (app.filenames.passes_of_folder, the one rule for `solve`, `extract`
and `upload`): one pass of a camera when it comes with its frames.json or as FITS frames, each photograph alone
otherwise, spot lists after them, the frames' sidecars never read as spot lists.

A folder of unrelated photographs read as one pass made every star a ghost and the folder no match (25 real frames
solved as `solve ../shared/real-frames`: one answer, no match); they are now so many answers."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from app.camera import CAMERAS
from app.cli.upload import FramePass, inputs as upload_inputs
from app.filenames import passes_of_folder
from app.simulate import frame_png_bytes, simulate_frames
from app.workflow.files import input_files

CAMERA = CAMERAS["tubsat-752x582-20deg"]


def _touch(folder: Path, *names: str) -> list[Path]:
    folder.mkdir(exist_ok=True)
    for name in names:
        (folder / name).write_bytes(b"x")
    return sorted(p for p in folder.iterdir())


def test_a_folder_is_one_pass_with_its_frames_json_or_as_fits_frames_and_else_each_photograph_alone(tmp_path):
    with_sidecar = _touch(tmp_path / "pass", "frames.json", "b.png", "a.png")
    assert passes_of_folder(with_sidecar) == [[tmp_path / "pass" / "a.png", tmp_path / "pass" / "b.png"]]
    fits = _touch(tmp_path / "fits", "f1.fits", "f2.fit.gz", "notes.csv")
    assert passes_of_folder(fits) == [[tmp_path / "fits" / "f1.fits", tmp_path / "fits" / "f2.fit.gz"]]
    photos = _touch(tmp_path / "photos", "b.jpg", "a.png", "c.tiff", "a.frames.json", "ref.json")
    assert passes_of_folder(photos) == [[tmp_path / "photos" / n] for n in ("a.png", "b.jpg", "c.tiff")]
    mixed = _touch(tmp_path / "mixed", "f1.fits", "a.jpg")
    assert passes_of_folder(mixed) == [[tmp_path / "mixed" / "a.jpg"], [tmp_path / "mixed" / "f1.fits"]]
    assert passes_of_folder(_touch(tmp_path / "none", "x.json")) == []


def test_solve_and_upload_take_the_same_inputs_from_a_folder(tmp_path):
    photos = tmp_path / "photos"
    _touch(photos, "b.jpg", "a.png", "a.frames.json", "ref.json", "x.truth.json")
    inputs, truth = input_files([str(photos)])
    # Each photograph, then the spot lists; a.png's own sidecar is read with it, never as a spot list.
    assert inputs == [str(photos / "a.png"), str(photos / "b.jpg"), str(photos / "ref.json")]
    assert truth == [str(photos / "x.truth.json")]
    sent, _ = upload_inputs([str(photos)])
    assert sent == [FramePass(photos / "a.png", (photos / "a.png",), photos / "a.frames.json"),
                    FramePass(photos / "b.jpg", (photos / "b.jpg",), None), photos / "ref.json"]
    one_pass = tmp_path / "pass"
    _touch(one_pass, "frames.json", "a.png", "b.png")
    assert input_files([str(one_pass)]) == ([str(one_pass)], [])
    sent, _ = upload_inputs([str(one_pass)])
    assert sent == [FramePass(one_pass, (one_pass / "a.png", one_pass / "b.png"), one_pass / "frames.json")]


def test_a_folder_of_two_photographs_of_two_skies_is_two_identified_answers(tmp_path, capsys, monkeypatch, sky):
    """End to end: `solve FOLDER` on two rendered frames of two skies and no frames.json, each given the field of
    view: two answers, each identified (one pass of both was no match, every star a ghost)."""
    from app.cli import main as cli_main

    monkeypatch.setattr("app.identification.Sky", lambda: sky)
    folder = tmp_path / "night"
    folder.mkdir()
    for seed, name in ((611, "sky-a.png"), (612, "sky-b.png")):
        frames, _, _ = simulate_frames(np.random.default_rng(seed), CAMERA, n_frames=1)
        (folder / name).write_bytes(frame_png_bytes(frames[0]))
    assert cli_main(["solve", "--json", "--fov-deg", f"{CAMERA.fov_deg[0]:.4f}", str(folder)]) == 0
    docs = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert [(Path(d["file"]).name, d["status"]) for d in docs] == [("sky-a.png", "identified"),
                                                                   ("sky-b.png", "identified")]
