"""Rasterise the capsule body template into an event camera's pixel grid (EventCap stage C).

One call casts one ray per pixel inside the body's projected bounding box against the posed
capsules of :mod:`process.body.surface` (its exact ray caster) and returns, per pixel, the
silhouette, the capsule and joint (*segment*) seen, the z-depth and the surface point in that
joint's local frame. A local point can be re-posed at any other pose with
:func:`pose_local_points` (numpy) or :func:`pose_local_points_torch` (differentiable): that is
"the mesh point seen at pixel p in frame i, posed at S_j" of the batch fit's E_cor, and
``v_b(S_f)`` of the refinement's E_sil (eventcap-method.md §1.5, §1.6).

Camera: ``K`` (3×3, px), Brown–Conrady ``(k1, k2, p1, p2, k3)`` and ``T_world_cam`` (camera →
world, metres) exactly as :mod:`calib.camera_model`, which does every world → pixel projection
here. Pixel rays come from undistorted pixel centres (``cv2.undistortPoints``, iterated to
1e-12); pixel ``(0, 0)`` is the centre of the top-left pixel, ``u`` is the column and ``v`` the row.

Boundary pixels are the silhouette minus its 4-neighbour erosion (pixels on the image border do
not count: the silhouette is cut there, it does not end). Their outward unit normals are the
normalised gradient of a Gaussian-smoothed signed distance transform of the silhouette.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import torch

from mocaprig.calib.camera_model import project_camera, world_to_camera
from mocaprig.errors import ValidationError
from mocaprig.process.body.kinematics import forward_kinematics, forward_kinematics_torch
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.body.skeleton import JOINTS, POSE_DIM
from mocaprig.process.body.surface import Capsules, capsules, raycast
from mocaprig.process.eventcap.camera import EventCamera
from mocaprig.validation import check_finite, check_positive, check_shape

__all__ = [
    "Raster",
    "pose_local_points",
    "pose_local_points_torch",
    "rasterize",
]

_log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

# Pixels the bounding box of the projected capsule boxes is grown by: Brown–Conrady distortion
# can push a projected point slightly outside the box of the projected corners.
_BOX_PAD_PX = 2
# The 8 corners of a box as (take hi?) flags per axis.
_CORNERS = np.array(list(itertools.product((False, True), repeat=3)))


@dataclass(frozen=True, slots=True, eq=False)
class Raster:
    """One rasterised view of the capsule body (camera frame: +X right, +Y down, +Z forward).

    Attributes:
        pose: the pose rendered (33,).
        mask: silhouette (H, W) bool.
        capsule_id: capsule index seen (H, W) int16 (``surface.CAPSULE_NAMES``); -1 outside.
        segment: joint index of that capsule (H, W) int16 (its rigid segment); -1 outside.
        depth_m: z-depth along the optical axis (H, W), m; 0 outside.
        local_points_m: surface point seen, in the owning joint's frame (H, W, 3), m; 0 outside.
        boundary_uv: boundary pixels (B, 2) int64 as ``(u, v)`` = (column, row), row-major order.
        boundary_normals: outward unit normals (B, 2) in pixel axes ``(du, dv)``.
        boundary_segment: joint index at each boundary pixel (B,) int64.
        boundary_local_m: surface point at each boundary pixel in its joint's frame (B, 3), m.
        box: pixel rectangle ``(u0, u1, v0, v1)`` (half-open) in which rays were cast.
    """

    pose: FloatArray = field(repr=False)
    mask: npt.NDArray[np.bool_] = field(repr=False)
    capsule_id: npt.NDArray[np.int16] = field(repr=False)
    segment: npt.NDArray[np.int16] = field(repr=False)
    depth_m: FloatArray = field(repr=False)
    local_points_m: FloatArray = field(repr=False)
    boundary_uv: IntArray = field(repr=False)
    boundary_normals: FloatArray = field(repr=False)
    boundary_segment: IntArray = field(repr=False)
    boundary_local_m: FloatArray = field(repr=False)
    box: tuple[int, int, int, int]


def _check_pose(pose: npt.ArrayLike) -> FloatArray:
    q = check_finite(check_shape(pose, [POSE_DIM], name="pose"), name="pose")
    return np.array(q, dtype=np.float64)


def _camera_capsules(caps_world: Capsules, cam: EventCamera) -> Capsules:
    return Capsules(
        a_m=world_to_camera(caps_world.a_m, cam.T_world_cam),
        b_m=world_to_camera(caps_world.b_m, cam.T_world_cam),
        radius_m=caps_world.radius_m,
        joint=caps_world.joint,
    )


def _body_box(caps_cam: Capsules, cam: EventCamera, near_m: float) -> tuple[int, int, int, int]:
    """Pixel rectangle [u0, u1) x [v0, v1) holding the body's image (may be empty)."""
    r = caps_cam.radius_m[:, None]
    lo = np.minimum(caps_cam.a_m, caps_cam.b_m) - r
    hi = np.maximum(caps_cam.a_m, caps_cam.b_m) + r
    w, h = cam.width, cam.height
    if np.all(hi[:, 2] <= near_m):
        return 0, 0, 0, 0
    if np.any(lo[:, 2] <= near_m):
        return 0, w, 0, h
    corners = np.where(_CORNERS[None, :, :], hi[:, None, :], lo[:, None, :]).reshape(-1, 3)
    uv = project_camera(corners, cam.K, cam.distortion)
    u0 = max(int(np.floor(uv[:, 0].min())) - _BOX_PAD_PX, 0)
    u1 = min(int(np.ceil(uv[:, 0].max())) + _BOX_PAD_PX + 1, w)
    v0 = max(int(np.floor(uv[:, 1].min())) - _BOX_PAD_PX, 0)
    v1 = min(int(np.ceil(uv[:, 1].max())) + _BOX_PAD_PX + 1, h)
    if u0 >= u1 or v0 >= v1:
        return 0, 0, 0, 0
    return u0, u1, v0, v1


