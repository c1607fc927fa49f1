"""The measured markers and DeMoCap joints in 3D on the live view of ``mocaprig record --live``.

``mocaprig record --live --calib calib.toml`` gives the live view
(:class:`~mocaprig.acquire.live_view.LiveView`) a :class:`DemocapLiveScene` (through the
``mocaprig.live_scene`` entry point ``democap``: acquire never imports process). The recorder's
tap offers it every D415 message as it is written (:meth:`DemocapLiveScene.offer`, writer
thread: a few dictionary operations): each camera's IR, depth and ``frame_info`` of one frame set
(the same log time) are paired, its sensor stamp unwrapped (:class:`~mocaprig.timebase.
U32Unwrapper`) and mapped onto the calibration's reference clock, and the rig instants grouped by
the one instant rule of the replay and ``democap live``
(:class:`~mocaprig.process.democap.instants.InstantGrouper`). A worker thread takes the newest
complete instant (older ones are skipped: the view drops its own work first, never the
recording's), runs it through the live pipeline (:class:`~mocaprig.process.democap.live.
LivePipeline`: blobs, depth, the 10 mm merge, the network) and leaves the scene updates of the
replay on its topics (``/democap/markers``, ``/democap/joints`` and the fused cloud on
``/democap/cloud``, so the replay's Foxglove layout shows them) for the live view's publisher
(:meth:`DemocapLiveScene.take`).

Units: metres in the calibration's world frame; times in ns of its reference clock (the entity
stamps) and of the recorder's host clock (log times).
"""

from __future__ import annotations

import logging
import re
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np

from mocaprig.acquire.recording_format import D415FrameInfo, ImageMsg, SceneUpdateMsg
from mocaprig.calib.calibration import Calibration, read_calibration
from mocaprig.errors import MocaprigError, ValidationError
from mocaprig.process.democap.instants import INSTANT_TOLERANCE, InstantGrouper
from mocaprig.process.democap.live import (
    CloudPredictor,
    LivePipeline,
    cameras_from_calibration,
)
from mocaprig.process.democap.replay import (
    CLOUD_TOPIC,
    JOINTS_TOPIC,
    MARKERS_TOPIC,
    cloud_scene,
    marker_scene,
    skeleton_scene,
)
from mocaprig.timebase import U32Unwrapper

__all__ = ["DemocapLiveScene", "LiveSceneStats", "live_scene"]

_log = logging.getLogger(__name__)

_D415_TOPIC: Final = re.compile(r"^/d415/([^/]+)/(ir|depth|frame_info)$")
#: How long a camera's frame waits for the other cameras' (frame periods), as ``democap live``.
_MAX_LAG_PERIODS: Final = 3
#: Partial frame sets (a part missing) older than this are forgotten (ns of log time).
_PARTIAL_TTL_NS: Final = 1_000_000_000


@dataclass(slots=True)
class LiveSceneStats:
    """Counts of a :class:`DemocapLiveScene` (instants grouped, run, skipped as stale, with a
    prediction, failed; frame sets of cameras the calibration does not have)."""

    grouped: int = 0
    run: int = 0
    skipped: int = 0
    predicted: int = 0
    failed: int = 0
    unknown_cameras: set[str] = field(default_factory=set)

    def as_dict(self) -> dict[str, Any]:
        return {
            "grouped": self.grouped,
            "run": self.run,
            "skipped": self.skipped,
            "predicted": self.predicted,
            "failed": self.failed,
            "unknown_cameras": sorted(self.unknown_cameras),
        }


