"""Characters that text from outside (telemetry names, operator names, comments) may not hold.

Such text ends up in audit records, JSON documents, CCSDS messages, log
lines and consoles.  A control character (Unicode category Cc: U+0000-U+001F,
U+007F-U+009F) breaks the CSV form and log lines, and ESC recolours or clears
the terminal that prints it; a bidirectional embedding, override or isolate
control (U+202A-U+202E, U+2066-U+2069) makes a name read as another one.
Everything else is accepted: accents, CJK, right-to-left scripts, emoji (the
implicit marks U+200E/U+200F are harmless and allowed).
"""

from __future__ import annotations

import unicodedata

#: Bidirectional embedding, override and isolate controls.
BIDI_CONTROLS = frozenset(chr(c) for c in (*range(0x202A, 0x202F), *range(0x2066, 0x206A)))


def refused_character(text: str, allowed: frozenset[str] = frozenset()) -> str | None:
    """The first control or bidirectional control character of ``text`` not in ``allowed``, else None."""
    for ch in text:
        if ch in allowed:
            continue
        if ch in BIDI_CONTROLS or unicodedata.category(ch) == "Cc":
            return ch
    return None


def described(ch: str) -> str:
    """``ch`` as a message names it: "the control character U+001B", "the bidirectional control U+202E"."""
    kind = "bidirectional control" if ch in BIDI_CONTROLS else "control character"
    return f"the {kind} U+{ord(ch):04X}"
