"""2D/3D joint detections at the APS frames through one :class:`Detector` protocol.

EventCap's E_2D and E_3D terms (paper Eqs. 6–7; eventcap-method.md §1.5, §3) need, at each APS
frame, 2D joints in pixels with confidences and root-relative 3D joints. The pipeline never calls
a detector network itself: it asks a :class:`Detector` for the :class:`Detection` at an APS time.

Every detection is in the 19-keypoint EventCap set
(:data:`mocaprig.process.body.kinematics.EVENTCAP_KEYPOINTS`: 15 body joints, then right/left eye
and right/left ear). Other keypoint sets are converted by the tables in :data:`KEYPOINT_MAPS`:
a slot takes one source keypoint, or the mean of several (neck and pelvis of COCO, the head of
every set) with the *minimum* of their confidences; a slot with no source gets confidence 0.

Implementations:

* :class:`OpenPoseJsonDetections` — a folder of OpenPose ``--write_json`` files (BODY_25 or
  COCO-18);
* :class:`CocoKeypointDetections` — a COCO keypoint results or annotations file (COCO-17);
* :class:`JsonDetections` — our own one-file-per-sequence schema (:func:`write_detections_json`
  writes it);
* :class:`SyntheticDetections` — ground truth plus detector-like noise, for simulated sessions,
  always labelled ``"synthetic"``.

MediaPipe (BlazePose) is not wrapped: mediapipe 0.10.14, the last wheel that ships its pose model,
pins ``protobuf<5`` and pulls ``opencv-contrib-python``, which break the project's
``foxglove-schemas-protobuf`` (its generated code needs protobuf ≥ 5.26) and replace its headless
OpenCV. Run it in a separate environment and write a ``"blazepose33"`` file for
:class:`JsonDetections`.

Frames: 2D in pixels of the image the detector saw (x right, y down, origin at the top-left
pixel's corner as OpenPose and COCO use); 3D in mm, camera axes (x right, y down, z forward),
pelvis at the origin.
"""

from __future__ import annotations

import json
import logging
import math
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

from mocaprig.calib.camera_model import world_to_camera
from mocaprig.errors import ProcessingError, RecordingError, ValidationError
from mocaprig.process.body.kinematics import EVENTCAP_KEYPOINTS
from mocaprig.validation import check_finite, check_range, check_shape

__all__ = [
    "DETECTIONS_FORMAT",
    "DETECTIONS_FORMAT_VERSION",
    "KEYPOINT_MAPS",
    "KEYPOINT_SET_SIZES",
    "NUM_KEYPOINTS",
    "CocoKeypointDetections",
    "Detection",
    "Detector",
    "JsonDetections",
    "KeypointSet",
    "OpenPoseJsonDetections",
    "SyntheticDetections",
    "SyntheticNoise",
    "convert_keypoints",
    "write_detections_json",
]

_log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

#: Keypoints per detection: 15 body joints + 4 face points, in ``EVENTCAP_KEYPOINTS`` order.
NUM_KEYPOINTS = len(EVENTCAP_KEYPOINTS)

#: Keypoint sets that can be converted to ours.
KeypointSet = Literal["eventcap19", "body25", "coco18", "coco17", "blazepose33"]

#: Number of keypoints of each set.
KEYPOINT_SET_SIZES: Mapping[KeypointSet, int] = {
    "eventcap19": NUM_KEYPOINTS,
    "body25": 25,
    "coco18": 18,
    "coco17": 17,
    "blazepose33": 33,
}

#: ``format`` field of our detections JSON, and the version this module writes and reads.
DETECTIONS_FORMAT = "mocaprig.eventcap.detections"
DETECTIONS_FORMAT_VERSION = 1


def _by_name(table: Mapping[str, tuple[int, ...]]) -> tuple[tuple[int, ...], ...]:
    missing = set(EVENTCAP_KEYPOINTS) ^ set(table)
    if missing:  # a programming error in the tables below, caught at import
        msg = f"keypoint table does not cover exactly EVENTCAP_KEYPOINTS: {sorted(missing)}"
        raise ProcessingError(msg)
    return tuple(table[n] for n in EVENTCAP_KEYPOINTS)


