"""Boundary validation helpers."""

from __future__ import annotations

import numpy as np
import pytest

from mocaprig.errors import MocaprigError, ValidationError
from mocaprig.validation import check_finite, check_positive, check_range, check_shape


def test_check_shape_accepts_named_and_ellipsis_patterns() -> None:
    check_shape(np.zeros((4, 5, 3)), ["...", "N", 3])
    check_shape(np.zeros((2, 2)), ["N", "N"])
    check_shape(np.zeros((3,)), ["...", 3])


@pytest.mark.parametrize(
    ("shape", "pattern"),
    [((4, 2), ["N", 3]), ((2, 3), ["N", "N"]), ((3,), ["...", "N", 3]), ((1, 2, 3), [1, 2])],
)
def test_check_shape_rejects_with_both_shapes_in_the_message(shape, pattern) -> None:
    with pytest.raises(ValidationError, match=r"points has the wrong shape[\s\S]*actual"):
        check_shape(np.zeros(shape), pattern, name="points")


def test_validation_error_is_a_mocaprig_error_and_a_value_error() -> None:
    assert issubclass(ValidationError, MocaprigError)
    assert issubclass(ValidationError, ValueError)


def test_scalar_checks() -> None:
    assert check_positive(2.0, name="rate_hz") == 2.0
    with pytest.raises(ValidationError, match="rate_hz must be a finite number > 0"):
        check_positive(0.0, name="rate_hz")
    with pytest.raises(ValidationError, match=r"must lie in \[0, 1\]"):
        check_range(1.5, 0, 1, name="fraction")
    with pytest.raises(ValidationError, match="1 non-finite"):
        check_finite([1.0, np.nan], name="x")


def test_scalar_checks_refuse_huge_ints_and_non_numbers_cleanly() -> None:
    # A TOML integer beyond 64 bits or a string from a hand-edited file must be a
    # ValidationError naming the field, not a TypeError from numpy.
    with pytest.raises(ValidationError, match=r"port must lie in \[0, 65535\]"):
        check_range(2**70, 0, 65535, name="port")
    assert check_positive(2**70, name="big") == 2**70
    with pytest.raises(ValidationError, match="rate_hz must be a finite number > 0"):
        check_positive("fast", name="rate_hz")  # type: ignore[arg-type]
