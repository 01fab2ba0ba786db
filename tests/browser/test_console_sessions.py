"""The operator's console of issue 13 in a real Chromium: own sessions, guard rails, "no valid attitude",
the work queue, a sky view that explains itself, keyboard, and the layout at 1280 and 1024 px.

The server is shared by every browser test (one archive), so each test uploads copies of the samples
under sequence ids of its own: new content, new sequences whose state only that test changes.  Facts
are read back from the server's API, never from the page alone.
"""

from __future__ import annotations

import json
import math
import re
import time
from pathlib import Path

import pytest

SAMPLES = Path(__file__).resolve().parents[2] / "sample_telemetry"
TIMEOUT_MS = 20_000
#: The work queue's order: what needs an operator first (docs/console.md, app/storage.py SEQUENCE_ORDERS).
QUEUE_ORDER = ["ambiguous", "no_match", "identified", "new", "rejected", "confirmed"]


def expect_text(locator, pattern: str, timeout: int = TIMEOUT_MS) -> None:
    from playwright.sync_api import expect

    expect(locator).to_contain_text(re.compile(pattern), timeout=timeout)


def supersede_rank_2_with_rank_1(page, api, seq_id: int, replaced_id: int) -> list[dict]:
    """The second step open to supersede attitude ``replaced_id`` (rank 2) with rank 1: confirmed there, and the
    audit trail keeps both, rank 1 current; returns the trail."""
    expect_visible(page.locator("#override-step"))
    expect_text(page.locator("#override-reasons"), f"replaces the current verdict: attitude #{replaced_id}")
    page.click("#confirm-override")
    expect_text(page.locator("#confirm"), r"Confirmed ✓")
    audit = wait_for(lambda: api(f"/api/sequences/{seq_id}/review")["audit"], lambda a: len(a) == 2)
    assert [(e["rank"], e["current"]) for e in audit] == [(2, False), (1, True)]
    return audit


def expect_value(locator, value: str, timeout: int = TIMEOUT_MS) -> None:
    from playwright.sync_api import expect

    expect(locator).to_have_value(value, timeout=timeout)


def expect_in_viewport(locator, timeout: int = TIMEOUT_MS) -> None:
    from playwright.sync_api import expect

    expect(locator).to_be_in_viewport(timeout=timeout)


def expect_visible(locator, visible: bool = True, timeout: int = TIMEOUT_MS) -> None:
    from playwright.sync_api import expect

    (expect(locator).to_be_visible if visible else expect(locator).to_be_hidden)(timeout=timeout)


def wait_for(read, ok, timeout_s: float = TIMEOUT_MS / 1000, interval_s: float = 0.1):
    """Poll ``read()`` until ``ok(value)`` or the deadline; the last value read."""
    deadline = time.monotonic() + timeout_s
    value = read()
    while not ok(value) and time.monotonic() < deadline:
        time.sleep(interval_s)
        value = read()
    return value


def fresh_copy(sample: str, tag: str, directory: Path) -> Path:
    """The sample under its own sequence id (new content: a new sequence in the shared archive)."""
    doc = json.loads((SAMPLES / sample).read_text())
    doc["sequence_id"] = f"{doc['sequence_id']}-{tag}"
    path = directory / f"{doc['sequence_id']}.json"
    path.write_text(json.dumps(doc))
    return path


def utc_text(api_time: str) -> str:
    """An API time as the console prints it (static/js/dom.js fmtTime): ``2026-11-23 18:57:41Z``."""
    return re.sub(r"\.\d+Z$", "Z", api_time.replace("T", " "))


def upload_and_search(api, path: Path, body: dict | None = None) -> tuple[int, dict]:
    seq_id = api("/api/sequences", "POST", raw=path.read_bytes())["id"]
    return seq_id, api(f"/api/sequences/{seq_id}/search", "POST", body=body or {})


def keep_brightest(api, sample: str, tag: str, directory: Path, n: int) -> int:
    """A fresh copy of ``sample`` whose pattern keeps only its ``n`` brightest tracks."""
    seq_id = api("/api/sequences", "POST", raw=fresh_copy(sample, tag, directory).read_bytes())["id"]
    points = api(f"/api/sequences/{seq_id}")["pattern"]["points"]
    brightest = [p["track"] for p in sorted(points, key=lambda p: -(p["brightness"] or 0))][:n]
    api(f"/api/sequences/{seq_id}/pattern", "PUT", body={"include_tracks": brightest})
    return seq_id


def make_ambiguous(api, sample: str, tag: str, directory: Path) -> int:
    """A sequence whose pattern keeps only its four brightest tracks: four stars fit, but not beyond doubt
    (three fit too many places to be credible at all)."""
    seq_id = keep_brightest(api, sample, tag, directory, 4)
    status = api(f"/api/sequences/{seq_id}/search", "POST", body={})["status"]
    assert status == "ambiguous", f"four stars of {sample} were expected to leave the choice to an operator ({status})"
    return seq_id


def console(new_page, server, width: int = 1280, height: int = 800):
    watched = new_page(width, height)
    watched.page.goto(server + "/")
    watched.page.wait_for_selector("body[data-ready='1']")
    return watched, watched.page.evaluate("document.body.dataset.session")


def open_sequence(page, seq_id: int, name: str) -> None:
    """Open a sequence from the work queue as an operator does: search its id, click it."""
    page.fill("#filter-search", name)
    page.locator(f"#sequence-list li[data-id='{seq_id}']").click()
    expect_text(page.locator("#seq-title"), re.escape(name))


def operator_on(new_page, server, operator: str, seq_id: int, name: str):
    """A console with ``operator`` typed in, showing sequence ``seq_id`` (named ``name``); its page."""
    watched, _ = console(new_page, server)
    watched.page.fill("#operator", operator)
    open_sequence(watched.page, seq_id, name)
    return watched


def press(page, key: str) -> None:
    """A key pressed with no text field focused, as an operator's shortcut is."""
    page.evaluate("document.activeElement && document.activeElement.blur()")
    page.keyboard.press(key)


def hold_back_polling(page) -> None:
    """From now on the console's once-a-second reads of its view fail (as with a network hiccup), so it
    learns of changes made elsewhere only through its own actions; its writes still go through."""
    page.route("**/api/view?*", lambda route: route.abort() if route.request.method == "GET" else route.continue_())


def unexpected_errors(watched) -> list[str]:
    """The page's console errors but Chromium's reports of refused (409) requests and of the reads
    :func:`hold_back_polling` failed."""
    return [e for e in watched.errors if "status of 409" not in e and "net::ERR_FAILED" not in e]


def boxes_overlap(a: dict, b: dict) -> bool:
    return a["x"] < b["x"] + b["width"] and b["x"] < a["x"] + a["width"] \
        and a["y"] < b["y"] + b["height"] and b["y"] < a["y"] + a["height"]


# ---------------------------------------------------------------------------------------------------------

