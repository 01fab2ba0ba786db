"""An operator trial's findings, in a real Chromium: snapshots named as the file, the CLI and the API name
them; a confirmation lost to another operator says whose it is and when; the 3D view's Confirm of a rank
that needs a reason opens the console's second step; the 3D panel says a status in the console's words; the
message log gives UTC times.

Screenshots: test-artifacts/screenshots/trial-*.png.
"""

from __future__ import annotations

import json
import re
from datetime import datetime, timezone
from pathlib import Path

from playwright.sync_api import expect

from test_console_sessions import (SAMPLES, expect_in_viewport, expect_text, expect_value, expect_visible, fresh_copy,
                                   hold_back_polling, open_sequence, operator_on, supersede_rank_2_with_rank_1,
                                   unexpected_errors, upload_and_search, utc_text)

VIEWER_TIMEOUT_MS = 40_000
SCREENSHOTS = Path(__file__).resolve().parents[2] / "test-artifacts" / "screenshots"


def open_viewer(new_page, api, session: str):
    """The 3D view in a page of its own (as an operator opens its address), drawing ``session``."""
    viewer = new_page()
    viewer.page.goto(f"{api('/api/viewer')['url']}?session={session}")
    return viewer


# ---------------------------------------------------------------------------------------------------------

def test_snapshots_are_named_by_their_index_in_the_file(server, api, new_page, tmp_path):
    """04-big-dipper's reference snapshot is snapshots[2] ("reference_snapshot": 2, the CLI's "reference
    snapshot 2"): the console names it 2 everywhere, and says its position (3 of 16) in other words."""
    seq_id, _ = upload_and_search(api, fresh_copy("04-big-dipper.json", "numbering", tmp_path))
    detail = api(f"/api/sequences/{seq_id}")
    assert (detail["extraction"]["reference_snapshot"], len(detail["telemetry"]["snapshots"])) == (2, 16)
    assert [s["index"] for s in detail["telemetry"]["snapshots"]][:3] == [0, 1, 2]
    watched = operator_on(new_page, server, "Numbering Tester", seq_id, "04-big-dipper-numbering")
    page = watched.page
    expect_text(page.locator("#snapshot-label"), r"^snapshot 2 \(3 of 16, reference\)$")
    assert page.locator("#snapshot-slider").get_attribute("aria-valuetext") == "snapshot 2 (3 of 16, reference)"
    expect(page.locator("#sky-canvas")).to_have_attribute("data-credible", "true")   # rank 1, identified
    expect_text(page.locator("#pattern-caption"), r"points, reference snapshot 2$")
    # Tracks carried into the reference snapshot beyond the sensor's edge say so (the camera's bounds:
    # pixel centres 0 .. width-1, so edges at -0.5 and width-0.5).
    camera = detail["telemetry"]["camera"]
    off = {p["track"] for p in detail["pattern"]["points"]
           if not (-0.5 <= p["x"] <= camera["width"] - 0.5 and -0.5 <= p["y"] <= camera["height"] - 0.5)}
    assert off and len(off) < len(detail["pattern"]["points"])
    for p in detail["pattern"]["points"]:
        cell = page.locator(f'#pattern-rows tr[data-track="{p["track"]}"] td').nth(3)
        expect_text(cell, r"\(off sensor\)$" if p["track"] in off else r"^[-\d.]+, [-\d.]+$")
    page.click("#step-fwd")
    expect_text(page.locator("#snapshot-label"), r"^snapshot 3 \(4 of 16\)$")

    # A point picked by hand in snapshot 3: the message and the pattern table name it 3.
    page.check("#pick-mode")
    box = page.locator("#player-canvas").bounding_box()
    page.mouse.click(box["x"] + 6, box["y"] + box["height"] - 6)   # a corner: no source to snap to
    expect_text(page.locator("#toast"), r"of snapshot 3 changed")
    # The candidates are stale now: the sky chart draws rank 1's matches as doubtful, as its verdict says.
    expect(page.locator("#sky-canvas")).to_have_attribute("data-credible", "false")
    row = page.locator("#pattern-rows tr.manual")
    expect_text(row, r"snap\. 3")
    expect_text(row, r"◆ hand 0")   # manual_points[0], as the pattern's errors name it
    assert row.locator("td").nth(2).get_attribute("title") == "picked in snapshot 3 (4 of 16)"
    point = api(f"/api/sequences/{seq_id}")["pattern"]["definition"]["manual_points"][0]
    assert point["snapshot"] == 3
    page.uncheck("#pick-mode")
    page.click("#step-back")
    expect_text(page.locator("#snapshot-label"), r"^snapshot 2 \(3 of 16, reference\)$")
    page.locator("#player-card").scroll_into_view_if_needed()
    watched.screenshot("trial-01-snapshot-numbering")

    # A file that numbers its snapshots from 100: the position is the name (as in the API), the file's
    # own index is said beside it.
    doc = json.loads((SAMPLES / "04-big-dipper.json").read_text())
    doc["sequence_id"] = "04-big-dipper-from-100"
    for snapshot in doc["snapshots"]:
        snapshot["index"] += 100
    shifted = tmp_path / "04-big-dipper-from-100.json"
    shifted.write_text(json.dumps(doc))
    other_id, _ = upload_and_search(api, shifted)
    assert api(f"/api/sequences/{other_id}")["extraction"]["reference_snapshot"] == 2
    open_sequence(page, other_id, "04-big-dipper-from-100")
    expect_text(page.locator("#snapshot-label"), r"^snapshot 2 \(3 of 16, reference, index 102 in the file\)$")
    expect_text(page.locator("#pattern-caption"), r"reference snapshot 2 \(index 102 in the file\)$")
    assert watched.errors == []


