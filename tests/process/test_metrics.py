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
