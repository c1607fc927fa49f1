"""Evaluation on held-out simulated sessions with known truth.

The test set is built from the ``test`` seed stream (:func:`dataset.make_pool`): subjects,
marker placements and takes never used in training, one take per procedural action, or a
given motion (e.g. a retargeted BVH clip never trained on) on new subjects. Each frame is
seen by a freshly sampled rig of ``num_cameras`` D415s, without rotation augmentation.

Metrics (:mod:`mocaprig.process.metrics`): joints over the paper's 17 evaluation joints (the two toe
joints left out, democap-method.md §5), markers over all 53. MPJAE uses segment orientations
built the same way for truth and estimate: the bone direction (joint to child joint) and a
marker pair across the segment, orthogonalised (the paper combines bone directions with
marker groups; its exact construction is not published). A network without markers (the
``"pose"`` baseline) gets no marker figures and no MPJAE: MPMPE, RMSPMPE, MPJAE and RMSPJAE
are None (JSON null).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from mocaprig.errors import ValidationError
from mocaprig.process.body import DEMOCAP_JOINTS, MARKER_NAMES, BvhClip
from mocaprig.process.democap.config import Variant
from mocaprig.process.democap.dataset import make_pool, make_sample, pool_from_bvh
from mocaprig.process.democap.infer import DemocapPredictor
from mocaprig.process.democap.simdata import PoseFrames
from mocaprig.process.metrics import PoseMetrics, pose_metrics

__all__ = [
    "EVAL_JOINTS",
    "SEGMENTS",
    "EvalReport",
    "evaluate",
    "held_out_pool",
    "segment_quaternions",
]

FloatArray = npt.NDArray[np.float64]

#: Indices (into DEMOCAP_JOINTS) of the 17 joints the paper evaluates (no toes).
EVAL_JOINTS: tuple[int, ...] = tuple(
    i for i, n in enumerate(DEMOCAP_JOINTS) if n not in ("RightToeBase", "LeftToeBase")
)

_J = {n: i for i, n in enumerate(DEMOCAP_JOINTS)}
_M = {n: i for i, n in enumerate(MARKER_NAMES)}

#: Segments for MPJAE: (joint, child joint, marker a, marker b); the frame's first axis is the
#: bone, the second the a -> b direction made orthogonal to it.
SEGMENTS: tuple[tuple[str, str, str, str], ...] = (
    ("Hips", "Spine1", "LFWT", "RFWT"),
    ("Spine2", "Neck", "T10", "STRN"),
    ("Neck", "Head", "LFHD", "RFHD"),
    *(
        (f"{s}{j}", f"{s}{c}", f"{p}{a}", f"{p}{b}")
        for s, p in (("Right", "R"), ("Left", "L"))
        for j, c, a, b in (
            ("Arm", "ForeArm", "IEL", "ELB"),
            ("ForeArm", "Hand", "IWR", "OWR"),
            ("UpLeg", "Leg", "KNI", "KNE"),
            ("Leg", "Foot", "HEL", "TOE"),
            ("Foot", "ToeBase", "MT1", "MT5"),
        )
    ),
)


def _unit(v: FloatArray, fallback: FloatArray) -> FloatArray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 1e-9, v / np.where(n > 1e-9, n, 1.0), fallback)


def segment_quaternions(joints: npt.ArrayLike, markers: npt.ArrayLike) -> FloatArray:
    """Orientation quaternions (F, S, 4) (x, y, z, w) of :data:`SEGMENTS` from joints
    (F, 19, 3) and markers (F, 53, 3)."""
    j = np.asarray(joints, np.float64)
    m = np.asarray(markers, np.float64)
    ji = np.array([[_J[a], _J[b]] for a, b, _, _ in SEGMENTS])
    mi = np.array([[_M[a], _M[b]] for _, _, a, b in SEGMENTS])
    x = _unit(j[:, ji[:, 1]] - j[:, ji[:, 0]], np.array([0.0, 0.0, 1.0]))
    y = m[:, mi[:, 1]] - m[:, mi[:, 0]]
    y = y - np.sum(y * x, -1, keepdims=True) * x
    # a degenerate marker pair (coincident, or along the bone) falls back to any perpendicular
    alt = np.cross(x, np.where(np.abs(x[..., :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]]))
    y = np.where(np.linalg.norm(y, axis=-1, keepdims=True) > 1e-9, y, alt)
    y = _unit(y, np.array([1.0, 0.0, 0.0]))
    z = np.cross(x, y)
    rot = np.stack([x, y, z], axis=-1)
    q = Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_quat()
    return np.asarray(q.reshape(j.shape[0], len(SEGMENTS), 4))


@dataclass(frozen=True, slots=True)
class EvalReport:
    """Figures of one evaluation run (see :class:`process.metrics.PoseMetrics`); ``variant`` is
    the evaluated network's (``"pose"``: no marker figures, no MPJAE)."""

    metrics: PoseMetrics
    num_cameras: int
    joint_names: tuple[str, ...]
    points_per_frame: float
    markers_seen: float
    variant: Variant = "markers-to-pose"

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict; per-joint errors keyed by joint name."""
        d = asdict(self.metrics)
        d["per_joint_mm"] = dict(zip(self.joint_names, d["per_joint_mm"], strict=True))
        d["variant"] = self.variant
        d["num_cameras"] = self.num_cameras
        d["points_per_frame"] = self.points_per_frame
        d["markers_seen"] = self.markers_seen
        return d


def held_out_pool(
    seed: int,
    *,
    motion: BvhClip | None = None,
    subjects: int = 1,
    freestyle: bool = False,
) -> list[PoseFrames]:
    """The held-out takes :func:`evaluate` uses: ``subjects`` rounds of the six procedural
    actions (4 s each, a new subject per take), or ``motion`` on ``subjects`` new bodies, or
    (``freestyle``) ``subjects`` × 6 takes of random key poses from the test stream (poses
    never trained on: the training takes draw other keys)."""
    if freestyle and motion is not None:
        msg = "pass either a BVH motion or freestyle, not both"
        raise ValidationError(msg)
    if freestyle:
        return make_pool(seed, "test", takes=subjects * 6, seconds=4.0, actions=("freestyle",))
    if motion is None:
        return make_pool(seed, "test", takes=subjects * 6, seconds=4.0)
    return pool_from_bvh(motion, seed, subjects=subjects)


def evaluate(
    predictor: DemocapPredictor,
    *,
    seed: int = 0,
    num_cameras: int = 4,
    motion: BvhClip | None = None,
    subjects: int = 1,
    frames_per_take: int = 40,
    batch: int = 16,
    pool: list[PoseFrames] | None = None,
) -> EvalReport:
    """Run ``predictor`` on a held-out simulated test set and measure it.

    A predictor without markers (``"pose"``) gets None for the marker figures and MPJAE.

    Args:
        predictor: the loaded network.
        seed: seed of the test set (the ``test`` stream; never the training one).
        num_cameras: 4, 3 or 2 D415s (3 drops one at random per frame, 2 keeps an opposing
            pair).
        motion: a BVH clip to test on instead of the procedural actions (retargeted onto
            new subjects).
        subjects: procedural: rounds of the six actions (a new subject per take); motion: the
            number of subjects performing it.
        frames_per_take: frames evenly spaced over each take.
        batch: frames per network batch.
        pool: takes to use instead of building them (for callers that reuse one test set).

    Raises:
        ValidationError: a non-positive ``frames_per_take`` or ``subjects``.
    """
    if frames_per_take < 1 or subjects < 1:
        msg = "frames_per_take and subjects must be >= 1"
        raise ValidationError(msg)
    takes = pool if pool is not None else held_out_pool(seed, motion=motion, subjects=subjects)
    rng = np.random.default_rng([seed, 7, num_cameras])
    size = predictor.size_px
    clouds, tm, tj, actions, seen = [], [], [], [], []
    for take in takes:
        idx = np.linspace(0, take.num_frames - 1, min(frames_per_take, take.num_frames))
        for i in np.round(idx).astype(int):
            s = make_sample(take, int(i), rng, num_cameras=num_cameras, augment=False, size_px=size)
            clouds.append(s.raw_m)
            tm.append(s.markers_m)
            tj.append(s.joints_m)
            actions.append(take.action)
            d = np.linalg.norm(s.raw_m[:, None, :] - s.markers_m[None], axis=-1)
            seen.append(float(np.mean(d.min(axis=0) < 0.03)))
    pm, pj = [], []
    for k in range(0, len(clouds), batch):
        for p in predictor.predict_many(clouds[k : k + batch]):
            pm.append(p.markers_m)
            pj.append(p.joints_m)
    pred_m, pred_j = np.array(pm) * 1000.0, np.array(pj) * 1000.0
    true_m, true_j = np.array(tm) * 1000.0, np.array(tj) * 1000.0
    keep = list(EVAL_JOINTS)
    markers = predictor.predicts_markers  # "pose": no markers, so no segment frames either
    met = pose_metrics(
        pred_j[:, keep],
        true_j[:, keep],
        pred_markers_mm=pred_m if markers else None,
        true_markers_mm=true_m if markers else None,
        actions=actions,
        q_pred=segment_quaternions(pred_j, pred_m) if markers else None,
        q_true=segment_quaternions(true_j, true_m) if markers else None,
    )
    return EvalReport(
        metrics=met,
        num_cameras=num_cameras,
        joint_names=tuple(DEMOCAP_JOINTS[k] for k in keep),
        points_per_frame=float(np.mean([len(c) for c in clouds])),
        markers_seen=float(np.mean(seen)),
        variant=predictor.checkpoint.config.variant,
    )