def test_two_consoles_keep_their_own_sequences_while_both_click_around(server, api, new_page, tmp_path):
    x_id, x_search = upload_and_search(api, fresh_copy("01-clean.json", "tab-a", tmp_path))
    y_id, y_search = upload_and_search(api, fresh_copy("04-big-dipper.json", "tab-b", tmp_path))
    z_id, _ = upload_and_search(api, fresh_copy("09-wide-30deg.json", "tab-b2", tmp_path))
    a, a_session = console(new_page, server)
    b, b_session = console(new_page, server)
    assert a_session != b_session
    open_sequence(a.page, x_id, "01-clean-tab-a")
    open_sequence(b.page, y_id, "04-big-dipper-tab-b")
    b.page.fill("#filter-search", "tab-b")  # B's queue shows both of its sequences
    n_x, n_y = len(x_search["candidates"]), len(y_search["candidates"])

    started, k = time.monotonic(), 0
    while time.monotonic() - started < 10.0:
        # A steps through its candidates with the table and the keyboard ...
        rank_a = 1 + k % n_x
        a.page.locator(f"#candidate-rows tr[data-rank='{rank_a}']").click()
        expect_text(a.page.locator("#cand-rank"), rf"rank {rank_a} of {n_x}")
        # ... while B switches between its two sequences and steps with Next.
        b_seq, b_name = (y_id, "04-big-dipper-tab-b") if k % 2 == 0 else (z_id, "09-wide-30deg-tab-b2")
        b.page.locator(f"#sequence-list li[data-id='{b_seq}']").click()
        expect_text(b.page.locator("#seq-title"), re.escape(b_name))
        b.page.locator("#cand-next").click()
        expect_text(b.page.locator("#cand-rank"), r"rank 2 of")
        # Nothing moved under A's hands, on screen or on the server.
        expect_text(a.page.locator("#seq-title"), "01-clean-tab-a")
        expect_text(a.page.locator("#cand-rank"), rf"rank {rank_a} of {n_x}")
        assert a.page.locator("#sequence-list li.selected").get_attribute("data-id") in (str(x_id), None)
        # The server's session state follows (a console may show the rank before its write is answered: B's
        # opening of the sequence drew the rank its Next had set while the Next's write waited its turn).
        state_a = wait_for(lambda: api(f"/api/view?session={a_session}"),
                           lambda doc: (doc["sequence"], doc["rank"]) == (x_id, rank_a))
        state_b = wait_for(lambda: api(f"/api/view?session={b_session}"),
                           lambda doc: (doc["sequence"], doc["rank"]) == (b_seq, 2))
        assert (state_a["sequence"], state_a["rank"]) == (x_id, rank_a)
        assert (state_b["sequence"], state_b["rank"]) == (b_seq, 2)
        k += 1
    assert k >= 3, "both consoles should have clicked around several times in 10 s"
    # A reload finds the tab's own selection again (sessionStorage keeps the session id).
    a.page.reload()
    expect_text(a.page.locator("#seq-title"), "01-clean-tab-a")
    assert n_y >= 2 and a.errors == [] and b.errors == []


def test_a_non_credible_candidate_is_confirmed_only_after_a_second_step_with_a_reason(server, api, new_page, tmp_path):
    seq_id, search = upload_and_search(api, fresh_copy("10-narrow-12deg-ghosts.json", "guard", tmp_path))
    assert search["status"] == "identified" and len(search["candidates"]) >= 2
    watched = operator_on(new_page, server, "Guard Tester", seq_id, "10-narrow-12deg-ghosts-guard")
    page = watched.page
    expect_text(page.locator("#cand-verdict"), "Rank 1 is credible")
    expect_text(page.locator("#confirm"), r"^Confirm rank 1$")

    page.locator("#candidate-rows tr[data-rank='2']").click()
    expect_text(page.locator("#cand-verdict"), "Rank 2 is not credible")
    expect_text(page.locator("#cand-verdict"), "not the best candidate")
    expect_text(page.locator("#confirm"), r"Confirm rank 2…")
    page.click("#confirm")
    expect_visible(page.locator("#override-step"))
    expect_text(page.locator("#override-reasons"), "not the best candidate")
    # The first step stored nothing; neither does the second without a reason.
    assert api(f"/api/sequences/{seq_id}/review")["audit"] == []
    page.click("#confirm-override")
    expect_text(page.locator("#toast"), "Give the reason")
    assert api(f"/api/sequences/{seq_id}/review")["audit"] == []
    watched.screenshot("10-guard-second-step")

    reason = "rank 1 matched a ghost pattern; checked against the star tracker of the other head"
    page.fill("#override-reason", reason)
    page.click("#confirm-override")
    expect_text(page.locator("#confirmed"), r"Confirmed: attitude #\d+")
    expect_text(page.locator("#confirmed"), "override: rank 1 matched a ghost")
    review = api(f"/api/sequences/{seq_id}/review")
    c = review["confirmation"]
    assert (c["rank"], c["override_reason"], c["operator"]) == (2, reason, "Guard Tester")
    assert any("not the best candidate" in r for r in c["overridden"])
    # After confirming, the button says so; confirming again stores nothing new.
    expect_text(page.locator("#confirm"), rf"Confirmed ✓ \(attitude #{c['id']}\)")
    assert page.locator("#confirm").is_disabled()
    # The confirmation says it is done (in the status line and its log) once the lists are read again: a "c" pressed
    # before then had its "confirmed already" replaced by that message when the lists came slowly.
    expect_text(page.locator("#message-log"), rf"Attitude #{c['id']} confirmed by Guard Tester")
    press(page, "c")
    expect_text(page.locator("#toast"), "confirmed already")
    watched.screenshot("11-guard-confirmed")

    # Rank 1 instead: an explicit supersede (second step), and the audit trail keeps both.
    page.locator("#candidate-rows tr[data-rank='1']").click()
    expect_text(page.locator("#confirm"), "Supersede with rank 1…")
    page.keyboard.press("c")
    audit = supersede_rank_2_with_rank_1(page, api, seq_id, c["id"])
    assert api(f"/api/attitudes/{c['id']}")["superseded_by"] == audit[1]["id"]
    assert watched.errors == []


def test_no_valid_attitude_is_recorded_with_its_reason(server, api, new_page, tmp_path):
    earth = fresh_copy("05-earth.json", "reject", tmp_path)
    truth = tmp_path / "05-earth-reject.truth.json"
    truth.write_text((SAMPLES / "05-earth.truth.json").read_text())
    watched, _ = console(new_page, server)
    page = watched.page
    page.fill("#operator", "Reject Tester")
    assert page.locator("#auto-search").is_checked()  # on by default
    # The console's upload skips the truth file with a note, and the new upload is searched by itself.
    page.set_input_files("#file-input", [str(earth), str(truth)])
    expect_text(page.locator(f".upload-item[data-file='{truth.name}']"), "skipped: a simulator's truth file")
    expect_text(page.locator(f".upload-item[data-file='{earth.name}']"), r"stored as #\d+")
    expect_text(page.locator("#seq-title"), "05-earth-reject")
    expect_text(page.locator("#seq-status"), "no match")  # searched without pressing Search
    seq_id = int(re.search(r"#(\d+)", page.locator(f".upload-item[data-file='{earth.name}']").inner_text()).group(1))
    expect_text(page.locator("#cand-verdict"), "not credible")
    expect_text(page.locator("#cand-verdict"), "no match")
    expect_text(page.locator("#confirm"), "Confirm rank 1…")

    press(page, "r")
    expect_visible(page.locator("#reject-step"))
    page.click("#reject-confirm")
    expect_text(page.locator("#toast"), "Give the reason")
    assert api(f"/api/sequences/{seq_id}")["status"] == "no_match"
    reason = "the Earth fills the field: no star at all"
    page.fill("#reject-reason", reason)
    page.click("#reject-confirm")
    expect_text(page.locator("#confirmed"), "No valid attitude")
    expect_text(page.locator("#seq-status"), "no valid attitude")
    review = api(f"/api/sequences/{seq_id}/review")
    assert review["status"] == "rejected" and review["rejection"]["reason"] == reason
    assert review["rejection"]["operator"] == "Reject Tester" and review["confirmation"] is None
    watched.screenshot("12-rejected")
    assert watched.errors == []


