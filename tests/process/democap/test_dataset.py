"""Sample pools: the subjects drawn off the body model (``SubjectModel``)."""

from __future__ import annotations

import numpy as np
import pytest

from mocaprig.errors import ValidationError
from mocaprig.process.democap.dataset import NOMINAL_SUBJECTS, SubjectModel, make_pool


def test_the_nominal_subjects_are_the_pools_bodies() -> None:
    a = make_pool(3, "test", takes=2, seconds=0.5)
    b = make_pool(3, "test", takes=2, seconds=0.5, subjects=SubjectModel())
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.markers_m, y.markers_m)
    assert NOMINAL_SUBJECTS.is_nominal
    assert not SubjectModel(placement=2.0).is_nominal


def test_wider_proportions_spread_the_heights_and_keep_the_draws_in_step() -> None:
    heights = {}
    for p in (1.0, 2.0):
        rng = np.random.default_rng(0)
        heights[p] = np.array(
            [SubjectModel(proportions=p).body(rng)[0].height_m for _ in range(200)]
        )
    assert heights[1.0].min() >= 1.55
    assert heights[1.0].max() <= 1.95
    assert heights[2.0].min() < 1.5
    assert heights[2.0].max() > 2.0
    # the same uniform draws stretched about 1.75 m, but for the rare body drawn again
    same = np.isclose(heights[2.0] - 1.75, 2.0 * (heights[1.0] - 1.75), atol=1e-9)
    assert same[:50].all()


def test_looser_placement_moves_the_markers_further_from_their_sites() -> None:
    def spread(placement: float) -> float:
        rng = np.random.default_rng(1)
        _, markers = SubjectModel(placement=placement).body(rng)
        rng0 = np.random.default_rng(1)
        _, exact = SubjectModel(placement=0.0).body(rng0)
        return float(np.linalg.norm(markers.offsets_m - exact.offsets_m, axis=1).mean())

    assert spread(2.5) == pytest.approx(2.5 * spread(1.0), rel=0.15)


def test_skin_motion_moves_markers_along_the_skin_every_frame_and_not_the_joints() -> None:
    base = make_pool(0, "test", takes=1, seconds=1.0)[0]
    moved = make_pool(0, "test", takes=1, seconds=1.0, subjects=SubjectModel(soft_tissue_m=0.015))[
        0
    ]
    np.testing.assert_array_equal(base.joints_m, moved.joints_m)
    d = moved.markers_m - base.markers_m
    along = np.sum(d * base.normals, axis=-1)
    assert np.abs(along).max() < 1e-12  # tangential
    # two tangential axes of sigma 1.5 cm: a mean displacement of 1.5 cm * sqrt(pi/2)
    assert np.linalg.norm(d, axis=-1).mean() == pytest.approx(0.015 * np.sqrt(np.pi / 2), rel=0.1)
    assert not np.allclose(d[0], d[1])  # fresh in every frame


def test_bad_subject_models_are_refused() -> None:
    with pytest.raises(ValidationError, match="placement"):
        SubjectModel(placement=-1.0)
    with pytest.raises(ValidationError, match="proportions"):
        SubjectModel(proportions=6.0)
