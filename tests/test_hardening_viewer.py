"""Issue 12, item 6: telemetry-derived text in the 3D view's panel is shown as text, never as markup.

viser renders the panel's Markdown with raw HTML allowed; markdown-it (a
CommonMark renderer) with HTML enabled stands in for it here: what the
escaped text renders to must contain no element but the paragraph, and its
text must be the original string, character for character.
"""

from __future__ import annotations

import html
import re
from datetime import timezone
from pathlib import Path

import pytest
from markdown_it import MarkdownIt

from app.viewer.server import markdown_text, panel_title

RENDERER = MarkdownIt("commonmark", {"html": True})

HOSTILE = [
    "<img src=x onerror=alert(1)>**bold** [link](http://e.com)",
    "<script>alert(1)</script>",
    "`code` _em_ *em* ~~strike~~ # heading",
    "![image](http://e.com/x.png) <http://e.com> [ref]: http://e.com",
    "&lt;b&gt; &amp; &#60;i&#62; \\*not emphasis\\*",
    "1. a list\n- another\n> quote\n---",
    "| a | b |\n|---|---|",
    "A-0427",
    "ünïcödé ✓ 星",
]


def rendered_text(markdown: str) -> tuple[str, list[str]]:
    """(the text a browser would show, the tags it would create) of ``markdown``."""
    out = RENDERER.render(markdown)
    tags = re.findall(r"<\s*([a-zA-Z0-9]+)", out)
    return html.unescape(re.sub(r"<[^>]+>", "", out)).strip(), tags


@pytest.mark.parametrize("value", HOSTILE)
def test_escaped_text_renders_as_exactly_its_characters(value):
    text, tags = rendered_text(markdown_text(value))
    assert tags == ["p"]
    assert text == " ".join(value.splitlines())


def test_the_renderer_stand_in_does_render_markup_unescaped():
    """The check above can fail: unescaped, the issue's sequence id becomes an image, bold text and a link."""
    _, tags = rendered_text(HOSTILE[0])
    assert {"img", "strong", "a"} <= set(tags)


def test_the_panel_title_escapes_the_sequence_id_and_spacecraft():
    text, tags = rendered_text(panel_title(HOSTILE[0], "<b>SAT</b>", "new"))
    assert tags == ["p", "strong"]
    assert text == f"{HOSTILE[0]} (<b>SAT</b>), status new"


def test_the_panel_title_says_the_status_in_the_consoles_words():
    """The panel says "no match" and "no valid attitude", as the console does, never the status codes."""
    for status, words in (("no_match", "no match"), ("rejected", "no valid attitude"), ("identified", "identified")):
        text, tags = rendered_text(panel_title("A-0427", "TUBSAT-A", status))
        assert tags == ["p", "strong"]
        assert text == f"A-0427 (TUBSAT-A), status {words}"


def test_the_status_words_are_the_consoles():
    """One mapping on each side (static/js/queue.js STATUS_TEXT, app/viewer/server.py STATUS_TEXT): the same."""
    from app.viewer.server import STATUS_TEXT

    source = (Path(__file__).resolve().parents[1] / "static" / "js" / "queue.js").read_text()
    mapping = re.search(r"const STATUS_TEXT = \{([^}]*)\}", source).group(1)
    assert dict(re.findall(r'(\w+): "([^"]*)"', mapping)) == STATUS_TEXT