# Our "head" joint is the head centre (atlanto-occipital level, process/body/skeleton.py), which
# no 2D detector outputs; the ears sit at about its height on either side, so their mean stands in.
_BODY25 = {
    "pelvis": (8,),  # MidHip
    "neck": (1,),
    "head": (17, 18),
    "right_shoulder": (2,),
    "right_elbow": (3,),
    "right_wrist": (4,),
    "left_shoulder": (5,),
    "left_elbow": (6,),
    "left_wrist": (7,),
    "right_hip": (9,),
    "right_knee": (10,),
    "right_ankle": (11,),
    "left_hip": (12,),
    "left_knee": (13,),
    "left_ankle": (14,),
    "right_eye": (15,),
    "left_eye": (16,),
    "right_ear": (17,),
    "left_ear": (18,),
}
_COCO18 = {  # OpenPose's COCO model: BODY_25 without MidHip and the feet
    "pelvis": (8, 11),
    "neck": (1,),
    "head": (16, 17),
    "right_shoulder": (2,),
    "right_elbow": (3,),
    "right_wrist": (4,),
    "left_shoulder": (5,),
    "left_elbow": (6,),
    "left_wrist": (7,),
    "right_hip": (8,),
    "right_knee": (9,),
    "right_ankle": (10,),
    "left_hip": (11,),
    "left_knee": (12,),
    "left_ankle": (13,),
    "right_eye": (14,),
    "left_eye": (15,),
    "right_ear": (16,),
    "left_ear": (17,),
}
_COCO17 = {  # COCO keypoint order: nose, eyes, ears, then left before right
    "pelvis": (11, 12),
    "neck": (5, 6),
    "head": (3, 4),
    "right_shoulder": (6,),
    "right_elbow": (8,),
    "right_wrist": (10,),
    "left_shoulder": (5,),
    "left_elbow": (7,),
    "left_wrist": (9,),
    "right_hip": (12,),
    "right_knee": (14,),
    "right_ankle": (16,),
    "left_hip": (11,),
    "left_knee": (13,),
    "left_ankle": (15,),
    "right_eye": (2,),
    "left_eye": (1,),
    "right_ear": (4,),
    "left_ear": (3,),
}
_BLAZEPOSE33 = {
    "pelvis": (23, 24),
    "neck": (11, 12),
    "head": (7, 8),
    "right_shoulder": (12,),
    "right_elbow": (14,),
    "right_wrist": (16,),
    "left_shoulder": (11,),
    "left_elbow": (13,),
    "left_wrist": (15,),
    "right_hip": (24,),
    "right_knee": (26,),
    "right_ankle": (28,),
    "left_hip": (23,),
    "left_knee": (25,),
    "left_ankle": (27,),
    "right_eye": (5,),
    "left_eye": (2,),
    "right_ear": (8,),
    "left_ear": (7,),
}

#: Source keypoint indices of each EventCap slot, per keypoint set (a tuple of several is
#: averaged, with the minimum confidence).
KEYPOINT_MAPS: Mapping[KeypointSet, tuple[tuple[int, ...], ...]] = {
    "eventcap19": tuple((i,) for i in range(NUM_KEYPOINTS)),
    "body25": _by_name(_BODY25),
    "coco18": _by_name(_COCO18),
    "coco17": _by_name(_COCO17),
    "blazepose33": _by_name(_BLAZEPOSE33),
}

# Left/right partner of each slot (itself for the centre line), for the synthetic swaps.
_MIRROR: tuple[int, ...] = tuple(
    EVENTCAP_KEYPOINTS.index(
        n.replace("right_", "\0").replace("left_", "right_").replace("\0", "left_")
    )
    for n in EVENTCAP_KEYPOINTS
)
_PELVIS = EVENTCAP_KEYPOINTS.index("pelvis")


def _frozen(a: npt.ArrayLike) -> FloatArray:
    out = np.array(a, dtype=np.float64)  # a copy: the record never aliases a caller's array
    out.flags.writeable = False
    return out


@dataclass(frozen=True, slots=True)
class Detection:
    """Joint detections at one APS frame, in the EventCap keypoint set.

    Attributes:
        t_us: The APS frame's time, µs (exposure centre, the same clock as the events).
        joints2d_px: (19, 2) pixel coordinates (x right, y down) in ``EVENTCAP_KEYPOINTS``
            order; a missing joint holds 0 and confidence 0.
        confidence: (19,) detector confidences in [0, 1]; 0 means missing.
        source: What produced it (``"openpose-body25"``, ``"coco17"``, ``"synthetic"``, ...);
            every output made from the detection carries it.
        joints3d_root_rel_mm: (19, 3) root-relative 3D joints in mm, camera axes (x right,
            y down, z forward), pelvis at the origin; None when the source has no 3D.

    Arrays are read-only copies.

    Raises:
        ValidationError: wrong shapes, non-finite values, confidences outside [0, 1], an empty
            source, or a 3D pelvis away from the origin.
    """

    t_us: int
    joints2d_px: FloatArray = field(repr=False)
    confidence: FloatArray = field(repr=False)
    source: str
    joints3d_root_rel_mm: FloatArray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        j2 = check_finite(
            check_shape(self.joints2d_px, [NUM_KEYPOINTS, 2], name="joints2d_px"),
            name="joints2d_px",
        )
        c = check_finite(
            check_shape(self.confidence, [NUM_KEYPOINTS], name="confidence"), name="confidence"
        )
        if np.any(c < 0) or np.any(c > 1):
            msg = f"detection at t_us={self.t_us}: confidences must lie in [0, 1], got {c}"
            raise ValidationError(msg)
        if not self.source:
            msg = f"detection at t_us={self.t_us} has no source label; say what produced it"
            raise ValidationError(msg)
        object.__setattr__(self, "t_us", int(self.t_us))
        object.__setattr__(self, "joints2d_px", _frozen(j2))
        object.__setattr__(self, "confidence", _frozen(c))
        if self.joints3d_root_rel_mm is not None:
            j3 = check_finite(
                check_shape(self.joints3d_root_rel_mm, [NUM_KEYPOINTS, 3], name="joints3d"),
                name="joints3d_root_rel_mm",
            )
            if not np.allclose(j3[_PELVIS], 0.0, atol=1e-6):
                msg = (
                    f"detection at t_us={self.t_us}: joints3d_root_rel_mm must have the pelvis "
                    f"at the origin, got {j3[_PELVIS]}; subtract the pelvis first"
                )
                raise ValidationError(msg)
            object.__setattr__(self, "joints3d_root_rel_mm", _frozen(j3))


