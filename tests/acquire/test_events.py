"""The canonical event dtype and its constructors."""

from __future__ import annotations

import numpy as np
import pytest

from mocaprig.acquire.events import EVENT_DTYPE, check_events, empty_events, make_events
from mocaprig.errors import ValidationError


def test_make_events_fills_every_column_and_normalises_polarity() -> None:
    ev = make_events([1, 2], [3, 4], [5, 6], [-1, 1])
    assert ev.dtype == EVENT_DTYPE
    assert ev["t"].tolist() == [1, 2]
    assert ev["p"].tolist() == [1, 1]
    assert make_events([1], [0], [0], [0])["p"].tolist() == [0]


def test_make_events_rejects_ragged_columns() -> None:
    with pytest.raises(ValidationError, match="equal length"):
        make_events([1, 2], [3], [5, 6], [0, 1])


def test_check_events_names_the_expected_dtype() -> None:
    assert check_events(empty_events()).size == 0
    with pytest.raises(ValidationError, match="make_events"):
        check_events(np.zeros(3))
