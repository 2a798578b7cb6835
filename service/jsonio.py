"""Strict JSON for request bodies: malformed text, NaN, Infinity, numbers that
overflow to infinity and integers too long to read are refused with a precise 400
(ServiceError)."""

from __future__ import annotations

import json
from typing import Any

from service.errors import ServiceError


def malformed(detail: str) -> ServiceError:
    return ServiceError(400, "malformed-body", "Malformed body", detail)


def _reject_constant(name: str) -> float:
    raise malformed(f"body: {name} is not a number JSON allows; numbers must be finite")


def _finite_float(text: str) -> float:
    value = float(text)
    if value in (float("inf"), float("-inf")):
        raise malformed(f"body: {text} overflows to infinity; numbers must be finite")
    return value


_PLAIN = json.JSONDecoder(parse_constant=_reject_constant)
_CHECKED = json.JSONDecoder(parse_constant=_reject_constant, parse_float=_finite_float)
_SHAPES = bytes.maketrans(b"123456789E", b"000000000e")
"""Digits to 0, E to e: the shapes a number must have to overflow, found with `in`."""


def _may_overflow(raw: bytes) -> bool:
    """`raw` may hold a number that overflows to infinity: one with an exponent of three
    digits or more, or 200 digits in a row (an exponent of two digits needs 210 before
    the point), or text that is not UTF-8 (NUL bytes: UTF-16 or UTF-32, whose digits
    this does not see). Nearly every body has none: its numbers are read by the decoder
    itself instead of a Python call each."""
    shapes = raw.translate(_SHAPES)
    return b"e000" in shapes or b"e+000" in shapes or b"0" * 200 in shapes or b"\x00" in raw


def strict_loads(raw: bytes) -> Any:
    """Parse a JSON body; ServiceError 400 naming the line and column of a syntax error."""
    if not raw.strip():
        raise malformed("body: empty; expected a JSON object")
    try:
        text = raw.decode(json.detect_encoding(raw), "surrogatepass")  # as json.loads
        return (_CHECKED if _may_overflow(raw) else _PLAIN).decode(text)
    except json.JSONDecodeError as exc:
        raise malformed(
            f"body: malformed JSON at line {exc.lineno} column {exc.colno}: {exc.msg}"
        ) from exc
    except UnicodeDecodeError as exc:
        raise malformed(f"body: not UTF-8 text ({exc.reason})") from exc
    except ValueError as exc:  # an integer literal beyond Python's 4300-digit limit
        raise malformed("body: a number has too many digits to read") from exc


def loads_object(raw: bytes, what: str) -> dict[str, Any]:
    """`strict_loads`, and the body must be an object (`what` names it in the error)."""
    value = strict_loads(raw)
    if not isinstance(value, dict):
        raise malformed(f"body: must be a JSON object ({what})")
    return value