@runtime_checkable
class Detector(Protocol):
    """Anything that gives the :class:`Detection` at an APS frame."""

    @property
    def source(self) -> str:
        """The label every detection of this detector carries."""
        ...

    def detect(self, t_us: int, image: npt.NDArray[Any] | None = None) -> Detection:
        """The detection at APS time ``t_us`` (µs); ``image`` (H, W) or (H, W, 3) is the frame
        for detectors that look at pixels (file-based ones ignore it).

        Raises:
            ProcessingError: the detector has nothing for ``t_us``.
        """
        ...


def convert_keypoints(
    joints: npt.ArrayLike,
    confidence: npt.ArrayLike,
    keypoint_set: KeypointSet,
    *,
    joints3d: npt.ArrayLike | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray | None]:
    """Convert one person's keypoints of ``keypoint_set`` to the EventCap set.

    Args:
        joints: (K, 2) pixel coordinates in the source set's order.
        confidence: (K,) confidences; 0 means missing.
        keypoint_set: The source set (``KEYPOINT_SET_SIZES`` gives K).
        joints3d: Optional (K, 3) 3D joints (mm); converted the same way, then re-centred on
            the converted pelvis.

    Returns:
        ``(joints2d_px (19, 2), confidence (19,), joints3d_root_rel_mm (19, 3) or None)``.
        A slot averaged from several keypoints gets the minimum of their confidences; a slot
        whose confidence is 0 gets coordinates 0.

    Raises:
        ValidationError: unknown set or wrong sizes.
    """
    if keypoint_set not in KEYPOINT_MAPS:
        msg = f"unknown keypoint set {keypoint_set!r}; use one of {sorted(KEYPOINT_MAPS)}"
        raise ValidationError(msg)
    k = KEYPOINT_SET_SIZES[keypoint_set]
    xy = np.asarray(check_shape(joints, [k, 2], name=f"{keypoint_set} joints"), np.float64)
    cf = np.asarray(check_shape(confidence, [k], name=f"{keypoint_set} confidence"), np.float64)
    table = KEYPOINT_MAPS[keypoint_set]
    out_xy = np.array([xy[list(src)].mean(axis=0) for src in table])
    out_c = np.array([cf[list(src)].min() for src in table])
    out_xy[out_c <= 0] = 0.0
    out3 = None
    if joints3d is not None:
        p3 = np.asarray(check_shape(joints3d, [k, 3], name=f"{keypoint_set} joints3d"), np.float64)
        out3 = np.array([p3[list(src)].mean(axis=0) for src in table])
        out3 = out3 - out3[_PELVIS]
    return out_xy, np.clip(out_c, 0.0, 1.0), out3


def _person_from_flat(flat: object, k: int, *, what: str) -> tuple[FloatArray, FloatArray]:
    """Split a flat ``x, y, c`` list of ``k`` keypoints."""
    try:
        arr = np.asarray(flat, dtype=np.float64)
    except (TypeError, ValueError) as err:
        msg = f"{what}: keypoints are not a flat list of numbers ({err}); re-export the file"
        raise RecordingError(msg) from err
    if arr.ndim != 1 or arr.size != 3 * k:
        msg = f"{what}: expected {3 * k} numbers (x, y, c for {k} keypoints), got shape {arr.shape}"
        raise RecordingError(msg)
    if not np.all(np.isfinite(arr)):
        msg = f"{what}: keypoints hold NaN or inf; re-export the file"
        raise RecordingError(msg)
    trip = arr.reshape(k, 3)
    return trip[:, :2].copy(), trip[:, 2].copy()


def _load_json(path: Path) -> Any:
    try:
        with path.open("rb") as f:
            return json.load(f)
    except OSError as err:
        msg = f"cannot read detections file {path}: {err}"
        raise RecordingError(msg) from err
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        msg = f"detections file {path} is not valid JSON ({err}); re-export it"
        raise RecordingError(msg) from err


