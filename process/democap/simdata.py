"""Marker-level simulated D415 observations for training and evaluating DeMoCap.

No images are rendered: each frame's 53 true markers are "seen" by each D415 of a sampled rig
through a measurement model of what the paper's per-view blob extraction and depth lifting
produce (democap-method.md §1.1), then fused as in §3.3/§3.4:

* **rig** (:func:`sample_rig`): D415s on a circle (radius 2.5 m ± 0.25, height 1.4 m ± 0.15,
  azimuths 45°, 135°, 225°, 315° ± 8°) aimed at (0, 0, 0.9 m) ± 0.1, 848×480 IR, fx 623 px
  ± 3 % (the simulated world's layout, docs/simulated-world.md). Three cameras drop one at
  random; two keep an opposing pair.
* **visibility** (:func:`visibility`): a marker is detected by a camera when it lies in the
  image (8 px margin), 0.3–6 m away, faces the camera (angle between the skin normal and the
  line of sight < 80°), and the line of sight is not blocked by any body capsule
  (:mod:`process.body.surface`). The blocking test is exact for capsules: the segment from the
  camera to 12 mm short of the marker centre must stay farther than the capsule radius from
  every capsule axis (segment–segment distance). Self-occlusion follows from the same test.
* **measurement** (:func:`observe`): the IR blob centre gets 0.25 px of lateral noise, the
  depth the D415 stereo noise ``σz = z²·s/(f·B)`` with s = 0.08 px, B = 55 mm (the D415 model
  of ``drivers_mock/d415_render.py``), plus a 2 mm floor for the retro-reflective surface; the
  lifted point is on the marker's front surface (7 mm short of its centre). 2 % of detections
  get a gross depth error of 3–15 cm (saturated IR in the stereo match); 4 % are lost at random.
* **ghosts**: per view a Poisson number (mean 0.7) of spurious points: half reflections on the
  suit (a random point 0–3 cm off the skin), half stray reflections within 1 m of the actor.
* **fusion** (:func:`merge_views`): union of the views, points outside the capture box dropped,
  then points from different cameras closer than 10 mm merged (connected components, mean).
  Duplicates whose errors exceed 10 mm stay separate, as on the real rig.

Everything is deterministic for a ``numpy.random.Generator``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from acquire.check import check_shape
from acquire.errors import ValidationError
from process.body import (
    BodyShape,
    MarkerSet,
    Motion,
    capsule_template,
    democap_joints,
    forward_kinematics,
)

__all__ = [
    "Camera",
    "PoseFrames",
    "merge_views",
    "observe",
    "pose_frames",
    "sample_rig",
    "visibility",
]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

IMAGE_W, IMAGE_H = 848, 480
FOCAL_PX = 623.0
BASELINE_M = 0.055
SUBPIXEL_RMS_PX = 0.08
LATERAL_RMS_PX = 0.25
DEPTH_FLOOR_M = 0.002
MARKER_RADIUS_M = 0.007
GROSS_RATE = 0.02
MISS_RATE = 0.04
GHOSTS_PER_VIEW = 0.7
MERGE_RADIUS_M = 0.010
CAPTURE_BOX_M = ((-2.2, 2.2), (-2.2, 2.2), (-0.1, 2.4))


@dataclass(frozen=True, slots=True)
class Camera:
    """One D415 depth viewpoint.

    Attributes:
        centre_m: optical centre (3,), world, m.
        r_cw: rotation world -> camera (3, 3); camera +Z forward, +X right, +Y down.
        focal_px: focal length (px), square pixels, principal point at the image centre.
    """

    centre_m: FloatArray
    r_cw: FloatArray
    focal_px: float


def _look_at(centre: FloatArray, target: FloatArray) -> FloatArray:
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.array([0.0, 0.0, 1.0]))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def sample_rig(rng: np.random.Generator, *, num_cameras: int = 4) -> list[Camera]:
    """A randomised 4-camera cross rig, reduced to ``num_cameras`` (2, 3 or 4).

    Raises:
        ValidationError: ``num_cameras`` not in {2, 3, 4}.
    """
    if num_cameras not in (2, 3, 4):
        msg = f"num_cameras must be 2, 3 or 4, got {num_cameras!r}"
        raise ValidationError(msg)
    cams: list[Camera] = []
    for k in range(4):
        az = np.deg2rad(45.0 + 90.0 * k + rng.uniform(-8.0, 8.0))
        rad = 2.5 + rng.uniform(-0.25, 0.25)
        c = np.array([rad * np.cos(az), rad * np.sin(az), 1.4 + rng.uniform(-0.15, 0.15)])
        aim = np.array([0.0, 0.0, 0.9]) + rng.uniform(-0.1, 0.1, 3)
        roll = Rotation.from_rotvec([0.0, 0.0, np.deg2rad(rng.uniform(-1.0, 1.0))]).as_matrix()
        cams.append(
            Camera(
                centre_m=c,
                r_cw=roll @ _look_at(c, aim),
                focal_px=FOCAL_PX * float(rng.uniform(0.97, 1.03)),
            )
        )
    if num_cameras == 3:
        cams.pop(int(rng.integers(4)))
    elif num_cameras == 2:
        first = int(rng.integers(2))
        cams = [cams[first], cams[first + 2]]
    return cams


@dataclass(frozen=True, slots=True)
class PoseFrames:
    """True geometry of T frames of one subject, world frame, metres.

    Attributes:
        markers_m: (T, 53, 3) marker centres.
        normals: (T, 53, 3) unit skin normals at the markers.
        joints_m: (T, 19, 3) DeMoCap joints.
        caps_a_m, caps_b_m: (T, C, 3) capsule axis end points.
        caps_radius_m: (C,) capsule radii.
        action: the motion's name.
    """

    markers_m: FloatArray
    normals: FloatArray
    joints_m: FloatArray
    caps_a_m: FloatArray
    caps_b_m: FloatArray
    caps_radius_m: FloatArray
    action: str

    @property
    def num_frames(self) -> int:
        """T."""
        return int(self.markers_m.shape[0])


def pose_frames(motion: Motion, shape: BodyShape, markers: MarkerSet) -> PoseFrames:
    """Forward kinematics of every frame of ``motion`` into markers, joints and capsules."""
    kin = forward_kinematics(motion.poses, shape)
    j = markers.joint_index
    rot = kin.rotations[:, j]
    pos = kin.positions_m[:, j]
    mk = pos + (rot @ markers.offsets_m[..., None])[..., 0]
    nrm = (rot @ markers.normals[..., None])[..., 0]
    t = capsule_template(shape)
    crot = kin.rotations[:, t.joint]
    cpos = kin.positions_m[:, t.joint]
    a = cpos + (crot @ t.a_local_m[..., None])[..., 0]
    b = cpos + (crot @ t.b_local_m[..., None])[..., 0]
    return PoseFrames(
        markers_m=mk,
        normals=nrm,
        joints_m=democap_joints(kin),
        caps_a_m=a,
        caps_b_m=b,
        caps_radius_m=t.radius_m.copy(),
        action=motion.name,
    )


def _segment_distance(p0: FloatArray, p1: FloatArray, q0: FloatArray, q1: FloatArray) -> FloatArray:
    """Distance between segments [p0, p1] and [q0, q1], broadcast over leading axes."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a = np.sum(d1 * d1, -1)
    e = np.sum(d2 * d2, -1)
    f = np.sum(d2 * r, -1)
    c = np.sum(d1 * r, -1)
    b = np.sum(d1 * d2, -1)
    denom = a * e - b * b
    s = np.where(
        denom > 1e-12, np.clip((b * f - c * e) / np.where(denom > 1e-12, denom, 1), 0, 1), 0.0
    )
    t = (b * s + f) / np.where(e > 1e-12, e, 1.0)
    # clamp t, recompute s (Ericson, Real-Time Collision Detection §5.1.9)
    t_lo, t_hi = t < 0, t > 1
    t = np.clip(t, 0.0, 1.0)
    s = np.where(t_lo, np.clip(-c / a, 0, 1), np.where(t_hi, np.clip((b - c) / a, 0, 1), s))
    diff = (p0 + s[..., None] * d1) - (q0 + t[..., None] * d2)
    return np.asarray(np.linalg.norm(diff, axis=-1))


