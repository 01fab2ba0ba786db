"""Operator-trial polish of the console in a real Chromium: an upload line says what its queued search
found, sources at the sensor's edge keep their whole names on the canvases, and the search summary
reads as sentences.

The sample used throughout is ``07-single.json``: one snapshot, whose reference (and only) snapshot
has track T0 at x = 750 of a 752-pixel sensor, and whose first search note is an extraction note in
lower case ("single snapshot: ...").  Screenshots: test-artifacts/screenshots/polish-*.png.
"""

from __future__ import annotations

import json
import re
from decimal import ROUND_HALF_UP, Decimal

import httpx
import numpy as np

from test_console_sessions import (TIMEOUT_MS, console, expect_text, expect_visible, fresh_copy, open_sequence,
                                   upload_and_search)

STATUS_TEXT = {"no_match": "no match", "rejected": "no valid attitude"}  # as the console's statusText says


def inside(box: dict, width: float, height: float) -> bool:
    return box["x"] >= 0 and box["y"] >= 0 and box["x"] + box["w"] <= width and box["y"] + box["h"] <= height


# ---------------------------------------------------------------------------------------------------------

def test_an_upload_line_says_what_its_queued_search_found(server, api, new_page, tmp_path):
    """The line next to an uploaded file said ", search queued" for good; once the console reads the
    sequence searched, it says the search's outcome as the status badge does."""
    path = fresh_copy("07-single.json", "upload-line", tmp_path)
    name = path.stem  # the sequence id
    watched, _ = console(new_page, server)
    page = watched.page
    page.check("#auto-search")
    page.set_input_files("#file-input", [str(path)])
    item = page.locator(f".upload-item[data-file='{path.name}']")
    expect_text(item, r"stored as #\d+: \d+ pattern points, searched: (identified|ambiguous|no match)")
    assert "queued" not in item.inner_text()
    seq_id = int(re.search(r"#(\d+)", item.inner_text()).group(1))
    # The same outcome as the archive's and the opened sequence's badge (the upload opens it).
    status = api(f"/api/sequences/{seq_id}")["status"]
    assert item.locator(".search-state").inner_text() == f", searched: {STATUS_TEXT.get(status, status)}"
    expect_text(page.locator("#seq-title"), re.escape(name))
    # The badge follows when the console reloads the sequence opened (the line may have heard it first).
    expect_text(page.locator("#seq-status"), rf"^{re.escape(STATUS_TEXT.get(status, status))}$")
    page.evaluate("window.scrollTo(0, 0)")
    shot = watched.screenshot("polish-01-upload-searched")
    page.locator("#upload-card").screenshot(path=str(shot))
    assert watched.errors == []


def test_label_placement_keeps_labels_inside_the_canvas(server, new_page):
    """placeLabel (static/js/dom.js), the one rule of both canvases: upper right of the marker, to its
    left past the right edge, below it past the top."""
    watched, _ = console(new_page, server)
    place = ("(args) => import('/js/dom.js').then((m) => m.placeLabel(args))")
    common = {"r": 5, "w": 20, "h": 11, "width": 560, "gap": 3, "above": 1}
    assert watched.page.evaluate(place, {"cx": 100, "cy": 100, **common}) == {"x": 108, "y": 88, "w": 20, "h": 11}
    right = watched.page.evaluate(place, {"cx": 555, "cy": 100, **common})
    assert right == {"x": 527, "y": 88, "w": 20, "h": 11}           # left of the circle (555 - 5 - 3 - 20)
    top = watched.page.evaluate(place, {"cx": 100, "cy": 4, **common})
    assert top == {"x": 108, "y": 12, "w": 20, "h": 11}             # below the circle (4 + 5 + 3)
    corner = watched.page.evaluate(place, {"cx": 555, "cy": 4, **common})
    assert corner == {"x": 527, "y": 12, "w": 20, "h": 11}
    assert all(inside(b, 560, 434) for b in (right, top, corner))
    assert watched.errors == []


def test_a_track_at_the_sensor_edge_keeps_its_name_on_the_player(server, api, new_page, tmp_path):
    """T0 of 07-single sits at x = 750 of 752 sensor pixels: its name was drawn past the player canvas's
    right edge (cut off); it is drawn whole, to the left of its circle."""
    path = fresh_copy("07-single.json", "edge-label", tmp_path)
    name = path.stem
    seq_id = api("/api/sequences", "POST", raw=path.read_bytes())["id"]
    detail = api(f"/api/sequences/{seq_id}")
    track = detail["extraction"]["tracks"][0]
    assert track["id"] == 0 and track["xy"][0][0] >= 749  # the sample's source at the right edge
    watched, _ = console(new_page, server)
    page = watched.page
    open_sequence(page, seq_id, name)
    page.wait_for_function("JSON.parse(document.getElementById('player-canvas').dataset.labels || '[]')"
                           ".some((l) => l.text === 'T0')", timeout=TIMEOUT_MS)
    canvas = page.locator("#player-canvas")
    width, height = page.evaluate("(() => { const c = document.getElementById('player-canvas'); "
                                  "return [c.width, c.height]; })()")
    labels = json.loads(canvas.get_attribute("data-labels"))
    assert labels and all(inside(label, width, height) for label in labels), labels
    # T0's name is left of its source's circle (of radius 6.5 at most), where the canvas shows it.
    [label] = [label for label in labels if label["text"] == "T0"]
    cx = (track["xy"][0][0] + 0.5) * width / detail["camera"]["width"]
    assert label["x"] + label["w"] <= cx - 6.5 + 0.5
    lit = page.evaluate("""(b) => {
        const data = document.getElementById('player-canvas').getContext('2d')
          .getImageData(Math.floor(b.x), Math.floor(b.y), Math.ceil(b.w), b.h).data;
        let n = 0;
        for (let i = 0; i < data.length; i += 4) if (Math.max(data[i], data[i + 1], data[i + 2]) > 100) n++;
        return n; }""", label)
    assert lit >= 10, f"no text drawn in T0's label box {label}"
    canvas.scroll_into_view_if_needed()
    shot = watched.screenshot("polish-02-player-edge-label")
    canvas.screenshot(path=str(shot))
    assert watched.errors == []


