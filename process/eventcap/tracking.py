"""EventCap stage A2/A3: feature trajectories inside one batch (brief §1.3–§1.4).

A batch is the interval [t0_us, t1_us] between two APS frames. Latent log-intensity images L(t)
(from EDI, or anything that renders log intensity at a time) are tracked with pyramidal KLT:

1. Harris corners on the sharp end images L(t0) and L(t1) (``cv2.goodFeaturesToTrack``).
2. Frame-to-frame ``cv2.calcOpticalFlowPyrLK`` forward from t0 and backward from t1. Each step
   is checked forward–backward over one frame and over ``long_fb_frames`` (which catches a
   feature sliding onto an occluder) and gated by LK status and error; a half-track stops once
   lost. With a silhouette mask, erode it by half the LK window so that windows see the body.
3. Stitching at the mid frame: forward and backward half-tracks alive there are paired by
   Hungarian matching on their distance, only within ``stitch_gate_px`` (4 px, as the paper).
4. One cubic smoothing B-spline per trajectory and coordinate over its fused samples, time
   rescaled to ms from the trajectory start, smoothing from the tracker noise, sampled every
   ``sample_step_us`` (1 kHz) on the batch grid inside the trajectory's time support.

Images are in pixels (x right, y down, pixel centres at integers, as OpenCV); times are integer
µs. The log images are mapped to 8 bit (OpenCV's LK needs it) by one affine map per batch
(:class:`IntensityMapping`), the same for every frame so that brightness constancy holds.

Optionally (``TrackingOptions.event_refinement``), every tracked sample is then refined with
the events around it against the sharp reference frame's log gradient ("EKLT-lite", brief §1.3
option 2): that removes the drift KLT accumulates frame to frame on noisy latent images. Its
own floor is the events' hysteresis lag: on ideal simulated events the refined position trails
the motion by about 1.5·C px (C the contrast threshold), so it pays off only where KLT is worse.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
import numpy.typing as npt
from scipy.interpolate import BSpline, splrep
from scipy.optimize import linear_sum_assignment

from mocaprig.acquire.events import check_events
from mocaprig.errors import MocaprigError, ProcessingError, ValidationError
from mocaprig.validation import check_finite, check_positive, check_shape

__all__ = [
    "CorrespondencePairs",
    "HalfTrack",
    "IntensityMapping",
    "LatentSource",
    "TrackingOptions",
    "TrackingResult",
    "Trajectory",
    "correspondence_pairs",
    "intensity_mapping",
    "log_to_u8",
    "smooth_and_sample",
    "stitch_pairs",
    "track_batch",
    "track_frames",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
BoolArr = npt.NDArray[np.bool_]

LatentSource = Callable[[int], npt.NDArray[np.float64]]
"""A latent log-intensity image at a time: ``latent(t_us) -> (H, W) float64``."""

Direction = Literal["forward", "backward"]
TrajectoryKind = Literal["stitched", "forward", "backward"]

# Gated Hungarian entries cost this much, so the assignment first maximises the number of pairs
# inside the gate and only then minimises their summed distance.
_GATED_COST = 1.0e6
# Samples per EKLT-lite Gauss–Newton chunk: ~0.1 GB of float64 Jacobians and samples.
_EKLT_CHUNK = 2048


@dataclass(frozen=True, slots=True)
class TrackingOptions:
    """Settings of the batch tracker (defaults: rpg_eklt's corner settings, brief §1.3–1.4).

    Attributes:
        max_features: Harris corners per end image (``maxCorners``).
        quality_level: ``qualityLevel`` of ``goodFeaturesToTrack`` (fraction of the best score).
        min_distance_px: Minimum distance between corners.
        block_size_px: Harris block size.
        harris_k: Harris free parameter k.
        border_px: Corners closer than this to the image border are not taken (half a 25 px
            patch by default).
        win_size_px: LK window side (odd).
        pyramid_levels: Pyramid levels above the base (``maxLevel``).
        lk_max_iter: LK iterations per level.
        lk_epsilon_px: LK convergence threshold.
        fb_max_px: A step is kept only if tracking the new point back lands within this distance
            of where it started.
        long_fb_frames: Baseline of the long forward–backward check: the new point tracked
            straight back this many frames (LK started at the track's position there, no
            pyramid) must land within ``long_fb_max_px`` of it, with an LK error within
            ``lk_max_err``. It drops features that slide onto an occluder, which the one-step
            check passes because occluder and feature then move consistently; too long a
            baseline drops rotating features instead. None turns it off.
        long_fb_max_px: Tolerance of the long check.
        lk_max_err: Largest LK error (mean absolute 8-bit difference over the window) accepted,
            frame to frame and over the long check's baseline.
        stitch_gate_px: Forward and backward tracks further apart than this at the mid frame are
            not stitched (4 px in the paper).
        keep_unpaired: Keep half-tracks that were not stitched as one-sided trajectories.
        noise_px: Tracker noise at the reference frame (1 σ, per coordinate).
        drift_px2_per_step: Variance that each frame-to-frame step adds (random-walk drift); with
            ``noise_px`` it sets the sample noise σ that weights the spline and its smoothing.
        min_samples: Trajectories with fewer tracked samples are dropped (≥ 4 for a cubic).
        sample_step_us: Output sampling step (1000 µs = 1 kHz), on the grid t0 + k·step.
        event_refinement: Refine each tracked sample with the events around it ("EKLT-lite",
            brief §1.3 option 2); needs ``events``. Off by default.
        event_window_us: Events within ± half this window of a frame time form its event frame.
        eklt_patch_px: Side of the EKLT patch (odd; 25 as rpg_eklt).
        eklt_iterations: Damped Gauss–Newton iterations.
        eklt_min_quality: Normalised correlation of observed and predicted event frames below
            which a sample keeps its KLT position (0.6 as rpg_eklt's tracking_quality).
        eklt_max_shift_px: Larger corrections are not trusted (the KLT position is kept).
        eklt_min_events: Fewer (bilinearly weighted) events in the patch: not refined.
    """

    max_features: int = 100
    quality_level: float = 0.01
    min_distance_px: float = 10.0
    block_size_px: int = 3
    harris_k: float = 0.04
    border_px: int = 12
    win_size_px: int = 21
    pyramid_levels: int = 3
    lk_max_iter: int = 30
    lk_epsilon_px: float = 0.01
    fb_max_px: float = 0.5
    long_fb_frames: int | None = 8
    long_fb_max_px: float = 1.0
    lk_max_err: float = 12.0
    stitch_gate_px: float = 4.0
    keep_unpaired: bool = True
    noise_px: float = 0.3
    drift_px2_per_step: float = 0.01
    min_samples: int = 5
    sample_step_us: int = 1000
    event_refinement: bool = False
    event_window_us: int = 1000
    eklt_patch_px: int = 25
    eklt_iterations: int = 10
    eklt_min_quality: float = 0.6
    eklt_max_shift_px: float = 2.0
    eklt_min_events: float = 20.0


@dataclass(frozen=True, slots=True)
class IntensityMapping:
    """The affine map of one batch from log intensity to 8 bit: ``u8 = clip((L - lo)·scale)``.

    Attributes:
        log_lo: Log intensity mapped to 0.
        log_hi: Log intensity mapped to 255.
    """

    log_lo: float
    log_hi: float

    @property
    def scale(self) -> float:
        """8-bit levels per unit of log intensity."""
        return 255.0 / (self.log_hi - self.log_lo)


@dataclass(frozen=True, slots=True)
class HalfTrack:
    """One KLT half-track, as tracked (before stitching and smoothing).

    Attributes:
        track_id: Index among the half-tracks of its direction.
        direction: ``"forward"`` (detected at t0) or ``"backward"`` (detected at t1).
        t_us: (K,) int64 frame times where the feature was tracked, increasing.
        xy_px: (K, 2) float64 positions (x, y) in pixels.
        refined: (K,) bool, samples moved by the event refinement (all False without it).
    """

    track_id: int
    direction: Direction
    t_us: I64 = field(repr=False)
    xy_px: F64 = field(repr=False)
    refined: BoolArr = field(repr=False)


@dataclass(frozen=True, slots=True)
class Trajectory:
    """One smoothed trajectory sampled at 1 kHz inside its time support.

    Attributes:
        trajectory_id: Index in :attr:`TrackingResult.trajectories`.
        kind: ``"stitched"`` (forward + backward), or a one-sided ``"forward"``/``"backward"``.
        forward_id: Track id of the forward half-track, or -1.
        backward_id: Track id of the backward half-track, or -1.
        t_us: (M,) int64 sample times on the grid t0 + k·sample_step_us, increasing.
        xy_px: (M, 2) float64 spline positions (x, y) in pixels at ``t_us``.
        fit_rms_px: RMS distance between the spline and the fused tracked samples.
    """

    trajectory_id: int
    kind: TrajectoryKind
    forward_id: int
    backward_id: int
    t_us: I64 = field(repr=False)
    xy_px: F64 = field(repr=False)
    fit_rms_px: float


@dataclass(frozen=True, slots=True)
class TrackingResult:
    """The trajectories of one batch and the half-tracks they came from.

    Attributes:
        t0_us: Batch start (the first APS frame time).
        t1_us: Batch end (the next APS frame time).
        sample_step_us: Step of the trajectory samples.
        trajectories: Smoothed trajectories, stitched ones first.
        forward: Forward half-tracks (from t0).
        backward: Backward half-tracks (from t1).
        mapping: The log-to-8-bit map used for every frame of the batch.
    """

    t0_us: int
    t1_us: int
    sample_step_us: int
    trajectories: tuple[Trajectory, ...]
    forward: tuple[HalfTrack, ...] = field(repr=False)
    backward: tuple[HalfTrack, ...] = field(repr=False)
    mapping: IntensityMapping

    @property
    def n_frames(self) -> int:
        """Tracking frames in the batch, ends included (N + 1 = 41 for 40 ms at 1 kHz)."""
        return (self.t1_us - self.t0_us) // self.sample_step_us + 1


@dataclass(frozen=True, slots=True)
class CorrespondencePairs:
    """E_cor pairs (paper Eq. 5): position of trajectory h at frame i and at neighbour j.

    Frames are indices on the sampling grid, f = (t - t0) / sample_step; i runs over 1..N-1 and
    j ∈ {i-1, i+1}; a pair exists where the trajectory has samples at both frames.

    Attributes:
        frame_i: (P,) int64 frame of ``p_i``.
        frame_j: (P,) int64 neighbour frame of ``p_j``.
        p_i: (P, 2) float64 position (x, y) in pixels at frame i.
        p_j: (P, 2) float64 position (x, y) in pixels at frame j.
        trajectory_id: (P,) int64 trajectory of each pair.
    """

    frame_i: I64 = field(repr=False)
    frame_j: I64 = field(repr=False)
    p_i: F64 = field(repr=False)
    p_j: F64 = field(repr=False)
    trajectory_id: I64 = field(repr=False)

    def __len__(self) -> int:
        return int(self.frame_i.shape[0])


def intensity_mapping(
    log_images: Sequence[npt.ArrayLike], *, percentiles: tuple[float, float] = (0.5, 99.5)
) -> IntensityMapping:
    """One log-to-8-bit map for a batch, from the pooled percentiles of ``log_images``.

    Pass the sharp end images of the batch; latent frames between them that leave the range
    are clipped.

    Raises:
        ValidationError: no images, or images with no contrast (every value the same).
    """
    if len(log_images) == 0:
        msg = "intensity_mapping got no images; pass the two end images of the batch"
        raise ValidationError(msg)
    pooled = np.concatenate([np.asarray(im, dtype=np.float64).ravel() for im in log_images])
    check_finite(pooled, name="log images")
    lo, hi = (float(v) for v in np.percentile(pooled, percentiles))
    if not hi > lo:
        msg = (
            f"log images have no contrast between percentiles {percentiles} "
            f"(both {lo:.4g}); a featureless batch cannot be tracked"
        )
        raise ValidationError(msg)
    return IntensityMapping(log_lo=lo, log_hi=hi)


def log_to_u8(log_image: npt.ArrayLike, mapping: IntensityMapping) -> npt.NDArray[np.uint8]:
    """Map one (H, W) log-intensity image to 8 bit with the batch ``mapping`` (rounded)."""
    arr = np.asarray(log_image, dtype=np.float64)
    scaled = (arr - mapping.log_lo) * mapping.scale
    return np.clip(np.rint(scaled), 0.0, 255.0).astype(np.uint8)


def track_batch(
    latent: LatentSource,
    *,
    t0_us: int,
    t1_us: int,
    step_us: int = 1000,
    mask_t0: npt.ArrayLike | None = None,
    mask_t1: npt.ArrayLike | None = None,
    events: npt.NDArray[np.void] | None = None,
    options: TrackingOptions | None = None,
) -> TrackingResult:
    """Track one batch by rendering latent frames at t0, t0 + step, ..., t1 (brief §1.3).

    Args:
        latent: Renders the (H, W) log-intensity image at a time in µs.
        t0_us: Batch start; the sharp image L(t0) gives the forward features.
        t1_us: Batch end; the sharp image L(t1) gives the backward features. ``t1_us - t0_us``
            must be a multiple of ``step_us``.
        step_us: Tracking step (1000 µs: 41 frames for a 40 ms batch).
        mask_t0: Optional (H, W) bool, where forward features may lie (e.g. the silhouette).
        mask_t1: Same for the backward features at t1.
        events: The batch's events (``acquire.events`` dtype, sorted by t); used only by the
            event refinement (``options.event_refinement``).
        options: Tracker settings.

    Raises:
        ValidationError: bad times, shapes or a frame that is not finite.
        ProcessingError: ``latent`` failed at a time.
    """
    check_positive(step_us, name="step_us")
    if t1_us <= t0_us or (t1_us - t0_us) % step_us != 0:
        msg = (
            f"batch [{t0_us}, {t1_us}] µs must be non-empty and a whole number of "
            f"{step_us} µs steps; pick t1_us = t0_us + N·step_us"
        )
        raise ValidationError(msg)
    times = np.arange(t0_us, t1_us + 1, step_us, dtype=np.int64)
    frames = []
    for t in times:
        try:
            frames.append(np.asarray(latent(int(t)), dtype=np.float64))
        except MocaprigError:
            raise
        except Exception as err:
            msg = f"latent image source failed at t = {int(t)} µs: {err}"
            raise ProcessingError(msg) from err
    shapes = {f.shape for f in frames}
    if len(shapes) != 1:
        msg = f"latent images differ in shape across the batch: {sorted(shapes)}"
        raise ValidationError(msg)
    return track_frames(
        times, np.stack(frames), mask_t0=mask_t0, mask_t1=mask_t1, events=events, options=options
    )


def track_frames(
    t_us: npt.ArrayLike,
    log_images: npt.ArrayLike,
    *,
    mask_t0: npt.ArrayLike | None = None,
    mask_t1: npt.ArrayLike | None = None,
    events: npt.NDArray[np.void] | None = None,
    options: TrackingOptions | None = None,
) -> TrackingResult:
    """Track one batch given its latent frames (the first and last are the sharp end images).

    Args:
        t_us: (F,) int frame times in µs, strictly increasing; t_us[0] = t0, t_us[-1] = t1.
        log_images: (F, H, W) log intensity at ``t_us``; not modified.
        mask_t0: Optional (H, W) bool, where forward features may lie (e.g. the silhouette).
        mask_t1: Same for the backward features at t1.
        events: The batch's events (``acquire.events`` dtype, sorted by t, pixel coordinates of
            these images); needed by, and used only for, ``options.event_refinement``.
        options: Tracker settings.

    Returns:
        Half-tracks, and trajectories sampled every ``options.sample_step_us`` from t0.

    Raises:
        ValidationError: bad shapes, times, masks or options.
    """
    opts = options if options is not None else TrackingOptions()
    _check_options(opts)
    times = _check_times(t_us)
    imgs = check_shape(log_images, [times.shape[0], "H", "W"], name="log_images")
    check_finite(imgs, name="log_images")
    n_frames, height, width = imgs.shape
    masks = [
        _check_mask(m, (height, width), name)
        for m, name in ((mask_t0, "mask_t0"), (mask_t1, "mask_t1"))
    ]
    ev = _check_refinement_events(events, opts)
    mapping = intensity_mapping([imgs[0], imgs[-1]])
    frames_u8 = [log_to_u8(im, mapping) for im in imgs]

    fwd_pos, fwd_alive = _track_half(frames_u8, _detect(frames_u8[0], masks[0], opts), opts)
    bwd_pos_r, bwd_alive_r = _track_half(
        frames_u8[::-1], _detect(frames_u8[-1], masks[1], opts), opts
    )
    bwd_pos, bwd_alive = bwd_pos_r[::-1], bwd_alive_r[::-1]
    fwd_ref = np.zeros_like(fwd_alive)
    bwd_ref = np.zeros_like(bwd_alive)
    if ev is not None:
        ev_imgs = _event_images(ev, times, opts.event_window_us, (height, width))
        fwd_pos, fwd_ref = _eklt_refine(imgs[0], fwd_pos[0], fwd_pos, fwd_alive, 0, ev_imgs, opts)
        bwd_pos, bwd_ref = _eklt_refine(
            imgs[-1], bwd_pos[-1], bwd_pos, bwd_alive, n_frames - 1, ev_imgs, opts
        )

    t0, t1 = int(times[0]), int(times[-1])
    mid = int(np.argmin(np.abs(2 * times - (t0 + t1))))  # the first of two equally close
    f_mid = np.flatnonzero(fwd_alive[mid])
    b_mid = np.flatnonzero(bwd_alive[mid])
    rows = stitch_pairs(fwd_pos[mid, f_mid], bwd_pos[mid, b_mid], gate_px=opts.stitch_gate_px)
    pairs = [(int(f_mid[i]), int(b_mid[j])) for i, j in rows]

    steps = np.arange(n_frames, dtype=np.float64)
    var_f = opts.noise_px**2 + opts.drift_px2_per_step * steps
    var_b = opts.noise_px**2 + opts.drift_px2_per_step * steps[::-1]

    candidates: list[tuple[TrajectoryKind, int, int, I64, F64, F64]] = []
    paired_f = {f for f, _ in pairs}
    paired_b = {b for _, b in pairs}
    for f_id, b_id in pairs:
        xy, sigma, sel = _fuse(
            fwd_pos[:, f_id], fwd_alive[:, f_id], bwd_pos[:, b_id], bwd_alive[:, b_id], var_f, var_b
        )
        candidates.append(("stitched", f_id, b_id, times[sel], xy, sigma))
    if opts.keep_unpaired:
        for f_id in range(fwd_alive.shape[1]):
            if f_id not in paired_f:
                a = fwd_alive[:, f_id]
                candidates.append(
                    ("forward", f_id, -1, times[a], fwd_pos[a, f_id], np.sqrt(var_f[a]))
                )
        for b_id in range(bwd_alive.shape[1]):
            if b_id not in paired_b:
                a = bwd_alive[:, b_id]
                candidates.append(
                    ("backward", -1, b_id, times[a], bwd_pos[a, b_id], np.sqrt(var_b[a]))
                )

    trajectories: list[Trajectory] = []
    for kind, f_id, b_id, ts, xy, sigma in candidates:
        if ts.shape[0] < opts.min_samples:
            continue
        t_s, xy_s, rms = smooth_and_sample(
            ts, xy, sigma_px=sigma, t0_us=t0, sample_step_us=opts.sample_step_us
        )
        if t_s.shape[0] == 0:
            continue
        trajectories.append(
            Trajectory(
                trajectory_id=len(trajectories),
                kind=kind,
                forward_id=f_id,
                backward_id=b_id,
                t_us=t_s,
                xy_px=xy_s,
                fit_rms_px=rms,
            )
        )
    _log.info(
        "batch [%d, %d] µs: %d forward, %d backward half-tracks, %d stitched, %d trajectories",
        t0,
        t1,
        fwd_alive.shape[1],
        bwd_alive.shape[1],
        len(pairs),
        len(trajectories),
    )
    return TrackingResult(
        t0_us=t0,
        t1_us=t1,
        sample_step_us=opts.sample_step_us,
        trajectories=tuple(trajectories),
        forward=_half_tracks("forward", times, fwd_pos, fwd_alive, fwd_ref),
        backward=_half_tracks("backward", times, bwd_pos, bwd_alive, bwd_ref),
        mapping=mapping,
    )


def correspondence_pairs(result: TrackingResult) -> CorrespondencePairs:
    """The E_cor pairs of a batch: for frames i = 1..N-1 and j = i ± 1 where a trajectory has
    samples at both, its positions p_i and p_j (paper Eq. 5, brief §1.4)."""
    n_last = result.n_frames - 1
    fi: list[I64] = []
    fj: list[I64] = []
    pi: list[F64] = []
    pj: list[F64] = []
    tid: list[I64] = []
    for traj in result.trajectories:
        frames = (traj.t_us - result.t0_us) // result.sample_step_us
        a, b = frames[:-1], frames[1:]
        adjacent = b == a + 1
        for src, dst, p_src, p_dst in (
            (a, b, traj.xy_px[:-1], traj.xy_px[1:]),
            (b, a, traj.xy_px[1:], traj.xy_px[:-1]),
        ):
            keep = adjacent & (src >= 1) & (src <= n_last - 1)
            fi.append(src[keep])
            fj.append(dst[keep])
            pi.append(p_src[keep])
            pj.append(p_dst[keep])
            tid.append(np.full(int(keep.sum()), traj.trajectory_id, dtype=np.int64))
    if not fi:
        empty_i = np.zeros(0, dtype=np.int64)
        empty_p = np.zeros((0, 2), dtype=np.float64)
        return CorrespondencePairs(empty_i, empty_i.copy(), empty_p, empty_p.copy(), empty_i.copy())
    frame_i = np.concatenate(fi)
    frame_j = np.concatenate(fj)
    traj_id = np.concatenate(tid)
    order = np.lexsort((frame_j, frame_i, traj_id))
    return CorrespondencePairs(
        frame_i=frame_i[order],
        frame_j=frame_j[order],
        p_i=np.concatenate(pi)[order],
        p_j=np.concatenate(pj)[order],
        trajectory_id=traj_id[order],
    )


def _check_options(opts: TrackingOptions) -> None:
    problems = []
    if opts.max_features < 1:
        problems.append(f"max_features = {opts.max_features} (need ≥ 1)")
    if opts.win_size_px < 3 or opts.win_size_px % 2 == 0:
        problems.append(f"win_size_px = {opts.win_size_px} (need an odd number ≥ 3)")
    if opts.pyramid_levels < 0:
        problems.append(f"pyramid_levels = {opts.pyramid_levels} (need ≥ 0)")
    if opts.min_samples < 4:
        problems.append(f"min_samples = {opts.min_samples} (a cubic spline needs ≥ 4)")
    if opts.sample_step_us < 1:
        problems.append(f"sample_step_us = {opts.sample_step_us} (need ≥ 1 µs)")
    for name in (
        "quality_level",
        "min_distance_px",
        "fb_max_px",
        "long_fb_max_px",
        "lk_max_err",
        "stitch_gate_px",
        "noise_px",
        "lk_epsilon_px",
    ):
        if not getattr(opts, name) > 0:
            problems.append(f"{name} = {getattr(opts, name)} (need > 0)")
    if opts.eklt_patch_px < 5 or opts.eklt_patch_px % 2 == 0:
        problems.append(f"eklt_patch_px = {opts.eklt_patch_px} (need an odd number ≥ 5)")
    if opts.event_window_us < 1 or opts.eklt_iterations < 1:
        problems.append("event_window_us and eklt_iterations must be ≥ 1")
    if opts.long_fb_frames is not None and opts.long_fb_frames < 2:
        problems.append(f"long_fb_frames = {opts.long_fb_frames} (need ≥ 2, or None)")
    if opts.drift_px2_per_step < 0:
        problems.append(f"drift_px2_per_step = {opts.drift_px2_per_step} (need ≥ 0)")
    if problems:
        msg = "TrackingOptions out of range: " + "; ".join(problems)
        raise ValidationError(msg)


def _check_refinement_events(
    events: npt.NDArray[np.void] | None, opts: TrackingOptions
) -> npt.NDArray[np.void] | None:
    if not opts.event_refinement:
        return None
    if events is None:
        msg = "TrackingOptions.event_refinement needs the batch's events; pass events=..."
        raise ValidationError(msg)
    ev = check_events(events)
    if ev.shape[0] > 1 and np.any(np.diff(ev["t"]) < 0):
        msg = "events must be sorted by t for the event refinement; sort them (stable) first"
        raise ValidationError(msg)
    return ev


def _check_times(t_us: npt.ArrayLike) -> I64:
    arr = check_shape(t_us, ["F"], name="t_us")
    if not np.issubdtype(arr.dtype, np.integer):
        msg = f"t_us must be integer µs, got dtype {arr.dtype}; round to µs first"
        raise ValidationError(msg)
    times = arr.astype(np.int64)
    if times.shape[0] < 2 or np.any(np.diff(times) <= 0):
        msg = "t_us must hold ≥ 2 strictly increasing frame times (t0 first, t1 last)"
        raise ValidationError(msg)
    return times


def _check_mask(mask: npt.ArrayLike | None, shape: tuple[int, int], name: str) -> BoolArr | None:
    if mask is None:
        return None
    arr = check_shape(mask, list(shape), name=name)
    if arr.dtype != np.bool_:
        msg = f"{name} must be a bool (H, W) array, got dtype {arr.dtype}"
        raise ValidationError(msg)
    return np.asarray(arr, dtype=np.bool_)


def _detect(image: npt.NDArray[np.uint8], mask: BoolArr | None, opts: TrackingOptions) -> F64:
    """Harris corners (K, 2) in pixels, away from the border and inside ``mask``."""
    allowed = np.zeros(image.shape, dtype=np.uint8)
    b = opts.border_px
    allowed[b : image.shape[0] - b, b : image.shape[1] - b] = 255
    if mask is not None:
        allowed[~mask] = 0
    corners: object = cv2.goodFeaturesToTrack(
        image,
        maxCorners=opts.max_features,
        qualityLevel=opts.quality_level,
        minDistance=opts.min_distance_px,
        mask=allowed,
        blockSize=opts.block_size_px,
        useHarrisDetector=True,
        k=opts.harris_k,
    )
    if corners is None:
        return np.zeros((0, 2), dtype=np.float64)
    return np.asarray(corners, dtype=np.float64).reshape(-1, 2)


def _track_half(
    frames: Sequence[npt.NDArray[np.uint8]], start_px: F64, opts: TrackingOptions
) -> tuple[F64, BoolArr]:
    """Frame-to-frame LK from frames[0]: positions (F, K, 2) and alive flags (F, K).

    A step survives if LK converged both ways, the point tracked back one frame lands within
    ``fb_max_px`` of where it started, tracked back ``long_fb_frames`` frames within
    ``long_fb_max_px`` of the track there, the LK error is small and the point stays in the
    image.
    """
    n_frames, n_pts = len(frames), start_px.shape[0]
    pos = np.full((n_frames, n_pts, 2), np.nan)
    alive = np.zeros((n_frames, n_pts), dtype=np.bool_)
    pos[0], alive[0] = start_px, True
    height, width = frames[0].shape
    win = (opts.win_size_px, opts.win_size_px)
    criteria = (
        cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT,
        opts.lk_max_iter,
        opts.lk_epsilon_px,
    )

    def lk(
        a: npt.NDArray[np.uint8],
        b: npt.NDArray[np.uint8],
        pts: npt.NDArray[np.float32],
        guess: npt.NDArray[np.float32] | None = None,
        levels: int = opts.pyramid_levels,
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.uint8], npt.NDArray[np.float32]]:
        out, status, error = cv2.calcOpticalFlowPyrLK(
            a,
            b,
            pts,
            pts.copy() if guess is None else guess.copy(),
            winSize=win,
            maxLevel=levels,
            criteria=criteria,
            flags=0 if guess is None else cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        return (
            np.asarray(out, np.float32),
            np.asarray(status, np.uint8),
            np.asarray(error, np.float32),
        )

    idx = np.arange(n_pts)
    for f in range(1, n_frames):
        if idx.size == 0:
            break
        prev = pos[f - 1, idx].astype(np.float32).reshape(-1, 1, 2)
        nxt, st, err = lk(frames[f - 1], frames[f], prev)
        back, st_b, _ = lk(frames[f], frames[f - 1], nxt)
        nxt2 = nxt.reshape(-1, 2).astype(np.float64)
        fb = np.linalg.norm(back.reshape(-1, 2) - prev.reshape(-1, 2), axis=1)
        ok = (st.ravel() == 1) & (st_b.ravel() == 1) & (fb <= opts.fb_max_px)
        if opts.long_fb_frames is not None and f > 1:
            r = max(0, f - opts.long_fb_frames)
            then = pos[r, idx].astype(np.float32).reshape(-1, 1, 2)
            # The old position is the guess and only drift is left to find: no pyramid, whose
            # coarse levels would see (and follow) other objects moving near the feature.
            home, st_h, err_h = lk(frames[f], frames[r], nxt, then, 0)
            miss = np.linalg.norm(home.reshape(-1, 2) - then.reshape(-1, 2), axis=1)
            ok &= (
                (st_h.ravel() == 1)
                & (miss <= opts.long_fb_max_px)
                & (err_h.ravel() <= opts.lk_max_err)
            )
        ok &= (
            (err.ravel() <= opts.lk_max_err)
            & (nxt2[:, 0] >= 0.0)
            & (nxt2[:, 0] <= width - 1.0)
            & (nxt2[:, 1] >= 0.0)
            & (nxt2[:, 1] <= height - 1.0)
        )
        idx = idx[ok]
        pos[f, idx] = nxt2[ok]
        alive[f, idx] = True
    return pos, alive


def stitch_pairs(
    forward_px: npt.ArrayLike, backward_px: npt.ArrayLike, *, gate_px: float = 4.0
) -> I64:
    """Pair forward and backward features at the mid time (paper §3.1, brief §1.4).

    Hungarian matching on the pixel distance: each feature is used at most once, as many pairs
    as possible lie within ``gate_px``, then their summed distance is smallest; pairs further
    apart than ``gate_px`` are not made.

    Args:
        forward_px: (A, 2) forward positions (x, y) in pixels at the mid time.
        backward_px: (B, 2) backward positions at the mid time.
        gate_px: Largest distance of a pair (4 px in the paper).

    Returns:
        (P, 2) int64 index pairs (forward row, backward row), sorted by forward row.

    Raises:
        ValidationError: bad shapes, non-finite positions or gate.
    """
    fwd = check_finite(check_shape(forward_px, ["A", 2], name="forward_px"), name="forward_px")
    bwd = check_finite(check_shape(backward_px, ["B", 2], name="backward_px"), name="backward_px")
    check_positive(gate_px, name="gate_px")
    if fwd.shape[0] == 0 or bwd.shape[0] == 0:
        return np.zeros((0, 2), dtype=np.int64)
    dist = np.linalg.norm(
        fwd[:, None, :].astype(np.float64) - bwd[None, :, :].astype(np.float64), axis=2
    )
    cost = np.where(dist <= gate_px, dist, _GATED_COST)
    rows, cols = linear_sum_assignment(cost)
    keep = dist[rows, cols] <= gate_px
    pairs = np.stack([rows[keep], cols[keep]], axis=1).astype(np.int64)
    return pairs[np.argsort(pairs[:, 0], kind="stable")]


def smooth_and_sample(
    t_us: npt.ArrayLike,
    xy_px: npt.ArrayLike,
    *,
    sigma_px: npt.ArrayLike,
    t0_us: int,
    sample_step_us: int = 1000,
) -> tuple[I64, F64, float]:
    """Smoothing cubic B-spline per coordinate, sampled on t0 + k·step inside the support.

    Time is rescaled to ms from the first sample: FITPACK's automatic knot placement fails on
    spans in s (or raw µs). With weights 1/σ the expected weighted residual sum is the sample
    count n, so s = n lets the curve deviate by the tracker noise and no more.

    Args:
        t_us: (n,) int sample times, strictly increasing, n ≥ 4.
        xy_px: (n, 2) tracked positions (x, y) in pixels.
        sigma_px: Noise (1 σ) per sample, scalar or (n,), > 0.
        t0_us: Origin of the sampling grid (the batch start).
        sample_step_us: Grid step (1000 µs = 1 kHz).

    Returns:
        Grid times (M,) int64 within [t_us[0], t_us[-1]], spline positions (M, 2) and the RMS
        distance between the spline and the samples in pixels.

    Raises:
        ValidationError: bad shapes, times or noise.
        ProcessingError: the spline fit failed.
    """
    times = _check_times(t_us)
    xy = check_finite(check_shape(xy_px, [times.shape[0], 2], name="xy_px"), name="xy_px")
    try:
        sigma = np.broadcast_to(np.asarray(sigma_px, dtype=np.float64), times.shape)
    except ValueError as err:
        msg = f"sigma_px must be a scalar or one value per sample ({times.shape[0]}): {err}"
        raise ValidationError(msg) from err
    if times.shape[0] < 4 or not np.all(np.isfinite(sigma) & (sigma > 0)):
        msg = "smooth_and_sample needs ≥ 4 samples and finite sigma_px > 0"
        raise ValidationError(msg)
    check_positive(sample_step_us, name="sample_step_us")
    first = t0_us + -((t0_us - int(times[0])) // sample_step_us) * sample_step_us
    grid = np.arange(first, int(times[-1]) + 1, sample_step_us, dtype=np.int64)
    t_ms = (times - times[0]).astype(np.float64) / 1000.0
    g_ms = (grid - times[0]).astype(np.float64) / 1000.0
    fit = np.empty((times.shape[0], 2))
    out = np.empty((grid.shape[0], 2))
    for c in range(2):
        try:
            tck = splrep(t_ms, xy[:, c].astype(np.float64), w=1.0 / sigma, k=3, s=float(len(t_ms)))
        except ValueError as err:
            msg = f"spline fit of a trajectory with {len(t_ms)} samples failed: {err}"
            raise ProcessingError(msg) from err
        spline = BSpline(*tck, extrapolate=False)
        fit[:, c] = spline(t_ms)
        out[:, c] = spline(g_ms)
    if not (np.all(np.isfinite(out)) and np.all(np.isfinite(fit))):
        msg = "spline fit of a trajectory gave non-finite values; check the samples"
        raise ProcessingError(msg)
    rms = float(np.sqrt(np.mean(np.sum((fit - xy) ** 2, axis=1))))
    return grid, out, rms


def _fuse(
    fwd_px: F64, fwd_alive: BoolArr, bwd_px: F64, bwd_alive: BoolArr, var_f: F64, var_b: F64
) -> tuple[F64, F64, BoolArr]:
    """One stitched sample track (positions, σ, frames used) from a forward and a backward one.

    Where both are alive, a linear cross-fade over their overlap: the forward position at the
    overlap's start, the backward one at its end. Stitched features may be different physical
    points (up to the gate apart); the cross-fade spreads their offset over the overlap instead
    of a jump at mid-batch, and keeps each end on its sharp-frame detection. This is the
    inverse-variance mean under pure random-walk drift from each reference frame.
    """
    both = np.flatnonzero(fwd_alive & bwd_alive)
    w_b = bwd_alive.astype(np.float64)
    w_b[fwd_alive & ~bwd_alive] = 0.0
    if both.size > 1:
        w_b[both] = (both - both[0]) / float(both[-1] - both[0])
    elif both.size == 1:
        w_b[both] = 0.5
    sel = fwd_alive | bwd_alive
    xy_f = np.where(fwd_alive[:, None], fwd_px, 0.0)
    xy_b = np.where(bwd_alive[:, None], bwd_px, 0.0)
    xy = (1.0 - w_b)[:, None] * xy_f + w_b[:, None] * xy_b
    inv = np.where(fwd_alive, 1.0 / var_f, 0.0) + np.where(bwd_alive, 1.0 / var_b, 0.0)
    return xy[sel], 1.0 / np.sqrt(inv[sel]), sel


def _half_tracks(
    direction: Direction, times: I64, pos: F64, alive: BoolArr, refined: BoolArr
) -> tuple[HalfTrack, ...]:
    return tuple(
        HalfTrack(
            track_id=k,
            direction=direction,
            t_us=times[alive[:, k]].copy(),
            xy_px=pos[alive[:, k], k].copy(),
            refined=refined[alive[:, k], k].copy(),
        )
        for k in range(alive.shape[1])
    )


def _event_images(
    events: npt.NDArray[np.void], times: I64, window_us: int, shape: tuple[int, int]
) -> F64:
    """Signed event counts (ON +1, OFF −1) per pixel in [t - w/2, t + w/2) for each frame time.

    Returns (F, H, W). Events are sorted by time (the canonical stream order).
    """
    height, width = shape
    t_ev = events["t"]
    lo = np.searchsorted(t_ev, times - window_us // 2, side="left")
    hi = np.searchsorted(t_ev, times - window_us // 2 + window_us, side="left")
    out = np.zeros((times.shape[0], height, width))
    x = events["x"].astype(np.int64)
    y = events["y"].astype(np.int64)
    pol = np.where(events["p"] != 0, 1.0, -1.0)
    inside = (x < width) & (y < height)
    for f in range(times.shape[0]):
        sl = slice(int(lo[f]), int(hi[f]))
        keep = inside[sl]
        flat = (y[sl] * width + x[sl])[keep]
        out[f] = np.bincount(flat, weights=pol[sl][keep], minlength=height * width).reshape(
            height, width
        )
    return out


def _eklt_refine(
    ref_log: F64,
    ref_px: F64,
    pos: F64,
    alive: BoolArr,
    ref_frame: int,
    event_images: F64,
    opts: TrackingOptions,
) -> tuple[F64, BoolArr]:
    """EKLT-lite (brief §1.3 option 2): refine every tracked sample with the events around it.

    For a sample at frame k, position c (from KLT) and reference position c_ref, the event frame
    ΔL(x) (signed counts in the window, sampled bilinearly at c + x over the patch) is explained
    by the reference log gradient T(x) = ∇L_ref(c_ref + x) shifted by the correction d and
    moving along the flow angle α: ΔL(x) ∝ -T(x - d)·(cos α, sin α). Both sides are normalised,
    which removes the contrast threshold and the speed. (d, α) are found by batched damped
    Gauss–Newton over all samples at once; a sample keeps its KLT position unless the
    normalised correlation reaches ``eklt_min_quality`` and |d| ≤ ``eklt_max_shift_px``.

    Returns the positions (F, K, 2) and which samples were refined (F, K).
    """
    import torch  # deferred: only this option needs it

    n_frames = alive.shape[0]
    height, width = ref_log.shape
    refined = np.zeros_like(alive)
    out = pos.copy()
    todo = alive.copy()
    todo[ref_frame] = False
    fr, kk = np.nonzero(todo)
    if fr.size == 0:
        return out, refined
    # Flow direction from the KLT track (central difference where possible).
    prev_f = np.clip(fr - 1, 0, n_frames - 1)
    next_f = np.clip(fr + 1, 0, n_frames - 1)
    prev_f = np.where(alive[prev_f, kk], prev_f, fr)
    next_f = np.where(alive[next_f, kk], next_f, fr)
    vel = pos[next_f, kk] - pos[prev_f, kk]
    half = opts.eklt_patch_px // 2
    offs = np.arange(-half, half + 1, dtype=np.float64)
    gy_off, gx_off = np.meshgrid(offs, offs, indexing="ij")
    grid_off = torch.from_numpy(np.stack([gx_off, gy_off], axis=-1))  # (P, P, 2) as (x, y)

    def to_norm(xy: torch.Tensor) -> torch.Tensor:
        scale = torch.tensor([2.0 / (width - 1), 2.0 / (height - 1)], dtype=xy.dtype)
        normed: torch.Tensor = xy * scale - 1.0
        return normed

    # Event patches ΔL(c + x), bilinear; one grid_sample per frame (never a copy per sample).
    n_b = fr.size
    dl = torch.empty((n_b, grid_off.shape[0] * grid_off.shape[1]), dtype=torch.float64)
    for f in np.unique(fr):
        sel = np.flatnonzero(fr == f)
        pts = torch.from_numpy(pos[f, kk[sel]])[:, None, None, :] + grid_off[None]
        img = torch.from_numpy(event_images[f])[None, None]
        patch = torch.nn.functional.grid_sample(
            img, to_norm(pts).reshape(1, -1, grid_off.shape[1], 2), align_corners=True
        )
        dl[torch.from_numpy(sel)] = patch.reshape(sel.size, -1)
    n_events = dl.abs().sum(dim=1)
    dl_n = dl / dl.norm(dim=1, keepdim=True).clamp_min(1e-12)

    # Reference log gradient and its derivatives (Sobel / 8: unit-step derivatives).
    gx = np.asarray(cv2.Sobel(ref_log, cv2.CV_64F, 1, 0, ksize=3), np.float64) / 8.0
    gy = np.asarray(cv2.Sobel(ref_log, cv2.CV_64F, 0, 1, ksize=3), np.float64) / 8.0
    gxx = cv2.Sobel(gx, cv2.CV_64F, 1, 0, ksize=3) / 8.0
    gxy = cv2.Sobel(gx, cv2.CV_64F, 0, 1, ksize=3) / 8.0
    gyy = cv2.Sobel(gy, cv2.CV_64F, 0, 1, ksize=3) / 8.0
    maps = torch.from_numpy(np.stack([gx, gy, gxx, gxy, gyy]))[None]  # (1, 5, H, W)

    def residual_and_jacobian(
        theta: torch.Tensor, c_ref: torch.Tensor, obs: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """r = ΔL/‖ΔL‖ - pred/‖pred‖ (b, P²) and ∂r/∂(dx, dy, α) (b, P², 3)."""
        n = theta.shape[0]
        d, alpha = theta[:, :2], theta[:, 2]
        where = c_ref[:, None, None, :] + grid_off[None] - d[:, None, None, :]
        g = torch.nn.functional.grid_sample(
            maps,
            to_norm(where).reshape(1, n * grid_off.shape[0], -1, 2),
            mode="bicubic",
            align_corners=True,
        )[0].reshape(5, n, -1)
        ux, uy = torch.cos(alpha)[:, None], torch.sin(alpha)[:, None]
        pred = -(g[0] * ux + g[1] * uy)
        # T(x - d): moving d moves the sample point by -d, so ∂/∂d = -(-∇) = +Hessian·u.
        d_pred = torch.stack(
            [g[2] * ux + g[3] * uy, g[3] * ux + g[4] * uy, g[0] * uy - g[1] * ux], dim=2
        )
        norm = pred.norm(dim=1, keepdim=True).clamp_min(1e-12)
        unit = pred / norm
        # ∂(p/‖p‖) = (I - n nᵀ) ∂p / ‖p‖
        proj = d_pred - unit[:, :, None] * (unit[:, None, :] @ d_pred)
        res: torch.Tensor = obs - unit
        return res, -proj / norm[:, :, None]

    theta_all = torch.zeros((n_b, 3), dtype=torch.float64)
    theta_all[:, 2] = torch.from_numpy(np.arctan2(vel[:, 1], vel[:, 0]))
    cost_all = torch.empty(n_b, dtype=torch.float64)
    c_ref_all = torch.from_numpy(ref_px[kk])
    # Chunks bound the memory of the (b, P², 3) Jacobians; samples are independent.
    for lo in range(0, n_b, _EKLT_CHUNK):
        sl = slice(lo, min(lo + _EKLT_CHUNK, n_b))
        c_ref, obs, theta = c_ref_all[sl], dl_n[sl], theta_all[sl]
        mu = torch.full((theta.shape[0],), 1e-3, dtype=torch.float64)
        r, jac = residual_and_jacobian(theta, c_ref, obs)
        cost = (r**2).sum(dim=1)
        for _ in range(opts.eklt_iterations):
            jtj = jac.transpose(1, 2) @ jac
            jtr = (jac.transpose(1, 2) @ r[:, :, None])[:, :, 0]
            diag = torch.diag_embed(torch.diagonal(jtj, dim1=1, dim2=2) + 1e-9)
            cand = theta - torch.linalg.solve(jtj + mu[:, None, None] * diag, jtr)
            r_c, jac_c = residual_and_jacobian(cand, c_ref, obs)
            cost_c = (r_c**2).sum(dim=1)
            better = cost_c < cost
            theta = torch.where(better[:, None], cand, theta)
            r = torch.where(better[:, None], r_c, r)
            jac = torch.where(better[:, None, None], jac_c, jac)
            cost = torch.where(better, cost_c, cost)
            mu = torch.where(better, mu / 3.0, mu * 2.0)
        theta_all[sl] = theta
        cost_all[sl] = cost
    theta, cost = theta_all, cost_all
    quality = 1.0 - cost / 2.0  # normalised correlation of observed and predicted ΔL
    shift = theta[:, :2].norm(dim=1)
    ok = (
        (quality >= opts.eklt_min_quality)
        & (shift <= opts.eklt_max_shift_px)
        & (n_events >= opts.eklt_min_events)
    ).numpy()
    new = pos[fr, kk] + theta[:, :2].numpy()
    out[fr[ok], kk[ok]] = new[ok]
    refined[fr[ok], kk[ok]] = True
    _log.debug("EKLT-lite refined %d of %d samples", int(ok.sum()), n_b)
    return out, refined
