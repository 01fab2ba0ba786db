"""The camera in the console (issue 11): a candidate's fitted optics beside it, and the spacecraft's
calibration with the residual map over the sensor, made from the archive with one click."""

from __future__ import annotations

import json
import re

import numpy as np

from app.camera import CAMERAS
from app.simulate import simulate_sequence, true_optics
from conftest import SCREENSHOTS
from test_console_sessions import SAMPLES, console, expect_text, expect_visible, open_sequence, wait_for

CAMERA = CAMERAS["tubsat-752x582-20deg"]


def test_calibrating_from_the_console_shows_the_fitted_camera_and_the_residual_map(server, api, new_page, tmp_path):
    spacecraft = "CONSOLE-OPTICS-SAT"
    true_camera = true_optics(CAMERA, focal_error=0.03, k1=0.01 / CAMERA.corner_radius ** 2)
    ids = []
    for i in range(4):
        sequence, _ = simulate_sequence(np.random.default_rng([21, i]), CAMERA, "nominal", true_camera=true_camera,
                                        sequence_id=f"console-optics-{i}")
        doc = sequence.to_json_dict()
        doc["spacecraft"] = spacecraft
        seq_id = api("/api/sequences", "POST", raw=json.dumps(doc).encode())["id"]
        assert api(f"/api/sequences/{seq_id}/search", "POST", body={})["status"] == "identified"
        ids.append(seq_id)

    watched, _ = console(new_page, server)
    page = watched.page
    open_sequence(page, ids[0], "console-optics-0")
    # The candidate's optics beside it: a focal length ~3 % longer than declared, used.
    expect_text(page.locator("#cand-facts"), r"optics")
    facts = page.locator("#cand-facts").inner_text()
    f_shown = float(re.search(r"\bf ([0-9.]+) ± ", facts).group(1))
    assert abs(f_shown / true_camera.focal_length_px - 1) < 0.002 and "used" in facts

    expect_visible(page.locator("#calibration-card"))
    expect_text(page.locator("#calibration-facts"), "No calibration yet")
    page.fill("#operator", "Calibration Operator")
    page.locator("#calibrate-button").click()
    expect_text(page.locator("#calibration-facts"), r"version 1 · Calibration Operator")
    stored = wait_for(lambda: api(f"/api/spacecraft/{spacecraft}/camera"), lambda doc: doc["version"] == 1)
    assert abs(stored["camera"]["focal_length_px"] / true_camera.focal_length_px - 1) < 1e-3
    expect_visible(page.locator("#residual-canvas"))
    expect_text(page.locator("#residual-legend"), "orange with the declared camera")
    # The map drew something: pixels of the "before" colour on the canvas.
    orange = page.evaluate("""() => {
        const c = document.getElementById('residual-canvas'), d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let n = 0; for (let i = 0; i < d.length; i += 4) if (d[i] > 200 && d[i + 1] > 120 && d[i + 1] < 170 && d[i + 2] < 80) n++;
        return n; }""")
    assert orange > 50
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    page.locator("#calibration-card").screenshot(path=str(SCREENSHOTS / "30-calibration-card.png"))
    watched.screenshot("31-console-with-calibration")


def test_a_refused_calibration_says_why_once(server, api, new_page, tmp_path):
    """Too few identified sequences: the refusal's reason is shown whole, and once (its one located
    problem repeats the reason word for word, which the console does not print again)."""
    doc = json.loads((SAMPLES / "01-clean.json").read_text())
    doc.update(sequence_id="too-few-for-a-calibration", spacecraft="TOO-FEW-SAT")
    seq_id = api("/api/sequences", "POST", raw=json.dumps(doc).encode())["id"]
    assert api(f"/api/sequences/{seq_id}/search", "POST", body={})["status"] == "identified"
    watched, _ = console(new_page, server)
    page = watched.page
    open_sequence(page, seq_id, "too-few-for-a-calibration")
    expect_visible(page.locator("#calibration-card"))
    page.locator("#calibrate-button").click()
    expect_text(page.locator("#toast"), "at least 3 sequences")
    said = page.locator("#toast").get_attribute("title")
    assert said.count("at least 3 sequences") == 1, said
    assert page.locator("#toast").evaluate("e => e.scrollWidth <= e.clientWidth && e.scrollHeight <= e.clientHeight")
    assert [e for e in watched.errors if "status of 422" not in e] == []
