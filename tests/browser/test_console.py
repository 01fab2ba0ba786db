"""End-to-end tests of the operator console and the 3D view in a real Chromium (issue 5 acceptance).

Truth comes from the simulator's files (``*.truth.json``): which track is a
star, and the attitude of the reference snapshot, against which the
confirmed APM's quaternion is checked through the CCSDS annex F2 formula
written out again here.
"""

from __future__ import annotations

import json
import re
import urllib.error

import numpy as np
import pytest

from pathlib import Path

SAMPLES = Path(__file__).resolve().parents[2] / "sample_telemetry"
SAMPLE = SAMPLES / "02-ghosts-hot-pixels.json"
TRUTH = json.loads((SAMPLES / "02-ghosts-hot-pixels.truth.json").read_text())
TIMEOUT_MS = 20_000


def expect_text(locator, pattern: str, timeout: int = TIMEOUT_MS) -> None:
    from playwright.sync_api import expect

    expect(locator).to_contain_text(re.compile(pattern), timeout=timeout)


def wait_for_state(read, wanted, timeout_s: float = TIMEOUT_MS / 1000, interval_s: float = 0.1):
    """Poll ``read()`` until it returns ``wanted`` or ``timeout_s`` passes; the last value read.

    The browser's writes reach the server asynchronously, so a test reads the
    server's state only once it has arrived (or the deadline says it never will).
    """
    import time

    deadline = time.monotonic() + timeout_s
    value = read()
    while value != wanted and time.monotonic() < deadline:
        time.sleep(interval_s)
        value = read()
    return value


def track_to_take_out(detail: dict) -> int:
    """A pattern track whose sightings are not all stars (a ghost, a hot pixel), else the shortest track."""
    kinds: dict[int, set] = {}
    for i, row in enumerate(detail["extraction"]["sources"]):
        for j, track in enumerate(row):
            if track is not None:
                kinds.setdefault(track, set()).add(TRUTH["sources"][i][j]["kind"])
    in_pattern = [p for p in detail["pattern"]["points"] if p["track"] is not None]
    not_star = [p["track"] for p in in_pattern if kinds.get(p["track"], {"star"}) != {"star"}]
    if not_star:
        return not_star[0]
    return min(in_pattern, key=lambda p: (p["sightings"], p["track"]))["track"]


def rotation_from_apm(text: str) -> np.ndarray:
    """M_BA of the APM's (Q1, Q2, Q3, QC) by CCSDS 355.0 annex F2 (independent of app.ccsds)."""
    values = {k: float(v) for k, v in re.findall(r"^(Q1|Q2|Q3|QC)\s*=\s*(\S+)", text, flags=re.MULTILINE)}
    q1, q2, q3, qc = (values[k] for k in ("Q1", "Q2", "Q3", "QC"))
    return np.array([
        [q1 * q1 - q2 * q2 - q3 * q3 + qc * qc, 2 * (q1 * q2 + q3 * qc), 2 * (q1 * q3 - q2 * qc)],
        [2 * (q1 * q2 - q3 * qc), -q1 * q1 + q2 * q2 - q3 * q3 + qc * qc, 2 * (q2 * q3 + q1 * qc)],
        [2 * (q1 * q3 + q2 * qc), 2 * (q2 * q3 - q1 * qc), -q1 * q1 - q2 * q2 + q3 * q3 + qc * qc],
    ])


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a @ b.T) - 1) / 2, -1, 1))))


def canvas_point(page, canvas_id: str, x: float, y: float) -> tuple[float, float]:
    """Viewport coordinates of sensor pixel (x, y) on the player canvas (pixel centres at +0.5), through the
    mapping the player drew with (the sensor fitted into the canvas, ``data-mapping``, canvas pixels)."""
    canvas = page.locator(f"#{canvas_id}")
    box = canvas.bounding_box()
    mapping = json.loads(canvas.get_attribute("data-mapping"))
    css = box["width"] / int(canvas.get_attribute("width"))
    return (box["x"] + (mapping["ox"] + (x + 0.5) * mapping["scale"]) * css,
            box["y"] + (mapping["oy"] + (y + 0.5) * mapping["scale"]) * css)