def test_a_next_pressed_while_a_sequence_opens_steps_the_sequence_being_opened(server, api, new_page, tmp_path):
    """An operator's moves are taken in the order made: a sequence clicked and Next clicked at once (one script,
    no time between: the opening's reads are still out) leave the new sequence at rank 2, on screen and in the
    session the 3D view draws.  Before, the Next stepped the sequence being left, and the opening then put the
    new one at rank 1: the Next was lost (a fresh-user trial, 10 of 10 times with the clicks 10 ms apart)."""
    y_id, _ = upload_and_search(api, fresh_copy("04-big-dipper.json", "moves", tmp_path))
    z_id, z_search = upload_and_search(api, fresh_copy("09-wide-30deg.json", "moves2", tmp_path))
    assert len(z_search["candidates"]) >= 2
    watched, session = console(new_page, server, 1600, 1000)  # the trial's window
    page = watched.page
    open_sequence(page, y_id, "04-big-dipper-moves")
    page.fill("#filter-search", "-moves")  # both sequences in the queue
    expect_visible(page.locator(f"#sequence-list li[data-id='{z_id}']"))
    player_at = {}
    for _ in range(3):
        for seq_id, name in ((z_id, "09-wide-30deg-moves2"), (y_id, "04-big-dipper-moves")):
            # Listed before the one script clicks it (a CI run found it unlisted once, 2026-11-26: not diagnosed).
            expect_visible(page.locator(f"#sequence-list li[data-id='{seq_id}']"))
            page.evaluate("""(id) => {
                document.querySelector(`#sequence-list li[data-id='${id}']`).click();
                document.querySelector('#cand-next').click();
            }""", seq_id)
            expect_text(page.locator("#seq-title"), re.escape(name))
            expect_text(page.locator("#cand-rank"), r"rank 2 of")
            view = wait_for(lambda: api(f"/api/view?session={session}"),
                            lambda doc, seq_id=seq_id: (doc["sequence"], doc["rank"]) == (seq_id, 2))
            assert (view["sequence"], view["rank"]) == (seq_id, 2)
            player_at[seq_id] = page.locator("#player-canvas").bounding_box()
    # The player keeps its size from a 752x582 camera's sequence to a 576x604 one's (the sensor fitted into it): a
    # taller sensor made it taller, and a click meant for Next, below it, landed on the player and took a track
    # out of the pattern.
    assert player_at[y_id] == player_at[z_id]
    assert watched.errors == []


def test_a_search_made_elsewhere_puts_the_console_and_its_session_at_rank_1(server, api, new_page, tmp_path):
    """A sequence open before it was ever searched (an upload's queued search still running, or another console
    searching it): when the search lands the console shows rank 1, and the session the 3D view draws says
    rank 1 too.  Before, the session kept no rank (a fresh-user trial: "rank": null while the page showed
    "rank 1 of 5", until the operator picked a rank)."""
    seq_id = api("/api/sequences", "POST", raw=fresh_copy("01-clean.json", "elsewhere", tmp_path).read_bytes())["id"]
    watched, session = console(new_page, server)
    page = watched.page
    open_sequence(page, seq_id, "01-clean-elsewhere")
    assert api(f"/api/view?session={session}")["rank"] is None  # nothing searched yet
    search = api(f"/api/sequences/{seq_id}/search", "POST", body={})
    expect_text(page.locator("#cand-rank"), rf"rank 1 of {len(search['candidates'])}")
    view = wait_for(lambda: api(f"/api/view?session={session}"), lambda doc: doc["rank"] == 1)
    assert (view["sequence"], view["rank"], view["search_id"]) == (seq_id, 1, search["search_id"])
    assert watched.errors == []


def test_a_search_finishing_between_the_two_reads_of_a_sequence_still_shows_its_verdicts(server, api, new_page,
                                                                                        tmp_path):
    """The console reads a sequence and its verdicts in parallel; an upload's queued search can finish
    between the two.  Here the first verdicts read are made to predate the search (as the server answered
    them a moment before it was stored): the console must read again rather than show the new candidates
    with no verdict, which the view polling would never repair (nothing changes afterwards)."""
    seq_id, search = upload_and_search(api, fresh_copy("01-clean.json", "race", tmp_path))
    assert search["status"] == "identified"
    watched, _ = console(new_page, server)
    page = watched.page
    stale = {"served": 0}

    def before_the_search(route):
        if stale["served"]:
            route.continue_()
            return
        stale["served"] += 1
        review = route.fetch().json()
        review.update(search_id=None, search_status=None, method=None, search_pattern_version=None, candidates=[])
        route.fulfill(json=review)

    page.route(f"**/api/sequences/{seq_id}/review", before_the_search)
    open_sequence(page, seq_id, "01-clean-race")
    expect_text(page.locator("#cand-verdict"), "Rank 1 is credible")
    assert stale["served"] == 1
    assert watched.errors == []


def test_a_confirmation_refused_for_a_replaced_search_shows_the_new_search_whole(server, api, new_page, tmp_path):
    """Another console's search replaces the candidates before this console's polling has noticed (its
    reads of the view are held back here), and this console presses Confirm: the server refuses (409),
    and the console must then show the new search whole, from rank 1, with the change announced, not the
    new table under the old rank and figures."""
    seq_id, first = upload_and_search(api, fresh_copy("10-narrow-12deg-ghosts.json", "replaced", tmp_path))
    assert first["status"] == "identified" and len(first["candidates"]) >= 3
    watched = operator_on(new_page, server, "Stale Tester", seq_id, "10-narrow-12deg-ghosts-replaced")
    page = watched.page
    page.locator("#candidate-rows tr[data-rank='3']").click()
    expect_text(page.locator("#cand-rank"), f"rank 3 of {len(first['candidates'])}")
    hold_back_polling(page)
    second = api(f"/api/sequences/{seq_id}/search", "POST", body={"method": "tf"})
    assert second["search_id"] != first["search_id"]
    page.fill("#comment", "about rank 3 of the first search")
    page.click("#confirm")
    expect_visible(page.locator("#override-step"))  # rank 3 is not the credible best: the second step
    page.fill("#override-reason", "checked by eye")
    page.click("#confirm-override")
    expect_text(page.locator("#toast"), "replaced by search")
    # The refusal is read whole in the status line, not cut to one line with the rest in a tooltip.
    assert page.locator("#toast").evaluate("e => e.scrollWidth <= e.clientWidth && e.scrollHeight <= e.clientHeight")
    # The second step asked about rank 3 of the old search: it must not stay to confirm the new rank 1,
    # and neither does the comment typed for it.
    expect_visible(page.locator("#override-step"), False)
    expect_value(page.locator("#comment"), "")
    n_new = len(second["candidates"])
    expect_text(page.locator("#cand-rank"), f"rank 1 of {n_new}")
    expect_text(page.locator("#change-notice"), f"a new search \\(#{second['search_id']}\\) replaced the candidates")
    # It lies over the header card, hiding the sequence's name: it names the sequence itself.
    expect_text(page.locator("#change-notice"), f"Changed by another console on 10-narrow-12deg-ghosts-replaced "
                                                f"\\(#{seq_id}\\): a new search")
    # The notice belongs at the top of the workspace, the Confirm step further down: it is held in view, under the
    # top bar (the page is not scrolled up to it).
    expect_in_viewport(page.locator("#change-notice"))
    # ... and not under the sticky top bar.
    assert page.locator("#change-notice").bounding_box()["y"] >= sum(
        page.locator(".topbar").bounding_box()[k] for k in ("y", "height"))
    assert page.locator("#candidate-rows tr").count() == n_new
    assert page.locator("#candidate-rows tr.selected").get_attribute("data-rank") == "1"
    expect_text(page.locator("#cand-facts"), f"1 of {n_new}")
    # The search summary names the method as the menu does, and counts in words.
    expect_text(page.locator("#search-summary"),
                f"by triangle features, {n_new} candidate{'' if n_new == 1 else 's'} in ")
    watched.screenshot("16-refused-for-a-replaced-search")
    review = api(f"/api/sequences/{seq_id}/review")
    assert review["confirmation"] is None and review["search_id"] == second["search_id"]
    assert unexpected_errors(watched) == []


