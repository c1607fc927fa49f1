"""The D415 cameras and frames of a recording, read for the Vicon calibration.

:func:`calib_cameras` gives each D415 to calibrate with its intrinsics and recorded settings
(:class:`CalibCamera`). The recording is measured (``calib.markers.measure_frame``) only in
device-time windows: :func:`first_frames` finds each camera's first frame and the end of the
streams, and :func:`read_device_window` the frames of each camera in its window, found by
bisection over the host log time (which in a simulated recording is not proportional to device
time), all cameras in one pass over the recording's chunks.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.device_streams import (
    D415Settings,
    DeviceId,
    RecordedD415,
    d415_devices,
    read_frame_sets,
)
from mocaprig.acquire.recording import Recording
from mocaprig.calib.markers import MarkerFrame
from mocaprig.errors import CalibrationError, RecordingError, ValidationError
from mocaprig.timebase import unwrap_u32_from

__all__ = [
    "CalibCamera",
    "FrameProbe",
    "calib_cameras",
    "first_frames",
    "probe_frame",
    "read_device_window",
]

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class CalibCamera:
    """A D415 to calibrate: its label, serial, intrinsics and recorded settings."""

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


def calib_cameras(rec: Recording, wanted: Sequence[str] | None, source: str) -> list[CalibCamera]:
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
            CalibCamera(
                dev.label, dev.serial, intr.width, intr.height, intr.k, intr.distortion, settings
            )
        )
    return out


@dataclass(frozen=True, slots=True)
class FrameProbe:
    """The first frame of a camera at or after a log time."""

    log_ns: int
    dev_ns: int
    counter: int


def _unwrap_ns(stamp_us: int, anchor_us: int) -> int:
    """Device ns of a u32 µs stamp, taken at or after the camera's first stamp ``anchor_us``."""
    return unwrap_u32_from(stamp_us, anchor_us) * 1000


def probe_frame(rec: Recording, cam: CalibCamera, log_ns: int, anchor_us: int) -> FrameProbe | None:
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
    return FrameProbe(
        m_log_ns, _unwrap_ns(int(fi.sensor_timestamp_us), anchor_us), fi.frame_counter
    )


def _log_at(
    rec: Recording, cam: CalibCamera, dev_ns: int, first: FrameProbe, end_log: int, anchor_us: int
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
        p = probe_frame(rec, cam, mid, anchor_us)
        if p is None or p.dev_ns >= dev_ns:
            hi, hi_log = p, mid
            if p is not None and p.counter - lo.counter <= 1:
                break
        else:
            lo, lo_log = p, p.log_ns
    return lo.log_ns, (hi.log_ns if hi is not None else end_log)


def _read_frames(
    rec: Recording,
    cams: Sequence[CalibCamera],
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


def read_device_window(
    rec: Recording,
    cams: Sequence[CalibCamera],
    dev_windows: Mapping[str, tuple[int, int]],
    firsts: Mapping[str, FrameProbe],
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


def first_frames(
    rec: Recording, cams: Sequence[CalibCamera], source: str
) -> tuple[int, dict[str, FrameProbe]]:
    """A log time past the end of the cameras' frames, and each camera's first frame.

    Raises:
        CalibrationError: a camera has no frames (no frame_info stream, or none at all).
    """
    fi_topics = [c.device.topic("frame_info") for c in cams]
    missing = [c.name for c in cams if c.device.topic("frame_info") not in rec.channels]
    if missing:
        msg = f"{source}: {missing[0]} has no frames (no frame_info stream)"
        raise CalibrationError(msg)
    first_msg = next(iter(rec.messages(fi_topics)), None)
    if first_msg is None:
        msg = f"{source}: the D415 streams hold no frames"
        raise CalibrationError(msg)
    end_log = first_msg.log_time_ns + 1
    while next(iter(rec.messages(fi_topics, start_ns=end_log)), None) is not None:
        end_log = first_msg.log_time_ns + 2 * (end_log - first_msg.log_time_ns)
    firsts: dict[str, FrameProbe] = {}
    for c in cams:
        fi = RecordedD415(rec, c.device).frame_info_at()
        p = None if fi is None else probe_frame(rec, c, fi[0], 0)
        if p is None:
            msg = f"{source}: {c.name} has no frames"
            raise CalibrationError(msg)
        firsts[c.name] = FrameProbe(p.log_ns, p.dev_ns, p.counter)
    return end_log, firsts
