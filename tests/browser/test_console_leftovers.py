"""The console's known leftovers of an operator trial, fixed, in a real Chromium: the sky chart's labels keep
clear of the tracks' circles, a point off the chart is drawn whole inside it, a success message is read
whole in the status line, a message about where the operator is goes when they move, a comment leaves
with the candidate it was typed for, and Next stays in its place from sequence to sequence.

Facts are read back from the server's API (the candidate view's pixels, the stored confirmation), never from
the page alone.  Screenshots: /tmp/leftovers-*.png.
"""

from __future__ import annotations

import json
import math
import re

from test_console_sessions import (console, expect_text, expect_value, expect_visible, fresh_copy, open_sequence,
                                   operator_on, press, upload_and_search)

#: The sky chart's pattern circles (static/js/sky.js POINT_RADIUS), in canvas pixels.
CIRCLE_RADIUS = 9
#: What "clear of a circle" means here: past the circle's stroke (1.6 px, 3.5 px when ringed) by a visible gap.
CLEAR_PX = CIRCLE_RADIUS + 3


def shot(target, name: str) -> None:
    """A screenshot of a page or an element, as /tmp/leftovers-NAME.png."""
    target.screenshot(path=f"/tmp/leftovers-{name}.png")


def box_distance(label: dict, x: float, y: float) -> float:
    """Distance from (x, y) to the nearest point of the label's box (0 inside it)."""
    dx = max(label["x"] - x, 0.0, x - label["x"] - label["w"])
    dy = max(label["y"] - y, 0.0, y - label["y"] - label["h"])
    return math.hypot(dx, dy)


def drawn(page, want: str) -> None:
    """Wait until the sky chart's ``data-view`` (``rank/magnitude limit``) ends with ``want``."""
    page.wait_for_function("(want) => ('/' + document.getElementById('sky-canvas').dataset.view).endsWith('/' + want)",
                           arg=want)


def show_sky(page, rank: int, mag: float) -> tuple[list[dict], list[dict]]:
    """The sky chart drawn at ``rank`` and magnitude limit ``mag`` (as the slider sets it): its labels and points."""
    page.evaluate("(mag) => { const s = document.getElementById('mag-slider'); if (Number(s.value) === mag) return; "
                  "s.value = mag; s.dispatchEvent(new Event('change')); }", mag)
    drawn(page, f"{mag:g}")     # first: the magnitude's redraw is of the rank shown before the key
    press(page, str(rank))
    drawn(page, f"{rank}/{mag:g}")
    canvas = page.locator("#sky-canvas")
    return json.loads(canvas.get_attribute("data-labels")), json.loads(canvas.get_attribute("data-points"))


# ---------------------------------------------------------------------------------------------------------

def test_no_label_comes_near_a_tracks_circle(server, api, new_page, tmp_path):
    """05-earth's candidates, every rank at three magnitude limits: a constellation's name sat on a track's
    circle ("Lyn" 0.2 px above T3's rim at rank 4 under magnitude 3, "CMa" beside T3 in the trial), the
    placement testing boxes against the circle's square and letting them touch.  Every label but a point's own
    (its track name, its matched star's name) now keeps CLEAR_PX from every circle's centre."""
    seq_id, search = upload_and_search(api, fresh_copy("05-earth.json", "clear", tmp_path))
    n = len(search["candidates"])
    assert n >= 2
    watched, _ = console(new_page, server)
    page = watched.page
    open_sequence(page, seq_id, "05-earth-clear")
    too_close, constellations = [], 0
    for mag in (3.0, 4.5, 6.0):
        for rank in range(1, n + 1):
            labels, points = show_sky(page, rank, mag)
            assert points and labels
            constellations += sum(label["kind"] == "constellation" for label in labels)
            too_close += [(mag, rank, label["text"], f"T{p['track']}", round(box_distance(label, p["x"], p["y"]), 2))
                          for label in labels for p in points
                          if label.get("owner") != f"p{p['index']}" and box_distance(label, p["x"], p["y"]) < CLEAR_PX]
            if (mag, rank) == (3.0, 4):
                page.locator("#sky-canvas").scroll_into_view_if_needed()
                shot(page.locator("#sky-canvas"), "01-labels-clear-rank4-mag3")
    assert too_close == []
    assert constellations >= 2 * n  # names are drawn, not dropped to keep clear
    assert watched.errors == []


