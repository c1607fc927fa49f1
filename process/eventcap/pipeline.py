"""EventCap end to end, one batch at a time (paper §3; docs/eventcap.md).

A batch spans two consecutive APS frames ``a`` and ``b``: tracking frames ``f = 0..N`` at
``t_a + f·step_us`` (N = 40 for 25 fps and 1 kHz), ``t`` the exposure midpoints. Per batch:

1. **EDI** (:mod:`.edi`): the batch's events are indexed once; one contrast ``C`` per batch is
   fitted so that both frames, brought to their common midpoint, agree
   (:meth:`~.edi.EdiBatch.fit_contrast`; the options' fixed contrast when too few events);
   both frames are deblurred to their own midpoints.
2. **Trajectories** (:mod:`.tracking`): latent images at every tracking frame, a time-weighted
   blend of the two sharp frames carried by the events (each weighted by its nearness, since
   EDI noise grows away from the reference frame), features on the body (the silhouette of the
   initial end poses, eroded) tracked forward and backward, stitched, smoothed, sampled.
3. **Detections** at both frames through any :class:`~.detections.Detector`; root-first
   per-frame fits initialise the batch (:func:`~.batch_fit.fit_batch`). Batch continuity
   (``continuity``): given ``start_pose`` (``run_take`` passes the previous batch's last pose,
   which is this batch's frame 0), S_0 starts there instead of a fresh fit of detection ``a``
   and is tied to it by keypoint pseudo-detections beside detection ``a``, so detection noise
   is averaged along the take rather than met afresh at every APS frame; a detection whose
   left/right mirror agrees better with that pose is mirrored (``swap_check``).
4. **Batch fit** (:mod:`.batch_fit`): E_cor + E_2D + E_3D + E_temp; E_cor's surface points are
   re-associated on the template rasterised at the current poses between rounds
   (:mod:`.raster`). ``association="trajectory"`` (default) looks each trajectory up once, at
   its frame nearest a batch end, inside the silhouette eroded by 1 px, and uses that one
   point for all its pairs (it follows one physical point); ``"per_frame"`` is the point under
   the tracked pixel at every frame ``i``, posed at ``i ± 1``.
5. **Refinement** (:mod:`.refine`): every ``refine_every``-th frame is refined against the
   events of its window (accepted only where the held-out data term drops); the accepted pose
   corrections are interpolated across the frames in between, so every frame gets one (frame 0
   is not refined again when it came from the previous batch).

Threads: the solvers' matrices are small, so :func:`run_batch` runs torch and the BLAS behind
numpy/scipy on ``threads`` (1) threads and restores the caller's settings on return.

Measured (issue 15; simulated whole 4 s takes of CMU 02_04 jump, 02_05 strike, 05_02 dance,
seeds 1–3, realistic DAVIS simulator, synthetic detector with default noise, 99 chained batches
each; AE on every 10th frame, 15 body joints): AE 23.0 mm vs 31.2 mm ``*_linear`` (0.74; every
take 0.67–0.79), ``*_all`` 36.8 mm; absolute MPJPE 46.9 vs 78.6 mm. Speed on the 2-core
machine (benchmarks/eventcap_batch.py): 3.55 s per batch on average (batch fit ~1.4 s,
refinement ~1.1 s), about twice that where the ``jump_check_mm`` refit runs. docs/eventcap.md
has the table and what each choice below gained.

Templates: the estimator is given the actor's :class:`~mocaprig.process.body.shape.BodyShape`
(the paper's pre-scanned template). Times are the events' clock (µs).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Literal

import cv2
import numpy as np
import numpy.typing as npt
import torch
from threadpoolctl import threadpool_limits

from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body.kinematics import (
    EVENTCAP_KEYPOINTS,
    clamp_to_limits,
    eventcap_keypoints,
    forward_kinematics,
)
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.body.skeleton import POSE_DIM
from mocaprig.process.eventcap.batch_fit import (
    NUM_BODY_KEYPOINTS,
    NUM_KEYPOINTS,
    BatchFitOptions,
    BatchFitResult,
    Correspondences,
    FrameDetections,
    fit_batch,
    fit_frame,
    interpolate_poses,
)
from mocaprig.process.eventcap.camera import EventCamera
from mocaprig.process.eventcap.detections import Detection
from mocaprig.process.eventcap.edi import EdiBatch, LinearResponse
from mocaprig.process.eventcap.event_index import build_event_index
from mocaprig.process.eventcap.raster import rasterize
from mocaprig.process.eventcap.refine import (
    FrameWindow,
    RefineOptions,
    refine_frames,
    split_events,
)
from mocaprig.process.eventcap.tracking import (
    CorrespondencePairs,
    TrackingOptions,
    correspondence_pairs,
    track_frames,
)
from mocaprig.validation import check_positive, check_shape

__all__ = [
    "ApsFrame",
    "BatchResult",
    "EventcapOptions",
    "frame_detections",
    "run_batch",
]

_log = logging.getLogger(__name__)

#: How :func:`run_batch` uses ``start_pose``: ``"off"``: only as the initial guess of the
#: frame-0 fit; ``"prior"``: S_0 starts there and is tied to it by keypoint pseudo-detections
#: beside detection ``a``; ``"replace"``: the pseudo-detections replace detection ``a`` (which
#: the previous batch already fitted), a recursive filter.
Continuity = Literal["off", "prior", "replace"]
#: E_cor association: ``"per_frame"``: the surface point under the tracked pixel at every
#: frame ``i`` (at S_i); ``"trajectory"``: one surface point per trajectory, looked up once at
#: its frame nearest a batch end inside the eroded silhouette.
Association = Literal["per_frame", "trajectory"]

_PELVIS = EVENTCAP_KEYPOINTS.index("pelvis")
# A mirrored detection replaces the detector's only when it is this much closer.
_SWAP_MARGIN = 0.8
# Left/right partner of each keypoint slot (itself on the centre line).
_MIRROR = np.array(
    [
        EVENTCAP_KEYPOINTS.index(
            n.replace("right_", "\0").replace("left_", "right_").replace("\0", "left_")
        )
        for n in EVENTCAP_KEYPOINTS
    ],
    dtype=np.int64,
)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]


@dataclass(frozen=True, slots=True, eq=False)
class ApsFrame:
    """One APS frame with its real exposure window (µs, the events' clock).

    Attributes:
        exposure_start_us: Exposure start.
        exposure_end_us: Exposure end (≥ start; equal for a frame known only by its time).
        image_dn: (H, W) frame in DN (any linear unit: 10-bit CDS counts, 8-bit grey).
    """

    exposure_start_us: int
    exposure_end_us: int
    image_dn: F64 = field(repr=False)

    def __post_init__(self) -> None:
        img = np.asarray(check_shape(self.image_dn, ["H", "W"], name="ApsFrame.image_dn"))
        if int(self.exposure_end_us) < int(self.exposure_start_us):
            msg = (
                f"ApsFrame: exposure ends ({self.exposure_end_us} µs) before it starts "
                f"({self.exposure_start_us} µs)"
            )
            raise ValidationError(msg)
        object.__setattr__(self, "image_dn", np.asarray(img, dtype=np.float64))

    @property
    def t_us(self) -> int:
        """The frame's time: the exposure midpoint (floored to µs)."""
        return (int(self.exposure_start_us) + int(self.exposure_end_us)) // 2


@dataclass(frozen=True, slots=True)
class EventcapOptions:
    """Settings of :func:`run_batch` (the stages' own options are nested).

    Attributes:
        step_us: Tracking step (1000 µs: 1 kHz output).
        contrast: Fallback ON/OFF contrast (ln) when a batch has too few events to fit one.
        fit_contrast: Fit one contrast per batch from its two frames (else use ``contrast``).
        t_shift_us: Added to event times for EDI (real DAVIS data may need one; 0 simulated).
        black_level_dn: The frames' black level (DN) for EDI's linear response.
        mask_erosion_px: Features are taken this far inside the initial silhouettes.
        association_rounds: Batch-fit solves, E_cor re-associated on the template before each
            solve after the first.
        refine_every: Refine every this-many tracking frames (0 turns refinement off).
        association: How E_cor's surface points are found (:data:`Association`).
        association_erosion_px: With ``"trajectory"``, reference pixels must lie this far
            inside the rendered silhouette.
        continuity: How a ``start_pose`` (the previous batch's last pose, at the shared APS
            frame) enters (:data:`Continuity`).
        continuity_weight: Confidence of the ``start_pose`` pseudo-detections (1 = as much as
            one detection).
        jump_check_mm: With a ``start_pose``: when the fresh fit of frame ``b`` moves the
            pelvis-relative body keypoints by more than this (mean, mm) from it, the batch is
            also fitted from the held pose and the lower final energy wins (None: never).
        swap_check: With a ``start_pose``: replace a detection by its left/right mirror when
            the mirror agrees better with the pose handed on (whole-body swaps are a common
            detector failure that no single-frame energy can see). Without one (a take's first
            batch), given a ``lookahead`` detection: a vote of frames a, b and the next.
        threads: intra-op threads of torch and of the BLAS behind numpy/scipy while the batch
            runs (both restored afterwards; None leaves them as they are). The solvers'
            matrices are small (33×33 blocks, 400×33 Jacobians), so extra threads only spin
            against each other and other jobs: on a loaded 2-core machine one thread measured
            several times faster than two (an SVD of 400×33: 0.42 vs 3.1 ms).
        tracking: Tracker settings.
        batch: Batch-fit weights and solver settings.
        refinement: Refinement settings.
    """

    step_us: int = 1000
    contrast: tuple[float, float] = (0.2, 0.2)
    fit_contrast: bool = True
    t_shift_us: int = 0
    black_level_dn: float = 0.0
    mask_erosion_px: int = 2
    association_rounds: int = 2
    refine_every: int = 10
    association: Association = "trajectory"
    association_erosion_px: int = 1
    continuity: Continuity = "prior"
    continuity_weight: float = 1.0
    jump_check_mm: float | None = 150.0
    swap_check: bool = True
    threads: int | None = 1
    tracking: TrackingOptions = field(default_factory=TrackingOptions)
    batch: BatchFitOptions = field(default_factory=BatchFitOptions)
    refinement: RefineOptions = field(default_factory=RefineOptions)

    def __post_init__(self) -> None:
        check_positive(float(self.step_us), name="EventcapOptions.step_us")
        for c in self.contrast:
            check_positive(float(c), name="EventcapOptions.contrast")
        if int(self.association_rounds) < 1:
            msg = f"EventcapOptions.association_rounds must be >= 1, got {self.association_rounds}"
            raise ValidationError(msg)
        if self.threads is not None and int(self.threads) < 1:
            msg = f"EventcapOptions.threads must be >= 1 or None, got {self.threads}"
            raise ValidationError(msg)
        if (
            int(self.refine_every) < 0
            or int(self.mask_erosion_px) < 0
            or int(self.association_erosion_px) < 0
        ):
            msg = (
                "EventcapOptions.refine_every, mask_erosion_px and association_erosion_px "
                "must be >= 0"
            )
            raise ValidationError(msg)
        if self.association not in ("per_frame", "trajectory"):
            msg = (
                "EventcapOptions.association must be 'per_frame' or 'trajectory', "
                f"got {self.association!r}"
            )
            raise ValidationError(msg)
        if self.continuity not in ("off", "prior", "replace"):
            msg = (
                "EventcapOptions.continuity must be 'off', 'prior' or 'replace', "
                f"got {self.continuity!r}"
            )
            raise ValidationError(msg)
        check_positive(float(self.continuity_weight), name="EventcapOptions.continuity_weight")
        if self.jump_check_mm is not None:
            check_positive(float(self.jump_check_mm), name="EventcapOptions.jump_check_mm")


@dataclass(frozen=True, slots=True, eq=False)
class BatchResult:
    """One batch of EventCap output.

    Attributes:
        t_us: (N+1,) tracking frame times, µs.
        poses: (N+1, 33) poses (``process.body.skeleton`` layout; world, m, rad).
        keypoints_m: (N+1, 19, 3) EventCap keypoints, world frame, m.
        contrast: The (ON, OFF) contrast EDI used (ln).
        trajectories: Trajectories tracked.
        correspondences: E_cor rows on the body in the last solve.
        refined: Frames refined.
        refined_accepted: Of those, refinements the data-term guard accepted.
        detection_source: The detector's label (``"synthetic"`` for simulated detections).
        fit: The batch fit's result (energies, iterations).
        stage_seconds: Wall time per stage (``edi``, ``tracking``, ``init``, ``batch_fit``,
            ``association``, ``refine``).
    """

    t_us: I64 = field(repr=False)
    poses: F64 = field(repr=False)
    keypoints_m: F64 = field(repr=False)
    contrast: tuple[float, float]
    trajectories: int
    correspondences: int
    refined: int
    refined_accepted: int
    detection_source: str
    fit: BatchFitResult = field(repr=False)
    stage_seconds: Mapping[str, float]


def frame_detections(detection: Detection, frame: int) -> FrameDetections:
    """A :class:`~.detections.Detection` as the batch fit's input at tracking frame ``frame``."""
    return FrameDetections(
        frame=frame,
        keypoints2d_px=detection.joints2d_px,
        confidence=detection.confidence,
        keypoints3d_mm=detection.joints3d_root_rel_mm,
    )


def _body_shift_mm(pose_a: F64, pose_b: F64, shape: BodyShape) -> float:
    """Mean distance (mm) between the 15 body keypoints of two poses, pelvis-relative."""
    kp = eventcap_keypoints(forward_kinematics(np.stack([pose_a, pose_b]), shape), shape)
    rel = kp[:, :NUM_BODY_KEYPOINTS] - kp[:, _PELVIS : _PELVIS + 1]
    return float(1000.0 * np.linalg.norm(rel[1] - rel[0], axis=-1).mean())


def _mirrored(det: FrameDetections) -> FrameDetections:
    """``det`` with every left/right keypoint pair exchanged (2D, confidences and 3D)."""
    return FrameDetections(
        frame=det.frame,
        keypoints2d_px=np.asarray(det.keypoints2d_px)[_MIRROR],
        confidence=np.asarray(det.confidence)[_MIRROR],
        keypoints3d_mm=(
            None if det.keypoints3d_mm is None else np.asarray(det.keypoints3d_mm)[_MIRROR]
        ),
        confidence3d=np.asarray(det.confidence3d)[_MIRROR],
    )


def _reprojection_px(
    pose: F64, det: FrameDetections, shape: BodyShape, camera: EventCamera
) -> float:
    """Confidence-weighted mean 2D distance (px) between a pose's keypoints and ``det``."""
    uv, _ = camera.project(eventcap_keypoints(forward_kinematics(pose, shape), shape))
    w = np.asarray(det.confidence, dtype=np.float64)
    d = np.linalg.norm(uv - np.asarray(det.keypoints2d_px), axis=-1)
    return float((w * d).sum() / max(float(w.sum()), 1e-9))


def _unswap(
    det: list[FrameDetections],
    pose_a: F64,
    shape: BodyShape,
    camera: EventCamera,
    options: BatchFitOptions,
) -> list[FrameDetections]:
    """Undo whole-body left/right swaps of the real detections against the handed-on pose.

    A detector that exchanges every left/right pair gives a mirrored body that fits its
    keypoints as well as the true one, so the detection's own energy cannot tell them apart;
    the pose handed on (frame ``a``, one APS interval earlier) can. Detection ``a`` (at that
    very pose) is flagged when its mirror reprojects closer to it; detection ``b`` is fitted
    both ways from ``pose_a`` and flagged when the mirror's body moved less from ``pose_a``.
    Flagged detections are mirrored, except when both are flagged: two swaps in a row are
    far less likely than a handed-on pose that is itself mirrored, so the detections stand.
    ``det`` is ``[pose prior, (detection a), detection b]``; a new list is returned.
    """
    out = list(det)
    flagged: list[int] = []
    for k in range(1, len(out) - 1):
        near = _reprojection_px(pose_a, out[k], shape, camera)
        if _reprojection_px(pose_a, _mirrored(out[k]), shape, camera) < _SWAP_MARGIN * near:
            flagged.append(k)
    last = len(out) - 1
    if _mirror_clearly_better(pose_a, out[last], shape, camera, options):
        flagged.append(last)
    if len(flagged) > 1:
        _log.info("both detections disagree with the pose handed on: keeping them as given")
        return out
    for k in flagged:
        _log.info("frame %d: detection mirrored (left/right swap)", out[k].frame)
        out[k] = _mirrored(out[k])
    return out


def _mirror_clearly_better(
    pose: F64, det: FrameDetections, shape: BodyShape, camera: EventCamera, options: BatchFitOptions
) -> bool:
    """Whether ``det``'s left/right mirror, fitted from ``pose``, moves the body clearly less
    than ``det`` itself does (the test of :func:`_unswap` for a later detection)."""
    fits = [
        fit_frame(d, camera, shape, initial_pose=pose, options=options)
        for d in (det, _mirrored(det))
    ]
    shifts = [_body_shift_mm(pose, f.pose, shape) for f in fits]
    return shifts[1] < _SWAP_MARGIN * shifts[0]


def _unswap_first(
    det: list[FrameDetections],
    lookahead: FrameDetections,
    shape: BodyShape,
    camera: EventCamera,
    options: BatchFitOptions,
) -> list[FrameDetections]:
    """Undo a left/right swap in the first batch, where no pose is handed on: a vote of three.

    Detections ``b`` and ``lookahead`` (the frame after ``b``) are each tested against the fit
    of detection ``a``: when both prefer their mirror, ``a`` is the swapped one; when only
    ``b`` does, ``b`` is (the next batch's :func:`_unswap` sees to a swapped ``lookahead``).
    Two swaps among three frames defeat it (with the synthetic detector's 5 % rate: 0.7 %).
    ``det`` is ``[detection a, detection b]``; a new list is returned.
    """
    out = list(det)
    pose_a = fit_frame(out[0], camera, shape, options=options).pose
    flip_b = _mirror_clearly_better(pose_a, out[1], shape, camera, options)
    flip_c = _mirror_clearly_better(pose_a, lookahead, shape, camera, options)
    if flip_b and flip_c:
        _log.info("frame 0: detection mirrored (left/right swap; the next two frames agree)")
        out[0] = _mirrored(out[0])
    elif flip_b:
        _log.info("frame %d: detection mirrored (left/right swap)", out[1].frame)
        out[1] = _mirrored(out[1])
    return out


def _pose_prior(pose: F64, shape: BodyShape, camera: EventCamera, weight: float) -> FrameDetections:
    """A pose as keypoint pseudo-detections at frame 0 (2D px and pelvis-relative 3D mm in
    camera axes, each with confidence ``weight``): the E_2D/E_3D terms then tie S_0 to it."""
    kp = eventcap_keypoints(forward_kinematics(pose, shape), shape)
    uv, _ = camera.project(kp)
    cam_mm = 1000.0 * (kp - kp[_PELVIS]) @ camera.R_world_cam  # world axes -> camera axes
    w3 = np.zeros(NUM_KEYPOINTS)
    w3[:NUM_BODY_KEYPOINTS] = weight
    return FrameDetections(
        frame=0,
        keypoints2d_px=uv,
        confidence=np.full(NUM_KEYPOINTS, float(weight)),
        keypoints3d_mm=cam_mm,
        confidence3d=w3,
    )


def _sharp_frames(
    events: npt.NDArray[np.void],
    frame_a: ApsFrame,
    frame_b: ApsFrame,
    camera: EventCamera,
    opt: EventcapOptions,
) -> tuple[EdiBatch, I64, F64, tuple[float, float]]:
    t_lo = min(frame_a.exposure_start_us, int(events["t"].min()) if events.size else 1 << 62)
    t_hi = max(frame_b.exposure_end_us, int(events["t"].max()) if events.size else -(1 << 62))
    edi = EdiBatch(
        events,
        shape_hw=(camera.height, camera.width),
        t_start_us=t_lo + opt.t_shift_us,
        t_end_us=t_hi + opt.t_shift_us,
        t_shift_us=opt.t_shift_us,
    )
    response = LinearResponse(black_level_dn=opt.black_level_dn)
    c_on, c_off = opt.contrast
    if opt.fit_contrast:
        try:
            est = edi.fit_contrast(
                frame_a.image_dn,
                frame_b.image_dn,
                exposure_a_us=(frame_a.exposure_start_us, frame_a.exposure_end_us),
                exposure_b_us=(frame_b.exposure_start_us, frame_b.exposure_end_us),
                off_ratio=c_off / c_on,
                response=response,
            )
            c_on, c_off = est.c_on, est.c_off
        except ProcessingError as err:
            _log.info(
                "batch at %d µs: contrast not fitted (%s); using %s",
                frame_a.t_us,
                err,
                opt.contrast,
            )
    sharp = [
        edi.deblur(
            f.image_dn,
            exposure_start_us=f.exposure_start_us,
            exposure_end_us=f.exposure_end_us,
            c_on=c_on,
            c_off=c_off,
            t_ref_us=f.t_us,
            response=response,
        )
        for f in (frame_a, frame_b)
    ]
    times = np.arange(frame_a.t_us, frame_b.t_us + 1, opt.step_us, dtype=np.int64)
    lat_a = edi.latent_log_images(sharp[0], times)
    lat_b = edi.latent_log_images(sharp[1], times)
    w = ((times - times[0]) / max(int(times[-1] - times[0]), 1))[:, None, None]
    latent: F64 = (1.0 - w) * lat_a + w * lat_b
    return edi, times, latent, (c_on, c_off)


def _body_mask(
    pose: F64, shape: BodyShape, camera: EventCamera, erosion_px: int
) -> npt.NDArray[np.bool_]:
    mask = rasterize(pose, shape, camera).mask
    if erosion_px > 0:
        k = 2 * erosion_px + 1
        mask = cv2.erode(mask.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    out: npt.NDArray[np.bool_] = np.asarray(mask, dtype=bool)
    return out


def _associate(
    pairs: CorrespondencePairs, poses: F64, shape: BodyShape, camera: EventCamera
) -> Correspondences:
    """E_cor rows: the surface point under each tracked pixel at frame i, posed at S_i."""
    frame_i: list[I64] = []
    frame_j: list[I64] = []
    segment: list[I64] = []
    local: list[F64] = []
    target: list[F64] = []
    for i in np.unique(pairs.frame_i):
        sel = np.flatnonzero(pairs.frame_i == i)
        r = rasterize(poses[int(i)], shape, camera)
        uv = np.rint(pairs.p_i[sel]).astype(np.int64)
        inside = (
            (uv[:, 0] >= 0)
            & (uv[:, 0] < camera.width)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] < camera.height)
        )
        sel, uv = sel[inside], uv[inside]
        on_body = r.mask[uv[:, 1], uv[:, 0]]
        sel, uv = sel[on_body], uv[on_body]
        frame_i.append(pairs.frame_i[sel])
        frame_j.append(pairs.frame_j[sel])
        segment.append(r.segment[uv[:, 1], uv[:, 0]].astype(np.int64))
        local.append(r.local_points_m[uv[:, 1], uv[:, 0]])
        target.append(pairs.p_j[sel])
    if not frame_i or sum(a.size for a in frame_i) == 0:
        return Correspondences.empty()
    fi = np.concatenate(frame_i)
    return Correspondences(
        frame_i=fi,
        frame_j=np.concatenate(frame_j),
        segment=np.concatenate(segment),
        local_m=np.concatenate(local),
        target_px=np.concatenate(target),
        weight=np.ones(fi.size),
    )


