"""Which characters an operator's free text may hold: names one line of plain text, comments a few lines.

Operator names, comments and reasons end up in audit records, JSON
documents, CCSDS messages and consoles.  A terminal escape sequence (ESC)
in a name recolours or clears the terminal that prints it, and a
bidirectional override (U+202E) makes a name read as another one; the
CCSDS export replaces such characters with '?' (and escapes other scripts), every other reader gets
them raw.  So they are refused where the text comes in (the API's request
bodies, the server's token list), with the character named as U+XXXX
(:mod:`app.text` holds the rule, which telemetry names follow too):

* an operator name: no control character at all (Unicode category Cc:
  U+0000-U+001F, U+007F-U+009F, which includes ESC, newline and tab) and no
  bidirectional embedding, override or isolate control (U+202A-U+202E,
  U+2066-U+2069);
* a comment or a reason: the same, except that newline and tab are allowed.

Everything else is accepted: accents, CJK, right-to-left scripts, emoji.
U+0000 has its own sentence (PostgreSQL's text cannot hold it at all).
"""

from __future__ import annotations

from app.text import described, refused_character
from app.workflow.errors import Invalid

#: Control characters a comment or a reason may hold: its lines and their indentation.
LAYOUT = frozenset("\n\t")

#: Longest operator name, in characters (the API refuses longer ones; so does the server's token list).
MAX_OPERATOR = 100
#: Longest comment or reason, in characters.
MAX_COMMENT = 2000

NUL_MESSAGE = "must not contain a NUL character (U+0000)"
#: Why the rest is refused, as the end of the message.
NAME_RULE = "an operator name is one line of plain text"
COMMENT_RULE = "line breaks and tabs are allowed"


def _problem(ch: str, rule: str) -> str:
    return NUL_MESSAGE if ch == "\x00" else f"must not contain {described(ch)} ({rule})"


def operator_name_problem(name: str) -> str | None:
    """Why ``name`` cannot be an operator's name ("must not contain ..."), None when it can."""
    if len(name) > MAX_OPERATOR:
        return f"must be at most {MAX_OPERATOR} characters, got {len(name)}"
    ch = refused_character(name)
    return None if ch is None else _problem(ch, NAME_RULE)


def comment_problem(text: str) -> str | None:
    """Why ``text`` cannot be a comment or a reason ("must not contain ..."), None when it can."""
    if len(text) > MAX_COMMENT:
        return f"must be at most {MAX_COMMENT} characters, got {len(text)}"
    ch = refused_character(text, LAYOUT)
    return None if ch is None else _problem(ch, COMMENT_RULE)


def require_audit_text(*, operator: str | None = None, **texts: str | None) -> None:
    """Refuse (:class:`app.workflow.errors.Invalid`, located at the argument's name) an operator name or a
    comment or reason (``texts``, by name) that cannot go into an audit record.

    The API's request bodies refuse them already; this is the rule for every
    interface (the 3D view's text boxes, scripts calling the workflow), at the
    one place each record is written."""
    problems = [("operator", operator_name_problem(operator))] if operator is not None else []
    problems += [(name, comment_problem(text)) for name, text in texts.items() if text is not None]
    for name, problem in problems:
        if problem:
            raise Invalid(f"{name.replace('_', ' ')}: {problem}", location=name, message=problem)