def _empty(t_us: int, source: str) -> Detection:
    return Detection(
        t_us=t_us,
        joints2d_px=np.zeros((NUM_KEYPOINTS, 2)),
        confidence=np.zeros(NUM_KEYPOINTS),
        source=source,
    )


class _TimeTable:
    """Detections keyed by APS time, looked up exactly or within a tolerance."""

    def __init__(self, by_time: Mapping[int, Detection], *, tolerance_us: int, what: str) -> None:
        if tolerance_us < 0:
            msg = f"tolerance_us must be >= 0, got {tolerance_us}"
            raise ValidationError(msg)
        self._times = np.array(sorted(by_time), dtype=np.int64)
        self._by_time = dict(by_time)
        self._tol = int(tolerance_us)
        self._what = what

    def get(self, t_us: int) -> Detection:
        if self._times.size == 0:
            msg = f"{self._what} holds no frames; check the file and the frame times"
            raise ProcessingError(msg)
        i = int(np.searchsorted(self._times, t_us))
        near = [j for j in (i - 1, i) if 0 <= j < self._times.size]
        best = min(near, key=lambda j: abs(int(self._times[j]) - t_us))
        t_best = int(self._times[best])
        if abs(t_best - t_us) > self._tol:
            msg = (
                f"{self._what} has no detection at t_us={t_us} (nearest {t_best}, tolerance "
                f"{self._tol} µs); give the APS frame times the detections were made at"
            )
            raise ProcessingError(msg)
        return self._by_time[t_best]

    @property
    def times_us(self) -> npt.NDArray[np.int64]:
        return self._times.copy()


_OPENPOSE_SETS: Mapping[int, KeypointSet] = {25: "body25", 18: "coco18"}
_FRAME_NUMBER = re.compile(r"(\d+)_keypoints\.json$")


class _TableDetections:
    """A detector read from a file: every detection known up front, looked up by time."""

    _source: str
    _table: _TimeTable

    @property
    def source(self) -> str:
        """The label of the file's detections (e.g. ``"openpose-body25"``, ``"coco17"``)."""
        return self._source

    @property
    def times_us(self) -> npt.NDArray[np.int64]:
        """The APS times (µs) the file has a detection for, sorted."""
        return self._table.times_us

    def detect(self, t_us: int, image: npt.NDArray[Any] | None = None) -> Detection:
        """The detection at ``t_us``; ``image`` is ignored (the file already holds them)."""
        return self._table.get(int(t_us))


class OpenPoseJsonDetections(_TableDetections):
    """Detections from a folder of OpenPose ``--write_json`` files (``*_keypoints.json``).

    Each file holds ``{"people": [{"pose_keypoints_2d": [x0, y0, c0, x1, ...]}, ...]}``. The
    frame index of a file is the number before ``_keypoints.json`` (OpenPose writes
    ``<name>_000000000012_keypoints.json``); when some file has no number, files are taken in
    sorted order. The caller gives the APS time of each frame index. With several people the
    one with the highest mean confidence is used (logged); a frame with none gives a detection
    with all confidences 0.

    Args:
        folder: The ``--write_json`` folder.
        frame_times_us: APS time (µs) of frame index 0, 1, ...
        keypoint_set: ``"body25"``, ``"coco18"`` or ``"auto"`` (from the keypoint count).
        tolerance_us: Largest |t - frame time| accepted by :meth:`detect`.

    Raises:
        RecordingError: no files, a malformed file, a frame index without a time, or a keypoint
            count that is neither 25 nor 18 (the message names the file).
    """

    def __init__(
        self,
        folder: Path,
        frame_times_us: Sequence[int],
        *,
        keypoint_set: Literal["auto", "body25", "coco18"] = "auto",
        tolerance_us: int = 0,
    ) -> None:
        folder = Path(folder)
        files = sorted(folder.glob("*_keypoints.json"))
        if not files:
            msg = f"no *_keypoints.json files in {folder}; run OpenPose with --write_json there"
            raise RecordingError(msg)
        numbers = [_FRAME_NUMBER.search(f.name) for f in files]
        if all(m is not None for m in numbers):
            indices = [int(m.group(1)) for m in numbers if m is not None]
        else:
            _log.info("%s: some files have no frame number; using sorted file order", folder)
            indices = list(range(len(files)))
        times = [int(t) for t in frame_times_us]
        read: dict[int, tuple[FloatArray, FloatArray]] = {}
        chosen: set[str] = set()
        for path, idx in zip(files, indices, strict=True):
            if idx >= len(times):
                msg = (
                    f"{path}: frame index {idx} has no time ({len(times)} frame times given); "
                    "give one APS time per OpenPose frame"
                )
                raise RecordingError(msg)
            j2, c2, kset = self._read(path, keypoint_set)
            if kset is not None:
                chosen.add(kset)
            read[times[idx]] = (j2, c2)
        if len(chosen) > 1:
            msg = f"{folder} mixes keypoint sets {sorted(chosen)}; export one model per folder"
            raise RecordingError(msg)
        # with every frame empty the label follows what was asked for
        fallback = "body25" if keypoint_set == "auto" else keypoint_set
        kset_used = chosen.pop() if chosen else fallback
        self._source = f"openpose-{kset_used}"
        by_time = {t: Detection(t, j2, c2, source=self._source) for t, (j2, c2) in read.items()}
        self._table = _TimeTable(by_time, tolerance_us=tolerance_us, what=f"OpenPose {folder}")

    @staticmethod
    def _read(
        path: Path, keypoint_set: Literal["auto", "body25", "coco18"]
    ) -> tuple[FloatArray, FloatArray, KeypointSet | None]:
        doc = _load_json(path)
        people = doc.get("people") if isinstance(doc, dict) else None
        if not isinstance(people, list):
            msg = f"{path}: no 'people' list; is this an OpenPose --write_json file?"
            raise RecordingError(msg)
        best: tuple[float, FloatArray, FloatArray, KeypointSet] | None = None
        for n, person in enumerate(people):
            flat = person.get("pose_keypoints_2d") if isinstance(person, dict) else None
            if flat is None:
                msg = f"{path}: person {n} has no 'pose_keypoints_2d'"
                raise RecordingError(msg)
            if not isinstance(flat, list) or len(flat) % 3:
                msg = f"{path}: person {n} 'pose_keypoints_2d' is not a flat x, y, c list"
                raise RecordingError(msg)
            k = len(flat) // 3
            kset: KeypointSet
            if keypoint_set == "auto":
                if k not in _OPENPOSE_SETS:
                    msg = (
                        f"{path}: person {n} has {k} keypoints; OpenPose BODY_25 has 25 and COCO "
                        "18 (pass keypoint_set for other models)"
                    )
                    raise RecordingError(msg)
                kset = _OPENPOSE_SETS[k]
            else:
                kset = keypoint_set
            xy, c = _person_from_flat(flat, KEYPOINT_SET_SIZES[kset], what=f"{path} person {n}")
            score = float(c.mean())
            if best is None or score > best[0]:
                best = (score, xy, c, kset)
        if best is None:
            _log.info("%s: no people; detection with confidence 0", path)
            return np.zeros((NUM_KEYPOINTS, 2)), np.zeros(NUM_KEYPOINTS), None
        if len(people) > 1:
            _log.info(
                "%s: %d people; using the one with the highest mean confidence (%.3f)",
                path,
                len(people),
                best[0],
            )
        j2, c2, _ = convert_keypoints(best[1], np.clip(best[2], 0.0, 1.0), best[3])
        return j2, c2, best[3]


