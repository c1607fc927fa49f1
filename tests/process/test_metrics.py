"""Tests of process.metrics on hand-computed cases."""

from __future__ import annotations

import numpy as np
import pytest

from mocaprig.errors import ValidationError
from mocaprig.process.metrics import (
    PCK_THRESHOLDS_MM,
    mean_error,
    pck,
    pck_curve,
    per_group_mean,
    per_point_mean,
    point_errors,
    pose_metrics,
    procrustes_align,
    quaternion_angle_deg,
    rms_error,
)


def _pair() -> tuple[np.ndarray, np.ndarray]:
    """2 frames, 2 points; errors [[3, 4], [0, 12]] mm (3-4-5 style offsets)."""
    true = np.zeros((2, 2, 3))
    pred = true.copy()
    pred[0, 0] = [3, 0, 0]
    pred[0, 1] = [0, 4, 0]
    pred[1, 1] = [0, 0, 12]
    return pred, true


def test_point_errors_are_euclidean() -> None:
    pred, true = _pair()
    np.testing.assert_allclose(point_errors(pred, true), [[3, 4], [0, 12]])


def test_mean_error_averages_all_points_and_frames() -> None:
    pred, true = _pair()
    assert mean_error(point_errors(pred, true)) == pytest.approx((3 + 4 + 0 + 12) / 4)


def test_rms_error_is_per_frame_rms_then_mean() -> None:
    pred, true = _pair()
    expected = (np.sqrt((9 + 16) / 2) + np.sqrt((0 + 144) / 2)) / 2
    assert rms_error(point_errors(pred, true)) == pytest.approx(expected)


def test_pck_counts_errors_at_or_below_threshold() -> None:
    e = np.array([[10.0, 50.0], [50.1, 200.0]])
    assert pck(e, 50.0) == pytest.approx(0.5)
    curve = pck_curve(e, [0.0, 10.0, 60.0, 300.0])
    np.testing.assert_allclose(curve, [0.0, 0.25, 0.75, 1.0])


def test_pck_curve_default_runs_0_to_150_mm() -> None:
    assert PCK_THRESHOLDS_MM[0] == 0.0
    assert PCK_THRESHOLDS_MM[-1] == 150.0
    assert pck_curve(np.array([[1.0]])).shape == PCK_THRESHOLDS_MM.shape


def test_quaternion_angle_matches_rotation_angle_and_ignores_sign() -> None:
    half = np.deg2rad(30.0) / 2  # 30 degrees about z
    q = np.array([0.0, 0.0, np.sin(half), np.cos(half)])
    ident = np.array([0.0, 0.0, 0.0, 1.0])
    assert quaternion_angle_deg(q, ident) == pytest.approx(30.0)
    assert quaternion_angle_deg(-q, ident) == pytest.approx(30.0)
    assert quaternion_angle_deg(ident, ident) == pytest.approx(0.0)
    # 180 degrees: <q, 1> = 0 -> arccos(-1)
    assert quaternion_angle_deg([1.0, 0, 0, 0], ident) == pytest.approx(180.0)


def test_quaternion_angle_rejects_zero_quaternion() -> None:
    with pytest.raises(ValidationError, match="zero norm"):
        quaternion_angle_deg([0.0, 0, 0, 0], [0.0, 0, 0, 1])


def test_per_point_and_per_group_means() -> None:
    e = np.array([[1.0, 3.0], [5.0, 7.0], [9.0, 11.0]])
    np.testing.assert_allclose(per_point_mean(e), [5.0, 7.0])
    assert per_group_mean(e, ["a", "b", "a"]) == {"a": 6.0, "b": 6.0}
    with pytest.raises(ValidationError, match="one per frame"):
        per_group_mean(e, ["a"])


def test_shape_mismatch_is_a_validation_error() -> None:
    with pytest.raises(ValidationError, match="true"):
        point_errors(np.zeros((2, 3, 3)), np.zeros((2, 4, 3)))


