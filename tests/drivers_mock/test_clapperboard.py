"""The clapperboard's marker distance profile and placement."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest

from mocaprig.drivers_mock.clapperboard import Clapperboard, make_clapperboard
from mocaprig.errors import ValidationError

MS = 1_000_000


def _distance(board: Clapperboard, t_ns: npt.ArrayLike) -> npt.NDArray[np.float64]:
    m = board.markers_m(t_ns)
    d: npt.NDArray[np.float64] = np.linalg.norm(m[..., 0, :] - m[..., 1, :], axis=-1)
    return d


def test_distance_reaches_the_contact_distance_at_each_clap() -> None:
    board = make_clapperboard(np.random.default_rng(1), seconds=6.0, static_start_s=1.0)
    contact = board.contact_distance_m
    assert contact == pytest.approx(2 * board.marker_radius_m + 2 * board.arm_thickness_m)
    t = np.array(board.clap_times_ns, dtype=np.int64)
    np.testing.assert_allclose(_distance(board, t), contact, atol=1e-9)


def test_distance_is_minimal_from_each_clap_and_open_in_between() -> None:
    board = make_clapperboard(np.random.default_rng(2), seconds=6.0, static_start_s=1.0)
    t = np.arange(0, 6000 * MS, MS, dtype=np.int64)
    d = _distance(board, t)
    contact = board.contact_distance_m
    for tc in board.clap_times_ns:
        # Just before contact the arms are still apart, and closing.
        before = _distance(board, np.array([tc - 20 * MS, tc - 10 * MS, tc - 1 * MS]))
        assert np.all(np.diff(before) < 0)
        assert before[0] > contact + 0.01
        # The first sample at the contact distance is the clap instant.
        window = (t >= tc - 400 * MS) & (t <= tc + 50 * MS)
        first_closed = t[window][np.argmax(d[window] <= contact + 1e-9)]
        assert abs(first_closed - tc) <= MS
    # Fully open between the claps reaches ≈ 2·L·sin(θ/2) ≥ 15 cm.
    assert d.max() > 0.15


def test_closing_is_fast_and_accelerating() -> None:
    board = make_clapperboard(np.random.default_rng(3), seconds=6.0, static_start_s=1.0)
    for k, tc in enumerate(board.clap_times_ns):
        assert 0.06 <= board.closing_s[k] <= 0.12
        assert np.radians(30) <= board.open_angles_rad[k] <= np.radians(40)
        t = tc - np.array([60, 40, 20, 0]) * MS
        speed = -np.diff(board.angle_rad(t))
        assert np.all(np.diff(speed) > 0)  # faster and faster until contact


def test_first_clap_follows_the_static_start_and_last_is_near_the_end() -> None:
    board = make_clapperboard(np.random.default_rng(4), seconds=10.0, static_start_s=1.0)
    first, last = (t * 1e-9 for t in board.clap_times_ns)
    assert 1.7 < first < 2.0
    assert 9.3 < last < 9.6


def test_too_short_a_session_is_refused() -> None:
    with pytest.raises(ValidationError, match="too short"):
        make_clapperboard(np.random.default_rng(0), seconds=2.0, static_start_s=0.4)
