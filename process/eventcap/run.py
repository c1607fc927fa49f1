"""``mocaprig eventcap run``: EventCap on a recording, results as MCAP, C3D and BVH.

:func:`run_eventcap` takes a recording (``mocaprig record`` / ``simulate``) with one DAVIS and
its calibration, and:

1. indexes the DAVIS's APS frames (frame info: exposure window, DAVIS µs; no image decoded) and
   its event packets (first/last event time and log time of each packet; the events are
   dropped again), see :class:`RecordingFrames` and :class:`RecordingEventSource`;
2. builds the detector from a detections file (our JSON, an OpenPose ``--write_json`` folder or
   a COCO keypoint JSON; OpenPose/COCO frame ``i`` is the recording's ``i``-th APS frame), the
   template from a height or a body-shape JSON, the camera from the calibration's DAVIS entry;
3. runs :func:`~.take.iter_take` over the selected frames. **Memory follows the batch**: an APS
   image is decoded when its batch asks for it, a batch's events are read from the file when
   the batch runs, and each batch's 1 kHz output goes to the files as soon as it is done
   (:class:`EventcapResultsWriter`); nothing grows with the take but the frame and packet
   indexes.

Outputs:

* **MCAP** (Foxglove): :data:`JOINTS_TOPIC` (the 19 EventCap keypoints as 30 mm spheres, bones
  as one line list, a label each) and :data:`TEMPLATE_TOPIC` (the fitted capsule template:
  a cylinder and two end spheres per capsule), schema ``foxglove.SceneUpdate``, one message per
  1 kHz tracking frame. ``log_time`` = the entity stamp = the frame's time on the calibration's
  reference clock when the calibration maps the DAVIS clock, else DAVIS time (ns since its
  timestamp reset); which one is in the channel metadata (``log_time``) and
  :attr:`ResultsHeader.time_base`. Frame id: the calibration's world frame. The file
  carries an ``eventcap_run`` metadata record and the calibration as ``calibration.toml``.
* **C3D** (:class:`calib.c3d_write.C3DFrameWriter`, mm): the 19 keypoints
  (:data:`EVENTCAP_KEYPOINTS` names), 1000 Hz, first frame 1 (row ``i`` at the first tracking
  time + ``i`` ms).
* **BVH** (:class:`process.body.bvh_export.BvhWriter`): the 33-DoF poses at 1000 Hz on the
  fitted template's skeleton (Y up, cm).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, Literal, overload

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.device_streams import RecordedDavis, davis_devices
from mocaprig.acquire.events import EVENT_DTYPE
from mocaprig.acquire.recorder import Attachment, Recorder
from mocaprig.acquire.recording import Recording
from mocaprig.acquire.recording_format import SceneUpdateMsg
from mocaprig.calib.calibration import (
    Calibration,
    CameraCalibration,
    ClockMapping,
    read_calibration,
)
from mocaprig.calib.calibration_attachment import ATTACHMENT_NAME
from mocaprig.errors import CalibrationError, ProcessingError, RecordingError, ValidationError
from mocaprig.process.body.kinematics import EVENTCAP_KEYPOINTS
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.body.skeleton import POSE_DIM
from mocaprig.process.eventcap.camera import EventCamera
from mocaprig.process.eventcap.detections import (
    CocoKeypointDetections,
    Detector,
    JsonDetections,
    OpenPoseJsonDetections,
)
from mocaprig.process.eventcap.pipeline import ApsFrame, EventcapOptions
from mocaprig.process.eventcap.take import iter_take
from mocaprig.process.outputs import replace_atomically
from mocaprig.process.scene import capsule_scene, points_scene

__all__ = [
    "JOINTS_TOPIC",
    "KEYPOINT_BONES",
    "METADATA_NAME",
    "TEMPLATE_TOPIC",
    "DetectionsFormat",
    "EventcapResultsWriter",
    "EventcapRunResult",
    "RecordingEventSource",
    "RecordingFrames",
    "ResultsHeader",
    "TemplateView",
    "check_coverage",
    "davis_calibration",
    "default_outputs",
    "keypoint_scene",
    "load_detector",
    "load_shape",
    "results_clock",
    "results_ns",
    "run_eventcap",
    "select_davis",
    "select_frames",
    "template_scene",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

JOINTS_TOPIC: Final = "/eventcap/joints"
TEMPLATE_TOPIC: Final = "/eventcap/template"
#: Name of the MCAP metadata record describing the run.
METADATA_NAME: Final = "eventcap_run"
#: Output rate of the tracking frames (Hz); ``EventcapOptions.step_us`` must be 1000.
_RATE_HZ: Final = 1000.0

#: The 19 keypoints' bones, index pairs into :data:`EVENTCAP_KEYPOINTS`.
KEYPOINT_BONES: Final[tuple[tuple[int, int], ...]] = tuple(
    (EVENTCAP_KEYPOINTS.index(a), EVENTCAP_KEYPOINTS.index(b))
    for a, b in (
        ("pelvis", "neck"),
        ("neck", "head"),
        ("neck", "right_shoulder"),
        ("right_shoulder", "right_elbow"),
        ("right_elbow", "right_wrist"),
        ("neck", "left_shoulder"),
        ("left_shoulder", "left_elbow"),
        ("left_elbow", "left_wrist"),
        ("pelvis", "right_hip"),
        ("right_hip", "right_knee"),
        ("right_knee", "right_ankle"),
        ("pelvis", "left_hip"),
        ("left_hip", "left_knee"),
        ("left_knee", "left_ankle"),
        ("head", "right_eye"),
        ("head", "left_eye"),
        ("right_eye", "right_ear"),
        ("left_eye", "left_ear"),
    )
)

#: How the fitted template is drawn on :data:`TEMPLATE_TOPIC`.
TemplateView = Literal["capsules", "none"]
#: Detections input: our JSON, an OpenPose ``--write_json`` folder, a COCO keypoint JSON, or
#: ``"auto"`` (a folder is OpenPose; a JSON file ours when its ``format`` says so, else COCO).
DetectionsFormat = Literal["auto", "json", "openpose", "coco"]


# ------------------------------------------------------------------------------ recording access


def select_davis(rec: Recording, serial: str | None = None) -> RecordedDavis:
    """The recording's DAVIS: the only one, or the one with ``serial``.

    Raises:
        RecordingError: no DAVIS, several and no ``serial``, or no DAVIS with that serial.
    """
    devs = davis_devices(rec)
    if not devs:
        msg = (
            f"{rec.path}: no DAVIS in the recording (topics: {', '.join(rec.topics)}); "
            "EventCap needs a DAVIS recording (mocaprig record with the DAVIS, or mocaprig "
            "simulate --devices davis --davis-dvs)"
        )
        raise RecordingError(msg)
    if serial is None:
        if len(devs) > 1:
            msg = (
                f"{rec.path}: {len(devs)} DAVIS cameras ({', '.join(d.serial for d in devs)}); "
                "choose one with --davis SERIAL"
            )
            raise RecordingError(msg)
        return RecordedDavis(rec, devs[0])
    for d in devs:
        if d.serial == serial:
            return RecordedDavis(rec, d)
    msg = (
        f"{rec.path}: no DAVIS with serial {serial!r}; its DAVIS cameras: "
        f"{', '.join(d.serial for d in devs)}"
    )
    raise RecordingError(msg)


@dataclass(frozen=True, slots=True)
class _FrameEntry:
    sequence: int
    exposure_start_us: int
    exposure_end_us: int
    log_lo_ns: int
    log_hi_ns: int


class RecordingFrames(Sequence[ApsFrame]):
    """The DAVIS's APS frames as a lazy sequence of :class:`ApsFrame` (DAVIS µs).

    Built from one pass over the frame info (exposure start/end; a frame without info is known
    by its timestamp only, start = end); images are decoded when an item is asked for, the last
    two kept (a batch uses two consecutive frames). ``start_us``/``end_us`` keep the frames whose
    exposure lies inside ``[start_us, end_us]`` (DAVIS µs); ``limit`` keeps the first ``limit``.

    Raises:
        RecordingError: the DAVIS recorded no APS frames.
    """

    def __init__(
        self,
        davis: RecordedDavis,
        *,
        start_us: int | None = None,
        end_us: int | None = None,
        limit: int | None = None,
    ) -> None:
        self._davis = davis
        entries = self._index(davis)
        self.all_times_us: I64 = np.array(
            [(e.exposure_start_us + e.exposure_end_us) // 2 for e in entries], dtype=np.int64
        )
        keep = [
            e
            for e in entries
            if (start_us is None or e.exposure_start_us >= start_us)
            and (end_us is None or e.exposure_end_us <= end_us)
        ]
        self._entries = keep[:limit] if limit is not None else keep
        self._cache: dict[int, ApsFrame] = {}

    @staticmethod
    def _index(davis: RecordedDavis) -> list[_FrameEntry]:
        dev = davis.device
        frame_topic, info_topic = dev.topic("frame"), dev.topic("frame_info")
        if not davis.has("frame"):
            msg = (
                f"{davis.rec.path}: DAVIS {dev.serial} recorded no APS frames; EventCap needs "
                "the APS frames (record with the APS on)"
            )
            raise RecordingError(msg)
        has_info = davis.has("frame_info")
        topics = [frame_topic, info_topic] if has_info else [frame_topic]
        slots: dict[int, dict[str, Any]] = {}
        for m in davis.rec.messages(topics):
            s = slots.setdefault(int(m.sequence), {"log": []})
            s["log"].append(int(m.log_time_ns))
            if m.topic == info_topic:
                info = m.decode()
                s["window"] = (int(info.t_start_exposure_us), int(info.t_end_exposure_us))
            elif not has_info:
                t_us = int(m.decode().timestamp_ns) // 1000
                s["window"] = (t_us, t_us)
            else:
                s["frame"] = True
        out = [
            _FrameEntry(seq, s["window"][0], s["window"][1], min(s["log"]), max(s["log"]))
            for seq, s in slots.items()
            if "window" in s and (not has_info or "frame" in s)
        ]
        out.sort(key=lambda e: e.exposure_start_us)
        return out

    def log_span_ns(self, first: int, end: int) -> tuple[int, int]:
        """The host log times (ns) over which frames ``first`` to ``end - 1`` were recorded
        (their frame and frame-info messages)."""
        part = self._entries[first:end]
        if not part:
            msg = f"no frame in [{first}, {end}) of {len(self._entries)}"
            raise IndexError(msg)
        return min(e.log_lo_ns for e in part), max(e.log_hi_ns for e in part)

    def __len__(self) -> int:
        return len(self._entries)

    @overload
    def __getitem__(self, index: int) -> ApsFrame: ...

    @overload
    def __getitem__(self, index: slice) -> Sequence[ApsFrame]: ...

    def __getitem__(self, index: int | slice) -> ApsFrame | Sequence[ApsFrame]:
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        e = self._entries[index]
        hit = self._cache.get(e.sequence)
        if hit is not None:
            return hit
        image = None
        for f in self._davis.frames(start_ns=e.log_lo_ns, end_ns=e.log_hi_ns + 1):
            start = int(f.info.t_start_exposure_us) if f.info is not None else int(f.t_ns) // 1000
            if start == e.exposure_start_us:
                image = f.image
                break
        if image is None:
            msg = f"{self._davis.rec.path}: APS frame {e.sequence} could not be read back"
            raise RecordingError(msg)
        frame = ApsFrame(e.exposure_start_us, e.exposure_end_us, image.astype(np.float64))
        if len(self._cache) >= 2:
            self._cache.pop(next(iter(self._cache)))
        self._cache[e.sequence] = frame
        return frame

    def __iter__(self) -> Iterator[ApsFrame]:
        for i in range(len(self)):
            yield self[i]

    @property
    def times_us(self) -> I64:
        """The selected frames' times (exposure midpoints, DAVIS µs)."""
        return np.array(
            [(e.exposure_start_us + e.exposure_end_us) // 2 for e in self._entries], np.int64
        )

    @property
    def span_us(self) -> tuple[int, int]:
        """First exposure start and last exposure end of the selected frames (DAVIS µs)."""
        return self._entries[0].exposure_start_us, self._entries[-1].exposure_end_us


def select_frames(
    davis: RecordedDavis,
    *,
    start_s: float | None = None,
    end_s: float | None = None,
    batches: int | None = None,
) -> RecordingFrames:
    """The DAVIS's APS frames exposed inside ``[start_s, end_s]`` (s on the DAVIS timeline,
    None: unbounded), the first ``batches + 1`` of them when ``batches`` is given."""
    return RecordingFrames(
        davis,
        start_us=None if start_s is None else round(start_s * 1e6),
        end_us=None if end_s is None else round(end_s * 1e6),
        limit=None if batches is None else batches + 1,
    )


class RecordingEventSource:
    """An :data:`~.take.EventSource` reading a DAVIS's events from the file per window.

    One pass at construction keeps each event packet's log time and first/last event time (the
    packet's events are dropped again); a window reads only the packets that overlap it.
    ``start_ns``/``end_ns`` (host log time) limit that pass to the packets recorded then (a
    segment of a long take need not decode the whole take's events); a window reaching past
    the events so indexed makes the pass again over the whole file (logged), so a window
    always gets every event it asks for. ``events_read`` counts the events returned,
    ``peak_window_events`` the largest window.

    Raises:
        RecordingError: the DAVIS recorded no events (in the log-time span, when given).
    """

    def __init__(
        self, davis: RecordedDavis, *, start_ns: int | None = None, end_ns: int | None = None
    ) -> None:
        self._davis = davis
        topic = davis.device.topic("events")
        if not davis.has("events"):
            msg = (
                f"{davis.rec.path}: DAVIS {davis.device.serial} recorded no DVS events; EventCap "
                "needs them (record with the DVS on, or simulate with --davis-dvs)"
            )
            raise RecordingError(msg)
        self._topic = topic
        self._bounded = start_ns is not None or end_ns is not None
        self._index(start_ns, end_ns)
        self.events_total_span_us = (int(self._first.min()), int(self._last.max()))
        self.events_read = 0
        self.peak_window_events = 0

    def _index(self, start_ns: int | None, end_ns: int | None) -> None:
        logs: list[int] = []
        first: list[int] = []
        last: list[int] = []
        for log_ns, packet in self._davis.rec.decoded(
            self._topic, start_ns=start_ns, end_ns=end_ns
        ):
            ev = packet.events
            if ev.size:
                logs.append(int(log_ns))
                first.append(int(ev["t"].min()))
                last.append(int(ev["t"].max()))
        if not logs:
            span = (
                ""
                if start_ns is None and end_ns is None
                else f" between {start_ns} and {end_ns} ns"
            )
            msg = (
                f"{self._davis.rec.path}: DAVIS {self._davis.device.serial} has an event topic but "
                f"no DVS events{span}; EventCap needs them (is the DVS on, the scene lit and "
                "moving?)"
            )
            raise RecordingError(msg)
        self._log = np.asarray(logs, dtype=np.int64)
        self._first = np.asarray(first, dtype=np.int64)
        self._last = np.asarray(last, dtype=np.int64)

    def __call__(self, t0_us: int, t1_us: int) -> npt.NDArray[np.void]:
        """Events with ``t0_us <= t <= t1_us``, sorted by time (canonical dtype)."""
        if self._bounded and (t0_us < self._first.min() or t1_us > self._last.max()):
            _log.info(
                "%s: events %d-%d µs asked beyond the indexed %d-%d µs: indexing the whole take",
                self._topic, t0_us, t1_us, int(self._first.min()), int(self._last.max()),
            )  # fmt: skip
            self._bounded = False
            self._index(None, None)
            self.events_total_span_us = (int(self._first.min()), int(self._last.max()))
        hit = np.flatnonzero((self._last >= t0_us) & (self._first <= t1_us))
        if not hit.size:
            return np.empty(0, EVENT_DTYPE)
        lo, hi = int(self._log[hit].min()), int(self._log[hit].max())
        ev = self._davis.rec.events(self._topic, start_ns=lo, end_ns=hi + 1)
        t = ev["t"]
        ev = ev[(t >= t0_us) & (t <= t1_us)]
        ev = ev[np.argsort(ev["t"], kind="stable")]
        self.events_read += int(ev.size)
        self.peak_window_events = max(self.peak_window_events, int(ev.size))
        return ev


# ------------------------------------------------------------------------------ inputs


def load_detector(
    path: str | Path,
    frame_times_us: Sequence[int] | I64,
    *,
    kind: DetectionsFormat = "auto",
    tolerance_us: int = 0,
) -> Detector:
    """The detector of a detections file (module doc). OpenPose/COCO frame or image id ``i`` is
    the recording's ``i``-th APS frame, at ``frame_times_us[i]`` (DAVIS µs).

    Raises:
        ValidationError: no such file or folder, or a ``kind`` that does not fit it.
        RecordingError: a malformed file (from the readers).
    """
    p = Path(path)
    if not p.exists():
        msg = (
            f"--detections {p}: no such file or folder; give our detections JSON, an OpenPose "
            "--write_json folder or a COCO keypoint JSON"
        )
        raise ValidationError(msg)
    times = [int(t) for t in frame_times_us]
    if kind == "auto":
        if p.is_dir():
            kind = "openpose"
        else:
            try:
                doc = json.loads(p.read_text(encoding="utf-8"))
            except (OSError, ValueError) as err:
                msg = f"--detections {p}: not readable JSON ({err})"
                raise RecordingError(msg) from err
            ours = isinstance(doc, dict) and doc.get("format") == "mocaprig.eventcap.detections"
            kind = "json" if ours else "coco"
    if kind == "openpose":
        if not p.is_dir():
            msg = f"--detections {p}: OpenPose detections are a folder of *_keypoints.json"
            raise ValidationError(msg)
        return OpenPoseJsonDetections(p, times, tolerance_us=tolerance_us)
    if p.is_dir():
        msg = f"--detections {p} is a folder; only OpenPose detections are a folder"
        raise ValidationError(msg)
    if kind == "coco":
        return CocoKeypointDetections(p, dict(enumerate(times)), tolerance_us=tolerance_us)
    return JsonDetections(p, tolerance_us=tolerance_us)


def load_shape(*, height_m: float | None = None, shape_path: str | Path | None = None) -> BodyShape:
    """The actor's template: from a standing height (m) or a body-shape JSON (the
    ``body_shape`` dict as the simulator's ``truth/scenario.json`` holds it, or that file).

    Raises:
        ValidationError: neither or both given, or a bad value or file.
    """
    if (height_m is None) == (shape_path is None):
        msg = "give the actor's template: --height M or --shape FILE.json (one of them)"
        raise ValidationError(msg)
    if height_m is not None:
        if not (math.isfinite(height_m) and 1.0 <= height_m <= 2.3):
            msg = f"--height {height_m}: give the actor's standing height in metres (1.0–2.3)"
            raise ValidationError(msg)
        return BodyShape.from_height(float(height_m))
    p = Path(str(shape_path))
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        msg = f"--shape {p}: cannot read the body-shape JSON ({err})"
        raise ValidationError(msg) from err
    if isinstance(doc, dict) and isinstance(doc.get("body_shape"), dict):
        doc = doc["body_shape"]
    try:
        return BodyShape(**{str(k): float(v) for k, v in doc.items()})
    except (TypeError, ValueError, AttributeError) as err:
        msg = (
            f"--shape {p}: not a body shape ({err}); give a JSON object with BodyShape's "
            "fields (e.g. the body_shape of a simulated truth/scenario.json)"
        )
        raise ValidationError(msg) from err


def davis_calibration(cal: Calibration, davis: RecordedDavis, cal_source: str) -> CameraCalibration:
    """The calibration entry of *davis* (by serial, else by label); ``cal_source`` names the file.

    Raises:
        CalibrationError: the calibration has no entry for this DAVIS.
    """
    serial = davis.device.serial
    for c in cal.cameras:
        if (c.kind == "davis" and serial in (c.serial, c.name)) or c.name == davis.device.label:
            return c
    have = [c.name for c in cal.cameras]
    msg = (
        f"the calibration {cal_source} has no DAVIS camera {serial} (it has {have or 'none'}); "
        f"calibrate the DAVIS first: mocaprig calibrate board (its intrinsics and pose in the "
        "world are needed)"
    )
    raise CalibrationError(msg)


def results_clock(cal: Calibration, label: str) -> tuple[ClockMapping | None, str]:
    """The clock mapping of the DAVIS ``label`` and the results' time base: the mapping and
    the calibration's reference clock, or ``(None, "davis")`` when the calibration maps no
    clock for it (the results then stay in DAVIS time)."""
    try:
        clock = cal.clock(label)
    except CalibrationError:
        return None, "davis"
    return clock, cal.reference_clock


def results_ns(clock: ClockMapping | None, t_us: npt.ArrayLike) -> I64:
    """DAVIS times (µs) as the results' times (int ns on the time base of
    :func:`results_clock`: through ``clock``, or DAVIS ns when it is None)."""
    t_dev_ns = np.asarray(t_us).astype(np.int64) * 1000
    t = clock.to_reference_ns(t_dev_ns) if clock is not None else t_dev_ns
    return np.asarray(t, dtype=np.int64)


# ------------------------------------------------------------------------------ result


@dataclass(frozen=True, slots=True)
class ResultsHeader:
    """What the results files say about the run (the MCAP's :data:`METADATA_NAME` record).

    Attributes:
        session: The recording.
        davis: The DAVIS (``davis/<serial>``).
        batches: Batches run.
        frames: 1 kHz tracking frames the run writes.
        time_base: The clock of the written times (``"<reference clock>"`` or ``"davis"``).
        t_first_davis_us: The first tracking frame's time, DAVIS µs.
        world_frame: The calibration's world frame.
        detection_source: The detector's label.
    """

    session: Path
    davis: str
    batches: int
    frames: int
    time_base: str
    t_first_davis_us: int
    world_frame: str
    detection_source: str = ""

    def record(self) -> dict[str, str]:
        """The metadata record (strings)."""
        from mocaprig import __version__

        return {
            "software_version": __version__,
            "session": str(self.session),
            "davis": self.davis,
            "batches": str(self.batches),
            "frames": str(self.frames),
            "rate_hz": f"{_RATE_HZ:g}",
            "time_base": self.time_base,
            "t_first_davis_us": str(self.t_first_davis_us),
            "world_frame": self.world_frame,
            "detections": self.detection_source,
        }


@dataclass(frozen=True, slots=True, eq=False)
class EventcapRunResult:
    """What :func:`run_eventcap` produced. The 1 kHz poses went to the files as the batches
    finished and are not held here (:meth:`read_keypoints_m` reads them back).

    Attributes:
        header: What the results files say about the run.
        outputs: ``{"mcap": ..., "c3d": ..., "bvh": ...}`` paths written.
        frames_total: APS frames in the recording.
        frames_used: APS frames the run used (batches + 1).
        t_first_ns: The first tracking frame's time on :attr:`ResultsHeader.time_base`, ns.
        events_read: Events read from the file over all batches.
        peak_window_events: The largest batch's events.
        timings_s: Wall seconds per stage: ``index_s`` (frames and packets indexed), the
            pipeline's stages summed over batches, ``take_s``, ``write_s`` (the files' own
            writing, inside ``take_s`` as the batches stream), ``total_s``.
    """

    header: ResultsHeader
    outputs: Mapping[str, Path]
    frames_total: int
    frames_used: int
    t_first_ns: int
    events_read: int = 0
    peak_window_events: int = 0
    timings_s: Mapping[str, float] = field(default_factory=dict)

    @property
    def batches(self) -> int:
        """Batches run (consecutive APS frame pairs)."""
        return self.header.batches

    @property
    def t_davis_us(self) -> I64:
        """(T,) the tracking frame times, DAVIS µs (every 1 ms from the first)."""
        step = round(1e6 / _RATE_HZ)
        return self.header.t_first_davis_us + step * np.arange(self.header.frames, dtype=np.int64)

    def read_keypoints_m(self) -> F64:
        """(T, 19, 3) the written keypoints (world, m), read back from the C3D (float32)."""
        from mocaprig.calib.c3d_read import read_c3d

        return np.asarray(read_c3d(self.outputs["c3d"]).positions_m, dtype=np.float64)

    def summary(self) -> dict[str, Any]:
        """A JSON-ready summary (what ``eventcap run --json`` prints)."""
        h = self.header
        return {
            "session": str(h.session),
            "davis": h.davis,
            "frames_total": self.frames_total,
            "frames_used": self.frames_used,
            "batches": self.batches,
            "tracking_frames": h.frames,
            "rate_hz": _RATE_HZ,
            "t_first_davis_us": h.t_first_davis_us,
            "t_last_davis_us": h.t_first_davis_us + round(1e6 / _RATE_HZ) * (h.frames - 1),
            "time_base": h.time_base,
            "t_first_ns": self.t_first_ns,
            "world_frame": h.world_frame,
            "detections": h.detection_source,
            "events_read": self.events_read,
            "peak_window_events": self.peak_window_events,
            "outputs": {k: str(v) for k, v in self.outputs.items()},
            "seconds": self.timings_s.get("total_s"),
            "timings_s": dict(self.timings_s),
        }


# ------------------------------------------------------------------------------ the run


def default_outputs(out: str | Path) -> tuple[Path, Path]:
    """The C3D and BVH written beside ``out`` with its stem: ``(<stem>.c3d, <stem>.bvh)``."""
    p = Path(out)
    return p.with_suffix(".c3d"), p.with_suffix(".bvh")


def _check_outputs(paths: Mapping[str, Path], overwrite: bool) -> None:
    for kind, p in paths.items():
        if p.suffix.lower() != f".{kind}":
            msg = f"the {kind.upper()} output {p} must end in .{kind}"
            raise ValidationError(msg)
        if p.exists() and not overwrite:
            msg = f"{p} exists; pass --overwrite to replace it"
            raise ProcessingError(msg)
        if not p.parent.is_dir():
            msg = f"cannot write {p}: folder {p.parent} does not exist; create it first"
            raise ProcessingError(msg)
    resolved = [p.resolve() for p in paths.values()]
    if len(set(resolved)) != len(resolved):
        msg = f"the outputs must be three different files, got {[str(p) for p in paths.values()]}"
        raise ValidationError(msg)


def check_coverage(detector: Detector, frames: Sequence[ApsFrame], source: str) -> None:
    """Every used APS frame must have a detection (the batch fit anchors on them)."""
    # A RecordingFrames knows its frames' times from the index (no image decoded).
    times = frames.times_us if isinstance(frames, RecordingFrames) else [f.t_us for f in frames]
    for k, t_k in enumerate(times):
        t = int(t_k)
        try:
            detector.detect(t, None)
        except (RecordingError, ValidationError, ProcessingError) as err:
            msg = (
                f"detections {source} do not cover APS frame {k} at {t} µs ({err}); run the "
                "detector on every APS frame of the recording, or narrow --start/--end/--batches "
                "to frames it covers"
            )
            raise ProcessingError(msg) from err


def run_eventcap(
    session: str | Path,
    calibration: Calibration | str | Path,
    *,
    out: str | Path,
    detections: str | Path,
    detections_format: DetectionsFormat = "auto",
    c3d: str | Path | None = None,
    bvh: str | Path | None = None,
    davis: str | None = None,
    height_m: float | None = None,
    shape_path: str | Path | None = None,
    batches: int | None = None,
    start_s: float | None = None,
    end_s: float | None = None,
    template: TemplateView = "capsules",
    options: EventcapOptions | None = None,
    overwrite: bool = False,
    progress: Callable[[str, int, int], None] | None = None,
) -> EventcapRunResult:
    """Run EventCap on a recording's DAVIS and write MCAP, C3D and BVH results (module doc).

    Args:
        session: The recording (``.mcap``).
        calibration: Its calibration (a DAVIS camera entry is required), or the file's path.
        out: The results MCAP (``.mcap``).
        detections: Detections file or folder (:func:`load_detector`).
        detections_format: Its format (``"auto"`` guesses, see :data:`DetectionsFormat`).
        c3d, bvh: Output paths (default: beside ``out``, same stem).
        davis: The DAVIS serial when the recording has several.
        height_m, shape_path: The template (:func:`load_shape`; exactly one).
        batches: Run only the first N batches (default: all).
        start_s, end_s: Use the APS frames exposed inside this span of the DAVIS timeline (s
            since its timestamp reset).
        template: Draw the fitted capsules on :data:`TEMPLATE_TOPIC` (``"none"`` leaves it out).
        options: Pipeline settings (``step_us`` must be 1000: 1 kHz output).
        overwrite: Replace existing outputs.
        progress: ``(stage, done, total)`` callback (``"index"``, ``"batches"``, ``"write"``).

    Raises:
        ValidationError: a bad option. RecordingError: no DAVIS, no events, no frames.
        CalibrationError: the calibration has no DAVIS entry. ProcessingError: fewer than 2
            APS frames selected, detections that do not cover them, a batch that failed, or an
            output that exists.
    """
    t_start = time.perf_counter()
    opt = options if options is not None else EventcapOptions()
    if opt.step_us != 1000:
        msg = (
            "run_eventcap writes 1 kHz results; EventcapOptions.step_us must be 1000, "
            f"got {opt.step_us}"
        )
        raise ValidationError(msg)
    if batches is not None and batches < 1:
        msg = f"--batches must be >= 1, got {batches}"
        raise ValidationError(msg)
    if start_s is not None and end_s is not None and end_s <= start_s:
        msg = f"--end {end_s} s must be after --start {start_s} s"
        raise ValidationError(msg)
    if template not in ("capsules", "none"):
        msg = f"template must be 'capsules' or 'none', got {template!r}"
        raise ValidationError(msg)
    session_path = Path(session)
    c3d_default, bvh_default = default_outputs(out)
    paths = {
        "mcap": Path(out),
        "c3d": Path(c3d) if c3d is not None else c3d_default,
        "bvh": Path(bvh) if bvh is not None else bvh_default,
    }
    _check_outputs(paths, overwrite)
    shape = load_shape(height_m=height_m, shape_path=shape_path)
    cal_source = "(given)" if isinstance(calibration, Calibration) else str(calibration)
    cal = calibration if isinstance(calibration, Calibration) else read_calibration(calibration)

    def report(stage: str, done: int, total: int) -> None:
        if progress is not None:
            progress(stage, done, total)

    with Recording(session_path) as rec:
        dav = select_davis(rec, davis)
        camera = EventCamera.from_calibration(davis_calibration(cal, dav, cal_source))
        report("index", 0, 2)
        t0 = time.perf_counter()
        frames = select_frames(dav, start_s=start_s, end_s=end_s, batches=batches)
        report("index", 1, 2)
        events = RecordingEventSource(dav)
        report("index", 2, 2)
        t_index = time.perf_counter() - t0
        if len(frames) < 2:
            msg = (
                f"{session_path}: {len(frames)} APS frame(s) of DAVIS {dav.device.serial} in the "
                f"selected span ({len(frames.all_times_us)} in the recording); EventCap needs at "
                "least 2 (widen --start/--end, or record longer)"
            )
            raise ProcessingError(msg)
        detector = load_detector(detections, frames.all_times_us, kind=detections_format)
        check_coverage(detector, frames, str(detections))
        clock, time_base = results_clock(cal, dav.device.label)
        if clock is None:
            _log.info(
                "%s: the calibration maps no clock for %s; results stamped in DAVIS time",
                session_path,
                dav.device.label,
            )
        times_us = frames.times_us
        t_first_us, t_last_us = int(times_us[0]), int(times_us[-1])
        header = ResultsHeader(
            session=session_path,
            davis=dav.device.label,
            batches=len(frames) - 1,
            frames=(t_last_us - t_first_us) // opt.step_us + 1,
            time_base=time_base,
            t_first_davis_us=t_first_us,
            world_frame=cal.world_frame,
            detection_source=detector.source,
        )

        t0 = time.perf_counter()
        stage: dict[str, float] = {}
        t_write = 0.0
        with EventcapResultsWriter(
            header,
            shape,
            mcap=paths["mcap"],
            c3d=paths["c3d"],
            bvh=paths["bvh"],
            calibration=cal,
            template=template,
            overwrite=overwrite,
        ) as writer:
            for chunk in iter_take(events, frames, detector, camera, shape, options=opt):
                for k, v in chunk.result.stage_seconds.items():
                    stage[f"{k}_s"] = stage.get(f"{k}_s", 0.0) + v
                tw = time.perf_counter()
                writer.write(results_ns(clock, chunk.t_us), chunk.poses, chunk.keypoints_m)
                t_write += time.perf_counter() - tw
                report("batches", chunk.batch + 1, chunk.batches)
            report("write", 0, 1)
            tw = time.perf_counter()
        t_write += time.perf_counter() - tw
        report("write", 1, 1)
        t_take = time.perf_counter() - t0
    timings = {
        "index_s": t_index,
        **stage,
        "take_s": t_take,
        "write_s": t_write,
        "total_s": time.perf_counter() - t_start,
    }
    result = EventcapRunResult(
        header=header,
        outputs=paths,
        frames_total=len(frames.all_times_us),
        frames_used=len(frames),
        t_first_ns=writer.t_first_ns,
        events_read=events.events_read,
        peak_window_events=events.peak_window_events,
        timings_s=timings,
    )
    _log.info(
        "%s: %d batches, %d frames at 1 kHz, %.1f s",
        session_path,
        result.batches,
        header.frames,
        timings["total_s"],
    )
    return result


# ------------------------------------------------------------------------------ writers


_JOINT_RGBA: Final = (0.2, 0.5, 1.0, 1.0)
#: Tracking frames whose capsules are posed at once while writing the MCAP.
_CAPSULE_BLOCK: Final = 1000


def keypoint_scene(frame_id: str, t_ns: int, keypoints_m: F64) -> SceneUpdateMsg:
    """The 19 keypoints ``(19, 3)`` world m as a scene update: 30 mm spheres, a label each and
    :data:`KEYPOINT_BONES` as one line list (``names`` in the metadata, sphere order)."""
    return points_scene(
        "eventcap_joints",
        frame_id,
        t_ns,
        keypoints_m,
        0.03,
        _JOINT_RGBA,
        {"names": ",".join(EVENTCAP_KEYPOINTS)},
        names=EVENTCAP_KEYPOINTS,
        bones=KEYPOINT_BONES,
    )


def template_scene(frame_id: str, t_ns: int, a_m: F64, b_m: F64, radius_m: F64) -> SceneUpdateMsg:
    """The posed capsule template (end points ``a_m``, ``b_m`` (C, 3) world m, radii (C,) m)."""
    return capsule_scene("eventcap_template", frame_id, t_ns, a_m, b_m, radius_m)


class EventcapResultsWriter:
    """The run's MCAP, C3D and BVH (module doc), written block by block as the batches finish.

    Memory is bounded by a block: each :meth:`write` goes to the three files at once (the MCAP
    through a :class:`~acquire.recorder.Recorder`, the C3D through
    :class:`~calib.c3d_write.C3DFrameWriter`, the BVH through
    :class:`~process.body.bvh_export.BvhWriter`). Every file is written beside its path and
    moved into place when the ``with`` block ends without an error; on an error nothing is
    left behind. Outputs given as None are not written.

    Args:
        header: What the files say about the run; ``header.frames`` frames must be written.
        shape: The template (the BVH skeleton and the capsules).
        mcap, c3d, bvh: Output paths (at least one).
        calibration: Attached to the MCAP as ``calibration.toml``.
        template: Draw the fitted capsules on :data:`TEMPLATE_TOPIC` (``"none"`` leaves it out).
        overwrite: Replace existing outputs.

    Raises:
        ProcessingError: an output exists and ``overwrite`` is False, a write failed, or the
            frames written are not ``header.frames``.
    """

    def __init__(
        self,
        header: ResultsHeader,
        shape: BodyShape,
        *,
        mcap: str | Path | None = None,
        c3d: str | Path | None = None,
        bvh: str | Path | None = None,
        calibration: Calibration | None = None,
        template: TemplateView = "capsules",
        overwrite: bool = False,
    ) -> None:
        from mocaprig.calib.c3d_write import C3DFrameWriter
        from mocaprig.calib.calibration import calibration_bytes
        from mocaprig.process.body.bvh_export import BvhWriter

        if mcap is None and c3d is None and bvh is None:
            msg = "EventcapResultsWriter: give at least one of mcap, c3d, bvh"
            raise ValidationError(msg)
        if template not in ("capsules", "none"):
            msg = f"template must be 'capsules' or 'none', got {template!r}"
            raise ValidationError(msg)
        self.header = header
        self._shape = shape
        self._overwrite = overwrite
        self._written = 0
        self._t_first_ns: int | None = None
        self._closed = False
        self._c3d: C3DFrameWriter | None = None
        self._bvh: BvhWriter | None = None
        self._rec: Recorder | None = None
        self._mcap = None if mcap is None else Path(mcap)
        if self._mcap is not None and self._mcap.exists() and not overwrite:
            msg = f"{self._mcap} exists; pass --overwrite to replace it"
            raise ProcessingError(msg)
        try:
            if c3d is not None:
                self._c3d = C3DFrameWriter(
                    c3d,
                    labels=tuple(EVENTCAP_KEYPOINTS),
                    rate_hz=_RATE_HZ,
                    unit="mm",
                    source=str(header.session),
                    overwrite=overwrite,
                )
            if bvh is not None:
                self._bvh = BvhWriter(bvh, shape, rate_hz=_RATE_HZ, overwrite=overwrite)
            if self._mcap is not None:
                attachments = []
                if calibration is not None:
                    attachments.append(
                        Attachment(
                            ATTACHMENT_NAME, "application/toml", calibration_bytes(calibration)
                        )
                    )
                self._tmp = self._mcap.with_name(f".{self._mcap.name}.{os.getpid()}.part")
                # The recorder's own diagnostics are stamped on the results' clock: one time
                # base (0 until the first block arrives, then the last frame time written).
                self._now = [0]
                self._rec = Recorder(
                    self._tmp,
                    metadata={METADATA_NAME: header.record()},
                    attachments=attachments,
                    clock_ns=lambda: self._now[0],
                    min_free_disk_bytes=0,
                )
                self._rec.start()
                meta = {
                    "frame_id": header.world_frame,
                    "units": "m",
                    "log_time": f"{header.time_base} ns",
                }
                self._hj = self._rec.add_stream(
                    JOINTS_TOPIC, SceneUpdateMsg, metadata={**meta, "content": "joints"}
                )
                self._ht = (
                    self._rec.add_stream(
                        TEMPLATE_TOPIC, SceneUpdateMsg, metadata={**meta, "content": "template"}
                    )
                    if template == "capsules"
                    else None
                )
        except Exception as err:
            self.discard()
            if isinstance(err, (ProcessingError, ValidationError)):
                raise
            msg = f"cannot start the results files ({err}); check the folder and free space"
            raise ProcessingError(msg) from err

    def __enter__(self) -> EventcapResultsWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.discard()

    @property
    def frames_written(self) -> int:
        """Tracking frames written so far."""
        return self._written

    @property
    def t_first_ns(self) -> int:
        """The first written frame's time (ns on the header's time base)."""
        if self._t_first_ns is None:
            msg = "no results were written"
            raise ProcessingError(msg)
        return self._t_first_ns

    def write(self, t_ns: npt.ArrayLike, poses: F64, keypoints_m: F64) -> None:
        """Append tracking frames: times ``(n,)`` ns on the header's time base, increasing;
        poses ``(n, 33)``; keypoints ``(n, 19, 3)`` world m."""
        from mocaprig.process.body.surface import capsules

        t = np.asarray(t_ns, dtype=np.int64)
        n = t.size
        if poses.shape != (n, POSE_DIM) or keypoints_m.shape != (n, len(EVENTCAP_KEYPOINTS), 3):
            msg = (
                f"results block: {n} times, poses {poses.shape}, keypoints {keypoints_m.shape}; "
                "expected (n,), (n, 33), (n, 19, 3)"
            )
            raise ValidationError(msg)
        if n == 0:
            return
        if self._t_first_ns is None:
            self._t_first_ns = int(t[0])
        try:
            if self._c3d is not None:
                self._c3d.write(keypoints_m)
            if self._bvh is not None:
                self._bvh.write(poses)
            if self._rec is not None:
                frame = self.header.world_frame
                for i0 in range(0, n, _CAPSULE_BLOCK):
                    i1 = min(i0 + _CAPSULE_BLOCK, n)
                    caps = capsules(poses[i0:i1], self._shape) if self._ht is not None else None
                    for i in range(i0, i1):
                        ti = int(t[i])
                        self._now[0] = ti
                        seq = self._written + i
                        scene = keypoint_scene(frame, ti, keypoints_m[i])
                        self._rec.put_wait(self._hj, scene, log_time_ns=ti, sequence=seq)
                        if self._ht is not None and caps is not None:
                            k = i - i0
                            cap = template_scene(frame, ti, caps.a_m[k], caps.b_m[k], caps.radius_m)
                            self._rec.put_wait(self._ht, cap, log_time_ns=ti, sequence=seq)
        except Exception as err:
            self.discard()
            if isinstance(err, (ProcessingError, ValidationError)):
                raise
            msg = f"writing the results failed ({err}); check the folder and free space"
            raise ProcessingError(msg) from err
        self._written += n

    def close(self) -> None:
        """Finish the files and move them into place (all or none)."""
        if self._closed:
            return
        if self._written != self.header.frames:
            self.discard()
            msg = (
                f"the results hold {self._written} tracking frames, but the run announced "
                f"{self.header.frames}; nothing was written"
            )
            raise ProcessingError(msg)
        try:
            if self._rec is not None:
                self._rec.close()
                self._rec.raise_if_failed()
            if self._c3d is not None:
                self._c3d.close()
            if self._bvh is not None:
                self._bvh.close()
            if self._rec is not None and self._mcap is not None:
                replace_atomically(self._tmp, self._mcap, overwrite=self._overwrite)
                _log.info("wrote %s (%d frames)", self._mcap, self._written)
        except Exception as err:
            self.discard()
            if isinstance(err, ProcessingError):
                raise
            msg = f"finishing the results failed ({err}); check the folder and free space"
            raise ProcessingError(msg) from err
        self._closed = True

    def discard(self) -> None:
        """Stop and remove every partial file (nothing new is left at the output paths)."""
        self._closed = True
        if self._rec is not None:
            with contextlib.suppress(Exception):
                self._rec.close()
            self._tmp.unlink(missing_ok=True)
        if self._c3d is not None:
            self._c3d.discard()
        if self._bvh is not None:
            self._bvh.discard()
