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
