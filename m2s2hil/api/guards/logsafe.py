"""Free text from a request made safe for the log and the journal.

One helper, :func:`clean_text`, used for every user string that is logged or recorded (the
hold reason, session notes, any free text of a sweep): control characters (C0, DEL, C1),
line and paragraph separators and invisible format characters (bidi overrides, zero-width)
are escaped, so a newline or a NUL cannot end a log line and forge the next one, and the
result is cut to a length limit."""

from __future__ import annotations

import unicodedata

#: Longest hold reason accepted by POST /queue/hold (characters, before escaping).
HOLD_REASON_MAX = 200
#: Default limit for free text that reaches the log or the journal (characters, after escaping).
TEXT_MAX = 200

_NAMED = {"\n": "\\n", "\r": "\\r", "\t": "\\t", "\\": "\\\\"}
_UNSAFE = frozenset(("Cc", "Cf", "Zl", "Zp", "Cs"))


def _escape(ch: str) -> str:
    if ch in _NAMED:
        return _NAMED[ch]
    if unicodedata.category(ch) not in _UNSAFE:
        return ch
    code = ord(ch)
    return f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"


def clean_text(value: object, limit: int = TEXT_MAX) -> str:
    """``value`` as one printable line of at most ``limit`` characters (escapes included);
    a cut is marked with ``…`` so a reader knows text was dropped."""
    text = "".join(_escape(ch) for ch in str(value))
    if len(text) > limit:
        text = text[: max(0, limit - 1)] + "…"
    return text
