"""Normalisation into the [0.1, 0.9] cuboid, rotation augmentation, dual-view rendering, fusion.

Frames. World points are metres, Z up (:mod:`mocaprig.process.body`). The method works in an "image"
frame (democap-method.md §1.2): ``u = x`` (image column, right), ``v = -z`` (image row, down),
``w = y`` (depth, away from a camera looking along +w). Normalisation (§1.2 step 5) is per
axis: ``n = (p - lo) / (1.25 (hi - lo)) + 0.1`` so the box spans [0.1, 0.9]. Unlike the
authors' loader the box is taken from the raw points only (never the ground truth, which is not
known at inference; note §9.3); each axis extent is floored at ``min_extent_m`` so a flat cloud
does not blow up.

Rendering (§1.3): the front view is the normalised cloud, the back view the cloud turned 180°
about the vertical axis (``u -> 1 - u``, ``w -> 1 - w``). Each point is a disc of radius 10 px
on an 800×800 canvas painted with its depth, nearest point wins, background 0, then point
sampled every 5th pixel to 160×160 (what OpenCV ``INTER_LINEAR_EXACT`` does for this ratio).
The two steps are done in one: only the canvas pixels that survive the down-sampling are
tested against each disc. Pixel centres are used throughout (the authors' ``floor(x·800) - 1``
disc centre is a one-pixel shift we do not copy).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from mocaprig.errors import ValidationError
from mocaprig.validation import check_finite, check_shape

__all__ = [
    "Normalisation",
    "back_view",
    "fuse_views",
    "normalise",
    "random_rotation",
    "render_view",
    "to_image_frame",
    "to_world_frame",
]

FloatArray = npt.NDArray[np.float64]

MARGIN = 0.1
SCALE_FACTOR = 1.25
RENDER_SCALE = 5
DISC_RADIUS_PX = 2 * RENDER_SCALE


def to_image_frame(p_world_m: npt.ArrayLike) -> FloatArray:
    """World (x, y, z; Z up) -> image frame (u, v, w) = (x, -z, y), metres."""
    p = np.asarray(p_world_m, dtype=np.float64)
    return np.stack([p[..., 0], -p[..., 2], p[..., 1]], axis=-1)


def to_world_frame(p_image_m: npt.ArrayLike) -> FloatArray:
    """Inverse of :func:`to_image_frame`."""
    p = np.asarray(p_image_m, dtype=np.float64)
    return np.stack([p[..., 0], p[..., 2], -p[..., 1]], axis=-1)


@dataclass(frozen=True, slots=True)
class Normalisation:
    """An affine map image-frame metres -> normalised cuboid, per axis.

    ``normalised = (p - lo_m) / scale_m + 0.1``; ``p = (normalised - 0.1) * scale_m + lo_m``.
    """

    lo_m: FloatArray
    scale_m: FloatArray

    def apply(self, p_m: npt.ArrayLike) -> FloatArray:
        """Metres (..., 3) -> normalised (..., 3)."""
        return (np.asarray(p_m, dtype=np.float64) - self.lo_m) / self.scale_m + MARGIN

    def invert(self, n: npt.ArrayLike) -> FloatArray:
        """Normalised (..., 3) -> metres (..., 3)."""
        return (np.asarray(n, dtype=np.float64) - MARGIN) * self.scale_m + self.lo_m


def normalise(points_m: npt.ArrayLike, *, min_extent_m: float = 0.3) -> Normalisation:
    """The per-axis normalisation of a raw cloud (N, 3) in the image frame, metres.

    Raises:
        ValidationError: fewer than 2 points, or non-finite values.
    """
    p = np.asarray(check_finite(check_shape(points_m, ["N", 3], name="points_m")), np.float64)
    if p.shape[0] < 2:
        msg = f"normalise needs at least 2 points, got {p.shape[0]}; the cloud is empty"
        raise ValidationError(msg)
    lo, hi = p.min(axis=0), p.max(axis=0)
    extent = hi - lo
    pad = np.maximum(min_extent_m - extent, 0.0) / 2
    lo, extent = lo - pad, extent + 2 * pad
    return Normalisation(lo_m=lo, scale_m=SCALE_FACTOR * extent)


def random_rotation(
    rng: np.random.Generator,
    *,
    tilt_deg: float = 10.0,
    heading_deg: float = 180.0,
) -> FloatArray:
    """A 3×3 rotation for the image frame: extrinsic x-y-z Euler angles drawn uniformly from
    ±``tilt_deg`` about u, ±``heading_deg`` about the vertical v and ±``tilt_deg`` about w
    (democap-method.md §1.2 step 4; paper §3.5)."""
    ang = rng.uniform([-tilt_deg, -heading_deg, -tilt_deg], [tilt_deg, heading_deg, tilt_deg])
    return np.asarray(Rotation.from_euler("xyz", ang, degrees=True).as_matrix(), np.float64)


def back_view(n: npt.ArrayLike) -> FloatArray:
    """Front-view normalised points (..., 3) -> the back view (180° about v), and back again."""
    q = np.array(n, dtype=np.float64)
    q[..., 0] = 1.0 - q[..., 0]
    q[..., 2] = 1.0 - q[..., 2]
    return q


def fuse_views(front: FloatArray, back: FloatArray) -> FloatArray:
    """Paper Eq. 7: average the front prediction with the back one mapped into the front."""
    return 0.5 * (np.asarray(front, np.float64) + back_view(back))


# Canvas pixel offsets (in output pixels) that a disc of radius 10 canvas px can reach: the
# disc spans at most 21 canvas px, i.e. 5 output samples per axis.
_OFF = np.arange(-2, 3)


def render_view(n: npt.ArrayLike, *, size_px: int = 160) -> npt.NDArray[np.float32]:
    """Render normalised points (N, 3) as a ``size_px``² depth image (float32, background 0).

    A point at normalised (x, y) is a disc of radius 10 px centred at (800 x, 800 y) on the
    800² canvas (pixel k covers [k, k+1)); output pixel (i, j) is canvas pixel (5i+2, 5j+2),
    so it takes the smallest depth among the discs that contain that pixel's centre.
    Points outside the unit square are dropped.
    """
    p = np.asarray(check_shape(n, ["N", 3], name="points"), dtype=np.float64)
    canvas = size_px * RENDER_SCALE
    img = np.full(size_px * size_px, np.inf)
    if p.shape[0]:
        ok = np.all((p[:, :2] >= 0.0) & (p[:, :2] < 1.0), axis=1)
        p = p[ok]
    if p.shape[0]:
        cx, cy = p[:, 0] * canvas, p[:, 1] * canvas
        # nearest output sample to the centre, then the 5×5 samples around it
        j0 = np.floor((cx - 2.5) / RENDER_SCALE + 0.5).astype(np.int64)
        i0 = np.floor((cy - 2.5) / RENDER_SCALE + 0.5).astype(np.int64)
        jj = j0[:, None, None] + _OFF[None, None, :]
        ii = i0[:, None, None] + _OFF[None, :, None]
        sx = jj * RENDER_SCALE + 2.5 - cx[:, None, None]
        sy = ii * RENDER_SCALE + 2.5 - cy[:, None, None]
        inside = (sx * sx + sy * sy <= DISC_RADIUS_PX**2) & (
            (ii >= 0) & (ii < size_px) & (jj >= 0) & (jj < size_px)
        )
        z = np.broadcast_to(p[:, 2, None, None], inside.shape)
        flat = (ii * size_px + jj)[inside]
        np.minimum.at(img, flat, z[inside])
    img[np.isinf(img)] = 0.0
    return img.reshape(size_px, size_px).astype(np.float32)
