"""DeMoCap replay on a recording: D415 markers -> rig instants -> labelled markers + joints.

:func:`run_replay` takes a recording (``mocaprig record`` / ``simulate``) and its calibration
(``mocaprig calibrate vicon``) and:

1. lists every D415 frame's device time (:meth:`~acquire.device_streams.RecordedD415.frame_index`,
   no image decoded)
   and maps it onto the calibration's reference clock with that camera's
   :class:`~mocaprig.calib.calibration.ClockMapping`;
2. groups the frames into **rig instants** (:func:`~.instants.group_instants`, the rule of
   :mod:`mocaprig.process.democap.instants`: frames closer than ``tolerance`` × the median frame
   period, ¼ by default, to the instant's first frame join it, one per camera; an instant seen
   by fewer cameras, a dropped frame, is still processed);
3. keeps every ``every``-th instant and reads only its frames, as the driver's
   :class:`~acquire.depth_camera.FrameSet` (:func:`~acquire.device_streams.read_frame_sets`);
4. feeds them to :class:`~mocaprig.process.democap.live.LivePipeline`, the live path itself:
   per camera IR blobs, depth, deprojection (:func:`calib.markers.measure_frame`, the
   camera's recorded ``camera_info`` intrinsics), camera -> world with the calibrated pose, the
   capture-box crop of the training data (:data:`DEFAULT_CROP_BOX_M`), the 10 mm merge of the
   views, then :class:`~mocaprig.process.democap.infer.DemocapPredictor` (instants whose cloud
   has fewer than 2 points are skipped and counted);
5. keeps each instant's labelled markers, joints and fused cloud;
6. writes the results (:func:`write_scene_mcap`, :func:`write_replay_c3d`,
   :func:`write_replay_csv`).

The steps are functions of their own, so that a long recording can run in parallel (``mocaprig
process``, docs/cluster.md): :func:`plan_replay` (1, 2 and the choice of 3),
:func:`replay_span` (the reading of 3, then 4–5, on any span of the instants: each instant
stands alone), :func:`join_spans` and :func:`write_replay` (6);
:func:`run_replay` chains them over one span of every instant.

Outputs (docs/democap.md "Replay"):

* **MCAP** (Foxglove): channels :data:`MARKERS_TOPIC`, :data:`JOINTS_TOPIC` and
  :data:`CLOUD_TOPIC`, schema ``foxglove.SceneUpdate`` (protobuf), one message per instant,
  ``log_time`` = ``publish_time`` = the instant's reference time (ns), frame = the calibration's
  world frame. Markers: 53 spheres (14 mm); joints: 19 spheres (30 mm), the bones of
  :data:`process.body.DEMOCAP_PARENTS` as one line list and a text label per joint; cloud: the
  fused input points (10 mm). Each entity's metadata holds ``names`` (comma-separated, in
  sphere order), ``cameras`` and ``points``. The file carries a ``democap_replay`` metadata
  record (inputs, checkpoint, counts) and the calibration as the ``calibration.toml`` attachment.
* **C3D** (:func:`calib.vicon.write_c3d`, mm): the 53 markers then the 19 joints as ``J_<joint>``;
  POINT:RATE = the frame rate / ``every``; row *i* is the instant nearest to the first instant's
  reference time + *i* periods; rows without an instant are gaps; first frame 1 (the exact
  reference times are in the CSV and the MCAP).
* **CSV**: a header line, then one line per instant: ``time_s`` (reference clock, s, 9
  decimals, exact from the ns), then ``<name>_x,<name>_y,<name>_z`` (mm, 3 decimals, world frame)
  for the 53 markers and the 19 ``J_<joint>`` joints.

Units: metres and ns inside; mm in the C3D and CSV.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from itertools import pairwise
from pathlib import Path
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.depth_camera import FrameSet
from mocaprig.acquire.device_id import DeviceId
from mocaprig.acquire.device_streams import (
    D415FrameIndex,
    D415Intrinsics,
    RecordedD415,
    d415_devices,
    read_frame_sets,
)
from mocaprig.acquire.recorder import Attachment, Recorder
from mocaprig.acquire.recording import Recording
from mocaprig.acquire.recording_format import SceneUpdateMsg
from mocaprig.calib.calibration import Calibration, read_calibration
from mocaprig.calib.calibration_attachment import ATTACHMENT_NAME
from mocaprig.errors import CalibrationError, ProcessingError, RecordingError, ValidationError
from mocaprig.process.body import DEMOCAP_JOINTS, DEMOCAP_PARENTS, MARKER_NAMES
from mocaprig.process.democap.evaluate import EVAL_JOINTS
from mocaprig.process.democap.infer import DemocapPredictor, Prediction
from mocaprig.process.democap.instants import (
    INSTANT_TOLERANCE,
    Grouping,
    Instant,
    group_instants,
)
from mocaprig.process.democap.live import LiveCamera, LivePipeline
from mocaprig.process.democap.simdata import CAPTURE_BOX_M, Box, Camera, check_crop_box
from mocaprig.process.democap.solve import SubjectCalibration
from mocaprig.process.metrics import PoseMetrics, pose_metrics
from mocaprig.process.outputs import replace_atomically
from mocaprig.process.scene import points_scene

__all__ = [
    "CLOUD_TOPIC",
    "DEFAULT_CROP_BOX_M",
    "INSTANT_TOLERANCE",
    "JOINTS_TOPIC",
    "JOINT_LABEL_PREFIX",
    "MARKERS_TOPIC",
    "METADATA_NAME",
    "SUBJECT_INSTANTS",
    "Grouping",
    "Instant",
    "ReplayPlan",
    "ReplayResult",
    "ReplaySpan",
    "SubjectFit",
    "cloud_scene",
    "default_outputs",
    "fit_subject",
    "group_instants",
    "join_spans",
    "marker_scene",
    "output_paths",
    "plan_replay",
    "replay_span",
    "run_replay",
    "score_replay",
    "skeleton_scene",
    "write_replay",
    "write_replay_c3d",
    "write_replay_csv",
    "write_scene_mcap",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

MARKERS_TOPIC: Final = "/democap/markers"
JOINTS_TOPIC: Final = "/democap/joints"
CLOUD_TOPIC: Final = "/democap/cloud"
#: Name of the MCAP metadata record describing the replay.
METADATA_NAME: Final = "democap_replay"
#: Prefix of the joint labels in the C3D and the CSV (``J_Hips``...).
JOINT_LABEL_PREFIX: Final = "J_"
#: The capture box of the training data (world, m): ``((x0, x1), (y0, y1), (z0, z1))``.
DEFAULT_CROP_BOX_M: Final = CAPTURE_BOX_M


# ------------------------------------------------------------------------------ result


@dataclass(frozen=True, slots=True, eq=False)
class ReplayResult:
    """What :func:`run_replay` produced.

    Attributes:
        session: The recording.
        outputs: ``{"mcap": ..., "c3d": ..., "csv": ...}`` paths written.
        cameras: The D415s of the recording (``d415/<serial>``).
        frames_per_camera: Frames of each camera in the recording.
        t_ref_ns: ``(N,)`` reference time of each instant written (ns).
        cameras_per_instant: ``(N,)`` cameras whose frame fed each instant.
        points_per_instant: ``(N,)`` points of each fused cloud.
        markers_m: ``(N, 53, 3)`` labelled markers (world, m), :data:`MARKER_NAMES` order.
        joints_m: ``(N, 19, 3)`` joints (world, m), :data:`DEMOCAP_JOINTS` order.
        instants_total: Instants found in the recording (before ``every``).
        skipped_instants: Selected instants not written (fused cloud under 2 points).
        every: Every n-th instant was processed.
        period_ns: Median frame period on the reference clock (ns).
        reference_clock: The calibration's reference clock (``"vicon"``).
        world_frame: The calibration's world frame.
        checkpoint: ``"<config> (<epochs> epochs)"`` of the network used.
        rotations: size of the rotation ensemble used (1: single shot).
        solve: whether the estimates are skeleton solves (:mod:`.solve`; else the
            network's own).
        subject_height_m: the standing height (m) of the calibrated subject every instant
            was solved as (:mod:`.subject`); None: every instant on its own.
        timings_s: Wall seconds per stage (``measure_s``, ``network_s``, ``write_s``,
            ``total_s``; summed over spans when the replay ran in spans).
        clouds_m: The N fused input clouds ``(Mi, 3)`` (world, m); empty when not kept.
    """

    session: Path
    outputs: Mapping[str, Path]
    cameras: tuple[str, ...]
    frames_per_camera: Mapping[str, int]
    t_ref_ns: I64 = field(repr=False)
    cameras_per_instant: I64 = field(repr=False)
    points_per_instant: I64 = field(repr=False)
    markers_m: F64 = field(repr=False)
    joints_m: F64 = field(repr=False)
    instants_total: int = 0
    skipped_instants: int = 0
    every: int = 1
    period_ns: int = 0
    reference_clock: str = "vicon"
    world_frame: str = "vicon"
    checkpoint: str = ""
    rotations: int = 1
    solve: bool = False
    subject_height_m: float | None = None
    timings_s: Mapping[str, float] = field(default_factory=dict)
    clouds_m: tuple[F64, ...] = field(default=(), repr=False)

    @property
    def instants(self) -> int:
        """Instants written."""
        return int(self.t_ref_ns.size)

    @property
    def camera_histogram(self) -> dict[int, int]:
        """Instants written per number of cameras that saw them, ``{cameras: instants}``."""
        counts = np.bincount(self.cameras_per_instant, minlength=len(self.cameras) + 1)
        return {k: int(n) for k, n in enumerate(counts) if n and k}

    @property
    def mean_points(self) -> float:
        """Mean points per fused cloud (NaN without instants)."""
        return float(self.points_per_instant.mean()) if self.instants else float("nan")

    def summary(self) -> dict[str, Any]:
        """A JSON-ready summary (what ``democap run --json`` prints)."""
        return {
            "session": str(self.session),
            "instants": self.instants,
            "instants_total": self.instants_total,
            "skipped_instants": self.skipped_instants,
            "every": self.every,
            "rate_hz": 1e9 / (self.period_ns * self.every) if self.period_ns else None,
            "cameras": list(self.cameras),
            "frames_per_camera": dict(self.frames_per_camera),
            "instants_by_camera_count": {str(k): v for k, v in self.camera_histogram.items()},
            "mean_points_per_instant": self.mean_points,
            "t_first_ns": int(self.t_ref_ns[0]) if self.instants else None,
            "t_last_ns": int(self.t_ref_ns[-1]) if self.instants else None,
            "reference_clock": self.reference_clock,
            "world_frame": self.world_frame,
            "checkpoint": self.checkpoint,
            "rotations": self.rotations,
            "solve": self.solve,
            "subject_height_m": self.subject_height_m,
            "outputs": {k: str(v) for k, v in self.outputs.items()},
            "seconds": self.timings_s.get("total_s"),
            "timings_s": dict(self.timings_s),
        }


def score_replay(
    result: ReplayResult, true_joints_m: npt.ArrayLike, true_markers_m: npt.ArrayLike | None = None
) -> PoseMetrics:
    """Figures of a replay against true joints (and markers) at its instants.

    MPJPE is over the paper's 17 joints (no toes, :data:`~process.democap.evaluate.EVAL_JOINTS`)
    as in :func:`~mocaprig.process.democap.evaluate.evaluate`, MPMPE over the 53 markers.

    Args:
        result: The replay.
        true_joints_m: ``(N, 19, 3)`` true joints at ``result.t_ref_ns`` (world, m).
        true_markers_m: ``(N, 53, 3)`` true marker centres, or None.

    Raises:
        ValidationError: shapes that do not match the replay.
    """
    tj = np.asarray(true_joints_m, dtype=np.float64)
    if tj.shape != result.joints_m.shape:
        msg = f"true_joints_m has shape {tj.shape}, the replay {result.joints_m.shape}"
        raise ValidationError(msg)
    tm = None if true_markers_m is None else np.asarray(true_markers_m, dtype=np.float64)
    if tm is not None and tm.shape != result.markers_m.shape:
        msg = f"true_markers_m has shape {tm.shape}, the replay {result.markers_m.shape}"
        raise ValidationError(msg)
    keep = list(EVAL_JOINTS)
    return pose_metrics(
        result.joints_m[:, keep] * 1e3,
        tj[:, keep] * 1e3,
        pred_markers_mm=None if tm is None else result.markers_m * 1e3,
        true_markers_mm=None if tm is None else tm * 1e3,
    )


# ------------------------------------------------------------------------------ the run


def default_outputs(out: str | Path) -> tuple[Path, Path]:
    """The C3D and CSV written beside ``out`` with its stem: ``(<stem>.c3d, <stem>.csv)``."""
    p = Path(out)
    return p.with_suffix(".c3d"), p.with_suffix(".csv")


def _check_outputs(paths: Mapping[str, Path], overwrite: bool) -> None:
    suffix = {"mcap": ".mcap", "c3d": ".c3d", "csv": ".csv"}
    for kind, p in paths.items():
        if p.suffix.lower() != suffix[kind]:
            msg = f"the {kind.upper()} output {p} must end in {suffix[kind]}"
            raise ValidationError(msg)
        if p.exists() and not overwrite:
            msg = f"{p} exists; pass --overwrite to replace it"
            raise ProcessingError(msg)
        if not p.parent.is_dir():
            msg = f"cannot write {p}: folder {p.parent} does not exist"
            raise ProcessingError(msg)
    resolved = [p.resolve() for p in paths.values()]
    if len(set(resolved)) != len(resolved):
        msg = f"the outputs must be three different files, got {[str(p) for p in paths.values()]}"
        raise ValidationError(msg)


def _check_calibrated(
    cal: Calibration, cameras: Sequence[str], session: Path, cal_source: str
) -> None:
    names = [c.name for c in cal.cameras]
    todo = (
        f"calibrate the rig with this recording: mocaprig calibrate vicon {session} VICON.c3d "
        "--out calib.toml (every D415 of the recording needs a pose and a clock)"
    )
    for cam in cameras:
        if cam not in names:
            msg = (
                f"{session}: camera {cam} has no entry in the calibration {cal_source} "
                f"(it has {names}); {todo}"
            )
            raise ProcessingError(msg)
        try:
            cal.clock(cam)
        except CalibrationError as err:
            msg = (
                f"{session}: camera {cam} has no clock mapping in the calibration {cal_source} "
                f"(it has {[c.device for c in cal.clocks]}), so its frames cannot be put on the "
                f"{cal.reference_clock} clock; {todo}"
            )
            raise ProcessingError(msg) from err


@dataclass(frozen=True, slots=True, eq=False)
class ReplayPlan:
    """A recording's rig instants, ready to be processed whole or in spans (:func:`plan_replay`).

    Small and picklable (frame indexes and times, no image): what a worker needs beside the
    recording and the calibration, which it reads where they are.

    Attributes:
        session: The recording.
        cameras: Its D415s (``d415/<serial>``), sorted.
        index: Camera -> its frame index (no image decoded).
        intrinsics: Camera -> its recorded ``camera_info`` intrinsics.
        instants: The selected instants (every ``every``-th), in time order.
        instants_total: Instants found in the recording (before ``every``).
        offset: Index of ``instants[0]`` among the whole plan's (a span's plan,
            :meth:`span`; 0 for a whole plan).
        every: Every n-th instant is selected.
        period_ns: Median frame period on the reference clock (ns).
        reference_clock: The calibration's reference clock.
        world_frame: The calibration's world frame.
    """

    session: Path
    cameras: tuple[str, ...]
    index: Mapping[str, D415FrameIndex] = field(repr=False)
    intrinsics: Mapping[str, D415Intrinsics] = field(repr=False)
    instants: tuple[Instant, ...] = field(repr=False)
    instants_total: int = 0
    every: int = 1
    period_ns: int = 0
    reference_clock: str = "vicon"
    world_frame: str = "vicon"
    offset: int = 0

    @property
    def frames_per_camera(self) -> dict[str, int]:
        """Frames of each camera in the recording."""
        return {c: len(self.index[c]) for c in self.cameras}

    def spans(self, size: int) -> list[tuple[int, int]]:
        """The selected instants cut into ``[start, stop)`` spans of at most ``size``.

        Raises:
            ValidationError: ``size`` < 1.
        """
        if isinstance(size, bool) or int(size) != size or size < 1:
            msg = f"a span needs at least 1 instant, got {size!r}"
            raise ValidationError(msg)
        n = len(self.instants)
        return [(a, min(a + int(size), n)) for a in range(0, n, int(size))] or [(0, 0)]

    def span(self, start: int, stop: int) -> ReplayPlan:
        """The plan of the instants ``[start, stop)`` alone: their frames' entries of the
        index and nothing else, so that a worker is sent little (``offset`` = ``start``).

        Raises:
            ValidationError: a span outside the plan.
        """
        n = len(self.instants)
        if not 0 <= start <= stop <= n:
            msg = f"span [{start}, {stop}) is not within the plan's {n} instants"
            raise ValidationError(msg)
        instants = self.instants[start:stop]
        index = {}
        for c in self.cameras:
            ix = self.index[c]
            wanted = np.fromiter((i.frames[c] for i in instants if c in i.frames), dtype=np.int64)
            keep = np.isin(ix.t_dev_ns, wanted)
            index[c] = replace(
                ix,
                log_time_ns=ix.log_time_ns[keep],
                sequence=ix.sequence[keep],
                frame_counter=ix.frame_counter[keep],
                t_dev_ns=ix.t_dev_ns[keep],
            )
        return replace(self, index=index, instants=instants, offset=self.offset + start)


@dataclass(frozen=True, slots=True, eq=False)
class ReplaySpan:
    """DeMoCap's results on the instants ``[start, stop)`` of a plan (:func:`replay_span`).

    Attributes:
        start, stop: The span, indices into :attr:`ReplayPlan.instants`.
        t_ref_ns: ``(N,)`` reference time of each instant with a result (ns).
        cameras_per_instant: ``(N,)`` cameras whose frame fed it.
        markers_m: ``(N, 53, 3)`` labelled markers (world, m).
        joints_m: ``(N, 19, 3)`` joints (world, m).
        clouds_m: N fused clouds ``(Mi, 3)`` (world, m).
        skipped: Instants of the span without a result (fused cloud under 2 points).
        measure_s, network_s: Seconds spent measuring + merging, and in the network.
        checkpoint: ``"<config> (<epochs> epochs)"`` of the network.
        rotations: Size of its rotation ensemble.
        solve: Whether its estimates are skeleton solves.
        subject_height_m: Standing height (m) of the subject it solved every instant as
            (None: none).
    """

    start: int
    stop: int
    t_ref_ns: I64 = field(repr=False)
    cameras_per_instant: I64 = field(repr=False)
    markers_m: F64 = field(repr=False)
    joints_m: F64 = field(repr=False)
    clouds_m: tuple[F64, ...] = field(repr=False)
    skipped: int = 0
    measure_s: float = 0.0
    network_s: float = 0.0
    checkpoint: str = ""
    rotations: int = 1
    solve: bool = False
    subject_height_m: float | None = None


def _check_every(every: int) -> None:
    if isinstance(every, bool) or int(every) != every or every < 1:
        msg = f"every must be an integer >= 1, got {every!r}"
        raise ValidationError(msg)


def _check_span_options(
    predictor: DemocapPredictor | None, crop_box_m: Box | None, batch: int
) -> None:
    if isinstance(batch, bool) or int(batch) != batch or batch < 1:
        msg = f"batch must be an integer >= 1, got {batch!r}"
        raise ValidationError(msg)
    if crop_box_m is not None:
        check_crop_box(crop_box_m)
    if predictor is not None and not predictor.predicts_markers:
        msg = (
            f"the checkpoint is a {predictor.checkpoint.config.variant!r} baseline, which "
            "estimates no markers; the replay writes markers, so use a markers-to-pose one"
        )
        raise ProcessingError(msg)


def _read_calibration(calibration: Calibration | str | Path) -> tuple[Calibration, str]:
    if isinstance(calibration, Calibration):
        return calibration, "given"
    return read_calibration(calibration), str(calibration)


def plan_replay(
    session: str | Path,
    calibration: Calibration | str | Path,
    *,
    every: int = 1,
    tolerance: float = INSTANT_TOLERANCE,
) -> ReplayPlan:
    """Steps 1–3 of the replay (module doc) but the reading: index the D415 frames, put them on
    the reference clock, group them into instants and select every ``every``-th.

    Raises:
        ValidationError: bad ``every`` or ``tolerance``.
        ProcessingError: no D415 stream, or a camera without calibration entry or clock.
        CalibrationError: the calibration file is unreadable, or a D415 stream has no
            ``camera_info``.
        RecordingError: the recording is unreadable.
    """
    _check_every(every)
    session_path = Path(session)
    cal, cal_source = _read_calibration(calibration)
    with Recording(session_path) as rec:
        d415 = {d.label: RecordedD415(rec, d) for d in d415_devices(rec)}
        if not d415:
            msg = f"{session_path}: no D415 stream in the recording; nothing to replay"
            raise ProcessingError(msg)
        cameras = tuple(sorted(d415))
        try:
            index = {c: d415[c].frame_index() for c in cameras}
            intrinsics = {c: d415[c].intrinsics() for c in cameras}
        except RecordingError as err:
            raise CalibrationError(str(err)) from err
    _check_calibrated(cal, cameras, session_path, cal_source)
    t_dev = {c: np.sort(index[c].t_dev_ns) for c in cameras}
    t_ref = {c: cal.clock(c).to_reference_ns(t_dev[c]) for c in cameras}
    grouping = group_instants(t_dev, t_ref, tolerance=tolerance)
    selected = tuple(grouping.instants[:: int(every)])
    _log.info(
        "%s: %d instants from %d cameras (period %.3f ms), %d selected (every %d)",
        session_path,
        len(grouping.instants),
        len(cameras),
        grouping.period_ns / 1e6,
        len(selected),
        every,
    )
    return ReplayPlan(
        session=session_path,
        cameras=cameras,
        index=index,
        intrinsics=intrinsics,
        instants=selected,
        instants_total=len(grouping.instants),
        every=int(every),
        period_ns=grouping.period_ns,
        reference_clock=cal.reference_clock,
        world_frame=cal.world_frame,
    )


def replay_span(
    plan: ReplayPlan,
    calibration: Calibration | str | Path,
    *,
    start: int = 0,
    stop: int | None = None,
    predictor: DemocapPredictor | None = None,
    crop_box_m: Box | None = DEFAULT_CROP_BOX_M,
    merge_radius_m: float = 0.010,
    batch: int = 16,
    progress: Callable[[int, int], None] | None = None,
) -> ReplaySpan:
    """Step 3's reading and steps 4–5 of the replay (module doc) on the instants
    ``plan.instants[start:stop]`` (indices of the returned span count from the whole plan's
    first instant, ``plan.offset``).

    Each instant is processed on its own (no state is carried from one to the next), so spans
    of one plan can run anywhere, in any order, and :func:`join_spans` gives what one span
    over all instants gives.

    Args:
        plan: From :func:`plan_replay`.
        calibration: The plan's calibration (or its path).
        start, stop: The span (``stop`` None: to the end).
        predictor, crop_box_m, merge_radius_m, batch, progress: As :func:`run_replay`.

    Raises:
        ValidationError: a bad span, ``batch`` or ``crop_box_m``.
        ProcessingError: the checkpoint estimates no markers (the ``"pose"`` baseline).
        RecordingError: the recording is unreadable.
    """
    n = len(plan.instants)
    stop = n if stop is None else stop
    if not 0 <= start <= stop <= n:
        msg = f"span [{start}, {stop}) is not within the plan's {n} instants"
        raise ValidationError(msg)
    _check_span_options(predictor, crop_box_m, batch)
    cal, _ = _read_calibration(calibration)
    pred = predictor if predictor is not None else DemocapPredictor()
    selected = plan.instants[start:stop]
    live_cams = _live_cameras(plan, cal)
    clouds: list[F64] = []
    preds: list[Prediction] = []
    kept: list[tuple[int, int]] = []  # (t_ref_ns, cameras)
    skipped = 0
    t_measure = t_network = 0.0
    with (
        Recording(plan.session) as rec,
        LivePipeline(
            pred,
            live_cams,
            crop_box_m=crop_box_m,
            merge_radius_m=merge_radius_m,
            queue_size=max(2, int(batch)),
        ) as pipeline,
    ):
        frames = _instant_frames(rec, plan.index, selected)
        for inst, res in zip(selected, pipeline.stream(frames), strict=True):
            t_measure += (res.timings_ms["measure_ms"] + res.timings_ms["merge_ms"]) / 1e3
            t_network += res.timings_ms["predict_ms"] / 1e3
            if res.prediction is None:
                skipped += 1
            else:
                clouds.append(res.cloud_m)
                preds.append(res.prediction)
                kept.append((inst.t_ref_ns, res.cameras_used))
            if progress is not None:
                progress(len(kept) + skipped, len(selected))
    ck = pred.checkpoint
    return ReplaySpan(
        start=plan.offset + start,
        stop=plan.offset + stop,
        t_ref_ns=np.array([t for t, _ in kept], dtype=np.int64),
        cameras_per_instant=np.array([c for _, c in kept], dtype=np.int64),
        markers_m=np.stack([p.markers_m for p in preds]) if preds else _empty(len(MARKER_NAMES)),
        joints_m=np.stack([p.joints_m for p in preds]) if preds else _empty(len(DEMOCAP_JOINTS)),
        clouds_m=tuple(clouds),
        skipped=skipped,
        measure_s=t_measure,
        network_s=t_network,
        checkpoint=f"{ck.config.name} ({ck.epoch} epochs)",
        rotations=pred.rotations,
        solve=pred.solves,
        subject_height_m=None if pred.subject is None else pred.subject.standing_height_m,
    )


def _live_cameras(plan: ReplayPlan, cal: Calibration) -> list[LiveCamera]:
    """The plan's cameras as the pipeline measures them: each camera's own intrinsics (its
    recorded ``camera_info``) and its calibrated pose."""
    return [
        LiveCamera.from_calibration(
            cal,
            c,
            K=plan.intrinsics[c].k,
            distortion=plan.intrinsics[c].distortion,
            depth_scale_m=plan.index[c].depth_scale_m,
        )
        for c in plan.cameras
    ]


def _empty(points: int) -> F64:
    return np.zeros((0, points, 3), dtype=np.float64)


def join_spans(
    plan: ReplayPlan, spans: Sequence[ReplaySpan], *, outputs: Mapping[str, Path]
) -> ReplayResult:
    """The :class:`ReplayResult` of spans that together cover every instant of the whole
    ``plan`` once (in any order; their clouds are in :attr:`ReplayResult.clouds_m`).

    Raises:
        ValidationError: the spans do not tile the plan's instants, or came from different
            networks.
        ProcessingError: no instant has a usable cloud.
    """
    if plan.offset:
        msg = f"join_spans needs the whole plan, got the span's plan from instant {plan.offset}"
        raise ValidationError(msg)
    ordered = sorted(spans, key=lambda s: s.start)
    edges = [(s.start, s.stop) for s in ordered]
    tiles = bool(ordered) and ordered[0].start == 0 and ordered[-1].stop == len(plan.instants)
    if not tiles or any(a[1] != b[0] for a, b in pairwise(edges)):
        msg = f"spans {edges} do not cover the plan's {len(plan.instants)} instants once"
        raise ValidationError(msg)
    nets = {(s.checkpoint, s.rotations, s.solve, s.subject_height_m) for s in ordered}
    if len(nets) != 1:
        msg = f"the spans were processed by different networks: {sorted(nets)}"
        raise ValidationError(msg)
    skipped = sum(s.skipped for s in ordered)
    if skipped:
        _log.warning("%s: %d instants skipped (fewer than 2 points)", plan.session, skipped)
    clouds = tuple(c for s in ordered for c in s.clouds_m)
    if not clouds:
        msg = (
            f"{plan.session}: none of the {len(plan.instants)} instants has 2 or more marker "
            "points after the merge; are the markers lit and inside the capture box?"
        )
        raise ProcessingError(msg)
    checkpoint, rotations, solve, subject_height_m = nets.pop()
    return ReplayResult(
        session=plan.session,
        outputs=dict(outputs),
        cameras=plan.cameras,
        frames_per_camera=plan.frames_per_camera,
        t_ref_ns=np.concatenate([s.t_ref_ns for s in ordered]),
        cameras_per_instant=np.concatenate([s.cameras_per_instant for s in ordered]),
        points_per_instant=np.array([c.shape[0] for c in clouds], dtype=np.int64),
        markers_m=np.concatenate([s.markers_m for s in ordered]),
        joints_m=np.concatenate([s.joints_m for s in ordered]),
        instants_total=plan.instants_total,
        skipped_instants=skipped,
        every=plan.every,
        period_ns=plan.period_ns,
        reference_clock=plan.reference_clock,
        world_frame=plan.world_frame,
        checkpoint=checkpoint,
        rotations=rotations,
        solve=solve,
        subject_height_m=subject_height_m,
        clouds_m=clouds,
        timings_s={
            "measure_s": sum(s.measure_s for s in ordered),
            "network_s": sum(s.network_s for s in ordered),
        },
    )


def output_paths(
    out: str | Path, *, c3d: str | Path | None = None, csv: str | Path | None = None
) -> dict[str, Path]:
    """``{"mcap", "c3d", "csv"}`` paths of a replay's outputs (C3D and CSV default beside
    ``out``, :func:`default_outputs`)."""
    out_path = Path(out)
    c3d_default, csv_default = default_outputs(out_path)
    return {
        "mcap": out_path,
        "c3d": c3d_default if c3d is None else Path(c3d),
        "csv": csv_default if csv is None else Path(csv),
    }


def write_replay(
    result: ReplayResult, calibration: Calibration | str | Path, *, overwrite: bool = False
) -> ReplayResult:
    """Step 6: write ``result`` to its outputs (MCAP with its clouds and the calibration
    attached, C3D, CSV); returns it with ``write_s`` in its timings.

    Raises:
        ProcessingError, ValidationError, ViconFileError: as the three writers.
    """
    cal, _ = _read_calibration(calibration)
    paths = result.outputs
    _check_outputs(paths, overwrite)
    t0 = time.monotonic()
    write_scene_mcap(
        result, paths["mcap"], clouds=result.clouds_m, calibration=cal, overwrite=overwrite
    )
    write_replay_c3d(result, paths["c3d"], overwrite=overwrite)
    write_replay_csv(result, paths["csv"], overwrite=overwrite)
    return replace(result, timings_s={**result.timings_s, "write_s": time.monotonic() - t0})


def run_replay(
    session: str | Path,
    calibration: Calibration | str | Path,
    *,
    out: str | Path,
    c3d: str | Path | None = None,
    csv: str | Path | None = None,
    predictor: DemocapPredictor | None = None,
    every: int = 1,
    overwrite: bool = False,
    crop_box_m: Box | None = DEFAULT_CROP_BOX_M,
    merge_radius_m: float = 0.010,
    tolerance: float = INSTANT_TOLERANCE,
    batch: int = 16,
    progress: Callable[[int, int], None] | None = None,
) -> ReplayResult:
    """Replay a recording through DeMoCap (module doc) and write MCAP, C3D and CSV results:
    :func:`plan_replay`, one :func:`replay_span` over every instant, :func:`join_spans`,
    :func:`write_replay`.

    Args:
        session: The recording (``.mcap``) with D415 streams.
        calibration: Its calibration, or the path of the calibration file.
        out: The results MCAP (``.mcap``).
        c3d: The C3D (default: beside ``out``, same stem, ``.c3d``).
        csv: The CSV (default: beside ``out``, same stem, ``.csv``).
        predictor: The network (default: the committed ``lite`` checkpoint).
        every: Process every n-th instant (1 = all).
        overwrite: Replace existing outputs.
        crop_box_m: Points outside this world box (m) are dropped before the merge; None keeps
            every point. Default: the capture box of the training data.
        merge_radius_m: Views' points closer than this are merged (m).
        tolerance: Instant grouping tolerance (fraction of the frame period).
        batch: Measured instants held ready for the network (the live pipeline's queue).
        progress: Optional ``(done, total)`` callback over the instants (the marker measurement
            draws its own bar on stderr when this is given).

    Returns:
        The :class:`ReplayResult` (the outputs are written).

    Raises:
        ProcessingError: an output exists (without ``overwrite``), the recording has no D415
            stream, a camera of the recording has no calibration entry or clock mapping, or
            no instant has a usable cloud; the checkpoint does not match or estimates no
            markers (the ``"pose"`` baseline).
        ValidationError: bad ``every``, ``batch``, ``tolerance`` or output suffixes.
        CalibrationError: the calibration file is unreadable, or a D415 stream of the
            recording has no ``camera_info`` (intrinsics).
        RecordingError: the recording is unreadable.
    """
    t_start = time.monotonic()
    _check_every(every)
    _check_span_options(predictor, crop_box_m, batch)
    paths = output_paths(out, c3d=c3d, csv=csv)
    _check_outputs(paths, overwrite)
    cal, _ = _read_calibration(calibration)
    plan = plan_replay(session, cal, every=every, tolerance=tolerance)
    span = replay_span(
        plan,
        cal,
        predictor=predictor if predictor is not None else DemocapPredictor(),
        crop_box_m=crop_box_m,
        merge_radius_m=merge_radius_m,
        batch=batch,
        progress=progress,
    )
    result = write_replay(join_spans(plan, [span], outputs=paths), cal, overwrite=overwrite)
    result = replace(result, timings_s={**result.timings_s, "total_s": time.monotonic() - t_start})
    _log.info(
        "%s: %d instants written (%s cameras per instant), %.1f points per cloud, %.1f s",
        plan.session,
        result.instants,
        result.camera_histogram,
        result.mean_points,
        result.timings_s["total_s"],
    )
    return result


#: Instants :func:`fit_subject` calibrates from by default, spread evenly over the recording.
SUBJECT_INSTANTS: Final = 40


@dataclass(frozen=True, slots=True, eq=False)
class SubjectFit:
    """A subject calibrated from a recording of them (:func:`fit_subject`).

    Attributes:
        subject: The calibration (:func:`.subject.save_subject` writes it).
        session: The recording.
        t_ref_ns: ``(N,)`` reference times of the instants it was made from (ns).
        instants_total: Instants in the recording.
        skipped_instants: Chosen instants whose fused cloud had under 2 points.
        rounds: Rounds of calibration.
        frame_heights_m: ``(N,)`` the standing height each instant's own solve found (m):
            their spread is what the calibration removes.
        seconds: Wall time.
    """

    subject: SubjectCalibration
    session: Path
    t_ref_ns: I64 = field(repr=False)
    instants_total: int = 0
    skipped_instants: int = 0
    rounds: int = 1
    frame_heights_m: F64 = field(default_factory=lambda: np.zeros(0), repr=False)
    seconds: float = 0.0

    def summary(self) -> dict[str, Any]:
        """A JSON-ready summary (what ``democap subject --json`` prints, beside the file)."""
        h = self.frame_heights_m
        return {
            "session": str(self.session),
            "instants": int(self.t_ref_ns.size),
            "instants_total": self.instants_total,
            "skipped_instants": self.skipped_instants,
            "rounds": self.rounds,
            "standing_height_m": self.subject.standing_height_m,
            "scale": self.subject.scale,
            "girth": self.subject.girth,
            "frame_by_frame_height_m": {
                "median": float(np.median(h)),
                "p10": float(np.percentile(h, 10)),
                "p90": float(np.percentile(h, 90)),
            },
            "segment_lengths_m": self.subject.segment_lengths_m,
            "seconds": self.seconds,
        }


class _KeepClouds:
    """A pipeline's predictor that keeps each cloud with the views the pipeline gives it, for
    one solve over all of them afterwards, and answers with the network alone meanwhile."""

    def __init__(self, network: DemocapPredictor) -> None:
        self.network = network
        self.clouds: list[F64] = []
        self.views: list[list[Camera]] = []

    def predict_many(
        self,
        clouds: Sequence[npt.ArrayLike],
        *,
        views: Sequence[Sequence[Camera]] | None = None,
        crop_box_m: Box | None = None,
    ) -> list[Prediction]:
        out = self.network.predict_many(clouds)
        self.clouds.extend(np.asarray(c, np.float64) for c in clouds)
        self.views.extend(list(v) for v in (views or [[]] * len(clouds)))
        return out


def fit_subject(
    session: str | Path,
    calibration: Calibration | str | Path,
    *,
    instants: int = SUBJECT_INSTANTS,
    rounds: int = 1,
    start_s: float | None = None,
    end_s: float | None = None,
    predictor: DemocapPredictor | None = None,
    crop_box_m: Box | None = DEFAULT_CROP_BOX_M,
    merge_radius_m: float = 0.010,
    tolerance: float = INSTANT_TOLERANCE,
    progress: Callable[[int, int], None] | None = None,
) -> SubjectFit:
    """Calibrate the subject of a recording (one actor; a range-of-motion take is best): the
    replay's pipeline on ``instants`` instants spread evenly over it (over its part from
    ``start_s`` to ``end_s``, seconds after its first instant, when given: the take's
    range-of-motion or static section), each cloud solved on its own, then the subject's
    lengths and marker placement from those solves and every cloud solved again with them,
    ``rounds`` times (:meth:`~.infer.DemocapPredictor.predict_subject`).

    Raises:
        ValidationError: ``instants`` < 3, ``rounds`` < 1, ``end_s`` not after ``start_s``,
            a bad ``crop_box_m``, or a predictor that does not solve.
        ProcessingError: fewer than 3 of the chosen instants have a usable cloud, or the
            part holds fewer than 3 instants; what :func:`plan_replay` raises.
        CalibrationError, RecordingError: as :func:`plan_replay`.
    """
    t0 = time.monotonic()
    if isinstance(instants, bool) or int(instants) != instants or instants < 3:
        msg = f"a subject is fitted from at least 3 instants, got {instants!r}"
        raise ValidationError(msg)
    if isinstance(rounds, bool) or int(rounds) != rounds or rounds < 1:
        msg = f"rounds must be an integer >= 1, got {rounds!r}"
        raise ValidationError(msg)
    lo_s = 0.0 if start_s is None else float(start_s)
    hi_s = np.inf if end_s is None else float(end_s)
    if not hi_s > lo_s:
        msg = f"end_s ({end_s}) must be after start_s ({start_s})"
        raise ValidationError(msg)
    pred = predictor if predictor is not None else DemocapPredictor()
    if not pred.solves:
        msg = "a subject is fitted by the skeleton solve; give a predictor with solve=True"
        raise ValidationError(msg)
    _check_span_options(pred, crop_box_m, 1)
    cal, _ = _read_calibration(calibration)
    plan = plan_replay(session, cal, tolerance=tolerance)
    n = len(plan.instants)
    t_ns = np.array([i.t_ref_ns for i in plan.instants], dtype=np.int64)
    t_s = (t_ns - (t_ns[0] if n else 0)) / 1e9
    part = np.flatnonzero((t_s >= lo_s) & (t_s <= hi_s))
    if len(part) < 3:
        msg = (
            f"{plan.session}: {len(part)} instants between {lo_s:g} and {hi_s:g} s of its "
            f"{t_s[-1] if n else 0:.2f} s; a subject needs at least 3"
        )
        raise ProcessingError(msg)
    at = np.linspace(0, len(part) - 1, min(int(instants), len(part))).round().astype(np.int64)
    chosen = [plan.instants[int(i)] for i in part[np.unique(at)]]
    keep = _KeepClouds(DemocapPredictor(pred.checkpoint, rotations=1, solve=False))
    times: list[int] = []
    with (
        Recording(plan.session) as rec,
        LivePipeline(
            keep, _live_cameras(plan, cal), crop_box_m=crop_box_m, merge_radius_m=merge_radius_m
        ) as pipeline,
    ):
        frames = _instant_frames(rec, plan.index, chosen)
        for k, (inst, res) in enumerate(zip(chosen, pipeline.stream(frames), strict=True)):
            if res.prediction is not None:
                times.append(inst.t_ref_ns)
            if progress is not None:
                progress(k + 1, len(chosen))
    if len(keep.clouds) < 3:
        msg = (
            f"{plan.session}: {len(keep.clouds)} of the {len(chosen)} chosen instants have 2 or "
            "more marker points; a subject needs at least 3 (is the actor inside the capture "
            "box? try more --instants)"
        )
        raise ProcessingError(msg)
    fit = pred.predict_subject(
        keep.clouds, views=keep.views, crop_box_m=crop_box_m, rounds=int(rounds)
    )
    heights = np.array([p.height_m for p in fit.frame_by_frame], dtype=np.float64)
    result = SubjectFit(
        subject=fit.calibration,
        session=plan.session,
        t_ref_ns=np.array(times, dtype=np.int64),
        instants_total=n,
        skipped_instants=len(chosen) - len(keep.clouds),
        rounds=int(rounds),
        frame_heights_m=heights,
        seconds=time.monotonic() - t0,
    )
    _log.info(
        "%s: subject of %.3f m from %d instants (frame by frame %.3f-%.3f m), %.1f s",
        plan.session,
        fit.calibration.standing_height_m,
        len(keep.clouds),
        float(np.percentile(heights, 10)),
        float(np.percentile(heights, 90)),
        result.seconds,
    )
    return result


def _instant_frames(
    rec: Recording,
    index: Mapping[str, D415FrameIndex],
    instants: Sequence[Instant],
) -> Iterator[dict[str, FrameSet | None]]:
    """The recording's frame sets of each instant, by camera (None: not in the file), in
    instant order, read in one pass over the file (only the frames of ``instants`` decoded)."""
    seq_of = {
        c: dict(zip(ix.t_dev_ns.tolist(), ix.sequence.tolist(), strict=True))
        for c, ix in index.items()
    }
    devices = {c: ix.device for c, ix in index.items()}
    slot: dict[tuple[str, int], int] = {}
    wanted: dict[DeviceId, set[int]] = {d: set() for d in devices.values()}
    logs: list[int] = []
    log_of = {
        c: dict(zip(ix.sequence.tolist(), ix.log_time_ns.tolist(), strict=True))
        for c, ix in index.items()
    }
    for k, inst in enumerate(instants):
        for c, d in inst.frames.items():
            seq = seq_of[c][d]
            slot[devices[c].serial, seq] = k
            wanted[devices[c]].add(seq)
            logs.append(log_of[c][seq])
    need = [len(inst.frames) for inst in instants]
    got: dict[int, dict[str, FrameSet]] = {}
    label = {d.serial: c for c, d in devices.items()}
    nxt = 0

    def take(k: int) -> dict[str, FrameSet | None]:
        have = got.pop(k, {})
        return {c: have.get(c) for c in index}

    if logs:
        for rfs in read_frame_sets(
            rec, sorted(wanted), start_ns=min(logs), end_ns=max(logs) + 1, sequences=wanted
        ):
            pos = slot.get((rfs.frames.serial, rfs.sequence))
            if pos is None:
                continue
            got.setdefault(pos, {})[label[rfs.frames.serial]] = rfs.frames
            while nxt < len(instants) and len(got.get(nxt, {})) == need[nxt]:
                yield take(nxt)
                nxt += 1
    while nxt < len(instants):  # frames missing from the file: what there is
        yield take(nxt)
        nxt += 1


# ------------------------------------------------------------------------------ writers


def _labels() -> tuple[list[str], list[str]]:
    return list(MARKER_NAMES), [f"{JOINT_LABEL_PREFIX}{j}" for j in DEMOCAP_JOINTS]


def write_replay_csv(result: ReplayResult, path: str | Path, *, overwrite: bool = False) -> Path:
    """Write the replay as CSV (module doc): ``time_s`` then ``<name>_x/_y/_z`` in mm.

    Raises:
        ProcessingError: ``path`` exists and ``overwrite`` is False.
    """
    dst = Path(path)
    if dst.exists() and not overwrite:
        msg = f"{dst} exists; pass --overwrite to replace it"
        raise ProcessingError(msg)
    markers, joints = _labels()
    header = ["time_s"] + [f"{n}_{a}" for n in markers + joints for a in "xyz"]
    values = np.concatenate([result.markers_m, result.joints_m], axis=1).reshape(
        result.instants, -1
    )
    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.tmp")
    with tmp.open("w", encoding="utf-8", newline="\n") as fh:
        fh.write(",".join(header) + "\n")
        for t, row in zip(result.t_ref_ns.tolist(), values * 1e3, strict=True):
            sec, ns = divmod(int(t), 1_000_000_000)
            fh.write(f"{sec}.{ns:09d}," + ",".join(f"{v:.3f}" for v in row) + "\n")
    replace_atomically(tmp, dst, overwrite=overwrite)
    _log.info("wrote %s (%d instants)", dst, result.instants)
    return dst


def write_replay_c3d(result: ReplayResult, path: str | Path, *, overwrite: bool = False) -> Path:
    """Write the replay as C3D (module doc): markers then ``J_<joint>``, mm, regular rows.

    Raises:
        ProcessingError: no instants.
        ViconFileError: ``path`` exists and ``overwrite`` is False, or the write failed.
    """
    from mocaprig.calib.vicon import MarkerTrajectories, write_c3d

    if not result.instants:
        msg = "the replay has no instants; nothing to write to a C3D file"
        raise ProcessingError(msg)
    period = float(result.period_ns * result.every)
    rows = np.rint((result.t_ref_ns - result.t_ref_ns[0]) / period).astype(np.int64)
    dupes = int(result.instants - np.unique(rows).size)
    if dupes:
        _log.warning(
            "%s: %d instants share a C3D row with an earlier one; kept the first", path, dupes
        )
    markers, joints = _labels()
    pos = np.full((int(rows[-1]) + 1, len(markers) + len(joints), 3), np.nan)
    both = np.concatenate([result.markers_m, result.joints_m], axis=1)
    for i in range(result.instants - 1, -1, -1):  # reversed: the first of a row wins
        pos[rows[i]] = both[i]
    traj = MarkerTrajectories(
        labels=tuple(markers + joints),
        rate_hz=1e9 / period,
        positions_m=pos,
        residuals_m=np.where(np.isnan(pos[..., 0]), np.nan, 0.0),
        first_frame=1,
        source_unit="mm",
        source=str(result.session),
        metadata={"software": "mocaprig democap run"},
    )
    return write_c3d(path, traj, unit="mm", overwrite=overwrite)


_MARKER_RGBA: Final = (1.0, 0.55, 0.1, 1.0)
_JOINT_RGBA: Final = (0.2, 0.5, 1.0, 1.0)
_CLOUD_RGBA: Final = (0.6, 0.6, 0.6, 0.6)


def cloud_scene(frame_id: str, t_ns: int, cloud_m: F64, info: Mapping[str, str]) -> SceneUpdateMsg:
    """The fused cloud the network saw at one instant, ``(M, 3)`` world m (10 mm grey
    spheres)."""
    return points_scene("cloud", frame_id, t_ns, cloud_m, 0.01, _CLOUD_RGBA, dict(info))


def marker_scene(
    frame_id: str, t_ns: int, markers_m: F64, info: Mapping[str, str]
) -> SceneUpdateMsg:
    """The labelled markers of one instant, ``(53, 3)`` world m, as a scene update (14 mm
    spheres; ``names`` in the metadata, in sphere order)."""
    meta = {"names": ",".join(MARKER_NAMES), **info}
    return points_scene("markers", frame_id, t_ns, markers_m, 0.014, _MARKER_RGBA, meta)


def skeleton_scene(
    frame_id: str, t_ns: int, joints_m: F64, info: Mapping[str, str]
) -> SceneUpdateMsg:
    """The joints of one instant, ``(19, 3)`` world m, as a scene update: 30 mm spheres, a text
    label per joint and the bones as one line list."""
    bones = [(j, p) for j, p in enumerate(DEMOCAP_PARENTS) if p >= 0]
    meta = {"names": ",".join(DEMOCAP_JOINTS), **info}
    joints = list(DEMOCAP_JOINTS)
    return points_scene(
        "skeleton", frame_id, t_ns, joints_m, 0.03, _JOINT_RGBA, meta, names=joints, bones=bones
    )


def write_scene_mcap(
    result: ReplayResult,
    path: str | Path,
    *,
    clouds: Sequence[npt.ArrayLike] | None = None,
    calibration: Calibration | None = None,
    overwrite: bool = False,
) -> Path:
    """Write the replay as a Foxglove MCAP (module doc): SceneUpdate per instant and channel.

    Args:
        result: The replay.
        path: Output ``.mcap``.
        clouds: The fused input clouds (one ``(Ni, 3)`` per instant, world m) for
            :data:`CLOUD_TOPIC`; None leaves that channel out.
        calibration: Attached as ``calibration.toml`` when given.
        overwrite: Replace an existing file.

    Raises:
        ProcessingError: ``path`` exists and ``overwrite`` is False, or the write failed.
    """
    from mocaprig.calib.calibration import calibration_bytes

    dst = Path(path)
    if dst.exists() and not overwrite:
        msg = f"{dst} exists; pass --overwrite to replace it"
        raise ProcessingError(msg)
    if clouds is not None and len(clouds) != result.instants:
        msg = f"clouds has {len(clouds)} entries for {result.instants} instants"
        raise ValidationError(msg)
    markers, joints = list(MARKER_NAMES), list(DEMOCAP_JOINTS)
    [(j, p) for j, p in enumerate(DEMOCAP_PARENTS) if p >= 0]
    frame = result.world_frame
    attachments = []
    if calibration is not None:
        attachments.append(
            Attachment(ATTACHMENT_NAME, "application/toml", calibration_bytes(calibration))
        )
    # The recorder's own diagnostics are stamped on the results' clock (the reference clock),
    # so the whole file has one time base.
    now = [int(result.t_ref_ns[0]) if result.instants else 0]
    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.part")
    try:
        with Recorder(
            tmp,
            metadata={METADATA_NAME: _metadata(result)},
            attachments=attachments,
            clock_ns=lambda: now[0],
            min_free_disk_bytes=0,
        ) as rec:
            meta = {"frame_id": frame, "units": "m", "log_time": f"{result.reference_clock} ns"}
            queue = max(16, result.instants)
            h = {}
            for topic, content in (
                (MARKERS_TOPIC, "markers"),
                (JOINTS_TOPIC, "joints"),
                (CLOUD_TOPIC, "cloud"),
            ):
                if content != "cloud" or clouds is not None:
                    h[content] = rec.add_stream(
                        topic,
                        SceneUpdateMsg,
                        metadata={**meta, "content": content},
                        queue_messages=queue,
                        queue_bytes=1 << 30,
                    )
            _names_m, _names_j = ",".join(markers), ",".join(joints)
            for i in range(result.instants):
                t = int(result.t_ref_ns[i])
                now[0] = t
                info = {
                    "cameras": str(int(result.cameras_per_instant[i])),
                    "points": str(int(result.points_per_instant[i])),
                }
                msgs = [
                    (h["markers"], marker_scene(frame, t, result.markers_m[i], info)),
                    (h["joints"], skeleton_scene(frame, t, result.joints_m[i], info)),
                ]
                if clouds is not None:
                    pts = np.asarray(clouds[i], dtype=np.float64).reshape(-1, 3)
                    msgs.append((h["cloud"], cloud_scene(frame, t, pts, info)))
                for handle, scene in msgs:
                    rec.put_wait(handle, scene, log_time_ns=t, sequence=i)
        replace_atomically(tmp, dst, overwrite=overwrite)
    except ProcessingError:
        raise
    except Exception as err:
        tmp.unlink(missing_ok=True)
        msg = f"{dst}: writing the results failed ({err}); check the folder and free space"
        raise ProcessingError(msg) from err
    _log.info("wrote %s (%d instants)", dst, result.instants)
    return dst


def _metadata(result: ReplayResult) -> dict[str, str]:
    from mocaprig import __version__

    return {
        "software_version": __version__,
        "session": str(result.session),
        "cameras": ",".join(result.cameras),
        "instants": str(result.instants),
        "instants_total": str(result.instants_total),
        "skipped_instants": str(result.skipped_instants),
        "every": str(result.every),
        "period_ns": str(result.period_ns),
        "reference_clock": result.reference_clock,
        "world_frame": result.world_frame,
        "checkpoint": result.checkpoint,
        "rotations": str(result.rotations),
        "solve": str(result.solve).lower(),
        "subject_height_m": (
            "" if result.subject_height_m is None else f"{result.subject_height_m:.4f}"
        ),
        "instants_by_camera_count": ",".join(
            f"{k}:{v}" for k, v in result.camera_histogram.items()
        ),
    }
