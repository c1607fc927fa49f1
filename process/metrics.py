"""Pose-estimation metrics (DeMoCap paper §5.2.1; democap-method.md §5).

Positions are (F frames, K points, 3) arrays in millimetres; errors are Euclidean.

* MPJPE / MPMPE (:func:`mean_error`): mean error over points and frames.
* RMSPJPE / RMSPMPE (:func:`rms_error`): per frame the root mean square over points, then the
  mean over frames.
* PCK3D (:func:`pck`, :func:`pck_curve`): the fraction of points within a threshold; the
  "mAP" of the paper is the curve over 0–150 mm (:data:`PCK_THRESHOLDS_MM`); its mean is
  reported as ``pck_auc``; ``pck50`` is the value at 50 mm.
* MPJAE / RMSPJAE (:func:`quaternion_angle_deg`): the angle between true and estimated unit
  quaternions, ``θ = arccos(2⟨q̂, q⟩² − 1)`` (paper Eq. 11), mean and per-frame RMS.
* per joint (:func:`per_point_mean`) and per action (:func:`per_group_mean`).
* Procrustes alignment (:func:`procrustes_align`): per-frame rotation + translation (optionally
  scale) of a prediction onto the truth, for errors that factor out the global pose (EventCap's
  AE, "PA-MPJPE").
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from mocaprig.errors import ValidationError
from mocaprig.validation import check_finite, check_shape

__all__ = [
    "PCK_THRESHOLDS_MM",
    "PoseMetrics",
    "ProcrustesResult",
    "mean_error",
    "pck",
    "pck_curve",
    "per_group_mean",
    "per_point_mean",
    "point_errors",
    "pose_metrics",
    "procrustes_align",
    "quaternion_angle_deg",
    "rms_error",
    "rms_per_frame",
]

FloatArray = npt.NDArray[np.float64]

#: Thresholds of the PCK3D curve: 0, 5, …, 150 mm.
PCK_THRESHOLDS_MM: FloatArray = np.arange(0.0, 150.0 + 1e-9, 5.0)


def point_errors(pred: npt.ArrayLike, true: npt.ArrayLike) -> FloatArray:
    """Euclidean errors (F, K) between positions (F, K, 3).

    Raises:
        ValidationError: shapes differ, are not (F, K, 3), or hold non-finite values.
    """
    p = np.asarray(check_finite(check_shape(pred, ["F", "K", 3], name="pred")), np.float64)
    t = np.asarray(check_finite(check_shape(true, list(p.shape), name="true")), np.float64)
    return np.asarray(np.linalg.norm(p - t, axis=-1))


def _errors(errors: npt.ArrayLike) -> FloatArray:
    e = np.asarray(check_finite(check_shape(errors, ["F", "K"], name="errors")), np.float64)
    if e.size == 0:
        msg = "errors is empty; a metric needs at least one frame and one point"
        raise ValidationError(msg)
    return e


def mean_error(errors: npt.ArrayLike) -> float:
    """MPJPE / MPMPE: the mean of errors (F, K)."""
    return float(_errors(errors).mean())


def rms_per_frame(errors: npt.ArrayLike) -> FloatArray:
    """Per-frame root mean square of errors (F, K) -> (F,)."""
    e = _errors(errors)
    return np.asarray(np.sqrt(np.mean(e * e, axis=1)))


def rms_error(errors: npt.ArrayLike) -> float:
    """RMSPJPE / RMSPMPE: the mean over frames of the per-frame RMS."""
    return float(rms_per_frame(errors).mean())


def pck(errors: npt.ArrayLike, threshold: float) -> float:
    """The fraction of errors (F, K) at or below ``threshold`` (same unit)."""
    return float(np.mean(_errors(errors) <= threshold))


def pck_curve(errors: npt.ArrayLike, thresholds: npt.ArrayLike = PCK_THRESHOLDS_MM) -> FloatArray:
    """PCK3D at each threshold -> (T,)."""
    e = _errors(errors).ravel()
    th = np.asarray(thresholds, dtype=np.float64)
    return np.asarray(np.mean(e[None, :] <= th[:, None], axis=1))


def per_point_mean(errors: npt.ArrayLike) -> FloatArray:
    """Mean error of each point (joint or marker) over frames -> (K,)."""
    return np.asarray(_errors(errors).mean(axis=0))


def per_group_mean(errors: npt.ArrayLike, groups: Sequence[str]) -> dict[str, float]:
    """Mean error per group label (one label per frame, e.g. the action).

    Raises:
        ValidationError: the number of labels differs from the number of frames.
    """
    e = _errors(errors)
    if len(groups) != e.shape[0]:
        msg = f"groups has {len(groups)} labels for {e.shape[0]} frames; give one per frame"
        raise ValidationError(msg)
    labels = np.asarray(list(groups))
    return {str(g): float(e[labels == g].mean()) for g in dict.fromkeys(groups)}


def quaternion_angle_deg(q_pred: npt.ArrayLike, q_true: npt.ArrayLike) -> FloatArray:
    """Angles (deg) between unit quaternions (..., 4): ``arccos(2⟨q̂, q⟩² − 1)`` (paper Eq. 11).

    Quaternions are normalised first; q and −q give the same angle.

    Raises:
        ValidationError: shapes differ or are not (..., 4), or a quaternion has zero norm.
    """
    a = np.asarray(check_finite(check_shape(q_pred, ["...", 4], name="q_pred")), np.float64)
    b = np.asarray(check_finite(check_shape(q_true, list(a.shape), name="q_true")), np.float64)
    na, nb = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
    if np.any(na == 0) or np.any(nb == 0):
        msg = "a quaternion has zero norm; orientations must be unit (or non-zero) quaternions"
        raise ValidationError(msg)
    dot = np.sum(a * b, axis=-1) / (na * nb)
    return np.asarray(np.rad2deg(np.arccos(np.clip(2.0 * dot * dot - 1.0, -1.0, 1.0))))


@dataclass(frozen=True, slots=True)
class PoseMetrics:
    """Summary figures (mm, degrees, fractions in [0, 1])."""

    mpjpe_mm: float
    rmspjpe_mm: float
    mpmpe_mm: float | None
    rmspmpe_mm: float | None
    pck50: float
    pck_auc: float
    pck_curve: list[float]
    per_joint_mm: list[float]
    per_action_mm: dict[str, float] = field(default_factory=dict)
    mpjae_deg: float | None = None
    rmspjae_deg: float | None = None
    frames: int = 0


def pose_metrics(
    pred_joints_mm: npt.ArrayLike,
    true_joints_mm: npt.ArrayLike,
    *,
    pred_markers_mm: npt.ArrayLike | None = None,
    true_markers_mm: npt.ArrayLike | None = None,
    actions: Sequence[str] | None = None,
    q_pred: npt.ArrayLike | None = None,
    q_true: npt.ArrayLike | None = None,
) -> PoseMetrics:
    """All figures for one test set. Joints (F, J, 3), markers (F, M, 3), mm; ``actions`` one
    label per frame; orientations (F, J', 4) quaternions for MPJAE."""
    ej = point_errors(pred_joints_mm, true_joints_mm)
    em = (
        point_errors(pred_markers_mm, true_markers_mm)
        if pred_markers_mm is not None and true_markers_mm is not None
        else None
    )
    ang = None
    if q_pred is not None and q_true is not None:
        ang = quaternion_angle_deg(q_pred, q_true)
        ang = ang.reshape(ang.shape[0], -1)
    return PoseMetrics(
        mpjpe_mm=mean_error(ej),
        rmspjpe_mm=rms_error(ej),
        mpmpe_mm=None if em is None else mean_error(em),
        rmspmpe_mm=None if em is None else rms_error(em),
        pck50=pck(ej, 50.0),
        pck_auc=float(pck_curve(ej).mean()),
        pck_curve=[float(v) for v in pck_curve(ej)],
        per_joint_mm=[float(v) for v in per_point_mean(ej)],
        per_action_mm={} if actions is None else per_group_mean(ej, actions),
        mpjae_deg=None if ang is None else float(ang.mean()),
        rmspjae_deg=None if ang is None else rms_error(ang),
        frames=int(ej.shape[0]),
    )


@dataclass(frozen=True, slots=True)
class ProcrustesResult:
    """Per-frame similarity alignments of a prediction onto the truth.

    ``aligned[f] = scales[f] * pred[f] @ rotations[f].T + translations[f]`` for each frame f.

    Attributes:
        aligned: (F, K, 3) the aligned prediction, in the truth's frame and unit.
        rotations: (F, 3, 3) proper rotations (det = +1, never a reflection).
        translations: (F, 3) translations, in the truth's unit.
        scales: (F,) scale factors (all 1 when the alignment is rigid).
        with_scale: Whether the scale was estimated.
    """

    aligned: FloatArray = field(repr=False)
    rotations: FloatArray = field(repr=False)
    translations: FloatArray = field(repr=False)
    scales: FloatArray = field(repr=False)
    with_scale: bool


def procrustes_align(
    pred: npt.ArrayLike, true: npt.ArrayLike, *, with_scale: bool = False
) -> ProcrustesResult:
    """Align each frame of ``pred`` onto ``true`` by the least-squares rotation and translation
    (and, with ``with_scale``, one scale factor): per-frame Procrustes analysis, as before a
    "PA-MPJPE".

    The rotation is a proper rotation (reflections are excluded), found on the centred points by
    :meth:`scipy.spatial.transform.Rotation.align_vectors` (Kabsch); the scale is then
    ``Σ⟨t_c, R p_c⟩ / Σ|p_c|²`` (Umeyama). Inputs are not modified.

    Args:
        pred: (F, K, 3) predicted points.
        true: (F, K, 3) true points, same unit.
        with_scale: Also fit a scale factor per frame.

    Raises:
        ValidationError: shapes differ or are not (F, K, 3), K < 3, non-finite values, or a
            predicted frame whose points all coincide.
    """
    # imported here: scipy.spatial is heavy and only this function needs it
    from scipy.spatial.transform import Rotation

    p = np.asarray(check_finite(check_shape(pred, ["F", "K", 3], name="pred")), np.float64)
    t = np.asarray(check_finite(check_shape(true, list(p.shape), name="true")), np.float64)
    if p.shape[1] < 3:
        msg = f"Procrustes needs at least 3 points per frame, got {p.shape[1]}"
        raise ValidationError(msg)
    p_mean = p.mean(axis=1, keepdims=True)
    t_mean = t.mean(axis=1, keepdims=True)
    pc, tc = p - p_mean, t - t_mean
    spread = np.sum(pc * pc, axis=(1, 2))
    tiny = spread <= 1e-24 * np.maximum(np.sum(tc * tc, axis=(1, 2)), 1.0)
    if np.any(tiny):
        bad = np.flatnonzero(tiny)
        msg = f"pred frames {bad[:5].tolist()} have all points at one place; cannot align them"
        raise ValidationError(msg)
    n = p.shape[0]
    rot = np.empty((n, 3, 3))
    for f in range(n):
        # align_vectors(a, b) minimises Σ|a_i − R b_i|²; it only returns proper rotations
        r, _ = Rotation.align_vectors(tc[f], pc[f])
        rot[f] = r.as_matrix()
    rp = np.einsum("fij,fkj->fki", rot, pc)
    scale = np.sum(tc * rp, axis=(1, 2)) / spread if with_scale else np.ones(n)
    aligned = scale[:, None, None] * rp + t_mean
    trans = t_mean[:, 0, :] - scale[:, None] * np.einsum("fij,fj->fi", rot, p_mean[:, 0, :])
    return ProcrustesResult(
        aligned=aligned, rotations=rot, translations=trans, scales=scale, with_scale=with_scale
    )
