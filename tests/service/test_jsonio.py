"""Strict JSON bodies: the decoder reads the numbers itself unless a number may overflow,
and a body is refused or read exactly as with a Python check of every number."""

from __future__ import annotations

import json

import pytest
from hypothesis import given
from hypothesis import strategies as st

from service.errors import ServiceError
from service.jsonio import _finite_float, _may_overflow, _reject_constant, strict_loads


def _checked(raw: bytes) -> object:
    """What every body used to go through: a Python call for each number."""
    return json.loads(raw, parse_constant=_reject_constant, parse_float=_finite_float)


@pytest.mark.parametrize(
    "raw",
    [
        b'{"a": 1e999}',
        b'{"a": -1E400}',
        b'{"a": 2e308}',
        b'{"a": 9.99e+308}',
        b'{"a": 1e0400}',
        ("[" + "9" * 400 + ".0]").encode(),
        ("[" + "9" * 210 + "e99]").encode(),
        '{"a": 1e999}'.encode("utf-16"),
        '{"a": 1e999}'.encode("utf-32"),
        '\ufeff{"a": 1e999}'.encode(),
    ],
)
def test_a_number_that_overflows_is_refused(raw: bytes) -> None:
    assert _may_overflow(raw)
    with pytest.raises(ServiceError, match="overflows to infinity") as caught:
        strict_loads(raw)
    assert caught.value.status == 400


@pytest.mark.parametrize(
    ("raw", "words"),
    [
        (b'{"a": NaN}', "NaN is not a number"),
        (b'{"a": -Infinity}', "-Infinity is not a number"),
        (b'{"a": ', "malformed JSON at line 1 column 7"),
        (b'{"a": "\xc3"}', "not UTF-8 text"),
        (("[" + "1" * 5000 + "]").encode(), "too many digits"),
        (b"  ", "empty"),
    ],
)
def test_other_bad_bodies_are_refused_as_before(raw: bytes, words: str) -> None:
    with pytest.raises(ServiceError, match=words):
        strict_loads(raw)


def test_bodies_without_the_shapes_of_an_overflow_take_the_decoder_alone() -> None:
    raw = b'{"robot": "r1e", "seq": 3, "stamp": 1.25e-999, "x": [1.5e12, -0.0, 17]}'
    assert not _may_overflow(raw)
    assert strict_loads(raw) == _checked(raw)
    assert strict_loads('\ufeff{"a": 1.5}'.encode()) == {"a": 1.5}


@given(st.lists(st.floats(allow_nan=False, allow_infinity=False) | st.integers(), max_size=20))
def test_numbers_read_exactly_as_with_the_check(values: list[float | int]) -> None:
    raw = json.dumps({"values": values, "label": "e+000 in text"}).encode()
    got = strict_loads(raw)
    want = _checked(raw)
    assert json.dumps(got) == json.dumps(want)
    assert [type(v) for v in got["values"]] == [type(v) for v in want["values"]]