class CocoKeypointDetections(_TableDetections):
    """Detections from a COCO keypoint file (17 keypoints), results or annotations.

    A *results* file is a list of ``{"image_id", "keypoints": [x, y, score, ...], "score"}``
    (MMPose, Detectron2 ... outputs); per image the entry with the highest ``score`` (or mean
    keypoint score) is used. An *annotations* file is a dict with ``"annotations"``; its third
    value is COCO's visibility flag v: v = 0 gives confidence 0, v = 1 or 2 confidence 1.
    Keypoint scores above 1 are clipped to 1.

    Args:
        path: The JSON file.
        image_times_us: APS time (µs) of each ``image_id`` used.
        tolerance_us: Largest |t - frame time| accepted by :meth:`detect`.

    Raises:
        RecordingError: malformed file, or an image id without a time (the message names it).
    """

    def __init__(
        self, path: Path, image_times_us: Mapping[int, int], *, tolerance_us: int = 0
    ) -> None:
        path = Path(path)
        doc = _load_json(path)
        visibility = isinstance(doc, dict)
        entries = doc.get("annotations") if isinstance(doc, dict) else doc
        if not isinstance(entries, list):
            msg = f"{path}: expected a list of results or a dict with 'annotations'"
            raise RecordingError(msg)
        best: dict[int, tuple[float, FloatArray, FloatArray]] = {}
        for n, e in enumerate(entries):
            if not isinstance(e, dict) or "image_id" not in e or "keypoints" not in e:
                msg = f"{path}: entry {n} lacks 'image_id' or 'keypoints'"
                raise RecordingError(msg)
            xy, c = _person_from_flat(e["keypoints"], 17, what=f"{path} entry {n}")
            c = (c > 0).astype(np.float64) if visibility else np.clip(c, 0.0, 1.0)
            try:
                score = float(e.get("score", c.mean())) if not visibility else float(c.mean())
                image_id = int(e["image_id"])
            except (TypeError, ValueError) as err:
                msg = f"{path}: entry {n} has a non-numeric 'image_id' or 'score' ({err})"
                raise RecordingError(msg) from err
            if image_id not in best or score > best[image_id][0]:
                best[image_id] = (score, xy, c)
        self._source = "coco17"
        if len(set(image_times_us.values())) != len(image_times_us):
            msg = "image_times_us gives two images the same time; give one time per image"
            raise ValidationError(msg)
        by_time: dict[int, Detection] = {}
        for image_id in image_times_us:
            t = int(image_times_us[image_id])
            if image_id not in best:
                by_time[t] = _empty(t, self._source)
                continue
            j2, c2, _ = convert_keypoints(best[image_id][1], best[image_id][2], "coco17")
            by_time[t] = Detection(t, j2, c2, source=self._source)
        unmapped = sorted(set(best) - set(image_times_us))
        if unmapped:
            msg = (
                f"{path}: image ids {unmapped[:5]} have no time; give image_times_us for every "
                "image in the file"
            )
            raise RecordingError(msg)
        self._table = _TimeTable(by_time, tolerance_us=tolerance_us, what=f"COCO file {path}")


