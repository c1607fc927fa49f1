"""Capsule surface template, an exact vectorised ray caster and a pinhole depth renderer.

The body surface is 22 capsules (a capsule = all points within ``radius`` of the segment
``a``–``b``): one per limb bone, a horizontal pelvis, a vertical abdomen and thorax, a
horizontal upper chest, two clavicles, the neck and a near-spherical head. Each capsule rides
rigidly on one joint frame (its *segment* label, a joint index). The feet's capsules touch the
floor and the head's top touches HeadEnd in the rest pose, so the surface spans exactly the
standing height.

Ray casting is exact (cylinder plus two spheres), one capsule at a time over all rays; the
renderer only casts the pixels inside each capsule's projected bounding box.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from mocaprig.errors import ValidationError
from mocaprig.process.body._capsule_math import closest_on_segment, ray_capsule, surface_normals
from mocaprig.process.body.kinematics import Kinematics, forward_kinematics
from mocaprig.process.body.shape import (
    BALL_FRACTION,
    HEEL_FRACTION,
    TOE_FRACTION,
    BodyShape,
    rest_offsets,
)
from mocaprig.process.body.skeleton import JOINT_INDEX
from mocaprig.validation import check_finite, check_shape

__all__ = [
    "CAPSULE_INDEX",
    "CAPSULE_NAMES",
    "CapsuleTemplate",
    "Capsules",
    "RenderResult",
    "capsule_template",
    "capsules",
    "raycast",
    "render_pinhole",
    "signed_distance",
]

_log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_SIDE_PARTS = ("clavicle", "upper_arm", "forearm", "hand", "thigh", "shank", "foot", "toe")
#: Capsule names in template order.
CAPSULE_NAMES: tuple[str, ...] = (
    "pelvis",
    "abdomen",
    "thorax",
    "chest",
    "neck",
    "head",
    *(f"right_{p}" for p in _SIDE_PARTS),
    *(f"left_{p}" for p in _SIDE_PARTS),
)
#: Capsule name -> index.
CAPSULE_INDEX: dict[str, int] = {n: i for i, n in enumerate(CAPSULE_NAMES)}


@dataclass(frozen=True, slots=True, eq=False)
class CapsuleTemplate:
    """Capsules in their joints' frames (rest-aligned body axes), metres.

    Attributes:
        names: capsule names (C,), as :data:`CAPSULE_NAMES`.
        joint: joint index each capsule rides on (C,).
        a_local_m, b_local_m: segment end points in that joint's frame (C, 3).
        radius_m: radii (C,).
    """

    names: tuple[str, ...]
    joint: IntArray
    a_local_m: FloatArray
    b_local_m: FloatArray
    radius_m: FloatArray


@dataclass(frozen=True, slots=True, eq=False)
class Capsules:
    """Posed capsules in the world frame.

    Attributes:
        a_m, b_m: segment end points (..., C, 3), world frame, metres.
        radius_m: radii (C,), metres.
        joint: segment label (C,): the joint index each capsule rides on.
    """

    a_m: FloatArray
    b_m: FloatArray
    radius_m: FloatArray
    joint: IntArray


@dataclass(frozen=True, slots=True, eq=False)
class RenderResult:
    """One rendered pinhole view (OpenCV camera: +Z forward, +X right, +Y down).

    Attributes:
        depth_m: z-depth along the optical axis (H, W), metres; 0 = background.
        segment: joint index of the visible capsule (H, W) int16; -1 = background.
            The silhouette is ``segment >= 0``.
        normals_cam: unit outward surface normals in the camera frame (H, W, 3); 0 on the
            background.
    """

    depth_m: FloatArray
    segment: npt.NDArray[np.int16]
    normals_cam: FloatArray


def capsule_template(shape: BodyShape) -> CapsuleTemplate:
    """The 22-capsule body surface of ``shape`` in joint frames (see :data:`CAPSULE_NAMES`)."""
    s = shape
    off = rest_offsets(shape)
    rows: dict[str, tuple[str, tuple[float, ...], tuple[float, ...], float]] = {}
    zero = (0.0, 0.0, 0.0)
    hl_pelvis = max(0.5 * s.hip_width_m - s.pelvis_radius_m, 0.0)
    rows["pelvis"] = ("Hips", (-hl_pelvis, 0.0, 0.0), (hl_pelvis, 0.0, 0.0), s.pelvis_radius_m)
    rows["abdomen"] = ("Hips", zero, tuple(off[JOINT_INDEX["Spine1"]]), s.abdomen_radius_m)
    rows["thorax"] = ("Spine1", zero, tuple(off[JOINT_INDEX["Spine2"]]), s.chest_radius_m)
    # Upper chest: a horizontal capsule at 40 % of the way up to C7, about 0.17H wide.
    hl_chest = 0.08 * s.shoulder_width_m
    zc = 0.4 * s.chest_length_m
    rows["chest"] = ("Spine2", (-hl_chest, 0.0, zc), (hl_chest, 0.0, zc), s.chest_radius_m)
    rows["neck"] = ("Neck", zero, tuple(off[JOINT_INDEX["Head"]]), s.neck_radius_m)
    # Head: top of the sphere at HeadEnd, chin halfway down the neck segment.
    fwd, r_h = s.head_forward_m, s.head_radius_m
    b_z = s.head_length_m - r_h
    a_z = min(r_h - 0.5 * s.neck_length_m, b_z)
    rows["head"] = ("Head", (0.0, fwd, a_z), (0.0, fwd, b_z), r_h)
    fl = s.foot_length_m
    # The thigh ends one thigh radius above the knee so the knee itself is only as wide as the
    # shank's upper sphere (a capsule cannot taper); the shank's lower sphere must stay above
    # the floor, so it is lifted if the calf is thick.
    knee = off[JOINT_INDEX["RightLeg"]]
    thigh_lift = min(s.thigh_radius_m, 0.5 * s.thigh_length_m)
    lift = max(0.0, s.shank_radius_m - 0.8 * s.ankle_height_m)
    right = {
        "clavicle": ("RightShoulder", zero, off[JOINT_INDEX["RightArm"]], s.clavicle_radius_m),
        "upper_arm": ("RightArm", zero, off[JOINT_INDEX["RightForeArm"]], s.upper_arm_radius_m),
        "forearm": ("RightForeArm", zero, off[JOINT_INDEX["RightHand"]], s.forearm_radius_m),
        "hand": ("RightHand", zero, (0.0, 0.0, s.hand_radius_m - s.hand_length_m), s.hand_radius_m),
        "thigh": ("RightUpLeg", zero, knee + np.array((0.0, 0.0, thigh_lift)), s.thigh_radius_m),
        "shank": (
            "RightLeg",
            zero,
            off[JOINT_INDEX["RightFoot"]] + (0.0, 0.0, lift),
            s.shank_radius_m,
        ),
        "foot": (
            "RightFoot",
            (0.0, s.foot_radius_m - HEEL_FRACTION * fl, s.foot_radius_m - s.ankle_height_m),
            (0.0, BALL_FRACTION * fl, s.foot_radius_m - s.ankle_height_m),
            s.foot_radius_m,
        ),
        "toe": (
            "RightToeBase",
            zero,
            (0.0, TOE_FRACTION * fl - s.toe_radius_m, s.toe_radius_m - s.foot_radius_m),
            s.toe_radius_m,
        ),
    }
    for part, (joint, a, b, r) in right.items():
        rows[f"right_{part}"] = (joint, tuple(a), tuple(b), r)
        rows[f"left_{part}"] = (
            "Left" + joint.removeprefix("Right"),
            (-a[0], a[1], a[2]),
            (-b[0], b[1], b[2]),
            r,
        )
    ordered = [rows[n] for n in CAPSULE_NAMES]
    return CapsuleTemplate(
        names=CAPSULE_NAMES,
        joint=np.array([JOINT_INDEX[r[0]] for r in ordered], dtype=np.int64),
        a_local_m=np.array([r[1] for r in ordered], dtype=np.float64),
        b_local_m=np.array([r[2] for r in ordered], dtype=np.float64),
        radius_m=np.array([r[3] for r in ordered], dtype=np.float64),
    )


def capsules(kin: Kinematics | npt.ArrayLike, shape: BodyShape) -> Capsules:
    """Pose the capsule template: ``kin`` is a :class:`Kinematics` or pose vectors (..., 33).

    Returns:
        :class:`Capsules` with end points (..., 22, 3) in the world frame, m.
    """
    k = kin if isinstance(kin, Kinematics) else forward_kinematics(kin, shape)
    t = capsule_template(shape)
    rot = k.rotations[..., t.joint, :, :]
    pos = k.positions_m[..., t.joint, :]
    a = pos + (rot @ t.a_local_m[..., None])[..., 0]
    b = pos + (rot @ t.b_local_m[..., None])[..., 0]
    return Capsules(a_m=a, b_m=b, radius_m=t.radius_m.copy(), joint=t.joint.copy())


def _check_capsules(caps: Capsules) -> tuple[FloatArray, FloatArray, FloatArray]:
    a = check_shape(caps.a_m, ["C", 3], name="capsules.a_m (one frame)")
    b = check_shape(caps.b_m, [a.shape[0], 3], name="capsules.b_m")
    r = check_shape(caps.radius_m, [a.shape[0]], name="capsules.radius_m")
    return (
        np.asarray(a, dtype=np.float64),
        np.asarray(b, dtype=np.float64),
        np.asarray(r, dtype=np.float64),
    )


def signed_distance(points: npt.ArrayLike, caps: Capsules) -> FloatArray:
    """Signed distance from points to each capsule's surface, m (negative inside).

    One frame of capsules (``a_m`` (C, 3)): points (..., 3) -> (..., C). A batch of frames
    (``a_m`` (..., C, 3)): points (..., N, 3) with the same leading dims -> (..., N, C).
    """
    p = np.asarray(check_shape(points, ["...", 3], name="points"), dtype=np.float64)[..., None, :]
    a = np.asarray(check_shape(caps.a_m, ["...", "C", 3], name="capsules.a_m"), dtype=np.float64)
    b = np.asarray(check_shape(caps.b_m, list(a.shape), name="capsules.b_m"), dtype=np.float64)
    r = np.asarray(check_shape(caps.radius_m, [a.shape[-2]], name="capsules.radius_m"))
    if a.ndim > 2:
        a, b = a[..., None, :, :], b[..., None, :, :]
    q = closest_on_segment(p, a, b)
    return np.asarray(np.linalg.norm(p - q, axis=-1) - r)


def raycast(
    origins: npt.ArrayLike,
    directions: npt.ArrayLike,
    caps: Capsules,
    *,
    t_min: float = 0.0,
) -> tuple[FloatArray, npt.NDArray[np.int64], FloatArray]:
    """Exact first hits of rays against one frame of capsules.

    Args:
        origins: ray origins (R, 3), same frame as ``caps``, m.
        directions: ray directions (R, 3), any non-zero length (normalised here).
        caps: one frame of capsules (C capsules).
        t_min: hits at a distance <= ``t_min`` (m) are ignored. An origin inside a capsule
            sees that capsule's exit point.

    Returns:
        ``(depth_m (R,), capsule_id (R,), normals (R, 3))``: distance along the unit
        direction (``inf`` on a miss), the capsule index (-1 on a miss) and the unit outward
        normal at the hit (0 on a miss).

    Raises:
        ValidationError: wrong shapes, non-finite values or zero-length directions.
    """
    a, b, r = _check_capsules(caps)
    o = np.asarray(check_finite(check_shape(origins, ["R", 3], name="origins")), dtype=np.float64)
    d = np.asarray(check_shape(directions, [o.shape[0], 3], name="directions"), dtype=np.float64)
    d = np.asarray(check_finite(d, name="directions"))
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    if np.any(norm <= 0):
        msg = "directions has zero-length rows; every ray needs a direction"
        raise ValidationError(msg)
    d = d / norm
    n_rays = o.shape[0]
    depth = np.full(n_rays, np.inf)
    cid = np.full(n_rays, -1, dtype=np.int64)
    for c in range(a.shape[0]):
        # Cull with the bounding sphere: cheap, and most rays miss most capsules.
        centre = 0.5 * (a[c] + b[c])
        rad = 0.5 * float(np.linalg.norm(b[c] - a[c])) + float(r[c])
        oc = centre - o
        along = np.sum(oc * d, axis=-1)
        perp2 = np.sum(oc * oc, axis=-1) - along * along
        cand = np.flatnonzero((perp2 <= rad * rad) & (along + rad > t_min))
        if cand.size == 0:
            continue
        t = ray_capsule(o[cand], d[cand], a[c], b[c], float(r[c]), t_min)
        better = t < depth[cand]
        idx = cand[better]
        depth[idx] = t[better]
        cid[idx] = c
    normals = np.zeros_like(d)
    hit = np.flatnonzero(cid >= 0)
    if hit.size:
        p = o[hit] + depth[hit, None] * d[hit]
        normals[hit] = surface_normals(p, a[cid[hit]], b[cid[hit]])
    return depth, cid, normals


def render_pinhole(
    caps: Capsules,
    K: npt.ArrayLike,
    T_cam_world: npt.ArrayLike,
    width: int,
    height: int,
    *,
    near_m: float = 1e-3,
) -> RenderResult:
    """Render depth, segment labels and normals of one frame of capsules through a pinhole.

    Pixel ``(u, v)`` (OpenCV: ``(0, 0)`` is the centre of the top-left pixel) looks along
    ``K⁻¹ [u, v, 1]`` in the camera frame (+Z forward, +X right, +Y down), with
    ``X_cam = T_cam_world @ X_world``. No lens distortion.

    Args:
        caps: one frame of posed capsules (C capsules), world frame.
        K: intrinsics (3, 3).
        T_cam_world: world -> camera rigid transform (4, 4).
        width, height: image size in pixels.
        near_m: surfaces nearer than this z-depth (m) are clipped.

    Returns:
        :class:`RenderResult` (depth 0 and segment -1 on the background).

    Raises:
        ValidationError: wrong shapes, non-finite values or a non-positive image size.
    """
    a_w, b_w, r = _check_capsules(caps)
    k_mat = np.asarray(check_finite(check_shape(K, [3, 3], name="K")), dtype=np.float64)
    t_cw = np.asarray(
        check_finite(check_shape(T_cam_world, [4, 4], name="T_cam_world")), dtype=np.float64
    )
    if width <= 0 or height <= 0:
        msg = f"image size must be positive, got {width}x{height}"
        raise ValidationError(msg)
    rot, trans = t_cw[:3, :3], t_cw[:3, 3]
    a = a_w @ rot.T + trans
    b = b_w @ rot.T + trans
    k_inv = np.linalg.inv(k_mat)
    depth = np.full((height, width), np.inf)
    cid = np.full((height, width), -1, dtype=np.int64)
    us = np.arange(width, dtype=np.float64)
    vs = np.arange(height, dtype=np.float64)
    origin = np.zeros(3)
    for c in range(a.shape[0]):
        box = _pixel_box(a[c], b[c], float(r[c]), k_mat, width, height, near_m)
        if box is None:
            continue
        u0, u1, v0, v1 = box
        uu, vv = np.meshgrid(us[u0:u1], vs[v0:v1])
        pix = np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)], axis=-1)
        # Rays with unit z: the ray parameter is the z-depth itself.
        d = pix @ k_inv.T
        d = d / d[:, 2:3]
        t = ray_capsule(origin, d, a[c], b[c], float(r[c]), near_m).reshape(uu.shape)
        region = depth[v0:v1, u0:u1]
        better = t < region
        region[better] = t[better]
        cid[v0:v1, u0:u1][better] = c
    hit = cid >= 0
    normals = np.zeros((height, width, 3))
    if np.any(hit):
        hv, hu = np.nonzero(hit)
        hpix = np.stack([hu, hv, np.ones(hu.size)], axis=-1).astype(np.float64)
        hd = hpix @ k_inv.T
        p = hd / hd[:, 2:3] * depth[hv, hu][:, None]
        ci = cid[hv, hu]
        normals[hv, hu] = surface_normals(p, a[ci], b[ci])
    segment = np.where(hit, caps.joint[np.where(hit, cid, 0)], -1).astype(np.int16)
    return RenderResult(depth_m=np.where(hit, depth, 0.0), segment=segment, normals_cam=normals)


def _pixel_box(
    a: FloatArray,
    b: FloatArray,
    r: float,
    k_mat: FloatArray,
    width: int,
    height: int,
    near_m: float,
) -> tuple[int, int, int, int] | None:
    """Pixel rectangle [u0, u1) x [v0, v1) that contains the capsule's image, or None.

    Projects the corners of the capsule's axis-aligned bounding box (camera frame); when the
    box reaches behind the near plane the whole image is a candidate.
    """
    lo = np.minimum(a, b) - r
    hi = np.maximum(a, b) + r
    if hi[2] <= near_m:
        return None
    if lo[2] <= near_m:
        return 0, width, 0, height
    corners = np.array(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij")).reshape(3, 8).T
    proj = corners @ k_mat.T
    uv = proj[:, :2] / proj[:, 2:3]
    u0 = max(int(np.floor(uv[:, 0].min())), 0)
    u1 = min(int(np.ceil(uv[:, 0].max())) + 1, width)
    v0 = max(int(np.floor(uv[:, 1].min())), 0)
    v1 = min(int(np.ceil(uv[:, 1].max())) + 1, height)
    if u0 >= u1 or v0 >= v1:
        return None
    return u0, u1, v0, v1