class DemocapLiveScene:
    """Markers and joints in 3D for the live view (module doc); a context manager.

    Args:
        calibration: Poses and clock mappings of the D415s (every D415 of it is used).
        predictor: The network (default: the committed checkpoint, 2 turns batched on one
            thread: the recording has the other core).
        fps: The cameras' frame rate (sets the instant grouping's period).
        max_hz: Most instants run per second (the worker sleeps the rest).

    Raises:
        CalibrationError: the calibration has no D415, or a D415 has no clock mapping.
        ValidationError: ``fps`` or ``max_hz`` not > 0.
    """

    def __init__(
        self,
        calibration: Calibration,
        *,
        predictor: CloudPredictor | None = None,
        fps: float = 30.0,
        max_hz: float = 15.0,
    ) -> None:
        if not fps > 0 or not max_hz > 0:
            msg = f"live scene: fps and max_hz must be > 0, got {fps!r} and {max_hz!r}"
            raise ValidationError(msg)
        self.calibration = calibration
        self._cams = cameras_from_calibration(calibration)
        self._labels = [c.name for c in self._cams]
        self._clocks = {label: calibration.clock(label) for label in self._labels}
        self._period_ns = round(1e9 / fps)
        self._grouper = self._new_grouper()
        self._unwrap = {label: U32Unwrapper() for label in self._labels}
        self._parts: dict[tuple[str, int], dict[str, Any]] = {}
        self._min_period_s = 1.0 / max_hz
        if predictor is None:
            from mocaprig.process.democap.infer import DemocapPredictor

            predictor = DemocapPredictor(rotations=2, solve=False, workers=1)
        self._pipeline = LivePipeline(predictor, self._cams, workers=1)
        self.stats = LiveSceneStats()
        # Shared between the writer thread (offer), the worker and the publisher (take).
        self._lock = threading.Lock()
        # (log time ns, reference time ns, frames by camera) of the newest grouped instant.
        self._newest: tuple[int, int, dict[str, tuple[Any, Any] | None]] | None = None
        self._shown_t_ref = -(2**63)
        self._out: list[tuple[str, SceneUpdateMsg, int]] = []
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mocaprig-live-scene", daemon=True)
        self._thread.start()

    # -- lifetime ---------------------------------------------------------------------------

    def __enter__(self) -> DemocapLiveScene:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the worker and the pipeline (idempotent)."""
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=10.0)
        self._pipeline.close()

    # -- the recorder's side ----------------------------------------------------------------

    def offer(self, topic: str, message: Any, log_time_ns: int) -> None:
        """A message the recorder wrote (writer thread); returns at once. Anything but a D415
        ``ir``, ``depth`` or ``frame_info`` is ignored."""
        m = _D415_TOPIC.match(topic)
        if m is None:
            return
        label = f"d415/{m.group(1)}"
        if label not in self._clocks:
            self.stats.unknown_cameras.add(label)
            return
        key = (label, int(log_time_ns))
        part = self._parts.setdefault(key, {})
        part[m.group(2)] = message
        if len(part) < 3:
            return
        del self._parts[key]
        info, ir, depth = part["frame_info"], part["ir"], part["depth"]
        if not (isinstance(info, D415FrameInfo) and isinstance(ir, ImageMsg)):
            return
        if not isinstance(depth, ImageMsg):
            return
        stamp = info.sensor_timestamp_us
        t_dev = info.host_time_ns if stamp is None else self._unwrap[label](int(stamp)) * 1000
        t_ref = int(self._clocks[label].to_reference_ns(np.int64(t_dev)))
        try:
            grouped = self._grouper.push(label, t_ref, t_dev, (ir.image, depth.image))
        except ValidationError:
            # A camera re-opened (its clock restarted): group afresh from here.
            self._grouper = self._new_grouper()
            self._unwrap[label] = U32Unwrapper()
            with self._lock:
                self._shown_t_ref = -(2**63)
            return
        if len(self._parts) > 64:  # a part that never completed: forget the old ones
            cut = int(log_time_ns) - _PARTIAL_TTL_NS
            for k in [k for k in self._parts if k[1] < cut]:
                del self._parts[k]
        if not grouped:
            return
        g = grouped[-1]
        with self._lock:
            self.stats.grouped += len(grouped)
            if g.instant.t_ref_ns <= self._shown_t_ref:
                # A lagging camera's frames grouped late: the view never goes back in time.
                self.stats.skipped += len(grouped)
                return
            self._shown_t_ref = g.instant.t_ref_ns
            self.stats.skipped += len(grouped) - 1 + (self._newest is not None)
            self._newest = (
                int(log_time_ns),
                int(g.instant.t_ref_ns),
                {c: g.items.get(c) for c in self._labels},
            )
        self._wake.set()

    def _new_grouper(self) -> InstantGrouper[tuple[Any, Any]]:
        return InstantGrouper(
            self._labels,
            self._period_ns,
            tolerance=INSTANT_TOLERANCE,
            max_lag_ns=_MAX_LAG_PERIODS * self._period_ns,
        )

    # -- the live view's side ---------------------------------------------------------------

    def take(self) -> list[tuple[str, SceneUpdateMsg, int]]:
        """The scene updates made since the last call: ``(topic, message, log_time_ns)``."""
        with self._lock:
            out, self._out = self._out, []
        return out

    # -- worker -----------------------------------------------------------------------------

    def _run(self) -> None:
        failed_once = False
        while not self._stop.is_set():
            self._wake.wait()
            self._wake.clear()
            with self._lock:
                newest, self._newest = self._newest, None
            if newest is None or self._stop.is_set():
                continue
            log_time, t_ref, frames = newest
            try:
                res = self._pipeline.process(frames)
            except MocaprigError as err:
                with self._lock:
                    self.stats.failed += 1
                if not failed_once:
                    _log.warning("live scene: an instant failed (%s); the next ones go on", err)
                failed_once = True
                continue
            frame = self.calibration.world_frame
            info = {"cameras": str(res.cameras_used), "points": str(res.points)}
            out = [(CLOUD_TOPIC, cloud_scene(frame, t_ref, res.cloud_m, info), log_time)]
            if res.prediction is not None:
                p = res.prediction
                out.append((MARKERS_TOPIC, marker_scene(frame, t_ref, p.markers_m, info), log_time))
                out.append((JOINTS_TOPIC, skeleton_scene(frame, t_ref, p.joints_m, info), log_time))
            with self._lock:
                self.stats.run += 1
                self.stats.predicted += res.prediction is not None
                self._out.extend(out)
                del self._out[: max(0, len(self._out) - 9)]  # the publisher is behind
            self._stop.wait(self._min_period_s)


def live_scene(calibration: str | Path | Calibration, **options: Any) -> DemocapLiveScene:
    """The ``mocaprig.live_scene`` entry point ``democap``: a :class:`DemocapLiveScene` for a
    calibration file (TOML or JSON) or object.

    Raises:
        CalibrationError: the file cannot be read, has no D415 or no clock mapping.
    """
    cal = calibration if isinstance(calibration, Calibration) else read_calibration(calibration)
    return DemocapLiveScene(cal, **options)
