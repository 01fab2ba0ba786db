"""The Frame panel's Annotated PNG (issue 26 item 6) in a real Chromium: the frame shown, annotated with
the candidate shown, downloads as the server draws it; an unsearched pass says why there is none.

Screenshots: test-artifacts/screenshots/annotated-01-panel.png, and the download as annotated-02-download.png.
"""

from __future__ import annotations

import io

import httpx
import numpy as np
from conftest import SCREENSHOTS
from PIL import Image
from test_console_frames import expect_text, open_console, open_sequence, upload_pass, wait_for_frame


def test_annotated_png_downloads_the_frame_shown_with_the_candidate_shown(server, api, new_page):
    searched = upload_pass(server, "annotated-console", 626)["id"]
    result = api(f"/api/sequences/{searched}/search", "POST", {"method": "bright_pair"})
    assert result["status"] == "identified"
    bare = upload_pass(server, "annotated-unsearched", 627)["id"]

    watched = open_console(new_page, server)
    page = watched.page
    open_sequence(page, searched, "annotated-console")
    index = int(page.locator("#frame-canvas").get_attribute("data-snapshot"))
    wait_for_frame(page, index)
    page.locator("#frame-card").scroll_into_view_if_needed()
    watched.screenshot("annotated-01-panel")
    with page.expect_download() as download:
        page.click("#frame-annotated")
    assert download.value.suggested_filename == f"sequence-{searched}-snapshot-{index}-rank-1.png"
    data = open(download.value.path(), "rb").read()
    (SCREENSHOTS / "annotated-02-download.png").write_bytes(data)
    image = Image.open(io.BytesIO(data))
    assert image.size == (752, 582) and image.mode == "RGB"
    served = httpx.get(f"{server}/api/sequences/{searched}/frames/{index}/annotated.png", params={"rank": 1},
                       timeout=60)
    assert served.status_code == 200
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(served.content))), np.asarray(image))

    open_sequence(page, bare, "annotated-unsearched")
    wait_for_frame(page, int(page.locator("#frame-canvas").get_attribute("data-snapshot")))
    page.click("#frame-annotated")
    expect_text(page.locator("#toast"), "No candidate to annotate the frame with: search the sequence first")
    assert not watched.errors, watched.errors
