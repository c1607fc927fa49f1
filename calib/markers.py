"""Retro-reflective marker measurement in D415 IR + depth frames.

Per frame (:func:`measure_frame`):

1. **Blobs** (:func:`detect_blobs`): the IR image is thresholded (markers saturate, the
   background of a D415 IR image sits far below), 8-connected components are labelled with
   ``cv2.connectedComponentsWithStats`` and kept when their area lies in
   ``[min_area_px, max_area_px]``. The centre is the intensity-weighted centroid of the
   component's pixels, sub-pixel (pixel (0, 0) is the centre of the top-left pixel).
2. **Depth at the blob**: D415 depth on a saturated marker is mostly invalid or wrong
   (realsense-d415.md §4.4), so the depth is read from a disc around the centroid that reaches
   ``ring_px`` beyond the blob's radius (the blob plus a ring of the surface it sits on). Of the
   valid samples, the *near cluster* is kept (within ``cluster_m`` of the 10th percentile: the
   background seen past a limb's edge is farther) and its median is the blob's depth. A blob with
   fewer than ``min_depth_samples`` valid samples gets NaN.
3. **Deprojection** with the intrinsics (``K``; optional Brown–Conrady distortion undone with
   ``cv2.undistortPoints``) into the camera frame (OpenCV: +Z forward, metres).

Across cameras: :func:`to_world` (camera → world with ``T_world_cam``), :func:`crop_volume`
(bounding-volume outlier removal) and :func:`merge_views` (points of several views closer than
``radius_m`` merged into their mean, single-linkage through ``scipy.spatial.cKDTree``).

:func:`measure_recording` runs :func:`measure_frame` over the D415 streams of a recording
(``/d415/<serial>/{ir,depth,frame_info,camera_info}``), optionally over a device-time window,
every n-th frame, or only the frames listed by device time, so calibration and replay measure
just what they need; :func:`frame_times` lists every frame's device time without decoding an
image (to pick frames by time across cameras).

Units: pixels for image positions, metres for 3-D points, integer ns for device times.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Final

import cv2
import numpy as np
import numpy.typing as npt
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from mocaprig.acquire.device_streams import (
    DeviceId,
    RecordedD415,
    d415_devices,
    read_frame_sets,
)
from mocaprig.acquire.recording import Recording
from mocaprig.errors import CalibrationError, RecordingError, ValidationError
from mocaprig.progress import ProgressBar
from mocaprig.validation import check_finite, check_positive, check_shape

__all__ = [
    "DEFAULT_THRESHOLD",
    "MarkerFrame",
    "check_blob_options",
    "crop_volume",
    "detect_blobs",
    "frame_times",
    "measure_frame",
    "measure_recording",
    "merge_views",
    "to_world",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: IR level (0..255) above which a pixel belongs to a marker blob.
DEFAULT_THRESHOLD: Final = 200
#: Smallest and largest blob areas kept (px); markers at 1–4 m cover ≈ 5–150 px at 848×480.
DEFAULT_MIN_AREA_PX: Final = 3
DEFAULT_MAX_AREA_PX: Final = 2000
_KERNEL: Final = np.ones((3, 3), np.uint8)
#: The wrap of the D415's u32 µs hardware clock.


@dataclass(frozen=True, slots=True, eq=False)
class MarkerFrame:
    """The markers one D415 saw in one frame.

    Attributes:
        camera: Camera label, ``"d415/<serial>"`` ("" when measured outside a recording).
        t_dev_ns: Device time of the frame (the camera's hardware clock, mid-exposure, integer
            ns, u32 µs wrap undone).
        frame_counter: The device frame counter.
        uv_px: ``(N, 2)`` sub-pixel blob centres (u right, v down; (0, 0) = centre of the
            top-left pixel).
        xyz_cam_m: ``(N, 3)`` marker positions in the camera frame (m); NaN rows where no depth.
        area_px: ``(N,)`` blob areas (pixels above the threshold).
    """

    camera: str
    t_dev_ns: int
    frame_counter: int
    uv_px: F64 = field(repr=False)
    xyz_cam_m: F64 = field(repr=False)
    area_px: F64 = field(repr=False)

    def __post_init__(self) -> None:
        uv = np.array(check_shape(self.uv_px, ["n", 2], name="uv_px"), dtype=np.float64)
        n = uv.shape[0]
        xyz = np.array(check_shape(self.xyz_cam_m, [n, 3], name="xyz_cam_m"), dtype=np.float64)
        area = np.array(check_shape(self.area_px, [n], name="area_px"), dtype=np.float64)
        for a in (uv, xyz, area):
            a.setflags(write=False)
        object.__setattr__(self, "uv_px", uv)
        object.__setattr__(self, "xyz_cam_m", xyz)
        object.__setattr__(self, "area_px", area)
        object.__setattr__(self, "t_dev_ns", int(self.t_dev_ns))
        object.__setattr__(self, "frame_counter", int(self.frame_counter))

    @property
    def n_markers(self) -> int:
        """Number of blobs N."""
        return int(self.uv_px.shape[0])

    @property
    def has_depth(self) -> npt.NDArray[np.bool_]:
        """``(N,)`` True where the blob got a depth."""
        ok: npt.NDArray[np.bool_] = np.asarray(np.isfinite(self.xyz_cam_m).all(axis=1))
        return ok


def check_blob_options(*, threshold: int, min_area_px: int, max_area_px: int) -> None:
    """Check blob-detection options (:func:`detect_blobs`).

    Raises:
        ValidationError: ``threshold`` outside 1..255, or not 1 <= min <= max area.
    """
    if not 1 <= int(threshold) <= 255:
        msg = f"threshold must lie in 1..255 (IR levels), got {threshold!r}"
        raise ValidationError(msg)
    if not 1 <= int(min_area_px) <= int(max_area_px):
        msg = (
            "blob area limits must satisfy 1 <= min_area_px <= max_area_px, "
            f"got {min_area_px!r}, {max_area_px!r}"
        )
        raise ValidationError(msg)


def detect_blobs(
    ir_u8: npt.ArrayLike,
    *,
    threshold: int = DEFAULT_THRESHOLD,
    min_area_px: int = DEFAULT_MIN_AREA_PX,
    max_area_px: int = DEFAULT_MAX_AREA_PX,
) -> tuple[F64, F64]:
    """Bright blobs of an IR image with sub-pixel centres.

    Args:
        ir_u8: ``(H, W)`` uint8 IR image.
        threshold: Pixels ``>= threshold`` are blob pixels (1..255).
        min_area_px: Smallest blob kept (pixels).
        max_area_px: Largest blob kept (pixels; larger are specular surfaces, not markers).

    Returns:
        ``(uv_px (N, 2), area_px (N,))``: intensity-weighted centroids and areas, ordered by
        row then column of the blob's first pixel.

    Raises:
        ValidationError: not a 2-D uint8 image, or bad threshold/area limits.
    """
    img = np.asarray(ir_u8)
    if img.ndim != 2 or img.dtype != np.uint8:
        msg = f"ir_u8 must be a 2-D uint8 IR image, got shape {img.shape} dtype {img.dtype}"
        raise ValidationError(msg)
    check_blob_options(threshold=threshold, min_area_px=min_area_px, max_area_px=max_area_px)
    img = np.ascontiguousarray(img)
    _, hi = cv2.threshold(img, int(threshold) - 1, 1, cv2.THRESH_BINARY)
    if not cv2.countNonZero(hi):
        return np.zeros((0, 2)), np.zeros(0)
    # The centroid also uses the blob's soft edge: one pixel around the saturated core, weighted
    # by the level above a quarter of the threshold (the background of a D415 IR image).
    low = int(threshold) // 4
    _, above_low = cv2.threshold(img, low, 1, cv2.THRESH_BINARY)
    region = cv2.bitwise_and(cv2.dilate(hi, _KERNEL), above_low)
    nz = cv2.findNonZero(region)  # not empty: the region holds the core
    width = img.shape[1]
    nz = nz.reshape(-1, 2)
    uu = nz[:, 0].astype(np.int64)
    vv = nz[:, 1].astype(np.int64)
    idx = vv * width + uu
    k = idx.size
    src, dst = [], []
    for off, col_ok in (
        (1, uu < width - 1),
        (width - 1, uu > 0),
        (width, np.ones(k, dtype=bool)),
        (width + 1, uu < width - 1),
    ):
        target = idx + off
        pos = np.searchsorted(idx, target)
        hit = col_ok & (pos < k)
        hit[hit] = idx[pos[hit]] == target[hit]
        src.append(np.flatnonzero(hit))
        dst.append(pos[hit])
    s_all, d_all = np.concatenate(src), np.concatenate(dst)
    graph = coo_matrix((np.ones(s_all.size, dtype=np.int8), (s_all, d_all)), shape=(k, k))
    n, lab = connected_components(graph, directed=False)
    area = np.bincount(lab, weights=hi[vv, uu].astype(np.float64), minlength=n).astype(np.float64)
    keep = (area >= min_area_px) & (area <= max_area_px)
    if not keep.any():
        return np.zeros((0, 2)), np.zeros(0)
    w = img[vv, uu].astype(np.float64) - low
    sw = np.bincount(lab, weights=w, minlength=n)
    su = np.bincount(lab, weights=w * uu, minlength=n)
    sv = np.bincount(lab, weights=w * vv, minlength=n)
    uv = np.stack([su / sw, sv / sw], axis=1)
    return uv[keep], area[keep]


def _disc_offsets(radius_px: int) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp], F64]:
    r = int(radius_px)
    dv, du = np.mgrid[-r : r + 1, -r : r + 1]
    dist = np.hypot(du, dv).ravel()
    order = np.argsort(dist, kind="stable")
    return dv.ravel()[order], du.ravel()[order], dist[order]


_DISCS: dict[int, tuple[npt.NDArray[np.intp], npt.NDArray[np.intp], F64]] = {}


def _blob_depth_m(
    depth: npt.NDArray[np.uint16],
    uv: F64,
    area: F64,
    *,
    depth_scale_m: float,
    ring_px: float,
    cluster_m: float,
    min_depth_samples: int,
) -> F64:
    """Robust depth (m) per blob: median of the near cluster of valid depth in blob + ring."""
    n = uv.shape[0]
    if n == 0:
        return np.zeros(0)
    h, w = depth.shape
    radius = np.sqrt(area / math.pi) + ring_px  # (N,) px
    rmax = math.ceil(float(radius.max()))
    if rmax not in _DISCS:
        _DISCS[rmax] = _disc_offsets(rmax)
    dv, du, dist = _DISCS[rmax]
    cu = np.rint(uv[:, 0]).astype(np.intp)
    cv_ = np.rint(uv[:, 1]).astype(np.intp)
    vv = cv_[:, None] + dv[None, :]
    uu = cu[:, None] + du[None, :]
    inside = (vv >= 0) & (vv < h) & (uu >= 0) & (uu < w) & (dist[None, :] <= radius[:, None])
    raw = depth[np.clip(vv, 0, h - 1), np.clip(uu, 0, w - 1)].astype(np.float64)
    z = np.sort(np.where(inside & (raw > 0), raw * depth_scale_m, np.inf), axis=1)
    valid = np.count_nonzero(np.isfinite(z), axis=1)
    rows = np.arange(n)
    # Sorted ascending, the near cluster is a prefix: from the 10th percentile sample up to
    # cluster_m beyond it.
    near = z[rows, np.floor(0.1 * np.maximum(valid - 1, 0)).astype(np.intp)]
    count = np.count_nonzero(z <= (near + cluster_m)[:, None], axis=1)
    out = np.full(n, np.nan)
    ok = (valid > 0) & (count >= min_depth_samples)
    lo = np.maximum(count - 1, 0) // 2
    hi = count // 2
    med = 0.5 * (z[rows, lo] + z[rows, np.minimum(hi, z.shape[1] - 1)])
    out[ok] = med[ok]
    return out


def measure_frame(
    ir: npt.ArrayLike,
    depth: npt.ArrayLike,
    K: npt.ArrayLike,
    *,
    depth_scale_m: float = 0.001,
    camera: str = "",
    t_dev_ns: int = 0,
    frame_counter: int = 0,
    distortion: npt.ArrayLike | None = None,
    threshold: int = DEFAULT_THRESHOLD,
    min_area_px: int = DEFAULT_MIN_AREA_PX,
    max_area_px: int = DEFAULT_MAX_AREA_PX,
    ring_px: float = 3.0,
    cluster_m: float = 0.08,
    min_depth_samples: int = 3,
) -> MarkerFrame:
    """Markers of one D415 frame: blobs, robust depth, deprojection (module doc).

    Args:
        ir: ``(H, W)`` uint8 left IR image.
        depth: ``(H, W)`` uint16 depth (Z16) aligned with ``ir`` (D415: left IR = depth frame);
            0 = invalid.
        K: ``(3, 3)`` intrinsics of the IR/depth image (px).
        depth_scale_m: Metres per depth unit.
        camera, t_dev_ns, frame_counter: Copied into the result.
        distortion: Brown–Conrady ``(k1, k2, p1, p2, k3)``; None or zeros for a rectified D415.
        threshold, min_area_px, max_area_px: Blob detection (:func:`detect_blobs`).
        ring_px: How far beyond the blob's radius depth is read (px).
        cluster_m: Width of the near depth cluster (m).
        min_depth_samples: Fewest valid samples in the near cluster for a depth.

    Raises:
        ValidationError: shapes, dtypes or intrinsics are wrong.
    """
    ir_arr = np.asarray(ir)
    depth_arr = np.asarray(depth)
    if depth_arr.dtype != np.uint16 or depth_arr.shape != ir_arr.shape:
        msg = (
            f"depth must be a uint16 image of the IR image's shape {ir_arr.shape}, got shape "
            f"{depth_arr.shape} dtype {depth_arr.dtype}"
        )
        raise ValidationError(msg)
    k = np.asarray(check_finite(check_shape(K, [3, 3], name="K")), dtype=np.float64)
    if k[0, 0] <= 0 or k[1, 1] <= 0:
        msg = f"K needs positive focal lengths (px), got fx={k[0, 0]!r}, fy={k[1, 1]!r}"
        raise ValidationError(msg)
    scale = check_positive(depth_scale_m, name="depth_scale_m")
    if scale > 0.1:
        msg = (
            f"depth_scale_m={scale!r} is metres per depth unit (D415: 0.001); "
            "a value above 0.1 m looks like the wrong unit"
        )
        raise ValidationError(msg)
    uv, area = detect_blobs(
        ir_arr, threshold=threshold, min_area_px=min_area_px, max_area_px=max_area_px
    )
    z = _blob_depth_m(
        depth_arr,
        uv,
        area,
        depth_scale_m=scale,
        ring_px=float(ring_px),
        cluster_m=float(cluster_m),
        min_depth_samples=int(min_depth_samples),
    )
    if uv.shape[0] and distortion is not None and np.any(np.asarray(distortion, float) != 0):
        dist = np.asarray(check_shape(distortion, [5], name="distortion"), dtype=np.float64)
        ab = cv2.undistortPoints(uv.reshape(-1, 1, 2), k, dist).reshape(-1, 2)
    else:
        ab = np.stack([(uv[:, 0] - k[0, 2]) / k[0, 0], (uv[:, 1] - k[1, 2]) / k[1, 1]], axis=1)
        ab[:, 0] -= k[0, 1] * ab[:, 1] / k[0, 0]
    xyz = np.column_stack([ab * z[:, None], z]) if uv.shape[0] else np.zeros((0, 3))
    return MarkerFrame(camera, t_dev_ns, frame_counter, uv, xyz, area)


def to_world(xyz_cam_m: npt.ArrayLike, T_world_cam: npt.ArrayLike) -> F64:
    """Camera-frame points ``(N, 3)`` (m) in the world: ``R·x + t``; NaN rows stay NaN."""
    p = np.asarray(check_shape(xyz_cam_m, ["n", 3], name="xyz_cam_m"), dtype=np.float64)
    t = np.asarray(check_finite(check_shape(T_world_cam, [4, 4], name="T_world_cam")), float)
    out: F64 = p @ t[:3, :3].T + t[:3, 3]
    return out


def crop_volume(points: npt.ArrayLike, lo: npt.ArrayLike, hi: npt.ArrayLike) -> F64:
    """The rows of ``points`` ``(N, 3)`` that are finite and inside the box ``[lo, hi]`` (m)."""
    p = np.asarray(check_shape(points, ["n", 3], name="points"), dtype=np.float64)
    low = np.asarray(check_finite(check_shape(lo, [3], name="lo")), dtype=np.float64)
    high = np.asarray(check_finite(check_shape(hi, [3], name="hi")), dtype=np.float64)
    if np.any(low > high):
        msg = f"crop box is empty: lo {low.tolist()} exceeds hi {high.tolist()} on some axis"
        raise ValidationError(msg)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(p).all(axis=1) & (p >= low).all(axis=1) & (p <= high).all(axis=1)
    out: F64 = p[ok]
    return out


def merge_views(points: Sequence[npt.ArrayLike], *, radius_m: float = 0.010) -> F64:
    """Fuse the marker points of several views into one cloud: the project's only view fusion.

    The replay, the live pipeline and the DeMoCap training data
    (:func:`process.democap.simdata.merge_views`, which crops to the capture box with
    :func:`crop_volume` first, as the replay and the live pipeline do) all call this function,
    so training and inference see the same fusion.

    * **NaN handling**: a row with any non-finite coordinate (NaN, ±inf: a blob without depth)
      is dropped before linking; it neither becomes a point nor links others.
    * **Linking**: single linkage over all the remaining points of all views (two points of one
      view link too): points closer than ``radius_m`` (``cKDTree.query_pairs``, distance
      ≤ ``radius_m``), chained, form one cluster; each cluster becomes the mean of its points.
    * **Order**: clusters in order of their first point in the concatenation of the views (view
      order, then row order within a view), so a single view comes back in its own order when
      no two of its points link.

    Args:
        points: One ``(Ni, 3)`` array per view, in one frame (the world), metres; not modified.
        radius_m: Linking distance (m).

    Returns:
        ``(M, 3)`` merged points (a new array; ``(0, 3)`` when no view has a finite point).
    """
    r = check_positive(radius_m, name="radius_m")
    parts = [
        np.asarray(check_shape(p, ["n", 3], name=f"points[{i}]"), dtype=np.float64)
        for i, p in enumerate(points)
    ]
    if not parts:
        return np.zeros((0, 3))
    allp = np.concatenate(parts)
    allp = allp[np.isfinite(allp).all(axis=1)]
    n = allp.shape[0]
    if n == 0:
        return np.zeros((0, 3))
    pairs = cKDTree(allp).query_pairs(r, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    n_clusters, lab = connected_components(graph, directed=False)
    # Relabel clusters in order of their first member.
    first = np.full(n_clusters, n, dtype=np.int64)
    np.minimum.at(first, lab, np.arange(n))
    rank = np.empty(n_clusters, dtype=np.int64)
    rank[np.argsort(first)] = np.arange(n_clusters)
    lab = rank[lab]
    counts = np.bincount(lab, minlength=n_clusters).astype(np.float64)
    return np.stack(
        [np.bincount(lab, weights=allp[:, j], minlength=n_clusters) / counts for j in range(3)],
        axis=1,
    )


# ------------------------------------------------------------------------- recordings


def _d415_cameras(rec: Recording) -> list[str]:
    return [d.label for d in d415_devices(rec)]


def measure_recording(
    rec: Recording,
    *,
    cameras: Sequence[str] | None = None,
    t_range_ns: tuple[int, int] | None = None,
    every: int = 1,
    frames_t_dev_ns: Mapping[str, Collection[int]] | None = None,
    progress: bool = False,
    threshold: int = DEFAULT_THRESHOLD,
    min_area_px: int = DEFAULT_MIN_AREA_PX,
    max_area_px: int = DEFAULT_MAX_AREA_PX,
) -> dict[str, list[MarkerFrame]]:
    """Measure the markers of the D415 streams of a recording.

    Args:
        rec: An open recording.
        cameras: ``"d415/<serial>"`` labels (or bare serials); None = every D415 in it, or the
            cameras of ``frames_t_dev_ns`` when that is given.
        t_range_ns: ``(start, end)`` device time window (each camera's own clock, ns, end
            excluded); None = all frames.
        every: Measure every n-th frame of the window (by frame order).
        frames_t_dev_ns: Per camera label (or bare serial), the device times (ns, as
            :func:`frame_times` gives them) of the only frames to measure; ``t_range_ns`` and
            ``every`` then apply to those. A camera without an entry is measured in full.
            Lets a caller pick frames by time across cameras (frame order differs between
            cameras once one drops a frame).
        progress: Draw a progress bar on stderr.
        threshold, min_area_px, max_area_px: Blob detection (:func:`detect_blobs`).

    Returns:
        ``{"d415/<serial>": [MarkerFrame, ...]}``, frames in time order. Frames whose device
        time is unknown (no metadata) use the image stamp (the host clock).

    Raises:
        CalibrationError: a camera is not in the recording, or has no ``camera_info``.
        ValidationError: bad ``every`` or ``t_range_ns``.
    """
    if isinstance(every, bool) or int(every) != every or every < 1:
        msg = f"every must be an integer >= 1, got {every!r}"
        raise ValidationError(msg)
    if t_range_ns is not None and not int(t_range_ns[0]) < int(t_range_ns[1]):
        msg = f"t_range_ns must be (start, end) with start < end (ns), got {t_range_ns!r}"
        raise ValidationError(msg)
    available = _d415_cameras(rec)
    keep = {_label(c): set(v) for c, v in (frames_t_dev_ns or {}).items()}
    if cameras is None:
        wanted = list(keep) if frames_t_dev_ns is not None else available
    else:
        wanted = [_label(c) for c in cameras]
    _check_cameras_present(rec, wanted, available)

    plans: dict[str, _Plan] = {}
    for cam in wanted:
        plans[cam] = _plan_camera(rec, cam, t_range_ns, int(every), keep.get(cam))
    total = sum(len(p.counters) for p in plans.values())
    bar: Callable[[int, int], None] | None = ProgressBar("markers") if progress else None
    out: dict[str, list[MarkerFrame]] = {cam: [] for cam in wanted}
    devs = {DeviceId.parse(cam, kind="d415"): cam for cam in wanted}
    live = [p for p in plans.values() if p.counters]
    done = 0
    if live:
        start = min(p.log_lo for p in live)
        end = max(p.log_hi for p in live) + 1
        frame_sets = read_frame_sets(
            rec,
            sorted(devs),
            start_ns=start,
            end_ns=end,
            sequences={d: plans[cam].wanted_seq.keys() for d, cam in devs.items()},
        )
        for rfs in frame_sets:
            fs = rfs.frames
            cam = devs[DeviceId("d415", fs.serial)]
            plan = plans[cam]
            counter, t_dev = plan.wanted_seq[rfs.sequence]
            out[cam].append(
                measure_frame(
                    fs.infrared.image,
                    fs.depth.image,
                    plan.K,
                    depth_scale_m=plan.depth_scale_m,
                    camera=cam,
                    t_dev_ns=t_dev,
                    frame_counter=counter,
                    distortion=plan.distortion,
                    threshold=threshold,
                    min_area_px=min_area_px,
                    max_area_px=max_area_px,
                )
            )
            done += 1
            if bar is not None:
                bar(done, total)
    if bar is not None and done < total:
        bar(total, total)
    for cam, frames in out.items():
        frames.sort(key=lambda f: f.t_dev_ns)
        _log.info(
            "measured %d frames of %s (%d planned)", len(frames), cam, len(plans[cam].counters)
        )
    return out


@dataclass(slots=True)
class _Plan:
    K: F64
    distortion: F64
    depth_scale_m: float
    counters: list[int]
    wanted_seq: dict[int, tuple[int, int]]  # MCAP sequence -> (counter, t_dev_ns)
    log_lo: int = 0
    log_hi: int = 0


def _check_cameras_present(rec: Recording, wanted: Sequence[str], available: Sequence[str]) -> None:
    """``CalibrationError`` naming the first of ``wanted`` that the recording lacks."""
    missing = [c for c in wanted if c not in available]
    if missing:
        msg = (
            f"{rec.path}: no D415 stream {missing[0]!r} (looked for its ir topic); "
            f"D415 cameras in the recording: {available or 'none'}"
        )
        raise CalibrationError(msg)


def _label(camera: str) -> str:
    return DeviceId.parse(camera, kind="d415").label


def frame_times(rec: Recording, *, cameras: Sequence[str] | None = None) -> dict[str, I64]:
    """Device times of every frame of the D415 streams of a recording, no image decoded.

    Args:
        rec: An open recording.
        cameras: ``"d415/<serial>"`` labels (or bare serials); None = every D415 in it.

    Returns:
        ``{"d415/<serial>": t_dev_ns (F,) int64}``, ascending: the times
        :func:`measure_recording` gives its frames (``MarkerFrame.t_dev_ns``), so a subset can
        be passed back as its ``frames_t_dev_ns``.

    Raises:
        CalibrationError: a camera is not in the recording, or has no ``camera_info``.
    """
    available = _d415_cameras(rec)
    wanted = available if cameras is None else [_label(c) for c in cameras]
    _check_cameras_present(rec, wanted, available)
    out: dict[str, I64] = {}
    for cam in wanted:
        plan = _plan_camera(rec, cam, None, 1, None)
        out[cam] = np.sort(np.array([t for _, t in plan.wanted_seq.values()], dtype=np.int64))
    return out


def _plan_camera(
    rec: Recording,
    cam: str,
    t_range_ns: tuple[int, int] | None,
    every: int,
    keep: Collection[int] | None,
) -> _Plan:
    d415 = RecordedD415(rec, DeviceId.parse(cam, kind="d415"))
    try:
        intr = d415.intrinsics()
    except RecordingError as err:
        raise CalibrationError(str(err)) from err
    index = d415.frame_index()
    t_dev = index.t_dev_ns
    order = np.argsort(t_dev, kind="stable")
    sel = []
    for i in order:
        t = int(t_dev[i])
        if keep is not None and t not in keep:
            continue
        if t_range_ns is None or int(t_range_ns[0]) <= t < int(t_range_ns[1]):
            sel.append(int(i))
    sel = sel[::every]
    counters = [int(index.frame_counter[i]) for i in sel]
    plan = _Plan(intr.k, intr.distortion, index.depth_scale_m, counters, {})
    for i in sel:
        plan.wanted_seq[int(index.sequence[i])] = (int(index.frame_counter[i]), int(t_dev[i]))
    if sel:
        logs = index.log_time_ns[sel]
        plan.log_lo, plan.log_hi = int(logs.min()), int(logs.max())
    return plan
