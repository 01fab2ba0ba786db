"""The console says when a sequence's time was assumed (issue 26 item 1): a real frame uploaded without a
time is listed with no time, and its header, player and candidate facts say its time is assumed; a frame
uploaded with a time says nothing of the kind.

Screenshots: test-artifacts/screenshots/times-*.png.
"""

from __future__ import annotations

import re
from pathlib import Path

import httpx

from test_console_frames import expect_text, open_console, open_sequence

REAL_FRAMES = Path(__file__).resolve().parents[2].parent / "shared" / "real-frames"


def upload_real(server: str, sequence_id: str, **fields) -> dict:
    data = (REAL_FRAMES / "feb16-2.png").read_bytes()
    r = httpx.post(server + "/api/frames", files=[("files", ("feb16-2.png", data, "image/png"))],
                   data={"fov_deg": "13.266", "sequence_id": sequence_id, **fields}, timeout=120)
    assert r.status_code == 201, r.text
    search = httpx.post(f"{server}/api/sequences/{r.json()['id']}/search", json={"method": "bright_pair"}, timeout=120)
    assert search.status_code == 200 and search.json()["status"] == "identified", search.text
    return r.json()


def test_a_sequence_whose_time_was_assumed_says_so_where_its_time_is_shown(server, new_page):
    assumed = upload_real(server, "times-assumed")
    known = upload_real(server, "times-known", time="2018-02-16T06:00:00Z")
    watched = open_console(new_page, server)
    page = watched.page

    open_sequence(page, assumed["id"], "times-assumed")
    item = page.locator(f"#sequence-list li[data-id='{assumed['id']}'] .sub")
    expect_text(item, r"· no time$")
    expect_text(page.locator("#seq-meta"), r"1 snapshot with no time \(assumed: the frames carried no time")
    expect_text(page.locator("#player-caption"), re.escape("2000-01-01T12:00:00.000Z (assumed: the frames carried"))
    expect_text(page.locator("#search-summary"), r"No time: solved at epoch J2000\.0 without aberration")
    expect_text(page.locator("#cand-facts"), re.escape("2000-01-01T12:00:00.000Z (assumed"))
    watched.screenshot("times-01-assumed")

    open_sequence(page, known["id"], "times-known")
    expect_text(page.locator("#seq-meta"), r"1 snapshot from 2018-02-16 06:00:00Z")
    expect_text(page.locator(f"#sequence-list li[data-id='{known['id']}'] .sub"), r"2018-02-16 06:00")
    expect_text(page.locator("#player-caption"), r"^2018-02-16T06:00:00\.000Z$")
    expect_text(page.locator("#cand-facts"), r"2018-02-16T06:00:00\.000Z")
    assert "assumed" not in page.locator("#seq-meta").inner_text()
    assert "assumed" not in page.locator("#cand-facts").inner_text()
    assert watched.errors == []