def _associate_trajectories(
    pairs: CorrespondencePairs,
    poses: F64,
    shape: BodyShape,
    camera: EventCamera,
    erosion_px: int,
) -> Correspondences:
    """E_cor rows with one surface point per trajectory (it follows one physical point).

    Each trajectory is looked up once, at its pair frame nearest a batch end (the poses there
    come straight from the detections, the ones in between are interpolated or fitted from
    them), on the template rendered at that frame's pose and eroded by ``erosion_px`` (a pixel
    near the silhouette may belong to the background at the true pose). Trajectories whose
    reference pixel falls outside the eroded body are dropped.
    """
    if len(pairs) == 0:
        return Correspondences.empty()
    n = poses.shape[0] - 1
    tid = pairs.trajectory_id
    ends = np.minimum(pairs.frame_i, n - pairs.frame_i)
    # Rows are sorted by trajectory: per trajectory, the row nearest an end (first on ties).
    order = np.lexsort((ends, tid))
    first = np.flatnonzero(np.r_[True, tid[order][1:] != tid[order][:-1]])
    ref_rows = order[first]
    ref_tid = tid[ref_rows]
    seg_of = np.full(ref_rows.size, -1, dtype=np.int64)
    local_of = np.zeros((ref_rows.size, 3))
    for f in np.unique(pairs.frame_i[ref_rows]):
        sel = np.flatnonzero(pairs.frame_i[ref_rows] == f)
        r = rasterize(poses[int(f)], shape, camera)
        mask = r.mask
        if erosion_px > 0:
            k = 2 * erosion_px + 1
            mask = cv2.erode(mask.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
        uv = np.rint(pairs.p_i[ref_rows[sel]]).astype(np.int64)
        inside = (
            (uv[:, 0] >= 0)
            & (uv[:, 0] < camera.width)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] < camera.height)
        )
        sel, uv = sel[inside], uv[inside]
        on_body = mask[uv[:, 1], uv[:, 0]]
        sel, uv = sel[on_body], uv[on_body]
        seg_of[sel] = r.segment[uv[:, 1], uv[:, 0]]
        local_of[sel] = r.local_points_m[uv[:, 1], uv[:, 0]]
    slot = np.searchsorted(ref_tid, tid)  # ref_tid is sorted (lexsort's primary key)
    keep = seg_of[slot] >= 0
    if not keep.any():
        return Correspondences.empty()
    return Correspondences(
        frame_i=pairs.frame_i[keep],
        frame_j=pairs.frame_j[keep],
        segment=seg_of[slot[keep]],
        local_m=local_of[slot[keep]],
        target_px=pairs.p_j[keep],
        weight=np.ones(int(keep.sum())),
    )


