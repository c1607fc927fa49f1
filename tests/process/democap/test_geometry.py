"""Tests of process.democap.geometry: frames, normalisation, rendering, views."""

from __future__ import annotations

import numpy as np
import pytest

from mocaprig.errors import ValidationError
from mocaprig.process.democap.geometry import (
    back_view,
    fuse_views,
    normalise,
    random_rotation,
    render_view,
    to_image_frame,
    to_world_frame,
)


def test_image_frame_round_trip_and_axes() -> None:
    p = np.array([[1.0, 2.0, 3.0]])
    q = to_image_frame(p)
    np.testing.assert_allclose(q, [[1.0, -3.0, 2.0]])  # v points down, w is world y
    np.testing.assert_allclose(to_world_frame(q), p)


def test_normalise_maps_cloud_box_to_01_09_and_inverts() -> None:
    rng = np.random.default_rng(0)
    p = rng.uniform([-0.4, -1.8, -0.3], [0.4, 0.0, 0.3], (60, 3))
    norm = normalise(p)
    n = norm.apply(p)
    np.testing.assert_allclose(n.min(axis=0), 0.1, atol=1e-12)
    np.testing.assert_allclose(n.max(axis=0), 0.9, atol=1e-12)
    np.testing.assert_allclose(norm.invert(n), p, atol=1e-12)


def test_normalise_floors_a_flat_axis() -> None:
    p = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    n = normalise(p, min_extent_m=0.3).apply(p)
    np.testing.assert_allclose(n[:, 2], 0.5)  # centred in a 0.3 m slab, not a division by 0


def test_normalise_rejects_empty_cloud() -> None:
    with pytest.raises(ValidationError, match="at least 2 points"):
        normalise(np.zeros((1, 3)))


def test_random_rotation_tilts_little_and_turns_fully() -> None:
    rng = np.random.default_rng(1)
    headings = []
    for _ in range(200):
        r = random_rotation(rng)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        up = r @ np.array([0.0, 1.0, 0.0])
        assert np.rad2deg(np.arccos(np.clip(up[1], -1, 1))) <= 20.0 + 1e-9  # 10 + 10 degrees
        fwd = r @ np.array([0.0, 0.0, 1.0])
        headings.append(np.rad2deg(np.arctan2(fwd[0], fwd[2])))
    assert min(headings) < -150.0
    assert max(headings) > 150.0


def test_back_view_is_an_involution_and_fusion_averages() -> None:
    n = np.array([[0.2, 0.3, 0.4]])
    np.testing.assert_allclose(back_view(n), [[0.8, 0.3, 0.6]])
    np.testing.assert_allclose(back_view(back_view(n)), n)
    # a back prediction that is exact fuses to the truth; errors average
    front = n + np.array([0.02, 0.0, 0.0])
    fused = fuse_views(front, back_view(n))
    np.testing.assert_allclose(fused, n + np.array([0.01, 0.0, 0.0]))


def test_render_disc_footprint_and_value() -> None:
    img = render_view(np.array([[0.5, 0.5, 0.37]]))
    assert img.shape == (160, 160)
    assert img.dtype == np.float32
    on = np.argwhere(img > 0)
    # radius 10 canvas px = 2 output px: a disc of about 4x4 output samples
    assert 9 <= len(on) <= 16
    np.testing.assert_allclose(img[img > 0], 0.37, rtol=1e-6)
    centre = on.mean(axis=0)
    np.testing.assert_allclose(centre, [79.5, 79.5], atol=0.6)  # row, column


def test_render_nearest_point_wins_and_background_is_zero() -> None:
    pts = np.array([[0.5, 0.5, 0.8], [0.505, 0.5, 0.2]])
    img = render_view(pts)
    assert img[80, 80] == pytest.approx(0.2)
    assert img[0, 0] == 0.0
    # outside the unit square: dropped, no error
    assert render_view(np.array([[1.2, 0.5, 0.5]])).max() == 0.0


def test_render_pixel_row_follows_y() -> None:
    img = render_view(np.array([[0.5, 0.2, 0.5]]))
    rows = np.argwhere(img > 0)[:, 0]
    assert abs(rows.mean() - 0.2 * 160 + 0.5) < 1.0