def visibility(
    markers_m: FloatArray,
    normals: FloatArray,
    caps_a_m: FloatArray,
    caps_b_m: FloatArray,
    caps_radius_m: FloatArray,
    cams: list[Camera],
    *,
    max_angle_deg: float = 80.0,
) -> BoolArray:
    """Which camera detects which marker, one frame: (K cameras, M markers) booleans."""
    m = np.asarray(check_shape(markers_m, ["M", 3], name="markers_m"), np.float64)
    out = np.zeros((len(cams), m.shape[0]), dtype=bool)
    cos_max = np.cos(np.deg2rad(max_angle_deg))
    for k, cam in enumerate(cams):
        v = cam.centre_m - m
        dist = np.linalg.norm(v, axis=-1)
        facing = np.sum(v * normals, -1) / dist > cos_max
        pc = (m - cam.centre_m) @ cam.r_cw.T
        z = pc[:, 2]
        zs = np.where(z > 1e-6, z, 1.0)
        u = cam.focal_px * pc[:, 0] / zs + IMAGE_W / 2
        w = cam.focal_px * pc[:, 1] / zs + IMAGE_H / 2
        inside = (
            (z > 0.3) & (dist < 6.0) & (u > 8) & (u < IMAGE_W - 8) & (w > 8) & (w < IMAGE_H - 8)
        )
        end = m + (v / dist[:, None]) * (MARKER_RADIUS_M + 0.005)
        dseg = _segment_distance(
            np.broadcast_to(cam.centre_m, end.shape)[:, None, :],
            end[:, None, :],
            caps_a_m[None],
            caps_b_m[None],
        )
        clear = np.all(dseg > caps_radius_m[None, :], axis=-1)
        out[k] = facing & inside & clear
    return out