def test_a_detection_at_the_canvas_corner_keeps_its_label_on_the_frame_panel(server, new_page):
    """A detection dragged to the frame panel's top-right corner: its label box was drawn past both edges;
    it is drawn inside the canvas."""
    from app.camera import CAMERAS
    from app.simulate import frames_fits_bytes, simulate_frames

    camera = CAMERAS["tubsat-752x582-20deg"]
    frames, times, _ = simulate_frames(np.random.default_rng(519), camera, n_frames=3, trail=True)
    data = frames_fits_bytes(frames, times, camera=camera, spacecraft="FRAME-SAT")
    r = httpx.post(server + "/api/frames", files=[("files", ("frames-edge.fits", data, "application/fits"))],
                   data={"sequence_id": "frames-edge"}, timeout=120)
    assert r.status_code == 201, r.text
    watched, _ = console(new_page, server)
    page = watched.page
    open_sequence(page, r.json()["id"], "frames-edge")
    page.wait_for_function("(() => { const c = document.getElementById('frame-canvas');"
                           " return c.dataset.image !== '' && JSON.parse(c.dataset.markers).some((m) => m.label); })()",
                           timeout=TIMEOUT_MS)
    canvas = page.locator("#frame-canvas")
    canvas.scroll_into_view_if_needed()
    width, height = page.evaluate("(() => { const c = document.getElementById('frame-canvas'); "
                                  "return [c.width, c.height]; })()")
    markers = json.loads(canvas.get_attribute("data-markers"))
    target = next(m for m in markers if m["kind"] == "detection" and m["label"])
    # Drag it to 4 canvas pixels from the top-right corner (the canvas is drawn 1:1 in CSS pixels).
    box = canvas.bounding_box()
    sx, sy = box["width"] / width, box["height"] / height
    page.mouse.move(box["x"] + target["x"] * sx, box["y"] + target["y"] * sy)
    page.mouse.down()
    page.mouse.move(box["x"] + (width - 4) * sx, box["y"] + 4 * sy, steps=6)
    page.mouse.up()
    page.wait_for_function(f"JSON.parse(document.getElementById('frame-canvas').dataset.markers).some((m) =>"
                           f" m.source === {target['source']} && m.kind === 'detection' && m.x > {width - 10})",
                           timeout=TIMEOUT_MS)
    moved = next(m for m in json.loads(canvas.get_attribute("data-markers"))
                 if m["kind"] == "detection" and m["source"] == target["source"])
    assert moved["y"] < 10
    assert inside(moved["label"], width, height), moved
    assert moved["label"]["x"] + moved["label"]["w"] < moved["x"] and moved["label"]["y"] > moved["y"]
    # Every label of a detection whose centre is on the canvas stays on it.
    on_canvas = [m for m in json.loads(canvas.get_attribute("data-markers"))
                 if m["kind"] == "detection" and m["label"] and 0 <= m["x"] <= width and 0 <= m["y"] <= height]
    assert all(inside(m["label"], width, height) for m in on_canvas), on_canvas
    shot = watched.screenshot("polish-03-frame-corner-label")
    canvas.screenshot(path=str(shot))
    assert watched.errors == []


def test_the_search_summary_reads_as_sentences(server, api, new_page, tmp_path):
    """The notes of a search followed the summary's full stop in lower case, joined by semicolons
    ("...). single snapshot: ...; 5698 bright_pair hypotheses ..."): each is a sentence now."""
    path = fresh_copy("07-single.json", "summary", tmp_path)
    name = path.stem
    seq_id = api("/api/sequences", "POST", raw=path.read_bytes())["id"]
    search = api(f"/api/sequences/{seq_id}/search", "POST", body={"method": "bright_pair"})
    assert search["notes"][0].startswith("single snapshot: ")  # the sample's lower-case first note
    watched, _ = console(new_page, server)
    page = watched.page
    open_sequence(page, seq_id, name)
    summary = page.locator("#search-summary")
    expect_text(summary, r"\(pattern version \d+\)\. Single snapshot: nothing to track against, every source is a "
                         r"pattern point\. \d+ bright_pair hypotheses from \d+ pattern features?")
    text = summary.inner_text()
    notes = text.split(")", 1)[1]
    assert "; " not in notes and text.endswith("."), text
    # One sentence per note, each starting with a capital or a number.
    sentences = re.split(r"(?<=\.) (?=\S)", notes.lstrip(". "))
    assert len(sentences) == len(search["notes"]), sentences
    assert all(re.match(r"[A-Z0-9]", s) for s in sentences), sentences
    summary.scroll_into_view_if_needed()
    shot = watched.screenshot("polish-04-search-summary")
    page.locator("#search-summary").screenshot(path=str(shot))
    assert watched.errors == []


