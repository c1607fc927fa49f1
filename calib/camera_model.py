"""The one camera model of mocaprig: rigid world → camera transform and Brown–Conrady projection.

Every projection of 3-D points into a camera image in :mod:`calib` goes through this module
(registration and bundle adjustment, ChArUco board extrinsics, time alignment by
reprojection), so calibration, evaluation and processing agree on one convention. Pure numpy
functions; inputs are never modified (results are new arrays).

Conventions:
    world: any right-handed frame in metres (the Vicon frame for the rig: Z up).
    camera: OpenCV, +X right, +Y down, +Z forward (along the optical axis), metres.
    pose: ``T_world_cam`` is the ``(4, 4)`` rigid transform camera → world
        (``x_world = R·x_cam + t``, ``t`` the camera centre in the world, metres); world →
        camera is therefore ``x_cam = Rᵀ·(x_world − t)`` (:func:`world_to_camera`).
    intrinsics: ``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` in pixels. The skew ``s``
        (``K[0, 1]``) is applied (``u = fx·x″ + s·y″ + cx``), as :func:`calib.markers.measure_frame`
        undoes it; ``cv2.projectPoints`` ignores it, so the two agree exactly when ``s = 0``,
        which is what every OpenCV calibration gives.
    pixels: pixel (0, 0) is the *centre* of the top-left pixel; ``u`` grows to the right
        (columns), ``v`` downwards (rows) — OpenCV's convention.
    distortion: Brown–Conrady as OpenCV, the vector ``(k1, k2, p1, p2, k3)`` (OpenCV order, 5
        numbers; ``None`` or zeros for rectified streams such as the D415's). With normalised
        coordinates ``x = X/Z``, ``y = Y/Z`` and ``r² = x² + y²``::

            radial = 1 + k1·r² + k2·r⁴ + k3·r⁶
            x″ = x·radial + 2·p1·x·y + p2·(r² + 2·x²)
            y″ = y·radial + p1·(r² + 2·y²) + 2·p2·x·y

    broadcasting: points are ``(..., 3)``; ``K`` may be one ``(3, 3)`` matrix or one per point
        ``(..., 3, 3)``, the distortion one ``(5,)`` vector or one per point ``(..., 5)``
        (NumPy broadcasting over the leading axes).
    behind the camera: a point with depth ``Z ≤ min_depth_m`` (default
        :data:`DEFAULT_MIN_DEPTH_M`, i.e. at or behind the camera centre), or with a non-finite
        depth, projects to NaN pixels (no division by zero, no warning). ``min_depth_m=None``
        turns the test off and applies the formula as it stands (a point behind the camera is
        mirrored through the centre, as ``cv2.projectPoints`` does; ``Z = 0`` gives inf/NaN):
        what a least-squares solver wants, since it needs finite residuals everywhere.
        ``z`` returned by :func:`project_points` lets a caller build its own validity mask.
    torch twins: :func:`world_to_camera_torch`, :func:`project_camera_torch` and
        :func:`project_points_torch` apply the same formulas to tensors (any float dtype,
        differentiable; float64 matches the numpy functions to ~1e-12 px) for solvers that
        need derivatives. torch is imported only when they are called.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final

import numpy as np
import numpy.typing as npt

from mocaprig.errors import ValidationError

if TYPE_CHECKING:
    import torch

__all__ = [
    "DEFAULT_MIN_DEPTH_M",
    "distort_normalized",
    "project_camera",
    "project_camera_torch",
    "project_points",
    "project_points_torch",
    "world_to_camera",
    "world_to_camera_torch",
]

F64 = npt.NDArray[np.float64]

#: Points at or closer than this depth (m) project to NaN: "at or behind the camera".
DEFAULT_MIN_DEPTH_M: Final = 1e-9


def _points(x: npt.ArrayLike, name: str) -> F64:
    p = np.asarray(x, dtype=np.float64)
    if p.ndim < 1 or p.shape[-1] != 3:
        msg = f"{name} must have shape (..., 3), got {p.shape}"
        raise ValidationError(msg)
    return p


def world_to_camera(points_world: npt.ArrayLike, T_world_cam: npt.ArrayLike) -> F64:
    """World points ``(..., 3)`` (m) in the camera frame: ``Rᵀ·(x − t)`` of ``T_world_cam``.

    Raises:
        ValidationError: ``points_world`` is not ``(..., 3)`` or ``T_world_cam`` not ``(4, 4)``.
    """
    p = _points(points_world, "points_world")
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.shape != (4, 4):
        msg = f"T_world_cam must be 4×4, got {T.shape}"
        raise ValidationError(msg)
    out: F64 = (p - T[:3, 3]) @ T[:3, :3]
    return out


def distort_normalized(xy: npt.ArrayLike, distortion: npt.ArrayLike | None) -> F64:
    """Brown–Conrady distortion of normalised image coordinates ``(..., 2)`` (``X/Z``, ``Y/Z``).

    Args:
        xy: Undistorted normalised coordinates ``(..., 2)``.
        distortion: ``(k1, k2, p1, p2, k3)``, shape ``(5,)`` or ``(..., 5)`` broadcast against
            ``xy``'s leading axes; ``None`` for none (a copy of ``xy`` is returned).

    Returns:
        Distorted normalised coordinates ``(..., 2)`` (a new array).

    Raises:
        ValidationError: ``xy`` is not ``(..., 2)`` or the distortion not ``(..., 5)``.
    """
    ab = np.asarray(xy, dtype=np.float64)
    if ab.ndim < 1 or ab.shape[-1] != 2:
        msg = f"xy must have shape (..., 2), got {ab.shape}"
        raise ValidationError(msg)
    a, b = ab[..., 0], ab[..., 1]
    ad, bd = _distort(a, b, distortion)
    return np.stack(np.broadcast_arrays(ad, bd), axis=-1)


def _distort(a: F64, b: F64, distortion: npt.ArrayLike | None) -> tuple[F64, F64]:
    if distortion is None:
        return a, b
    d = np.asarray(distortion, dtype=np.float64)
    if d.ndim < 1 or d.shape[-1] != 5:
        msg = f"distortion must be (k1, k2, p1, p2, k3), shape (..., 5), got {d.shape}"
        raise ValidationError(msg)
    k1, k2, p1, p2, k3 = (d[..., i] for i in range(5))
    r2 = a * a + b * b
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    ad: F64 = a * radial + 2.0 * p1 * a * b + p2 * (r2 + 2.0 * a * a)
    bd: F64 = b * radial + p1 * (r2 + 2.0 * b * b) + 2.0 * p2 * a * b
    return ad, bd


def project_camera(
    points_cam: npt.ArrayLike,
    K: npt.ArrayLike,
    distortion: npt.ArrayLike | None = None,
    *,
    min_depth_m: float | None = DEFAULT_MIN_DEPTH_M,
) -> F64:
    """Pixels ``(..., 2)`` of camera-frame points ``(..., 3)`` (m); see the module conventions.

    Args:
        points_cam: Points in the camera frame (OpenCV axes), metres.
        K: ``(3, 3)`` intrinsics, or one per point ``(..., 3, 3)``.
        distortion: ``(k1, k2, p1, p2, k3)`` ``(5,)`` or per point ``(..., 5)``; ``None``: none.
        min_depth_m: Points with depth ``Z ≤ min_depth_m`` (or non-finite) get NaN pixels;
            ``None``: no test, the formula as it stands (behind the camera: mirrored).

    Returns:
        ``(..., 2)`` pixels ``(u, v)`` (a new array).

    Raises:
        ValidationError: shapes that do not fit (``(..., 3)``, ``(..., 3, 3)``, ``(..., 5)``).
    """
    p = _points(points_cam, "points_cam")
    k = np.asarray(K, dtype=np.float64)
    if k.ndim < 2 or k.shape[-2:] != (3, 3):
        msg = f"K must have shape (3, 3) or (..., 3, 3), got {k.shape}"
        raise ValidationError(msg)
    z = p[..., 2]
    ok: npt.NDArray[np.bool_] | None = None
    if min_depth_m is None:
        with np.errstate(divide="ignore", invalid="ignore"):
            a = p[..., 0] / z
            b = p[..., 1] / z
    else:
        ok = z > min_depth_m
        zs = np.where(ok, z, 1.0)
        a = p[..., 0] / zs
        b = p[..., 1] / zs
    with np.errstate(invalid="ignore", over="ignore"):
        ad, bd = _distort(a, b, distortion)
        u = k[..., 0, 0] * ad + k[..., 0, 1] * bd + k[..., 0, 2]
        v = k[..., 1, 1] * bd + k[..., 1, 2]
    uv: F64 = np.stack(np.broadcast_arrays(u, v), axis=-1)
    if ok is not None and not ok.all():
        uv = np.where(ok[..., None], uv, np.nan)
    return uv


def project_points(
    points_world: npt.ArrayLike,
    T_world_cam: npt.ArrayLike,
    K: npt.ArrayLike,
    distortion: npt.ArrayLike | None = None,
    *,
    min_depth_m: float | None = DEFAULT_MIN_DEPTH_M,
) -> tuple[F64, F64]:
    """Project world points ``(..., 3)`` (m) into a camera posed by ``T_world_cam``.

    :func:`world_to_camera` then :func:`project_camera` (same arguments).

    Returns:
        ``(uv_px (..., 2), z_m (...))``: pixels (NaN at or behind the camera, see
        ``min_depth_m``) and the depth of every point in the camera frame (m, any sign).
    """
    pc = world_to_camera(points_world, T_world_cam)
    uv = project_camera(pc, K, distortion, min_depth_m=min_depth_m)
    z: F64 = pc[..., 2].copy()
    return uv, z


# --- torch twins (differentiable) -----------------------------------------------------------


def world_to_camera_torch(points_world: torch.Tensor, T_world_cam: torch.Tensor) -> torch.Tensor:
    """Torch twin of :func:`world_to_camera`: ``Rᵀ·(x − t)`` for points ``(..., 3)`` (m).

    Raises:
        ValidationError: ``points_world`` is not ``(..., 3)`` or ``T_world_cam`` not ``(4, 4)``.
    """
    if points_world.ndim < 1 or points_world.shape[-1] != 3:
        msg = f"points_world must have shape (..., 3), got {tuple(points_world.shape)}"
        raise ValidationError(msg)
    if tuple(T_world_cam.shape) != (4, 4):
        msg = f"T_world_cam must be 4×4, got {tuple(T_world_cam.shape)}"
        raise ValidationError(msg)
    T = T_world_cam.to(dtype=points_world.dtype, device=points_world.device)
    return (points_world - T[:3, 3]) @ T[:3, :3]


def project_camera_torch(
    points_cam: torch.Tensor,
    K: torch.Tensor,
    distortion: torch.Tensor | None = None,
    *,
    min_depth_m: float | None = DEFAULT_MIN_DEPTH_M,
) -> torch.Tensor:
    """Torch twin of :func:`project_camera`: pixels ``(..., 2)`` of camera points ``(..., 3)``.

    Same conventions, broadcasting and depth test as the numpy function (NaN pixels at or
    behind the camera unless ``min_depth_m=None``); differentiable in every input. ``K`` and
    ``distortion`` are cast to ``points_cam``'s dtype and device. With ``min_depth_m`` set, the
    masked points get zero gradients, never NaN ones.

    Raises:
        ValidationError: shapes that do not fit (``(..., 3)``, ``(..., 3, 3)``, ``(..., 5)``).
    """
    import torch

    if points_cam.ndim < 1 or points_cam.shape[-1] != 3:
        msg = f"points_cam must have shape (..., 3), got {tuple(points_cam.shape)}"
        raise ValidationError(msg)
    if K.ndim < 2 or tuple(K.shape[-2:]) != (3, 3):
        msg = f"K must have shape (3, 3) or (..., 3, 3), got {tuple(K.shape)}"
        raise ValidationError(msg)
    k = K.to(dtype=points_cam.dtype, device=points_cam.device)
    z = points_cam[..., 2]
    ok: torch.Tensor | None = None
    if min_depth_m is None:
        zs = z
    else:
        ok = z > min_depth_m
        # Divide by 1 where the point is invalid: no inf/NaN values or gradients leak out.
        zs = torch.where(ok, z, torch.ones_like(z))
    a = points_cam[..., 0] / zs
    b = points_cam[..., 1] / zs
    if distortion is not None:
        d = distortion.to(dtype=points_cam.dtype, device=points_cam.device)
        if d.ndim < 1 or d.shape[-1] != 5:
            msg = f"distortion must be (k1, k2, p1, p2, k3), shape (..., 5), got {tuple(d.shape)}"
            raise ValidationError(msg)
        k1, k2, p1, p2, k3 = (d[..., i] for i in range(5))
        r2 = a * a + b * b
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        a, b = (
            a * radial + 2.0 * p1 * a * b + p2 * (r2 + 2.0 * a * a),
            b * radial + p1 * (r2 + 2.0 * b * b) + 2.0 * p2 * a * b,
        )
    u = k[..., 0, 0] * a + k[..., 0, 1] * b + k[..., 0, 2]
    v = k[..., 1, 1] * b + k[..., 1, 2]
    zero = torch.zeros_like(u + v)  # broadcasts u and v against each other
    uv = torch.stack([u + zero, v + zero], dim=-1)
    if ok is not None:
        uv = torch.where(ok[..., None], uv, torch.full_like(uv, float("nan")))
    return uv


def project_points_torch(
    points_world: torch.Tensor,
    T_world_cam: torch.Tensor,
    K: torch.Tensor,
    distortion: torch.Tensor | None = None,
    *,
    min_depth_m: float | None = DEFAULT_MIN_DEPTH_M,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Torch twin of :func:`project_points`: ``(uv_px (..., 2), z_m (...))``."""
    pc = world_to_camera_torch(points_world, T_world_cam)
    return project_camera_torch(pc, K, distortion, min_depth_m=min_depth_m), pc[..., 2]
