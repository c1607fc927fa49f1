"""Calibrate a recorded D415 rig against a Vicon trial; score a calibration against truth.

:func:`calibrate_vicon` (``mocaprig calibrate vicon``):

1. **Vicon**: the trial's trajectories (metres), frame times on the Vicon clock
   ``(first_frame − 1 + i)/rate``; a unit check on the marker cloud's extent; the **static
   start** (markers within ``static_tolerance_m`` of the first frames) and its median cloud; the
   claps (``mocaprig.calib.time_align.find_claps_vicon``; none is an error).
2. **Reading**: the recording is measured (``calib.markers.measure_frame``) only in device-time
   windows — the first ``head_window_s``, around each Vicon clap, and ``extra_windows`` — found
   by bisection over the host log time, all cameras in one pass per window.
3. **Registration** per camera on its static start (blobs still within
   ``static_tolerance_px``): :func:`calib.registration.register_camera` (coarse alignment without
   an initial pose, gated matching, bundle adjustment).
4. **Clock** (``clock_method``): reprojection offsets of 0.5 s stretches of frames per camera;
   the cameras whose frames pair with one another's (hardware sync, checked, not assumed) share
   one line through all their stretches (offset, drift) composed with each camera's tie to the
   pivot camera (:func:`_pooled_clocks`); optionally refined by ``mocaprig.calib.time_align``.
   With a **sync channel** in the Vicon trial (``CalibrationOptions.sync_channel``, default
   ``D415_SYNC``: the sync box's toggle output on a Vicon analog input, docs/wiring.md §7),
   the master's clock is instead the line through the channel's edges paired with its frames
   (``calib.time_align.clock_from_sync_edges``, the video clock as the pairing prior), and every
   camera tied to it by frame counters in the pool gets it through its tie plus its trigger
   delay (:func:`_sync_clocks`); without the channel, or when it is unusable, the video clocks
   stay and a note says why.
5. **Final bundle adjustment** over all frames read, the Vicon markers interpolated at each
   frame's mapped time (fast markers and partly occluded blobs left out); clock and pose are
   iterated twice.
6. **Refusal**: a camera whose reprojection RMS exceeds ``max_rms_px`` (default
   :data:`MAX_RMS_PX` = 1.5 px) or with fewer than ``min_inliers`` (default 30) inlier
   observations makes the calibration fail with the figures, unless ``force`` is set.

7. **DAVIS clock** (when the recording has ``/davis/<serial>/trigger``): the D415 master's sync
   pulses on the DAVIS's external input, paired with the master's frames
   (``calib.time_align.clock_from_pulses``) and composed with the master's Vicon mapping; see
   :func:`_davis_pulse_inputs` for the pairing prior. The DAVIS's extrinsics come from
   ``mocaprig calibrate board``.

:func:`evaluate_calibration` (``mocaprig calibrate evaluate``) compares a calibration with a
simulated session's truth (``SIMDIR/truth/scenario.json``, read directly: calib/ never imports
the simulator).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import logging
import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, Literal

import numpy as np
import numpy.typing as npt

from mocaprig import __version__
from mocaprig.acquire.device_streams import (
    D415Settings,
    DeviceId,
    RecordedD415,
    RecordedDavis,
    d415_devices,
    davis_devices,
    read_frame_sets,
)
from mocaprig.acquire.recording import Recording
from mocaprig.calib.calibration import (
    Calibration,
    CameraCalibration,
    ClockMapping,
    calibration_bytes,
)
from mocaprig.calib.markers import MarkerFrame
from mocaprig.calib.registration import (
    CameraRegistration,
    project_points,
    register_camera,
    rotation_error_deg,
)
from mocaprig.calib.time_align import ClapDetection, SyncEdges
from mocaprig.calib.vicon import MarkerTrajectories
from mocaprig.errors import CalibrationError, RecordingError, ValidationError
from mocaprig.timebase import U32_US_WRAP, unwrap_u32_from
from mocaprig.validation import check_positive

__all__ = [
    "ATTACHMENT_NAME",
    "MAX_RMS_PX",
    "CalibrationOptions",
    "DeviceEvaluation",
    "Evaluation",
    "ViconCalibrationResult",
    "ViconStatic",
    "attach_calibration",
    "calibrate_vicon",
    "evaluate_calibration",
    "vicon_static_start",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: Default refusal threshold on a camera's reprojection RMS (px). The simulated rig gives
#: 0.2–0.4 px; a wrong registration gives several px.
MAX_RMS_PX: Final = 1.5
#: Name of the calibration attachment written into a recording copy.
ATTACHMENT_NAME: Final = "calibration.toml"
#: A body marker cloud spans 0.3–4 m; outside [_MIN_EXTENT_M, _MAX_EXTENT_M] the units are wrong.
_MIN_EXTENT_M: Final = 0.2
_MAX_EXTENT_M: Final = 10.0
#: Length of the stretches of frames that each give one clock offset (ns).
_CHUNK_NS: Final = 500_000_000
_U32_NS: Final = U32_US_WRAP * 1000


@dataclass(frozen=True, slots=True)
class CalibrationOptions:
    """Options of :func:`calibrate_vicon`.

    Attributes:
        head_window_s: How much of the recording's start is measured: the static start, the
            motion onset (coarse clock) and usually the first clap (s).
        clock_method: ``"reprojection"``: offsets of the Vicon markers' reprojection over
            chunks of frames, a line through them; ``"claps+speed"``: that as the prior, then
            :mod:`mocaprig.calib.time_align` (claps, speed cross-correlation).
        max_marker_speed_m_s: Markers moving faster are left out of the final bundle
            adjustment (m/s).
        min_area_ratio: Blobs whose area × depth² is below this fraction of the camera's median
            (partly occluded markers) are left out of the final bundle adjustment; 0 keeps all.
        extra_windows: Further 0.6 s windows read for the clock fit, as fractions of the
            session (the windows around the Vicon claps are always read).
        static_tolerance_m: Vicon markers within this of the first frames count as still (m).
        static_tolerance_px: D415 blobs within this of the first frame count as still (px).
        min_static_frames: Fewest still D415 frames a camera needs.
        max_rms_px: Refusal threshold on the reprojection RMS (px).
        min_inliers: Refusal threshold on the inlier observations per camera.
        force: Write the calibration even above the thresholds (the figures are kept).
        cameras: ``"d415/<serial>"`` labels to calibrate; None = every D415 of the recording.
        seed: Seed of the coarse alignment's sampling.
        unit: Length unit of the Vicon file when it does not say (``"mm"``, ``"cm"``, ``"m"``).
        sync_pulse_us: Width of the D415 master's sync pulse (µs): a DAVIS reporting whole
            pulses (special type 4, stamped at the trailing edge) is moved back by it to the
            rising edge (the exposure start); rising-edge events (type 2) need no correction.
        sync_channel: Label of the Vicon analog channel carrying the D415 master's pulses (the
            sync box's toggle output: one edge per pulse, docs/wiring.md §7); matched exactly,
            else ignoring case. None: do not look for one (video clocks only).
        sync_latency_us: The wiring's delay from the master's pulse to the channel's edge (µs):
            the sync box's interrupt latency, ≈ 2 µs (assumed; measure it with a scope).
        slave_trigger_delay_us: A D415 slave's exposure start after the pulse (µs), for slaves
            mapped through the sync channel. Undocumented by Intel (realsense-d415.md §2.2);
            100 µs is the mock's assumption: measure it (LED flash test) for a real rig.
    """

    head_window_s: float = 2.2
    clock_method: Literal["reprojection", "claps+speed"] = "reprojection"
    max_marker_speed_m_s: float = 0.3
    min_area_ratio: float = 0.85
    extra_windows: tuple[float, ...] = (0.1, 0.33, 0.67, 0.9)
    static_tolerance_m: float = 0.003
    static_tolerance_px: float = 0.6
    min_static_frames: int = 5
    max_rms_px: float = MAX_RMS_PX
    min_inliers: int = 30
    force: bool = False
    cameras: tuple[str, ...] | None = None
    seed: int = 0
    unit: str | None = None
    sync_pulse_us: float = 50.0
    sync_channel: str | None = "D415_SYNC"
    sync_latency_us: float = 2.0
    slave_trigger_delay_us: float = 100.0

    def __post_init__(self) -> None:
        check_positive(self.head_window_s, name="head_window_s")
        check_positive(self.sync_pulse_us, name="sync_pulse_us")
        for name in ("sync_latency_us", "slave_trigger_delay_us"):
            if not math.isfinite(getattr(self, name)):
                msg = f"{name} must be a finite number of µs, got {getattr(self, name)!r}"
                raise ValidationError(msg)
        check_positive(self.static_tolerance_m, name="static_tolerance_m")
        check_positive(self.static_tolerance_px, name="static_tolerance_px")
        check_positive(self.max_rms_px, name="max_rms_px")


@dataclass(frozen=True, slots=True)
class ViconStatic:
    """The Vicon trial's static start.

    Attributes:
        labels: Marker labels (M).
        cloud_m: ``(M, 3)`` median positions over the still frames (m); NaN if never seen.
        n_frames: Still frames used.
        t_vicon_ns: ``(F,)`` Vicon-clock time of every frame of the trial (ns).
        extent_m: Bounding-box diagonal of the still cloud (m).
    """

    labels: tuple[str, ...]
    cloud_m: F64 = field(repr=False)
    n_frames: int
    t_vicon_ns: npt.NDArray[np.int64] = field(repr=False)
    extent_m: float


@dataclass(frozen=True, slots=True)
class ViconCalibrationResult:
    """What :func:`calibrate_vicon` found, with diagnostics for the report.

    Attributes:
        calibration: The calibration (cameras with residual statistics, clock mappings).
        registrations: Per camera label, the registration (coarse and final pose, observations).
        static_frames: Per camera label, the number of still D415 frames used.
        vicon: The Vicon static start.
        refused: Cameras above the thresholds (written anyway because ``force`` was set).
        notes: Human-readable remarks (what was not done and why).
        vicon_claps: The claps found in the Vicon trial (for the report).
        clock_fits: Per camera, the reprojection clock's stretches: device times (ns), offsets
            (ns) and their 1σ (ns) (for the report).
    """

    calibration: Calibration
    registrations: Mapping[str, CameraRegistration] = field(repr=False)
    static_frames: Mapping[str, int]
    vicon: ViconStatic = field(repr=False)
    refused: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()
    vicon_claps: tuple[ClapDetection, ...] = field(default=(), repr=False)
    clock_fits: Mapping[str, tuple[F64, F64, F64]] = field(default_factory=dict, repr=False)

    def summary(self) -> dict[str, Any]:
        """Plain JSON-able figures (``--json``)."""
        cams = []
        for c in self.calibration.cameras:
            cams.append(
                {
                    "name": c.name,
                    "serial": c.serial,
                    "static_frames": self.static_frames.get(c.name, 0),
                    **dict(c.residuals),
                    "camera_centre_m": c.T_world_cam[:3, 3].tolist(),
                }
            )
        clocks = [
            {
                "device": k.device,
                "offset_ns": k.offset_ns,
                "drift_ppm": k.drift_ppm,
                "offset_sigma_ns": k.offset_sigma_ns,
                "method": k.method,
            }
            for k in self.calibration.clocks
        ]
        return {
            "cameras": cams,
            "clocks": clocks,
            "vicon_static_frames": self.vicon.n_frames,
            "refused": list(self.refused),
            "notes": list(self.notes),
            "statistics": dict(self.calibration.statistics),
        }


# --------------------------------------------------------------------------------------------
# Vicon
# --------------------------------------------------------------------------------------------


def vicon_static_start(
    positions_m: npt.ArrayLike,
    labels: Sequence[str],
    t_vicon_ns: npt.ArrayLike,
    *,
    tolerance_m: float = 0.003,
    min_frames: int = 5,
    source: str = "Vicon trial",
) -> ViconStatic:
    """The leading still frames of a trial and their median cloud.

    A frame is still while the 90th percentile of the markers' distances to the median of the
    first 5 frames stays below ``tolerance_m``.

    Raises:
        CalibrationError: the cloud's extent is implausible for a person in metres (wrong
            units), or fewer than ``min_frames`` still frames (no static start).
    """
    p = np.asarray(positions_m, dtype=np.float64)
    if p.ndim != 3 or p.shape[2] != 3 or p.shape[0] == 0:
        msg = f"{source}: expected (F, M, 3) marker positions, got {p.shape}"
        raise CalibrationError(msg)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN frames or markers
        head = np.nanmedian(p[: min(5, len(p))], axis=0)
        dist = np.linalg.norm(p - head, axis=2)
        p90 = np.nanpercentile(dist, 90, axis=1)
    still = np.isfinite(p90) & (p90 < tolerance_m)
    n = int(np.argmin(still)) if not still.all() else len(still)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        cloud = np.nanmedian(p[: max(n, 1)], axis=0)
    ok = np.isfinite(cloud).all(axis=1)
    extent = float(np.linalg.norm(np.ptp(cloud[ok], axis=0))) if ok.sum() >= 2 else 0.0
    if not (_MIN_EXTENT_M <= extent <= _MAX_EXTENT_M):
        msg = (
            f"{source}: the markers span {extent:.3g} m (bounding-box diagonal); a person in "
            f"metres spans {_MIN_EXTENT_M}–{_MAX_EXTENT_M} m, so the file's units are wrong "
            "(POINT:UNITS says one unit, the values are in another?); fix the file or pass the "
            "right unit (--unit)"
        )
        raise CalibrationError(msg)
    if n < min_frames:
        msg = (
            f"{source}: no static start: only {n} leading frames keep the markers within "
            f"{1e3 * tolerance_m:.0f} mm (need {min_frames}); the calibration needs the actor "
            "still (T-pose) for the first second"
        )
        raise CalibrationError(msg)
    return ViconStatic(
        labels=tuple(labels),
        cloud_m=cloud,
        n_frames=n,
        t_vicon_ns=np.asarray(t_vicon_ns, dtype=np.int64),
        extent_m=extent,
    )


# --------------------------------------------------------------------------------------------
# The pipeline
# --------------------------------------------------------------------------------------------


def _d415_static_frames(frames: Sequence[MarkerFrame], tolerance_px: float) -> tuple[int, int]:
    """(first, count) of the leading frames whose blobs stay within ``tolerance_px`` (median
    nearest-neighbour distance) of the first frame with ≥ 4 blobs."""
    from scipy.spatial import cKDTree

    k0 = 0
    while k0 < len(frames) and frames[k0].n_markers < 4:
        k0 += 1
    if k0 == len(frames):
        return 0, 0
    tree = cKDTree(frames[k0].uv_px)
    n = 1
    for f in frames[k0 + 1 :]:
        if f.n_markers == 0:
            break
        d, _ = tree.query(f.uv_px)
        if float(np.median(d)) > tolerance_px:
            break
        n += 1
    return k0, n


@dataclass(frozen=True, slots=True)
class _Cam:
    name: str
    serial: str
    width: int
    height: int
    K: F64
    dist: F64
    settings: D415Settings

    @property
    def device(self) -> DeviceId:
        return DeviceId("d415", self.serial)

    @property
    def sync_mode(self) -> int | None:
        """``inter_cam_sync_mode`` from the recording's metadata (None: unknown)."""
        mode = self.settings.sync_mode
        return None if mode is None else int(mode)

    @property
    def exposure_us(self) -> int | None:
        """Recorded manual exposure, µs (None: the recorder was not given the options)."""
        return None if self.settings.options is None else self.settings.options.exposure_us