def test_a_confirmation_lost_to_another_operator_says_whose_it_is(server, api, new_page, tmp_path):
    """The console shows rank 1 unconfirmed; another operator confirms it through the API; this console's
    Confirm then stores nothing new, and its message names that operator and the time (UTC)."""
    seq_id, search = upload_and_search(api, fresh_copy("01-clean.json", "lost-race", tmp_path))
    assert search["status"] == "identified"
    watched = operator_on(new_page, server, "Console Op", seq_id, "01-clean-lost-race")
    page = watched.page
    expect_text(page.locator("#confirm"), r"^Confirm rank 1$")
    hold_back_polling(page)   # its operator clicks before the console has noticed
    won = api(f"/api/sequences/{seq_id}/confirm", "POST", body={"rank": 1, "operator": "API Op"})
    page.click("#confirm")
    said = f"Rank 1 was confirmed already by API Op at {utc_text(won['confirmed_at'])} (attitude #{won['id']}); " \
           "nothing new stored"
    expect_text(page.locator("#toast"), "^" + re.escape(said) + "$")
    # A warning, read whole in the status line (not cut to one line with the rest in a tooltip).
    expect(page.locator("#toast")).to_have_class(re.compile(r"\bwarn\b"))
    assert page.locator("#toast").evaluate("e => e.scrollWidth <= e.clientWidth && e.scrollHeight <= e.clientHeight")
    expect_text(page.locator("#confirmed"), f"by API Op at {re.escape(utc_text(won['confirmed_at']))}")
    watched.screenshot("trial-02-lost-race")
    assert len(api(f"/api/sequences/{seq_id}/review")["audit"]) == 1
    # Once shown, pressing c says the same of the confirmation shown.
    page.evaluate("document.activeElement && document.activeElement.blur()")
    page.keyboard.press("c")
    expect_text(page.locator("#toast"), re.escape(f"Rank 1 is confirmed already by API Op at "
                                                  f"{utc_text(won['confirmed_at'])} (attitude #{won['id']})"))
    assert unexpected_errors(watched) == []


