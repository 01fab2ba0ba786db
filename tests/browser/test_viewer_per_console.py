"""One 3D view per console (issue 29): two consoles, each on its own sequence, each 3D view tab drawing its own
console's sequence and rank at once; a step or a confirmation in one view lands in its own console only.

The combined screenshot (console A's 3D tab | console B's 3D tab) goes to /tmp/viewer-two.png and
test-artifacts/screenshots/viewer-two.png.
"""

from __future__ import annotations

import re

import numpy as np
from PIL import Image

from test_console_sessions import expect_text, expect_visible, fresh_copy, operator_on, upload_and_search

VIEWER_TIMEOUT_MS = 40_000


def open_3d_tab(watched):
    """The console's 3D view tab: its frame, once it shows a candidate."""
    page = watched.page
    page.click("#tab-3d")
    expect_text(page.locator("#viewer-note"), "Draws this console's selection")
    frame = page.frame_locator("#viewer-frame")
    expect_text(frame.locator("body"), r"Rank \d+ of \d+", timeout=VIEWER_TIMEOUT_MS)
    return frame


def test_two_consoles_each_see_their_own_sequence_in_their_own_3d_view(server, api, new_page, tmp_path):
    dipper, dipper_search = upload_and_search(api, fresh_copy("04-big-dipper.json", "two-views", tmp_path))
    clean, clean_search = upload_and_search(api, fresh_copy("01-clean.json", "two-views", tmp_path))
    n_dipper, n_clean = len(dipper_search["candidates"]), len(clean_search["candidates"])
    assert dipper_search["status"] == clean_search["status"] == "identified" and n_dipper >= 2 and n_clean >= 2

    a = operator_on(new_page, server, "Ann Alpha", dipper, "04-big-dipper-two-views")
    b = operator_on(new_page, server, "Bob Beta", clean, "01-clean-two-views")
    session_a, session_b = (w.page.evaluate("document.body.dataset.session") for w in (a, b))
    assert session_a != session_b
    failed = []  # the server's errors, by address (a console error names none)
    for w in (a, b):
        w.page.on("response", lambda r: failed.append(f"{r.status} {r.request.method} {r.url}") if r.status >= 500
                  else None)
    a.page.locator("#operator").dispatch_event("change")
    b.page.locator("#operator").dispatch_event("change")

    # Each console's 3D tab is a view of its own session, both open at once.
    frame_a = open_3d_tab(a)
    frame_b = open_3d_tab(b)
    url_a, url_b = (w.page.locator("#viewer-frame").get_attribute("src") for w in (a, b))
    assert url_a == api(f"/api/viewer?session={session_a}")["url"] and session_a in url_a.replace("%3D", "=")
    assert url_b != url_a
    body_a, body_b = frame_a.locator("body"), frame_b.locator("body")
    expect_text(body_a, "04-big-dipper-two-views")
    expect_text(body_b, "01-clean-two-views")
    expect_text(body_a, rf"Rank 1 of {n_dipper}")
    expect_text(body_b, rf"Rank 1 of {n_clean}")
    # Each draws its own candidate's attitude, as the search gave it (the panel prints RA to 3 decimals).
    expect_text(body_a, re.escape(f"RA {dipper_search['candidates'][0]['ra_deg']:.3f}°"))
    expect_text(body_b, re.escape(f"RA {clean_search['candidates'][0]['ra_deg']:.3f}°"))
    assert "01-clean" not in body_a.inner_text() and "04-big-dipper" not in body_b.inner_text()
    assert api("/api/viewer")["views"] >= 2

    # B's Next moves B's console only; A's view and console stay at rank 1.
    frame_b.get_by_role("button", name="Next").click()
    expect_text(body_b, rf"Rank 2 of {n_clean}")
    expect_text(body_b, re.escape(f"RA {clean_search['candidates'][1]['ra_deg']:.3f}°"))
    assert api(f"/api/view?session={session_b}")["rank"] == 2
    b.page.click("#tab-work")
    expect_text(b.page.locator("#cand-rank"), rf"rank 2 of {n_clean}")
    view_a = api(f"/api/view?session={session_a}")
    assert (view_a["sequence"], view_a["rank"]) == (dipper, 1)
    expect_text(body_a, rf"Rank 1 of {n_dipper}")

    # A's magnitude limit is A's: B's session keeps its own.
    api(f"/api/view?session={session_a}", "PUT", body={"mag": 4.0})
    assert api(f"/api/view?session={session_b}")["mag"] == 6.0

    # Both views side by side, looked at by a person: /tmp/viewer-two.png.
    a.page.wait_for_timeout(1500)  # let the software renderer draw the sphere before the screenshot
    b.page.click("#tab-3d")
    expect_text(body_b, rf"Rank 2 of {n_clean}")
    b.page.wait_for_timeout(1500)
    shots = [Image.open(w.screenshot(f"viewer-two-{name}")) for w, name in ((a, "a"), (b, "b"))]
    combined = Image.fromarray(np.hstack([np.asarray(s.convert("RGB")) for s in shots]))
    combined.save("/tmp/viewer-two.png")
    combined.save(shots[0].filename.replace("viewer-two-a", "viewer-two"))

    # A's Confirm of a rank needing the console's second step goes to A's console, not to B's.
    frame_a.get_by_role("button", name="Next").click()
    expect_text(body_a, rf"Rank 2 of {n_dipper}")
    frame_a.get_by_role("button", name="Confirm").click()
    expect_text(body_a, "Sent to the console: its second step asks for the reason")
    request = api(f"/api/view?session={session_a}")["confirm_request"]
    assert (request["sequence"], request["rank"]) == (dipper, 2)
    assert api(f"/api/view?session={session_b}")["confirm_request"] is None
    expect_visible(a.page.locator("#override-step"))
    expect_text(a.page.locator("#override-title"), r"^Rank 2 \(sent from the 3D view\)")
    expect_visible(b.page.locator("#override-step"), False)
    assert failed == [] and a.errors == [] and b.errors == []