def test_the_3d_view_confirms_the_credible_best_and_sends_any_other_rank_to_the_console(tmp_path, sky, sample_dir):
    """The panel has no second step: another rank, or a confirmation replacing the sequence's verdict, is sent
    to the console drawn (its view state's confirm_request names the sequence, rank and search) in an operator's
    words (no API field
    names), nothing is stored; the credible best is confirmed under the operator's name, and confirming it
    again names who confirmed it and when."""
    from app.storage import Storage
    from app.viewer.server import confirm_from_3d
    from app.workflow import AppContext, archive, confirm as confirming, search as searching
    from app.workflow.errors import Invalid
    from app.workflow.view import view_document

    ctx = AppContext(storage=Storage.open(tmp_path / "v.sqlite3"), sky=sky)
    console = "c-0123456789abcdef01234567"
    try:
        upload = archive.parse_upload(ctx, (sample_dir / "04-big-dipper.json").read_bytes(), "04-big-dipper.json")
        doc = archive.store_upload(ctx, upload, archive.extraction_job(upload.sequence, upload.known_hot))
        job = searching.prepare_search(ctx, doc.id, "bright_pair", None)
        result = searching.store_search(ctx, job, searching.compute_search(job, sky=ctx.sky))
        assert result.status == "identified" and len(result.candidates) >= 2
        assert view_document(ctx, console).confirm_request is None

        said = confirm_from_3d(ctx, doc.id, 2, "Vera", "typed in 3D", console)
        assert said.replace("\\", "").startswith(  # as shown: Markdown's escapes gone
            "Rank 2 is not the credible best candidate (not the best candidate: rank 1 matches ") and "override_reason" not in said
        assert "Sent to the console: its second step asks for the reason, which the audit record keeps." in said
        assert "The comment typed here goes with it, into the console's comment box." in said
        sent = view_document(ctx, console)
        assert sent.confirm_request.model_dump() == {"sequence": doc.id, "rank": 2, "search_id": result.search_id,
                                                     "number": 1, "comment": "typed in 3D"}
        assert (sent.sequence, sent.rank, sent.updated_by) == (None, None, "viewer")  # the selection is not touched
        assert ctx.storage.current_verdict(doc.id) is None
        # Without a console (the 3D view's default session) nothing is said to be sent.
        alone = confirm_from_3d(ctx, doc.id, 2, "Vera", "typed in 3D")
        assert "Confirm it in the console: its second step" in alone and "The comment typed here is not sent" in alone

        assert confirm_from_3d(ctx, doc.id, 1, "", None, console).startswith("**Error:** enter the operator's name")
        # The panel's text boxes follow the API's rules for what goes into the audit record (the panel shows
        # the refusal): a terminal's bell in the name, a comment beyond 2,000 characters; nothing is stored.
        with pytest.raises(Invalid, match=r"^operator: must not contain the control character U\+0007"):
            confirm_from_3d(ctx, doc.id, 1, "Ve\x07ra", None, console)
        with pytest.raises(Invalid, match=r"^comment: must be at most 2000 characters, got 2001$"):
            confirm_from_3d(ctx, doc.id, 1, "Vera", "c" * 2001, console)
        assert ctx.storage.current_verdict(doc.id) is None
        said = confirm_from_3d(ctx, doc.id, 1, "Vera", "from the 3D view", console)
        assert said.startswith("Confirmed rank 1 as attitude ")
        stored = ctx.storage.current_verdict(doc.id)
        assert stored.operator == "Vera"
        # Again, by someone else: nothing new, and the panel says whose confirmation it is and when (UTC).
        at = stored.confirmed_at.astimezone(timezone.utc).strftime("%Y-%m-%d %H:%M:%S")
        said = confirm_from_3d(ctx, doc.id, 1, "Walt", None, console)
        text, tags = rendered_text(said)
        assert text == f"Rank 1 was confirmed already by Vera at {at}Z (attitude #{stored.id}); nothing new stored."
        assert tags == ["p"] and ctx.storage.current_verdict(doc.id).id == stored.id

        # The workflow's other audit records refuse them too, whichever interface calls it.
        with pytest.raises(Invalid, match=r"^reason: must not contain the control character U\+001B"):
            confirming.reject(ctx, doc.id, "Rex", "clears the screen \x1b[2J", supersede=True)
        with pytest.raises(Invalid, match=r"^operator: must not contain the control character U\+000A"):
            archive.reset_pattern(ctx, doc.id, "Rex\nAdmin")
        assert ctx.storage.current_verdict(doc.id).operator == "Vera"

        # Replacing a verdict takes the console's second step too, even for the credible best.
        confirming.reject(ctx, doc.id, "Rex", "<b>a ghost</b> pattern", supersede=True)
        said = confirm_from_3d(ctx, doc.id, 1, "Vera", None, console)
        text, tags = rendered_text(said)
        assert text.startswith('Rank 1 would replace the sequence\'s verdict: "no valid attitude" recorded by Rex at ')
        assert ": <b>a ghost</b> pattern. Sent to the console: its second step asks you to confirm the replacement." \
            in text and tags == ["p"]
        request = view_document(ctx, console).confirm_request
        assert (request.sequence, request.rank, request.number) == (doc.id, 1, 2)  # a new request
        assert ctx.storage.current_verdict(doc.id).operator == "Rex"
    finally:
        ctx.close()
