"""Marker-level simulated D415 observations for training and evaluating DeMoCap.

No images are rendered: each frame's 53 true markers are "seen" by each D415 of a sampled rig
through a model of what the real measurement (:mod:`calib.markers`: IR blobs, depth read in a
disc around each blob, deprojection) gives, then fused as the replay fuses them. Every
parameter below was matched to that measurement on simulated recordings with truth (the mock
D415 renders IR and depth images; ``benchmarks/democap_simdata_match.py``: fitted on 300 rig
instants of two 30 s sessions, 4 D415s, true camera poses, checked on 599; docs/democap.md
"Training data"):

* **rig** (:func:`sample_rig`): D415s on a circle (radius 2.5 m ± 0.25, height 1.4 m ± 0.15,
  azimuths 45°, 135°, 225°, 315° ± 8°) aimed at (0, 0, 0.9 m) ± 0.1, 848×480 IR, fx 623 px
  ± 3 % (the simulated world's layout, docs/simulated-world.md). Three cameras drop one at
  random; two keep an opposing pair.
* **line of sight** (:func:`visibility`): markers are retro-reflective spheres standing
  :data:`MARKER_RADIUS_M` off the skin, so there is no facing cut: a camera sees a marker until
  a body capsule (:mod:`mocaprig.process.body.surface`, its own limb included) covers it. The
  *normalised gap* ``g`` is the clearance of the segment camera → marker centre from the
  nearest capsule surface, as an angle, in units of the marker's angular radius: ``g ≥ 1`` the
  whole sphere is in view, ``g = 0`` half of it, ``g ≤ -1`` none (a straight occluding edge).
  Measured: markers 90–135° from facing the camera are still detected 92–97 % of the time when
  the line of sight is clear.
* **detection** (:func:`observe`): in the image (:data:`IMAGE_MARGIN_PX`), 0.3–6 m, and then
  with probability ``DETECT_MAX / (1 + exp(-(g - DETECT_GAP50) / DETECT_GAP_WIDTH))``; blobs of
  two detected markers whose image discs (radius ρ = f·r/Z) nearly touch merge, with a
  probability falling with the gap between the discs (:data:`BLOB_MERGE_PX50`), into one blob
  at their mean position and the nearer depth.
* **blob centre**: the projected centre + :data:`LATERAL_RMS_PX` of noise per axis, moved
  ``OCCLUSION_SHIFT·(1 - g)·ρ`` away from the occluder when the sphere is partly hidden (the
  visible part's centroid).
* **depth** (the near-cluster median of the blob's disc): the D415 gives the depth of the
  nearest surface around the blob, not of the marker. The model takes ``Z_near``, the nearest
  capsule surface within :data:`RING_PX` of the line of sight (the marker's own limb at grazing
  angles, or another limb passing in front), and sets the depth error
  ``dZ = bias(Z_near - Z) + k·σz(Z)·N(0, 1)`` with ``bias`` the piecewise-linear
  :data:`DEPTH_BIAS_KNOTS_M` (≈ +9 mm for a marker facing the camera: the skin around it lies
  behind its centre; ≈ ``Z_near - Z`` when a limb is in front: the occlusion tail),
  ``σz = Z²·s/(f·B)`` (s = 0.08 px, B = 55 mm, the D415 model of
  ``drivers_mock/d415_render.py``) and ``k`` = :data:`DEPTH_NOISE_CLEAR` or, within 10 mm of a
  nearer surface, :data:`DEPTH_NOISE_EDGE`. :data:`GROSS_RATE` of the detections are gross
  outliers ``-(GROSS_MIN_M + Exp(GROSS_SCALE_M))`` (the marker's saturated core matched wrong
  and nearer). The point is deprojected from the blob centre at the measured depth.
* **strays**: per view a Poisson number (:data:`DOT_GHOSTS_PER_VIEW`) of projector-dot blobs
  on the suit: points on the camera-facing surface of a random capsule (weighted by its
  projected area), kept when the line of sight is clear; and per sample a Poisson number
  (:data:`REFLECTORS_MEAN`) of static reflective objects 0.5–1.2 m from the actor at 0.9–1.6 m
  height (the simulated world's clapperboard markers), seen by every camera like a marker.
* **fusion** (:func:`merge_views`): the replay's own code: each view cropped to the capture box
  (:func:`calib.markers.crop_volume`), then :func:`calib.markers.merge_views` (points closer
  than 10 mm merged, single linkage over all points; NaN rows dropped; clusters in order of
  their first point). Most markers seen by two cameras stay two points: their depth errors
  point along different rays.

Everything is deterministic for a ``numpy.random.Generator``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import torch
from scipy.spatial.transform import Rotation

from mocaprig.calib import markers as calib_markers
from mocaprig.errors import ValidationError
from mocaprig.process.body import (
    BodyShape,
    MarkerSet,
    Motion,
    capsule_template,
    democap_joints,
    forward_kinematics,
)
from mocaprig.validation import check_shape

__all__ = [
    "NOMINAL_OBSERVATION",
    "PERTURBATION_KNOBS",
    "Box",
    "Camera",
    "ObservationModel",
    "PoseFrames",
    "check_crop_box",
    "in_frustum",
    "in_frustum_torch",
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
#: D415 sub-pixel disparity RMS (px): σz = Z²·s/(f·B) per depth pixel (d415_render.py).
SUBPIXEL_RMS_PX = 0.08
#: Marker sphere radius (m); centres sit this far off the skin (process.body.markers).
MARKER_RADIUS_M = 0.007
#: A blob centre must lie this far inside the image (px).
IMAGE_MARGIN_PX = 2.0
#: Detection range (m).
RANGE_M = (0.3, 6.0)

#: Normalised gap at which half the markers are detected; measured −0.87 (logistic fit over
#: 48,100 marker views in the image with no marker within 10 px: 49 % detected at
#: g ∈ [−1, −0.75], 24 % at [−1.25, −1], 91 % at [−0.5, −0.25]).
DETECT_GAP50 = -0.87
#: Width of the detection logistic (normalised gap); measured 0.21.
DETECT_GAP_WIDTH = 0.21
#: Detection rate of a fully visible, isolated marker: measured 99.5 % (so 0.5 % random
#: misses).
DETECT_MAX = 0.995
#: Two detected markers' blobs merge with probability 1 / (1 + exp((x − BLOB_MERGE_PX50) /
#: BLOB_MERGE_WIDTH_PX)), x = the gap between their discs in the image (centre distance minus
#: both image radii ρ, px): the blob reaches ≈ 0.6 px beyond ρ (soft edge far above the
#: threshold) and 8-connectivity joins diagonal neighbours. Measured on 908 pairs of visible
#: markers (centres ≤ 10 px apart) in 200 rendered frames: one blob for 95 % of the pairs at
#: x ∈ [1, 1.5], 57 % at [1.75, 2], 33 % at [2, 2.25], 12 % at [2.25, 2.5].
BLOB_MERGE_PX50 = 1.9
BLOB_MERGE_WIDTH_PX = 0.25
#: Blob centre noise (px, per axis) of a fully visible marker: measured median 0.13 px and 90th
#: percentile 0.32 px of the centre error for g ≥ 0.9.
LATERAL_RMS_PX = 0.11
#: Centroid shift of a partly hidden marker, in units of (1 − g)·ρ: measured median shift
#: 0.23ρ at g ∈ [0.5, 0.9], 0.38ρ at [0, 0.5], 0.71ρ at [−0.5, 0], 0.91ρ at [−1, −0.5].
OCCLUSION_SHIFT = 0.5
#: Log-normal spread (σ of the log) of that shift: measured 90th/50th percentile ratio 1.4–1.9
#: per gap bin.
OCCLUSION_SHIFT_SPREAD = 0.4
#: A capsule surface this close to the line of sight (px, at the surface's depth) sets the
#: blob's depth. calib.markers reads the depth in a disc ≈ ρ + 3.6 px wide (the blob and a
#: 3 px ring) and keeps the median of its near cluster, so a surface counts once it fills much
#: of the disc: with 3 px the measured median error follows Z_near − Z within 1–9 mm over
#: −200…−20 mm, and the relation holds at 1.5–2.3, 2.3–2.6 and 2.6–3.2 m alike.
RING_PX = 3.0
#: Median depth error (m) against Z_near − Z (m), piecewise linear, clamped at the ends: the
#: measured medians of 37,200 lifted markers per Z_near − Z bin.
DEPTH_BIAS_KNOTS_M: tuple[tuple[float, float], ...] = (
    (-0.600, -0.526),
    (-0.300, -0.317),
    (-0.150, -0.169),
    (-0.100, -0.081),
    (-0.070, -0.062),
    (-0.050, -0.046),
    (-0.035, -0.030),
    (-0.020, -0.018),
    (-0.010, -0.0067),
    (0.000, -0.0026),
    (0.010, 0.0036),
    (0.020, 0.0067),
    (0.035, 0.0093),
    (0.080, 0.0090),
)
#: Depth noise around the bias in units of σz, for a marker with no nearer surface within
#: 10 mm: measured MAD 0.38–0.40σz at every distance from 1.5 to 3.2 m (σ ≈ 0.56σz: the
#: median over the disc averages pixels).
DEPTH_NOISE_CLEAR = 0.56
#: ... and with a nearer surface within 10 mm: measured MAD 0.55–0.74σz.
DEPTH_NOISE_EDGE = 0.9
#: Gross depth outliers, −(GROSS_MIN_M + Exp(GROSS_SCALE_M)): measured 0.9 % of the markers
#: with nothing nearer around them 35–300 mm too near (10th/50th/90th percentile 35, 120,
#: 290 mm; the mock D415's saturated marker cores, 15 % of them offset by σ 5 cm).
GROSS_RATE = 0.009
GROSS_MIN_M = 0.035
GROSS_SCALE_M = 0.10
#: Projector-dot blobs on the suit per view, before the line-of-sight test (the laser dots'
#: speckle peaks cross the blob threshold on bright clothing): 4.5 give 3.3 per view, as
#: measured (3.3 per view, on the body surface — median 1 mm off it — and facing the camera,
#: median cos 0.9).
DOT_GHOSTS_PER_VIEW = 4.5
#: Largest angle (deg) between a dot ghost's surface normal and the line of sight.
DOT_GHOST_MAX_ANGLE_DEG = 60.0
#: Static stray reflectors per sample (Poisson mean), 0.5–1.2 m from the actor at 0.9–1.6 m:
#: the simulated world's clapperboard holds 2 markers, measured 1.6 blobs off the body per
#: view; the model gives 1.8.
REFLECTORS_MEAN = 2.0
#: Fusion: points closer than this merge (m), as in the replay.
MERGE_RADIUS_M = 0.010
#: A world box (m): ``((x0, x1), (y0, y1), (z0, z1))``.
Box = tuple[tuple[float, float], tuple[float, float], tuple[float, float]]
#: Points outside this world box (m) are dropped before the merge (the replay's crop).
CAPTURE_BOX_M: Box = ((-2.2, 2.2), (-2.2, 2.2), (-0.1, 2.4))


def check_crop_box(box: Box) -> FloatArray:
    """The crop box as a (3, 2) array (world, m; low, high per axis).

    Raises:
        ValidationError: not three finite (low <= high) pairs.
    """
    arr = np.asarray(box, dtype=np.float64)
    if arr.shape != (3, 2) or not np.all(np.isfinite(arr)) or np.any(arr[:, 0] > arr[:, 1]):
        msg = f"crop_box_m must be ((x0, x1), (y0, y1), (z0, z1)) in m with lo <= hi, got {box!r}"
        raise ValidationError(msg)
    return arr


#: Z_near − Z below which a marker counts as next to a nearer surface (m).
_EDGE_ZNEAR_M = 0.010
_KNOTS = np.array(DEPTH_BIAS_KNOTS_M, dtype=np.float64)
#: Dot ghosts are placed this far off the skin so their own capsule does not hide them (m).
_DOT_LIFT_M = 0.002


#: The knobs of :class:`ObservationModel` that the ``perturbed`` evaluation protocol moves.
PERTURBATION_KNOBS: tuple[str, ...] = ("detection", "noise", "strays", "occlusion")


@dataclass(frozen=True, slots=True)
class ObservationModel:
    """Scales on the measured observation model, for stress tests (1.0 everywhere: the model
    training uses, :data:`NOMINAL_OBSERVATION`).

    Attributes:
        detection: scales every marker's detection probability (the occlusion logistic times
            :data:`DETECT_MAX`), clipped to [0, 1]: 0.5 loses half the detections, 1.5 finds
            partly hidden markers more often (a wholly visible one is capped at 100 %).
        noise: scales the blob-centre noise (:data:`LATERAL_RMS_PX`), the depth noise
            (:data:`DEPTH_NOISE_CLEAR`, :data:`DEPTH_NOISE_EDGE`) and the gross depth outlier
            rate (:data:`GROSS_RATE`).
        strays: scales the projector-dot blobs per view (:data:`DOT_GHOSTS_PER_VIEW`) and the
            static reflectors per sample (:data:`REFLECTORS_MEAN`).
        occlusion: scales how much a partly hidden marker suffers: the half-detection gap
            becomes ``DETECT_GAP50 * (2 - occlusion)`` (1.5: a marker must show more of itself
            to be found) and the occluded blob's centre shift :data:`OCCLUSION_SHIFT` is
            multiplied by it.

    Raises:
        ValidationError: a negative scale, or ``occlusion`` outside [0, 2).
    """

    detection: float = 1.0
    noise: float = 1.0
    strays: float = 1.0
    occlusion: float = 1.0

    def __post_init__(self) -> None:
        for name in PERTURBATION_KNOBS:
            if not float(getattr(self, name)) >= 0.0:
                msg = f"ObservationModel.{name} must be >= 0, got {getattr(self, name)!r}"
                raise ValidationError(msg)
        if self.occlusion >= 2.0:
            msg = f"ObservationModel.occlusion must be < 2, got {self.occlusion!r}"
            raise ValidationError(msg)

    @property
    def is_nominal(self) -> bool:
        """Whether every scale is 1 (the training model)."""
        return all(getattr(self, k) == 1.0 for k in PERTURBATION_KNOBS)


#: The observation model training uses.
NOMINAL_OBSERVATION = ObservationModel()


@dataclass(frozen=True, slots=True)
class Camera:
    """One D415 depth viewpoint: a pinhole of square pixels (the D415's rectified IR/depth).

    Attributes:
        centre_m: optical centre (3,), world, m.
        r_cw: rotation world -> camera (3, 3); camera +Z forward, +X right, +Y down.
        focal_px: focal length (px).
        principal_px: principal point ``(cx, cy)`` (px); the simulated rig's is the image
            centre.
        size_px: image ``(width, height)`` (px); the simulated rig's is 848 × 480.
    """

    centre_m: FloatArray
    r_cw: FloatArray
    focal_px: float
    principal_px: tuple[float, float] = (IMAGE_W / 2, IMAGE_H / 2)
    size_px: tuple[int, int] = (IMAGE_W, IMAGE_H)


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


def in_frustum(points_m: FloatArray, cams: list[Camera]) -> BoolArray:
    """(K cameras, P points) booleans: the point projects into the camera's image (with the
    :data:`IMAGE_MARGIN_PX` margin) at 0.3–6 m, whatever is in the way."""
    p = np.asarray(points_m, np.float64).reshape(1, -1, 3)
    k = len(cams)
    centre = np.array([[c.centre_m for c in cams]], np.float64).reshape(1, k, 3)
    r_cw = np.array([[c.r_cw for c in cams]], np.float64).reshape(1, k, 3, 3)
    focal = np.array([[c.focal_px for c in cams]], np.float64).reshape(1, k)
    principal = np.array([[c.principal_px for c in cams]], np.float64).reshape(1, k, 2)
    size = np.array([[c.size_px for c in cams]], np.float64).reshape(1, k, 2)
    seen = in_frustum_torch(
        *(torch.from_numpy(a) for a in (p, centre, r_cw, focal)),
        principal_px=torch.from_numpy(principal),
        size_px=torch.from_numpy(size),
    )
    return np.asarray(seen[0].numpy().T)


def in_frustum_torch(
    points_m: torch.Tensor,
    centre_m: torch.Tensor,
    r_cw: torch.Tensor,
    focal_px: torch.Tensor,
    *,
    principal_px: torch.Tensor | None = None,
    size_px: torch.Tensor | None = None,
) -> torch.Tensor:
    """:func:`in_frustum` for B problems at once, each with its own rig: points (B, M, 3),
    the cameras' centres (B, K, 3), world -> camera rotations (B, K, 3, 3), focal lengths
    (B, K), principal points (B, K, 2) and image sizes (B, K, 2) (px; None: the simulated
    rig's) -> (B, M, K) booleans. A camera of focal 0 (padding a smaller rig) sees nothing."""
    rel = points_m[:, :, None] - centre_m[:, None]  # (B, M, K, 3)
    pc = (r_cw[:, None] @ rel[..., None])[..., 0]
    z = pc[..., 2]
    zs = torch.where(z > 1e-6, z, torch.ones_like(z))
    f = focal_px[:, None]
    size = (
        torch.tensor([IMAGE_W, IMAGE_H], dtype=pc.dtype).expand(*focal_px.shape, 2)
        if size_px is None
        else size_px
    )[:, None]
    c = size / 2 if principal_px is None else principal_px[:, None]
    u = f * pc[..., 0] / zs + c[..., 0]
    v = f * pc[..., 1] / zs + c[..., 1]
    mg = IMAGE_MARGIN_PX
    ok = (f > 0) & (z > RANGE_M[0]) & ((rel * rel).sum(-1) < RANGE_M[1] ** 2)
    inside_u = (u > mg) & (u < size[..., 0] - mg)
    return ok & inside_u & (v > mg) & (v < size[..., 1] - mg)


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


@dataclass(frozen=True, slots=True)
class _Sight:
    """What one camera sees of P points (markers, reflectors, stray candidates)."""

    z: FloatArray  # (P,) camera Z (m)
    uv: FloatArray  # (P, 2) projected centres (px)
    inside: BoolArray  # (P,) in the image and range
    gap: FloatArray  # (P,) normalised gap g (large when nothing is near)
    away_cam: FloatArray  # (P, 2) image direction from the occluder to the point (unit or 0)
    znear: FloatArray  # (P,) nearest capsule surface within RING_PX, minus z (m; inf: none)


def _sight(
    points: FloatArray,
    caps_a: FloatArray,
    caps_b: FloatArray,
    caps_r: FloatArray,
    cam: Camera,
) -> _Sight:
    """Projection, normalised gap, occluder direction and Z_near of ``points`` for ``cam``.

    The closest approach of each line of sight (segment camera -> point) to each capsule axis
    (segment a -> b) is solved for all pairs at once from dot products (Ericson, Real-Time
    Collision Detection §5.1.9).
    """
    f = cam.focal_px
    (cx, cy), (w, h) = cam.principal_px, cam.size_px
    rel = points - cam.centre_m  # d1, (P, 3)
    pc = rel @ cam.r_cw.T
    z = pc[:, 2]
    zs = np.where(z > 1e-6, z, 1.0)
    uv = np.stack([f * pc[:, 0] / zs + cx, f * pc[:, 1] / zs + cy], axis=1)
    n = points.shape[0]
    dist2 = np.einsum("ij,ij->i", rel, rel)
    mg = IMAGE_MARGIN_PX
    inside = (z > RANGE_M[0]) & (dist2 < RANGE_M[1] ** 2)
    inside &= (uv[:, 0] > mg) & (uv[:, 0] < w - mg)
    inside &= (uv[:, 1] > mg) & (uv[:, 1] < h - mg)
    if caps_r.size == 0 or n == 0:
        return _Sight(z, uv, inside, np.full(n, 10.0), np.zeros((n, 2)), np.full(n, np.inf))
    ax = caps_b - caps_a  # d2, (C, 3)
    r0 = cam.centre_m - caps_a  # (C, 3)
    a = np.maximum(dist2, 1e-12)[:, None]  # (P, 1)
    e = np.einsum("ij,ij->i", ax, ax)[None]  # (1, C)
    ff = np.einsum("ij,ij->i", ax, r0)[None]  # (1, C)
    c = rel @ r0.T  # (P, C)
    b = rel @ ax.T  # (P, C)
    denom = a * e - b * b
    ok = denom > 1e-12
    s = np.where(ok, np.clip((b * ff - c * e) / np.where(ok, denom, 1.0), 0.0, 1.0), 0.0)
    t = (b * s + ff) / np.where(e > 1e-12, e, 1.0)
    t_lo, t_hi = t < 0, t > 1
    t = np.clip(t, 0.0, 1.0)
    s = np.where(t_lo, np.clip(-c / a, 0, 1), np.where(t_hi, np.clip((b - c) / a, 0, 1), s))
    r2 = np.einsum("ij,ij->i", r0, r0)[None]
    d2 = r2 + s * s * a + t * t * e + 2 * s * c - 2 * t * ff - 2 * s * t * b
    d = np.sqrt(np.maximum(d2, 0.0))
    z_seg = np.maximum(s * z[:, None], 0.05)
    rad = caps_r[None]
    gap = (d - rad) * z[:, None] / (z_seg * MARKER_RADIUS_M)
    k = np.argmin(gap, axis=1)
    rows = np.arange(n)
    # Image direction from the occluder's axis to the line of sight at the closest approach.
    sk, tk = s[rows, k, None], t[rows, k, None]
    w = (r0[k] + sk * rel - tk * ax[k]) @ cam.r_cw[:2].T
    norm = np.linalg.norm(w, axis=1, keepdims=True)
    away = np.where(norm > 1e-9, w / np.where(norm > 1e-9, norm, 1.0), 0.0)
    # Nearest capsule surface within RING_PX of the line of sight (its camera Z).
    ring = RING_PX * z_seg / f
    lat = np.maximum(d - ring, 0.0)
    z_axis = -(r0 @ cam.r_cw[2])[None] + t * (ax @ cam.r_cw[2])[None]
    cand = np.where(
        d - rad < ring, z_axis - np.sqrt(np.maximum(rad * rad - lat * lat, 0.0)), np.inf
    )
    return _Sight(z, uv, inside, gap[rows, k], away, cand.min(axis=1) - z)


def visibility(
    markers_m: FloatArray,
    normals: FloatArray,
    caps_a_m: FloatArray,
    caps_b_m: FloatArray,
    caps_radius_m: FloatArray,
    cams: list[Camera],
    *,
    max_angle_deg: float = 180.0,
) -> BoolArray:
    """Which camera sees which marker, one frame: (K cameras, M markers) booleans.

    A marker is visible when its centre projects into the image (:data:`IMAGE_MARGIN_PX`),
    0.3–6 m away, and its normalised gap (module doc) is at least :data:`DETECT_GAP50`, where
    half of such markers are detected. ``max_angle_deg`` adds a facing cut (angle between the
    skin normal and the line of sight); the default keeps none, as the measurement shows.
    """
    m = np.asarray(check_shape(markers_m, ["M", 3], name="markers_m"), np.float64)
    nrm = np.asarray(check_shape(normals, [m.shape[0], 3], name="normals"), np.float64)
    a = np.asarray(caps_a_m, np.float64).reshape(-1, 3)
    b = np.asarray(caps_b_m, np.float64).reshape(-1, 3)
    r = np.asarray(caps_radius_m, np.float64).reshape(-1)
    out = np.zeros((len(cams), m.shape[0]), dtype=bool)
    cos_max = np.cos(np.deg2rad(max_angle_deg))
    for k, cam in enumerate(cams):
        sight = _sight(m, a, b, r, cam)
        v = cam.centre_m - m
        facing = np.sum(v * nrm, -1) / np.linalg.norm(v, axis=-1) >= cos_max - 1e-12
        out[k] = sight.inside & (sight.gap >= DETECT_GAP50) & facing
    return out


def _depth_bias(znear: FloatArray) -> FloatArray:
    x = np.where(np.isfinite(znear), znear, _KNOTS[-1, 0])
    return np.asarray(np.interp(x, _KNOTS[:, 0], _KNOTS[:, 1]))


def _sigma_z(z: FloatArray, focal_px: float) -> FloatArray:
    return np.asarray(z * z * SUBPIXEL_RMS_PX / (focal_px * BASELINE_M))


def _merge_blobs(
    uv: FloatArray, z: FloatArray, focal_px: float, rng: np.random.Generator
) -> npt.NDArray[np.int64]:
    """Blob label of each detection: detections whose blobs run together share a label."""
    n = uv.shape[0]
    lab = np.arange(n, dtype=np.int64)
    if n < 2:
        return lab
    rho = focal_px * MARKER_RADIUS_M / z
    gap = np.linalg.norm(uv[:, None] - uv[None], axis=-1) - rho[:, None] - rho[None]
    ii, jj = np.nonzero(np.triu(gap < BLOB_MERGE_PX50 + 6.0 * BLOB_MERGE_WIDTH_PX, 1))
    if ii.size == 0:
        return lab
    x = (gap[ii, jj] - BLOB_MERGE_PX50) / BLOB_MERGE_WIDTH_PX
    merge = rng.random(ii.size) < 1.0 / (1.0 + np.exp(x))
    for i, j in zip(ii[merge].tolist(), jj[merge].tolist(), strict=True):  # a handful
        lab[lab == lab[j]] = lab[i]
    return np.unique(lab, return_inverse=True)[1].astype(np.int64)


def _cross(u: FloatArray, v: FloatArray) -> FloatArray:
    """Row-wise cross product of (N, 3) arrays (np.cross is slow for small arrays)."""
    return np.stack(
        [
            u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1],
            u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2],
            u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0],
        ],
        axis=1,
    )