def test_a_replacing_search_without_candidates_is_announced_in_words(server, api, new_page, tmp_path):
    """Another console searches again with a method that finds nothing (triangle features on three
    points, none with two neighbours inside the rim): the notice says so, not "back at rank -"."""
    seq_id = keep_brightest(api, "06-sparse.json", "emptied", tmp_path, 3)
    first = api(f"/api/sequences/{seq_id}/search", "POST", body={})
    assert first["candidates"]
    watched = operator_on(new_page, server, "Sparse Watcher", seq_id, "06-sparse-emptied")
    page = watched.page
    expect_text(page.locator("#cand-rank"), f"rank 1 of {len(first['candidates'])}")
    second = api(f"/api/sequences/{seq_id}/search", "POST", body={"method": "tf"})
    assert second["candidates"] == []
    expect_text(page.locator("#change-notice"), f"a new search \\(#{second['search_id']}\\) replaced the "
                                                 "candidates shown; it found no candidates")
    assert "rank -" not in page.locator("#change-notice").inner_text()
    assert unexpected_errors(watched) == []


def test_a_change_notice_goes_once_this_console_gives_its_verdict(server, api, new_page, tmp_path):
    """Another console's new search is announced; this console then confirms the new rank 1: the notice was
    about what the verdict was given on, and goes (it stayed, telling of a change already dealt with)."""
    seq_id, _ = upload_and_search(api, fresh_copy("01-clean.json", "notice", tmp_path))
    watched = operator_on(new_page, server, "Notice Reader", seq_id, "01-clean-notice")
    page = watched.page
    second = api(f"/api/sequences/{seq_id}/search", "POST", body={"method": "bright_pair", "max_candidates": 3})
    expect_text(page.locator("#change-notice"), f"a new search \\(#{second['search_id']}\\) replaced the candidates")
    page.click("#confirm")
    expect_text(page.locator("#confirmed"), r"Confirmed: attitude #\d+")
    expect_visible(page.locator("#change-notice"), False)
    assert api(f"/api/sequences/{seq_id}/review")["confirmation"]["search_id"] == second["search_id"]
    assert unexpected_errors(watched) == []


#: What an operator may be about to click when another console's change is announced: these must not move.
CLICKED = {"next": "#cand-next", "player": "#player-canvas", "pattern": "#pattern-card"}
#: ... and what the notice must not lie over while the page is at its top.
NOT_COVERED = ["#player-canvas", "#play", "#snapshot-slider", "#search-method", "#search", "#reset-pattern",
               "#cand-prev", "#cand-next", "#tab-work", "#tab-3d", "#operator", "#seq-status"]


def boxes_of(page, selectors: dict) -> dict:
    return {name: page.locator(sel).bounding_box() for name, sel in selectors.items()}


def searched_elsewhere(page, api, seq_id: int, body: dict) -> dict:
    """A search of ``seq_id`` by another console (through the API), returned once this console has shown it: its
    rank 1 drawn again in the sky view, the last thing the console does on seeing a new search (after the notice)."""
    page.evaluate("""() => { window.skyDrawn = 0;
        new MutationObserver(() => { window.skyDrawn++; })
          .observe(document.getElementById("sky-canvas"), { attributes: true, attributeFilter: ["data-view"] }); }""")
    result = api(f"/api/sequences/{seq_id}/search", "POST", body=body)
    page.wait_for_function("window.skyDrawn > 0", timeout=TIMEOUT_MS)
    return result


def assert_same_boxes(before: dict, after: dict) -> None:
    for name, box in before.items():
        moved = {k: after[name][k] - box[k] for k in box if abs(after[name][k] - box[k]) > 0.5}
        assert not moved, f"{name} moved when the notice came: {moved} ({box} -> {after[name]})"


