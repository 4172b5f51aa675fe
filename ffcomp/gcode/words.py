"""Splitting one G-code line into command word and parameter words.

Rules (the union of what Klipper and Marlin accept, minus what neither does):

* ``;`` starts a comment that runs to the end of the line; ``( ... )`` is a comment too (an unclosed
  ``(`` comments out the rest of the line).
* A line that starts with ``N<digits>`` carries a line number; if it also has ``*<digits>`` (before
  any ``;``), that is a checksum: the XOR of every byte before the last ``*`` (leading white space
  excluded).  A wrong or malformed checksum is an error.  Lines without ``N`` are never checksummed
  (Marlin's rule), so ``*`` inside an M117 message is harmless.
* Words are upper-cased (``g1 x10`` means ``G1 X10``); ``G01`` is ``G1``.  Words need not be
  separated by spaces (``G1X10Y20``).  A sub-code (``G92.1``) makes a different command.
* Klipper's extended commands (``SET_VELOCITY_LIMIT ACCEL=3000``) keep their ``KEY=VALUE`` text.

Errors raise :class:`ValueError` with a short reason; the parser adds path, line number and text.
"""

from __future__ import annotations

import re

__all__ = ["lex", "classic_words", "extended_params", "number", "checksum"]

_NUMCHARS = "0123456789.+-"
_HEAD = re.compile(r"([A-Z])(\d+)(\.\d+)?(.*)\Z", re.S)
_EXT = re.compile(r"[A-Z_][A-Z0-9_]*\Z")
_PIECES = re.compile(r"([A-Z])([^A-Z]*)")
_LINENO = re.compile(r"N\s*(\d+)\s*", re.I)


def checksum(text: str) -> int:
    """XOR of the UTF-8 bytes of ``text`` (the RepRap host-protocol checksum)."""
    c = 0
    for b in text.encode("utf-8", "surrogateescape"):
        c ^= b
    return c


def _strip_parens(code: str) -> str:
    out = []
    depth_start = 0
    i = code.find("(")
    while i >= 0:
        out.append(code[depth_start:i])
        j = code.find(")", i + 1)
        if j < 0:
            return "".join(out)
        depth_start = j + 1
        i = code.find("(", depth_start)
    out.append(code[depth_start:])
    return " ".join(out)


def lex(text: str) -> tuple[str, object]:
    """Split a line (without its terminator) into ``(command, params)``.

    Returns
    -------
    command : str
        ``""`` for a blank or comment-only line; ``"G1"``, ``"M104"``, ``"G92.1"``; an extended command
        name such as ``"SET_VELOCITY_LIMIT"``; or the first word as written (upper-cased) when the line
        does not start with a command word.
    params : list of str or str
        For ``letter+number`` commands: the remaining upper-cased white-space separated tokens (a token may
        still hold several words, ``"X10Y20"``).  For extended commands: the parameter text after the
        name, case preserved.

    Raises
    ------
    ValueError
        Bad line number or checksum.
    """
    s = text.strip()
    if not s or s[0] == ";":
        return "", ()
    semi = s.find(";")
    code = s if semi < 0 else s[:semi]
    if code[0] in "Nn":
        m = _LINENO.match(code)
        if m is None:
            raise ValueError("bad line number word")
        star = code.rfind("*")
        if star >= 0:
            digits = code[star + 1:].strip()
            if not digits.isdigit():
                raise ValueError(f"malformed checksum {code[star:].strip()!r}")
            want = checksum(s[:star])
            if int(digits) != want:
                raise ValueError(f"checksum mismatch: line says {int(digits)}, computed {want}")
            code = code[:star]
        code = code[m.end():]
    if "(" in code:
        code = _strip_parens(code)
    code = code.strip()
    if not code:
        return "", ()
    upper = code.upper()
    parts = upper.split()
    head = parts[0]
    c0 = head[0]
    if "A" <= c0 <= "Z" and len(head) > 1 and head[1].isdigit():
        rest = head[1:]
        if rest.isdigit():
            return c0 + str(int(rest)), parts[1:]
        m = _HEAD.match(head)
        if m is None:  # pragma: no cover - the regex accepts any letter+digits head
            return head, parts[1:]
        cmd = c0 + str(int(m.group(2))) + (m.group(3) or "")
        tail = m.group(4)
        return cmd, ([tail] if tail else []) + parts[1:]
    if _EXT.match(head):
        return head, code[len(head):].strip()
    return head, parts[1:]


def _split_compact(tok: str) -> list[tuple[str, str]]:
    pieces = _PIECES.findall(tok)
    if not pieces or "".join(a + b for a, b in pieces) != tok:
        raise ValueError(f"malformed word {tok!r}")
    has_digit = any(ch.isdigit() for ch in tok)
    out = []
    for letter, val in pieces:
        val = val.strip()
        if val.strip(_NUMCHARS) or (has_digit and not val):
            raise ValueError(f"bad number in {tok!r}")
        out.append((letter, val))
    return out


def classic_words(tokens) -> list[tuple[str, str]]:
    """``["X10", "Y-2.5E.3"]`` -> ``[("X", "10"), ("Y", "-2.5"), ("E", ".3")]`` (values unconverted).

    A letter may have an empty value (``G28 X``).  Raises ValueError on malformed words (``X1O``).
    """
    out = []
    for t in tokens:
        c = t[0]
        v = t[1:]
        if "A" <= c <= "Z" and not v.strip(_NUMCHARS):
            out.append((c, v))
        else:
            out.extend(_split_compact(t))
    return out


def number(letter: str, val: str) -> float:
    """Convert a word's value; raises ValueError naming the word."""
    if not val:
        raise ValueError(f"missing value for {letter}")
    try:
        x = float(val)
    except ValueError:
        raise ValueError(f"bad number {letter}{val!r}") from None
    return x


def extended_params(text: str) -> dict[str, str]:
    """``'VELOCITY=300 accel=3000'`` -> ``{'VELOCITY': '300', 'ACCEL': '3000'}``."""
    out = {}
    for tok in text.split():
        key, eq, val = tok.partition("=")
        if not eq or not key:
            raise ValueError(f"malformed parameter {tok!r} (expected KEY=VALUE)")
        out[key.upper()] = val.strip("\"'")
    return out
