"""Evaluation with known truth, and the evaluation protocols (docs/democap.md, "Protocols").

:func:`evaluate` measures a predictor on a set of takes: by default the ``test`` seed stream
(:func:`dataset.make_pool`): subjects, marker placements and takes never used in training, one
take per procedural action, or a given motion (e.g. a retargeted BVH clip never trained on) on
new subjects. Each frame is seen by a freshly sampled rig of ``num_cameras`` D415s, without
rotation augmentation. A frame whose fused cloud has fewer than 2 points is skipped and
counted (``skipped_frames``). Every figure is given over all evaluated frames and over the
frames in which the actor stands inside the volume the cameras see (the pelvis in the image of
every camera of that frame's rig, 0.3–6 m: :func:`simdata.in_frustum`), with that share: a
walking clip that leaves the rig's view measures the rig, not the network.

The protocols (:data:`PROTOCOLS`, :func:`run_protocol`), each labelled with what it holds out:

* ``in-distribution``: held-out simulated takes of the six procedural actions: new bodies and
  takes, but the same actions, body sampler and observation model as training;
* ``unseen-real``: the motion corpus's test split (:mod:`.corpus`): real captured motion of
  performers none of whose clips is in the training or validation split (the headline);
  clips the checkpoint was trained on are flagged and left out;
* ``leave-one-activity-out``: the corpus clips of each activity (train and test splits; the
  validation split is for model selection and never reported), without the clips the
  checkpoint was trained on; each activity says whether any clip of it was trained on;
* ``off-model``: the ``unseen-real`` clips on subjects the body model does not mirror
  (:data:`OFF_MODEL_SUBJECTS`: proportions spread twice as wide, markers placed 2.5× as
  loosely, the skin sliding 1.5 cm over the bone in every frame; :class:`dataset.SubjectModel`):
  what a body-model fit such as the skeleton solve is worth on people who are not our bodies;
* ``perturbed``: the ``in-distribution`` takes seen through the D415 model with its detection
  rate, noise, stray points and occlusion each pushed to 0.5× and 1.5× the values training
  uses (:class:`simdata.ObservationModel`), one knob at a time, then all four together the
  harder way and the easier way; then the subjects pushed off the body model, one way at a
  time and all together (:data:`BODY_PERTURBATIONS`).

Metrics (:mod:`mocaprig.process.metrics`): joints over the paper's 17 evaluation joints (the two toe
joints left out, democap-method.md §5), markers over all 53. MPJAE uses segment orientations
built the same way for truth and estimate: the bone direction (joint to child joint) and a
marker pair across the segment, orthogonalised (the paper combines bone directions with
marker groups; its exact construction is not published). A network without markers (the
``"pose"`` baseline) gets no marker figures and no MPJAE: MPMPE, RMSPMPE, MPJAE and RMSPJAE
are None (JSON null).
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body import DEMOCAP_JOINTS, MARKER_NAMES, BvhClip
from mocaprig.process.democap.checkpoint import Checkpoint
from mocaprig.process.democap.config import Variant
from mocaprig.process.democap.corpus import (
    CorpusClip,
    CorpusSplit,
    corpus_pool,
    load_split,
    read_corpus_clips,
)
from mocaprig.process.democap.dataset import (
    NOMINAL_SUBJECTS,
    SubjectModel,
    make_pool,
    pool_from_bvh,
    simulate_sample,
)
from mocaprig.process.democap.infer import DemocapPredictor
from mocaprig.process.democap.simdata import (
    CAPTURE_BOX_M,
    NOMINAL_OBSERVATION,
    PERTURBATION_KNOBS,
    Camera,
    ObservationModel,
    PoseFrames,
    in_frustum,
)
from mocaprig.process.metrics import PoseMetrics, per_group_mean, point_errors, pose_metrics
from mocaprig.progress import bind_stage

__all__ = [
    "BODY_PERTURBATIONS",
    "EVAL_JOINTS",
    "OFF_MODEL_SUBJECTS",
    "PERTURBATION_SCALES",
    "PROTOCOLS",
    "SEGMENTS",
    "TILT_BINS_DEG",
    "EvalReport",
    "Protocol",
    "ProtocolResult",
    "evaluate",
    "held_out_pool",
    "leave_one_activity_out",
    "off_model",
    "perturbed",
    "run_protocol",
    "segment_quaternions",
    "torso_tilt_deg",
    "trained_observation_jitter",
    "unseen_real",
]

_log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

Protocol = Literal[
    "in-distribution", "unseen-real", "off-model", "leave-one-activity-out", "perturbed"
]
#: The evaluation protocols (module doc).
PROTOCOLS: tuple[Protocol, ...] = get_args(Protocol)
#: The ``perturbed`` protocol's scales on each observation-model knob (±50 %).
PERTURBATION_SCALES: tuple[float, ...] = (0.5, 1.5)
#: Subjects the body model does not mirror (the ``off-model`` protocol, the last of
#: :data:`BODY_PERTURBATIONS`).
OFF_MODEL_SUBJECTS = SubjectModel(proportions=2.0, placement=2.5, soft_tissue_m=0.015)
#: The ``perturbed`` protocol's subjects: one way off the body model at a time, then all.
BODY_PERTURBATIONS: tuple[tuple[str, SubjectModel], ...] = (
    ("body proportions x2", SubjectModel(proportions=2.0)),
    ("marker placement x2.5", SubjectModel(placement=2.5)),
    ("skin motion 1.5 cm", SubjectModel(soft_tissue_m=0.015)),
    ("body all off", OFF_MODEL_SUBJECTS),
)

#: Indices (into DEMOCAP_JOINTS) of the 17 joints the paper evaluates (no toes).
EVAL_JOINTS: tuple[int, ...] = tuple(
    i for i, n in enumerate(DEMOCAP_JOINTS) if n not in ("RightToeBase", "LeftToeBase")
)

#: Edges (degrees) of the torso-tilt bins the figures are also given over (:func:`torso_tilt_deg`).
TILT_BINS_DEG: tuple[float, ...] = (0.0, 20.0, 40.0, 60.0, 180.0)

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


def torso_tilt_deg(joints: npt.ArrayLike) -> FloatArray:
    """The torso's tilt from the vertical, degrees (F,), of joints (F, J, 3) in DEMOCAP_JOINTS
    order, world frame (z up): the angle of Hips -> Neck from +z (0 upright, 90 bent double)."""
    j = np.asarray(joints, np.float64)
    t = j[:, _J["Neck"]] - j[:, _J["Hips"]]
    cos = t[:, 2] / np.maximum(np.linalg.norm(t, axis=-1), 1e-12)
    return np.asarray(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def _per_tilt(errors_mm: FloatArray, tilt_deg: FloatArray) -> dict[str, dict[str, Any]]:
    """Per torso-tilt bin ("0-20", ...) of joint errors (F, K): frames and their MPJPE (None
    without frames)."""
    names = [f"{lo:.0f}-{hi:.0f}" for lo, hi in itertools.pairwise(TILT_BINS_DEG)]
    labels = [names[i] for i in np.digitize(tilt_deg, TILT_BINS_DEG[1:-1])]
    means = per_group_mean(errors_mm, labels) if labels else {}
    return {n: {"frames": labels.count(n), "mpjpe_mm": means.get(n)} for n in names}


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
    the evaluated network's (``"pose"``: no marker figures, no MPJAE).

    Attributes:
        metrics: over every evaluated frame.
        inside_metrics: over the frames with the actor inside the volume the cameras see
            (module doc); None when there is none.
        inside_share: that share of the evaluated frames.
        frames_requested: frames asked for; ``skipped_frames`` of them had fewer than 2 points
            and are in no figure.
        per_torso_tilt: MPJPE and frames per bin of the true torso's tilt from the vertical
            (:data:`TILT_BINS_DEG`, :func:`torso_tilt_deg`), over every frame;
            ``inside_per_torso_tilt`` over the frames inside the volume.
        subject_calibration: rounds of subject calibration per take (0: every frame on its
            own; :attr:`DemocapPredictor.subject_calibration`).
        frame_by_frame: with ``subject_calibration``, the figures of the same run's first
            solve, every frame on its own (over every frame, and inside the volume or None).
    """

    metrics: PoseMetrics
    num_cameras: int
    joint_names: tuple[str, ...]
    points_per_frame: float
    markers_seen: float
    variant: Variant = "markers-to-pose"
    inside_metrics: PoseMetrics | None = None
    inside_share: float = 1.0
    frames_requested: int = 0
    skipped_frames: int = 0
    per_torso_tilt: dict[str, dict[str, Any]] = field(default_factory=dict)
    inside_per_torso_tilt: dict[str, dict[str, Any]] = field(default_factory=dict)
    subject_calibration: int = 0
    frame_by_frame: tuple[PoseMetrics, PoseMetrics | None] | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict: the all-frames figures at the top (per-joint errors keyed by joint
        name), the inside-the-volume ones under ``inside_volume``."""
        d = asdict(self.metrics)
        d["per_joint_mm"] = dict(zip(self.joint_names, d["per_joint_mm"], strict=True))
        d["variant"] = self.variant
        d["num_cameras"] = self.num_cameras
        d["points_per_frame"] = self.points_per_frame
        d["markers_seen"] = self.markers_seen
        d["frames_requested"] = self.frames_requested
        d["skipped_frames"] = self.skipped_frames
        d["per_torso_tilt"] = self.per_torso_tilt
        d["subject_calibration"] = self.subject_calibration
        if self.frame_by_frame is not None:
            whole, inside = self.frame_by_frame
            d["frame_by_frame"] = _summary(whole) | {
                "inside_volume": _summary(inside) | {"share": self.inside_share}
            }
        d["inside_volume"] = _summary(self.inside_metrics) | {
            "share": self.inside_share,
            "per_torso_tilt": self.inside_per_torso_tilt,
        }
        return d


def _summary(m: PoseMetrics | None) -> dict[str, Any]:
    if m is None:
        return {"frames": 0, "mpjpe_mm": None, "mpmpe_mm": None, "pck50": None}
    return {
        "frames": m.frames,
        "mpjpe_mm": m.mpjpe_mm,
        "mpmpe_mm": m.mpmpe_mm,
        "pck50": m.pck50,
        "mpjae_deg": m.mpjae_deg,
        "per_action_mm": dict(m.per_action_mm),
    }


def held_out_pool(
    seed: int,
    *,
    motion: BvhClip | None = None,
    subjects: int = 1,
    freestyle: bool = False,
    subject_model: SubjectModel = NOMINAL_SUBJECTS,
) -> list[PoseFrames]:
    """The held-out takes :func:`evaluate` uses: ``subjects`` rounds of the six procedural
    actions (4 s each, a new subject per take), or ``motion`` on ``subjects`` new bodies, or
    (``freestyle``) ``subjects`` × 6 takes of random key poses from the test stream (poses
    never trained on: the training takes draw other keys); ``subject_model`` draws the
    bodies."""
    if freestyle and motion is not None:
        msg = "pass either a BVH motion or freestyle, not both"
        raise ValidationError(msg)
    if freestyle:
        return make_pool(
            seed,
            "test",
            takes=subjects * 6,
            seconds=4.0,
            actions=("freestyle",),
            subjects=subject_model,
        )
    if motion is None:
        return make_pool(seed, "test", takes=subjects * 6, seconds=4.0, subjects=subject_model)
    return pool_from_bvh(motion, seed, subjects=subjects, subject_model=subject_model)


def _metrics(
    predicts_markers: bool,
    pred_j: FloatArray,
    true_j: FloatArray,
    pred_m: FloatArray,
    true_m: FloatArray,
    actions: list[str],
) -> PoseMetrics:
    keep = list(EVAL_JOINTS)
    return pose_metrics(
        pred_j[:, keep],
        true_j[:, keep],
        pred_markers_mm=pred_m if predicts_markers else None,
        true_markers_mm=true_m if predicts_markers else None,
        actions=actions,
        q_pred=segment_quaternions(pred_j, pred_m) if predicts_markers else None,
        q_true=segment_quaternions(true_j, true_m) if predicts_markers else None,
    )


def _by_subject(
    predictor: DemocapPredictor,
    clouds: list[FloatArray],
    views: list[list[Camera]],
    take_of: npt.NDArray[np.intp],
    progress: Callable[[int, int], None] | None,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Each take's frames through :meth:`DemocapPredictor.predict_subject` (one subject per
    take; a take of fewer than 3 clouds frame by frame) -> markers (B, 53, 3), joints
    (B, 19, 3) with the calibration, then each frame solved on its own, m, in cloud order."""
    n, nm, nj = len(clouds), len(MARKER_NAMES), len(DEMOCAP_JOINTS)
    pm, pj = np.empty((n, nm, 3)), np.empty((n, nj, 3))
    fm, fj = np.empty((n, nm, 3)), np.empty((n, nj, 3))
    done = 0
    for t in np.unique(take_of):
        rows = np.flatnonzero(take_of == t)
        cl, vw = [clouds[i] for i in rows], [views[i] for i in rows]
        if len(rows) >= 3:
            res = predictor.predict_subject(
                cl, views=vw, crop_box_m=CAPTURE_BOX_M, rounds=predictor.subject_calibration
            )
            out, alone = res.predictions, res.frame_by_frame
        else:
            out = alone = predictor.predict_many(cl, views=vw, crop_box_m=CAPTURE_BOX_M)
        for i, p, a in zip(rows, out, alone, strict=True):
            pm[i], pj[i], fm[i], fj[i] = p.markers_m, p.joints_m, a.markers_m, a.joints_m
        done += len(rows)
        if progress is not None:
            progress(done, len(clouds))
    return pm, pj, fm, fj


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
    observation: ObservationModel = NOMINAL_OBSERVATION,
    progress: Callable[[int, int], None] | None = None,
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
        observation: the D415 model's scales (the ``perturbed`` protocol; default: training's).
        progress: called ``(frames estimated, frames)`` after each batch.

    Raises:
        ValidationError: a non-positive ``frames_per_take`` or ``subjects``.
        ProcessingError: no frame gave a cloud of 2 points or more.
    """
    if frames_per_take < 1 or subjects < 1:
        msg = "frames_per_take and subjects must be >= 1"
        raise ValidationError(msg)
    takes = pool if pool is not None else held_out_pool(seed, motion=motion, subjects=subjects)
    rng = np.random.default_rng([seed, 7, num_cameras])
    size = predictor.size_px
    clouds, tm, tj, actions, seen, inside, views = [], [], [], [], [], [], []
    take_of: list[int] = []
    requested = 0
    for k_take, take in enumerate(takes):
        idx = np.linspace(0, take.num_frames - 1, min(frames_per_take, take.num_frames))
        for i in np.round(idx).astype(int):
            requested += 1
            s = simulate_sample(
                take,
                int(i),
                rng,
                num_cameras=num_cameras,
                augment=False,
                size_px=size,
                observation=observation,
            )
            if s is None:  # fewer than 2 points: no cloud to measure, counted
                continue
            clouds.append(s.raw_m)
            tm.append(s.markers_m)
            tj.append(s.joints_m)
            actions.append(take.action)
            d = np.linalg.norm(s.raw_m[:, None, :] - s.markers_m[None], axis=-1)
            seen.append(float(np.mean(d.min(axis=0) < 0.03)))
            inside.append(bool(in_frustum(s.joints_m[:1], list(s.cameras)).all()))
            views.append(list(s.cameras))
            take_of.append(k_take)
    if not clouds:
        msg = f"none of the {requested} frames gave a cloud of 2 points or more"
        raise ProcessingError(msg)
    if requested > len(clouds):
        _log.info(
            "%d of %d frames skipped: fewer than 2 points", requested - len(clouds), requested
        )
    pm: list[FloatArray] = []
    pj: list[FloatArray] = []
    alone: tuple[FloatArray, FloatArray] | None = None
    if progress is not None:
        progress(0, len(clouds))
    if predictor.subject_calibration:
        cal_m, cal_j, fm, fj = _by_subject(predictor, clouds, views, np.array(take_of), progress)
        pm, pj, alone = list(cal_m), list(cal_j), (fm * 1000.0, fj * 1000.0)
    else:
        for k in range(0, len(clouds), batch):
            # the rig is calibrated: the solve knows where the cameras look
            # the simulated clouds are cropped to the capture box, as the replay's are
            for p in predictor.predict_many(
                clouds[k : k + batch], views=views[k : k + batch], crop_box_m=CAPTURE_BOX_M
            ):
                pm.append(p.markers_m)
                pj.append(p.joints_m)
            if progress is not None:
                progress(len(pm), len(clouds))
    pred_m, pred_j = np.array(pm) * 1000.0, np.array(pj) * 1000.0
    true_m, true_j = np.array(tm) * 1000.0, np.array(tj) * 1000.0
    markers = predictor.predicts_markers  # "pose": no markers, so no segment frames either
    met = _metrics(markers, pred_j, true_j, pred_m, true_m, actions)
    ins = np.array(inside)
    keep = list(EVAL_JOINTS)
    err = point_errors(pred_j[:, keep], true_j[:, keep])
    tilt = torso_tilt_deg(true_j)
    inside_actions = [a for a, k in zip(actions, inside, strict=True) if k]
    met_in = None
    if ins.any():
        met_in = _metrics(
            markers, pred_j[ins], true_j[ins], pred_m[ins], true_m[ins], inside_actions
        )
    alone_met: tuple[PoseMetrics, PoseMetrics | None] | None = None
    if alone is not None:
        am, aj = alone
        alone_met = (
            _metrics(markers, aj, true_j, am, true_m, actions),
            _metrics(markers, aj[ins], true_j[ins], am[ins], true_m[ins], inside_actions)
            if ins.any()
            else None,
        )
    return EvalReport(
        metrics=met,
        num_cameras=num_cameras,
        joint_names=tuple(DEMOCAP_JOINTS[k] for k in EVAL_JOINTS),
        points_per_frame=float(np.mean([len(c) for c in clouds])),
        markers_seen=float(np.mean(seen)),
        variant=predictor.checkpoint.config.variant,
        inside_metrics=met_in,
        inside_share=float(ins.mean()),
        frames_requested=requested,
        skipped_frames=requested - len(clouds),
        per_torso_tilt=_per_tilt(err, tilt),
        inside_per_torso_tilt=_per_tilt(err[ins], tilt[ins]),
        subject_calibration=predictor.subject_calibration,
        frame_by_frame=alone_met,
    )


# ------------------------------------------------------------------------------- protocols


@dataclass(frozen=True, slots=True)
class ProtocolResult:
    """One labelled figure of a protocol.

    Attributes:
        protocol: the protocol (:data:`PROTOCOLS`), or ``"bvh-motion"`` / ``"freestyle"``
            for ``eval --motion`` / ``--freestyle``.
        label: this figure within it (an activity, a perturbation, or the protocol again).
        holds_out: what the figure holds out from training, in words.
        report: the figures (None: nothing was left to evaluate, ``note`` says why).
        clips: corpus clips evaluated.
        trained_clips: clips of this set the checkpoint was trained on: flagged and left out.
        trained_on: whether the figure's data was (partly) trained on (``leave-one-activity-
            out``: some clip of the activity was in training).
        budget: frames per clip or take, bodies per clip, seed.
        note: anything the reader must know.
    """

    protocol: str
    label: str
    holds_out: str
    report: EvalReport | None
    clips: tuple[str, ...] = ()
    trained_clips: tuple[str, ...] = ()
    trained_on: bool = False
    budget: dict[str, int] = field(default_factory=dict)
    note: str = ""

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict: the labels, then the report's figures (:meth:`EvalReport.to_dict`)."""
        d: dict[str, Any] = {
            "protocol": self.protocol,
            "label": self.label,
            "holds_out": self.holds_out,
            "clips": list(self.clips),
            "trained_clips": list(self.trained_clips),
            "trained_on": self.trained_on,
            "budget": dict(self.budget),
            "note": self.note,
        }
        if self.report is not None:
            d.update(self.report.to_dict())
        return d