def test_a_point_off_the_chart_is_drawn_whole_inside_it(server, api, new_page, tmp_path):
    """09-wide-30deg's pattern has tracks carried far off the sensor (x = -296 px of 576): their circles were cut
    by the canvas edge or not drawn at all.  Every circle is now whole on the canvas: where it lies when it fits,
    else pinned inside the edge with an arrow towards where it lies, and its tooltip says so."""
    seq_id, search = upload_and_search(api, fresh_copy("09-wide-30deg.json", "offchart", tmp_path))
    assert search["status"] == "identified"
    sky = api(f"/api/sequences/{seq_id}/candidates/1?mag=6")["sky"]
    b = sky["bounds"]
    width = 640  # the canvas's width (static/index.html); its height follows the section's aspect
    scale = width / (b["x_max"] - b["x_min"])
    height = round((b["y_max"] - b["y_min"]) * scale)
    where = {p["index"]: ((p["x"] - b["x_min"]) * scale, (p["y"] - b["y_min"]) * scale)
             for p in sky["pattern_points"] if p["x"] is not None}
    r = CIRCLE_RADIUS
    cut = {i for i, (x, y) in where.items() if x - r < 0 or y - r < 0 or x + r > width or y + r > height}
    assert len(cut) >= 3  # the sample's far tracks

    watched, _ = console(new_page, server)
    page = watched.page
    open_sequence(page, seq_id, "09-wide-30deg-offchart")
    show_sky(page, 1, 6.0)
    canvas = page.locator("#sky-canvas")
    assert (int(canvas.get_attribute("width")), int(canvas.get_attribute("height"))) == (width, height)
    points = {p["index"]: p for p in json.loads(canvas.get_attribute("data-points"))}
    assert set(points) == set(where)
    assert {i for i, p in points.items() if p["pinned"]} == cut
    for i, p in points.items():
        assert r <= p["x"] <= width - r and r <= p["y"] <= height - r, p   # whole on the canvas
        if i not in cut:
            assert math.hypot(p["x"] - where[i][0], p["y"] - where[i][1]) < 0.01  # where it lies
    # Pixels: each pinned circle's rim is drawn all round, and its arrow between the rim and the edge points
    # to where the point lies.
    pixels = page.evaluate("""(pts) => { const ctx = document.getElementById('sky-canvas').getContext('2d');
        const lit = (x, y) => { const d = ctx.getImageData(Math.round(x), Math.round(y), 1, 1).data;
                                return Math.max(d[0], d[1], d[2]) > 90; };
        return pts.map(([x, y, ux, uy]) => ({
          rim: Array.from({ length: 24 }, (_, k) => [0, 0.5, -0.5].some((dr) =>
            lit(x + (9 + dr) * Math.cos(k * Math.PI / 12), y + (9 + dr) * Math.sin(k * Math.PI / 12)))).filter(Boolean).length,
          arrow: [12, 14, 16].filter((d) => lit(x + ux * d, y + uy * d)).length })); }""",
        [[points[i]["x"], points[i]["y"], *unit(where[i][0] - points[i]["x"], where[i][1] - points[i]["y"])]
         for i in sorted(cut)])
    assert all(p["rim"] >= 22 and p["arrow"] >= 2 for p in pixels), pixels
    # The tooltip says where it lies.
    far = max(cut, key=lambda i: abs(where[i][0] - points[i]["x"]) + abs(where[i][1] - points[i]["y"]))
    canvas.scroll_into_view_if_needed()
    box = canvas.bounding_box()
    css = box["width"] / width
    page.mouse.move(box["x"] + points[far]["x"] * css, box["y"] + points[far]["y"] * css)
    expect_text(page.locator("#sky-tip"), r"off the chart at \(-?\d+, -?\d+\) px of the reference snapshot")
    shot(canvas, "02-off-chart-pinned")
    assert watched.errors == []