def test_the_3d_views_confirm_of_another_rank_opens_the_consoles_second_step(server, api, new_page, tmp_path):
    """docs/console.md: the 3D view's Confirm takes the credible best only; any other rank is sent to the console,
    whose second step asks for the reason.  3D view -> Next (rank 2, not credible) -> Confirm: the console
    (on its 3D tab) turns to its Sequence tab at rank 2 with the second step open, asking for the reason;
    a confirmation replacing the verdict (rank 1 afterwards) takes the console's second step too."""
    seq_id, search = upload_and_search(api, fresh_copy("04-big-dipper.json", "from-3d", tmp_path))
    n = len(search["candidates"])
    assert search["status"] == "identified" and n >= 2
    watched = operator_on(new_page, server, "Vera Viewer", seq_id, "04-big-dipper-from-3d")
    page = watched.page
    page.locator("#operator").dispatch_event("change")   # the 3D view confirms under the console's name
    session = page.evaluate("document.body.dataset.session")
    page.click("#tab-3d")   # the 3D view draws this console
    expect_text(page.locator("#viewer-note"), "Draws this console's selection")
    viewer = open_viewer(new_page, api, session)
    panel = viewer.page.locator("body")
    expect_text(panel, rf"Rank 1 of {n}", timeout=VIEWER_TIMEOUT_MS)
    expect_text(panel, "Credible: Confirm takes it.")   # said before any click, as the console's verdict line
    viewer.page.get_by_role("button", name="Next").click()
    expect_text(panel, rf"Rank 2 of {n}")
    expect_text(panel, re.escape("Not credible (not the best candidate: rank 1 matches "))
    typed = "seen from the 3D view: both heads"
    # viser's labels name no input (their "for" is another id): the text box after the label.
    comment_box = viewer.page.locator("xpath=//label[normalize-space()='Comment']/following::input[1]")
    comment_box.fill(typed)
    viewer.page.get_by_role("button", name="Confirm").click()
    expect_text(panel, re.escape("Rank 2 is not the credible best candidate (not the best candidate: rank 1 matches "))
    expect_text(panel, "Sent to the console: its second step asks for the reason, which the audit record keeps. "
                       "The comment typed here goes with it, into the console's comment box.")
    expect_value(comment_box, "")   # sent: not carried into the next confirmation, as the console's
    viewer.screenshot("trial-03-viewer-sent-rank-2")

    # The console opens its second step for rank 2, on its Sequence tab, and stores nothing yet.
    expect_visible(page.locator("#panel-work"))
    expect_visible(page.locator("#panel-3d"), False)
    expect_text(page.locator("#cand-rank"), rf"rank 2 of {n}")
    expect_visible(page.locator("#override-step"))
    expect_text(page.locator("#override-title"), r"^Rank 2 \(sent from the 3D view\) is not the credible best: "
                                                 r"confirm anyway\?$")
    expect_text(page.locator("#override-reasons"), "not the best candidate")
    expect(page.locator("#override-reason")).to_be_focused()
    expect_in_viewport(page.locator("#override-step"))
    expect_text(page.locator("#toast"), "The 3D view sent rank 2 here: give the reason to confirm it anyway")
    expect_value(page.locator("#comment"), typed)   # the comment typed there came with it
    watched.screenshot("trial-04-console-second-step-from-3d")
    assert api(f"/api/sequences/{seq_id}/review")["audit"] == []

    reason = "rank 1 is a ghost pattern; rank 2 agrees with the other head"
    page.fill("#override-reason", reason)
    page.click("#confirm-override")
    expect_text(page.locator("#confirmed"), "override: rank 1 is a ghost pattern")
    c = api(f"/api/sequences/{seq_id}/review")["confirmation"]
    assert (c["rank"], c["operator"], c["override_reason"], c["comment"]) == (2, "Vera Viewer", reason, typed)

    # Rank 1 now would replace that verdict: the 3D view sends it to the console's second step too.
    page.click("#tab-3d")
    expect_text(panel, rf"Rank 2 of {n}")
    viewer.page.get_by_role("button", name="Prev").click()
    expect_text(panel, rf"Rank 1 of {n}")
    comment_box.fill("rank 1 after all (3D)")
    viewer.page.get_by_role("button", name="Confirm").click()
    expect_text(panel, re.escape(f"Rank 1 would replace the sequence's verdict: attitude #{c['id']} (rank 2) "
                                 "confirmed by Vera Viewer at "))
    expect_text(page.locator("#override-title"), r"^Replace the verdict with rank 1 \(sent from the 3D view\)\?$")
    expect_value(page.locator("#comment"), "rank 1 after all (3D)")
    # Cancelled, the step takes the comment sent for it along (it went with another rank's confirmation).
    page.click("#override-cancel")
    expect_value(page.locator("#comment"), "")
    page.click("#confirm")
    supersede_rank_2_with_rank_1(page, api, seq_id, c["id"])
    assert api(f"/api/sequences/{seq_id}/review")["confirmation"]["comment"] is None
    # The panel's message was about that sequence: it goes when the console opens another.
    expect_text(panel, "would replace the sequence's verdict")
    other_id, _ = upload_and_search(api, fresh_copy("01-clean.json", "after-3d", tmp_path))
    open_sequence(page, other_id, "01-clean-after-3d")
    expect_text(panel, r"01-clean-after-3d \(SIM-TUBSAT\), status identified")
    expect(panel).not_to_contain_text("would replace")
    assert watched.errors == [] and viewer.errors == []