def _cameras(rec: Recording, wanted: Sequence[str] | None, source: str) -> list[_Cam]:
    available = d415_devices(rec)
    try:
        names = [DeviceId.parse(c, kind="d415") for c in wanted] if wanted else available
    except ValidationError as err:
        msg = f"{source}: {err}"
        raise CalibrationError(msg) from err
    if not names:
        msg = f"{source}: the recording has no D415 stream (/d415/<serial>/ir)"
        raise CalibrationError(msg)
    out = []
    for dev in names:
        if dev not in available:
            have = [d.label for d in available]
            msg = f"{source}: no D415 {dev.label!r}; the recording has {have or 'none'}"
            raise CalibrationError(msg)
        d415 = RecordedD415(rec, dev)
        try:
            intr = d415.intrinsics()
            settings = d415.settings()
        except RecordingError as err:
            msg = f"{source}: {err}"
            raise CalibrationError(msg) from err
        out.append(
            _Cam(dev.label, dev.serial, intr.width, intr.height, intr.k, intr.distortion, settings)
        )
    return out


@dataclass(frozen=True, slots=True)
class _Probe:
    """The first frame of a camera at or after a log time."""

    log_ns: int
    dev_ns: int
    counter: int


def _unwrap_ns(stamp_us: int, anchor_us: int) -> int:
    """Device ns of a u32 µs stamp, taken at or after the camera's first stamp ``anchor_us``."""
    return unwrap_u32_from(stamp_us, anchor_us) * 1000


def _probe(rec: Recording, cam: _Cam, log_ns: int, anchor_us: int) -> _Probe | None:
    first = RecordedD415(rec, cam.device).frame_info_at(log_ns)
    if first is None:
        return None
    m_log_ns, fi = first
    if fi.sensor_timestamp_us is None:
        msg = (
            f"{rec.path}: {cam.name} frames have no device timestamps (no metadata); the "
            "calibration needs the D415 hardware clock"
        )
        raise CalibrationError(msg)
    return _Probe(m_log_ns, _unwrap_ns(int(fi.sensor_timestamp_us), anchor_us), fi.frame_counter)


def _log_at(
    rec: Recording, cam: _Cam, dev_ns: int, first: _Probe, end_log: int, anchor_us: int
) -> tuple[int, int]:
    """(log time of the last frame before ``dev_ns``, of the first frame at or after it), by
    bisection over the host log time (which in a simulated recording is not proportional to
    device time, so no rate is assumed)."""
    lo, hi = first, None
    lo_log, hi_log = first.log_ns, end_log
    if first.dev_ns >= dev_ns:
        return first.log_ns, first.log_ns
    while hi_log - lo_log > 1:
        mid = (lo_log + hi_log) // 2
        p = _probe(rec, cam, mid, anchor_us)
        if p is None or p.dev_ns >= dev_ns:
            hi, hi_log = p, mid
            if p is not None and p.counter - lo.counter <= 1:
                break
        else:
            lo, lo_log = p, p.log_ns
    return lo.log_ns, (hi.log_ns if hi is not None else end_log)


def _read_frames(
    rec: Recording,
    cams: Sequence[_Cam],
    log_lo: int,
    log_hi: int,
    dev_windows: Mapping[str, tuple[int, int]],
    anchors: Mapping[str, int],
) -> dict[str, list[MarkerFrame]]:
    """Measure the D415 frames with messages in ``[log_lo, log_hi]`` whose device time lies in
    their camera's ``dev_windows`` entry; one pass over the recording's chunks for all cameras."""
    from mocaprig.calib.markers import measure_frame

    by_device = {c.device: c for c in cams}
    out: dict[str, list[MarkerFrame]] = {c.name: [] for c in cams}
    for rfs in read_frame_sets(rec, list(by_device), start_ns=log_lo, end_ns=log_hi + 1):
        fs = rfs.frames
        cam = by_device[DeviceId("d415", fs.serial)]
        stamp_us = fs.timing.sensor_timestamp_us
        if stamp_us is None:
            continue
        t_dev = _unwrap_ns(int(stamp_us), anchors[cam.name])
        lo, hi = dev_windows[cam.name]
        if not lo <= t_dev < hi:
            continue
        mf = measure_frame(
            fs.infrared.image,
            fs.depth.image,
            cam.K,
            depth_scale_m=fs.depth_scale_m,
            camera=cam.name,
            t_dev_ns=t_dev,
            frame_counter=int(fs.timing.frame_counter),
            distortion=cam.dist,
        )
        out[cam.name].append(mf)
    for frames in out.values():
        frames.sort(key=lambda f: f.t_dev_ns)
    return out