def test_pose_metrics_summary() -> None:
    pred, true = _pair()
    q = np.tile([0.0, 0.0, 0.0, 1.0], (2, 1, 1))
    half = np.deg2rad(10.0) / 2
    q2 = q.copy()
    q2[1, 0] = [np.sin(half), 0.0, 0.0, np.cos(half)]
    m = pose_metrics(
        pred,
        true,
        pred_markers_mm=pred,
        true_markers_mm=true,
        actions=["x", "y"],
        q_pred=q2,
        q_true=q,
    )
    assert m.mpjpe_mm == pytest.approx(4.75)
    assert m.mpmpe_mm == pytest.approx(4.75)
    assert m.pck50 == 1.0
    assert m.per_action_mm == {"x": 3.5, "y": 6.0}
    assert m.mpjae_deg == pytest.approx(5.0)
    assert m.rmspjae_deg == pytest.approx((0.0 + 10.0) / 2)  # per-frame RMS, then mean
    assert m.frames == 2


def _random_rigid(seed: int, frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random points (F, 15, 3) mm, proper rotations (F, 3, 3) and translations (F, 3) mm."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    pts = rng.normal(scale=300.0, size=(frames, 15, 3))
    rot = Rotation.random(frames, rng=rng).as_matrix()
    trans = rng.normal(scale=1000.0, size=(frames, 3))
    return pts, rot, trans


def test_procrustes_recovers_a_known_rigid_transform_exactly() -> None:
    pts, rot, trans = _random_rigid(0, 5)
    true = np.einsum("fij,fkj->fki", rot, pts) + trans[:, None, :]
    res = procrustes_align(pts, true)
    np.testing.assert_allclose(res.rotations, rot, atol=1e-12)
    np.testing.assert_allclose(res.translations, trans, atol=1e-9)
    np.testing.assert_allclose(res.aligned, true, atol=1e-9)
    np.testing.assert_array_equal(res.scales, np.ones(5))
    assert not res.with_scale


def test_procrustes_with_scale_recovers_the_scale() -> None:
    pts, rot, trans = _random_rigid(1, 3)
    true = 0.8 * np.einsum("fij,fkj->fki", rot, pts) + trans[:, None, :]
    res = procrustes_align(pts, true, with_scale=True)
    np.testing.assert_allclose(res.scales, 0.8, rtol=1e-12)
    np.testing.assert_allclose(res.aligned, true, atol=1e-9)
    rigid = procrustes_align(pts, true)
    assert np.abs(rigid.aligned - true).max() > 1.0  # without scale a residual must remain


def test_procrustes_never_returns_a_reflection_for_a_mirrored_pose() -> None:
    pts, _, _ = _random_rigid(2, 4)
    mirrored = pts * np.array([-1.0, 1.0, 1.0])
    res = procrustes_align(pts, mirrored)
    np.testing.assert_allclose(np.linalg.det(res.rotations), 1.0, atol=1e-12)
    # a reflection would fit exactly; a rotation cannot
    assert np.abs(res.aligned - mirrored).max() > 1.0


def test_procrustes_does_not_modify_its_inputs() -> None:
    pts, rot, trans = _random_rigid(3, 2)
    true = np.einsum("fij,fkj->fki", rot, pts) + trans[:, None, :]
    pts0, true0 = pts.copy(), true.copy()
    procrustes_align(pts, true, with_scale=True)
    np.testing.assert_array_equal(pts, pts0)
    np.testing.assert_array_equal(true, true0)


def test_procrustes_rejects_fewer_than_three_points() -> None:
    with pytest.raises(ValidationError, match="at least 3 points"):
        procrustes_align(np.zeros((1, 2, 3)), np.ones((1, 2, 3)))


def test_procrustes_rejects_a_frame_with_all_points_coincident() -> None:
    true = np.random.default_rng(4).normal(size=(2, 5, 3))
    pred = true.copy()
    pred[1] = 7.0
    with pytest.raises(ValidationError, match=r"pred frames \[1\]"):
        procrustes_align(pred, true)


def test_procrustes_rejects_mismatched_shapes() -> None:
    with pytest.raises(ValidationError, match="true has the wrong shape"):
        procrustes_align(np.zeros((2, 5, 3)), np.zeros((2, 4, 3)))
