"""The static start of the Vicon calibration: still Vicon markers, still D415 blobs, and each
camera registered on them.

:func:`vicon_static_start` finds the trial's leading still frames (markers within
``static_tolerance_m`` of the first frames) and their median cloud, with a unit check on the
cloud's extent; :func:`d415_static_frames` a camera's leading still frames (blobs within
``static_tolerance_px``); :func:`register_static_start` registers a camera on its still frames
(:func:`calib.registration.register_camera`: coarse alignment without an initial pose, gated
matching, bundle adjustment).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Final

import numpy as np
import numpy.typing as npt

from mocaprig.calib.markers import MarkerFrame
from mocaprig.calib.registration import CameraRegistration, register_camera
from mocaprig.calib.vicon_calibration_frames import CalibCamera
from mocaprig.calib.vicon_calibration_options import CalibrationOptions
from mocaprig.errors import CalibrationError

__all__ = ["ViconStatic", "d415_static_frames", "register_static_start", "vicon_static_start"]

F64 = npt.NDArray[np.float64]

#: A body marker cloud spans 0.3–4 m; outside [_MIN_EXTENT_M, _MAX_EXTENT_M] the units are wrong.
_MIN_EXTENT_M: Final = 0.2
_MAX_EXTENT_M: Final = 10.0


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


def d415_static_frames(frames: Sequence[MarkerFrame], tolerance_px: float) -> tuple[int, int]:
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


def register_static_start(
    cam: CalibCamera, frames: Sequence[MarkerFrame], vicon: ViconStatic, opt: CalibrationOptions
) -> tuple[CameraRegistration, int, int]:
    """A camera registered on its static start: ``(registration, first still frame, still
    frames)``.

    Raises:
        CalibrationError: fewer than ``opt.min_static_frames`` still frames, or a failed
            registration.
    """
    k0, n_still = d415_static_frames(frames, opt.static_tolerance_px)
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
    return reg, k0, n_still