def test_the_gap_to_rank_1_is_signed(server, api, new_page, tmp_path):
    """Ranks follow the matches first, so a rank below 1 can have a smaller deviation: 06-sparse with a point
    picked by hand at (700, 40) gives ranks whose gap to rank 1 is negative, which the table showed as
    "+-272″"."""
    seq_id = api("/api/sequences", "POST", raw=fresh_copy("06-sparse.json", "gap", tmp_path).read_bytes())["id"]
    ref = api(f"/api/sequences/{seq_id}")["extraction"]["reference_snapshot"]
    api(f"/api/sequences/{seq_id}/pattern", "PUT", body={"manual_points": [{"snapshot": ref, "x": 700.0, "y": 40.0}]})
    api(f"/api/sequences/{seq_id}/search", "POST", body={})
    gaps = {v["rank"]: v["deviation_gap_arcsec"] for v in api(f"/api/sequences/{seq_id}/review")["candidates"]}
    assert min(gaps.values()) < 0 < max(gaps.values())
    watched, _ = console(new_page, server)
    page = watched.page
    open_sequence(page, seq_id, "06-sparse-gap")
    for rank, gap in gaps.items():
        # JavaScript's toFixed(0): the exact binary value rounded half up (Python's format rounds half to even).
        whole = Decimal(abs(gap)).quantize(Decimal(1), rounding=ROUND_HALF_UP)
        shown = "-" if rank == 1 else f"{'+' if gap >= 0 else '-'}{whole}″"
        expect_text(page.locator(f"#candidate-rows tr[data-rank='{rank}'] td").last, f"^{re.escape(shown)}$")
    # The point picked by hand is "hand 0" in the candidate's matches too, as in the table and the sky chart.
    expect_text(page.locator("#cand-matches"), r"(^| · )hand 0 → ")
    watched.screenshot("polish-05-signed-gap")


def test_a_search_by_another_method_says_it_replaces_the_identified_candidates(server, api, new_page, tmp_path):
    """An operator trial searched an identified sequence by triangle features "for a second opinion": its
    answer (no match) replaced the bright-pair candidates and the status in every console.  Before the
    click, the console now says that it will."""
    seq_id, search = upload_and_search(api, fresh_copy("02-ghosts-hot-pixels.json", "replaces", tmp_path))
    assert search["status"] == "identified" and search["method"] == "bright_pair"
    watched, _ = console(new_page, server)
    page = watched.page
    open_sequence(page, seq_id, "02-ghosts-hot-pixels-replaces")
    page.select_option("#search-method", "bright_pair")
    expect_visible(page.locator("#search-replaces"), False)
    page.select_option("#search-method", "tf")
    expect_text(page.locator("#search-replaces"),
                rf"^Searching by triangle features replaces the identified candidates of search #{search['search_id']} "
                r"\(bright pairs\): the sequence's status becomes what it finds\.$")
    watched.screenshot("polish-06-search-replaces")
    page.select_option("#search-method", "bright_pair")
    expect_visible(page.locator("#search-replaces"), False)


def test_the_snapshot_players_names_never_overlap(server, api, new_page, tmp_path):
    """03-jupiter has a double star (T3 and T8, 2.5 px apart) whose two names the player drew over each other:
    in every snapshot each name has a place of its own, on the canvas."""
    seq_id, _ = upload_and_search(api, fresh_copy("03-jupiter.json", "labels", tmp_path))
    n = len(api(f"/api/sequences/{seq_id}")["telemetry"]["snapshots"])
    watched, _ = console(new_page, server)
    page = watched.page
    open_sequence(page, seq_id, "03-jupiter-labels")
    canvas = page.locator("#player-canvas")
    width, height = (int(canvas.get_attribute(k)) for k in ("width", "height"))
    page.locator("#snapshot-slider").fill("0")
    for k in range(n):
        expect_text(page.locator("#snapshot-label"), rf"^snapshot {k} ")
        labels = json.loads(canvas.get_attribute("data-labels"))
        assert labels and all(inside(lab, width, height) for lab in labels)
        overlapping = [(a["text"], b["text"]) for i, a in enumerate(labels) for b in labels[i + 1:]
                       if a["x"] < b["x"] + b["w"] and b["x"] < a["x"] + a["w"]
                       and a["y"] < b["y"] + b["h"] and b["y"] < a["y"] + a["h"]]
        assert not overlapping, (k, overlapping)
        if k + 1 < n:
            page.click("#step-fwd")
