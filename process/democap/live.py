"""Live DeMoCap: one synchronised set of D415 IR + depth frames -> labelled markers + joints.

:class:`LivePipeline` takes, per rig instant, one frame per camera (the frames of the
hardware-synchronised D415s that exposed together): the driver's
:class:`~acquire.depth_camera.FrameSet`, as a live camera's ``poll()`` or a recording's
:func:`~acquire.device_streams.read_frame_sets` gives it, or bare ``(IR, depth)`` images. The
replay (:mod:`mocaprig.process.democap.replay`) is this pipeline fed from a recording, so live and
replay are one path:

1. **measure**, per camera (:func:`mocaprig.calib.markers.measure_frame`): IR blobs, robust depth,
   deprojection into the camera frame;
2. **merge**: camera -> world (:func:`mocaprig.calib.markers.to_world`), the capture-box crop of the
   training data (:func:`mocaprig.calib.markers.crop_volume` with
   :data:`~mocaprig.process.democap.replay.DEFAULT_CROP_BOX_M`), the 10 mm merge of the views
   (:func:`mocaprig.calib.markers.merge_views`, views in the pipeline's camera order;
   :func:`cameras_from_calibration` sorts them by name, as the replay does);
3. **predict**: :meth:`DemocapPredictor.predict_many` on the one cloud (whatever stages the
   predictor has: render, network, decode...; its ``last_timings_s`` are copied into the
   result's timings).

:meth:`LivePipeline.process` runs one set (the cameras measured on ``workers`` threads, the
calling thread included: OpenCV and most of numpy release the GIL). :meth:`LivePipeline.stream`
runs an iterable of sets as a two-stage pipeline: a producer thread measures and merges set
k + 1 while the calling thread runs the network on set k (bounded queue, order kept, the first
error of either stage raised in the caller at its position, the producer stopped when the
caller stops iterating). The pipeline owns a thread pool: use it as a context manager (or call
:meth:`LivePipeline.close`).

A camera whose frame is missing (``None`` in the set: a dropped frame) is left out of that
instant, as in the replay. An instant whose fused cloud has fewer than ``min_points`` points
gets no prediction (``LiveResult.prediction`` is None) rather than an error, so one empty
instant does not end a stream.

Torch runs with whatever ``torch.get_num_threads()`` the caller set; nothing here changes
global state (torch threads, OpenCV threads).

Units: metres (world frame of the cameras' ``T_world_cam``), milliseconds for timings.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Final, Protocol, TypeAlias, cast

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.depth_camera import FrameSet
from mocaprig.acquire.device_id import DeviceId
from mocaprig.calib.calibration import Calibration, cameras_of_kind
from mocaprig.calib.markers import (
    DEFAULT_MAX_AREA_PX,
    DEFAULT_MIN_AREA_PX,
    DEFAULT_THRESHOLD,
    MarkerFrame,
    check_blob_options,
    crop_volume,
    measure_frame,
    merge_views,
    to_world,
)
from mocaprig.errors import CalibrationError, ProcessingError, ValidationError
from mocaprig.process.democap.checkpoint import Checkpoint
from mocaprig.process.democap.infer import DemocapPredictor, Prediction
from mocaprig.process.democap.simdata import CAPTURE_BOX_M, Box, Camera, check_crop_box
from mocaprig.validation import check_finite, check_shape

__all__ = [
    "DEFAULT_MERGE_RADIUS_M",
    "DEFAULT_WORKERS",
    "LIVE_ROTATIONS",
    "CameraFrame",
    "CloudPredictor",
    "FramePair",
    "LiveCamera",
    "LivePipeline",
    "LiveResult",
    "RigFrames",
    "cameras_from_calibration",
    "live_predictor",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
# (ir, depth, metres per depth unit) of one camera, validated.
_Pair = tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint16], float]

#: The replay's merge radius (m).
DEFAULT_MERGE_RADIUS_M: Final = 0.010
#: Threads measuring one set's cameras by default: 1, so that in :meth:`LivePipeline.stream`
#: on a 2-core machine one core measures while the other runs the network (a second
#: measuring thread would take the network's core; it shortens :meth:`LivePipeline.process`
#: only where a core is idle).
DEFAULT_WORKERS: Final = 1
#: Rotation-ensemble size for live use (:func:`live_predictor`): two turns, both in one
#: batched, compiled network pass, keep a 2-core machine above 36 fps (the offline default,
#: :data:`~mocaprig.process.democap.infer.DEFAULT_ROTATIONS`, does not: docs/democap.md, "Speed").
LIVE_ROTATIONS: Final = 2
#: How long closing a stream waits for its producer thread (s) before leaving it behind.
_JOIN_TIMEOUT_S: Final = 10.0
#: How often a producer blocked on a full queue checks whether it should stop (s).
_POLL_S: Final = 0.05

#: One camera's frame as bare images: ``(ir (H, W) uint8, depth (H, W) uint16)``.
FramePair: TypeAlias = tuple[npt.ArrayLike, npt.ArrayLike]
#: One camera's frame: the driver's :class:`~acquire.depth_camera.FrameSet` (what a camera's
#: ``poll()`` and a recording's :func:`~acquire.device_streams.read_frame_sets` give; its own
#: depth scale is used) or bare images; ``None`` for a camera whose frame was dropped.
CameraFrame: TypeAlias = FrameSet | FramePair | None
#: One rig instant: a frame per camera in the pipeline's camera order, or by camera name.
RigFrames: TypeAlias = Sequence[CameraFrame] | Mapping[str, CameraFrame]


def _check_serial(camera: str, serial: str) -> None:
    """A frame set of D415 ``serial`` must not feed the pipeline camera of another serial."""
    try:
        dev = DeviceId.parse(camera)
    except ValidationError:
        return  # a camera named freely (not ``d415/<serial>``): nothing to compare
    if dev.kind == "d415" and dev.serial != serial:
        msg = f"camera {camera!r} was given a frame set of D415 {serial!r}"
        raise ValidationError(msg)


class CloudPredictor(Protocol):
    """What the pipeline needs of a predictor (:class:`~process.democap.infer.DemocapPredictor`
    is one); an attribute ``last_timings_s`` (stage -> s), when present, is read after each
    call, and a method ``warm_up()`` (-> s), when present, is called by live capture before
    the cameras start."""

    def predict_many(
        self,
        clouds: Sequence[npt.ArrayLike],
        *,
        views: Sequence[Sequence[Camera]] | None = None,
        crop_box_m: Box | None = None,
    ) -> list[Prediction]:
        """Fused world clouds ``(N, 3)`` (m) -> one :class:`Prediction` each; ``views``: per
        cloud, the cameras whose frames made it, and ``crop_box_m`` the box the points were
        cropped to (what the rig can see)."""
        ...


def live_predictor(
    checkpoint: Checkpoint | None = None,
    *,
    rotations: int = LIVE_ROTATIONS,
    compile: bool = True,
) -> DemocapPredictor:
    """The predictor for live use: :data:`LIVE_ROTATIONS` turns in one batched network pass
    on the calling thread, compiled (``compile``; 10-30 s on the first pass, which
    :meth:`~.infer.DemocapPredictor.warm_up` makes before the cameras start), the
    network's estimates without the skeleton solve (its cost is an offline one). On the
    2-core machine this is the fastest live setting and the least CPU a set: 48.7 fps end to
    end against 40.1 for the uncompiled turns as two passes at once (the setting before), in
    one run (docs/democap.md, "Speed"); the other core measures the next set.
    ``checkpoint`` None is the committed ``lite`` one.

    Raises:
        ProcessingError: the checkpoint is missing or does not match.
        ValidationError: ``rotations`` < 1.
    """
    return DemocapPredictor(checkpoint, rotations=rotations, solve=False, compile=compile)


# ------------------------------------------------------------------------------ cameras


@dataclass(frozen=True, slots=True)
class LiveCamera:
    """One D415 of the live rig: intrinsics of its IR/depth image and pose in the world.

    Attributes:
        name: Label, e.g. ``"d415/819612070593"`` (named in errors and timings).
        K: ``(3, 3)`` intrinsics of the left IR = depth image (px).
        T_world_cam: ``(4, 4)`` camera-to-world transform (translation in m).
        distortion: ``(5,)`` Brown–Conrady ``(k1, k2, p1, p2, k3)``; zeros for a rectified
            D415 (the default).
        depth_scale_m: Metres per depth unit (D415: 0.001).
        width, height: Expected image size (px); 0 = any (IR and depth must still agree).
    """

    name: str
    K: F64 = field(repr=False)
    T_world_cam: F64 = field(repr=False)
    distortion: F64 = field(default_factory=lambda: np.zeros(5), repr=False)
    depth_scale_m: float = 0.001
    width: int = 0
    height: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            msg = f"a live camera needs a non-empty name, got {self.name!r}"
            raise ValidationError(msg)
        what = f"camera {self.name!r}"
        k = np.array(check_finite(check_shape(self.K, [3, 3], name=f"{what} K")), np.float64)
        if k[0, 0] <= 0 or k[1, 1] <= 0:
            msg = f"{what}: K needs positive focal lengths (px), got fx={k[0, 0]}, fy={k[1, 1]}"
            raise ValidationError(msg)
        t = np.array(
            check_finite(check_shape(self.T_world_cam, [4, 4], name=f"{what} T_world_cam")),
            np.float64,
        )
        d = np.array(
            check_finite(check_shape(self.distortion, [5], name=f"{what} distortion")),
            np.float64,
        )
        scale = float(self.depth_scale_m)
        if not 0.0 < scale <= 0.1:
            msg = (
                f"{what}: depth_scale_m is metres per depth unit (D415: 0.001), "
                f"got {self.depth_scale_m!r}"
            )
            raise ValidationError(msg)
        w, h = int(self.width), int(self.height)
        if w < 0 or h < 0 or (w == 0) != (h == 0):
            msg = f"{what}: width and height must both be > 0, or both 0 (any), got {w}×{h}"
            raise ValidationError(msg)
        for a in (k, t, d):
            a.setflags(write=False)
        object.__setattr__(self, "K", k)
        object.__setattr__(self, "T_world_cam", t)
        object.__setattr__(self, "distortion", d)
        object.__setattr__(self, "depth_scale_m", scale)
        object.__setattr__(self, "width", w)
        object.__setattr__(self, "height", h)

    def view(self) -> Camera:
        """What this camera sees, as the skeleton solve takes a view of the rig: the
        calibrated pose, the mean of K's focal lengths (the D415's rectified images have
        square pixels), K's principal point and the image size (twice the principal point
        where the size is any)."""
        k, t = self.K, self.T_world_cam
        cx, cy = float(k[0, 2]), float(k[1, 2])
        size = (self.width, self.height) if self.width else (round(2 * cx), round(2 * cy))
        return Camera(
            centre_m=t[:3, 3].copy(),
            r_cw=t[:3, :3].T.copy(),
            focal_px=float(k[0, 0] + k[1, 1]) / 2.0,
            principal_px=(cx, cy),
            size_px=size,
        )

    @classmethod
    def from_calibration(
        cls,
        calibration: Calibration,
        key: str,
        *,
        depth_scale_m: float = 0.001,
        K: npt.ArrayLike | None = None,
        distortion: npt.ArrayLike | None = None,
    ) -> LiveCamera:
        """The camera ``key`` (name or serial) of a calibration: its pose and image size, and
        its K and distortion unless the camera's own are given; the depth scale is not in a
        calibration, so it is given.

        The replay and ``democap live`` pass the camera's own intrinsics (its recorded
        ``camera_info`` or ``intrinsics()``) with the calibrated pose; these agree with the
        calibration's when they are the factory ones (what ``mocaprig calibrate vicon`` writes).

        Raises:
            CalibrationError: no such camera, or it is not a D415.
            ValidationError: bad ``depth_scale_m``, ``K`` or ``distortion``.
        """
        cam = calibration.camera(key)
        if cam.kind != "d415":
            msg = f"camera {cam.name!r} is a {cam.kind!r} camera; the live pipeline takes D415s"
            raise CalibrationError(msg)
        return cls(
            name=cam.name,
            K=cam.K if K is None else np.asarray(K, dtype=np.float64),
            T_world_cam=cam.T_world_cam,
            distortion=cam.distortion
            if distortion is None
            else np.asarray(distortion, dtype=np.float64),
            depth_scale_m=depth_scale_m,
            width=cam.width,
            height=cam.height,
        )


def cameras_from_calibration(
    calibration: Calibration, *, depth_scale_m: float = 0.001
) -> tuple[LiveCamera, ...]:
    """Every D415 of a calibration, sorted by name (the replay's merge order).

    Raises:
        CalibrationError: the calibration has no D415.
    """
    names = sorted(c.name for c in cameras_of_kind(calibration, "d415"))
    if not names:
        msg = f"the calibration has no D415 camera (it has {[c.name for c in calibration.cameras]})"
        raise CalibrationError(msg)
    return tuple(
        LiveCamera.from_calibration(calibration, n, depth_scale_m=depth_scale_m) for n in names
    )


# ------------------------------------------------------------------------------ result


@dataclass(frozen=True, slots=True, eq=False)
class LiveResult:
    """One rig instant through the live pipeline.

    Attributes:
        index: Position of the frame set in the stream (0 for :meth:`LivePipeline.process`).
        prediction: Markers + joints (world, m); None when the cloud has fewer than the
            pipeline's ``min_points`` points.
        cloud_m: ``(M, 3)`` the fused cloud the network saw (world, m).
        markers: Per camera (pipeline order), what it measured; None where its frame was
            missing.
        timings_ms: Stage -> milliseconds: ``measure_ms`` (the measurement stage's wall
            time, all cameras), ``measure_<camera>_ms`` (each camera's measurement),
            ``merge_ms`` (world, crop, merge), ``predict_ms`` (the predictor's wall time) and
            its own stages (``render_ms``, ``network_ms``, ``decode_ms``... from its
            ``last_timings_s``), ``total_ms`` (measure + merge + predict: the work on this
            set) and ``latency_ms`` (from the start of its measurement to the result, waits
            for the network in :meth:`LivePipeline.stream` included); empty for a skipped set.
        skipped: The set was measured but never reached the network: a newer one replaced it
            while the network was behind (:meth:`LivePipeline.stream` with ``keep_up``); no
            prediction, an empty cloud, no markers.
    """

    index: int
    prediction: Prediction | None
    cloud_m: F64 = field(repr=False)
    markers: tuple[MarkerFrame | None, ...] = field(repr=False)
    timings_ms: Mapping[str, float] = field(default_factory=dict)
    skipped: bool = False

    @property
    def cameras_used(self) -> int:
        """Cameras whose frame fed the cloud."""
        return sum(m is not None for m in self.markers)

    @property
    def points(self) -> int:
        """Points of the fused cloud."""
        return int(self.cloud_m.shape[0])


@dataclass(frozen=True, slots=True, eq=False)
class _Measured:
    """The first stage's output for one set."""

    index: int
    cloud_m: F64
    markers: tuple[MarkerFrame | None, ...]
    timings_ms: dict[str, float]
    t_start: float  # perf_counter at the start of its measurement


@dataclass(frozen=True, slots=True)
class _Failure:
    error: BaseException


_END: Final = object()


# ------------------------------------------------------------------------------ pipeline


class LivePipeline:
    """Synchronised D415 IR + depth frames -> :class:`LiveResult` (module doc).

    Args:
        predictor: The network (:class:`~mocaprig.process.democap.infer.DemocapPredictor`).
        cameras: The rig's D415s, in the order of the frame sets' pairs (names unique). The
            order is also the merge order; pass frame sets by camera name (a mapping) when
            the source's order may differ (:func:`cameras_from_calibration` sorts by name).
        workers: Threads measuring the cameras of one set at once, the calling (or producer)
            thread included; 1 (:data:`DEFAULT_WORKERS`) measures them one after the other.
        queue_size: Measured sets :meth:`stream` holds ready for the network (≥ 1).
        crop_box_m: World box (m) outside which points are dropped before the merge
            (default: the training data's capture box, as the replay); None keeps all.
        merge_radius_m: Views' points closer than this are merged (m).
        min_points: Fewest fused points for a prediction (≥ 2, what the network needs).
        threshold, min_area_px, max_area_px: Blob detection (:func:`calib.markers.detect_blobs`;
            the defaults are the replay's).

    Raises:
        ValidationError: no camera, duplicate names, or a bad option.
    """

    def __init__(
        self,
        predictor: CloudPredictor,
        cameras: Sequence[LiveCamera],
        *,
        workers: int = DEFAULT_WORKERS,
        queue_size: int = 2,
        crop_box_m: Box | None = CAPTURE_BOX_M,
        merge_radius_m: float = DEFAULT_MERGE_RADIUS_M,
        min_points: int = 2,
        threshold: int = DEFAULT_THRESHOLD,
        min_area_px: int = DEFAULT_MIN_AREA_PX,
        max_area_px: int = DEFAULT_MAX_AREA_PX,
    ) -> None:
        cams = tuple(cameras)
        if not cams or not all(isinstance(c, LiveCamera) for c in cams):
            msg = f"cameras must be one or more LiveCamera, got {cameras!r}"
            raise ValidationError(msg)
        names = [c.name for c in cams]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            msg = f"camera names must be unique; {dup} appear more than once"
            raise ValidationError(msg)
        for what, value, low in (
            ("workers", workers, 1),
            ("queue_size", queue_size, 1),
            ("min_points", min_points, 2),
        ):
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                msg = f"{what} must be an integer >= {low}, got {value!r}"
                raise ValidationError(msg)
        if not np.isfinite(merge_radius_m) or merge_radius_m <= 0:
            msg = f"merge_radius_m must be a finite number > 0 (m), got {merge_radius_m!r}"
            raise ValidationError(msg)
        check_blob_options(threshold=threshold, min_area_px=min_area_px, max_area_px=max_area_px)
        self._box: F64 | None = None if crop_box_m is None else check_crop_box(crop_box_m)
        self._crop_box_m = crop_box_m
        self.predictor = predictor
        self.cameras = cams
        self._views = tuple(c.view() for c in cams)
        self.workers = workers
        self.queue_size = queue_size
        self.merge_radius_m = float(merge_radius_m)
        self.min_points = min_points
        self._measure_kw = {
            "threshold": int(threshold),
            "min_area_px": int(min_area_px),
            "max_area_px": int(max_area_px),
        }
        # Per worker beyond the calling thread, the cameras it measures (round robin).
        self._chunks = [list(range(i, len(cams), workers)) for i in range(min(workers, len(cams)))]
        self._pool = (
            ThreadPoolExecutor(max_workers=len(self._chunks) - 1, thread_name_prefix="democap-live")
            if len(self._chunks) > 1
            else None
        )
        self._closed = False
        self._lock = threading.Lock()
        self._streams: set[threading.Event] = set()

    # -- lifetime -------------------------------------------------------------------------

    def __enter__(self) -> LivePipeline:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    def close(self) -> None:
        """Stop the streams still running and shut the thread pool down (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            for stop in self._streams:
                stop.set()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)

    def _check_open(self) -> None:
        if self._closed:
            msg = "the live pipeline is closed; create a new LivePipeline"
            raise ProcessingError(msg)

    # -- stages ---------------------------------------------------------------------------

    def _pairs(self, frames: object) -> list[_Pair | None]:
        """Validate one frame set against the cameras; pairs in camera order."""
        names = [c.name for c in self.cameras]
        items: list[object]
        if isinstance(frames, Mapping):
            missing = [n for n in names if n not in frames]
            extra = sorted(str(k) for k in frames if k not in names)
            if missing or extra:
                msg = (
                    f"the frame set's cameras do not match the pipeline's {names}: "
                    + ", ".join(
                        s
                        for s in (
                            f"missing {missing}" if missing else "",
                            f"unknown {extra}" if extra else "",
                        )
                        if s
                    )
                    + " (use None for a camera whose frame was dropped)"
                )
                raise ValidationError(msg)
            items = [frames[n] for n in names]
        elif isinstance(frames, Sequence) and not isinstance(frames, (str, bytes)):
            if len(frames) != len(names):
                msg = (
                    f"the frame set has {len(frames)} (IR, depth) pair(s) for the "
                    f"{len(names)} cameras {names} (one per camera, in that order; None for a "
                    "dropped frame)"
                )
                raise ValidationError(msg)
            items = list(frames)
        else:
            msg = (
                "a frame set must be a sequence of (IR, depth) pairs in camera order or a "
                f"mapping camera name -> pair, got {type(frames).__name__}"
            )
            raise ValidationError(msg)
        out: list[_Pair | None] = []
        for cam, item in zip(self.cameras, items, strict=True):
            if item is None:
                out.append(None)
                continue
            what = f"camera {cam.name!r}"
            scale = cam.depth_scale_m
            if isinstance(item, FrameSet):
                _check_serial(cam.name, item.serial)
                ir, depth = item.infrared.image, item.depth.image
                scale = item.depth_scale_m
            elif not isinstance(item, (tuple, list)) or len(item) != 2:
                msg = (
                    f"{what}: expected an (IR, depth) pair or the driver's FrameSet, "
                    f"got {type(item).__name__}"
                )
                raise ValidationError(msg)
            else:
                ir, depth = np.asarray(item[0]), np.asarray(item[1])
            if ir.ndim != 2 or ir.dtype != np.uint8:
                msg = (
                    f"{what}: the IR image must be 2-D uint8 (Y8), got shape {ir.shape} "
                    f"dtype {ir.dtype}"
                )
                raise ValidationError(msg)
            if depth.dtype != np.uint16 or depth.shape != ir.shape:
                msg = (
                    f"{what}: the depth image must be uint16 (Z16) of the IR image's shape "
                    f"{ir.shape}, got shape {depth.shape} dtype {depth.dtype}"
                )
                raise ValidationError(msg)
            if cam.width and ir.shape != (cam.height, cam.width):
                msg = (
                    f"{what}: images are {ir.shape[1]}×{ir.shape[0]} but the camera is "
                    f"calibrated at {cam.width}×{cam.height}"
                )
                raise ValidationError(msg)
            out.append((ir, depth, scale))
        return out

    def _measure_cams(
        self,
        idx: Sequence[int],
        pairs: Sequence[_Pair | None],
    ) -> list[tuple[int, MarkerFrame | None, float]]:
        out: list[tuple[int, MarkerFrame | None, float]] = []
        for i in idx:
            pair = pairs[i]
            if pair is None:
                out.append((i, None, 0.0))
                continue
            cam = self.cameras[i]
            t0 = time.perf_counter()
            mf = measure_frame(
                pair[0],
                pair[1],
                cam.K,
                depth_scale_m=pair[2],
                camera=cam.name,
                distortion=cam.distortion,
                **self._measure_kw,
            )
            out.append((i, mf, time.perf_counter() - t0))
        return out

    def _measure(self, frames: RigFrames, index: int) -> _Measured:
        """Stage 1: validate, measure every camera, world + crop + merge."""
        t_start = time.perf_counter()
        pairs = self._pairs(frames)
        futures: list[Future[list[tuple[int, MarkerFrame | None, float]]]] = []
        if self._pool is not None:
            futures = [
                self._pool.submit(self._measure_cams, chunk, pairs) for chunk in self._chunks[1:]
            ]
        done = self._measure_cams(self._chunks[0], pairs)
        for fut in futures:
            done.extend(fut.result())
        t1 = time.perf_counter()
        markers: list[MarkerFrame | None] = [None] * len(self.cameras)
        timings = {"measure_ms": 1e3 * (t1 - t_start)}
        for i, mf, sec in sorted(done, key=lambda r: r[0]):
            markers[i] = mf
            if mf is not None:
                timings[f"measure_{self.cameras[i].name}_ms"] = 1e3 * sec
        views = []
        for cam, mf in zip(self.cameras, markers, strict=True):
            if mf is None:
                continue
            p = to_world(mf.xyz_cam_m, cam.T_world_cam)
            views.append(
                p if self._box is None else crop_volume(p, self._box[:, 0], self._box[:, 1])
            )
        cloud = merge_views(views, radius_m=self.merge_radius_m)
        timings["merge_ms"] = 1e3 * (time.perf_counter() - t1)
        return _Measured(index, cloud, tuple(markers), timings, t_start)

    def _predict(self, m: _Measured) -> LiveResult:
        """Stage 2: the network on one measured set."""
        timings = dict(m.timings_ms)
        pred: Prediction | None = None
        t0 = time.perf_counter()
        if m.cloud_m.shape[0] >= self.min_points:
            # the cameras that fed the cloud: a body part no one of them sees is not missing
            seen_by = [v for v, mf in zip(self._views, m.markers, strict=True) if mf is not None]
            pred = self.predictor.predict_many(
                [m.cloud_m], views=[seen_by], crop_box_m=self._crop_box_m
            )[0]
            stages = getattr(self.predictor, "last_timings_s", None)
            if isinstance(stages, Mapping):
                for k, v in stages.items():
                    key = str(k).removesuffix("_s")
                    if key not in ("measure", "merge", "predict", "total", "latency"):
                        timings[f"{key}_ms"] = 1e3 * float(v)
        else:
            _log.debug(
                "frame set %d: %d fused point(s), under %d: no prediction",
                m.index,
                m.cloud_m.shape[0],
                self.min_points,
            )
        t1 = time.perf_counter()
        timings["predict_ms"] = 1e3 * (t1 - t0)
        timings["total_ms"] = timings["measure_ms"] + timings["merge_ms"] + timings["predict_ms"]
        timings["latency_ms"] = 1e3 * (t1 - m.t_start)
        return LiveResult(m.index, pred, m.cloud_m, m.markers, timings)

    # -- public ---------------------------------------------------------------------------

    def process(self, frames: RigFrames) -> LiveResult:
        """One frame set -> its :class:`LiveResult` (both stages in the calling thread, the
        cameras spread over ``workers`` threads).

        Args:
            frames: One frame per camera, in the pipeline's camera order (or a mapping camera
                name -> frame): the driver's :class:`~acquire.depth_camera.FrameSet` or an
                ``(ir (H, W) uint8, depth (H, W) uint16)`` pair; None for a camera whose frame
                was dropped.

        Raises:
            ValidationError: the wrong number of pairs or cameras, or a wrong image shape or
                dtype (the message names the camera).
            ProcessingError: the pipeline is closed.
        """
        self._check_open()
        return self._predict(self._measure(frames, 0))

    def stream(
        self, frame_sets: Iterable[RigFrames], *, keep_up: bool = False
    ) -> Iterator[LiveResult]:
        """Frame sets -> their :class:`LiveResult`, in order, as a two-stage pipeline.

        A producer thread takes the sets from ``frame_sets`` and measures + merges them
        (holding at most ``queue_size`` measured sets ahead); the network runs in the thread
        iterating over the returned iterator. The first error of either stage (a bad set,
        an error of the source iterable, of the measurement or of the network) is raised
        from the iterator at that set's position, after the results before it. Stopping
        the iteration early (``break``, ``close()``, an error) stops the producer after
        the set it is on.

        ``keep_up`` (live cameras): the producer never waits for the network. When
        ``queue_size`` measured sets are waiting, the oldest is dropped for the newest, so
        the network always runs on the latest sets and the latency stays bounded when it is
        slower than the cameras; each dropped set still comes out, in its place, as a
        result with ``skipped`` set (nothing is lost silently). Off (the default, a
        recording's replay): every set is predicted and the producer waits.

        Raises:
            ValidationError: as :meth:`process`, for the set at fault.
            ProcessingError: the pipeline is closed.
        """
        self._check_open()
        return self._stream(iter(frame_sets), keep_up=keep_up)

    def _skipped(self, index: int) -> LiveResult:
        return LiveResult(
            index, None, np.zeros((0, 3)), (None,) * len(self.cameras), {}, skipped=True
        )

    def _stream(self, source: Iterator[RigFrames], *, keep_up: bool) -> Iterator[LiveResult]:
        q: queue.Queue[object] = queue.Queue(maxsize=self.queue_size)
        stop = threading.Event()
        with self._lock:
            if self._closed:
                msg = "the live pipeline is closed; create a new LivePipeline"
                raise ProcessingError(msg)
            self._streams.add(stop)

        def put(item: object) -> bool:
            while not stop.is_set():
                try:
                    q.put(item, timeout=_POLL_S)
                except queue.Full:
                    continue
                return True
            return False

        def put_newest(item: _Measured) -> None:
            # the oldest waiting set gives way; the consumer sees the gap in the indices
            while True:
                try:
                    q.put_nowait(item)
                except queue.Full:
                    with contextlib.suppress(queue.Empty):
                        q.get_nowait()
                    continue
                return

        def produce() -> None:
            index = 0
            try:
                while not stop.is_set():
                    try:
                        frames = next(source)
                    except StopIteration:
                        break
                    measured = self._measure(frames, index)
                    if keep_up:
                        put_newest(measured)
                    elif not put(measured):
                        return
                    index += 1
                put(_END)
            except BaseException as err:  # forwarded to the consumer, raised there
                put(_Failure(err))

        worker = threading.Thread(target=produce, name="democap-live-measure", daemon=True)
        worker.start()
        expected = 0
        try:
            while True:
                try:
                    item = q.get(timeout=_POLL_S)
                except queue.Empty:
                    if stop.is_set():
                        msg = "the live pipeline was closed while streaming"
                        raise ProcessingError(msg) from None
                    continue
                if item is _END:
                    return
                if isinstance(item, _Failure):
                    raise item.error
                measured = cast(_Measured, item)
                while expected < measured.index:  # sets dropped to keep up (keep_up)
                    yield self._skipped(expected)
                    expected += 1
                expected = measured.index + 1
                yield self._predict(measured)
        finally:
            stop.set()
            while True:  # unblock a producer waiting on a full queue
                try:
                    q.get_nowait()
                except queue.Empty:
                    break
            worker.join(_JOIN_TIMEOUT_S)
            if worker.is_alive():
                _log.warning(
                    "the live pipeline's measurement thread is still busy after %.0f s "
                    "(a frame source blocked?); left behind",
                    _JOIN_TIMEOUT_S,
                )
            with self._lock:
                self._streams.discard(stop)
