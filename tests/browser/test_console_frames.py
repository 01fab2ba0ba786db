"""The console's frame panel (issue 15 item 5) in a real Chromium: a rendered pass of frames uploaded,
opened, its frame shown with one marker per reported source, zoomed, panned, stepped, clicked.

Screenshots: test-artifacts/screenshots/frames-*.png.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import httpx
import numpy as np

from app.camera import CAMERAS
from app.simulate import frame_png_bytes, frames_fits_bytes, frames_sidecar, simulate_frames

TIMEOUT_MS = 20_000
CAMERA = CAMERAS["tubsat-752x582-20deg"]


def expect_text(locator, pattern: str, timeout: int = TIMEOUT_MS) -> None:
    from playwright.sync_api import expect

    expect(locator).to_contain_text(re.compile(pattern), timeout=timeout)


def upload_pass(server: str, sequence_id: str, seed: int) -> dict:
    frames, times, _ = simulate_frames(np.random.default_rng(seed), CAMERA, n_frames=4, trail=True)
    data = frames_fits_bytes(frames, times, camera=CAMERA, spacecraft="FRAME-SAT")
    r = httpx.post(server + "/api/frames", files=[("files", (f"{sequence_id}.fits", data, "application/fits"))],
                   data={"sequence_id": sequence_id}, timeout=120)
    assert r.status_code == 201, r.text
    return r.json()


def open_console(new_page, server: str, width: int = 1280, height: int = 800):
    watched = new_page(width, height)
    watched.page.goto(server + "/")
    watched.page.wait_for_selector("body[data-ready='1']")
    return watched


def open_sequence(page, seq_id: int, name: str) -> None:
    page.fill("#filter-search", name)
    page.locator(f"#sequence-list li[data-id='{seq_id}']").click()
    expect_text(page.locator("#seq-title"), re.escape(name))


def markers(page) -> list[dict]:
    return json.loads(page.locator("#frame-canvas").get_attribute("data-markers") or "[]")


def wait_for_frame(page, snapshot: int) -> None:
    """Until the frame panel shows the image of ``snapshot``."""
    page.wait_for_function(
        f"(() => {{ const c = document.getElementById('frame-canvas');"
        f" return c.dataset.snapshot === '{snapshot}' && c.dataset.image.endsWith('/frames/{snapshot}.png'); }})()",
        timeout=TIMEOUT_MS)


def to_page(page, marker: dict) -> tuple[float, float]:
    """Page coordinates of a marker (its canvas coordinates, through the canvas's CSS size)."""
    page.locator("#frame-canvas").scroll_into_view_if_needed()
    box = page.locator("#frame-canvas").bounding_box()
    size = page.evaluate("(() => { const c = document.getElementById('frame-canvas'); return [c.width, c.height]; })()")
    return box["x"] + marker["x"] * box["width"] / size[0], box["y"] + marker["y"] * box["height"] / size[1]


def canvas_pixels_hash(page) -> str:
    return page.evaluate("document.getElementById('frame-canvas').toDataURL().slice(-4000)")


def test_the_frame_panel_shows_zooms_follows_and_edits(server, api, new_page):
    doc = upload_pass(server, "frames-console", 515)
    seq_id = doc["id"]
    detail = api(f"/api/sequences/{seq_id}")
    frames = api(f"/api/sequences/{seq_id}/frames")["frames"]
    assert len(frames) == 4

    watched = open_console(new_page, server)
    page = watched.page
    open_sequence(page, seq_id, "frames-console")
    card = page.locator("#frame-card")
    assert card.is_visible()
    index = int(page.locator("#frame-canvas").get_attribute("data-snapshot"))
    wait_for_frame(page, index)
    # Named by its index in the pass (as the API's frames and reference_snapshot are), its position in words.
    assert index == detail["extraction"]["reference_snapshot"]
    expect_text(page.locator("#frame-caption"), rf"^snapshot {index} \({index + 1} of 4, reference\) · 752×582 px")

    # One detection marker per reported source, each labelled with its track as the player names it.
    shown = markers(page)
    detections = [m for m in shown if m["kind"] == "detection"]
    sources = detail["telemetry"]["snapshots"][index]["sources"]
    assert len(detections) == len(sources) > 0
    assert sorted(m["source"] for m in detections) == list(range(len(sources)))
    tracks = detail["extraction"]["sources"][index]
    assert all(m["track"] == tracks[m["source"]] for m in detections)
    assert any(m["kind"] == "rejected" for m in shown)  # the camera's hot pixels, unmapped yet
    # The markers sit on the sensor positions: the canvas is the sensor scaled to fit.
    box = page.locator("#frame-canvas").bounding_box()
    zoom = float(page.locator("#frame-canvas").get_attribute("data-zoom"))
    assert abs(zoom - min(box["width"] / 752, box["height"] / 582)) < 0.02
    watched.screenshot("frames-01-opened", full_page=True)

    # The tooltip of a detection names its track; of a rejected blob, why.
    some = next(m for m in detections if m["track"] is not None)
    page.mouse.move(*to_page(page, some))
    expect_text(page.locator("#frame-tip"), rf"T{some['track']}\b")
    # ... and its source by its index in the snapshot, as the extraction and the errors number it.
    expect_text(page.locator("#frame-tip"), rf"· source {some['source']} at ")

    # Zoom: the + button, then the wheel about a source; the markers grow apart.
    before = markers(page)
    page.click("#frame-zoom-in")
    zoomed = float(page.locator("#frame-canvas").get_attribute("data-zoom"))
    assert zoomed > zoom * 1.4
    # Clicking the button scrolled it into view, which can leave the canvas's middle below the window (a
    # wheel there reaches nothing): the canvas back in view first.
    page.locator("#frame-canvas").scroll_into_view_if_needed()
    box = page.locator("#frame-canvas").bounding_box()
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page.mouse.wheel(0, -400)
    page.wait_for_function(f"Number(document.getElementById('frame-canvas').dataset.zoom) > {zoomed * 1.2}")
    more = float(page.locator("#frame-canvas").get_attribute("data-zoom"))
    assert more <= 32
    watched.screenshot("frames-02-zoomed")
    # Drag to pan: the markers move with the mouse.
    first = {(m["kind"], m.get("source")): m for m in markers(page) if m["kind"] == "detection"}
    box = page.locator("#frame-canvas").bounding_box()
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(cx, cy)
    page.mouse.down()
    page.mouse.move(cx + 60, cy + 30, steps=4)
    page.mouse.up()
    moved = {(m["kind"], m.get("source")): m for m in markers(page) if m["kind"] == "detection"}
    common = set(first) & set(moved)
    assert common and all(moved[k]["x"] > first[k]["x"] + 40 for k in common)
    page.click("#frame-fit")
    assert abs(float(page.locator("#frame-canvas").get_attribute("data-zoom")) - zoom) < 1e-3
    assert len(markers(page)) == len(before)

    # The snapshot player steps: the frame panel follows, with another image and its own sources.
    picture = canvas_pixels_hash(page)
    page.click("#step-fwd")
    following = (index + 1) % 4
    wait_for_frame(page, following)
    expect_text(page.locator("#frame-caption"), rf"^snapshot {following} \({following + 1} of 4\) · 752×582 px")
    assert canvas_pixels_hash(page) != picture
    detections = [m for m in markers(page) if m["kind"] == "detection"]
    assert len(detections) == len(detail["telemetry"]["snapshots"][following]["sources"])
    page.evaluate("window.scrollTo(0, 0)")  # a full-page shot of a scrolled page repeats the sticky header
    watched.screenshot("frames-03-next-snapshot", full_page=True)

    # A click on a tracked detection takes its track out of the pattern, as a click in the player does.
    in_pattern = {p["track"] for p in detail["pattern"]["points"] if p["track"] is not None}
    target = next(m for m in detections if m["track"] in in_pattern)
    page.mouse.click(*to_page(page, target))
    expect_text(page.locator("#pattern-caption"), r"version 2 \(edit")
    after = api(f"/api/sequences/{seq_id}")
    assert target["track"] in after["pattern"]["definition"]["exclude_tracks"]
    # The panel keeps the snapshot and draws the track dashed (out of the pattern).
    wait_for_frame(page, following)
    assert not watched.errors, watched.errors


def test_another_sequence_of_frames_opens_whole_not_at_the_last_ones_zoom(server, api, new_page):
    """A photograph trial zoomed into one pass and opened another of the same size: it showed a corner of it at the
    first one's zoom. A sequence opened is fitted whole."""
    first, second = upload_pass(server, "zoom-first", 521), upload_pass(server, "zoom-second", 522)
    watched = open_console(new_page, server)
    page = watched.page
    canvas = page.locator("#frame-canvas")
    open_sequence(page, first["id"], "zoom-first")
    wait_for_frame(page, int(canvas.get_attribute("data-snapshot")))
    fitted = float(canvas.get_attribute("data-zoom"))
    page.click("#frame-zoom-in")
    page.click("#frame-zoom-in")
    assert float(canvas.get_attribute("data-zoom")) > 1.9 * fitted
    open_sequence(page, second["id"], "zoom-second")
    wait_for_frame(page, int(canvas.get_attribute("data-snapshot")))
    page.wait_for_function(f"Math.abs(Number(document.getElementById('frame-canvas').dataset.zoom) - {fitted}) < 1e-6")
    assert not watched.errors, watched.errors


def test_the_frame_panel_fits_1024_pixel_screens_and_stays_away_from_spot_lists(server, api, new_page):
    doc = upload_pass(server, "frames-narrow", 516)
    watched = open_console(new_page, server, 1024, 768)
    page = watched.page
    open_sequence(page, doc["id"], "frames-narrow")
    index = int(page.locator("#frame-canvas").get_attribute("data-snapshot"))
    wait_for_frame(page, index)
    card = page.locator("#frame-card").bounding_box()
    canvas = page.locator("#frame-canvas").bounding_box()
    assert canvas["x"] >= card["x"] and canvas["x"] + canvas["width"] <= card["x"] + card["width"] + 0.5
    assert page.evaluate("document.documentElement.scrollWidth") <= 1024
    watched.screenshot("frames-04-1024px", full_page=True)
    # A spot-list upload has no frame panel.
    sample = Path(__file__).resolve().parents[2] / "sample_telemetry" / "01-clean.json"
    spot = api("/api/sequences", "POST", raw=sample.read_bytes())
    open_sequence(page, spot["id"], spot["sequence"]["sequence_id"])
    assert page.locator("#frame-card").is_hidden()
    assert not watched.errors, watched.errors


def all_sequences(api) -> list[dict]:
    return api("/api/sequences?limit=1000&order=newest")["items"]


def test_dropped_frames_and_their_sidecar_are_one_pass(server, api, new_page, tmp_path):
    """Images dropped on the upload box go as one pass (POST /api/frames) with their frames.json; a
    spot list in the same drop still goes on its own, and the sidecar is never taken for one."""
    frames, times, _ = simulate_frames(np.random.default_rng(517), CAMERA, n_frames=2, trail=True)
    names = ["frame-00.png", "frame-01.png"]
    paths = []
    for name, frame in zip(names, frames):
        (tmp_path / name).write_bytes(frame_png_bytes(frame))
        paths.append(tmp_path / name)
    sidecar = tmp_path / "frames.json"
    sidecar.write_text(json.dumps(frames_sidecar(names, times, CAMERA, sequence_id="frames-dropped",
                                                 spacecraft="DROP-SAT")))
    spot = Path(__file__).resolve().parents[2] / "sample_telemetry" / "01-clean.json"
    before = {s["id"] for s in all_sequences(api)}

    watched = open_console(new_page, server)
    page = watched.page
    assert page.locator("#upload-fov").is_visible()
    page.set_input_files("#file-input", [str(p) for p in paths] + [str(sidecar), str(spot)])
    item = page.locator(".upload-item[data-kind='frames']")
    expect_text(item, r"2 frames → #\d+ frames-dropped, \d+ sources")
    assert item.count() == 1 and "frames.json" in item.locator(".name").inner_text()
    expect_text(page.locator(f".upload-item[data-file='{spot.name}']"), r"(stored|already stored) as #\d+")
    # The sidecar has no line of its own: it went with the images, not as a spot list.
    assert page.locator(".upload-item[data-file='frames.json']").count() == 0
    seq_id = int(re.search(r"#(\d+)", item.inner_text()).group(1))

    spot_ids = {s["id"] for s in all_sequences(api) if s["filename"] == spot.name}
    new = [s for s in all_sequences(api) if s["id"] not in before and s["id"] not in spot_ids]
    assert [s["id"] for s in new] == [seq_id]
    assert new[0]["sequence_id"] == "frames-dropped" and new[0]["n_snapshots"] == 2
    assert new[0]["spacecraft"] == "DROP-SAT"
    assert not any((s["filename"] or "").endswith("frames.json") for s in all_sequences(api))
    assert len(api(f"/api/sequences/{seq_id}/frames")["frames"]) == 2

    # The pass is opened (the last upload of the drop), with its frame panel.
    expect_text(page.locator("#seq-title"), "frames-dropped")
    assert page.locator("#frame-card").is_visible()
    wait_for_frame(page, int(page.locator("#frame-canvas").get_attribute("data-snapshot")))
    page.evaluate("window.scrollTo(0, 0)")
    shot = watched.screenshot("frames-05-upload")  # makes the folder; the card alone replaces the page
    page.locator("#upload-card").screenshot(path=str(shot))
    assert not watched.errors, watched.errors


def test_a_json_dropped_with_images_but_not_named_as_their_sidecar_says_how_one_is_named(server, api, new_page,
                                                                                          tmp_path):
    """An operator trial dropped sky.png with sky.json (its reference, not a sidecar): the JSON went as telemetry and
    failed with "snapshots: missing" alone. Its line now also says how a sidecar is named; a spot list dropped with
    the same images is stored as before (the hint only follows a JSON that failed)."""
    frames, times, _ = simulate_frames(np.random.default_rng(518), CAMERA, n_frames=1)
    image = tmp_path / "sky.png"
    image.write_bytes(frame_png_bytes(frames[0]))
    meant = tmp_path / "sky.json"
    meant.write_text(json.dumps(frames_sidecar(["sky.png"], times, CAMERA, sequence_id="sky-meant")))
    spot = Path(__file__).resolve().parents[2] / "sample_telemetry" / "01-clean.json"
    watched = open_console(new_page, server)
    page = watched.page
    page.set_input_files("#file-input", [str(image), str(meant), str(spot)])
    line = page.locator(".upload-item[data-file='sky.json']")
    expect_text(line, "invalid telemetry")
    expect_text(line.locator(".upload-note"), "a JSON is read as their sidecar only when named frames.json or "
                                              "IMAGE.frames.json \\(format tubsat-frames/1\\); this one was read as "
                                              "telemetry")
    spot_line = page.locator(f".upload-item[data-file='{spot.name}']")
    expect_text(spot_line, r"(stored|already stored) as #\d+")
    assert spot_line.locator(".upload-note").count() == 0
    expect_text(page.locator(".upload-item[data-kind='frames']"), r"1 frame → #\d+")
    # Chromium reports the refused upload (422) in the console; nothing else may be there.
    assert [e for e in watched.errors if "status of 422" not in e] == [], watched.errors


def test_photographs_chosen_together_are_so_many_photographs_each_identified(server, api, new_page, tmp_path):
    """Two photographs of two skies chosen at once (a photograph trial): they went up as one pass of a camera, every
    star a ghost, no match. Without a frames.json (and not FITS) each is its own upload, as `solve a.jpg b.jpg`
    takes them, and each is identified on its own sky."""
    names = []
    for seed, name in ((601, "sky-a.png"), (602, "sky-b.png")):
        frames, _, _ = simulate_frames(np.random.default_rng(seed), CAMERA, n_frames=1)
        (tmp_path / name).write_bytes(frame_png_bytes(frames[0]))
        names.append(name)
    before = {s["id"] for s in all_sequences(api)}
    watched = open_console(new_page, server)
    page = watched.page
    page.fill("#upload-fov", f"{CAMERA.fov_deg[0]:.4f}")
    page.set_input_files("#file-input", [str(tmp_path / n) for n in names])
    for name in names:
        line = page.locator(f".upload-item[data-kind='frames'][data-file='{name}']")
        expect_text(line, r"1 frame → #\d+ sky-[ab], \d+ sources, searched: identified", timeout=60_000)
    new = [s for s in all_sequences(api) if s["id"] not in before]
    assert sorted(s["sequence_id"] for s in new) == ["sky-a", "sky-b"]
    assert all(s["n_snapshots"] == 1 and s["status"] == "identified" for s in new), new
    assert not watched.errors, watched.errors


def test_a_frame_with_no_time_and_no_optics_is_stored_and_a_bad_field_of_view_is_located(server, api, new_page,
                                                                                         tmp_path):
    """Issue 26: a plain image (no sidecar, no time, no field of view) is stored, its time assumed and its field
    of view to be searched; a field of view out of range is refused at the field, and nothing is stored."""
    frames, _, _ = simulate_frames(np.random.default_rng(518), CAMERA, n_frames=1)
    png = tmp_path / "lonely.png"
    png.write_bytes(frame_png_bytes(frames[0]))
    before = {s["id"] for s in all_sequences(api)}

    watched = open_console(new_page, server)
    page = watched.page
    page.fill("#upload-fov", "500")
    page.set_input_files("#file-input", [str(png)])
    item = page.locator(".upload-item[data-kind='frames']")
    problems = item.locator(".problems li")
    problems.first.wait_for(timeout=TIMEOUT_MS)
    locations = [problems.nth(k).locator("code").inner_text() for k in range(problems.count())]
    assert locations == ["field of view"], locations  # the console names its own field
    watched.screenshot("frames-06-upload-error")
    assert {s["id"] for s in all_sequences(api)} == before

    page.fill("#upload-fov", "")
    again = tmp_path / "lonely-again.png"  # a new choice of file (the same one again would not be a change)
    again.write_bytes(png.read_bytes())
    page.set_input_files("#file-input", [str(again)])
    expect_text(page.locator(".upload-item[data-file='lonely-again.png']"), r"1 frame → #\d+")
    new = [s for s in all_sequences(api) if s["id"] not in before]
    assert len(new) == 1
    stored = api(f"/api/sequences/{new[0]['id']}")
    assert stored["camera"]["focal_length_unknown"] is True
    # Searched as it came: the candidate says the field of view the stars gave, and where the centre points.
    expect_text(page.locator("#seq-title"), "lonely")
    facts = page.locator("#cand-facts")
    expect_text(facts, r"field of view\s*\d+\.\d{3}°")
    shown = float(re.search(r"field of view\s*(\d+\.\d+)°", facts.inner_text()).group(1))
    assert abs(shown / CAMERA.fov_deg[0] - 1) < 0.01, shown
    expect_text(facts, r"image centre")
    assert "declared camera kept" not in facts.inner_text()  # no camera was declared: the optics are found ones
    watched.screenshot("frames-07-fov-found")
    # The only console error allowed is Chromium's own report of the refused (422) request.
    assert [e for e in watched.errors if "status of 422" not in e] == []


def test_a_photograph_stored_turned_is_shown_upright_and_the_frame_panel_says_so(server, api, new_page, tmp_path):
    """A phone held upright stores its picture turned and says so in EXIF ``Orientation`` (6): the frame is read
    upright, the panel shows it at the upright size, and says why (the notes of the frames' reading were
    only among a search's notes)."""
    import io

    from PIL import Image

    frames, _, _ = simulate_frames(np.random.default_rng(519), CAMERA, n_frames=1)
    exif = Image.Exif()
    exif[0x0112] = 6  # turn the stored image a quarter clockwise to see it
    stream = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(np.rot90(frames[0].astype(np.uint16), 1))).save(stream, format="PNG",
                                                                                           exif=exif)
    r = httpx.post(server + "/api/frames", files=[("files", ("phone.png", stream.getvalue(), "image/png"))],
                   data={"fov_deg": f"{CAMERA.fov_deg[0]:.3f}"}, timeout=120)
    assert r.status_code == 201, r.text
    seq_id = r.json()["id"]

    watched = open_console(new_page, server)
    page = watched.page
    open_sequence(page, seq_id, "phone")
    wait_for_frame(page, 0)
    expect_text(page.locator("#frame-caption"), r"· 752×582 px")
    expect_text(page.locator("#frame-note"), r"phone\.png: turned upright as its EXIF Orientation \(6\) says")
    assert len(markers(page)) >= 10  # its stars, found in the upright picture
    page.locator("#frame-card").scroll_into_view_if_needed()
    watched.screenshot("frames-08-turned-upright")
    assert watched.errors == []