def test_invalid_upload_shows_located_problems(server, new_page, tmp_path):
    watched = new_page()
    page = watched.page
    bad = tmp_path / "bad-telemetry.json"
    bad.write_text(json.dumps({"format": "tubsat-snapshots/1", "sequence_id": "bad",
                               "camera": "tubsat-752x582-20deg", "snapshots": [{"time": "yesterday"}]}))
    page.goto(server + "/")
    page.set_input_files("#file-input", [str(bad)])
    item = page.locator(".upload-item[data-file='bad-telemetry.json']")
    expect_text(item, "invalid telemetry")
    problems = item.locator(".problems li")
    assert problems.count() >= 1
    # Each problem names where it is: the location the server gave, e.g. snapshots[0].time.
    assert any(re.match(r"snapshots\[0\]", problems.nth(k).locator("code").inner_text())
               for k in range(problems.count()))
    watched.screenshot("00-upload-error")
    # The only console error allowed is Chromium's own report of the refused (422) upload request.
    unexpected = [e for e in watched.errors if "status of 422" not in e]
    assert unexpected == []


def test_a_single_located_problem_is_shown_once(server, new_page, tmp_path):
    """The server's reason quotes a lone problem ("f.json: invalid telemetry: LOCATION: MESSAGE") and
    lists it too: the console says which file and what kind of refusal, then the problem, once."""
    watched = new_page()
    page = watched.page
    bad = tmp_path / "one-problem.json"
    bad.write_text(json.dumps({"format": "tubsat-snapshots/1", "sequence_id": "one", "camera": "tubsat-752x582-20deg",
                               "snapshots": [{"index": 0, "time": "2026-01-01T00:00:00Z",
                                              "sources": [{"x": 812, "y": 20, "brightness": 5}]}]}))
    page.goto(server + "/")
    page.set_input_files("#file-input", [str(bad)])
    item = page.locator(".upload-item[data-file='one-problem.json']")
    expect_text(item.locator(".problems"), "outside the sensor")
    problem = item.locator(".problems li")
    assert problem.count() == 1
    text = item.locator(".error").inner_text()
    assert text.count("outside the sensor") == 1, text
    assert "invalid telemetry" in item.locator(".error > div").inner_text()
    assert problem.locator("code").inner_text() == "snapshots[0].sources[0].x"
    watched.screenshot("00-upload-one-problem")
    assert [e for e in watched.errors if "status of 422" not in e] == []


def test_uploads_of_the_same_sequence_are_told_apart(server, api, new_page, tmp_path):
    """The same CSV in other line endings is a second sequence: its upload line says which stored upload
    has the same spacecraft and sequence id.  A file stored before without a search, dropped again with
    "search new uploads automatically" ticked, is searched now."""
    text = (SAMPLES / "08-csv.csv").read_text()
    assert "# sequence_id: 08-csv\n" in text
    text = text.replace("# sequence_id: 08-csv\n", "# sequence_id: told-apart\n")
    unix, dos = tmp_path / "told-apart.csv", tmp_path / "told-apart-crlf.csv"
    unix.write_text(text)
    dos.write_bytes(text.replace("\n", "\r\n").encode())
    watched = new_page()
    page = watched.page
    page.goto(server + "/")
    page.wait_for_selector("body[data-ready='1']")
    page.uncheck("#auto-search")
    page.set_input_files("#file-input", [str(unix)])
    first = page.locator(".upload-item[data-file='told-apart.csv']")
    expect_text(first, r"stored as #\d+")
    first_id = int(re.search(r"#(\d+)", first.inner_text()).group(1))
    assert "search queued" not in first.inner_text()
    page.check("#auto-search")
    page.set_input_files("#file-input", [str(dos)])
    second = page.locator(".upload-item[data-file='told-apart-crlf.csv']")
    expect_text(second.locator(".upload-note"), rf'another stored upload \(#{first_id} "told-apart.csv"\) has the '
                                                 "same spacecraft and sequence id")
    page.set_input_files("#file-input", [str(unix)])
    # The line says the search was queued, and once the console sees the sequence searched, its outcome
    # (the search can finish before the line is looked at: either words say a search was asked for).
    again = page.locator(".upload-item[data-file='told-apart.csv']").first
    expect_text(again, rf"already stored as #{first_id}, (never searched: search queued|searched: )")
    assert wait_for_state(lambda: api(f"/api/sequences/{first_id}")["search"] is not None, True) is True
    expect_text(again, rf"already stored as #{first_id}, searched: (identified|ambiguous|no match)")
    watched.screenshot("00-upload-same-sequence")
    assert watched.errors == []