def unit(dx: float, dy: float) -> tuple[float, float]:
    n = math.hypot(dx, dy)
    return dx / n, dy / n


def test_a_success_message_is_read_whole_and_bounded(server, api, new_page, tmp_path):
    """A success was cut to one line in the status line (whole only on hover and in the log).  At 1280 px,
    where the status line shares the header's row, a pattern edit's message wraps, whole and uncut; a very long
    one stops growing at four lines and scrolls in its box, opening over the page without moving it.  At
    1024 px the status line has a row of its own, where the message is one line (it had 140 px there)."""
    seq_id, _ = upload_and_search(api, fresh_copy("01-clean.json", "toast", tmp_path))
    watched, _ = console(new_page, server)
    page = watched.page
    open_sequence(page, seq_id, "01-clean-toast")
    header_before = page.locator(".topbar").bounding_box()["height"]
    player_before = page.locator("#player-canvas").bounding_box()
    page.locator("#pattern-rows tr[data-track] input[type=checkbox]").first.click()
    toast = page.locator("#toast")
    expect_text(toast, r"^Pattern version \d+: track T\d+ changed, \d+ points\. Press Search to identify it\.$")
    version = api(f"/api/sequences/{seq_id}")["pattern"]["version"]
    assert f"Pattern version {version}:" in toast.inner_text()
    fit = toast.evaluate("e => ({ sw: e.scrollWidth, cw: e.clientWidth, sh: e.scrollHeight, ch: e.clientHeight, "
                         "lh: parseFloat(getComputedStyle(e).lineHeight) })")
    assert fit["sw"] <= fit["cw"] and fit["sh"] <= fit["ch"], fit   # nothing cut
    assert fit["ch"] > 1.5 * fit["lh"], fit                          # wrapped at this width, not cut
    shot(page.locator(".topbar"), "03-toast-wrapped-1280")
    said = toast.inner_text()

    long = " ".join(f"Sentence {k} of a long success message that says what was done." for k in range(40))
    page.evaluate("(text) => import('/js/dom.js').then((m) => m.toast(text))", long)
    expect_text(toast, "^Sentence 0 ")
    assert toast.evaluate("e => e.textContent") == long             # all of it, not its first line
    fit = toast.evaluate("e => ({ sh: e.scrollHeight, ch: e.clientHeight, lh: parseFloat(getComputedStyle(e).lineHeight),"
                         " oy: getComputedStyle(e).overflowY })")
    assert fit["ch"] <= 4 * fit["lh"] + 12 + 1 and fit["sh"] > fit["ch"] and fit["oy"] == "auto", fit
    # The header keeps its height, and the page does not move under the operator's pointer: the message opens
    # downwards over the sequence's header card (a header that grew with it moved everything by 1-3 lines,
    # and a click computed before a message came landed beside its source).
    assert page.locator(".topbar").bounding_box()["height"] == header_before
    assert page.locator("#player-canvas").bounding_box() == player_before
    toast_box = toast.bounding_box()
    assert toast_box["y"] + toast_box["height"] > header_before   # it does open over the page
    shot(page.locator(".topbar"), "04-toast-long-bounded")
    assert watched.errors == []

    narrow, _ = console(new_page, server, width=1024)
    narrow.page.evaluate("(text) => import('/js/dom.js').then((m) => m.toast(text))", said)
    toast = narrow.page.locator("#toast")
    expect_text(toast, f"^{re.escape(said)}$")
    fit = toast.evaluate("e => ({ sw: e.scrollWidth, cw: e.clientWidth, sh: e.scrollHeight, ch: e.clientHeight, "
                         "lh: parseFloat(getComputedStyle(e).lineHeight) })")
    assert fit["sw"] <= fit["cw"] and fit["sh"] <= fit["ch"] < 1.5 * fit["lh"] + 12, fit
    assert toast.bounding_box()["width"] > 900
    shot(narrow.page.locator(".topbar"), "05-toast-row-1024")


