"""The rig in 3D beside the Vicon volume: a figure of a calibration report.

Each calibrated camera is drawn as its viewing frustum (the image corners back-projected through
its intrinsics and distortion, ``cv2.undistortPoints``) at its pose in the world; the Vicon
markers as the static-start cloud, a sample of their positions over the trial and the box they
span (the volume the trial used). Matplotlib 3D, Agg backend, PNG.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from mocaprig.calib.calibration import CameraCalibration
from mocaprig.errors import CalibrationError

__all__ = ["frustum_corners_m", "marker_volume_m", "write_rig_figure"]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]

#: At most this many sampled marker positions are drawn (a readable cloud, a small PNG).
_MAX_SAMPLES = 4000
#: Box edges as pairs of corner indices (corner k has x, y, z from bits 0, 1, 2 of k).
_BOX_EDGES = tuple(
    (a, a | bit) for a in range(8) for bit in (1, 2, 4) if not a & bit
)  # fmt: skip


def frustum_corners_m(camera: CameraCalibration, depth_m: float) -> F64:
    """The world positions ``(4, 3)`` (m) of the image corners seen at ``depth_m`` along the
    optical axis: top-left, top-right, bottom-right, bottom-left.

    Raises:
        CalibrationError: ``depth_m`` is not positive.
    """
    import cv2

    if not depth_m > 0:
        msg = f"camera {camera.name}: frustum depth must be > 0 m, got {depth_m}"
        raise CalibrationError(msg)
    w, h = float(camera.width), float(camera.height)
    uv = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]], dtype=np.float64)
    xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), camera.K, camera.distortion).reshape(-1, 2)
    cam = np.column_stack([xy * depth_m, np.full(4, depth_m)])
    T = np.asarray(camera.T_world_cam, dtype=np.float64)
    out: F64 = cam @ T[:3, :3].T + T[:3, 3]
    return out


def marker_volume_m(positions_m: npt.ArrayLike) -> tuple[F64, F64] | None:
    """The box ``(low, high)`` (m, each ``(3,)``) every finite marker sample lies in; None when
    there is none. ``positions_m`` is any ``(..., 3)`` array with NaN gaps."""
    p = np.asarray(positions_m, dtype=np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    if p.size == 0:
        return None
    return p.min(axis=0), p.max(axis=0)


def _draw_box(ax: Any, low: F64, high: F64) -> None:
    corners = np.array([[(high if k >> i & 1 else low)[i] for i in range(3)] for k in range(8)])
    for n, (a, b) in enumerate(_BOX_EDGES):
        seg = corners[[a, b]]
        ax.plot(
            seg[:, 0], seg[:, 1], seg[:, 2], color="tab:green", lw=1.0,
            label="Vicon markers' extent" if n == 0 else None,
        )  # fmt: skip


def write_rig_figure(
    cameras: Sequence[CameraCalibration],
    path: str | Path,
    *,
    static_markers_m: npt.ArrayLike,
    trial_markers_m: npt.ArrayLike | None = None,
    title: str = "",
) -> Path:
    """Draw the cameras' frusta beside the Vicon markers and write the PNG; returns its path.

    Args:
        cameras: The calibrated cameras (world frame = the markers' frame).
        path: The PNG written.
        static_markers_m: ``(M, 3)`` the markers of the static start (m; NaN where unseen).
        trial_markers_m: ``(F, M, 3)`` the markers over the trial (m; NaN gaps), or None: their
            box is then the static start's.
        title: The figure's title.

    Raises:
        CalibrationError: no camera and no finite marker to draw.
    """
    import matplotlib as mpl

    mpl.use("Agg", force=False)  # no display on a capture PC's CI or over ssh
    from matplotlib.figure import Figure

    static = np.asarray(static_markers_m, dtype=np.float64).reshape(-1, 3)
    trial = None if trial_markers_m is None else np.asarray(trial_markers_m, dtype=np.float64)
    box = marker_volume_m(static if trial is None else trial)
    if not cameras and box is None:
        msg = f"rig figure {path}: no camera and no finite Vicon marker to draw"
        raise CalibrationError(msg)
    centres = np.array([np.asarray(c.T_world_cam)[:3, 3] for c in cameras]).reshape(-1, 3)
    extent_pts = np.vstack([centres, *([] if box is None else list(box))])
    size = float(np.linalg.norm(np.ptp(extent_pts, axis=0))) or 1.0

    fig = Figure(figsize=(9, 7.5), layout="constrained")
    # mplot3d ships no type information: its axes are Any here.
    ax: Any = fig.add_subplot(projection="3d")
    if trial is not None:
        pts = trial.reshape(-1, 3)
        pts = pts[np.isfinite(pts).all(axis=1)]
        if len(pts) > _MAX_SAMPLES:
            pts = pts[:: len(pts) // _MAX_SAMPLES + 1]
        ax.scatter(
            pts[:, 0], pts[:, 1], pts[:, 2], s=1, c="tab:gray", alpha=0.25,
            label="markers over the trial (sample)",
        )  # fmt: skip
    ok = np.isfinite(static).all(axis=1)
    ax.scatter(
        static[ok, 0], static[ok, 1], static[ok, 2], s=8, c="k",
        label=f"static start ({int(ok.sum())} markers)",
    )  # fmt: skip
    if box is not None:
        _draw_box(ax, *box)
    depth = 0.15 * size
    rings = [frustum_corners_m(cam, depth) for cam in cameras]
    for n, (cam, ring) in enumerate(zip(cameras, rings, strict=True)):
        colour = "tab:purple" if cam.kind == "davis" else "tab:blue"
        c = np.asarray(cam.T_world_cam, dtype=np.float64)[:3, 3]
        loop = np.vstack([ring, ring[:1]])
        ax.plot(loop[:, 0], loop[:, 1], loop[:, 2], color=colour, lw=1.2)
        for corner in ring:
            ax.plot(*np.column_stack([c, corner]), color=colour, lw=0.8)
        # The top edge drawn thick: which way is up in the image.
        ax.plot(ring[:2, 0], ring[:2, 1], ring[:2, 2], color=colour, lw=3.0)
        ax.scatter(*c, color=colour, s=25, label=f"{cam.kind} frusta" if n == 0 else None)
        ax.text(c[0], c[1], c[2], f" {cam.serial or cam.name}", fontsize=7, color=colour)
    # Equal scale on every axis: a camera's distance to the volume is read off the figure.
    drawn = np.vstack([extent_pts, *rings])
    lo, hi = np.nanmin(drawn, 0), np.nanmax(drawn, 0)
    mid, half = (lo + hi) / 2, float(np.max(hi - lo)) / 2 * 1.05
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_box_aspect((1.0, 1.0, 1.0))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.view_init(elev=25, azim=-60)
    if box is not None:
        dims = " × ".join(f"{d:.2f}" for d in box[1] - box[0])
        extent = f"Vicon markers' extent {dims} m"
        title = f"{title}\n{extent}" if title else extent
    ax.set_title(title, fontsize=10)
    ax.legend(loc="upper left", fontsize=8)
    out = Path(path)
    fig.savefig(out, dpi=100)
    _log.debug("rig figure written to %s", out)
    return out