def test_an_upload_refused_without_located_problems_shows_the_reason_alone(server, new_page, tmp_path):
    """A file over the size limit is refused whole (413, no problem list): the line next to the file
    says why, and nothing else (it once printed a stray "null" under the reason)."""
    from app.config import Settings

    watched = new_page()
    page = watched.page
    huge = tmp_path / "huge.json"
    huge.write_bytes(b" " * (Settings().max_upload_bytes + 1))
    page.goto(server + "/")
    page.set_input_files("#file-input", [str(huge)])
    item = page.locator(".upload-item[data-file='huge.json']")
    expect_text(item, "larger than the limit")
    assert item.locator(".error").inner_text().strip() == item.locator(".error > div").inner_text().strip()
    assert "null" not in item.inner_text()
    assert [e for e in watched.errors if "status of 413" not in e] == []


def test_operator_flow(server, api, new_page):
    watched = new_page()
    page = watched.page
    page.goto(server + "/")
    expect_text(page.locator("#health"), "ready")
    # This console's own selection (issue 13: every console has its session).
    view = f"/api/view?session={page.evaluate('document.body.dataset.session')}"

    # Upload: the file is stored and opened.
    page.set_input_files("#file-input", [str(SAMPLE)])
    expect_text(page.locator(f".upload-item[data-file='{SAMPLE.name}']"), r"(stored|already stored) as #\d+")
    expect_text(page.locator("#seq-title"), "02-ghosts-hot-pixels")
    seq_id = int(re.search(r"#(\d+)", page.locator(".upload-item").first.inner_text()).group(1))
    expect_text(page.locator("#sequence-list"), "02-ghosts-hot-pixels")
    watched.screenshot("01-uploaded")

    detail = api(f"/api/sequences/{seq_id}")
    track = track_to_take_out(detail)
    version = detail["pattern"]["version"]

    # Click the track's source in the player (reference snapshot shown): it leaves the pattern ...
    ref = detail["extraction"]["reference_snapshot"]
    sighting = detail["extraction"]["tracks"][track]
    k = sighting["snapshots"].index(ref) if ref in sighting["snapshots"] else None
    if k is None:  # not seen in the reference snapshot: step the player to its first sighting
        page.locator("#snapshot-slider").fill(str(sighting["snapshots"][0]))
        k = 0
    x, y = sighting["xy"][k]
    page.mouse.click(*canvas_point(page, "player-canvas", x, y))
    expect_text(page.locator("#pattern-caption"), rf"version {version + 1} ")
    assert api(f"/api/sequences/{seq_id}")["pattern"]["definition"]["exclude_tracks"] == [track]
    # ... and clicking it again puts it back.
    page.mouse.click(*canvas_point(page, "player-canvas", x, y))
    expect_text(page.locator("#pattern-caption"), rf"version {version + 2} ")
    assert api(f"/api/sequences/{seq_id}")["pattern"]["definition"]["exclude_tracks"] == []

    # Take it out through its row in the pattern table.
    page.locator(f"#pattern-rows tr[data-track='{track}'] input[type=checkbox]").uncheck()
    expect_text(page.locator("#pattern-caption"), rf"version {version + 3} ")
    current = api(f"/api/sequences/{seq_id}")["pattern"]
    assert current["definition"]["exclude_tracks"] == [track]
    assert track not in [p["track"] for p in current["points"]]
    assert page.locator(f"#pattern-rows tr[data-track='{track}']").get_attribute("class") == "out"
    watched.screenshot("02-pattern-edited")

    # Search: rank 1 of N is the true attitude of the reference snapshot.
    page.click("#search")
    # The upload was searched automatically already (pattern version 1): wait for this search's result.
    expect_text(page.locator("#search-summary"), rf"\(pattern version {version + 3}\)")
    expect_text(page.locator("#cand-rank"), r"rank 1 of \d+")
    search = api(f"/api/sequences/{seq_id}")["search"]
    n = len(search["candidates"])
    assert n >= 2, "the flow needs at least two candidates to step through"
    assert search["pattern_version"] == version + 3
    expect_text(page.locator("#cand-facts"), rf"1 of {n}")
    facts = page.locator("#cand-facts").inner_text()
    ra, dec = (float(v) for v in re.search(r"([\d.]+)°, (-?[\d.]+)°", facts).groups())
    truth_ra, truth_dec, _ = TRUTH["radec_roll_deg"][search["reference_snapshot"]]
    assert abs(ra - truth_ra) < 0.05 and abs(dec - truth_dec) < 0.05
    # The answer's precision in a reader's terms beside the seed's deviation (which counts unmatched points too).
    best = search["candidates"][0]
    rms, matched = re.search(r"([\d.]+)″ RMS over the (\d+) matched stars", facts).groups()
    assert abs(float(rms) - best["rms_arcsec"]) <= 0.05 and int(matched) == best["n_matched"]
    page.mouse.move(0, 0)
    watched.screenshot("03-candidate-rank1")

    # Next / Prev buttons and the arrow keys; this console's view state follows.
    page.click("#cand-next")
    expect_text(page.locator("#cand-rank"), rf"rank 2 of {n}")
    assert api(view)["rank"] == 2
    watched.screenshot("04-candidate-rank2")
    page.click("#cand-prev")
    expect_text(page.locator("#cand-rank"), rf"rank 1 of {n}")
    page.locator("body").focus()
    page.keyboard.press("ArrowRight")
    expect_text(page.locator("#cand-rank"), rf"rank 2 of {n}")
    page.keyboard.press("ArrowLeft")
    expect_text(page.locator("#cand-rank"), rf"rank 1 of {n}")
    assert api(view)["rank"] == 1

    # The magnitude slider redraws with fainter stars (the server lists more of them).
    page.locator("#mag-slider").fill("7")
    page.locator("#mag-slider").dispatch_event("change")
    expect_text(page.locator("#mag-label"), r"7\.0")
    # The label changes before the console's PUT /api/view reaches the server: wait for the server's state.
    assert wait_for_state(lambda: api(view)["mag"], 7.0) == 7.0

    # Confirm rank 1.
    page.fill("#operator", "Test Operator")
    page.fill("#comment", "browser test")
    page.click("#confirm")
    expect_text(page.locator("#confirmed"), r"Confirmed: attitude #\d+")
    expect_text(page.locator("#seq-status"), "confirmed")
    attitude_id = int(re.search(r"attitude #(\d+)", page.locator("#confirmed").inner_text()).group(1))
    assert api(f"/api/sequences/{seq_id}/review")["confirmation"]["comment"] == "browser test"
    # Stored with this confirmation: the field is empty again, not carried into a later one.
    assert page.locator("#comment").input_value() == ""

    # The attitude list has it, with the operator, and its APM downloads.
    row = page.locator(f"#attitude-list tr[data-id='{attitude_id}']")
    expect_text(row, "Test Operator")
    candidate = search["candidates"][0]
    expect_text(row, f"{candidate['ra_deg']:.3f}")
    watched.screenshot("05-confirmed")
    with page.expect_download() as info:
        row.locator("a.apm-link").click()
    apm = open(info.value.path(), encoding="utf-8").read()
    assert re.search(r"^CCSDS_APM_VERS\s*=\s*2\.0\s*$", apm, flags=re.MULTILINE)
    rotation = rotation_from_apm(apm)
    # The candidate's matrix is stored to 10 digits, the APM quaternion to its own precision.
    assert np.allclose(rotation, np.array(candidate["rotation_matrix"]), atol=1e-6)
    truth_rotation = np.array(TRUTH["rotation_matrices"][search["reference_snapshot"]])
    assert angle_deg(rotation, truth_rotation) < 0.05
    assert watched.errors == []


