"""The text encoding Mitsuba's XML parser (pugixml) reads a scene file in.

Expat decodes a file in the encoding it declares; pugixml ignores most declarations and reads
UTF-8, so a file's names could be checked as other names than Mitsuba opens. The walker parses
in `pugixml_encoding` (pugixml's ``guess_buffer_encoding``) and refuses UTF-16/32 files and a
non-ASCII file declaring another encoding than that (`declaration_error`).
"""
from __future__ import annotations

import re

#: pugixml's ct_symbol bytes: what an encoding name in the declaration may hold
_SYMBOL = rb"[A-Za-z0-9_:.\-\x80-\xff]*"
_DECLARATION = re.compile(rb"<\?xml[ \t\r\n]")
_ENCODING = re.compile(rb"encoding[ \t\r\n]*=[ \t\r\n]*(?:\"(" + _SYMBOL + rb")\"|'(" + _SYMBOL + rb")')")
_LATIN1 = re.compile(rb"(?i:iso)-8859-1|(?i:latin)1")
#: declared names of the encodings pugixml may read a file in
_NAMES = {"UTF-8": {"utf-8", "utf8"}, "ISO-8859-1": {"iso-8859-1", "latin1", "latin-1", "iso8859-1"}}


def pugixml_encoding(data: bytes) -> str | None:
    """``"UTF-8"`` or ``"ISO-8859-1"``: the encoding pugixml parses `data` in; None for
    UTF-16 or UTF-32 (or NUL bytes where pugixml looks for them)."""
    if len(data) < 4 or data[:3] == b"\xef\xbb\xbf":
        return "UTF-8"
    if data[:2] in (b"\xfe\xff", b"\xff\xfe") or 0 in data[:2]:
        return None
    if _DECLARATION.match(data):
        question = data.find(b"?", 6)
        at = data.find(b"en", 6, None if question < 0 else question)
        found = _ENCODING.match(data, at) if at >= 0 else None
        if found and _LATIN1.fullmatch(found.group(1) or found.group(2) or b""):
            return "ISO-8859-1"
    return "UTF-8"


def declaration_error(declared: str | None, used: str, data: bytes) -> str | None:
    """Why a file declaring `declared` and read in `used` is refused, or None (always for ASCII)."""
    if declared is None or declared.lower() in _NAMES[used] or data.isascii():
        return None
    return (f'declares encoding="{declared}", but Mitsuba reads it as {used}: save it as UTF-8 '
            "(or drop the declaration)")