_HOLDS_OUT = {
    "in-distribution": (
        "bodies, marker placements and takes (test seed stream); the actions, body sampler "
        "and observation model are training's"
    ),
    "unseen-real": (
        "real captured motion of performers whose clips are in no training or validation "
        "split (the corpus test split, retargeted onto new bodies)"
    ),
    "off-model": (
        "real captured motion of performers in no training or validation split, on subjects "
        "the body model does not mirror (proportions x2, marker placement x2.5, 1.5 cm skin "
        "motion)"
    ),
    "perturbed": (
        "the observation model: in-distribution takes seen with a D415 model pushed away "
        "from training's"
    ),
    "perturbed-body": (
        "the subjects: in-distribution takes on bodies pushed away from the body model"
    ),
}


def _budget(frames: int, subjects: int, seed: int) -> dict[str, int]:
    return {"frames_per_take": frames, "subjects": subjects, "seed": seed}


def unseen_real(
    predictor: DemocapPredictor,
    corpus_dir: Path,
    *,
    split: CorpusSplit | None = None,
    seed: int = 0,
    num_cameras: int = 4,
    subjects: int = 1,
    frames_per_clip: int = 20,
    subject_model: SubjectModel = NOMINAL_SUBJECTS,
    progress: Callable[[str, int, int], None] | None = None,
) -> ProtocolResult:
    """The ``unseen-real`` protocol: the corpus test split on ``subjects`` new bodies per clip,
    ``frames_per_clip`` frames each, without the clips the checkpoint was trained on (flagged
    in ``trained_clips``); with ``subject_model`` other than the nominal one, the
    ``off-model`` protocol (:func:`off_model`). ``progress`` is told ``(figure, frames
    estimated, frames)``.

    Raises:
        ValidationError: the corpus folder or one of its test clips is missing.
    """
    name = "unseen-real" if subject_model.is_nominal else "off-model"
    table = split or load_split()
    trained = set(predictor.checkpoint.train_motions)
    clips = table.in_split("test")
    flagged = tuple(c.name for c in clips if c.name in trained)
    use = [c for c in clips if c.name not in trained]
    budget = _budget(frames_per_clip, subjects, seed)
    if not use:
        note = "every test clip was trained on: no held-out figure"
        return ProtocolResult(
            name,
            name,
            _HOLDS_OUT[name],
            None,
            trained_clips=flagged,
            trained_on=True,
            budget=budget,
            note=note,
        )
    pool = corpus_pool(
        read_corpus_clips(corpus_dir, use),
        seed,
        split="test",
        subjects=subjects,
        subject_model=subject_model,
    )
    rep = evaluate(
        predictor,
        seed=seed,
        num_cameras=num_cameras,
        frames_per_take=frames_per_clip,
        pool=pool,
        progress=bind_stage(progress, name),
    )
    note = ""
    if flagged:
        note = f"left out, trained on: {', '.join(flagged)}"
    return ProtocolResult(
        name,
        name,
        _HOLDS_OUT[name],
        rep,
        clips=tuple(c.name for c in use),
        trained_clips=flagged,
        budget=budget,
        note=note,
    )