def test_a_message_about_where_the_operator_is_goes_when_they_move(server, api, new_page, tmp_path):
    """"Last sequence of this page" stayed in the status line after `k` had moved back.  The page's toast timer
    is held (its 5 s would hide any message in time), so only the move can take it away."""
    ids = {}
    for tag in ("lastpage-a", "lastpage-b"):
        ids[tag] = api("/api/sequences", "POST", raw=fresh_copy("07-single.json", tag, tmp_path).read_bytes())["id"]
    watched = new_page()
    page = watched.page
    page.add_init_script("""(() => { const plain = window.setTimeout;
        window.setTimeout = (f, ms, ...rest) => (ms >= 5000 ? 0 : plain(f, ms, ...rest)); })();""")
    page.goto(server + "/")
    page.wait_for_selector("body[data-ready='1']")
    page.fill("#filter-search", "07-single-lastpage")
    rows = page.locator("#sequence-list li")
    expect_text(rows.nth(1), "lastpage")
    assert rows.count() == 2
    first_id, last_id = (int(rows.nth(k).get_attribute("data-id")) for k in (0, 1))
    assert {first_id, last_id} == set(ids.values())
    rows.nth(1).click()
    expect_text(page.locator("#seq-title"), "lastpage")
    press(page, "j")
    toast = page.locator("#toast")
    expect_text(toast, "^Last sequence of this page$")
    expect_visible(toast)
    shot(page, "06-last-sequence-toast")
    press(page, "k")
    page.wait_for_function("(id) => document.querySelector('#sequence-list li.selected')?.dataset.id === String(id)",
                           arg=first_id)
    expect_visible(toast, False)
    shot(page, "07-moved-back-no-toast")
    # At the first sequence, `k` says so in turn: messages still show.
    press(page, "k")
    expect_text(toast, "^First sequence of this page$")
    expect_visible(toast)
    assert watched.errors == []


def test_a_comment_typed_here_leaves_with_its_candidate(server, api, new_page, tmp_path):
    """A comment typed in the console for rank 1 stayed in the box when the operator moved to rank 2, and would
    have been stored with rank 2's confirmation.  It goes with the candidate it was typed for, as the 3D view's
    comment goes with its step; one typed for rank 2 is stored with rank 2's confirmation."""
    seq_id, search = upload_and_search(api, fresh_copy("02-ghosts-hot-pixels.json", "comment", tmp_path))
    assert search["status"] == "identified" and len(search["candidates"]) >= 2
    watched = operator_on(new_page, server, "Comment Operator", seq_id, "02-ghosts-hot-pixels-comment")
    page = watched.page
    expect_text(page.locator("#cand-rank"), "^rank 1 of")
    page.fill("#comment", "written for rank 1")
    press(page, "ArrowRight")
    expect_text(page.locator("#cand-rank"), "^rank 2 of")
    expect_value(page.locator("#comment"), "")
    shot(page.locator("#decision"), "08-comment-left-with-rank-1")
    press(page, "ArrowLeft")
    expect_text(page.locator("#cand-rank"), "^rank 1 of")
    expect_value(page.locator("#comment"), "")          # gone, not hidden away for rank 1
    press(page, "ArrowRight")
    expect_text(page.locator("#cand-rank"), "^rank 2 of")
    page.fill("#comment", "written for rank 2")
    press(page, "c")                                    # rank 2 is not the credible best: the second step
    expect_visible(page.locator("#override-step"))
    expect_value(page.locator("#comment"), "written for rank 2")   # opening the step keeps it
    page.fill("#override-reason", "the operator's own check of rank 2")
    page.click("#confirm-override")
    expect_text(page.locator("#confirm"), r"Confirmed ✓")
    confirmation = api(f"/api/sequences/{seq_id}/review")["confirmation"]
    assert (confirmation["rank"], confirmation["comment"]) == (2, "written for rank 2")
    assert watched.errors == []