def _read_device_window(
    rec: Recording,
    cams: Sequence[_Cam],
    dev_windows: Mapping[str, tuple[int, int]],
    firsts: Mapping[str, _Probe],
    end_log: int,
) -> dict[str, list[MarkerFrame]]:
    """Frames of each camera in its device-time window, reading the union of their log ranges."""
    anchors = {c.name: firsts[c.name].dev_ns // 1000 for c in cams}
    lo_log, hi_log = None, None
    for c in cams:
        lo, hi = dev_windows[c.name]
        a, _ = _log_at(rec, c, lo, firsts[c.name], end_log, anchors[c.name])
        _, b = _log_at(rec, c, hi, firsts[c.name], end_log, anchors[c.name])
        lo_log = a if lo_log is None else min(lo_log, a)
        hi_log = b if hi_log is None else max(hi_log, b)
    if lo_log is None or hi_log is None:
        return {c.name: [] for c in cams}
    return _read_frames(rec, cams, lo_log, hi_log, dev_windows, anchors)


class _ViconInterp:
    """Vicon marker positions at Vicon-clock times: cubic (Catmull–Rom) between frames, linear
    next to a gap, NaN inside gaps and outside the trial."""

    def __init__(self, t_ns: I64, positions_m: F64) -> None:
        self.t = t_ns.astype(np.float64)
        self.p = positions_m

    def at(self, t_ns: npt.ArrayLike) -> F64:
        t = np.asarray(t_ns, dtype=np.float64)
        n = len(self.t)
        i = np.clip(np.searchsorted(self.t, t) - 1, 0, n - 2)
        u = ((t - self.t[i]) / (self.t[i + 1] - self.t[i]))[:, None, None]
        p0 = self.p[np.maximum(i - 1, 0)]
        p1 = self.p[i]
        p2 = self.p[i + 1]
        p3 = self.p[np.minimum(i + 2, n - 1)]
        linear = (1.0 - u) * p1 + u * p2
        cubic = 0.5 * (
            2.0 * p1
            + (p2 - p0) * u
            + (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3) * u**2
            + (3.0 * p1 - p0 - 3.0 * p2 + p3) * u**3
        )
        out: F64 = np.where(np.isfinite(cubic), cubic, linear)
        outside = (t < self.t[0]) | (t > self.t[-1])
        out[outside] = np.nan
        return out


def _project_frames(frames: Sequence[MarkerFrame], ref: F64, T: F64, cam: _Cam) -> F64:
    uv, _ = project_points(ref.reshape(-1, 3), T, cam.K, cam.dist)
    out: F64 = uv.reshape(len(frames), -1, 2)
    return out


def _reprojection_cost(
    frames: Sequence[MarkerFrame],
    T: F64,
    cam: _Cam,
    vicon: _ViconInterp,
    t_vicon_ns: npt.ArrayLike,
    *,
    gate_px: float,
) -> float:
    """Truncated reprojection cost (px²) of the frames' blobs against the Vicon markers
    interpolated at the frames' Vicon times: each blob's distance to the nearest projected
    marker, capped at ``gate_px``."""
    from scipy.spatial import cKDTree

    uv = _project_frames(frames, vicon.at(np.asarray(t_vicon_ns, dtype=np.int64)), T, cam)
    total = 0.0
    for i, f in enumerate(frames):
        ok = np.isfinite(uv[i]).all(axis=1)
        if ok.any():
            d, _ = cKDTree(uv[i][ok]).query(f.uv_px, distance_upper_bound=gate_px)
            total += float((np.minimum(d, gate_px) ** 2).sum())
        else:
            total += gate_px**2 * f.n_markers
    return total


def _grid_offset(
    frames: Sequence[MarkerFrame],
    T: F64,
    cam: _Cam,
    vicon: _ViconInterp,
    prior_ns: int,
    *,
    half_width_ns: int,
    step_ns: int,
    gate_px: float = 3.0,
) -> int:
    """The device → Vicon offset (ns) minimising the truncated reprojection cost: a coarse grid
    (5 × ``step_ns``, gate 2 × ``gate_px``) over ±``half_width_ns``, then ``step_ns`` around
    the coarse minimum."""

    t_dev = np.array([f.t_dev_ns for f in frames], dtype=np.int64)
    used = [k for k, f in enumerate(frames) if f.n_markers > 0]
    sub = [frames[k] for k in used]

    def cost(delta: int, gate: float) -> float:
        return _reprojection_cost(sub, T, cam, vicon, t_dev[used] + delta, gate_px=gate)

    if not used:
        return prior_ns
    coarse = 5 * step_ns
    grid = range(prior_ns - half_width_ns, prior_ns + half_width_ns + 1, coarse)
    best = min(grid, key=lambda d: cost(d, 2.0 * gate_px))
    fine = range(best - coarse, best + coarse + 1, step_ns)
    return min(fine, key=lambda d: cost(d, gate_px))


def _fit_offset(
    frames: Sequence[MarkerFrame],
    T: F64,
    cam: _Cam,
    vicon: _ViconInterp,
    delta0_ns: int,
    *,
    gate_px: float = 3.0,
) -> tuple[float, float, int]:
    """Continuous device → Vicon offset over frames: matched blobs, soft-L1 least squares over
    the offset (ms). Returns (offset ns, 1σ ns, pairs); σ is inf without motion."""
    from scipy.optimize import least_squares

    from mocaprig.calib.registration import match_markers

    t_dev = np.array([f.t_dev_ns for f in frames], dtype=np.float64)
    delta = float(delta0_ns)
    sigma, n_pairs = math.inf, 0
    for _ in range(2):
        uv = _project_frames(frames, vicon.at(t_dev + delta), T, cam)
        rows: list[tuple[int, int, int]] = []
        for k, f in enumerate(frames):
            i, j = match_markers(f.uv_px, uv[k], gate_m=gate_px)
            rows.extend((k, int(a), int(b)) for a, b in zip(i, j, strict=True))
        if len(rows) < 6:
            return delta, math.inf, len(rows)
        fk = np.array([r[0] for r in rows])
        bi = np.array([r[1] for r in rows])
        mj = np.array([r[2] for r in rows])
        obs = np.stack([frames[k].uv_px[b] for k, b in zip(fk, bi, strict=True)])

        base = delta

        def residuals(x: F64, fk: npt.NDArray[np.int_] = fk, mj: npt.NDArray[np.int_] = mj,
                      obs: F64 = obs, base: float = base) -> F64:  # fmt: skip
            # x: correction to ``base`` in ms (a small number: finite differences stay sane).
            ref = vicon.at(t_dev[fk] + base + x[0] * 1e6)
            pts = ref[np.arange(len(fk)), mj]
            uvp, _ = project_points(pts, T, cam.K, cam.dist)
            r: F64 = np.nan_to_num(uvp - obs, nan=50.0).ravel()
            return r

        sol = least_squares(residuals, [0.0], loss="soft_l1", f_scale=1.0, diff_step=1e-2)
        delta = base + float(sol.x[0] * 1e6)
        n_pairs = len(rows)
        jtj = float(sol.jac[:, 0] @ sol.jac[:, 0])
        s2 = float(np.mean(sol.fun**2))
        sigma = math.sqrt(s2 / jtj) * 1e6 if jtj > 0 else math.inf
    return delta, sigma, n_pairs


@dataclass(frozen=True, slots=True)
class _DavisPulses:
    """A DAVIS's external-input edges and the D415 master they come from."""

    device: str
    edges_ns: I64
    master: str | None
    frame_delay_ns: int
    note: str = ""


def _davis_pulse_inputs(
    rec: Recording, cams: Sequence[_Cam], sync_pulse_us: float
) -> list[_DavisPulses]:
    """The rising edges of every DAVIS's external input (DAVIS ns since its last timestamp
    reset) and the D415 sync master (``sync_mode`` 1 in its device metadata) whose exposure
    starts they mark, with that master's frame delay (half its exposure: a D415 stamps frames
    mid-exposure). Rising-edge events (type 2) are used as they are; whole pulses (type 4,
    stamped at the trailing edge) are moved back by ``sync_pulse_us``."""

    master, delay, why = None, 0, ""
    for cam in cams:
        if cam.sync_mode == 1:
            master = cam.name
            if cam.exposure_us is None:
                master, why = None, f"{cam.name}'s metadata has no options.exposure_us"
            else:
                delay = round(float(cam.exposure_us) * 500.0)
            break
    else:
        why = "no calibrated D415 is the sync master (device metadata sync_mode = 1)"
    out = []
    for dev in davis_devices(rec):
        davis = RecordedDavis(rec, dev)
        if not davis.has("trigger"):
            continue
        edges, none_why = davis.external_edges_ns(pulse_us=sync_pulse_us)
        note = why
        if not edges.size and not note:
            note = none_why
        out.append(_DavisPulses(dev.label, edges, master, delay, note))
    return out


def _davis_clock(
    pulses: _DavisPulses, master_first_ns: int, master_frames_ns: I64, master_map: ClockMapping
) -> ClockMapping:
    """The DAVIS → Vicon mapping through the master's pulses.

    Pairing prior (a periodic train pairs equally well at every whole-period shift): the DAVIS's
    first edge after its timestamp reset is the master's first recorded frame. That holds when
    the DAVIS was reset and listening before the master's pulse train began (the recorder
    starts the DAVIS first; the simulated rig resets it at session time 0 and starts the D415s
    then) and is checked: the first edge must come ≥ 1.5 periods after the reset, else the
    train was already running and the pairing is refused.

    Raises:
        CalibrationError: too few edges or frames, the train already running at the reset, or
            a failed pulse fit (from ``clock_from_pulses``).
    """
    from mocaprig.calib.time_align import clock_from_pulses

    edges = pulses.edges_ns
    if edges.size < 10 or master_frames_ns.size < 10:
        msg = (
            f"cannot map {pulses.device} by pulses: {edges.size} external-input edges and "
            f"{master_frames_ns.size} master frames; need 10 of each (is the D415 master's sync "
            "output wired to the DAVIS trigger input, with edge or pulse detection on?)"
        )
        raise CalibrationError(msg)
    period = float(np.median(np.diff(edges)))
    if edges[0] < 1.5 * period:
        msg = (
            f"cannot map {pulses.device} by pulses: its first edge comes {edges[0] / 1e6:.1f} ms "
            f"after its timestamp reset (< 1.5 periods of {period / 1e6:.1f} ms), so the pulse "
            "train was already running and which pulse is which frame is unknown; start the "
            "DAVIS (timestamp reset) before the D415 master streams"
        )
        raise CalibrationError(msg)
    prior = int(master_first_ns - pulses.frame_delay_ns - int(edges[0]))
    return clock_from_pulses(
        pulses.device,
        edges,
        master_frames_ns,
        d415_mapping=master_map,
        frame_delay_ns=pulses.frame_delay_ns,
        prior_offset_ns=prior,
    )


@dataclass(frozen=True, slots=True)
class _SyncInputs:
    """The Vicon sync channel's edges and the D415 master they come from (or why not)."""

    edges: SyncEdges | None
    master: str | None = None
    master_frames_ns: I64 = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    frame_delay_ns: int = 0
    delays_ns: Mapping[str, float] = field(default_factory=dict)
    note: str = ""


def _sync_channel_edges(vicon_path: Path, opt: CalibrationOptions) -> tuple[SyncEdges | None, str]:
    """The edges of the Vicon trial's sync channel (Vicon clock), or ``None`` and a note saying
    why not (option off, no analog section or no such channel, unreadable or flat channel)."""
    from mocaprig.calib.time_align import analog_times_ns, find_sync_edges
    from mocaprig.calib.vicon import ViconFileError, read_c3d_analogs

    label = opt.sync_channel
    fallback = "the D415 clocks come from the video"
    if label is None:
        return None, f"clock: sync channel not used (option); {fallback}"
    if vicon_path.suffix.lower() == ".csv":
        return None, (
            f"clock: a Nexus CSV export holds no analog channel (export the trial as C3D to use "
            f"the sync channel {label!r}); {fallback}"
        )
    try:
        analogs = read_c3d_analogs(vicon_path)
    except ViconFileError as err:
        return None, f"clock: no sync channel: {err}; {fallback}"
    try:
        values = analogs.channel(label)
    except ValidationError as err:
        return None, (
            f"clock: {err}; {fallback} (drift good to ~10 ppm only: record the sync box's "
            "toggle output on a Vicon analog input, docs/wiring.md §7)"
        )
    name = analogs.labels[analogs.index(label)]
    try:
        return find_sync_edges(analog_times_ns(analogs), values, channel=name), ""
    except CalibrationError as err:
        return None, f"clock: {err}; {fallback}"


def _sync_channel_inputs(
    vicon_path: Path,
    rec: Recording,
    cams: Sequence[_Cam],
    frames_ns: Mapping[str, I64],
    opt: CalibrationOptions,
) -> _SyncInputs:
    """The sync channel's edges (:func:`_sync_channel_edges`), the master's frame stamps (those
    of the frames read for the calibration: the windows spread over the session pin the line
    to well under a µs and 0.1 ppm, and reading every ``frame_info`` would decompress the
    whole recording), its frame delay (half its exposure: pulse at the exposure start, stamp
    mid-exposure) and, per other camera, its exposure's delay after the master's
    (``slave_trigger_delay_us`` plus half the exposure difference). A missing or unusable
    channel gives ``edges=None`` and a note saying why."""
    fallback = "the D415 clocks come from the video"
    edges, note = _sync_channel_edges(vicon_path, opt)
    if edges is None:
        return _SyncInputs(None, note=note)
    name = edges.channel
    master = next((c for c in cams if c.sync_mode == 1), None)
    if master is None:
        return _SyncInputs(
            None,
            note=(
                f"clock: sync channel {name!r} found but no calibrated D415 was recorded as the "
                f"sync master (sync_mode 1); {fallback}"
            ),
        )

    def exposure_ns(c: _Cam) -> float | None:
        return None if c.exposure_us is None else float(c.exposure_us) * 1e3

    exp_m = exposure_ns(master)
    if exp_m is None:
        return _SyncInputs(
            None,
            note=f"clock: {master.name}'s metadata has no options.exposure_us; {fallback}",
        )
    delays = {}
    for c in cams:
        if c is master:
            continue
        exp_c = exposure_ns(c)
        delays[c.name] = opt.slave_trigger_delay_us * 1e3 + 0.5 * ((exp_c or exp_m) - exp_m)
    return _SyncInputs(
        edges,
        master.name,
        np.unique(np.asarray(frames_ns[master.name], dtype=np.int64)),
        round(0.5 * exp_m),
        delays,
    )


#: Whole edge periods tried either side of a sync-channel mapping (see :func:`_sync_clocks`).
_SYNC_PERIOD_SHIFTS: Final = 3


def _sync_clocks(
    sync: _SyncInputs,
    mappings: Mapping[str, ClockMapping],
    ties: Mapping[str, _Tie],
    opt: CalibrationOptions,
    score: Callable[[str, ClockMapping], float] | None = None,
) -> tuple[dict[str, ClockMapping], list[str]]:
    """The D415 clocks from the sync channel: the master's by its edges (the video mapping as
    the pairing prior), every camera tied to the pool's pivot (``ties``, from
    :func:`_pooled_clocks`) through its tie, the master's tie inverted and the master's mapping,
    plus its exposure's delay after the master's. Cameras without a tie keep ``mappings``
    (video), and so does every camera when the master's fit fails; notes say so.

    The edges fix each clock only up to whole periods (a periodic train pairs as well one edge
    over): when the video prior is off by more than a quarter period (on the 30 s seed-11
    session the master's pooled video clock was 41 ms off), or a tie's counter shift is one
    frame off, the mapping is a whole period out. So each camera's mapping is moved by the
    number of edge periods (±:data:`_SYNC_PERIOD_SHIFTS`) whose ``score`` (the reprojection cost
    of its frames) is lowest; no move on a tie."""
    from mocaprig.calib.time_align import clock_from_sync_edges

    out = dict(mappings)
    m, edges = sync.master, sync.edges
    if m is None or edges is None or m not in mappings:
        return out, []
    period = float(np.median(np.diff(np.sort(edges.t_ns)))) if edges.count > 1 else 0.0
    moved: list[str] = []

    def best_period(name: str, mapping: ClockMapping) -> ClockMapping:
        if score is None or not period > 0:
            return mapping
        cands = [
            dataclasses.replace(mapping, offset_ns=mapping.offset_ns + round(k * period))
            for k in range(-_SYNC_PERIOD_SHIFTS, _SYNC_PERIOD_SHIFTS + 1)
        ]
        costs = [score(name, c) for c in cands]
        k = int(np.argmin(costs))
        if costs[k] < 0.99 * costs[_SYNC_PERIOD_SHIFTS]:
            shift = k - _SYNC_PERIOD_SHIFTS
            moved.append(f"{name} {shift:+d}")
            _log.info("%s: sync clock moved by %+d edge periods (reprojection cost)", name, shift)
            return cands[k]
        return mapping

    try:
        mmap = clock_from_sync_edges(
            m,
            edges,
            sync.master_frames_ns,
            prior=mappings[m],
            frame_delay_ns=sync.frame_delay_ns,
            edge_delay_ns=round(opt.sync_latency_us * 1e3),
        )
    except CalibrationError as err:
        _log.warning("%s", err)
        return out, [f"clock: {err}; the D415 clocks come from the video"]
    mmap = best_period(m, mmap)
    out[m] = mmap
    done = [m]
    tm = ties.get(m)
    if tm is not None and len(ties) >= 2:
        # The pivot's clock → the master's (its tie inverted) → Vicon (the sync line).
        anchor_p = mmap.anchor_ns + tm.a_ns + tm.s * (mmap.anchor_ns - tm.centre_ns)
        pivot_map = ClockMapping(
            device="pivot",
            reference=mmap.reference,
            offset_ns=round(mmap.anchor_ns + mmap.offset_ns - anchor_p),
            drift_ppm=((1.0 + mmap.drift_ppm * 1e-6) / (1.0 + tm.s) - 1.0) * 1e6,
            anchor_ns=round(anchor_p),
            drift_sigma_ppm=mmap.drift_sigma_ppm,
        )
        for c, tie in ties.items():
            if c == m or c not in out:
                continue
            mc = _through_tie(
                c,
                tie,
                pivot_map,
                delay_ns=sync.delays_ns.get(c, 0.0),
                method=f"{mmap.method} via {m} (frame tie)",
            )
            sigma = math.hypot(
                mmap.offset_sigma_ns,
                tie.rms_ns / math.sqrt(max(tie.pairs, 1)),
                tm.rms_ns / math.sqrt(max(tm.pairs, 1)),
            )
            out[c] = best_period(c, dataclasses.replace(mc, offset_sigma_ns=sigma))
            done.append(c)
    notes = [
        f"clock: {m} from the Vicon sync channel {edges.channel!r} ({edges.count} edges, "
        f"τ {edges.tau_ns / 1e3:.0f} µs; ±{mmap.offset_sigma_ns / 1e3:.1f} µs, "
        f"±{mmap.drift_sigma_ppm:.3f} ppm)"
        + (f", {len(done) - 1} more D415 through their frame ties" if len(done) > 1 else "")
    ]
    if moved:
        notes.append(
            "clock: whole edge periods chosen by the reprojection cost (the video prior or a "
            f"frame tie was a period out): {', '.join(moved)}"
        )
    for c in mappings:
        if c not in done:
            notes.append(f"{c}: video clock: it is not tied to {m}'s frames")
    # Cross-check against the video clocks (a wrong trigger delay or tie shows here).
    diffs = []
    for c in done:
        t = np.array([out[c].anchor_ns], dtype=np.int64)
        d_us = float(out[c].to_reference_ns(t)[0] - mappings[c].to_reference_ns(t)[0]) / 1e3
        diffs.append(f"{c} {d_us:+.0f} µs / {out[c].drift_ppm - mappings[c].drift_ppm:+.1f} ppm")
    notes.append("clock: sync channel minus video clock: " + "; ".join(diffs))
    return out, notes


def _merge_windows(windows: Sequence[tuple[int, int]]) -> list[tuple[int, int]]:
    out: list[tuple[int, int]] = []
    for lo, hi in sorted(windows):
        if out and lo <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], hi))
        else:
            out.append((lo, hi))
    return out