def _cast_box(
    caps_cam: Capsules, cam: EventCamera, box: tuple[int, int, int, int], near_m: float
) -> tuple[IntArray, IntArray, FloatArray, IntArray, FloatArray]:
    """Rays through every pixel of ``box``: ``(u, v, z-depth, capsule id, hit point cam)``."""
    u0, u1, v0, v1 = box
    vv, uu = np.mgrid[v0:v1, u0:u1]
    u, v = uu.ravel().astype(np.int64), vv.ravel().astype(np.int64)
    dirs = cam.pixel_rays(np.stack([u, v], axis=-1).astype(np.float64))
    dist, cid, _ = raycast(np.zeros_like(dirs), dirs, caps_cam, t_min=near_m)
    hit = cid >= 0
    unit = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    p_cam = np.where(hit[:, None], unit * np.where(hit, dist, 0.0)[:, None], 0.0)
    return u[hit], v[hit], p_cam[hit, 2], cid[hit], p_cam[hit]


def _touches_inner_edge(
    u: IntArray, v: IntArray, box: tuple[int, int, int, int], w: int, h: int
) -> bool:
    u0, u1, v0, v1 = box
    return bool(
        (u0 > 0 and np.any(u == u0))
        or (u1 < w and np.any(u == u1 - 1))
        or (v0 > 0 and np.any(v == v0))
        or (v1 < h and np.any(v == v1 - 1))
    )


