"""Live DeMoCap on the rig: D415 cameras -> rig instants -> joints, written into a recording.

:func:`run_live` configures the cameras (master/slave, :func:`acquire.d415_sync.configure_rig`),
starts them master first, and polls them round-robin. Each camera's frame sets (the driver's
:class:`~acquire.depth_camera.FrameSet`, as in a recording) get their device time unwrapped once
(:class:`~mocaprig.timebase.U32Unwrapper`) and mapped onto the calibration's reference clock,
and the one instant rule (:class:`~.instants.InstantGrouper`, as the replay) groups them. The
instants stream through :class:`~.live.LivePipeline` (the replay's stages, on two threads) and
each result is written through the :class:`~acquire.recorder.Recorder` as
``foxglove.SceneUpdate`` on the replay's topics (log time: host receive time; the entity stamp:
the instant's reference time), so the file opens in Foxglove as a replay's does.

A camera that stops delivering holds the others back at most ``max_lag`` frame periods; a
frame the recorder cannot take is dropped and counted in the file, never waited for.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np

from mocaprig.acquire.d415_sync import configure_rig, iter_framesets, start_rig
from mocaprig.acquire.depth_camera import (
    DepthCamera,
    FrameSet,
    SensorOptions,
    StreamConfig,
)
from mocaprig.acquire.device_id import DeviceId
from mocaprig.acquire.recorder import Attachment, Recorder
from mocaprig.acquire.recording_format import SceneUpdateMsg
from mocaprig.calib.calibration import Calibration, calibration_bytes
from mocaprig.calib.calibration_attachment import ATTACHMENT_NAME
from mocaprig.errors import ProcessingError
from mocaprig.process.democap.instants import INSTANT_TOLERANCE, GroupedInstant, InstantGrouper
from mocaprig.process.democap.live import (
    CloudPredictor,
    LiveCamera,
    LivePipeline,
    LiveResult,
    live_predictor,
)
from mocaprig.process.democap.replay import (
    JOINTS_TOPIC,
    MARKERS_TOPIC,
    marker_scene,
    skeleton_scene,
)
from mocaprig.timebase import U32Unwrapper
from mocaprig.validation import check_positive

__all__ = ["LIVE_METADATA_NAME", "LiveInstant", "LiveSummary", "rig_instants", "run_live"]

_log = logging.getLogger(__name__)

#: Name of the MCAP metadata record describing a live run.
LIVE_METADATA_NAME: Final = "democap_live"
#: How long a frame waits for the other cameras' frames of its instant (frame periods).
_MAX_LAG_PERIODS: Final = 3


@dataclass(frozen=True, slots=True)
class LiveInstant:
    """One rig instant as it came off the cameras: reference time (ns) and a frame set per
    camera label (None: that camera's frame is missing)."""

    t_ref_ns: int
    frames: dict[str, FrameSet | None] = field(repr=False)


@dataclass(frozen=True, slots=True)
class LiveSummary:
    """What :func:`run_live` did (figures for ``--json``)."""

    cameras: tuple[str, ...]
    seconds: float
    frame_sets: dict[str, int]
    instants: int
    predicted: int
    wall_s: float
    fps: float
    latency_ms_p50: float | None
    out: Path | None
    drops: int | None
    #: instants measured but skipped to keep up with the cameras (the network was behind;
    #: each is logged in the results file's ``/log``)
    skipped: int = 0
    #: seconds the predictor's warm-up took before the cameras started (the compile)
    warm_up_s: float = 0.0
    #: whether the network ran compiled (None: a predictor that does not say)
    compiled: bool | None = None
    #: standing height (m) of the subject every instant was solved as (None: none)
    subject_height_m: float | None = None

    def as_dict(self) -> dict[str, Any]:
        return {
            "cameras": list(self.cameras),
            "seconds": self.seconds,
            "frame_sets": dict(self.frame_sets),
            "instants": self.instants,
            "predicted": self.predicted,
            "wall_s": self.wall_s,
            "fps": self.fps,
            "latency_ms_p50": self.latency_ms_p50,
            "out": None if self.out is None else str(self.out),
            "drops": self.drops,
            "skipped": self.skipped,
            "warm_up_s": self.warm_up_s,
            "compiled": self.compiled,
            "subject_height_m": self.subject_height_m,
        }


def rig_instants(
    cameras: Sequence[DepthCamera],
    calibration: Calibration,
    *,
    seconds: float,
    fps: int = 30,
    tolerance: float = INSTANT_TOLERANCE,
    stop: threading.Event | None = None,
    stall_s: float = 2.0,
    counts: dict[str, int] | None = None,
) -> Iterator[LiveInstant]:
    """Rig instants of started cameras for ``seconds`` of their host time (module doc).

    ``counts`` (optional) is filled with the frame sets received per camera. Frames without a
    hardware stamp are placed by their host time.

    Raises:
        CalibrationError: a camera has no calibration entry or clock mapping.
    """
    check_positive(seconds, name="seconds")
    labels = [DeviceId("d415", c.info.serial).label for c in cameras]
    clocks = {label: calibration.clock(label) for label in labels}
    period = round(1e9 / fps)
    grouper: InstantGrouper[FrameSet] = InstantGrouper(
        labels, period, tolerance=tolerance, max_lag_ns=_MAX_LAG_PERIODS * period
    )
    unwrap = {label: U32Unwrapper() for label in labels}
    seen = counts if counts is not None else {}
    for label in labels:
        seen.setdefault(label, 0)

    def emit(grouped: Sequence[GroupedInstant[FrameSet]]) -> Iterator[LiveInstant]:
        for g in grouped:
            yield LiveInstant(g.instant.t_ref_ns, {c: g.items.get(c) for c in labels})

    for fs in iter_framesets(cameras, seconds=seconds, stall_s=stall_s, stop=stop):
        label = DeviceId("d415", fs.serial).label
        seen[label] += 1
        stamp = fs.timing.sensor_timestamp_us
        t_dev = fs.timing.host_time_ns if stamp is None else unwrap[label](int(stamp)) * 1000
        t_ref = int(clocks[label].to_reference_ns(np.int64(t_dev)))
        yield from emit(grouper.push(label, t_ref, t_dev, fs))
    yield from emit(grouper.flush())


def run_live(
    cameras: Sequence[DepthCamera],
    calibration: Calibration,
    *,
    seconds: float,
    out: Path | None = None,
    predictor: CloudPredictor | None = None,
    stream: StreamConfig | None = None,
    options: SensorOptions | None = None,
    on_result: Callable[[LiveResult, LiveInstant], None] | None = None,
    stop: threading.Event | None = None,
) -> LiveSummary:
    """Run DeMoCap live on opened D415 cameras for ``seconds`` (module doc).

    Args:
        cameras: The rig's D415s, opened (the first is the sync master).
        calibration: Poses and clock mappings of every camera.
        seconds: How long to capture (camera host time).
        out: The results recording (``.mcap``; never overwritten); None writes nothing.
        predictor: The network (default: :func:`~.live.live_predictor`, 2 turns).
        stream, options: Camera mode and sensor options (defaults: 848x480@30, manual exposure).
        on_result: Called with each result and its instant (a status line, a live view).
        stop: Set it to end the capture early (Ctrl-C).

    Raises:
        DeviceError: no camera, or a camera fails.
        CalibrationError: a camera is not in the calibration.
        RecordingError: ``out`` exists or cannot be written.
    """
    if not cameras:
        msg = "no D415 camera to run on; connect the rig or use --mock"
        raise ProcessingError(msg)
    mode = StreamConfig() if stream is None else stream
    configure_rig(cameras, stream=mode, options=options)
    labels = tuple(DeviceId("d415", c.info.serial).label for c in cameras)
    live_cams = []
    for cam, label in zip(cameras, labels, strict=True):
        intr = cam.intrinsics()
        live_cams.append(
            LiveCamera.from_calibration(
                calibration,
                label,
                K=intr.camera_matrix(),
                distortion=np.asarray(intr.coeffs, dtype=np.float64),
                depth_scale_m=cam.depth_scale_m,
            )
        )
    pred = live_predictor() if predictor is None else predictor
    # a compiled network compiles here (and logs it), before the cameras stream
    warm_up = getattr(pred, "warm_up", None)
    warm_up_s = float(warm_up()) if callable(warm_up) else 0.0
    counts: dict[str, int] = {}
    latencies: list[float] = []
    instants = predicted = skipped = 0
    drops: int | None = None
    t_start = time.monotonic()
    with contextlib.ExitStack() as stack:
        recorder: Recorder | None = None
        handles: dict[str, Any] = {}
        if out is not None:
            recorder = stack.enter_context(
                Recorder(
                    Path(out),
                    metadata={LIVE_METADATA_NAME: _metadata(labels, calibration, pred)},
                    attachments=[
                        Attachment(
                            ATTACHMENT_NAME, "application/toml", calibration_bytes(calibration)
                        )
                    ],
                )
            )
            meta = {"frame_id": calibration.world_frame, "units": "m"}
            for topic, content in ((MARKERS_TOPIC, "markers"), (JOINTS_TOPIC, "joints")):
                handles[content] = recorder.add_stream(
                    topic, SceneUpdateMsg, metadata={**meta, "content": content}
                )
        start_rig(cameras)
        stack.callback(_stop_all, cameras)
        source = rig_instants(
            cameras, calibration, seconds=seconds, fps=mode.fps, stop=stop, counts=counts
        )
        pending: collections.deque[LiveInstant] = collections.deque()

        def frames() -> Iterator[dict[str, FrameSet | None]]:
            for inst in source:
                pending.append(inst)
                yield inst.frames

        pipeline = stack.enter_context(LivePipeline(pred, live_cams, workers=1))
        # keep_up: a network slower than the cameras skips sets rather than falling behind
        for res in pipeline.stream(frames(), keep_up=True):
            inst = pending.popleft()
            instants += 1
            if res.skipped:
                skipped += 1
                if recorder is not None:
                    recorder.log(
                        "WARNING",
                        f"instant {inst.t_ref_ns} ns skipped: the network was behind the cameras",
                        name="democap_live",
                    )
            else:
                latencies.append(res.timings_ms["latency_ms"])
            if res.prediction is not None:
                predicted += 1
                if recorder is not None:
                    info = {"cameras": str(res.cameras_used), "points": str(res.points)}
                    frame = calibration.world_frame
                    p = res.prediction
                    recorder.put(
                        handles["markers"],
                        marker_scene(frame, inst.t_ref_ns, p.markers_m, info),
                        sequence=instants,
                    )
                    recorder.put(
                        handles["joints"],
                        skeleton_scene(frame, inst.t_ref_ns, p.joints_m, info),
                        sequence=instants,
                    )
            if on_result is not None:
                on_result(res, inst)
        if recorder is not None:
            drops = recorder.status().dropped_total
    wall = time.monotonic() - t_start
    if skipped:
        _log.warning(
            "%d of %d instants skipped: the network was behind the cameras", skipped, instants
        )
    return LiveSummary(
        cameras=labels,
        seconds=float(seconds),
        frame_sets=counts,
        instants=instants,
        predicted=predicted,
        wall_s=wall,
        fps=instants / wall if wall > 0 else 0.0,
        latency_ms_p50=float(np.median(latencies)) if latencies else None,
        out=None if out is None else Path(out),
        drops=drops,
        skipped=skipped,
        warm_up_s=warm_up_s,
        compiled=getattr(pred, "compiled", None),
        subject_height_m=_subject_height_m(pred),
    )


def _subject_height_m(predictor: CloudPredictor) -> float | None:
    subject = getattr(predictor, "subject", None)
    return None if subject is None else float(subject.standing_height_m)


def _stop_all(cameras: Sequence[DepthCamera]) -> None:
    for cam in cameras:
        cam.stop()


def _metadata(
    labels: Sequence[str], calibration: Calibration, predictor: CloudPredictor
) -> dict[str, str]:
    from mocaprig import __version__

    ck = getattr(predictor, "checkpoint", None)
    return {
        "software_version": __version__,
        "cameras": ",".join(labels),
        "reference_clock": calibration.reference_clock,
        "world_frame": calibration.world_frame,
        "checkpoint": "" if ck is None else f"{ck.config.name} ({ck.epoch} epochs)",
        "rotations": str(getattr(predictor, "rotations", "")),
        "compiled": str(getattr(predictor, "compiled", "")),
        "subject_height_m": "" if (h := _subject_height_m(predictor)) is None else f"{h:.4f}",
    }