def calibrate_vicon(
    session_mcap: str | Path,
    vicon_c3d: str | Path,
    *,
    options: CalibrationOptions | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ViconCalibrationResult:
    """Calibrate the D415s of a recording against a Vicon trial of the same session.

    Args:
        session_mcap: The recording (``mocaprig record``).
        vicon_c3d: The Vicon trial (C3D or Nexus CSV).
        options: :class:`CalibrationOptions`.
        progress: Optional ``(done, total)`` callback.

    Returns:
        The calibration and its diagnostics.

    Raises:
        CalibrationError: unreadable inputs, wrong units, no static start, no clap, too few
            markers, no alignment, or (without ``force``) a camera above the residual
            thresholds; the message names the camera and the cause.
    """
    from mocaprig.calib.time_align import find_claps_vicon, vicon_times_ns
    from mocaprig.calib.vicon import read_trajectories

    opt = options or CalibrationOptions()
    steps = 7
    done = 0

    def tick() -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, steps)

    traj = read_trajectories(vicon_c3d, unit=opt.unit)
    t_vicon = vicon_times_ns(traj)
    vicon = vicon_static_start(
        traj.positions_m,
        traj.labels,
        t_vicon,
        tolerance_m=opt.static_tolerance_m,
        source=str(vicon_c3d),
    )
    vicon_claps = find_claps_vicon(traj)
    interp = _ViconInterp(t_vicon, traj.positions_m)
    tick()
    _log.info(
        "Vicon: %d still frames, %d markers, claps at %s s (Vicon clock)",
        vicon.n_frames,
        len(vicon.labels),
        [round(c.t_ns * 1e-9, 3) for c in vicon_claps],
    )
    try:
        rec = Recording(Path(session_mcap))
    except RecordingError as err:
        msg = f"cannot read the recording {session_mcap}: {err}"
        raise CalibrationError(msg) from err
    registrations: dict[str, CameraRegistration] = {}
    static_frames: dict[str, int] = {}
    clock_fits: dict[str, tuple[F64, F64, F64]] = {}
    clocks: list[ClockMapping] = []
    notes: list[str] = []
    with rec:
        cams = _cameras(rec, opt.cameras, str(session_mcap))
        fi_topics = [c.device.topic("frame_info") for c in cams]
        missing = [c.name for c in cams if c.device.topic("frame_info") not in rec.channels]
        if missing:
            msg = f"{session_mcap}: {missing[0]} has no frames (no frame_info stream)"
            raise CalibrationError(msg)
        first_msg = next(iter(rec.messages(fi_topics)), None)
        if first_msg is None:
            msg = f"{session_mcap}: the D415 streams hold no frames"
            raise CalibrationError(msg)
        end_log = first_msg.log_time_ns + 1
        while next(iter(rec.messages(fi_topics, start_ns=end_log)), None) is not None:
            end_log = first_msg.log_time_ns + 2 * (end_log - first_msg.log_time_ns)
        firsts: dict[str, _Probe] = {}
        for c in cams:
            fi = RecordedD415(rec, c.device).frame_info_at()
            p = None if fi is None else _probe(rec, c, fi[0], 0)
            if p is None:
                msg = f"{session_mcap}: {c.name} has no frames"
                raise CalibrationError(msg)
            firsts[c.name] = _Probe(p.log_ns, p.dev_ns, p.counter)
        head_ns = round(opt.head_window_s * 1e9)
        head_windows = {c: (p.dev_ns, p.dev_ns + head_ns) for c, p in firsts.items()}
        head = _read_device_window(rec, cams, head_windows, firsts, end_log)
        tick()
        poses: dict[str, F64] = {}
        deltas: dict[str, int] = {}
        t_onset_v = int(t_vicon[min(vicon.n_frames, len(t_vicon) - 1)])
        for cam in cams:
            frames = head[cam.name]
            k0, n_still = _d415_static_frames(frames, opt.static_tolerance_px)
            if n_still < opt.min_static_frames:
                msg = (
                    f"{cam.name}: no static start: {n_still} leading frames keep their blobs "
                    f"within {opt.static_tolerance_px} px (need {opt.min_static_frames}; "
                    f"{len(frames)} frames in the first {opt.head_window_s:g} s, "
                    f"{max((f.n_markers for f in frames), default=0)} blobs at most); the "
                    "actor must stand still for the first second"
                )
                raise CalibrationError(msg)
            still = frames[k0 : k0 + n_still]
            static_frames[cam.name] = n_still
            reg = register_camera(
                [f.uv_px for f in still],
                [f.xyz_cam_m for f in still],
                [vicon.cloud_m] * len(still),
                K=cam.K,
                distortion=cam.dist,
                name=cam.name,
                static_reference_m=vicon.cloud_m,
                seed=opt.seed,
            )
            registrations[cam.name] = reg
            poses[cam.name] = reg.T_world_cam
            # Coarse clock: the motion onsets of both, then the reprojection cost on a grid.
            onset_d = frames[min(k0 + n_still, len(frames) - 1)].t_dev_ns
            prior = t_onset_v - onset_d
            deltas[cam.name] = _grid_offset(
                frames, reg.T_world_cam, cam, interp, prior,
                half_width_ns=200_000_000, step_ns=2_000_000,
            )  # fmt: skip
        tick()
        # Windows with motion across the session, in Vicon time, then per camera device time.
        v_first = t_vicon[0]
        span_ns = int(t_vicon[-1] - v_first)  # ≈ the session
        windows_v = [(c.t_ns - 800_000_000, c.t_ns + 400_000_000) for c in vicon_claps]
        for frac in opt.extra_windows:
            mid = int(v_first) + round(frac * span_ns)
            windows_v.append((mid - 300_000_000, mid + 300_000_000))
        frames_all: dict[str, list[MarkerFrame]] = {c.name: list(head[c.name]) for c in cams}
        for lo_v, hi_v in _merge_windows(windows_v):
            dev_windows = {}
            for c in cams:
                lo = max(lo_v - deltas[c.name], head_windows[c.name][1])
                dev_windows[c.name] = (lo, max(lo, hi_v - deltas[c.name]))
            if all(lo >= hi for lo, hi in dev_windows.values()):
                continue
            got = _read_device_window(rec, cams, dev_windows, firsts, end_log)
            for c in cams:
                frames_all[c.name].extend(got[c.name])
        davis_inputs = _davis_pulse_inputs(rec, cams, opt.sync_pulse_us)
        sync = _sync_channel_inputs(
            Path(vicon_c3d),
            rec,
            cams,
            {c: np.array([f.t_dev_ns for f in fr], dtype=np.int64) for c, fr in frames_all.items()},
            opt,
        )
        tick()
    # Clocks and final poses, iterated twice: per-camera stretch offsets, then one pooled clock
    # line for the hardware-synchronised cameras, then each camera's bundle adjustment.
    mappings: dict[str, ClockMapping] = {}
    by_name = {c.name: c for c in cams}

    def shift_cost(name: str, m: ClockMapping) -> float:
        # Reprojection cost of every third frame read, at the Vicon times m gives them.
        fr = frames_all[name][::3]
        t_ref = m.to_reference_ns(np.array([f.t_dev_ns for f in fr], dtype=np.int64))
        return _reprojection_cost(fr, poses[name], by_name[name], interp, t_ref, gate_px=3.0)

    # The frames read do not change between the two passes.
    stamps = {
        c.name: np.array([f.t_dev_ns for f in frames_all[c.name]], dtype=np.int64) for c in cams
    }
    counters = {
        c.name: np.array([f.frame_counter for f in frames_all[c.name]], dtype=np.int64)
        for c in cams
    }
    ties: dict[str, _Tie] = {}
    for _ in range(2):
        own: dict[str, ClockMapping] = {}
        for cam in cams:
            t_w, d_w, s_w = _stretch_offsets(
                cam, frames_all[cam.name], poses[cam.name], interp, deltas[cam.name],
                mappings.get(cam.name),
            )  # fmt: skip
            clock_fits[cam.name] = (t_w, d_w, s_w)
            own[cam.name] = _line_clock(cam.name, t_w, d_w, s_w)
        mappings, pool_notes = _pooled_clocks(
            {c.name: (stamps[c.name], counters[c.name]) for c in cams},
            clock_fits,
            own,
            shift_cost,
            {c.name: c.sync_mode for c in cams},
            ties_out=ties,
        )
        video = mappings
        mappings, sync_notes = _sync_clocks(sync, video, ties, opt, shift_cost)
        for cam in cams:
            if opt.clock_method == "claps+speed" and mappings[cam.name] is video[cam.name]:
                mappings[cam.name] = _time_align_clock(
                    cam.name, frames_all[cam.name], vicon_claps, traj, mappings[cam.name]
                )
            frames = frames_all[cam.name]
            t_ref = mappings[cam.name].to_reference_ns(stamps[cam.name])
            refs = interp.at(t_ref)
            # Fast markers carry the clock's error into the pose (1 ms at 1 m/s = 1 mm): the
            # final bundle adjustment uses the markers slower than opt.max_marker_speed_m_s.
            step = 5_000_000
            speed = np.linalg.norm(interp.at(t_ref + step) - interp.at(t_ref - step), axis=2)
            refs[speed / (2 * step * 1e-9) > opt.max_marker_speed_m_s] = np.nan
            reg = register_camera(
                [f.uv_px for f in frames],
                [f.xyz_cam_m for f in frames],
                list(refs),
                K=cam.K,
                distortion=cam.dist,
                name=cam.name,
                T_world_cam_init=poses[cam.name],
                gates_px=(4.0, 2.5),
                areas_px_frames=[f.area_px for f in frames] if opt.min_area_ratio > 0 else None,
                min_area_ratio=opt.min_area_ratio,
            )
            poses[cam.name] = reg.T_world_cam
            registrations[cam.name] = dataclasses.replace(
                reg, T_world_cam_coarse=registrations[cam.name].T_world_cam_coarse,
                coarse_inliers=registrations[cam.name].coarse_inliers,
                coarse_rms_m=registrations[cam.name].coarse_rms_m,
            )  # fmt: skip
    notes.extend(pool_notes)
    notes.extend([sync.note] if sync.note else sync_notes)
    clocks.extend(mappings[c.name] for c in cams)
    tick()
    refused = tuple(
        name
        for name, r in registrations.items()
        if r.bundle.reprojection_rms_px > opt.max_rms_px or r.bundle.n_inliers < opt.min_inliers
    )
    if refused and not opt.force:
        figures = "; ".join(
            f"{n}: {registrations[n].bundle.reprojection_rms_px:.2f} px RMS, "
            f"{registrations[n].bundle.n_inliers} inliers"
            for n in refused
        )
        msg = (
            f"refusing the calibration: {figures} (thresholds: RMS ≤ {opt.max_rms_px} px, "
            f"≥ {opt.min_inliers} inliers); check the markers and the Vicon file, or pass "
            "--force to write it anyway"
        )
        raise CalibrationError(msg)
    cameras = []
    for cam in cams:
        reg = registrations[cam.name]
        stats = reg.residual_statistics()
        k = next(c for c in clocks if c.device == cam.name)
        stats["clock_offset_sigma_ns"] = k.offset_sigma_ns
        stats = {key: v for key, v in stats.items() if math.isfinite(v)}
        cameras.append(
            CameraCalibration(
                name=cam.name,
                kind="d415",
                serial=cam.serial,
                width=cam.width,
                height=cam.height,
                K=cam.K,
                distortion=cam.dist,
                T_world_cam=reg.T_world_cam,
                residuals=stats,
                source="vicon",
            )
        )
    for dp in davis_inputs:
        master_map = next((k for k in clocks if k.device == dp.master), None)
        if dp.master is None or master_map is None or dp.note:
            notes.append(f"{dp.device}: no clock mapping: {dp.note}")
            continue
        try:
            dmap = _davis_clock(
                dp,
                firsts[dp.master].dev_ns,
                np.unique(np.array([f.t_dev_ns for f in frames_all[dp.master]], dtype=np.int64)),
                master_map,
            )
        except CalibrationError as err:
            notes.append(f"{dp.device}: no clock mapping: {err}")
            _log.warning("%s", err)
            continue
        dmap = dataclasses.replace(dmap, method=f"pulses via {dp.master}")
        clocks.append(dmap)
        notes.append(
            f"{dp.device}: clock from the {dp.master} sync pulses on its trigger input "
            f"(DAVIS ns since its last timestamp reset → Vicon), ±{dmap.offset_sigma_ns / 1e3:.1f}"
            " µs; extrinsics come from `mocaprig calibrate board`"
        )
    if not davis_inputs:
        notes.append(
            "DAVIS: not in the recording (no /davis/<serial>/trigger): no DAVIS clock mapping"
        )
    rms = [r.bundle.reprojection_rms_px for r in registrations.values()]
    cal = Calibration(
        cameras=tuple(cameras),
        clocks=tuple(clocks),
        reference_clock="vicon",
        world_frame="vicon",
        statistics={
            "cameras": float(len(cameras)),
            "max_reprojection_rms_px": float(max(rms)),
            "vicon_static_frames": float(vicon.n_frames),
            "vicon_claps": float(len(vicon_claps)),
            "max_rms_threshold_px": float(opt.max_rms_px),
            "forced": float(bool(refused)),
        },
        software_version=__version__,
        created_utc=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
    )
    tick()
    return ViconCalibrationResult(
        calibration=cal,
        registrations=registrations,
        static_frames=static_frames,
        vicon=vicon,
        refused=refused,
        notes=tuple(notes),
        vicon_claps=tuple(vicon_claps),
        clock_fits=clock_fits,
    )