class JsonDetections(_TableDetections):
    """Detections from our own one-file-per-sequence JSON (written by
    :func:`write_detections_json`; eventcap-method.md §3.2)::

        {"format": "mocaprig.eventcap.detections", "format_version": 1,
         "source": "synthetic", "keypoint_set": "eventcap19",
         "frames": [{"t_us": 40000, "joints2d": [[x, y, conf], ...],
                     "joints3d_root_rel_mm": [[x, y, z], ...]}, ...]}

    ``keypoint_set`` (top level, or per frame to override it) is one of
    :data:`KEYPOINT_SET_SIZES`; ``joints3d_root_rel_mm`` is optional. The ``source`` label is
    kept on every detection.

    Raises:
        RecordingError: malformed file or newer format version (the message names the file).
    """

    def __init__(self, path: Path, *, tolerance_us: int = 0) -> None:
        path = Path(path)
        doc = _load_json(path)
        if not isinstance(doc, dict) or doc.get("format") != DETECTIONS_FORMAT:
            msg = f"{path}: not a detections file (its 'format' is not {DETECTIONS_FORMAT!r})"
            raise RecordingError(msg)
        version = doc.get("format_version")
        if not isinstance(version, int) or version > DETECTIONS_FORMAT_VERSION:
            msg = (
                f"{path}: format_version {version!r} is not supported (this mocaprig reads "
                f"<= {DETECTIONS_FORMAT_VERSION}); upgrade mocaprig"
            )
            raise RecordingError(msg)
        source = doc.get("source")
        frames = doc.get("frames")
        if not isinstance(source, str) or not source or not isinstance(frames, list):
            msg = f"{path}: needs a non-empty 'source' string and a 'frames' list"
            raise RecordingError(msg)
        top_set = doc.get("keypoint_set", "eventcap19")
        by_time: dict[int, Detection] = {}
        for n, fr in enumerate(frames):
            by_time_det = self._frame(path, n, fr, top_set, source)
            if by_time_det.t_us in by_time:
                msg = f"{path}: frame {n} repeats t_us={by_time_det.t_us}"
                raise RecordingError(msg)
            by_time[by_time_det.t_us] = by_time_det
        self._source = source
        self._table = _TimeTable(by_time, tolerance_us=tolerance_us, what=f"detections {path}")

    @staticmethod
    def _frame(path: Path, n: int, fr: object, top_set: object, source: str) -> Detection:
        where = f"{path} frame {n}"
        if not isinstance(fr, dict) or not isinstance(fr.get("t_us"), int):
            msg = f"{where}: needs an integer 't_us' (µs)"
            raise RecordingError(msg)
        kset = fr.get("keypoint_set", top_set)
        if kset not in KEYPOINT_SET_SIZES:
            msg = f"{where}: unknown keypoint_set {kset!r}; use one of {sorted(KEYPOINT_SET_SIZES)}"
            raise RecordingError(msg)
        k = KEYPOINT_SET_SIZES[kset]
        j2 = np.asarray(fr.get("joints2d"), dtype=object)
        try:
            flat = np.asarray(fr.get("joints2d"), dtype=np.float64).reshape(-1)
        except (TypeError, ValueError) as err:
            msg = f"{where}: 'joints2d' must be [[x, y, conf], ...] numbers"
            raise RecordingError(msg) from err
        if j2.shape != (k, 3):
            msg = f"{where}: 'joints2d' has shape {j2.shape}, expected ({k}, 3) for {kset}"
            raise RecordingError(msg)
        xy, c = _person_from_flat(flat, k, what=where)
        p3: FloatArray | None = None
        if fr.get("joints3d_root_rel_mm") is not None:
            try:
                p3 = np.asarray(fr["joints3d_root_rel_mm"], dtype=np.float64)
            except (TypeError, ValueError) as err:
                msg = f"{where}: 'joints3d_root_rel_mm' must be [[x, y, z], ...] numbers"
                raise RecordingError(msg) from err
            if p3.shape != (k, 3) or not np.all(np.isfinite(p3)):
                msg = f"{where}: 'joints3d_root_rel_mm' must be finite, shape ({k}, 3)"
                raise RecordingError(msg)
        if np.any(c < 0) or np.any(c > 1):
            msg = f"{where}: confidences must lie in [0, 1]"
            raise RecordingError(msg)
        j2o, co, j3o = convert_keypoints(xy, c, kset, joints3d=p3)
        return Detection(int(fr["t_us"]), j2o, co, source=source, joints3d_root_rel_mm=j3o)