def test_next_candidate_stays_in_its_place_from_sequence_to_sequence(server, api, new_page, tmp_path):
    """The candidate card's head (‹ Prev, Next ›) sat under the pattern card, whose length follows its rows and
    notes: from one sequence to the next Next moved by up to 200 px, and a click meant for it landed on the
    snapshots and took a track out of the pattern.  The pattern card now keeps the snapshots' height, its table
    and notes scrolling inside it, and an image pass's frame panel comes after the candidates, so Next is at
    the same place of the page for a long pattern, a short one and a pass of frames, at 1280 and 1920 px."""
    from test_console_frames import upload_pass, wait_for_frame

    # Long: 09-wide-30deg's 22 tracks and ten points picked by hand after its search (whose summary then says
    # it is stale); short: 05-earth's four tracks; and a pass of frames.
    long_id, _ = upload_and_search(api, fresh_copy("09-wide-30deg.json", "nextstill", tmp_path))
    picked = [{"snapshot": 0, "x": 40.0 + 50 * k, "y": 60.0} for k in range(10)]
    api(f"/api/sequences/{long_id}/pattern", "PUT", body={"manual_points": picked})
    short_id, _ = upload_and_search(api, fresh_copy("05-earth.json", "nextstill", tmp_path))
    # A sequence id, spacecraft and file name of the most characters the telemetry allows (128): the header
    # must not grow a line.
    long_name = fresh_copy("05-earth.json", "nextstill-long-name", tmp_path)
    doc = json.loads(long_name.read_text())
    doc["sequence_id"] = (doc["sequence_id"] + "-" + "long-name-" * 13)[:128]
    doc["spacecraft"] = ("SPACECRAFT-WITH-A-VERY-LONG-NAME-" * 4)[:128]
    long_name.write_text(json.dumps(doc))
    long_name_id, _ = upload_and_search(api, long_name)
    frames_id = upload_pass(server, "frames-nextstill", 518)["id"]
    api(f"/api/sequences/{frames_id}/search", "POST", body={})
    rows = {seq_id: len(api(f"/api/sequences/{seq_id}")["extraction"]["pattern"])
            for seq_id in (long_id, short_id, long_name_id)}
    rows[long_id] += len(picked)
    sequences = [(long_id, "09-wide-30deg-nextstill"), (short_id, "05-earth-nextstill"),
                 (frames_id, "frames-nextstill"), (long_name_id, doc["sequence_id"]),
                 (long_id, "09-wide-30deg-nextstill")]

    for width, height in ((1280, 800), (1920, 1080)):
        watched, _ = console(new_page, server, width=width, height=height)
        page = watched.page
        seen = {}
        for seq_id, name in sequences:
            open_sequence(page, seq_id, name)
            if seq_id == frames_id:
                wait_for_frame(page, int(page.locator("#frame-canvas").get_attribute("data-snapshot")))
            else:
                page.wait_for_function("(n) => document.querySelectorAll('#pattern-rows tr').length === n",
                                       arg=rows[seq_id])
            expect_text(page.locator("#search-summary"), "^Latest search: ")
            page.evaluate("window.scrollTo(0, 0)")
            # The pattern table's "scroll for more" is counted in the frame after its box changes size: two
            # frames on, the layout measured is the one the operator sees.
            page.evaluate("() => new Promise((done) => requestAnimationFrame(() => requestAnimationFrame(done)))")
            card = page.locator("#pattern-card").bounding_box()
            content = page.evaluate("""() => [...document.querySelectorAll('#pattern-card > *')]
                .filter((e) => e.offsetParent).map((e) => { const b = e.getBoundingClientRect();
                  return { id: e.id || e.className, top: b.top, bottom: b.bottom }; })""")
            # Nothing of the pattern card is cut or spills over: every part lies inside it.
            assert all(card["y"] - 0.5 <= c["top"] and c["bottom"] <= card["y"] + card["height"] + 0.5
                       for c in content), (width, name, card, content)
            seen[(seq_id, name)] = {"next": page.locator("#cand-next").bounding_box(),
                                    "header": page.locator(".seq-header").bounding_box()["height"],
                                    "summary": page.locator("#search-summary").inner_text(),
                                    "rows": page.locator("#pattern-rows tr").count()}
            if seq_id == long_name_id:  # the spacecraft's name is cut on its line, the whole text in the tooltip
                assert page.evaluate("() => { const e = document.querySelector('#seq-meta'); "
                                     "return e.scrollWidth > e.clientWidth && e.title === e.textContent; }")
                assert page.locator("#seq-title").get_attribute("title") == doc["sequence_id"]
            shot(page, f"09-next-{width}-{name[:40]}")
        long, short = seen[(long_id, "09-wide-30deg-nextstill")], seen[(short_id, "05-earth-nextstill")]
        assert long["rows"] >= 30 and short["rows"] <= 5 and "STALE" in long["summary"]
        assert len(long["summary"]) > len(short["summary"])
        # The last rows of the long pattern are reachable: the table says that it scrolls.
        expect_text(page.locator("#pattern-more"), rf"{long['rows']} rows: scroll the table for \d+ more")
        # The count follows the table's scrolling: none left at its end, the same again back at its top.
        before = page.locator("#pattern-more").inner_text()
        page.locator("#pattern-wrap").evaluate("(e) => { e.scrollTop = e.scrollHeight; }")
        expect_visible(page.locator("#pattern-more"), False)
        page.locator("#pattern-wrap").evaluate("(e) => { e.scrollTop = 0; }")
        expect_text(page.locator("#pattern-more"), re.escape(before))
        nexts = {name: s["next"] for (_, name), s in seen.items()}
        assert all(box == nexts["09-wide-30deg-nextstill"] for box in nexts.values()), (width, nexts)
        assert len({s["header"] for s in seen.values()}) == 1, (width, seen)
        # The sidebar keeps its width with that spacecraft in its AEM export's menu: its button takes its click.
        page.locator("#bulk-export summary").click()
        page.wait_for_function("(name) => [...document.querySelectorAll('#bulk-spacecraft option')]"
                               ".some((o) => o.value === name)", arg=doc["spacecraft"])
        page.select_option("#bulk-spacecraft", doc["spacecraft"])
        page.locator("#bulk-go").scroll_into_view_if_needed()
        go = page.locator("#bulk-go").bounding_box()
        assert page.evaluate("([x, y]) => document.elementFromPoint(x, y)?.id",
                             [go["x"] + go["width"] / 2, go["y"] + go["height"] / 2]) == "bulk-go"
        # And it is on the first screen.
        assert nexts["05-earth-nextstill"]["y"] + nexts["05-earth-nextstill"]["height"] <= height
        assert watched.errors == []