def _lift(uv: FloatArray, z: FloatArray, cam: Camera) -> FloatArray:
    f, (cx, cy) = cam.focal_px, cam.principal_px
    pc = np.stack([(uv[:, 0] - cx) / f * z, (uv[:, 1] - cy) / f * z, z], axis=1)
    return np.asarray(pc @ cam.r_cw + cam.centre_m)


def _dot_candidates(
    rng: np.random.Generator,
    caps_a: FloatArray,
    caps_b: FloatArray,
    caps_r: FloatArray,
    cam: Camera,
    mean: float = DOT_GHOSTS_PER_VIEW,
) -> FloatArray:
    """Candidate projector-dot blobs on the suit facing ``cam`` (world, m), before the
    line-of-sight test; Poisson(``mean``) of them."""
    n = int(rng.poisson(mean))
    if n == 0 or caps_r.size == 0:
        return np.zeros((0, 3))
    axis = caps_b - caps_a
    length = np.linalg.norm(axis, axis=1)
    to_cam = cam.centre_m - 0.5 * (caps_a + caps_b)
    dist = np.linalg.norm(to_cam, axis=1)
    sin_ax = np.linalg.norm(_cross(axis, to_cam), axis=1) / np.maximum(length * dist, 1e-9)
    weight = (2.0 * caps_r * length * sin_ax + np.pi * caps_r**2) / dist**2
    c = rng.choice(caps_r.size, size=n, p=weight / weight.sum())
    q = caps_a[c] + rng.random(n)[:, None] * axis[c]
    u_ax = axis[c] / np.maximum(length[c], 1e-9)[:, None]
    v = cam.centre_m - q
    e = v - np.sum(v * u_ax, axis=1, keepdims=True) * u_ax
    e /= np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-9)
    phi = np.deg2rad(rng.uniform(-DOT_GHOST_MAX_ANGLE_DEG, DOT_GHOST_MAX_ANGLE_DEG, n))
    e = np.cos(phi)[:, None] * e + np.sin(phi)[:, None] * _cross(u_ax, e)
    return np.asarray(q + (caps_r[c, None] + _DOT_LIFT_M) * e)