def _boundary(mask: npt.NDArray[np.bool_], smoothing_px: float) -> tuple[IntArray, FloatArray]:
    """Boundary pixels ``(B, 2)`` (u, v) and their outward unit normals ``(B, 2)``."""
    m8 = mask.astype(np.uint8)
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    # Replicated borders: a silhouette cut by the image edge has no boundary there.
    eroded = cv2.erode(m8, cross, borderType=cv2.BORDER_REPLICATE)
    bv, bu = np.nonzero((m8 == 1) & (eroded == 0))
    if bu.size == 0:
        return np.zeros((0, 2), np.int64), np.zeros((0, 2))
    # Signed distance, positive outside: its gradient points outward across the boundary.
    d_out = cv2.distanceTransform((1 - m8).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    d_in = cv2.distanceTransform(m8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    sdf = (d_out - d_in).astype(np.float64)
    if smoothing_px > 0:
        sdf = np.asarray(
            cv2.GaussianBlur(sdf, (0, 0), smoothing_px, borderType=cv2.BORDER_REPLICATE),
            dtype=np.float64,
        )
    gu = cv2.Sobel(sdf, cv2.CV_64F, 1, 0, ksize=3, borderType=cv2.BORDER_REPLICATE)
    gv = cv2.Sobel(sdf, cv2.CV_64F, 0, 1, ksize=3, borderType=cv2.BORDER_REPLICATE)
    g = np.stack([gu[bv, bu], gv[bv, bu]], axis=-1)
    norm = np.linalg.norm(g, axis=-1)
    # A one-pixel-thin sliver can have a symmetric distance field and no direction: drop it.
    ok = norm > 1e-9
    uv = np.stack([bu, bv], axis=-1).astype(np.int64)
    return uv[ok], g[ok] / norm[ok, None]


def rasterize(
    pose: npt.ArrayLike,
    shape: BodyShape,
    camera: EventCamera,
    *,
    near_m: float = 1e-3,
    normal_smoothing_px: float = 1.0,
) -> Raster:
    """Rasterise the capsule body at ``pose`` (33,) as seen by ``camera``.

    Rays are cast only inside the projected bounding box of the body (the whole image when
    the body reaches behind the near plane, or when the silhouette touches the box's edge,
    which a strong lens distortion can cause).

    Args:
        pose: pose vector (33,) of :mod:`process.body.skeleton`.
        shape: body shape (capsule template and bone lengths).
        camera: the camera and its sensor size.
        near_m: surfaces nearer than this distance (m) are not seen.
        normal_smoothing_px: Gaussian sigma (px) applied to the signed distance field before
            its gradient gives the boundary normals; 0 for none.

    Returns:
        :class:`Raster`.

    Raises:
        ValidationError: wrong pose shape or non-finite values, non-positive ``near_m``.
    """
    q = _check_pose(pose)
    check_positive(near_m, name="near_m")
    kin = forward_kinematics(q, shape)
    caps_cam = _camera_capsules(capsules(kin, shape), camera)
    w, h = camera.width, camera.height
    box = _body_box(caps_cam, camera, near_m)
    u, v, z, cid, p_cam = _cast_box(caps_cam, camera, box, near_m)
    if box != (0, w, 0, h) and _touches_inner_edge(u, v, box, w, h):
        _log.debug("silhouette reaches the cast box %s: casting the whole image", box)
        box = (0, w, 0, h)
        u, v, z, cid, p_cam = _cast_box(caps_cam, camera, box, near_m)
    seg = caps_cam.joint[cid]
    rot_wc, t_wc = camera.T_world_cam[:3, :3], camera.T_world_cam[:3, 3]
    p_world = p_cam @ rot_wc.T + t_wc
    rot_j = kin.rotations[seg]
    local = np.einsum("nji,nj->ni", rot_j, p_world - kin.positions_m[seg])

    mask = np.zeros((h, w), dtype=bool)
    mask[v, u] = True
    capsule_id = np.full((h, w), -1, dtype=np.int16)
    capsule_id[v, u] = cid
    segment = np.full((h, w), -1, dtype=np.int16)
    segment[v, u] = seg
    depth = np.zeros((h, w))
    depth[v, u] = z
    local_img = np.zeros((h, w, 3))
    local_img[v, u] = local
    b_uv, b_n = _boundary(mask, normal_smoothing_px)
    return Raster(
        pose=q,
        mask=mask,
        capsule_id=capsule_id,
        segment=segment,
        depth_m=depth,
        local_points_m=local_img,
        boundary_uv=b_uv,
        boundary_normals=b_n,
        boundary_segment=segment[b_uv[:, 1], b_uv[:, 0]].astype(np.int64),
        boundary_local_m=local_img[b_uv[:, 1], b_uv[:, 0]],
        box=box,
    )


def _check_segments(segment: npt.ArrayLike, n: int) -> IntArray:
    seg = np.asarray(check_shape(segment, [n], name="segment"))
    if seg.size and (
        not np.issubdtype(seg.dtype, np.integer) or seg.min() < 0 or seg.max() >= len(JOINTS)
    ):
        msg = f"segment must hold joint indices in [0, {len(JOINTS)}); got {seg.dtype} values"
        raise ValidationError(msg)
    return seg.astype(np.int64)


def pose_local_points(
    pose: npt.ArrayLike,
    shape: BodyShape,
    segment: npt.ArrayLike,
    local_points_m: npt.ArrayLike,
) -> FloatArray:
    """World positions of joint-local surface points re-posed at ``pose``.

    Args:
        pose: pose vector(s) (..., 33).
        shape: body shape.
        segment: joint index of each point (N,) (e.g. :attr:`Raster.boundary_segment`).
        local_points_m: points in their joint's frame (N, 3), m.

    Returns:
        World points (..., N, 3), m: ``x_j + R_j @ local``.

    Raises:
        ValidationError: wrong shapes, non-finite values or joint indices out of range.
    """
    loc = np.asarray(
        check_finite(check_shape(local_points_m, ["N", 3], name="local_points_m")), np.float64
    )
    seg = _check_segments(segment, loc.shape[0])
    kin = forward_kinematics(pose, shape)
    rot = kin.rotations[..., seg, :, :]
    out: FloatArray = kin.positions_m[..., seg, :] + (rot @ loc[:, :, None])[..., 0]
    return out


def pose_local_points_torch(
    pose: torch.Tensor,
    shape: BodyShape,
    segment: npt.ArrayLike | torch.Tensor,
    local_points_m: npt.ArrayLike | torch.Tensor,
) -> torch.Tensor:
    """Differentiable :func:`pose_local_points`: pose tensor (..., 33) -> (..., N, 3), m.

    Gradients flow to ``pose`` (and to ``local_points_m`` if it is a tensor that requires
    them); computed in ``pose``'s dtype and device (use float64 for fitting).

    Raises:
        ValidationError: wrong shapes or joint indices out of range.
    """
    kw: dict[str, Any] = {"dtype": pose.dtype, "device": pose.device}
    loc = torch.as_tensor(local_points_m, **kw)
    if loc.ndim != 2 or loc.shape[-1] != 3:
        msg = f"local_points_m must have shape (N, 3), got {tuple(loc.shape)}"
        raise ValidationError(msg)
    seg_np = _check_segments(
        segment.detach().cpu().numpy() if isinstance(segment, torch.Tensor) else segment,
        int(loc.shape[0]),
    )
    pos, rot = forward_kinematics_torch(pose, shape)
    seg = torch.as_tensor(seg_np, device=pose.device)
    r = rot.index_select(-3, seg)
    return pos.index_select(-2, seg) + (r @ loc[..., None])[..., 0]