def write_detections_json(
    path: Path, detections: Iterable[Detection], *, overwrite: bool = False
) -> None:
    """Write detections (one source) as our JSON schema, keypoint set ``"eventcap19"``.

    Raises:
        RecordingError: ``path`` exists and ``overwrite`` is False, or it cannot be written.
        ValidationError: no detections, mixed sources or repeated times.
    """
    dets = sorted(detections, key=lambda d: d.t_us)
    if not dets:
        msg = "no detections to write"
        raise ValidationError(msg)
    sources = {d.source for d in dets}
    if len(sources) != 1:
        msg = f"detections mix sources {sorted(sources)}; write one file per source"
        raise ValidationError(msg)
    times = [d.t_us for d in dets]
    if len(set(times)) != len(times):
        msg = "detections repeat a t_us; give one detection per APS frame"
        raise ValidationError(msg)
    path = Path(path)
    if path.exists() and not overwrite:
        msg = f"{path} exists already, not overwriting (pass overwrite=True to replace it)"
        raise RecordingError(msg)
    frames: list[dict[str, Any]] = []
    for d in dets:
        fr: dict[str, Any] = {
            "t_us": d.t_us,
            "joints2d": np.column_stack([d.joints2d_px, d.confidence]).tolist(),
        }
        if d.joints3d_root_rel_mm is not None:
            fr["joints3d_root_rel_mm"] = d.joints3d_root_rel_mm.tolist()
        frames.append(fr)
    doc = {
        "format": DETECTIONS_FORMAT,
        "format_version": DETECTIONS_FORMAT_VERSION,
        "source": dets[0].source,
        "keypoint_set": "eventcap19",
        "keypoint_names": list(EVENTCAP_KEYPOINTS),
        "frames": frames,
    }
    try:
        path.write_text(json.dumps(doc, indent=1), encoding="utf-8")
    except OSError as err:
        msg = f"cannot write detections file {path}: {err}"
        raise RecordingError(msg) from err


@dataclass(frozen=True, slots=True)
class SyntheticNoise:
    """Detector-like noise (eventcap-method.md §3.1, "paper level").

    Attributes:
        sigma_px: Gaussian noise per 2D coordinate, px.
        swap_probability: Chance per frame that every left/right pair is swapped (2D and 3D
            together, as one detector mislabelling the body's side).
        drop_probability: Chance per joint and frame of a missing 2D joint (confidence 0).
        confidence_low: Kept joints get a confidence uniform in [confidence_low, 1].
        sigma_3d_mm: Gaussian noise per root-relative 3D coordinate (pelvis stays at 0), mm.
        scale_sigma: Standard deviation of one global 3D scale factor around 1, drawn once per
            sequence (a monocular 3D net's error in body size).
    """

    sigma_px: float = 3.0
    swap_probability: float = 0.05
    drop_probability: float = 0.05
    confidence_low: float = 0.6
    sigma_3d_mm: float = 40.0
    scale_sigma: float = 0.03

    def __post_init__(self) -> None:
        check_range(self.sigma_px, 0.0, math.inf, name="sigma_px")
        check_range(self.swap_probability, 0.0, 1.0, name="swap_probability")
        check_range(self.drop_probability, 0.0, 1.0, name="drop_probability")
        check_range(self.confidence_low, 0.0, 1.0, name="confidence_low")
        check_range(self.sigma_3d_mm, 0.0, math.inf, name="sigma_3d_mm")
        check_range(self.scale_sigma, 0.0, 0.5, name="scale_sigma")