@pytest.mark.parametrize("width,height", [(1280, 800), (1920, 1080)])
def test_a_change_notice_moves_nothing_the_operator_clicks(server, api, new_page, tmp_path, width, height):
    """Another console's new search is announced at a moment this operator did not choose, maybe with the pointer
    on a point of the snapshots or on Next.  The notice was put in the page's flow above the panels (and scrolled
    into view): everything under it jumped down by its height and a click meant for one thing landed on another.
    It now comes over the sequence's header card, and under the top bar when the page is scrolled: the player, the
    pattern card and Next stay where they were, the page is not scrolled, and the notice covers none of them."""
    tag = f"still-{width}"
    seq_id, first = upload_and_search(api, fresh_copy("01-clean.json", tag, tmp_path))
    n = len(first["candidates"])
    watched = new_page(width, height)
    page = watched.page
    page.goto(server + "/")
    page.wait_for_selector("body[data-ready='1']")
    page.fill("#operator", "Still Hands")
    open_sequence(page, seq_id, f"01-clean-{tag}")
    expect_text(page.locator("#cand-rank"), f"rank 1 of {n}")
    page.locator("#player-canvas").hover()   # the pointer on the snapshots, as an operator's about to pick a point
    before, scroll_before = boxes_of(page, CLICKED), page.evaluate("window.scrollY")

    second = searched_elsewhere(page, api, seq_id, {"method": "bright_pair", "max_candidates": n})
    assert second["search_id"] != first["search_id"] and len(second["candidates"]) == n   # "rank 1 of n" again
    notice = page.locator("#change-notice")
    expect_text(notice, f"a new search \\(#{second['search_id']}\\) replaced the candidates shown; back at rank 1")
    assert_same_boxes(before, boxes_of(page, CLICKED))
    assert page.evaluate("window.scrollY") == scroll_before
    # Seen where it is, read whole, read out by a screen reader, and lying over nothing clicked.
    expect_in_viewport(notice)
    topbar = page.locator(".topbar").bounding_box()
    box = notice.bounding_box()
    assert box["y"] >= topbar["y"] + topbar["height"]
    assert notice.get_attribute("role") == "status"
    assert notice.evaluate("e => e.scrollHeight <= e.clientHeight && e.scrollWidth <= e.clientWidth")
    covered = [sel for sel in NOT_COVERED if boxes_overlap(box, page.locator(sel).bounding_box())]
    assert covered == [], f"the notice lies over {covered}"
    watched.screenshot(f"18-change-notice-{width}")

    # Scrolled down to the verdict, the operator is told again, there, and the page is not scrolled back up to it.
    page.locator("#confirm").scroll_into_view_if_needed()
    expect_in_viewport(page.locator("#confirm"))
    before, scroll_before = boxes_of(page, {**CLICKED, "confirm": "#confirm"}), page.evaluate("window.scrollY")
    assert scroll_before > 0
    third = searched_elsewhere(page, api, seq_id, {"method": "bright_pair", "max_candidates": n + 1})
    assert third["search_id"] != second["search_id"] and len(third["candidates"]) == n
    expect_text(notice, f"a new search \\(#{third['search_id']}\\) replaced the candidates shown")
    assert_same_boxes(before, boxes_of(page, {**CLICKED, "confirm": "#confirm"}))
    assert page.evaluate("window.scrollY") == scroll_before
    expect_in_viewport(notice)
    box = notice.bounding_box()
    assert box["y"] >= topbar["y"] + topbar["height"]   # held just under the top bar, not under it
    # ... and as tall as its words (one or two lines here, with the sequence's name), not the header card's height,
    # over whatever is there.
    lines = notice.evaluate("e => { const s = getComputedStyle(e); return (e.clientHeight - parseFloat(s.paddingTop)"
                            " - parseFloat(s.paddingBottom)) / parseFloat(s.lineHeight); }")
    assert lines < 2.5 and abs(lines - round(lines)) < 0.2, f"held over the page, the notice is {lines:.1f} lines high"
    for sel in ("#cand-prev", "#cand-next", "#confirm", "#reject-open"):
        assert not boxes_overlap(box, page.locator(sel).bounding_box()), f"the notice lies over {sel}"
    watched.screenshot(f"19-change-notice-scrolled-{width}")

    # Read, it can be put away from the keyboard (it also goes with this console's verdict, as before).
    page.locator("#change-notice-close").focus()
    page.keyboard.press("Enter")
    expect_visible(notice, False)
    assert_same_boxes(before, boxes_of(page, {**CLICKED, "confirm": "#confirm"}))
    assert unexpected_errors(watched) == []


def test_the_pattern_table_shows_a_whole_pattern(server, api, new_page, tmp_path):
    """A pattern of a dozen points is listed whole: the table does not hide its last rows in a box that
    scrolls without showing a scrollbar (headless and overlay scrollbars show none)."""
    seq_id, _ = upload_and_search(api, fresh_copy("10-narrow-12deg-ghosts.json", "rows", tmp_path))
    n_rows = len(api(f"/api/sequences/{seq_id}")["extraction"]["pattern"])
    assert n_rows >= 12
    watched, _ = console(new_page, server)
    page = watched.page
    open_sequence(page, seq_id, "10-narrow-12deg-ghosts-rows")
    rows = page.locator("#pattern-rows tr")
    assert rows.count() == n_rows
    wrap = page.locator("#pattern-wrap").bounding_box()
    last = rows.nth(n_rows - 1).bounding_box()
    assert last["y"] + last["height"] <= wrap["y"] + wrap["height"] + 1
    expect_visible(page.locator("#pattern-more"), False)

    # Ten points picked by hand besides: longer than the table, which then says that it scrolls.
    picked = [{"snapshot": 0, "x": 40.0 + 60 * k, "y": 50.0} for k in range(10)]
    api(f"/api/sequences/{seq_id}/pattern", "PUT", body={"manual_points": picked})
    page.reload()
    page.wait_for_selector("body[data-ready='1']")
    open_sequence(page, seq_id, "10-narrow-12deg-ghosts-rows")
    expect_text(page.locator("#pattern-more"), rf"{n_rows + 10} rows: scroll the table for \d+ more")


def test_a_comment_stays_with_its_sequence(server, api, new_page, tmp_path):
    """A comment typed for one sequence is not carried to the next one opened (where Confirm would have
    stored it with the wrong attitude)."""
    first, _ = upload_and_search(api, fresh_copy("01-clean.json", "comment-a", tmp_path))
    second, _ = upload_and_search(api, fresh_copy("03-jupiter.json", "comment-b", tmp_path))
    watched = operator_on(new_page, server, "Commenter", first, "01-clean-comment-a")
    page = watched.page
    page.fill("#comment", "about the first sequence")
    open_sequence(page, second, "03-jupiter-comment-b")
    assert page.locator("#comment").input_value() == ""
    # Jupiter explains the point no star does, and the candidate's facts say so (not only "12 of 13").
    expect_text(page.locator("#cand-facts"), r"12 of 13 points, and 1 to jupiter \(a planet: no catalogue star")
    assert unexpected_errors(watched) == []


def test_j_after_a_confirmation_goes_to_the_sequence_that_followed_it(server, api, new_page, tmp_path):
    """In "needs an operator first" a confirmed sequence moves to the end of the queue; j then opens the
    sequence that followed it when it was opened, not one after its new place (finished work)."""
    for sample in ("01-clean.json", "03-jupiter.json", "04-big-dipper.json"):
        upload_and_search(api, fresh_copy(sample, "jnav", tmp_path))
    watched, _ = console(new_page, server)
    page = watched.page
    page.fill("#operator", "Stepper")
    page.select_option("#sort-order", "queue")
    page.fill("#filter-search", "jnav")
    rows = page.locator("#sequence-list li[data-id]")
    expect_text(page.locator("#seq-page-info"), "1-3 of 3")
    names = [rows.nth(k).locator(".seq-name").inner_text() for k in range(3)]
    rows.nth(0).click()
    expect_text(page.locator("#seq-title"), re.escape(names[0]))
    expect_text(page.locator("#cand-verdict"), "Rank 1 is credible")
    press(page, "c")
    expect_text(page.locator("#seq-status"), "confirmed")
    expect_text(page.locator("#sequence-list li[data-id]").last, re.escape(names[0]))  # moved to the end
    press(page, "j")
    expect_text(page.locator("#seq-title"), re.escape(names[1]))
    press(page, "j")
    expect_text(page.locator("#seq-title"), re.escape(names[2]))
    # Opened from a queue filtered down to it alone, then the filter widened: j goes on in the list as it is.
    page.fill("#filter-search", names[2])
    expect_text(page.locator("#seq-page-info"), "1-1 of 1")
    page.locator("#sequence-list li[data-id]").first.click()
    page.fill("#filter-search", "jnav")
    expect_text(page.locator("#seq-page-info"), "1-3 of 3")
    listed = [rows.nth(k).locator(".seq-name").inner_text() for k in range(3)]
    at = listed.index(names[2])
    assert at > 0
    press(page, "k")
    expect_text(page.locator("#seq-title"), re.escape(listed[at - 1]))
    assert unexpected_errors(watched) == []