def _refine(
    poses: F64,
    times: I64,
    events: npt.NDArray[np.void],
    shape: BodyShape,
    camera: EventCamera,
    opt: EventcapOptions,
    *,
    skip_first: bool,
) -> tuple[F64, int, int]:
    n = poses.shape[0] - 1
    frames = np.arange(0, n + 1, int(opt.refine_every), dtype=np.int64)
    if frames[-1] != n:
        frames = np.append(frames, n)
    if skip_first:
        # Frame 0 is the previous batch's refined last frame (tied to it by the prior):
        # refining it again costs a refinement and its correction is taken as zero.
        frames = frames[1:]
    fit_ev, check_ev = split_events(events)
    size = {"width": camera.width, "height": camera.height}
    fit_index = build_event_index(fit_ev, **size)
    check_index = build_event_index(check_ev, **size)
    windows = [FrameWindow(int(times[f]), int(times[0]), int(times[-1])) for f in frames]
    results = refine_frames(
        poses[frames],
        shape,
        camera,
        fit_index,
        windows,
        check_index=check_index,
        options=opt.refinement,
    )
    # Interpolate each accepted correction (refined − fitted) across the frames in between.
    delta = np.stack([r.pose - poses[f] for r, f in zip(results, frames, strict=True)])
    knots = frames
    if skip_first:
        knots = np.r_[0, frames]
        delta = np.vstack([np.zeros((1, poses.shape[1])), delta])
    out = poses.copy()
    for d in range(poses.shape[1]):
        out[:, d] += np.interp(np.arange(n + 1), knots, delta[:, d])
    out = clamp_to_limits(out)
    accepted = sum(r.accepted for r in results)
    return out, len(results), accepted


