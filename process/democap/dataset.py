"""Training and held-out sample pools and batches, deterministic for a seed.

A pool is a list of takes (:class:`process.democap.simdata.PoseFrames`) at 30 Hz, each a new
subject (:meth:`BodyShape.sample`, marker placement jitter σ = 1 cm), a procedural motion with
new take variation and, for training, a constant random offset on every joint angle (up to
±12°, clipped to the limits) so the poses are not limited to the six scores; a third of the
training takes are ``freestyle`` (random key poses within the joint limits,
:mod:`mocaprig.process.body.procedural`). The training,
validation and held-out (test) pools come from different seed streams, so validation and test
bodies, placements and takes are never seen in training, and the validation set that guides a
run is never a test set; a BVH clip (``--motion``) gives an action never trained on. BVH clips
(``democap train --bvh``) and the motion corpus's training split (``--corpus``,
:mod:`.corpus`) join the training pool on bodies of their own seed stream; the checkpoint
lists their names so an evaluation on one of them is flagged.

A sample: one frame of one take, the actor turned to a random heading and moved up to 0.6 m
off the centre, seen by a freshly sampled rig (:func:`simdata.sample_rig`), fused
(:func:`simdata.merge_views`), moved to the image frame, centred on the raw centroid, rotated
(training: ±10° / ±180° / ±10°), normalised from the raw points and rendered front and back.
Training may see each sample through its own D415 model (``observation_jitter``,
:func:`jittered_observation`: detection, noise, strays and occlusion scaled by draws around 1),
so the network meets sparser and noisier clouds than the nominal model gives.
A frame whose fused cloud has fewer than 2 points (the actor out of every camera's view) gives
no sample (:func:`simulate_sample` returns None): training draws another frame, evaluation
skips it and counts it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
import numpy.typing as npt
import torch
from scipy.spatial.transform import Rotation

from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body import (
    DOF_LIMITS_RAD,
    PROCEDURAL_MOTIONS,
    BodyShape,
    BvhClip,
    MarkerSet,
    Motion,
    make_motion,
    retarget_bvh,
)
from mocaprig.process.democap.geometry import (
    Normalisation,
    back_view,
    normalise,
    random_rotation,
    render_view,
    to_image_frame,
)
from mocaprig.process.democap.simdata import (
    NOMINAL_OBSERVATION,
    PERTURBATION_KNOBS,
    Camera,
    ObservationModel,
    PoseFrames,
    merge_views,
    observe,
    pose_frames,
    sample_rig,
)

__all__ = [
    "NOMINAL_SUBJECTS",
    "TRAIN_ACTIONS",
    "Batch",
    "Sample",
    "SubjectModel",
    "check_observation_jitter",
    "jittered_observation",
    "make_batch",
    "make_pool",
    "make_sample",
    "pool_from_bvh",
    "prepare_cloud",
    "simulate_sample",
]

FloatArray = npt.NDArray[np.float64]
Split = Literal["train", "validation", "test"]

#: The scored procedural actions, used in both pools (the static T-pose is left out: it adds
#: nothing; ``freestyle`` has no score and is training-only).
TRAIN_ACTIONS: tuple[str, ...] = tuple(
    m for m in PROCEDURAL_MOTIONS if m not in ("t_pose", "freestyle")
)
#: The training pool's cycle: the scored actions, then random key poses (``freestyle``) for a
#: third of the takes, so the network sees poses beyond the scores.
_TRAIN_CYCLE: tuple[str, ...] = (*TRAIN_ACTIONS, *(("freestyle",) * (len(TRAIN_ACTIONS) // 2)))
RATE_HZ = 30.0
_SPLIT_KEY = {"train": 0, "test": 1, "validation": 4}
#: Seed streams of BVH takes (the held-out one predates the training one).
_BVH_KEY = {"train": 3, "test": 2, "validation": 5}
#: Seed-stream key of the soft-tissue displacements (SubjectModel.soft_tissue_m), apart from
#: the take's own stream so that the takes stay the same.
_SKIN_KEY = 6
#: make_batch gives up after this many frames in a row without a usable cloud.
_MAX_REDRAWS = 200


@dataclass(frozen=True, slots=True)
class SubjectModel:
    """How far the simulated subjects depart from the body model, for stress tests (the
    defaults: the bodies training and the nominal test sets draw, :data:`NOMINAL_SUBJECTS`).

    A real subject is not one of our bodies: their proportions stray further from Drillis &
    Contini, markers are stuck on by hand, and the skin slides over the bone as they move.
    None of this is told to the estimator.

    Attributes:
        proportions: scales the spreads of :meth:`BodyShape.sample` about its centre: the
            height range (1.75 ± 0.20 m), each segment's ±5 % and each radius's ±5 %, and
            the girth range (0.9-1.15); 2 doubles them all.
        placement: scales the marker placement jitter along the skin (σ = 1 cm).
        soft_tissue_m: σ of a fresh displacement of every marker along the skin in every
            frame (m; 0 nominal): skin and suit moving over the bone.

    Raises:
        ValidationError: a negative value, or ``proportions`` so large that a sampled body
            would have non-positive segments (above 5).
    """

    proportions: float = 1.0
    placement: float = 1.0
    soft_tissue_m: float = 0.0

    def __post_init__(self) -> None:
        for name in ("proportions", "placement", "soft_tissue_m"):
            if not float(getattr(self, name)) >= 0.0:
                msg = f"SubjectModel.{name} must be >= 0, got {getattr(self, name)!r}"
                raise ValidationError(msg)
        if self.proportions > 5.0:
            msg = f"SubjectModel.proportions must be <= 5, got {self.proportions!r}"
            raise ValidationError(msg)

    @property
    def is_nominal(self) -> bool:
        """Whether these are the bodies training draws."""
        return self == NOMINAL_SUBJECTS

    def body(self, rng: np.random.Generator) -> tuple[BodyShape, MarkerSet]:
        """A subject and their markers. The random numbers drawn do not depend on the scales
        (a scaled pool holds the same takes on other bodies), except that a body on which a
        marker cannot be placed (wide proportions make one in 200 at ×2) is drawn again.

        Raises:
            ProcessingError: 20 draws in a row gave such bodies (proportions far too wide).
        """
        p = self.proportions
        for _ in range(20):
            # The nominal call as it always was, so nominal pools stay bit for bit the same.
            shape = (
                BodyShape.sample(rng)
                if p == 1.0
                else BodyShape.sample(
                    rng,
                    height_range_m=(1.75 - 0.20 * p, 1.75 + 0.20 * p),
                    segment_variation=min(0.05 * p, 0.3),
                    girth_range=(1.025 - 0.125 * p, 1.025 + 0.125 * p),
                    radius_variation=min(0.05 * p, 0.3),
                )
            )
            try:
                markers = MarkerSet.for_shape(shape)
            except ProcessingError:
                continue
            return shape, markers.jittered(rng, sigma_m=0.01 * self.placement)
        msg = f"SubjectModel(proportions={p}): 20 sampled bodies could not carry the markers"
        raise ProcessingError(msg)

    def moved(self, frames: PoseFrames, rng: np.random.Generator) -> PoseFrames:
        """``frames`` with every marker moved along the skin by ``soft_tissue_m`` per frame."""
        if self.soft_tissue_m == 0.0:
            return frames
        g = rng.normal(0.0, self.soft_tissue_m, frames.markers_m.shape)
        g -= np.sum(g * frames.normals, axis=-1, keepdims=True) * frames.normals
        return replace(frames, markers_m=frames.markers_m + g)


#: The bodies training and the nominal test sets draw.
NOMINAL_SUBJECTS = SubjectModel()


def _offset_motion(motion: Motion, rng: np.random.Generator, max_deg: float) -> Motion:
    off = np.deg2rad(rng.uniform(-max_deg, max_deg, DOF_LIMITS_RAD.shape[0]))
    poses = np.array(motion.poses)
    poses[:, 6:] = np.clip(poses[:, 6:] + off, DOF_LIMITS_RAD[:, 0], DOF_LIMITS_RAD[:, 1])
    return Motion(motion.name, motion.rate_hz, poses)


def _check_split_and_count(split: str, **count: int) -> None:
    if split not in _SPLIT_KEY:
        msg = f"split must be 'train', 'validation' or 'test', got {split!r}"
        raise ValidationError(msg)
    for name, n in count.items():
        if n < 1:
            msg = f"{name} must be >= 1, got {n}"
            raise ValidationError(msg)


def make_pool(
    seed: int,
    split: Split,
    *,
    takes: int,
    seconds: float = 6.0,
    actions: Sequence[str] | None = None,
    subjects: SubjectModel = NOMINAL_SUBJECTS,
) -> list[PoseFrames]:
    """``takes`` takes from the ``split`` seed stream, cycling through :data:`TRAIN_ACTIONS`
    (``"train"``: then three ``freestyle`` takes of random key poses per cycle) or through
    ``actions`` (procedural motion names) when given. ``"validation"`` and ``"test"`` take
    the scored actions without the training pose offsets, from streams of their own.
    ``subjects`` draws the bodies (default: the nominal ones).

    Raises:
        ValidationError: ``takes`` < 1, an unknown split or an unknown or empty action list.
    """
    if actions is not None and (not actions or any(a not in PROCEDURAL_MOTIONS for a in actions)):
        msg = f"actions must be procedural motions ({', '.join(PROCEDURAL_MOTIONS)}), got {actions}"
        raise ValidationError(msg)
    _check_split_and_count(split, takes=takes)
    pool = []
    for k in range(takes):
        rng = np.random.default_rng([seed, _SPLIT_KEY[split], k])
        shape, markers = subjects.body(rng)
        cycle = actions or (_TRAIN_CYCLE if split == "train" else TRAIN_ACTIONS)
        action = cycle[k % len(cycle)]
        motion = make_motion(action, seconds=seconds, rng=rng, rate_hz=RATE_HZ, shape=shape)
        if split == "train":
            motion = _offset_motion(motion, rng, 12.0)
        skin = np.random.default_rng([seed, _SPLIT_KEY[split], k, _SKIN_KEY])
        pool.append(subjects.moved(pose_frames(motion, shape, markers), skin))
    return pool


def _centred(motion: Motion) -> Motion:
    poses = np.array(motion.poses)
    poses[:, 3:5] -= poses[:, 3:5].mean(axis=0)
    return Motion(motion.name, motion.rate_hz, poses)


def pool_from_bvh(
    clip: BvhClip,
    seed: int,
    *,
    subjects: int = 1,
    split: Split = "test",
    centre: bool = False,
    first_body: int = 0,
    subject_model: SubjectModel = NOMINAL_SUBJECTS,
) -> list[PoseFrames]:
    """Takes of a BVH clip on ``subjects`` new bodies: the clip is thinned to about 30 Hz and
    retargeted onto each body (:func:`mocaprig.process.body.retarget_bvh`). ``"test"``: held-out
    bodies (e.g. for a clip never trained on); ``"train"`` / ``"validation"``: bodies of seed
    streams of their own, for clips in the training pool / the validation set. ``centre``
    moves the clip on the floor so that the mean of its root's floor positions is the rig's
    centre (the corpus clips: a capture is made where the cameras look; without it a clip keeps
    the position it was recorded at). The bodies are numbers ``first_body`` ...
    ``first_body + subjects - 1`` of the split's stream (callers with many clips give each clip
    bodies of its own). ``subject_model`` draws the bodies (default: the nominal ones).

    Raises:
        ValidationError: ``subjects`` < 1, a negative ``first_body`` or an unknown split.
    """
    _check_split_and_count(split, subjects=subjects)
    if first_body < 0:
        msg = f"first_body must be >= 0, got {first_body}"
        raise ValidationError(msg)
    step = max(1, round(1.0 / (clip.frame_time_s * RATE_HZ)))
    thin = replace(clip, frames=clip.frames[::step], frame_time_s=clip.frame_time_s * step)
    out = []
    for k in range(first_body, first_body + subjects):
        rng = np.random.default_rng([seed, _BVH_KEY[split], k])
        shape, markers = subject_model.body(rng)
        motion = retarget_bvh(thin, shape)
        if centre:
            motion = _centred(motion)
        skin = np.random.default_rng([seed, _BVH_KEY[split], k, _SKIN_KEY])
        frames = pose_frames(motion.with_name(clip.name), shape, markers)
        out.append(subject_model.moved(frames, skin))
    return out


@dataclass(frozen=True, slots=True)
class Sample:
    """One prepared sample.

    Attributes:
        front, back: rendered views (S, S) float32.
        norm: the normalisation (image frame, after centring and rotation).
        rotation: the augmentation rotation (3, 3) applied about ``centre_m``.
        centre_m: raw-cloud centroid, image frame, m.
        raw_m: the fused raw cloud (N, 3), world, m.
        markers_m, joints_m: truth (53, 3), (19, 3), world, m.
        markers_n, joints_n: truth, normalised front frame.
        action: the take's action.
        cameras: the sampled rig that saw it.
    """

    front: npt.NDArray[np.float32]
    back: npt.NDArray[np.float32]
    norm: Normalisation
    rotation: FloatArray
    centre_m: FloatArray
    raw_m: FloatArray
    markers_m: FloatArray
    joints_m: FloatArray
    markers_n: FloatArray
    joints_n: FloatArray
    action: str
    cameras: tuple[Camera, ...] = ()


def prepare_cloud(
    raw_m: FloatArray, rotation: FloatArray | None = None, *, size_px: int = 160
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], Normalisation, FloatArray]:
    """World cloud -> (front, back, normalisation, centre): image frame, centred, rotated,
    normalised from the raw points, rendered.

    Raises:
        ValidationError: fewer than 2 points.
    """
    p = to_image_frame(raw_m)
    if p.shape[0] < 2:
        msg = f"the marker cloud has {p.shape[0]} point(s); DeMoCap needs at least 2"
        raise ValidationError(msg)
    centre = p.mean(axis=0)
    q = p - centre
    if rotation is not None:
        q = q @ rotation.T
    norm = normalise(q)
    n = norm.apply(q)
    return render_view(n, size_px=size_px), render_view(back_view(n), size_px=size_px), norm, centre


def _place(frames: PoseFrames, index: int, yaw: float, shift: FloatArray) -> PoseFrames:
    r = Rotation.from_rotvec([0.0, 0.0, yaw]).as_matrix()
    root = frames.joints_m[index, 0] * np.array([1.0, 1.0, 0.0])

    def move(p: FloatArray) -> FloatArray:
        return np.asarray((p - root) @ r.T + root + shift)

    return PoseFrames(
        markers_m=move(frames.markers_m[index : index + 1]),
        normals=frames.normals[index : index + 1] @ r.T,
        joints_m=move(frames.joints_m[index : index + 1]),
        caps_a_m=move(frames.caps_a_m[index : index + 1]),
        caps_b_m=move(frames.caps_b_m[index : index + 1]),
        caps_radius_m=frames.caps_radius_m,
        action=frames.action,
    )


def simulate_sample(
    frames: PoseFrames,
    index: int,
    rng: np.random.Generator,
    *,
    num_cameras: int = 4,
    augment: bool = True,
    size_px: int = 160,
    observation: ObservationModel = NOMINAL_OBSERVATION,
) -> Sample | None:
    """Simulate, fuse, normalise and render frame ``index`` of a take (see module doc); None
    when the fused cloud has fewer than 2 points (nothing to normalise: the actor is out of
    every camera's view or the capture box). ``observation`` scales the D415 model (stress
    tests; the default is the model training uses)."""
    placed = _place(
        frames,
        index,
        float(rng.uniform(-np.pi, np.pi)),
        np.append(rng.uniform(-0.6, 0.6, 2), 0.0),
    )
    cams = sample_rig(rng, num_cameras=num_cameras)
    views, _ = observe(placed, 0, cams, rng, model=observation)
    raw = merge_views(views)
    if raw.shape[0] < 2:
        return None
    rot = random_rotation(rng) if augment else np.eye(3)
    front, back, norm, centre = prepare_cloud(raw, rot, size_px=size_px)

    def to_n(p: FloatArray) -> FloatArray:
        return norm.apply((to_image_frame(p) - centre) @ rot.T)

    return Sample(
        front=front,
        back=back,
        norm=norm,
        rotation=rot,
        centre_m=centre,
        raw_m=raw,
        markers_m=placed.markers_m[0],
        joints_m=placed.joints_m[0],
        markers_n=to_n(placed.markers_m[0]),
        joints_n=to_n(placed.joints_m[0]),
        action=frames.action,
        cameras=tuple(cams),
    )


def make_sample(
    frames: PoseFrames,
    index: int,
    rng: np.random.Generator,
    *,
    num_cameras: int = 4,
    augment: bool = True,
    size_px: int = 160,
    observation: ObservationModel = NOMINAL_OBSERVATION,
) -> Sample:
    """:func:`simulate_sample`, for callers that need a sample.

    Raises:
        ProcessingError: the fused cloud has fewer than 2 points (no fallback: a cloud that
            cannot be normalised is not a sample).
    """
    s = simulate_sample(
        frames,
        index,
        rng,
        num_cameras=num_cameras,
        augment=augment,
        size_px=size_px,
        observation=observation,
    )
    if s is None:
        msg = (
            f"frame {index} of take {frames.action!r}: the simulated rig saw fewer than 2 "
            "points (the actor is out of view); pick another frame"
        )
        raise ProcessingError(msg)
    return s


@dataclass(frozen=True, slots=True)
class Batch:
    """Tensors for one training step: views (B, 1, S, S), truth (B, 53, 3) and (B, 19, 3)."""

    front: torch.Tensor
    back: torch.Tensor
    markers: torch.Tensor
    joints: torch.Tensor


def check_observation_jitter(jitter: float, *, name: str = "observation jitter") -> None:
    """Refuse an observation jitter outside [0, 1) (``name`` is how the error calls it).

    Raises:
        ValidationError: ``jitter`` outside [0, 1).
    """
    if not 0.0 <= jitter < 1.0:
        msg = f"{name} must be in [0, 1), got {jitter!r}"
        raise ValidationError(msg)


def jittered_observation(rng: np.random.Generator, jitter: float) -> ObservationModel:
    """A D415 model whose scales (:data:`simdata.PERTURBATION_KNOBS`) are each drawn uniformly
    from ``[1 - jitter, 1 + jitter]``; ``jitter`` 0 gives the nominal model and draws nothing.

    Raises:
        ValidationError: ``jitter`` outside [0, 1).
    """
    check_observation_jitter(jitter)
    if jitter == 0.0:
        return NOMINAL_OBSERVATION
    lo, hi = 1.0 - jitter, 1.0 + jitter
    return ObservationModel(**{k: float(rng.uniform(lo, hi)) for k in PERTURBATION_KNOBS})


def make_batch(
    pool: list[PoseFrames],
    rng: np.random.Generator,
    size: int,
    *,
    size_px: int = 160,
    observation_jitter: float = 0.0,
) -> Batch:
    """``size`` random samples from random takes and frames of ``pool``; a frame without a
    usable cloud (:func:`simulate_sample`) is replaced by another random draw. With
    ``observation_jitter`` > 0 every sample sees its own D415 model
    (:func:`jittered_observation`): a network that has met denser and sparser clouds than the
    nominal model's.

    Raises:
        ProcessingError: :data:`_MAX_REDRAWS` draws in a row gave no usable cloud.
        ValidationError: ``observation_jitter`` outside [0, 1).
    """
    check_observation_jitter(observation_jitter)
    samples: list[Sample] = []
    misses = 0
    while len(samples) < size:
        take = pool[int(rng.integers(len(pool)))]
        obs = jittered_observation(rng, observation_jitter)
        s = simulate_sample(
            take, int(rng.integers(take.num_frames)), rng, size_px=size_px, observation=obs
        )
        if s is None:
            misses += 1
            if misses >= _MAX_REDRAWS:
                msg = (
                    f"{misses} training frames in a row were out of the rig's view; "
                    "the pool's takes leave the capture volume"
                )
                raise ProcessingError(msg)
            continue
        misses = 0
        samples.append(s)
    return Batch(
        front=torch.from_numpy(np.stack([s.front for s in samples]))[:, None],
        back=torch.from_numpy(np.stack([s.back for s in samples]))[:, None],
        markers=torch.from_numpy(np.stack([s.markers_n for s in samples])).float(),
        joints=torch.from_numpy(np.stack([s.joints_n for s in samples])).float(),
    )