def test_no_valid_attitude_refused_after_another_verdict_shows_that_verdict(server, api, new_page, tmp_path):
    """This console opens "no valid attitude" while another operator confirms the sequence through the API
    and before this console's polling has noticed (its reads of the view are answered with the view as it
    was): the server refuses the rejection (409, it would replace a verdict unasked), and the console must
    close the step and show the other operator's confirmation."""
    seq_id, search = upload_and_search(api, fresh_copy("01-clean.json", "late-reject", tmp_path))
    assert search["status"] == "identified"
    watched = operator_on(new_page, server, "Late Rejecter", seq_id, "01-clean-late-reject")
    page = watched.page
    expect_text(page.locator("#cand-verdict"), "Rank 1 is credible")
    hold_back_polling(page)
    press(page, "r")
    expect_visible(page.locator("#reject-step"))
    page.fill("#reject-reason", "looks like a ghost pattern")
    confirmed = api(f"/api/sequences/{seq_id}/confirm", "POST",
                    body={"rank": 1, "operator": "Other Operator", "search_id": search["search_id"]})
    page.click("#reject-confirm")
    # Said in the console's words (the server's named the API's supersede field).
    said = (f"Not recorded: another console gave the verdict first: attitude #{confirmed['id']} (rank 1) confirmed "
            f"by Other Operator at {utc_text(confirmed['confirmed_at'])}. To replace it, record it again (the "
            "replaced verdict stays in the audit trail)")
    expect_text(page.locator("#toast"), f"^{re.escape(said)}$")
    expect_visible(page.locator("#reject-step"), False)
    expect_text(page.locator("#confirmed"), "Other Operator")
    review = api(f"/api/sequences/{seq_id}/review")
    assert review["rejection"] is None and review["confirmation"]["id"] == confirmed["id"]
    assert unexpected_errors(watched) == []


def test_the_work_queue_puts_what_needs_an_operator_first(server, api, new_page, tmp_path):
    ambiguous = make_ambiguous(api, "01-clean.json", "queue", tmp_path)
    upload_and_search(api, fresh_copy("05-earth.json", "queue", tmp_path))
    api("/api/sequences", "POST", raw=fresh_copy("07-single.json", "queue", tmp_path).read_bytes())  # stays new
    for name in ("01-clean.json", "03-jupiter.json", "08-csv.csv"):
        api("/api/sequences", "POST", raw=(SAMPLES / name).read_bytes())
    total = api("/api/sequences?limit=1")["total"]
    assert total > 8
    watched, _ = console(new_page, server)
    page = watched.page
    assert page.locator("#sort-order").input_value() == "queue"
    items = page.locator("#sequence-list li[data-status]")
    expect_text(page.locator("#seq-page-info"), rf"of {total}")
    statuses = [items.nth(k).get_attribute("data-status") for k in range(items.count())]
    assert items.count() == min(total, 20) > 8  # more than 8 per page
    assert statuses[0] == "ambiguous" and "no_match" in statuses
    ranks = [QUEUE_ORDER.index(s) for s in statuses]
    assert ranks == sorted(ranks), statuses
    assert page.locator("#sequence-list li").first.get_attribute("data-id") == str(ambiguous)
    # The server's order agrees with the page.
    assert [s["id"] for s in api("/api/sequences?order=queue&limit=20")["items"]] == \
        [int(items.nth(k).get_attribute("data-id")) for k in range(items.count())]
    # Filter by status and search by sequence id.
    page.select_option("#filter-status", "no_match")
    expect_text(page.locator("#seq-page-info"), r"\d")
    page.wait_for_function("[...document.querySelectorAll('#sequence-list li[data-status]')]"
                           ".every((li) => li.dataset.status === 'no_match')")
    page.select_option("#filter-status", "")
    page.fill("#filter-search", "01-clean-queue")
    page.wait_for_function(f"document.querySelectorAll('#sequence-list li[data-id]').length === 1 && "
                           f"document.querySelector('#sequence-list li[data-id]').dataset.id === '{ambiguous}'")
    watched.screenshot("13-queue")
    assert watched.errors == []


def test_the_sky_view_explains_itself(server, api, new_page, tmp_path):
    seq_id, search = upload_and_search(api, fresh_copy("04-big-dipper.json", "sky", tmp_path))
    watched, _ = console(new_page, server)
    page = watched.page
    open_sequence(page, seq_id, "04-big-dipper-sky")
    canvas = page.locator("#sky-canvas")
    page.wait_for_function("document.getElementById('sky-canvas').dataset.points")
    expect_visible(page.locator("#sky-legend"))
    expect_text(page.locator("#sky-legend"), "generating edge")

    # Labels: the track names of the matched points are drawn, and no two labels overlap.
    labels = json.loads(canvas.get_attribute("data-labels"))
    best = search["candidates"][0]
    tracks = {f"T{m['track']}" for m in best["matches"] if m["track"] is not None}
    assert tracks and tracks <= {lab["text"] for lab in labels if lab["kind"] == "track"}
    assert any(lab["text"] == "Dubhe" for lab in labels)
    boxes = [{"x": lab["x"], "y": lab["y"], "width": lab["w"], "height": lab["h"]} for lab in labels]
    assert not any(boxes_overlap(p, q) for i, p in enumerate(boxes) for q in boxes[i + 1:])

    # North and east: docs/conventions.md's roll is the position angle of the image's up (-y) from north through
    # east, so the arrows drawn must give back the candidate's roll.
    compass = page.evaluate("async (R) => (await import('/js/sky.js')).northEast(R)", best["rotation_matrix"])
    north, east = compass["north"], compass["east"]
    roll = math.degrees(math.atan2(-east[1], -north[1])) % 360
    assert abs((roll - best["roll_deg"] + 180) % 360 - 180) < 0.5
    assert abs(north[0] * east[0] + north[1] * east[1]) < 0.05  # at right angles on a 20 deg field

    # A tooltip names the point's track and star; a click rings the track in the snapshot player.
    points = json.loads(canvas.get_attribute("data-points"))
    point = next(p for p in points if p["track"] is not None and f"T{p['track']}" in tracks)
    canvas.scroll_into_view_if_needed()
    box = canvas.bounding_box()
    scale = box["width"] / page.evaluate("document.getElementById('sky-canvas').width")
    page.mouse.move(box["x"] + point["x"] * scale, box["y"] + point["y"] * scale)
    expect_visible(page.locator("#sky-tip"))
    expect_text(page.locator("#sky-tip"), rf"T{point['track']} → ")
    watched.screenshot("14-sky-tooltip")
    page.mouse.click(box["x"] + point["x"] * scale, box["y"] + point["y"] * scale)
    expect_text(page.locator("#toast"), rf"T{point['track']} is ringed in the snapshots")
    # What deviation and false-match probability mean is one hover away.
    assert "nearest catalogue star" in page.locator("#candidates-table th").nth(1).get_attribute("title")
    assert "chance alignment" in page.locator("#candidates-table th").nth(4).get_attribute("title")
    assert "chance alignment" in page.locator("#cand-facts dt", has_text="false match").get_attribute("title")
    assert watched.errors == []


