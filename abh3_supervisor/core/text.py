"""Text a client supplied, made safe for a log line or an audit entry.

A log is read on terminals and by scripts: a newline in a client's text would forge a line
of its own, an escape sequence would drive the reader's terminal. Every character that is
not printable (controls, format characters such as bidi overrides, separators other than
the space) is written as its escape, and the text is capped so no client can flood a line.
"""

from __future__ import annotations

MAX_LOGGED = 200  # characters of a client's text kept in one log line


def clean(text: str, limit: int = MAX_LOGGED) -> str:
    """``text`` with every non-printable character escaped, at most ``limit`` characters
    of it kept (the rest counted)."""
    kept = text[:limit]
    out = kept if kept.isprintable() else "".join(_escape(c) for c in kept)
    if len(text) > limit:
        out += f"… (+{len(text) - limit} characters)"
    return out


def _escape(char: str) -> str:
    # Python's own escapes: \n, \x1b, \u202e — unambiguous and familiar to readers of logs
    return char if char.isprintable() else char.encode("unicode_escape").decode("ascii")