def _reflectors(
    rng: np.random.Generator, root_m: FloatArray, mean: float = REFLECTORS_MEAN
) -> FloatArray:
    """Static stray reflectors around the actor (world, m), Poisson(``mean``) of them."""
    n = int(rng.poisson(mean))
    az = rng.uniform(0.0, 2.0 * np.pi, n)
    rad = rng.uniform(0.5, 1.2, n)
    return np.stack(
        [root_m[0] + rad * np.cos(az), root_m[1] + rad * np.sin(az), rng.uniform(0.9, 1.6, n)],
        axis=1,
    )


def observe(
    frames: PoseFrames,
    index: int,
    cams: list[Camera],
    rng: np.random.Generator,
    *,
    realistic: bool = True,
    model: ObservationModel = NOMINAL_OBSERVATION,
) -> tuple[list[FloatArray], BoolArray]:
    """Per-camera lifted 3D detections of frame ``index`` (world, m) and which markers each
    camera detected ((K, 53) booleans).

    With ``realistic=False`` detection is deterministic (:func:`visibility`), there are no
    gross errors, blob merges, strays or reflectors, and the blob centre has no noise; the
    depth bias and noise stay. ``model`` scales the measured model (stress tests; the default
    is the model training uses, and draws the same random numbers as before it existed).
    """
    gap50 = DETECT_GAP50 * (2.0 - model.occlusion)
    noise = model.noise
    mk = frames.markers_m[index]
    n_mk = mk.shape[0]
    caps_a = frames.caps_a_m[index]
    caps_b = frames.caps_b_m[index]
    caps_r = frames.caps_radius_m
    shared = mk
    if realistic:
        refl = _reflectors(rng, frames.joints_m[index, 0], REFLECTORS_MEAN * model.strays)
        shared = np.concatenate([mk, refl])
    n_sh = shared.shape[0]
    views: list[FloatArray] = []
    detected = np.zeros((len(cams), n_mk), dtype=bool)
    for k, cam in enumerate(cams):
        pts = shared
        if realistic:
            dots_mean = DOT_GHOSTS_PER_VIEW * model.strays
            pts = np.concatenate(
                [shared, _dot_candidates(rng, caps_a, caps_b, caps_r, cam, dots_mean)]
            )
        sight = _sight(pts, caps_a, caps_b, caps_r, cam)
        if realistic:
            with np.errstate(over="ignore"):  # far behind an occluder: exp -> inf, p -> 0
                p = DETECT_MAX / (1.0 + np.exp(-(sight.gap - gap50) / DETECT_GAP_WIDTH))
            if model.detection != 1.0:
                p = np.clip(p * model.detection, 0.0, 1.0)
            det = sight.inside & (rng.random(pts.shape[0]) < p)
            # Dot blobs are on the surface: seen where their line of sight is clear.
            det[n_sh:] = sight.inside[n_sh:] & (sight.gap[n_sh:] > 0.0)
        else:
            det = sight.inside & (sight.gap >= gap50)
        detected[k] = det[:n_mk]
        idx = np.flatnonzero(det[:n_sh])
        z = sight.z[idx]
        rho = cam.focal_px * MARKER_RADIUS_M / z
        hidden = 1.0 - np.clip(sight.gap[idx], -1.5, 1.0)
        shift = OCCLUSION_SHIFT * model.occlusion * hidden * rho
        if realistic:
            shift = shift * np.exp(OCCLUSION_SHIFT_SPREAD * rng.normal(size=shift.size))
        uv = sight.uv[idx] + shift[:, None] * sight.away_cam[idx]
        znear = sight.znear[idx]
        sigma = np.where(znear < _EDGE_ZNEAR_M, DEPTH_NOISE_EDGE, DEPTH_NOISE_CLEAR) * noise
        dz = _depth_bias(znear) + rng.normal(size=z.size) * sigma * _sigma_z(z, cam.focal_px)
        if realistic:
            uv = uv + rng.normal(size=uv.shape) * (LATERAL_RMS_PX * noise)
            gross = rng.random(z.size) < GROSS_RATE * noise
            dz = dz - gross * (GROSS_MIN_M + rng.exponential(GROSS_SCALE_M, z.size))
        zm = z + dz
        if realistic and idx.size > 1:
            lab = _merge_blobs(uv, z, cam.focal_px, rng)
            if lab.max() + 1 < lab.size:
                count = np.bincount(lab)
                uv = np.stack([np.bincount(lab, uv[:, j]) / count for j in (0, 1)], axis=1)
                zmin = np.full(count.size, np.inf)
                np.minimum.at(zmin, lab, zm)
                zm = zmin
        q = _lift(uv, zm, cam)
        if realistic:
            dots = n_sh + np.flatnonzero(det[n_sh:])
            zd = sight.z[dots]
            zd_noise = rng.normal(size=zd.size) * (DEPTH_NOISE_CLEAR * noise)
            zd = zd + zd_noise * _sigma_z(zd, cam.focal_px)
            q = np.concatenate([q, _lift(sight.uv[dots], zd, cam)])
        views.append(q)
    return views, detected


def merge_views(views: list[FloatArray], *, radius_m: float = MERGE_RADIUS_M) -> FloatArray:
    """Fuse per-camera points (world, m) exactly as the replay and the live pipeline do: each
    view cropped to :data:`CAPTURE_BOX_M` (:func:`calib.markers.crop_volume`: non-finite rows
    and rows outside the box dropped), then :func:`calib.markers.merge_views` (single linkage
    at ``radius_m`` over all points of all views, clusters averaged, in order of their first
    point). One fusion for training and inference."""
    box = np.asarray(CAPTURE_BOX_M, dtype=np.float64)
    cropped = [
        calib_markers.crop_volume(np.asarray(v, np.float64).reshape(-1, 3), box[:, 0], box[:, 1])
        for v in views
    ]
    return calib_markers.merge_views(cropped, radius_m=radius_m)