def _stretch_offsets(
    cam: _Cam,
    frames: Sequence[MarkerFrame],
    T: F64,
    interp: _ViconInterp,
    delta0_ns: int,
    mapping: ClockMapping | None,
) -> tuple[F64, F64, F64]:
    """Device → Vicon offsets of stretches of ≤ ``_CHUNK_NS`` of frames.

    Returns ``(t_dev (S,), offset (S,), σ (S,))`` in ns, stretches without a finite offset left
    out. Without ``mapping`` each stretch starts from a grid search around ``delta0_ns``; with
    one (good to ~1 ms) a fit from the mapped offset suffices.

    Raises:
        CalibrationError: no stretch gives an offset (no motion seen in the windows read).
    """
    t_all = np.array([f.t_dev_ns for f in frames], dtype=np.int64)
    wins = (t_all - t_all.min()) // _CHUNK_NS if len(t_all) else t_all
    t_w, d_w, s_w = [], [], []
    for w in np.unique(wins):
        fw = [f for f, k in zip(frames, wins, strict=True) if k == w]
        if mapping is None:
            d0 = _grid_offset(
                fw, T, cam, interp, delta0_ns, half_width_ns=20_000_000, step_ns=1_000_000
            )
        else:
            tm = int(np.median([f.t_dev_ns for f in fw]))
            d0 = int(mapping.to_reference_ns(tm)) - tm
        d, s, n_pairs = _fit_offset(fw, T, cam, interp, d0)
        _log.debug(
            "%s: frames at %d ns: offset %d ns ± %.0f ns (%d pairs)",
            cam.name, int(np.median([f.t_dev_ns for f in fw])), round(d), s, n_pairs,
        )  # fmt: skip
        if math.isfinite(s):
            t_w.append(float(np.median([f.t_dev_ns for f in fw])))
            d_w.append(d)
            s_w.append(s)
    if not d_w:
        msg = (
            f"{cam.name}: no time offset to the Vicon: its markers never matched the "
            "Vicon markers while moving (no motion in the windows read?)"
        )
        raise CalibrationError(msg)
    return np.array(t_w), np.array(d_w), np.array(s_w)


