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


def strict_loads(raw: bytes) -> Any:
    """Parse a JSON body; ServiceError 400 naming the line and column of a syntax error."""
    if not raw.strip():
        raise malformed("body: empty; expected a JSON object")
    try:
        return json.loads(raw, parse_constant=_reject_constant, parse_float=_finite_float)
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
