"""The attitude timeline page (static/timeline.html): opened from the console's link, it plots every stored
attitude where its value and epoch put it (read back from the SVG's scales and compared with the stored
searches and confirmations), marks the gap, the overlap and the jump, and a click on a point opens that
sequence in the console.

Screenshots: test-artifacts/screenshots/timeline-*.png and /tmp/timeline.png.
"""

from __future__ import annotations

import re
import shutil
import sys
from datetime import datetime
from pathlib import Path

import httpx
import pytest

from test_console_frames import expect_text, open_console

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from test_timeline import trajectory_uploads  # noqa: E402 - the simulated trajectory of the API tests

SPACECRAFT = "TL-BROWSER"
PANEL_VALUES = {"ra": "ra_deg", "dec": "dec_deg", "roll": "roll_deg"}


@pytest.fixture(scope="module")
def uploaded(server):
    """The five trajectory uploads of TL-BROWSER, searched; tlb-1 confirmed by ann, tlb-earth rejected by bob."""
    ids = {}
    for key, filename, text, _ in trajectory_uploads(SPACECRAFT, prefix="tlb"):
        r = httpx.post(f"{server}/api/sequences?filename={filename}", content=text.encode(), timeout=60,
                       headers={"Content-Type": "text/csv" if filename.endswith(".csv") else "application/json"})
        assert r.status_code == 201, r.text
        ids[key] = r.json()["id"]
        r = httpx.post(f"{server}/api/sequences/{ids[key]}/search", json={"method": "bright_pair"}, timeout=60)
        assert r.status_code == 200, r.text
    r = httpx.post(f"{server}/api/sequences/{ids['s1']}/confirm", json={"rank": 1, "operator": "ann"}, timeout=60)
    assert r.status_code == 201, r.text
    r = httpx.post(f"{server}/api/sequences/{ids['earth']}/reject", json={"operator": "bob", "reason": "Earth"},
                   timeout=60)
    assert r.status_code == 201, r.text
    return ids


def _plotted(page, key: str) -> list[dict]:
    """The points of panel ``key`` read back through the chart's scales: (sequence, value, epoch in ms)."""
    return page.evaluate("""key => {
        const svg = document.getElementById('tl-svg'), g = svg.querySelector(`.tl-panel[data-key='${key}']`);
        const n = (e, a) => Number(e.dataset[a]);
        return [...g.querySelectorAll('circle.tl-point')].map(c => ({
            sequence: Number(c.dataset.sequence), status: c.getAttribute('class'),
            value: n(g, 'y0') + (n(g, 'bottom') - Number(c.getAttribute('cy'))) / (n(g, 'bottom') - n(g, 'top'))
                   * (n(g, 'y1') - n(g, 'y0')),
            epoch: n(svg, 't0') + (Number(c.getAttribute('cx')) - n(svg, 'left')) / (n(svg, 'right') - n(svg, 'left'))
                   * (n(svg, 't1') - n(svg, 't0'))}));
    }""", key)


def _ms(text: str) -> float:
    return datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp() * 1000


def test_the_timeline_plots_the_stored_attitudes_and_a_click_opens_that_sequence(server, api, uploaded, new_page):
    watched = open_console(new_page, server, 1280, 1050)
    page = watched.page
    page.click("#timeline-link")
    page.wait_for_url(re.compile(r"/timeline\.html"))
    page.wait_for_selector("body[data-ready='1']")
    page.select_option("#tl-spacecraft", SPACECRAFT)
    page.click("#tl-form button[type=submit]")
    expect_text(page.locator("#tl-summary"), rf"^{SPACECRAFT}: 5 sequences .* 4 with an attitude · 1 gap, 1 overlap, "
                                             r"1 jump$")
    assert f"spacecraft={SPACECRAFT}" in page.url

    # The stored attitudes, read from the sequences themselves: the confirmation's, else the search's rank 1.
    stored = {}
    for key, seq_id in uploaded.items():
        detail = api(f"/api/sequences/{seq_id}")
        if key != "earth":
            chosen = detail["confirmation"]["candidate"] if key == "s1" else detail["search"]["candidates"][0]
            stored[seq_id] = (chosen, detail["search"]["reference_time"])
    for key, field in PANEL_VALUES.items():
        plotted = _plotted(page, key)
        assert sorted(p["sequence"] for p in plotted) == sorted(stored), key
        for p in plotted:
            candidate, epoch = stored[p["sequence"]]
            assert p["value"] == pytest.approx(candidate[field], abs=1e-6), (key, p)
            assert p["epoch"] == pytest.approx(_ms(epoch), abs=1e-3), (key, p)
    statuses = {p["sequence"]: p["status"] for p in _plotted(page, "ra")}
    assert "status-confirmed" in statuses[uploaded["s1"]] and "status-identified" in statuses[uploaded["s3"]]
    # The lane holds all five, the rejected one as a cross; the flags are drawn and listed.
    assert page.locator(".tl-seq").count() == 5
    assert page.locator(f".tl-seq.status-rejected[data-sequence='{uploaded['earth']}'] path.tl-cross").count() == 1
    assert page.locator(f"line.tl-jump[data-later='{uploaded['s3']}']").count() == 1
    assert page.locator(f"rect.tl-gap[data-later='{uploaded['earth']}']").count() == 1
    assert page.locator(f"rect.tl-overlap[data-later='{uploaded['s2csv']}']").count() == 1
    expect_text(page.locator("#tl-flags .flag-jump"), rf"jump: #{uploaded['s3']} tlb-3 is 1\.9\d* deg from")
    path = watched.screenshot("timeline-01-chart")
    shutil.copyfile(path, "/tmp/timeline.png")

    # Hovering says what the point is; clicking opens it in the console.
    point = page.locator(f".tl-panel[data-key='dec'] circle.tl-point[data-sequence='{uploaded['s3']}']")
    point.hover()
    expect_text(page.locator("#tl-detail"), rf"^#{uploaded['s3']} tlb-3 · identified \(search \d+, bright_pair\)")
    point.click()
    page.wait_for_url(re.compile(r"/\?session="))
    page.wait_for_selector("body[data-ready='1']")
    expect_text(page.locator("#seq-title"), "tlb-3")
    watched.screenshot("timeline-02-opened")
    assert watched.errors == []


def test_a_bad_range_is_said_on_the_page(server, uploaded, new_page):
    watched = new_page()
    page = watched.page
    page.goto(f"{server}/timeline.html?spacecraft={SPACECRAFT}&start=2021-03-04T06:00:00Z&end=2021-03-04T05:00:00Z")
    page.wait_for_selector("body[data-ready='1']")
    expect_text(page.locator("#tl-summary"), r"the time range is empty: end 2021-03-04T05:00:00\.000Z is not after start")
    assert page.locator("#tl-svg").count() == 0
    page.fill("#tl-start", "")
    page.fill("#tl-end", "")
    page.fill("#tl-limit", "2")
    page.click("#tl-form button[type=submit]")
    expect_text(page.locator("#tl-summary"), r"2 sequences \(the newest 2 sequences of 5 with a time\)")
    assert page.locator(".tl-seq").count() == 2
    # The console refuses the bad range in the browser's console log (a 422): only page errors would count.
    assert [e for e in watched.errors if "422" not in e] == []