def test_keyboard_search_methods_and_the_remembered_operator(server, api, new_page, tmp_path):
    seq_id, search = upload_and_search(api, fresh_copy("01-clean.json", "keys", tmp_path))
    n = len(search["candidates"])
    watched, session = console(new_page, server)
    page = watched.page
    open_sequence(page, seq_id, "01-clean-keys")
    expect_text(page.locator("#cand-rank"), rf"rank 1 of {n}")
    press(page, "?")
    expect_visible(page.locator("#help"))
    expect_text(page.locator("#help"), "confirm the candidate shown")
    watched.screenshot("15-help")
    page.keyboard.press("Escape")
    expect_visible(page.locator("#help"), False)
    page.keyboard.press("2")
    expect_text(page.locator("#cand-rank"), rf"rank 2 of {n}")
    page.keyboard.press("ArrowLeft")
    expect_text(page.locator("#cand-rank"), rf"rank 1 of {n}")
    page.keyboard.press(" ")
    expect_text(page.locator("#play"), "Pause")
    page.keyboard.press(" ")
    expect_text(page.locator("#play"), "Play")
    # j and k walk the work queue: the next sequence opens, and this console's view follows.
    ids = [int(page.locator("#sequence-list li[data-id]").nth(k).get_attribute("data-id"))
           for k in range(page.locator("#sequence-list li[data-id]").count())]
    page.fill("#filter-search", "")
    page.wait_for_function(f"document.querySelectorAll('#sequence-list li[data-id]').length > {len(ids)}")
    queue = [int(page.locator("#sequence-list li[data-id]").nth(k).get_attribute("data-id"))
             for k in range(page.locator("#sequence-list li[data-id]").count())]
    at = queue.index(seq_id)
    step = "j" if at + 1 < len(queue) else "k"
    other = queue[at + 1] if step == "j" else queue[at - 1]
    press(page, step)
    page.wait_for_function(f"document.querySelector('#sequence-list li.selected')?.dataset.id === '{other}'")
    assert wait_for(lambda: api(f"/api/view?session={session}")["sequence"], lambda v: v == other) == other
    press(page, "k" if step == "j" else "j")
    expect_text(page.locator("#seq-title"), "01-clean-keys")

    # Triangle features with the key s: a search of its own, by that method.
    page.select_option("#search-method", "tf")
    press(page, "s")
    detail = wait_for(lambda: api(f"/api/sequences/{seq_id}"), lambda d: d["search"]["method"] == "tf")
    assert detail["search"]["method"] == "tf"
    expect_text(page.locator("#search-summary"), "by triangle features")

    # Tracking from a prior taken from the candidate shown and edited: it finds the same attitude.
    page.select_option("#search-method", "tracking")
    expect_visible(page.locator("#prior-box"))
    page.click("#prior-from-candidate")
    assert page.locator("#prior-given").is_checked()
    ra = float(page.input_value("#prior-ra"))
    page.fill("#prior-ra", f"{ra + 0.3:.4f}")  # 0.3 deg off, within the prior's 1 deg
    page.click("#search")
    detail = wait_for(lambda: api(f"/api/sequences/{seq_id}"), lambda d: d["search"]["method"] == "tracking")
    found = detail["search"]["candidates"][0]
    best = search["candidates"][0]
    assert detail["search"]["status"] == "identified"
    assert abs(found["ra_deg"] - best["ra_deg"]) < 0.05 and abs(found["dec_deg"] - best["dec_deg"]) < 0.05
    # ... and from the spacecraft's last confirmed attitude (no prior sent).
    api(f"/api/sequences/{seq_id}/confirm", "POST", body={"rank": 1, "operator": "keys", "supersede": True})
    page.check("#prior-last")
    search_id = detail["search"]["search_id"]
    page.click("#search")
    detail = wait_for(lambda: api(f"/api/sequences/{seq_id}"), lambda d: d["search"]["search_id"] != search_id)
    assert detail["search"]["method"] == "tracking" and detail["search"]["candidates"]

    # The operator's name is remembered by the browser.
    page.fill("#operator", "Kay Board")
    page.locator("#operator").dispatch_event("change")
    page.reload()
    page.wait_for_selector("body[data-ready='1']")
    assert page.input_value("#operator") == "Kay Board"
    assert watched.errors == []


@pytest.mark.parametrize("width", [1280, 1024])
def test_every_screen_is_usable_and_nothing_is_cut_or_covered(server, api, new_page, tmp_path, width):
    seq_id, _ = upload_and_search(api, fresh_copy("02-ghosts-hot-pixels.json", f"layout{width}", tmp_path))
    # A confirmed attitude with long numbers (negative Dec) for the attitude table.
    api(f"/api/sequences/{seq_id}/confirm", "POST", body={"rank": 1, "operator": "Layout Operator"})
    watched, _ = console(new_page, server, width=width, height=800)
    page = watched.page
    watched.screenshot(f"20-start-{width}")
    page.fill("#operator", "Layout Operator")
    open_sequence(page, seq_id, f"02-ghosts-hot-pixels-layout{width}")
    page.wait_for_function("document.getElementById('sky-canvas').dataset.points")
    page.evaluate("window.scrollTo(0, 0)")
    # No horizontal scrolling of the page at this width.
    assert page.evaluate("document.documentElement.scrollWidth") <= width
    # The confirmed attitudes' numbers are never cut.
    cut = page.evaluate("""[...document.querySelectorAll('#attitude-list td.num div')]
        .filter((d) => d.scrollWidth > d.clientWidth + 0.5 || d.closest('td').scrollWidth > d.closest('td').clientWidth + 0.5)
        .map((d) => d.textContent)""")
    assert page.locator("#attitude-list td.num").count() >= 1 and cut == []
    # Nor are the candidates side by side (the table fits its box).
    assert page.evaluate("(() => { const w = document.querySelector('.candidates-wrap'); "
                         "return w.scrollWidth <= w.clientWidth + 1; })()")
    # A message shows in the header's status line and covers no list and no link.
    page.locator("#candidate-rows tr[data-rank='2']").click()
    press(page, "ArrowLeft")
    page.keyboard.press("ArrowLeft")
    expect_visible(page.locator("#toast"))
    toast = page.locator("#toast").bounding_box()
    covered = []
    for selector in ("#sequence-list", "#attitude-list", "#upload-list", "#candidate-rows", "a", "button"):
        for k in range(page.locator(selector).count()):
            item = page.locator(selector).nth(k)
            box = item.bounding_box()
            if box and box["width"] and item.is_visible() and boxes_overlap(toast, box):
                covered.append(selector)
    assert covered == []
    watched.screenshot(f"21-candidates-{width}")
    page.locator("#candidate-card").scroll_into_view_if_needed()
    watched.screenshot(f"22-candidate-card-{width}")
    page.locator("#candidate-rows tr[data-rank='2']").click()
    page.click("#confirm")
    expect_visible(page.locator("#override-step"))
    page.locator("#decision").scroll_into_view_if_needed()
    watched.screenshot(f"23-second-step-{width}")
    page.keyboard.press("Escape")
    press(page, "?")
    expect_visible(page.locator("#help"))
    watched.screenshot(f"24-help-{width}")
    page.keyboard.press("Escape")
    page.click("#tab-3d")
    expect_text(page.locator("#viewer-note"), "this console's selection")
    expect_text(page.frame_locator("#viewer-frame").locator("body"), r"Rank \d+ of", timeout=40_000)
    # Opened from deep in the sequence tab, the 3D view shows at the top, not scrolled out of view.
    assert page.locator("#viewer-frame").bounding_box()["y"] < 200
    page.wait_for_timeout(1500)  # let the software renderer draw the sphere before the screenshot
    watched.screenshot(f"25-3d-tab-{width}")
    # Back on the sequence tab, the decision is where the operator left it.
    page.click("#tab-work")
    expect_in_viewport(page.locator("#decision"))
    assert watched.errors == []


