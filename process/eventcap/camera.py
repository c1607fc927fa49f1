"""The event camera as every EventCap stage sees it: one record over :mod:`calib.camera_model`.

Conventions are :mod:`mocaprig.calib.camera_model`'s: Brown–Conrady distortion (OpenCV order),
pixel (0, 0) the centre of the top-left pixel, ``T_world_cam`` camera → world (metres), camera
axes OpenCV (+X right, +Y down, +Z forward).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import numpy.typing as npt

from mocaprig.calib.calibration import CameraCalibration
from mocaprig.calib.camera_model import project_points
from mocaprig.errors import ValidationError
from mocaprig.validation import check_finite, check_shape

__all__ = ["EventCamera"]

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True, eq=False)
class EventCamera:
    """A calibrated event camera (conventions in the module doc).

    Attributes:
        K: intrinsics (3, 3), px.
        distortion: Brown–Conrady ``(k1, k2, p1, p2, k3)`` (5,); zeros for none.
        T_world_cam: camera → world rigid transform (4, 4), translation in metres.
        width, height: sensor size, px (240×180 for a DAVIS240C, 346×260 for a DAVIS346).

    Raises:
        ValidationError: wrong shapes, non-finite values, ``fx``/``fy`` not positive, or a
            non-positive sensor size.
    """

    K: FloatArray = field(repr=False)
    distortion: FloatArray = field(repr=False)
    T_world_cam: FloatArray = field(repr=False)
    width: int
    height: int

    def __post_init__(self) -> None:
        k = np.array(check_finite(check_shape(self.K, [3, 3], name="K"), name="K"), np.float64)
        d = np.array(
            check_finite(check_shape(self.distortion, [5], name="distortion"), name="distortion"),
            np.float64,
        )
        t = np.array(
            check_finite(check_shape(self.T_world_cam, [4, 4], name="T_world_cam")), np.float64
        )
        if k[0, 0] <= 0 or k[1, 1] <= 0:
            msg = f"EventCamera: K needs fx, fy > 0, got {k[0, 0]}, {k[1, 1]}"
            raise ValidationError(msg)
        if int(self.width) <= 0 or int(self.height) <= 0:
            msg = f"EventCamera: sensor size must be positive, got {self.width}x{self.height}"
            raise ValidationError(msg)
        for a in (k, d, t):
            a.setflags(write=False)
        object.__setattr__(self, "K", k)
        object.__setattr__(self, "distortion", d)
        object.__setattr__(self, "T_world_cam", t)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @classmethod
    def from_calibration(cls, cal: CameraCalibration) -> EventCamera:
        """One calibrated camera (DAVIS or D415) of a rig calibration."""
        return cls(
            K=cal.K,
            distortion=cal.distortion,
            T_world_cam=cal.T_world_cam,
            width=cal.width,
            height=cal.height,
        )

    def project(self, points_world: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """``(uv_px (..., 2), z_m (...))`` of world points (..., 3), m: :func:`project_points`.

        Points at or behind the camera get NaN pixels.
        """
        return project_points(points_world, self.T_world_cam, self.K, self.distortion)

    def pixel_rays(self, uv_px: npt.ArrayLike) -> FloatArray:
        """Camera-frame ray directions (N, 3) with z = 1 through pixel positions (N, 2), px.

        The inverse of the Brown–Conrady projection, by ``cv2.undistortPoints`` (with termination
        criteria: 100 iterations or 1e-12) on the
        normalised distorted coordinates (so a skew ``K[0, 1]`` is honoured as in
        :mod:`calib.camera_model`).
        """
        uv = np.asarray(check_finite(check_shape(uv_px, ["N", 2], name="uv_px")), np.float64)
        k = self.K
        yd = (uv[:, 1] - k[1, 2]) / k[1, 1]
        xd = (uv[:, 0] - k[0, 2] - k[0, 1] * yd) / k[0, 0]
        out = np.ones((uv.shape[0], 3))
        if not np.any(self.distortion) or uv.shape[0] == 0:
            out[:, 0], out[:, 1] = xd, yd
            return out
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        src = np.stack([xd, yd], axis=-1)[:, None, :]
        und = cv2.undistortPoints(src, np.eye(3), self.distortion, None, None, None, criteria)
        out[:, :2] = und[:, 0, :]
        return out

    @property
    def R_world_cam(self) -> FloatArray:
        """Rotation camera → world axes ``(3, 3)``."""
        return np.array(self.T_world_cam[:3, :3])