def test_3d_view_follows_the_console_that_opened_it(server, api, new_page):
    doc = api("/api/sequences", "POST", raw=(SAMPLES / "04-big-dipper.json").read_bytes())
    seq_id = doc["id"]
    search = api(f"/api/sequences/{seq_id}/search", "POST", body={})
    n = len(search["candidates"])
    assert n >= 2

    # A console opens the sequence from its work queue.
    console = new_page()
    console.page.goto(server + "/")
    session = console.page.evaluate("document.body.dataset.session")
    view = f"/api/view?session={session}"
    console.page.fill("#operator", "Console Operator")
    console.page.locator("#operator").dispatch_event("change")
    console.page.fill("#filter-search", "04-big-dipper")
    console.page.locator(f"#sequence-list li[data-id='{seq_id}']").click()
    expect_text(console.page.locator("#seq-title"), "04-big-dipper")
    expect_text(console.page.locator("#cand-rank"), rf"rank 1 of {n}")
    assert (api(view)["sequence"], api(view)["rank"]) == (seq_id, 1)
    assert api(view)["operator"] == "Console Operator"  # the 3D view confirms under the console's name
    # A rank the latest search does not have is refused with its location.
    with pytest.raises(urllib.error.HTTPError) as refused:
        api(view, "PUT", body={"rank": n + 1})
    assert refused.value.code == 422
    assert json.loads(refused.value.read())["problems"][0]["location"] == "body.rank"

    # Its 3D tab makes the 3D view draw this console's selection.
    info = api("/api/viewer")
    assert info["available"] and info["url"].startswith("http://127.0.0.1:")
    console.page.click("#tab-3d")
    expect_text(console.page.locator("#viewer-note"), "Draws this console's selection")
    expect_text(console.page.locator("#viewer-note"), re.escape(info["url"]))
    assert api("/api/view")["session"] == session  # requests without a session mean the 3D view's
    frame = console.page.frame_locator("#viewer-frame")
    expect_text(frame.locator("body"), r"Rank 1 of", timeout=40_000)
    console.screenshot("06-console-3d-tab")

    viewer = new_page()
    viewer.page.goto(f"{info['url']}?session={session}")
    expect_text(viewer.page.locator("body"), rf"Rank 1 of {n}", timeout=40_000)
    # Its Operator field took the console's name (viser's text fields have no label element to find them by).
    viewer.page.wait_for_function("() => [...document.querySelectorAll('input, textarea')]"
                                  ".some((i) => i.value === 'Console Operator')", timeout=10_000)
    viewer.page.wait_for_timeout(1500)  # let the software renderer draw the sphere before the screenshot
    viewer.screenshot("07-viewer-rank1")
    viewer.page.get_by_role("button", name="Next").click()
    expect_text(viewer.page.locator("body"), rf"Rank 2 of {n}")
    assert wait_for_state(lambda: api(view)["rank"], 2) == 2

    # The console follows its own session: back on its sequence tab it shows rank 2.
    console.page.click("#tab-work")
    expect_text(console.page.locator("#cand-rank"), rf"rank 2 of {n}")
    expect_text(console.page.locator("#cand-facts"), rf"2 of {n}")
    console.screenshot("08-console-after-3d-next")
    viewer.page.wait_for_timeout(1000)
    viewer.screenshot("09-viewer-rank2")

    # Another console opening its 3D tab gets a view of its own (tests/browser/test_viewer_per_console.py); the
    # 3D view at the bare address draws the console that opened its 3D tab last.
    other = new_page()
    other.page.goto(server + "/")
    other.page.click("#tab-3d")
    expect_text(other.page.locator("#viewer-note"), "Draws this console's selection")
    expect_text(console.page.locator("#viewer-note"), "Draws this console's selection")
    assert api("/api/view")["session"] == other.page.evaluate("document.body.dataset.session")
    assert console.errors == [] and viewer.errors == [] and other.errors == []


def test_api_docs_render_without_internet(server, new_page):
    """/docs serves Swagger UI from the application itself: every operation is listed offline."""
    watched = new_page()
    page = watched.page
    external = []
    page.on("request", lambda request: external.append(request.url)
            if not request.url.startswith(server) and not request.url.startswith("data:") else None)
    page.goto(server + "/docs")
    page.wait_for_selector(".opblock", timeout=20000)
    paths = {page.locator(".opblock-summary-path").nth(k).inner_text().replace("\u200b", "")
             for k in range(page.locator(".opblock-summary-path").count())}
    assert {"/api/sequences", "/api/sequences/{seq_id}/search", "/api/attitudes/{attitude_id}/apm"} <= paths
    assert external == []
    watched.screenshot("07-api-docs")
    assert watched.errors == []