def test_a_slow_answer_to_an_earlier_filter_never_replaces_the_list_asked_for_since(server, api, new_page, tmp_path):
    """The work queue's list is read again at every filter, order and page; an answer that came late (a slow
    request, a busy server) was drawn over the answer to what the controls ask for now. Here the answer for
    "race-alpha" is held until the list shows "race-beta", then let go: the list stays race-beta's, and its
    page line too. (The confirmed attitudes' pages take the same numbered guard.)"""
    from playwright.sync_api import expect

    for tag in ("race-alpha", "race-beta"):
        api("/api/sequences", "POST", raw=fresh_copy("07-single.json", tag, tmp_path).read_bytes())
    watched, _ = console(new_page, server)
    page = watched.page
    held = []
    page.route(re.compile(r".*/api/sequences\?.*search=07-single-race-alpha.*"), lambda route: held.append(route))
    with page.expect_request(lambda r: "search=07-single-race-alpha" in r.url):
        page.fill("#filter-search", "07-single-race-alpha")
    with page.expect_response(lambda r: "search=07-single-race-beta" in r.url):
        page.fill("#filter-search", "07-single-race-beta")
    rows = page.locator("#sequence-list li")
    expect(rows).to_have_count(1)
    expect_text(rows.first, "race-beta")   # the answer to what the box now asks
    assert len(held) == 1
    with page.expect_response(lambda r: "search=07-single-race-alpha" in r.url):
        held[0].continue_()
    # The late answer is read and dropped within the same task as its arrival; two frames later it would show.
    page.evaluate("() => new Promise((done) => requestAnimationFrame(() => requestAnimationFrame(done)))")
    assert rows.count() == 1 and "race-beta" in rows.first.inner_text()
    assert page.locator("#seq-page-info").inner_text() == "1-1 of 1"

    assert watched.errors == []