def run_batch(
    events: npt.NDArray[np.void],
    frame_a: ApsFrame,
    frame_b: ApsFrame,
    detection_a: Detection,
    detection_b: Detection,
    camera: EventCamera,
    shape: BodyShape,
    *,
    options: EventcapOptions | None = None,
    start_pose: npt.ArrayLike | None = None,
    lookahead: Detection | None = None,
    progress: Callable[[str], None] | None = None,
) -> BatchResult:
    """Run EventCap on one batch (module doc).

    Args:
        events: The events from frame ``a``'s exposure start to frame ``b``'s exposure end
            (canonical dtype, µs, the frames' clock).
        frame_a: The APS frame opening the batch.
        frame_b: The next APS frame; ``t_b − t_a`` a whole number of ``step_us``.
        detection_a: Detections at frame ``a``.
        detection_b: Detections at frame ``b``.
        camera: The DAVIS (sensor size included).
        shape: The actor's template.
        options: Settings.
        start_pose: The previous batch's last pose (33,), at frame ``a``: with
            ``options.continuity`` ``"prior"`` (default) S_0 starts there and is tied to it,
            with ``"off"`` it only seeds the frame-``a`` fit.
        lookahead: Detections at the APS frame after ``b``. Without a ``start_pose`` and
            with ``options.swap_check``, they vote with ``a`` and ``b`` on left/right swaps
            (the first batch of a take has no pose handed on to check against).
        progress: Called with each stage's name as it starts.

    Raises:
        ValidationError: frames out of order or not a whole number of steps apart.
        ProcessingError: a stage failed (too few detections, a failed solve).
    """
    opt = options if options is not None else EventcapOptions()
    if opt.threads is None:
        return _run_batch(
            events, frame_a, frame_b, detection_a, detection_b, camera, shape, opt, start_pose,
            lookahead, progress,
        )  # fmt: skip
    before = torch.get_num_threads()
    torch.set_num_threads(int(opt.threads))
    try:
        with threadpool_limits(int(opt.threads), user_api="blas"):
            return _run_batch(
                events, frame_a, frame_b, detection_a, detection_b, camera, shape, opt,
                start_pose, lookahead, progress,
            )  # fmt: skip
    finally:
        torch.set_num_threads(before)