def test_the_3d_panel_says_the_status_in_the_consoles_words(server, api, new_page, tmp_path):
    """The 3D panel said "status no_match" and "status rejected" where the console says "no match" and
    "no valid attitude"."""
    seq_id, search = upload_and_search(api, fresh_copy("05-earth.json", "3d-status", tmp_path))
    assert search["status"] == "no_match" and search["candidates"]
    watched = operator_on(new_page, server, "Status Tester", seq_id, "05-earth-3d-status")
    page = watched.page
    expect_text(page.locator("#seq-status"), "^no match$")
    session = page.evaluate("document.body.dataset.session")
    page.click("#tab-3d")
    expect_text(page.locator("#viewer-note"), "Draws this console's selection")
    viewer = open_viewer(new_page, api, session)
    panel = viewer.page.locator("body")
    expect_text(panel, r"\(SIM-TUBSAT\), status no match\b", timeout=VIEWER_TIMEOUT_MS)
    assert "no_match" not in panel.inner_text()
    viewer.page.wait_for_function("() => document.querySelector('canvas') !== null")
    viewer.screenshot("trial-05-viewer-status-no-match")
    api(f"/api/sequences/{seq_id}/reject", "POST", body={"reason": "the Earth fills the field", "operator": "Rex"})
    expect_text(panel, r"status no valid attitude\b")
    assert "rejected" not in panel.inner_text()
    expect_text(page.locator("#seq-status"), "^no valid attitude$")
    viewer.screenshot("trial-06-viewer-status-no-valid-attitude")
    assert watched.errors == [] and viewer.errors == []


def test_the_message_log_gives_utc_times(server, browser):
    """The help's Messages list gave the browser's local 12-hour time ("11:12:16 PM"); every other time of
    the console is UTC as 2026-11-23 23:12:16Z.  The browser here runs 5 hours behind UTC."""
    context = browser.new_context(viewport={"width": 1280, "height": 800}, timezone_id="America/Bogota",
                                  locale="en-US")
    try:
        page = context.new_page()
        errors = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(server + "/")
        page.wait_for_selector("body[data-ready='1']")
        assert page.evaluate("new Date().getTimezoneOffset()") == 300
        truth = SAMPLES / "04-big-dipper.truth.json"
        before = datetime.now(timezone.utc).replace(microsecond=0)
        page.set_input_files("#file-input", [str(truth)])   # skipped: a message in the status line, and logged
        expect_text(page.locator("#toast"), "1 truth file skipped")
        after = datetime.now(timezone.utc)
        page.keyboard.press("?")
        expect_visible(page.locator("#help"))
        stamp = page.locator("#message-log li time").first
        text = stamp.inner_text()
        assert re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\dZ", text), text
        logged = datetime.strptime(text, "%Y-%m-%d %H:%M:%SZ").replace(tzinfo=timezone.utc)
        assert before <= logged <= after
        assert stamp.get_attribute("datetime").startswith(text[:10] + "T" + text[11:19])
        expect_text(page.locator("#message-log li").first, "1 truth file skipped")
        SCREENSHOTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(SCREENSHOTS / "trial-07-message-log-utc.png"))
        assert errors == []
    finally:
        context.close()