#: Largest RMS (ns) of a camera's frame times about a line through the pivot camera's frame
#: times for the two to count as hardware-synchronised (the D415's sync jitter is µs-level;
#: a free-running slave slides through a whole frame period).
_SYNC_RMS_NS: Final = 100_000


@dataclass(frozen=True, slots=True)
class _Tie:
    """Camera c's device time on the pivot's: ``t_p = t_c + a_ns + s·(t_c − centre_ns)``."""

    a_ns: float
    s: float
    centre_ns: float
    pairs: int
    rms_ns: float
    counter_shift: int


def _tie_by_counters(t_c: I64, n_c: I64, t_p: I64, n_p: I64, shift: int) -> _Tie | None:
    """The line through the frames with ``counter_c − counter_p == shift`` (ns), or None
    without 10 such pairs over ≥ 5 s or with an RMS above :data:`_SYNC_RMS_NS`."""
    idx = {int(n): k for k, n in enumerate(n_p)}
    kc, kp = [], []
    for k, n in enumerate(n_c):
        m = idx.get(int(n) - shift)
        if m is not None:
            kc.append(k)
            kp.append(m)
    if len(kc) < 10:
        return None
    x = t_c[kc].astype(np.float64)
    if np.ptp(x) < 5e9:
        return None
    centre = float(np.mean(x))
    y = (t_p[kp] - t_c[kc]).astype(np.float64)
    A = np.stack([np.ones_like(x), (x - centre) * 1e-9], axis=1)
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    rms = float(np.sqrt(np.mean((y - A @ coef) ** 2)))
    if rms > _SYNC_RMS_NS:
        return None
    return _Tie(float(coef[0]), float(coef[1]) * 1e-9, centre, len(kc), rms, shift)


def _through_tie(
    name: str, tie: _Tie, pivot_map: ClockMapping, *, delay_ns: float = 0.0, method: str
) -> ClockMapping:
    """Camera ``name``'s mapping: its time → the pivot's (``tie``) → Vicon (``pivot_map``),
    plus ``delay_ns`` (the camera's own constant, e.g. a slave's trigger delay)."""
    a, s, centre = tie.a_ns, tie.s, tie.centre_ns
    dp = pivot_map.drift_ppm * 1e-6
    # Anchored where the camera's time maps onto the pivot map's anchor.
    anchor = round((pivot_map.anchor_ns - a + s * centre) / (1.0 + s))
    t_pa = anchor + a + s * (anchor - centre)
    offset = t_pa - anchor + pivot_map.offset_ns + delay_ns + dp * (t_pa - pivot_map.anchor_ns)
    return ClockMapping(
        device=name,
        reference=pivot_map.reference,
        offset_ns=round(offset),
        drift_ppm=(s + dp * (1.0 + s)) * 1e6,
        anchor_ns=anchor,
        offset_sigma_ns=pivot_map.offset_sigma_ns,
        drift_sigma_ppm=pivot_map.drift_sigma_ppm,
        method=method,
    )


def _pooled_clocks(
    frames: Mapping[str, tuple[I64, I64]],
    fits: Mapping[str, tuple[F64, F64, F64]],
    own: Mapping[str, ClockMapping],
    score: Callable[[str, ClockMapping], float] | None = None,
    sync_modes: Mapping[str, int | None] | None = None,
    ties_out: dict[str, _Tie] | None = None,
) -> tuple[dict[str, ClockMapping], list[str]]:
    """One Vicon clock line through the stretch offsets of every hardware-synchronised camera.

    Slaves capture on the master's pulses, so frame k of a slave and frame k + shift of the
    pivot camera (the one whose own line is best determined) are the same instant: a line
    through their device times ties each camera's clock to the pivot's to well under a µs and
    0.1 ppm (frame counters pair the frames: host arrival times cannot be relied on, and a
    camera's own Vicon line can be off by more than a frame period). The counter shift is
    ambiguous by whole periods: the one whose mapping (the pivot's own line through the tie)
    gives the lowest ``score`` (the reprojection cost of the camera's frames) is kept, or
    without ``score`` the one that puts the camera's stretch offsets closest to the pivot's
    line. Every camera's stretch offsets are then moved onto the pivot's clock and one robust
    weighted line (:func:`_shared_line_fit`) is fitted through all of them (N cameras' worth
    of data; a camera whose own stretches are poor is outvoted instead of getting a poor
    clock), plus a constant per camera from its inlier stretches (a slave exposes a fixed
    trigger delay after the pulse). A camera whose frames do not pair (free-running, counters
    restarted, too little data) keeps its own line, and a note says so.

    Args:
        frames: Per camera the frames' ``(device times ns, frame counters)``.
        fits: Per camera ``(t_dev, offset, σ)`` of its stretches (ns).
        own: Per camera the line through its own stretches alone.
        score: ``(camera, candidate mapping) -> cost``, lower is better.
        sync_modes: Per camera its recorded ``inter_cam_sync_mode`` (None: unknown). Only
            masters (1), slaves (2) and unknowns are pooled: a camera in mode 0 free-runs on
            its own crystal, and a free-running camera at the same frame rate can pair with
            the master's frames on a line (its phase slides linearly), so the frame times
            alone cannot always tell it.
        ties_out: Filled with each pooled camera's tie to the pivot (the pivot's own is the
            identity), for the sync-channel clocks (:func:`_sync_clocks`).

    Returns:
        ``(mapping per camera, notes)``.
    """
    out = dict(own)
    modes = sync_modes or {}
    notes: list[str] = []
    names = []
    for n in own:
        if modes.get(n) not in (None, 1, 2):
            notes.append(
                f"{n}: clock fitted on its own: recorded with inter_cam_sync_mode "
                f"{modes.get(n)} (not a master or slave)"
            )
        else:
            names.append(n)
    if len(names) < 2:
        return out, notes
    pivot = min(
        names,
        key=lambda n: own[n].drift_sigma_ppm if math.isfinite(own[n].drift_sigma_ppm) else 1e9,
    )
    t_p, n_p = frames[pivot]
    line_p = own[pivot]
    rel: dict[str, _Tie] = {pivot: _Tie(0.0, 0.0, 0.0, len(t_p), 0.0, 0)}
    for n in names:
        if n == pivot:
            continue
        t_c, n_c = frames[n]
        # First guess of the counter shift: nearest pivot frame through the own lines.
        r_c = own[n].to_reference_ns(t_c)
        r_p = line_p.to_reference_ns(t_p)
        order = np.argsort(r_p)
        k = np.clip(np.searchsorted(r_p[order], r_c), 0, len(r_p) - 1)
        shifts, counts = np.unique(n_c - n_p[order][k], return_counts=True)
        guess = int(shifts[np.argmax(counts)]) if len(shifts) else 0
        best: tuple[float, _Tie] | None = None
        for shift in range(guess - 2, guess + 3):
            tie = _tie_by_counters(t_c, n_c, t_p, n_p, shift)
            if tie is None:
                continue
            if score is not None:
                cost = score(n, _through_tie(n, tie, line_p, method="candidate"))
            else:
                t_w, d_w, _ = fits[n]
                tp_w = (t_w + tie.a_ns + tie.s * (t_w - tie.centre_ns)).round()
                on_pivot = (t_w + d_w - tp_w) - (line_p.to_reference_ns(tp_w) - tp_w)
                cost = float(np.median(np.abs(on_pivot)))
            if best is None or cost < best[0]:
                best = (cost, tie)
        if best is None:
            notes.append(
                f"{n}: clock fitted on its own: its frames do not pair with {pivot}'s (no frame "
                f"counter shift gives a line within {_SYNC_RMS_NS / 1e3:.0f} µs RMS over ≥ 5 s); "
                "is it hardware-synchronised?"
            )
            _log.warning("%s", notes[-1])
            continue
        tie = best[1]
        _log.info(
            "%s: synchronised with %s (counter shift %d, %d frame pairs, %.1f µs RMS, relative "
            "rate %+.3f ppm)",
            n, pivot, tie.counter_shift, tie.pairs, tie.rms_ns / 1e3, tie.s * 1e6,
        )  # fmt: skip
        rel[n] = tie
    if ties_out is not None and len(rel) >= 2:
        ties_out.update(rel)
    if len(rel) < 2:
        return out, notes
    t_all, d_all, s_all, cam_all = [], [], [], []
    for c, (n, tie) in enumerate(rel.items()):
        t_w, d_w, s_w = fits[n]
        tp_w = t_w + tie.a_ns + tie.s * (t_w - tie.centre_ns)
        t_all.append(tp_w)
        d_all.append(t_w + d_w - tp_w)
        s_all.append(s_w)
        cam_all.append(np.full(len(t_w), c))
    pooled, delays, delay_sig = _shared_line_fit(
        pivot,
        np.concatenate(t_all),
        np.concatenate(d_all),
        np.concatenate(s_all),
        np.concatenate(cam_all),
        len(rel),
    )
    method = f"reprojection, pooled over {len(rel)} synchronised cameras"
    for c, (n, tie) in enumerate(rel.items()):
        m = _through_tie(n, tie, pooled, delay_ns=delays[c], method=method)
        out[n] = dataclasses.replace(
            m, offset_sigma_ns=math.hypot(pooled.offset_sigma_ns, delay_sig[c])
        )
    notes.append(
        f"clock: one line fitted through the stretch offsets of {len(rel)} hardware-"
        f"synchronised cameras (pivot {pivot}), each camera's clock tied to the pivot's by its "
        "frame times, plus its own constant delay"
    )
    return out, notes