def off_model(
    predictor: DemocapPredictor,
    corpus_dir: Path,
    *,
    split: CorpusSplit | None = None,
    seed: int = 0,
    num_cameras: int = 4,
    subjects: int = 1,
    frames_per_clip: int = 20,
    progress: Callable[[str, int, int], None] | None = None,
) -> ProtocolResult:
    """The ``off-model`` protocol: :func:`unseen_real` on :data:`OFF_MODEL_SUBJECTS`, bodies
    the body model does not mirror (the estimator is not told).

    Raises:
        ValidationError: the corpus folder or one of its test clips is missing.
    """
    return unseen_real(
        predictor,
        corpus_dir,
        split=split,
        seed=seed,
        num_cameras=num_cameras,
        subjects=subjects,
        frames_per_clip=frames_per_clip,
        subject_model=OFF_MODEL_SUBJECTS,
        progress=progress,
    )


def leave_one_activity_out(
    predictor: DemocapPredictor,
    corpus_dir: Path,
    *,
    split: CorpusSplit | None = None,
    seed: int = 0,
    num_cameras: int = 4,
    subjects: int = 1,
    frames_per_clip: int = 10,
    activities: Sequence[str] | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> list[ProtocolResult]:
    """The ``leave-one-activity-out`` protocol: per activity of the split table, its clips of
    the train and test splits that the checkpoint was not trained on (the validation split is
    never reported). ``trained_on`` is True when any corpus clip of that activity was trained
    on: the figure then holds out the clips, not the activity (train with ``democap train
    --hold-out-activity A`` for a true leave-one-activity-out run). ``progress`` is told
    ``(activity, frames estimated, frames)``.

    Raises:
        ValidationError: the corpus folder or a clip is missing, or an unknown activity.
    """
    table = split or load_split()
    acts = tuple(activities) if activities is not None else table.activities()
    unknown = [a for a in acts if a not in table.activities()]
    if unknown:
        msg = f"unknown activities {unknown}; the split table has {', '.join(table.activities())}"
        raise ValidationError(msg)
    trained = set(predictor.checkpoint.train_motions)
    trained_acts = {c.activity for c in table.clips if c.name in trained}
    budget = _budget(frames_per_clip, subjects, seed)
    out = []
    for act in acts:
        clips = [c for c in table.clips if c.activity == act and c.split != "validation"]
        flagged = tuple(c.name for c in clips if c.name in trained)
        use: list[CorpusClip] = [c for c in clips if c.name not in trained]
        seen = act in trained_acts
        holds = (
            f"the clips of {act!r} not trained on; other clips of the activity were"
            if seen
            else f"the activity {act!r}: no clip of it was trained on"
        )
        if not use:
            out.append(
                ProtocolResult(
                    "leave-one-activity-out",
                    act,
                    holds,
                    None,
                    trained_clips=flagged,
                    trained_on=seen,
                    budget=budget,
                    note="every clip of the activity was trained on",
                )
            )
            continue
        pool = corpus_pool(
            read_corpus_clips(corpus_dir, use), seed, split="test", subjects=subjects
        )
        rep = evaluate(
            predictor,
            seed=seed,
            num_cameras=num_cameras,
            frames_per_take=frames_per_clip,
            pool=pool,
            progress=bind_stage(progress, act),
        )
        out.append(
            ProtocolResult(
                "leave-one-activity-out",
                act,
                holds,
                rep,
                clips=tuple(c.name for c in use),
                trained_clips=flagged,
                trained_on=seen,
                budget=budget,
            )
        )
    return out


def trained_observation_jitter(checkpoint: Checkpoint) -> float:
    """The widest D415-model jitter any epoch of ``checkpoint`` trained with
    (:attr:`train.TrainOptions.observation_jitter`; 0: the nominal model only)."""
    return max((float(h.get("observation_jitter", 0.0)) for h in checkpoint.history), default=0.0)


def _trained_range_note(model: ObservationModel, jitter: float) -> str:
    """Where a perturbation's scales lie against the range training drew them from."""
    if jitter == 0.0:
        return "training saw the nominal D415 model only (every scale 1)"
    lo, hi = 1.0 - jitter, 1.0 + jitter
    moved = [k for k in PERTURBATION_KNOBS if getattr(model, k) != 1.0]
    inside = sorted(k for k in moved if lo <= getattr(model, k) <= hi)
    where = (
        f"inside it for {', '.join(inside)}: not a model training never saw"
        if inside
        else "every moved scale lies outside it"
    )
    drew = f"training drew each scale from [{lo:g}, {hi:g}] (observation jitter {jitter:g})"
    return f"{drew}; {where}"


def perturbed(
    predictor: DemocapPredictor,
    *,
    seed: int = 0,
    num_cameras: int = 4,
    subjects: int = 1,
    frames_per_take: int = 8,
    scales: Sequence[float] = PERTURBATION_SCALES,
    bodies: bool = True,
    progress: Callable[[str, int, int], None] | None = None,
) -> list[ProtocolResult]:
    """The ``perturbed`` protocol: the ``in-distribution`` takes of ``seed`` through the D415
    model with each knob (:data:`simdata.PERTURBATION_KNOBS`) at each of ``scales``, one knob
    at a time, then all knobs together the harder way (``"all harder"``: detection at the
    smallest scale, noise, strays and occlusion at the largest) and the easier way; then
    (``bodies``) the same takes on subjects pushed off the body model
    (:data:`BODY_PERTURBATIONS`), one way at a time and all together. ``progress`` is told
    ``(perturbation, frames estimated, frames)``."""
    pool = held_out_pool(seed, subjects=subjects)
    budget = _budget(frames_per_take, subjects, seed)
    runs: list[tuple[str, ObservationModel]] = [
        (f"{knob} x{f:g}", ObservationModel(**{knob: f}))
        for knob in PERTURBATION_KNOBS
        for f in scales
    ]
    # all knobs at once, each pushed the harder way, then each the easier way (fewer
    # detections is harder; more noise, strays and occlusion are)
    lo, hi = min(scales), max(scales)
    runs.append(("all harder", ObservationModel(detection=lo, noise=hi, strays=hi, occlusion=hi)))
    runs.append(("all easier", ObservationModel(detection=hi, noise=lo, strays=lo, occlusion=lo)))
    jitter = trained_observation_jitter(predictor.checkpoint)
    out = []
    for label, model in runs:
        rep = evaluate(
            predictor,
            seed=seed,
            num_cameras=num_cameras,
            frames_per_take=frames_per_take,
            pool=pool,
            observation=model,
            progress=bind_stage(progress, label),
        )
        note = _trained_range_note(model, jitter)
        out.append(
            ProtocolResult(
                "perturbed", label, _HOLDS_OUT["perturbed"], rep, budget=budget, note=note
            )
        )
    for label, subject_model in BODY_PERTURBATIONS if bodies else ():
        rep = evaluate(
            predictor,
            seed=seed,
            num_cameras=num_cameras,
            frames_per_take=frames_per_take,
            pool=held_out_pool(seed, subjects=subjects, subject_model=subject_model),
            progress=bind_stage(progress, label),
        )
        out.append(
            ProtocolResult("perturbed", label, _HOLDS_OUT["perturbed-body"], rep, budget=budget)
        )
    return out


def run_protocol(
    predictor: DemocapPredictor,
    protocol: Protocol,
    *,
    corpus_dir: Path | None = None,
    seed: int = 0,
    num_cameras: int = 4,
    subjects: int = 1,
    frames: int | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> list[ProtocolResult]:
    """One protocol's labelled figures. ``frames`` per take or clip (default: 40 for
    ``in-distribution``, 20 for ``unseen-real`` and ``off-model``, 10 for
    ``leave-one-activity-out``, 8 per perturbation). ``progress`` is told ``(figure's
    label, frames estimated, frames)`` as each figure's frames are estimated.

    Raises:
        ValidationError: an unknown protocol, or a corpus protocol without ``corpus_dir``.
    """
    if protocol not in PROTOCOLS:
        msg = f"unknown protocol {protocol!r}; choose one of {', '.join(PROTOCOLS)}"
        raise ValidationError(msg)
    if protocol == "in-distribution":
        n = frames or 40
        pool = held_out_pool(seed, subjects=subjects)
        rep = evaluate(
            predictor,
            seed=seed,
            num_cameras=num_cameras,
            frames_per_take=n,
            pool=pool,
            progress=bind_stage(progress, protocol),
        )
        return [
            ProtocolResult(
                protocol,
                protocol,
                _HOLDS_OUT[protocol],
                rep,
                budget=_budget(n, subjects, seed),
            )
        ]
    if protocol == "perturbed":
        return perturbed(
            predictor,
            seed=seed,
            num_cameras=num_cameras,
            subjects=subjects,
            frames_per_take=frames or 8,
            progress=progress,
        )
    if corpus_dir is None:
        msg = (
            f"protocol {protocol!r} needs the motion corpus (../shared/data/motion/corpus); "
            "pass its folder"
        )
        raise ValidationError(msg)
    if protocol in ("unseen-real", "off-model"):
        return [
            unseen_real(
                predictor,
                corpus_dir,
                seed=seed,
                num_cameras=num_cameras,
                subjects=subjects,
                frames_per_clip=frames or 20,
                subject_model=NOMINAL_SUBJECTS if protocol == "unseen-real" else OFF_MODEL_SUBJECTS,
                progress=progress,
            )
        ]
    return leave_one_activity_out(
        predictor,
        corpus_dir,
        seed=seed,
        num_cameras=num_cameras,
        subjects=subjects,
        frames_per_clip=frames or 10,
        progress=progress,
    )
