"""The per-pixel event index and the closest-event search against brute force."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest

from mocaprig.acquire.events import make_events
from mocaprig.errors import ValidationError
from mocaprig.process.eventcap.event_index import (
    build_event_index,
    closest_events,
    events_at,
    patch_offsets,
)

W, H = 40, 30


def _events(seed: int, n: int = 4000, *, width: int = W, height: int = H) -> npt.NDArray[np.void]:
    rng = np.random.default_rng(seed)
    return make_events(
        rng.integers(0, 50_000, n),  # unsorted on purpose
        rng.integers(0, width, n),
        rng.integers(0, height, n),
        rng.integers(0, 2, n),
    )


def test_patch_of_eight_spans_minus_four_to_plus_three() -> None:
    off = patch_offsets(8)
    assert off.shape == (64, 2)
    assert off[:, 0].min() == -4
    assert off[:, 0].max() == 3
    assert off[:, 1].min() == -4
    assert off[:, 1].max() == 3
    assert sorted(set(patch_offsets(9)[:, 0].tolist())) == list(range(-4, 5))


def test_events_at_returns_exactly_the_pixels_events_in_the_window_in_time_order() -> None:
    ev = _events(1)
    idx = build_event_index(ev, width=W, height=H)
    for x, y in ((0, 0), (7, 11), (39, 29)):
        got = events_at(idx, x, y, t_start_us=10_000, t_end_us=30_000)
        sel = (ev["x"] == x) & (ev["y"] == y) & (ev["t"] >= 10_000) & (ev["t"] <= 30_000)
        want = np.sort(ev[sel], order="t", kind="stable")
        np.testing.assert_array_equal(got["t"], want["t"])
        np.testing.assert_array_equal(np.sort(got["p"]), np.sort(want["p"]))
        assert np.all(got["x"] == x)
        assert np.all(got["y"] == y)


def _brute_force(
    ev: npt.NDArray[np.void],
    q: npt.NDArray[np.int64],
    t_ref: int,
    half: int,
    dur: int,
    patch: int,
) -> npt.NDArray[np.float64]:
    lo = -(patch // 2)
    hi = patch - patch // 2 - 1
    x, y, t = ev["x"].astype(np.int64), ev["y"].astype(np.int64), ev["t"].astype(np.int64)
    out = np.full(len(q), np.inf)
    for i, (qx, qy) in enumerate(q):
        dx, dy = x - qx, y - qy
        ok = (dx >= lo) & (dx <= hi) & (dy >= lo) & (dy <= hi)
        ok &= (t >= t_ref - half) & (t <= t_ref + half)
        if ok.any():
            d = 4.0 * ((t_ref - t[ok]) / dur) ** 2 + dx[ok] ** 2 + dy[ok] ** 2
            out[i] = d.min()
    return out


@pytest.mark.parametrize("patch", [8, 9])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_closest_events_equal_a_brute_force_search(patch: int, seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    ev = _events(seed, n=300)
    idx = build_event_index(ev, width=W, height=H)
    q = np.stack([rng.integers(-2, W + 2, 300), rng.integers(-2, H + 2, 300)], axis=-1)
    t_ref, half, dur = 25_000, 8_000, 40_000
    got = closest_events(
        idx, q, t_ref_us=t_ref, half_window_us=half, batch_duration_us=dur, patch_size=patch
    )
    want = _brute_force(ev, q, t_ref, half, dur, patch)
    np.testing.assert_array_equal(got.found, np.isfinite(want))
    np.testing.assert_allclose(got.distance, want, rtol=1e-12)
    assert 0 < got.found.sum() < len(q)  # both cases occur
    # The reported event is a real one with the reported pixel, time and distance.
    f = got.found
    src = ev[got.source_index[f]]
    np.testing.assert_array_equal(src["x"], got.uv[f, 0])
    np.testing.assert_array_equal(src["y"], got.uv[f, 1])
    np.testing.assert_array_equal(src["t"], got.t_us[f])
    d = 4.0 * ((t_ref - got.t_us[f]) / dur) ** 2 + np.sum((got.uv[f] - q[f]) ** 2, axis=-1)
    np.testing.assert_allclose(d, got.distance[f], rtol=1e-12)
    assert np.all(got.source_index[~f] == -1)


def test_time_breaks_ties_between_equally_near_pixels() -> None:
    ev = make_events([10_000, 19_000], [5, 6], [5, 5], [1, 1])
    idx = build_event_index(ev, width=W, height=H)
    got = closest_events(
        idx, np.array([[5, 4], [6, 4]]), t_ref_us=20_000, half_window_us=20_000,
        batch_duration_us=40_000,
    )  # fmt: skip
    # Both events lie 1 px below each query; the one at 19 ms is nearer in time to 20 ms,
    # but for the query (5, 4) the event at (5, 5) is nearer in space.
    np.testing.assert_array_equal(got.source_index, [0, 1])


def test_events_outside_the_time_window_are_not_candidates() -> None:
    ev = make_events([1_000, 39_000], [5, 5], [5, 5], [1, 0])
    idx = build_event_index(ev, width=W, height=H)
    got = closest_events(
        idx, np.array([[5, 5]]), t_ref_us=20_000, half_window_us=10_000, batch_duration_us=40_000
    )
    assert not got.found[0]
    assert got.distance[0] == np.inf


def test_building_the_index_leaves_the_events_unchanged() -> None:
    ev = _events(4)
    before = ev.copy()
    build_event_index(ev, width=W, height=H, t_start_us=1000, t_end_us=40_000)
    np.testing.assert_array_equal(ev, before)


def test_index_keeps_only_the_requested_time_range() -> None:
    ev = _events(5)
    idx = build_event_index(ev, width=W, height=H, t_start_us=10_000, t_end_us=20_000)
    expected = np.count_nonzero((ev["t"] >= 10_000) & (ev["t"] <= 20_000))
    assert idx.num_events == expected
    assert idx.indptr[-1] == expected


def test_events_outside_the_sensor_are_refused_with_the_sensor_size() -> None:
    ev = make_events([0], [240], [10], [1])
    with pytest.raises(ValidationError, match="240x180"):
        build_event_index(ev, width=240, height=180)


def test_sensor_size_is_a_parameter() -> None:
    ev = _events(6, width=346, height=260)
    idx = build_event_index(ev, width=346, height=260)
    assert idx.indptr.shape == (346 * 260 + 1,)
    x, y = int(ev["x"][0]), int(ev["y"][0])
    got = events_at(idx, x, y, t_start_us=0, t_end_us=10**9)
    assert int(ev["t"][0]) in got["t"]


def test_an_empty_index_finds_nothing() -> None:
    idx = build_event_index(make_events([], [], [], []), width=W, height=H)
    got = closest_events(
        idx, np.array([[1, 1]]), t_ref_us=0, half_window_us=100, batch_duration_us=1000
    )
    assert not got.found.any()


def test_fractional_query_pixels_are_refused() -> None:
    idx = build_event_index(_events(7), width=W, height=H)
    with pytest.raises(ValidationError, match="integer"):
        closest_events(
            idx, np.array([[1.5, 2.0]]), t_ref_us=0, half_window_us=1, batch_duration_us=10
        )