#: Fewest inlier stretches for a camera's own constant delay in the pooled clock; with fewer
#: it gets none (0 ± the pooled line's σ).
_MIN_DELAY_STRETCHES: Final = 3
#: Largest per-camera constant (trigger delay) of the pooled clock, and the prior it is shrunk
#: with (ns). A D415 slave exposes a fixed delay after the pulse (the mock: 100 µs).
_MAX_DELAY_NS: Final = 1_000_000.0
_DELAY_PRIOR_NS: Final = 300_000.0


def _shared_line_fit(
    pivot: str, t_ns: F64, delta_ns: F64, sigma_ns: F64, cam: npt.NDArray[np.int_], n_cams: int
) -> tuple[ClockMapping, list[float], list[float]]:
    """Robust weighted line ``delta = offset + drift·(t − anchor)`` (ns; ``t`` on the pivot's
    clock) through every camera's stretches, with the weighting and rejection of
    :func:`_line_clock`, then per camera the median of its inlier residuals (its constant
    delay, with ≥ :data:`_MIN_DELAY_STRETCHES` inliers).

    Returns ``(the pivot's mapping, delay ns per camera, delay σ ns per camera)``.
    """
    ok = np.isfinite(sigma_ns) & np.isfinite(delta_ns) & np.isfinite(t_ns)
    t_ns, delta_ns, sigma_ns, cam = t_ns[ok], delta_ns[ok], sigma_ns[ok], cam[ok]
    w = 1.0 / (sigma_ns**2 + _STRETCH_SIGMA_FLOOR_NS**2)
    pooled = _line_clock(pivot, t_ns, delta_ns, sigma_ns)
    res = delta_ns - (pooled.to_reference_ns(t_ns.round()) - t_ns.round())
    z = res * np.sqrt(w)
    scale = max(1.4826 * float(np.median(np.abs(z))), 1.0)
    # A per-camera constant is a trigger delay: physically ≤ _MAX_DELAY_NS. Only stretches that
    # close to the line say anything about it (wider ones are fits on a neighbouring frame or a
    # bad stretch), and a weak estimate is shrunk towards 0 (Gaussian prior _DELAY_PRIOR_NS).
    inlier = (np.abs(z) <= _STRETCH_REJECT_SIGMA * scale) & (np.abs(res) <= _MAX_DELAY_NS)
    delays, sig = [], []
    for c in range(n_cams):
        r = res[inlier & (cam == c)]
        if len(r) >= _MIN_DELAY_STRETCHES:
            med = float(np.median(r))
            se = 1.2533 * 1.4826 * float(np.median(np.abs(r - med))) / math.sqrt(len(r))
            k = _DELAY_PRIOR_NS**2 / (_DELAY_PRIOR_NS**2 + se**2)
            delays.append(k * med)
            sig.append(math.sqrt(k) * se)
        else:
            delays.append(0.0)
            sig.append(0.0)
    _log.info(
        "%s clock (pooled): %d of %d stretches inliers; delays %s µs",
        pivot, int(inlier.sum()), len(inlier), [round(d / 1e3, 1) for d in delays],
    )  # fmt: skip
    return pooled, delays, sig


def _time_align_clock(
    device: str,
    frames: Sequence[MarkerFrame],
    vicon_claps: Sequence[ClapDetection],
    traj: MarkerTrajectories,
    prior: ClockMapping,
) -> ClockMapping:
    """The clock from :mod:`mocaprig.calib.time_align`: the camera's claps paired with the Vicon's
    (offset, and drift from two claps), then refined by the marker-speed correlation over the
    frames read. Falls back to ``prior`` (the reprojection clock) for a step that fails, and
    says so in the log."""
    from mocaprig.calib.time_align import (
        clock_from_claps,
        find_claps_d415,
        refine_by_speed,
        speed_from_frames,
        speed_from_trajectories,
    )

    mapping = prior
    try:
        claps = find_claps_d415(frames, device=device)
        mapping = clock_from_claps(device, claps, vicon_claps)
    except CalibrationError as err:
        _log.warning("%s: clap clock unavailable (%s); keeping the reprojection clock", device, err)
    a = prior.anchor_ns
    if abs(int(mapping.to_reference_ns(a)) - int(prior.to_reference_ns(a))) > 50_000_000:
        _log.warning("%s: the clap clock disagrees with the reprojection clock by > 50 ms", device)
        mapping = prior
    try:
        td, vd = speed_from_frames(frames)
        tr, vr = speed_from_trajectories(traj)
        mapping = refine_by_speed(mapping, td, vd, tr, vr, search_ns=20_000_000)
    except CalibrationError as err:
        _log.warning("%s: speed refinement failed (%s)", device, err)
    return mapping


#: Floor added (in quadrature) to each stretch's offset σ in the clock line. A stretch's own σ
#: (from its reprojection fit) is 70–900 µs, but stretches of the same camera scatter by
#: 0.3–1 ms about the line (blob bias that depends on the motion), and a σ near zero from a
#: degenerate stretch would otherwise take all the weight.
_STRETCH_SIGMA_FLOOR_NS: Final = 250_000.0
#: Stretches farther than this many robust σ from the line are rejected, then it is refitted.
_STRETCH_REJECT_SIGMA: Final = 3.0


def _line_clock(device: str, t_dev: F64, delta_ns: F64, sigma_ns: F64) -> ClockMapping:
    """A device → Vicon mapping through per-stretch offsets (ns, at device times ns): a
    weighted line (offset + drift) when the stretches span ≥ 5 s, else the weighted mean
    offset with no drift.

    Each stretch is weighted by ``1/(σ² + floor²)`` (:data:`_STRETCH_SIGMA_FLOOR_NS`); stretches
    beyond :data:`_STRETCH_REJECT_SIGMA` robust σ (MAD of the weighted residuals) are rejected
    and the line refitted, until none is (at least 3 kept). The reported σ are scaled by the
    residual χ² when it exceeds 1."""
    ok = np.isfinite(sigma_ns) & np.isfinite(delta_ns) & np.isfinite(t_dev)
    t_dev, delta_ns, sigma_ns = t_dev[ok], delta_ns[ok], sigma_ns[ok]
    if len(t_dev) == 0:
        msg = f"{device}: no stretch gave a finite clock offset"
        raise CalibrationError(msg)
    w = 1.0 / (sigma_ns**2 + _STRETCH_SIGMA_FLOOR_NS**2)
    keep = np.ones(len(t_dev), dtype=bool)
    anchor = round(float((w * t_dev).sum() / w.sum()))
    x = (t_dev - anchor) * 1e-9
    line = len(t_dev) >= 2 and np.ptp(t_dev) >= 5e9
    A = np.stack([np.ones_like(x), x], axis=1) if line else np.ones((len(x), 1))
    for _ in range(len(t_dev)):
        wk = w * keep
        cov = np.linalg.inv(A.T @ (A * wk[:, None]))
        coef = cov @ (A.T @ (wk * delta_ns))
        z = (delta_ns - A @ coef) * np.sqrt(w)
        scale = max(1.4826 * float(np.median(np.abs(z[keep]))), 1.0)
        worse = keep & (np.abs(z) > _STRETCH_REJECT_SIGMA * scale)
        if not worse.any() or keep.sum() - 1 < max(3, A.shape[1] + 1):
            break
        keep[np.argmax(np.where(worse, np.abs(z), -np.inf))] = False
    n_rej = int((~keep).sum())
    if n_rej:
        _log.info("%s: clock line: %d of %d stretches rejected", device, n_rej, len(keep))
    chi2 = float((z[keep] ** 2).sum()) / max(int(keep.sum()) - A.shape[1], 1)
    cov = cov * max(chi2, 1.0)
    return ClockMapping(
        device=device,
        reference="vicon",
        offset_ns=round(float(coef[0])),
        drift_ppm=float(coef[1]) * 1e-3 if line else 0.0,
        anchor_ns=anchor,
        offset_sigma_ns=math.sqrt(cov[0, 0]),
        drift_sigma_ppm=math.sqrt(cov[1, 1]) * 1e-3 if line else math.nan,
        method="reprojection",
    )


# --------------------------------------------------------------------------------------------
# Attachment
# --------------------------------------------------------------------------------------------