class SyntheticDetections:
    """Ground truth plus detector-like noise, for simulated sessions; ``source`` is always
    ``"synthetic"``.

    Noise at a frame depends only on ``seed`` and the frame's ``t_us``, never on which frames
    were asked for before or in what order.

    Args:
        t_us: (F,) APS times, µs.
        joints2d_px: (F, 19, 2) true 2D projections, pixels.
        joints3d_root_rel_mm: Optional (F, 19, 3) true 3D joints, mm, camera axes; re-centred on
            the pelvis here.
        noise: The noise model.
        seed: The seed of every draw.
        tolerance_us: Largest |t - frame time| accepted by :meth:`detect`.

    Raises:
        ValidationError: shapes, non-finite values or repeated times.
    """

    def __init__(
        self,
        t_us: npt.ArrayLike,
        joints2d_px: npt.ArrayLike,
        *,
        joints3d_root_rel_mm: npt.ArrayLike | None = None,
        noise: SyntheticNoise | None = None,
        seed: int,
        tolerance_us: int = 0,
    ) -> None:
        t = np.asarray(check_shape(t_us, ["F"], name="t_us"))
        if not np.issubdtype(t.dtype, np.integer):
            msg = f"t_us must be integer µs, got dtype {t.dtype}"
            raise ValidationError(msg)
        if np.unique(t).size != t.size:
            msg = "t_us repeats a time; give one truth frame per APS time"
            raise ValidationError(msg)
        f = t.size
        j2 = check_finite(check_shape(joints2d_px, [f, NUM_KEYPOINTS, 2], name="joints2d_px"))
        self._truth2d = _frozen(j2)
        self._truth3d: FloatArray | None = None
        if joints3d_root_rel_mm is not None:
            j3 = np.asarray(
                check_finite(
                    check_shape(joints3d_root_rel_mm, [f, NUM_KEYPOINTS, 3], name="joints3d")
                ),
                np.float64,
            )
            self._truth3d = _frozen(j3 - j3[:, _PELVIS : _PELVIS + 1])
        self._noise = noise if noise is not None else SyntheticNoise()
        self._seed = int(seed)
        self._t = t.astype(np.int64)
        self._index = {int(v): i for i, v in enumerate(t.tolist())}
        # one body-size error for the whole sequence
        rng = np.random.default_rng([self._seed, 0])
        self._scale = float(1.0 + self._noise.scale_sigma * rng.standard_normal())
        self._table_times = np.array(sorted(self._index), dtype=np.int64)
        if tolerance_us < 0:
            msg = f"tolerance_us must be >= 0, got {tolerance_us}"
            raise ValidationError(msg)
        self._tol = int(tolerance_us)

    @classmethod
    def from_world(
        cls,
        t_us: npt.ArrayLike,
        keypoints_px: npt.ArrayLike,
        keypoints_world_m: npt.ArrayLike,
        T_world_cam: npt.ArrayLike,
        *,
        noise: SyntheticNoise | None = None,
        seed: int,
        tolerance_us: int = 0,
    ) -> SyntheticDetections:
        """From a simulated take's truth: projections (F, 19, 2) px and world keypoints
        (F, 19, 3) m, with the camera-to-world pose ``T_world_cam`` (4, 4) giving the camera
        axes of the root-relative 3D (converted to mm).

        Raises:
            ValidationError: shapes or non-finite values.
        """
        kw = check_finite(
            check_shape(keypoints_world_m, ["F", NUM_KEYPOINTS, 3], name="keypoints_world_m")
        )
        cam_mm = 1000.0 * world_to_camera(kw, T_world_cam)
        return cls(
            t_us,
            keypoints_px,
            joints3d_root_rel_mm=cam_mm,
            noise=noise,
            seed=seed,
            tolerance_us=tolerance_us,
        )

    @property
    def source(self) -> str:
        """Always ``"synthetic"``."""
        return "synthetic"

    @property
    def scale(self) -> float:
        """The sequence's 3D scale factor (1 = no size error)."""
        return self._scale

    @property
    def times_us(self) -> npt.NDArray[np.int64]:
        """The truth frames' APS times (µs), sorted."""
        return self._table_times.copy()

    def _frame_index(self, t_us: int) -> int:
        i = int(np.searchsorted(self._table_times, t_us))
        near = [j for j in (i - 1, i) if 0 <= j < self._table_times.size]
        t_best = int(min((self._table_times[j] for j in near), key=lambda v: abs(int(v) - t_us)))
        if abs(t_best - t_us) > self._tol:
            msg = (
                f"synthetic detector has no truth frame at t_us={t_us} (nearest {t_best}, "
                f"tolerance {self._tol} µs)"
            )
            raise ProcessingError(msg)
        return self._index[t_best]

    def detect(self, t_us: int, image: npt.NDArray[Any] | None = None) -> Detection:
        """Noisy truth at ``t_us``; ``image`` is ignored."""
        i = self._frame_index(int(t_us))
        t_frame = int(self._t[i])
        nz = self._noise
        # keyed by (seed, 1, time): independent of call order; offset keeps keys non-negative
        rng = np.random.default_rng([self._seed, 1, t_frame + (1 << 62)])
        swap = bool(rng.random() < nz.swap_probability)
        order = list(_MIRROR) if swap else list(range(NUM_KEYPOINTS))
        j2 = self._truth2d[i][order] + nz.sigma_px * rng.standard_normal((NUM_KEYPOINTS, 2))
        conf = rng.uniform(nz.confidence_low, 1.0, NUM_KEYPOINTS)
        dropped = rng.random(NUM_KEYPOINTS) < nz.drop_probability
        conf[dropped] = 0.0
        j2[dropped] = 0.0
        j3 = None
        if self._truth3d is not None:
            j3 = self._scale * self._truth3d[i][order]
            j3 = j3 + nz.sigma_3d_mm * rng.standard_normal((NUM_KEYPOINTS, 3))
            j3 = j3 - j3[_PELVIS]
        return Detection(t_frame, j2, conf, source="synthetic", joints3d_root_rel_mm=j3)