def observe(
    frames: PoseFrames,
    index: int,
    cams: list[Camera],
    rng: np.random.Generator,
    *,
    realistic: bool = True,
) -> tuple[list[FloatArray], BoolArray]:
    """Per-camera lifted 3D detections of frame ``index`` (world, m) and the visibility mask.

    With ``realistic=False`` there are no misses, gross errors or ghosts (noise only).
    """
    mk = frames.markers_m[index]
    vis = visibility(
        mk,
        frames.normals[index],
        frames.caps_a_m[index],
        frames.caps_b_m[index],
        frames.caps_radius_m,
        cams,
    )
    views: list[FloatArray] = []
    for k, cam in enumerate(cams):
        sel = vis[k].copy()
        if realistic:
            sel &= rng.random(sel.shape) >= MISS_RATE
        p = mk[sel]
        ray = p - cam.centre_m
        dist = np.linalg.norm(ray, axis=-1, keepdims=True)
        d = ray / np.where(dist > 0, dist, 1.0)
        z = (p - cam.centre_m) @ cam.r_cw[2]
        lat_sigma = dist[:, 0] * LATERAL_RMS_PX / cam.focal_px
        lat = rng.normal(size=(p.shape[0], 2)) * lat_sigma[:, None]
        sz = np.hypot(z * z * SUBPIXEL_RMS_PX / (cam.focal_px * BASELINE_M), DEPTH_FLOOR_M)
        dz = rng.normal(size=p.shape[0]) * sz
        if realistic:
            gross = rng.random(p.shape[0]) < GROSS_RATE
            dz = dz + gross * rng.choice([-1.0, 1.0], p.shape[0]) * rng.uniform(
                0.03, 0.15, p.shape[0]
            )
        q = (
            p
            - MARKER_RADIUS_M * d
            + dz[:, None] * d
            + lat[:, 0:1] * cam.r_cw[0]
            + lat[:, 1:2] * cam.r_cw[1]
        )
        if realistic:
            n_ghost = int(rng.poisson(GHOSTS_PER_VIEW))
            ghosts = []
            for _ in range(n_ghost):
                if rng.random() < 0.5:
                    c = int(rng.integers(frames.caps_radius_m.shape[0]))
                    t = rng.random()
                    axis = frames.caps_a_m[index, c] + t * (
                        frames.caps_b_m[index, c] - frames.caps_a_m[index, c]
                    )
                    dirn = rng.normal(size=3)
                    dirn /= np.linalg.norm(dirn)
                    ghosts.append(axis + dirn * (frames.caps_radius_m[c] + rng.uniform(0, 0.03)))
                else:
                    ghosts.append(mk.mean(axis=0) + rng.uniform(-1.0, 1.0, 3))
            if ghosts:
                q = np.concatenate([q, np.array(ghosts)])
        views.append(q)
    return views, vis


def merge_views(views: list[FloatArray], *, radius_m: float = MERGE_RADIUS_M) -> FloatArray:
    """Fuse per-camera points (world, m): drop points outside the capture box, then merge points
    of different cameras closer than ``radius_m`` (connected components, averaged)."""
    pts = [np.asarray(v, np.float64).reshape(-1, 3) for v in views]
    cam = np.concatenate([np.full(len(v), i) for i, v in enumerate(pts)]) if pts else np.zeros(0)
    p = np.concatenate(pts) if pts else np.zeros((0, 3))
    box = np.array(CAPTURE_BOX_M)
    keep = np.all((p >= box[:, 0]) & (p <= box[:, 1]), axis=1)
    p, cam = p[keep], cam[keep]
    if p.shape[0] < 2:
        return p
    pairs = cKDTree(p).query_pairs(radius_m, output_type="ndarray")
    if pairs.size:
        pairs = pairs[cam[pairs[:, 0]] != cam[pairs[:, 1]]]
    n = p.shape[0]
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    count, label = connected_components(g, directed=False)
    sums = np.zeros((count, 3))
    np.add.at(sums, label, p)
    return sums / np.bincount(label, minlength=count)[:, None]