def _run_batch(
    events: npt.NDArray[np.void],
    frame_a: ApsFrame,
    frame_b: ApsFrame,
    detection_a: Detection,
    detection_b: Detection,
    camera: EventCamera,
    shape: BodyShape,
    opt: EventcapOptions,
    start_pose: npt.ArrayLike | None,
    lookahead: Detection | None,
    progress: Callable[[str], None] | None,
) -> BatchResult:
    n_us = frame_b.t_us - frame_a.t_us
    if n_us <= 0 or n_us % opt.step_us:
        msg = (
            f"APS frames at {frame_a.t_us} and {frame_b.t_us} µs: a batch needs the second "
            f"after the first by a whole number of {opt.step_us} µs steps"
        )
        raise ValidationError(msg)
    n = n_us // opt.step_us
    seconds: dict[str, float] = {}

    def stage(name: str) -> float:
        if progress is not None:
            progress(name)
        return time.perf_counter()

    t = stage("edi")
    edi, times, latent, contrast = _sharp_frames(events, frame_a, frame_b, camera, opt)
    del edi
    seconds["edi"] = time.perf_counter() - t

    t = stage("init")
    det = [frame_detections(detection_a, 0), frame_detections(detection_b, n)]
    if start_pose is not None and opt.continuity != "off":
        # The previous batch's S_N already fitted detection a (with the events before it):
        # start there, and tie S_0 to it (the shared APS frame) instead of refitting.
        pose_a = clamp_to_limits(
            np.asarray(check_shape(start_pose, [POSE_DIM], name="start_pose"), np.float64)
        )
        prior = _pose_prior(pose_a, shape, camera, opt.continuity_weight)
        det = [prior, det[1]] if opt.continuity == "replace" else [prior, *det]
    else:
        if start_pose is None and lookahead is not None and opt.swap_check:
            det = _unswap_first(det, frame_detections(lookahead, 2 * n), shape, camera, opt.batch)
        pose_a = fit_frame(det[0], camera, shape, initial_pose=start_pose, options=opt.batch).pose
    chained = start_pose is not None and opt.continuity != "off"
    if chained and opt.swap_check:
        det = _unswap(det, pose_a, shape, camera, opt.batch)
    end_b = fit_frame(det[-1], camera, shape, initial_pose=pose_a, options=opt.batch)
    init = interpolate_poses(pose_a, end_b.pose, n=n)
    # A fresh fit of one noisy detection can land on a mirrored or turned body (swapped
    # left/right detections); when frame b's body shape is implausibly far from the pose
    # handed on, also fit from the held pose and let the events decide (lower energy wins).
    alternative = None
    if chained and opt.jump_check_mm is not None:
        shift_mm = _body_shift_mm(pose_a, end_b.pose, shape)
        if shift_mm > opt.jump_check_mm:
            _log.info(
                "batch at %d µs: frame b's fit moves the body %.0f mm from the pose handed "
                "on; fitting from both",
                frame_a.t_us,
                shift_mm,
            )
            alternative = np.repeat(pose_a[None], n + 1, axis=0)
    seconds["init"] = time.perf_counter() - t

    t = stage("tracking")
    masks = [_body_mask(p, shape, camera, opt.mask_erosion_px) for p in (init[0], init[-1])]
    tracks = track_frames(times, latent, mask_t0=masks[0], mask_t1=masks[1], options=opt.tracking)
    pairs = correspondence_pairs(tracks)
    seconds["tracking"] = time.perf_counter() - t

    assoc_s = 0.0
    last_count = 0

    def reassociate(poses: F64) -> Correspondences:
        nonlocal assoc_s, last_count
        t_a = time.perf_counter()
        if opt.association == "trajectory":
            out = _associate_trajectories(pairs, poses, shape, camera, opt.association_erosion_px)
        else:
            out = _associate(pairs, poses, shape, camera)
        assoc_s += time.perf_counter() - t_a
        last_count = out.count
        return out

    t = stage("batch_fit")

    def solve(start: F64) -> tuple[BatchFitResult, int]:
        out = fit_batch(
            reassociate(start),
            det,
            camera,
            shape,
            n=n,
            initial_poses=start,
            options=opt.batch,
            reassociate=reassociate,
            rounds=opt.association_rounds,
        )
        return out, last_count

    fit, n_corr = solve(init)
    if alternative is not None:
        held, n_held = solve(alternative)
        if held.final_energy.total < fit.final_energy.total:
            fit, n_corr = held, n_held
    seconds["batch_fit"] = time.perf_counter() - t - assoc_s
    seconds["association"] = assoc_s
    poses = fit.poses

    refined = accepted = 0
    if opt.refine_every > 0:
        t = stage("refine")
        poses, refined, accepted = _refine(
            poses, times, events, shape, camera, opt, skip_first=chained
        )
        seconds["refine"] = time.perf_counter() - t

    kp = eventcap_keypoints(forward_kinematics(poses, shape), shape)
    return BatchResult(
        t_us=times,
        poses=poses,
        keypoints_m=kp,
        contrast=contrast,
        trajectories=len(tracks.trajectories),
        correspondences=n_corr,
        refined=refined,
        refined_accepted=accepted,
        detection_source=detection_a.source,
        fit=fit,
        stage_seconds=MappingProxyType(seconds),
    )