def attach_calibration(
    source: str | Path, output: str | Path, cal: Calibration, *, overwrite: bool = False
) -> Path:
    """Write a copy of a recording with the calibration attached as :data:`ATTACHMENT_NAME`.

    MCAP files are append-only once finished, so the recording is rewritten: every schema,
    channel, message (chunked, lz4), metadata record and attachment is copied, an older
    ``calibration.toml`` attachment is replaced, and the new one added.

    Raises:
        CalibrationError: ``output`` exists and ``overwrite`` is False, ``output`` is the
            source, or the source cannot be read.
    """
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    src, dst = Path(source), Path(output)
    if dst.exists() and dst.resolve() == src.resolve():
        msg = f"{dst}: --attach-to must name a new file, not the recording itself"
        raise CalibrationError(msg)
    if dst.exists() and not overwrite:
        msg = f"{dst} exists; pass --overwrite to replace it"
        raise CalibrationError(msg)
    part = dst.with_name(dst.name + ".part")
    try:
        with src.open("rb") as fin, part.open("wb") as fout:
            reader = make_reader(fin)
            summary = reader.get_summary()
            header = reader.get_header()
            w = Writer(fout, compression=CompressionType.LZ4)
            w.start(profile=header.profile, library=header.library)
            schema_ids: dict[int, int] = {}
            channel_ids: dict[int, int] = {}
            if summary is not None:
                for sid, sch in summary.schemas.items():
                    schema_ids[sid] = w.register_schema(sch.name, sch.encoding, sch.data)
                for ch_id, ch in summary.channels.items():
                    channel_ids[ch_id] = w.register_channel(
                        ch.topic,
                        ch.message_encoding,
                        schema_ids.get(ch.schema_id, 0),
                        dict(ch.metadata),
                    )
            for meta in reader.iter_metadata():
                w.add_metadata(meta.name, dict(meta.metadata))
            for att in reader.iter_attachments():
                if att.name == ATTACHMENT_NAME:
                    continue
                w.add_attachment(
                    create_time=att.create_time,
                    log_time=att.log_time,
                    name=att.name,
                    media_type=att.media_type,
                    data=att.data,
                )
            now = _dt.datetime.now(_dt.UTC)
            t_ns = int(now.timestamp() * 1e9)
            w.add_attachment(
                create_time=t_ns,
                log_time=t_ns,
                name=ATTACHMENT_NAME,
                media_type="application/toml",
                data=calibration_bytes(cal),
            )
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                cid = channel_ids.get(channel.id)
                if cid is None:
                    sid = 0
                    if schema is not None:
                        if schema.id not in schema_ids:
                            schema_ids[schema.id] = w.register_schema(
                                schema.name, schema.encoding, schema.data
                            )
                        sid = schema_ids[schema.id]
                    cid = w.register_channel(
                        channel.topic, channel.message_encoding, sid, dict(channel.metadata)
                    )
                    channel_ids[channel.id] = cid
                w.add_message(
                    channel_id=cid,
                    log_time=message.log_time,
                    publish_time=message.publish_time,
                    data=message.data,
                    sequence=message.sequence,
                )
            w.finish()  # type: ignore[no-untyped-call]
    except Exception as err:
        part.unlink(missing_ok=True)
        if isinstance(err, CalibrationError):
            raise
        msg = f"cannot attach the calibration: copying {src} to {dst} failed: {err}"
        raise CalibrationError(msg) from err
    part.replace(dst)
    return dst


# --------------------------------------------------------------------------------------------
# Evaluation against a simulated session's truth
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class DeviceEvaluation:
    """Errors of one device against the truth (NaN where the calibration lacks that part).

    Attributes:
        device: The calibration's label (``"d415/<serial>"``, ``"davis/<serial>"``).
        truth_name: The simulated world's name of the device (``"d415-0"``, ``"davis"``).
        rotation_error_deg: Angle between calibrated and true camera orientation (deg).
        translation_error_mm: Distance between calibrated and true camera centres (mm).
        clock_offset_error_ms: Mapped minus true Vicon time at the session midpoint (ms).
        drift_error_ppm: Calibrated minus true drift (ppm).
        clock_error_vs_via_us: For a mapping derived through another device's (method
            ``"pulses via <device>"``): its offset error minus that device's, i.e. the error of
            the DAVIS ↔ D415 mapping itself (µs); NaN otherwise.
    """

    device: str
    truth_name: str
    rotation_error_deg: float = math.nan
    translation_error_mm: float = math.nan
    clock_offset_error_ms: float = math.nan
    drift_error_ppm: float = math.nan
    clock_error_vs_via_us: float = math.nan


@dataclass(frozen=True, slots=True)
class Evaluation:
    """A calibration scored against truth.

    Attributes:
        truth_dir: The session folder read.
        devices: One entry per device found in both.
        missing: Truth devices the calibration does not describe.
    """

    truth_dir: str
    devices: tuple[DeviceEvaluation, ...]
    missing: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON-able view (NaN → null in ``emit_json``)."""
        return {
            "truth": self.truth_dir,
            "devices": [
                {
                    "device": d.device,
                    "truth_name": d.truth_name,
                    "rotation_error_deg": d.rotation_error_deg,
                    "translation_error_mm": d.translation_error_mm,
                    "clock_offset_error_ms": d.clock_offset_error_ms,
                    "drift_error_ppm": d.drift_error_ppm,
                    "clock_error_vs_via_us": d.clock_error_vs_via_us,
                }
                for d in self.devices
            ],
            "missing": list(self.missing),
        }


def _read_scenario(truth_dir: Path) -> dict[str, Any]:
    for cand in (truth_dir / "truth" / "scenario.json", truth_dir / "scenario.json"):
        if cand.is_file():
            try:
                data: dict[str, Any] = json.loads(cand.read_text(encoding="utf-8"))
            except (OSError, ValueError) as err:
                msg = f"cannot read the truth file {cand}: {err}"
                raise CalibrationError(msg) from err
            return data
    msg = (
        f"{truth_dir}: no truth/scenario.json; give the folder `mocaprig simulate --out` wrote "
        "(or its truth/ folder)"
    )
    raise CalibrationError(msg)


def _read_davis_clock(root: Path) -> dict[str, Any] | None:
    """``truth/davis_clock.json`` (the recorded DAVIS time base), or None when absent."""
    for cand in (root / "truth" / "davis_clock.json", root / "davis_clock.json"):
        if cand.is_file():
            try:
                data: dict[str, Any] = json.loads(cand.read_text(encoding="utf-8"))
            except (OSError, ValueError) as err:
                msg = f"cannot read the truth file {cand}: {err}"
                raise CalibrationError(msg) from err
            return data
    return None


def _true_clock_error_ns(
    mapping: ClockMapping,
    dev: Mapping[str, Any],
    vic: Mapping[str, Any],
    t_mid_ns: int,
    wraps: bool,
) -> tuple[float, float]:
    """(offset error ns at the session midpoint, drift error ppm) of a device → Vicon mapping."""
    a = float(dev["drift_ppm"]) * 1e-6
    b = float(vic["drift_ppm"]) * 1e-6
    dev_mid = int(dev["offset_ns"]) + round(t_mid_ns * (1.0 + a))
    ref_mid = int(vic["offset_ns"]) + round(t_mid_ns * (1.0 + b))
    candidates = [dev_mid]
    if wraps:  # a D415's u32 µs clock: the recording's device ns may lack whole wraps
        candidates = [dev_mid - k * _U32_NS for k in range(dev_mid // _U32_NS + 1)]
    errs = [float(mapping.to_reference_ns(c) - ref_mid) for c in candidates]
    # The mapped device time may be on any wrap; the right one is the closest.
    err = min(errs, key=abs)
    drift_true = ((1.0 + b) / (1.0 + a) - 1.0) * 1e6
    return err, mapping.drift_ppm - drift_true


def evaluate_calibration(cal: Calibration, truth_dir: str | Path) -> Evaluation:
    """Score a calibration against a simulated session's truth.

    Per device found in both (matched by serial): rotation error (deg) and camera-centre error
    (mm) of ``T_world_cam``; for each clock mapping, the error of the mapped Vicon time at the
    session midpoint (ms) and of the drift (ppm). Truth clocks: ``device_ns = offset_ns +
    t·(1 + drift_ppm·1e-6)``, Vicon likewise; a D415's device time is its u32 µs hardware clock,
    so the wrap closest to the mapping is used. A DAVIS's recorded time restarts at its
    timestamp reset: it is scored against ``truth/davis_clock.json`` (written by ``mocaprig
    simulate`` with a recording: ``(t − reset_session_ns)·(1 + drift_ppm·1e-6)``); without that
    file its clock error is NaN (the free-running clock of ``scenario.json`` is not what the
    recording holds).

    Raises:
        CalibrationError: the truth folder is unreadable.
    """
    root = Path(truth_dir)
    sc = _read_scenario(root)
    rig = sc.get("rig", {})
    clocks = {c["name"]: c for c in sc.get("clocks", [])}
    t_mid = int(sc.get("duration_ns", 0)) // 2
    davis_base = _read_davis_clock(root)
    entries: list[tuple[str, str, str, Any]] = []  # (label, truth name, kind, T_world_cam)
    for d in rig.get("d415", []):
        entries.append((f"d415/{d['serial']}", d["name"], "d415", d["ir_left"]["T_world_cam"]))
    dv = rig.get("davis")
    if dv:
        entries.append(
            (f"davis/{dv['serial']}", dv.get("name", "davis"), "davis", dv["camera"]["T_world_cam"])
        )
    out: list[DeviceEvaluation] = []
    missing: list[str] = []
    cam_names = {c.name for c in cal.cameras}
    clock_names = {c.device for c in cal.clocks}
    for label, name, kind, T_true in entries:
        if label not in cam_names and label not in clock_names:
            missing.append(label)
            continue
        rot = tr = off = drift = math.nan
        if label in cam_names:
            T = cal.camera(label).T_world_cam
            Tt = np.asarray(T_true, dtype=np.float64)
            rot = rotation_error_deg(T, Tt)
            tr = 1e3 * float(np.linalg.norm(T[:3, 3] - Tt[:3, 3]))
        dev_clock: Mapping[str, Any] | None = clocks.get(name)
        if kind == "davis":
            dev_clock = None
            if davis_base is not None and davis_base.get("device") in (None, label):
                a = float(davis_base["drift_ppm"]) * 1e-6
                reset = int(davis_base["reset_session_ns"])
                dev_clock = {"offset_ns": -round(reset * (1.0 + a)), "drift_ppm": a * 1e6}
        if label in clock_names and dev_clock is not None and "vicon" in clocks:
            err_ns, drift = _true_clock_error_ns(
                cal.clock(label), dev_clock, clocks["vicon"], t_mid, wraps=kind == "d415"
            )
            off = err_ns / 1e6
        out.append(DeviceEvaluation(label, name, rot, tr, off, drift))
    by_label = {d.device: d for d in out}
    for i, d in enumerate(out):
        if d.device not in clock_names:
            continue
        method = cal.clock(d.device).method
        via = by_label.get(method.split(" via ", 1)[1]) if " via " in method else None
        if via is not None:
            rel = 1e3 * (d.clock_offset_error_ms - via.clock_offset_error_ms)
            out[i] = dataclasses.replace(d, clock_error_vs_via_us=rel)
    return Evaluation(truth_dir=str(root), devices=tuple(out), missing=tuple(missing))
