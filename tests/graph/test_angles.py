import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from graph.angles import angle_diff, wrap_angle, wrap_angles


def test_convention_wrap_is_half_open_at_pi() -> None:
    assert wrap_angle(math.pi) == math.pi
    assert wrap_angle(-math.pi) == math.pi
    assert wrap_angle(3 * math.pi) == math.pi
    assert wrap_angle(0.0) == 0.0
    assert math.isclose(wrap_angle(-math.pi + 1e-9), -math.pi + 1e-9)


def test_angle_diff_across_pi() -> None:
    assert math.isclose(angle_diff(math.pi - 0.1, -math.pi + 0.1), -0.2, abs_tol=1e-12)
    assert math.isclose(angle_diff(-math.pi + 0.1, math.pi - 0.1), 0.2, abs_tol=1e-12)


@given(st.floats(-1e4, 1e4, allow_nan=False))
def test_wrap_range_and_equivalence(a: float) -> None:
    w = wrap_angle(a)
    assert -math.pi < w <= math.pi
    assert math.isclose(math.cos(w), math.cos(a), abs_tol=1e-9)
    assert math.isclose(math.sin(w), math.sin(a), abs_tol=1e-9)
    assert wrap_angles(np.array([a]))[0] == w