def test_bulk_aem_export_from_the_console(server, api, new_page, tmp_path):
    seq_id, _ = upload_and_search(api, fresh_copy("03-jupiter.json", "bulk", tmp_path))
    api(f"/api/sequences/{seq_id}/confirm", "POST", body={"rank": 1, "operator": "bulk"})
    current = [a for a in api("/api/attitudes?limit=1000")["items"] if a["current"] and a["spacecraft"] == "SIM-TUBSAT"]
    watched, _ = console(new_page, server)
    page = watched.page
    page.click("#bulk-export summary")
    page.select_option("#bulk-spacecraft", "SIM-TUBSAT")
    with page.expect_download() as info:
        page.click("#bulk-go")
    text = open(info.value.path(), encoding="utf-8").read()
    assert info.value.suggested_filename.endswith(".aem")
    assert text.startswith("CCSDS_AEM_VERS") and text.count("META_START") == len(current) >= 1
    assert f"archive id {seq_id})" in text
    # A range with nothing in it says so instead of downloading an empty file.
    page.fill("#bulk-start", "1990-01-01T00:00:00")
    page.fill("#bulk-end", "1990-01-02T00:00:00")
    page.click("#bulk-go")
    expect_text(page.locator("#toast"), "No AEM: no confirmed attitude of spacecraft 'SIM-TUBSAT'")
    assert watched.errors == [] or all("404" in e for e in watched.errors)


def test_a_focal_length_the_stars_contradict_is_named_above_the_verdict(server, api, new_page, tmp_path):
    """A single snapshot seen 8 % off a camera declared to 5 %: nothing is identified, and a warning above
    the verdict (where an operator looks first) names the focal length the stars fit and where they put the
    camera, once (not again in the search summary); a clean sample shows none.  The header counts one
    snapshot (not "1 snapshots") and a whole sample sixteen."""
    from app.cli import main as cli_main

    assert cli_main(["simulate", str(tmp_path), "--n", "1", "--seed", "5", "--scenario", "single",
                     "--focal-error", "0.08", "--name", "focal-8-percent"]) == 0
    [path] = [p for p in tmp_path.glob("*.json") if not p.name.endswith(".truth.json")]
    seq_id, search = upload_and_search(api, path)
    assert search["status"] != "identified"
    name = json.loads(path.read_text())["sequence_id"]
    watched = operator_on(new_page, server, "Focal Watcher", seq_id, name)
    page = watched.page
    expect_text(page.locator("#seq-meta"), r"· 1 snapshot from ")
    warning = page.locator("#focal-contradiction")
    expect_text(warning, r"^⚠ The stars contradict the declared focal length\s*The pattern's bright triangles fit a "
                         r"focal length of 2\d{3}\.\d px \(\+8\.\d% of the declared\), outside its tolerance of "
                         r"5\.0%, with \d+ of \d+ points on stars near RA \d+\.\d deg, Dec [+-]\d+\.\d deg: .*search "
                         r"again\.$")
    found = search["focal_length_contradiction"]
    assert f"{found['focal_length_px']:.1f} px" in warning.inner_text()
    assert "bright triangles" not in page.locator("#search-summary").inner_text()
    warning.scroll_into_view_if_needed()
    watched.screenshot("17-focal-length-contradicted")
    clean_id = api("/api/sequences", "POST", raw=fresh_copy("01-clean.json", "focal", tmp_path).read_bytes())["id"]
    open_sequence(page, clean_id, "01-clean-focal")
    expect_text(page.locator("#seq-meta"), r"· 16 snapshots from ")
    expect_visible(warning, False)
    assert unexpected_errors(watched) == []


def test_a_verdict_given_elsewhere_first_is_named_in_the_consoles_words(server, api, new_page, tmp_path):
    """This console has the second step open for rank 2 when another one confirms rank 1 (this console's
    reads of the view are held back: it has not noticed).  Its Confirm anyway is refused (409); the status
    line then names the verdict that came first, who gave it and when, and how to replace it here, not the
    API's "Send supersede: true"."""
    seq_id, search = upload_and_search(api, fresh_copy("10-narrow-12deg-ghosts.json", "overtaken", tmp_path))
    assert search["status"] == "identified" and len(search["candidates"]) >= 2
    watched = operator_on(new_page, server, "Second Op", seq_id, "10-narrow-12deg-ghosts-overtaken")
    page = watched.page
    page.locator("#candidate-rows tr[data-rank='2']").click()
    page.click("#confirm")
    expect_visible(page.locator("#override-step"))
    page.fill("#override-reason", "rank 1 is a ghost pattern")
    hold_back_polling(page)
    first = api(f"/api/sequences/{seq_id}/confirm", "POST", body={"rank": 1, "operator": "First Op"})
    page.click("#confirm-override")
    said = (f"Not confirmed: another console gave the verdict first: attitude #{first['id']} (rank 1) confirmed by "
            f"First Op at {utc_text(first['confirmed_at'])}. To replace it, confirm again (the replaced verdict "
            "stays in the audit trail)")
    expect_text(page.locator("#toast"), f"^{re.escape(said)}$")
    expect_visible(page.locator("#override-step"), False)
    review = api(f"/api/sequences/{seq_id}/review")
    assert review["confirmation"]["id"] == first["id"] and len(review["audit"]) == 1
    assert unexpected_errors(watched) == []


def test_a_supersede_replaces_only_the_verdict_its_console_showed(server, api, new_page, tmp_path):
    """Alice has the step open to replace Bob's confirmation with rank 2 when Bob records "no valid attitude"
    (her reads of the view held back: she has not seen it).  Her Supersede is refused, Bob's verdict stays,
    and she is told whose verdict came first, in the console's words."""
    seq_id, search = upload_and_search(api, fresh_copy("10-narrow-12deg-ghosts.json", "seen", tmp_path))
    bob = api(f"/api/sequences/{seq_id}/confirm", "POST", body={"rank": 1, "operator": "Bob"})
    watched = operator_on(new_page, server, "Alice", seq_id, "10-narrow-12deg-ghosts-seen")
    page = watched.page
    page.locator("#candidate-rows tr[data-rank='2']").click()
    page.click("#confirm")
    expect_text(page.locator("#override-reasons"), re.escape(f"replaces the current verdict: attitude #{bob['id']} "
                                                             f"(rank 1) confirmed by Bob at {utc_text(bob['confirmed_at'])}"))
    page.fill("#override-reason", "rank 1 is a ghost pattern")
    hold_back_polling(page)
    rejected = api(f"/api/sequences/{seq_id}/reject", "POST", body={
        "reason": "every candidate is a ghost", "operator": "Bob", "supersede": True,
        "replaces": {"kind": "attitude", "id": bob["id"]}})
    page.click("#confirm-override")
    said = (f'Not confirmed: another console gave the verdict first: "no valid attitude" recorded by Bob at '
            f'{utc_text(rejected["rejected_at"])} ("every candidate is a ghost"). To replace it, confirm again '
            "(the replaced verdict stays in the audit trail)")
    expect_text(page.locator("#toast"), f"^{re.escape(said)}$")
    review = api(f"/api/sequences/{seq_id}/review")
    assert review["rejection"]["id"] == rejected["id"] and [e["kind"] for e in review["audit"]] == \
        ["confirmed", "rejected"]
    assert unexpected_errors(watched) == []
