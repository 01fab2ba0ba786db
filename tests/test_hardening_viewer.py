"""Issue 12, item 6: telemetry-derived text in the 3D view's panel is shown as text, never as markup.

viser renders the panel's Markdown with raw HTML allowed; markdown-it (a
CommonMark renderer) with HTML enabled stands in for it here: what the
escaped text renders to must contain no element but the paragraph, and its
text must be the original string, character for character.
"""

from __future__ import annotations

import html
import re

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


def test_the_3d_view_confirms_the_credible_best_and_sends_any_other_rank_to_the_console(tmp_path, sky, sample_dir):
    """The panel has no second step: another rank is refused in an operator's words (no API field names),
    nothing is stored, and the credible best is confirmed under the operator's name."""
    from app.storage import Storage
    from app.viewer.server import confirm_from_3d
    from app.workflow import AppContext, archive, search as searching

    ctx = AppContext(storage=Storage.open(tmp_path / "v.sqlite3"), sky=sky)
    try:
        upload = archive.parse_upload(ctx, (sample_dir / "04-big-dipper.json").read_bytes(), "04-big-dipper.json")
        doc = archive.store_upload(ctx, upload, archive.extraction_job(upload.sequence, upload.known_hot))
        job = searching.prepare_search(ctx, doc.id, "bright_pair", None)
        result = searching.store_search(ctx, job, searching.compute_search(job, sky=ctx.sky))
        assert result.status == "identified" and len(result.candidates) >= 2
        said = confirm_from_3d(ctx, doc.id, 2, "Vera", None)
        assert said.startswith("Rank 2 is not the credible best candidate: ") and "override_reason" not in said
        assert "Confirm it in the console" in said and ctx.storage.current_verdict(doc.id) is None
        assert confirm_from_3d(ctx, doc.id, 1, "", None).startswith("**Error:** enter the operator's name")
        said = confirm_from_3d(ctx, doc.id, 1, "Vera", "from the 3D view")
        assert said.startswith("Confirmed rank 1 as attitude ")
        assert ctx.storage.current_verdict(doc.id).operator == "Vera"
    finally:
        ctx.close()
