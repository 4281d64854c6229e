"""Outside text (model names, option values, file paths) made safe for where NNCG prints it: a C or
CMake comment, a terminal line. Every such text goes through one of these functions."""

from __future__ import annotations

import html
import re
import unicodedata

NAME_LIMIT = 80  # characters of an outside name shown in a comment or a message


def escaped(text: str) -> str:
    """`text` with every character that is not printable ASCII written as a Python-style escape
    (\\n, \\x1b, \\u202e, ...) and backslashes doubled: one line, no terminal control, no bidi
    override, no invisible characters, and distinct texts stay distinct."""
    out = []
    for ch in text:
        code = ord(ch)
        if ch == "\\":
            out.append("\\\\")
        elif 0x20 <= code < 0x7F:
            out.append(ch)
        elif ch in "\n\r\t":
            out.append({"\n": "\\n", "\r": "\\r", "\t": "\\t"}[ch])
        elif code < 0x100:
            out.append(f"\\x{code:02x}")
        elif code < 0x10000:
            out.append(f"\\u{code:04x}")
        else:
            out.append(f"\\U{code:08x}")
    return "".join(out)


def capped(text: str, limit: int = NAME_LIMIT) -> str:
    """At most `limit` characters: a longer text keeps its head and tail around "..."."""
    if len(text) <= limit:
        return text
    head = (limit - 3) * 2 // 3
    return text[:head] + "..." + text[len(text) - (limit - 3 - head) :]


def shown(name: object, limit: int = NAME_LIMIT) -> str:
    """An outside name as a message or comment shows it: quoted, escaped, capped."""
    return "'" + capped(escaped(str(name)), limit) + "'"


def terminal_line(text: str) -> str:
    """A message for a terminal: every control, format (bidi, zero-width) or otherwise unprintable
    character escaped so it stays one visible line. Backslashes are kept (paths on Windows, and
    names already escaped by `shown`); letters of other scripts are kept."""
    return "".join(ch if _visible(ch) else escaped(ch) for ch in text)


def _visible(ch: str) -> bool:
    if ch == "\\" or ch == " ":
        return True
    return ch.isprintable() and unicodedata.category(ch) not in ("Cf", "Co", "Cs", "Zl", "Zp")


def c_comment(text: str) -> str:
    """Text for inside a C block comment: printable ASCII with no comment delimiter, no trigraph
    and no line splice, so neither the comment nor the line can end early."""
    safe = escaped(text).replace("*/", "*\\/").replace("/*", "/\\*")
    while "??" in safe:
        safe = safe.replace("??", "?\\?")
    return safe


def comment_name(name: object) -> str:
    """An outside name inside a C comment: quoted, safe (see c_comment) and capped."""
    return "'" + capped(c_comment(str(name))) + "'"


def html_text(text: object, limit: int = NAME_LIMIT) -> str:
    """Outside text for an HTML page: one visible line (see terminal_line), capped, with the
    characters HTML gives meaning (< > & and quotes) as entities."""
    return html.escape(capped(terminal_line(str(text)), limit))


_MARKDOWN_SPECIAL = re.compile(r"([\\`*_\[\]|<>&~])")


def markdown_text(text: object, limit: int = NAME_LIMIT) -> str:
    """Outside text for Markdown (a table cell, a line): printable ASCII (see escaped), capped, every
    character Markdown or HTML gives meaning backslash-escaped, so no tag, link, emphasis or cell
    boundary comes through."""
    return _MARKDOWN_SPECIAL.sub(r"\\\1", capped(escaped(str(text)), limit))
