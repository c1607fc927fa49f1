"""Validation helpers for public boundaries (never ``assert``)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from mocaprig.errors import ValidationError

__all__ = ["check_finite", "check_positive", "check_range", "check_shape"]


def check_shape(
    x: npt.ArrayLike, expected: Sequence[int | str], *, name: str = "array"
) -> npt.NDArray[Any]:
    """Check ``x`` against a shape pattern and return it as an array (not copied).

    ``expected`` holds ints (that exact size), names (any size, equal wherever the same name
    repeats) and at most one ``"..."`` (any number of leading or inner axes).

    Raises:
        ValidationError: the shape does not match; the message shows both shapes.
    """
    arr = np.asarray(x)
    shape = arr.shape
    pattern = list(expected)
    if pattern.count("...") > 1:
        msg = f"shape pattern {pattern!r} has more than one '...'"
        raise ValidationError(msg)
    if "..." in pattern:
        i = pattern.index("...")
        head, tail = pattern[:i], pattern[i + 1 :]
        ok_len = len(shape) >= len(head) + len(tail)
        dims = list(shape[: len(head)]) + list(shape[len(shape) - len(tail) :]) if ok_len else []
        pats = head + tail
    else:
        ok_len = len(shape) == len(pattern)
        dims, pats = list(shape), pattern
    bound: dict[str, int] = {}
    ok = ok_len
    if ok:
        for d, p in zip(dims, pats, strict=True):
            if isinstance(p, int):
                ok = ok and d == p
            elif p in bound:
                ok = ok and bound[p] == d
            else:
                bound[p] = d
    if not ok:
        msg = (
            f"{name} has the wrong shape\n"
            f"  expected: ({', '.join(str(p) for p in pattern)})\n"
            f"  actual:   {tuple(shape)}"
        )
        raise ValidationError(msg)
    return arr


def check_finite(x: npt.ArrayLike, *, name: str = "array") -> npt.NDArray[Any]:
    """Return ``x`` as an array, raising if any element is NaN or infinite."""
    arr = np.asarray(x)
    if not np.all(np.isfinite(arr)):
        bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        msg = f"{name} has {bad} non-finite value(s) (NaN or inf); clean or mask them first"
        raise ValidationError(msg)
    return arr


def _finite(value: float) -> bool:
    """``np.isfinite`` that also takes Python ints beyond int64 (finite) and non-numbers (not)."""
    if isinstance(value, int):
        return True
    try:
        return bool(np.isfinite(value))
    except TypeError:
        return False


def check_positive(value: float, *, name: str) -> float:
    """Return ``value`` if it is a finite number > 0."""
    if not _finite(value) or value <= 0:
        msg = f"{name} must be a finite number > 0, got {value!r}"
        raise ValidationError(msg)
    return value


def check_range(value: float, low: float, high: float, *, name: str) -> float:
    """Return ``value`` if ``low <= value <= high``."""
    if not (_finite(value) and low <= value <= high):
        msg = f"{name} must lie in [{low}, {high}], got {value!r}"
        raise ValidationError(msg)
    return value
