"""EventCap stage B: the hybrid batch optimisation of a batch of poses (paper Eqs. 3–8).

One batch spans two APS frames: tracking frames ``f = 0..N`` (N = 40 at 25 fps and 1 kHz).
The unknowns are the poses ``S_0..S_N`` (33-vectors of :mod:`process.body.skeleton`) and the
auxiliary translation ``t′`` that places the root-relative 3D detections in the world. The
energy is::

    E = λ_cor·E_cor + λ_2D·E_2D + λ_3D·E_3D + λ_temp·E_temp      (defaults 50, 200, 1, 80)

* ``E_cor`` (px²): per correspondence ``τ·ρ(‖π(x_h(S_i, S_j)) − p_j‖)``: the body surface
  point seen under the tracked pixel ``p_i`` at frame ``i`` (a point ``q`` in the frame of
  joint ``s``, from the caller's rasteriser), carried to frame ``j = i ± 1``. With the
  ``"relative"`` model (default; paper Eq. 5, where ``v_{i,h}`` depends on ``S_i``) the point
  stays where it was seen, ``X = T_s(S_i⁰)·q`` at the association poses ``S⁰``, and moves
  rigidly with its segment from ``S_i`` to ``S_j``: ``x = T_s(S_j)·T_s(S_i)⁻¹·X``. With
  ``"fixed"`` it rides on the segment, ``x = T_s(S_j)·q``, and only ``S_j`` moves it.
* ``E_2D`` (px²): at detection frames, ``c_l·ρ(‖π(J_l(S_f)) − P2D_l‖)`` over 19 keypoints.
* ``E_3D`` (mm²): at detection frames, ``w_l·‖J_l(S_f) − (P3D_l + t′)‖²`` over the 15 body
  joints (the paper's N_J), P3D root-relative, rotated from camera into world axes.
* ``E_temp`` (mm²): ``φ(l)·‖J_l(S_i) − J_l(S_{i+1})‖²`` over consecutive frames and the 15 body
  joints, ``φ`` from :func:`temporal_weights`.

``ρ`` is the identity on squared norms, or Huber (``e²`` below ``k``, ``2k·e − k²`` above).

Frames and units. World: Z up, metres (poses, ``t′``); camera: OpenCV axes of
``T_world_cam`` (:mod:`calib.camera_model`); pixels: OpenCV, (0, 0) the centre of the top-left
pixel; 3D detections in mm in *camera* axes, root-relative (as VNect gives them).

Solver: damped Gauss–Newton (Levenberg–Marquardt) in torch float64, with IRLS weights for
Huber. Every residual depends on one or two poses (E_cor, E_2D, E_temp) or one pose and
``t′`` (E_3D), so ``JᵀJ`` is assembled from 33×33 frame blocks (block-tridiagonal plus the
``t′`` coupling) without ever forming the full Jacobian. The blocks are analytic: a point on
segment ``s`` moves with each angle as ``a × (x − p_j)`` for every Euler axis ``a`` of every
joint ``j`` above it (axes and pivots from the posed skeleton), and with the root increment
as ``δω × (x − t) + δt``; the projection's 2×3 derivative is that of
:func:`calib.camera_model.project_camera_torch` (tests check all blocks against autograd).
Steps solve ``(JᵀJ + μ·diag(JᵀJ)) δ = −Jᵀr`` by Cholesky with Nielsen's damping update; the
root rotation is updated by a world-frame axis-angle increment (``R ← exp(δω)·R``, no
singularity at π), the 27 angles are projected onto ``DOF_LIMITS_RAD`` after each step, and a
step is kept only when the (robust) energy drops, so it never increases.

Initialisation is root first (:func:`fit_frame`): each end frame is fitted to its detections
alone, first the root (6 DoF and ``t′``) with the angles held, then everything; the frames in
between are interpolated (:func:`interpolate_poses`: slerp for the root rotation, linear for
the rest). The same per-frame fit, linearly upsampled, is the ``*_linear`` baseline
(:func:`linear_baseline`); run at every tracking frame it is the ``*_all`` baseline.

E_cor associations come from the caller (the rasteriser), made at the initial poses; an
optional ``reassociate`` callback refreshes them between rounds, ICP-style.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
import scipy.linalg
import torch
from scipy.spatial.transform import Rotation, Slerp

from mocaprig.calib.camera_model import project_camera_torch
from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body.jacobian import point_jacobian, pose_geometry
from mocaprig.process.body.kinematics import (
    EVENTCAP_KEYPOINT_JOINTS,
    EVENTCAP_KEYPOINTS,
    eventcap_keypoints,
    eventcap_keypoints_torch,
    forward_kinematics,
    forward_kinematics_torch,
    rotvec_to_matrix,
    skew_torch,
)
from mocaprig.process.body.shape import BodyShape, rest_offsets
from mocaprig.process.body.skeleton import (
    DOF_LIMITS_RAD,
    JOINTS,
    NUM_DOF,
    PARENTS,
    POSE_DIM,
    ROOT_DIM,
)
from mocaprig.process.eventcap.camera import EventCamera
from mocaprig.validation import check_finite, check_positive, check_range, check_shape

__all__ = [
    "NUM_BODY_KEYPOINTS",
    "NUM_KEYPOINTS",
    "BatchFitOptions",
    "BatchFitResult",
    "CorrespondenceModel",
    "Correspondences",
    "EnergyTerms",
    "FrameDetections",
    "FrameFitResult",
    "RobustLoss",
    "TranslationMode",
    "fit_batch",
    "fit_frame",
    "interpolate_poses",
    "linear_baseline",
    "temporal_weights",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: Keypoints of E_2D: 15 body joints then 4 face points (``EVENTCAP_KEYPOINTS``).
NUM_KEYPOINTS = len(EVENTCAP_KEYPOINTS)
#: Body joints of E_3D and E_temp (the paper's N_J): the first 15 keypoints.
NUM_BODY_KEYPOINTS = len(EVENTCAP_KEYPOINT_JOINTS)

RobustLoss = Literal["none", "huber"]
#: ``"relative"``: a correspondence point stays where it was seen at frame ``i`` relative to
#: its segment at ``S_i``, so E_cor ties ``S_j`` to ``S_i`` (paper Eq. 5: ``v_{i,h}`` depends
#: on ``S_i``); ``"fixed"``: the point is fixed in the segment frame and only ``S_j`` moves it.
CorrespondenceModel = Literal["relative", "fixed"]
#: ``"shared"``: one ``t′`` for all 3D detections of a batch (paper Eq. 7);
#: ``"per_detection"``: one per detection frame (the root may travel within a batch).
TranslationMode = Literal["shared", "per_detection"]

_MM_PER_M = 1000.0


# --- records --------------------------------------------------------------------------------


def _frozen(
    x: npt.ArrayLike, pattern: Sequence[int | str], name: str, dtype: type[np.generic]
) -> npt.NDArray[Any]:
    """A read-only copy of ``x`` after shape and finiteness checks."""
    arr: npt.NDArray[Any] = np.array(check_shape(x, pattern, name=name), dtype=dtype, copy=True)
    check_finite(arr, name=name)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, slots=True, eq=False)
class Correspondences:
    """E_cor correspondences already associated to the body surface (one row per pair).

    Row ``c`` says: the surface point ``local_m[c]``, fixed in the frame of joint
    ``segment[c]`` (found under the tracked pixel at frame ``frame_i[c]``), should project at
    frame ``frame_j[c]`` (``i ± 1``) onto ``target_px[c]``, with weight ``weight[c]`` (τ).

    Attributes:
        frame_i: ``(C,)`` frame of the association (0..N), int.
        frame_j: ``(C,)`` frame whose pose is evaluated (0..N), int.
        segment: ``(C,)`` joint index (0..25) whose frame the point rides on.
        local_m: ``(C, 3)`` point in that joint's frame, metres.
        target_px: ``(C, 2)`` tracked pixel at frame ``j``.
        weight: ``(C,)`` τ ≥ 0 (0 for a pixel off the body).

    Raises:
        ValidationError: shapes that disagree, non-finite values, negative weights, segments
            outside the skeleton or ``frame_i == frame_j``.
    """

    frame_i: I64 = field(repr=False)
    frame_j: I64 = field(repr=False)
    segment: I64 = field(repr=False)
    local_m: F64 = field(repr=False)
    target_px: F64 = field(repr=False)
    weight: F64 = field(repr=False)

    def __post_init__(self) -> None:
        fi = _frozen(self.frame_i, ["C"], "Correspondences.frame_i", np.int64)
        c = fi.shape[0]
        fj = _frozen(self.frame_j, [c], "Correspondences.frame_j", np.int64)
        seg = _frozen(self.segment, [c], "Correspondences.segment", np.int64)
        loc = _frozen(self.local_m, [c, 3], "Correspondences.local_m", np.float64)
        tgt = _frozen(self.target_px, [c, 2], "Correspondences.target_px", np.float64)
        w = _frozen(self.weight, [c], "Correspondences.weight", np.float64)
        if np.any(w < 0):
            msg = "Correspondences.weight has negative entries; τ must be >= 0 (0 drops a row)"
            raise ValidationError(msg)
        if np.any((seg < 0) | (seg >= len(JOINTS))):
            msg = f"Correspondences.segment must be joint indices in [0, {len(JOINTS)})"
            raise ValidationError(msg)
        if np.any(fi == fj):
            msg = "Correspondences: frame_i == frame_j in some rows; E_cor pairs distinct frames"
            raise ValidationError(msg)
        for name, arr in (
            ("frame_i", fi),
            ("frame_j", fj),
            ("segment", seg),
            ("local_m", loc),
            ("target_px", tgt),
            ("weight", w),
        ):
            object.__setattr__(self, name, arr)

    @property
    def count(self) -> int:
        """Number of rows ``C``."""
        return int(self.frame_i.shape[0])

    @classmethod
    def empty(cls) -> Correspondences:
        """No correspondences (a detections-only fit)."""
        return cls(
            frame_i=np.zeros(0, np.int64),
            frame_j=np.zeros(0, np.int64),
            segment=np.zeros(0, np.int64),
            local_m=np.zeros((0, 3)),
            target_px=np.zeros((0, 2)),
            weight=np.zeros(0),
        )


def _default_confidence3d() -> F64:
    w = np.zeros(NUM_KEYPOINTS)
    w[:NUM_BODY_KEYPOINTS] = 1.0
    return w


@dataclass(frozen=True, slots=True, eq=False)
class FrameDetections:
    """2D (and optionally root-relative 3D) keypoint detections at one tracking frame.

    Attributes:
        frame: tracking frame index (0..N) of the detections.
        keypoints2d_px: ``(19, 2)`` pixels in ``EVENTCAP_KEYPOINTS`` order.
        confidence: ``(19,)`` weights ≥ 0 of the 2D residuals (0 = missing keypoint).
        keypoints3d_mm: ``(19, 3)`` root-relative positions in *camera* axes (OpenCV: X
            right, Y down, Z forward), mm, or ``None``. Only the 15 body joints enter E_3D.
        confidence3d: ``(19,)`` weights ≥ 0 of the 3D residuals; default 1 for the body
            joints, 0 for the face points.

    Raises:
        ValidationError: wrong shapes, non-finite values, negative weights or frame.
    """

    frame: int
    keypoints2d_px: F64 = field(repr=False)
    confidence: F64 = field(repr=False)
    keypoints3d_mm: F64 | None = field(default=None, repr=False)
    confidence3d: F64 = field(default_factory=_default_confidence3d, repr=False)

    def __post_init__(self) -> None:
        if int(self.frame) < 0:
            msg = f"FrameDetections.frame must be >= 0, got {self.frame}"
            raise ValidationError(msg)
        object.__setattr__(self, "frame", int(self.frame))
        kp = _frozen(self.keypoints2d_px, [NUM_KEYPOINTS, 2], "keypoints2d_px", np.float64)
        conf = _frozen(self.confidence, [NUM_KEYPOINTS], "confidence", np.float64)
        conf3 = _frozen(self.confidence3d, [NUM_KEYPOINTS], "confidence3d", np.float64)
        if np.any(conf < 0) or np.any(conf3 < 0):
            msg = "FrameDetections confidences must be >= 0 (0 marks a missing keypoint)"
            raise ValidationError(msg)
        object.__setattr__(self, "keypoints2d_px", kp)
        object.__setattr__(self, "confidence", conf)
        object.__setattr__(self, "confidence3d", conf3)
        if self.keypoints3d_mm is not None:
            p3 = _frozen(self.keypoints3d_mm, [NUM_KEYPOINTS, 3], "keypoints3d_mm", np.float64)
            object.__setattr__(self, "keypoints3d_mm", p3)


@dataclass(frozen=True, slots=True)
class BatchFitOptions:
    """Weights and solver settings (paper weights by default; units px and mm).

    Attributes:
        lambda_cor, lambda_2d, lambda_3d, lambda_temp: term weights (λ_cor is the paper's
            λ_adj).
        robust: ``"huber"`` (default) or ``"none"`` on E_cor and E_2D.
        huber_cor_px, huber_2d_px: Huber thresholds (px).
        correspondence_model: how E_cor depends on the poses (:data:`CorrespondenceModel`).
        phi_observed: φ of the joints the events observe (:func:`temporal_weights`). The
            paper's rule gives 0; a little smoothing (0.1) keeps noisy tracks from letting
            limbs drift in depth, which monocular flow barely sees (measured on simulated
            batches with 0.3 px tracks: PA-MPJPE -3 to -27 % against 0).
        translation_3d: one ``t′`` per batch (paper) or one per detection frame.
        max_iterations: LM iterations (accepted and rejected steps).
        rtol: stop when an accepted step lowers the energy by less than ``rtol`` of it.
        mu_init: initial damping μ (relative to ``diag(JᵀJ)``).
    """

    lambda_cor: float = 50.0
    lambda_2d: float = 200.0
    lambda_3d: float = 1.0
    lambda_temp: float = 80.0
    robust: RobustLoss = "huber"
    huber_cor_px: float = 2.0
    huber_2d_px: float = 5.0
    correspondence_model: CorrespondenceModel = "relative"
    phi_observed: float = 0.1
    translation_3d: TranslationMode = "shared"
    max_iterations: int = 30
    rtol: float = 1e-4
    mu_init: float = 1e-3

    def __post_init__(self) -> None:
        for name in ("lambda_cor", "lambda_2d", "lambda_3d", "lambda_temp"):
            value = float(getattr(self, name))
            if not np.isfinite(value) or value < 0:
                msg = f"BatchFitOptions.{name} must be a finite number >= 0, got {value!r}"
                raise ValidationError(msg)
        check_range(float(self.phi_observed), 0.0, 1.0, name="BatchFitOptions.phi_observed")
        for name in ("huber_cor_px", "huber_2d_px", "rtol", "mu_init"):
            check_positive(float(getattr(self, name)), name=f"BatchFitOptions.{name}")
        if self.robust not in ("none", "huber"):
            msg = f"BatchFitOptions.robust must be 'none' or 'huber', got {self.robust!r}"
            raise ValidationError(msg)
        if self.correspondence_model not in ("relative", "fixed"):
            msg = (
                "BatchFitOptions.correspondence_model must be 'relative' or 'fixed', "
                f"got {self.correspondence_model!r}"
            )
            raise ValidationError(msg)
        if self.translation_3d not in ("shared", "per_detection"):
            msg = (
                "BatchFitOptions.translation_3d must be 'shared' or 'per_detection', "
                f"got {self.translation_3d!r}"
            )
            raise ValidationError(msg)
        if int(self.max_iterations) < 0:
            msg = f"BatchFitOptions.max_iterations must be >= 0, got {self.max_iterations}"
            raise ValidationError(msg)


@dataclass(frozen=True, slots=True)
class EnergyTerms:
    """The λ-weighted (and robustified) energy terms: E_cor, E_2D (px²), E_3D, E_temp (mm²)."""

    cor: float
    d2: float
    d3: float
    temp: float

    @property
    def total(self) -> float:
        """Sum of the four terms."""
        return self.cor + self.d2 + self.d3 + self.temp


@dataclass(frozen=True, slots=True, eq=False)
class BatchFitResult:
    """Outcome of :func:`fit_batch`.

    Attributes:
        poses: ``(N+1, 33)`` fitted poses (world frame, m and rad), angles within limits.
        translation_3d_m: ``(T, 3)`` ``t′`` (world, m): one row (shared) or one per 3D
            detection frame in the order given; ``(0, 3)`` without 3D detections.
        initial_energy, final_energy: the terms at the initial and the fitted state.
        energy_history: total energy after every accepted step, starting with the initial.
        iterations: LM iterations run (accepted and rejected).
        converged: stopped on ``rtol`` (not on ``max_iterations`` or a stalled damping).
        seconds: wall time of the solve (initialisation included).
    """

    poses: F64 = field(repr=False)
    translation_3d_m: F64 = field(repr=False)
    initial_energy: EnergyTerms
    final_energy: EnergyTerms
    energy_history: tuple[float, ...] = field(repr=False)
    iterations: int
    converged: bool
    seconds: float


@dataclass(frozen=True, slots=True, eq=False)
class FrameFitResult:
    """Outcome of :func:`fit_frame`: ``pose`` (33,), ``translation_3d_m`` (3,) or ``None``."""

    pose: F64 = field(repr=False)
    translation_3d_m: F64 | None = field(repr=False)
    energy: EnergyTerms
    iterations: int
    seconds: float


# --- φ(l) -----------------------------------------------------------------------------------


def _keypoint_segments() -> tuple[tuple[int, ...], ...]:
    """Per body keypoint, the segments (joint frames) whose bones meet at its joint."""
    out = []
    for j in EVENTCAP_KEYPOINT_JOINTS:
        segs = [s for s in range(len(JOINTS)) if s == j or (PARENTS[j] >= 0 and s == PARENTS[j])]
        out.append(tuple(segs))
    return tuple(out)


_KEYPOINT_SEGMENTS = _keypoint_segments()


def temporal_weights(
    correspondences: Correspondences, *, min_points: int = 1, observed: float = 0.0
) -> F64:
    """φ(l) of E_temp for the 15 body keypoints: 1 where the part has no event correspondence.

    Rule: keypoint ``l`` (joint ``J``) counts as observed by the events when at least
    ``min_points`` correspondences with τ > 0 lie on a segment riding on ``J``'s own frame or
    on its parent's frame: the two bones that meet at the joint, whose motion moves it (a
    forearm point observes both the elbow and the wrist). Observed keypoints get φ =
    ``observed`` (the paper: 0), the others φ = 1 (static parts stay still).

    Returns:
        ``(15,)`` weights in {``observed``, 1}.

    Raises:
        ValidationError: ``observed`` outside [0, 1].
    """
    check_range(float(observed), 0.0, 1.0, name="observed")
    seg = correspondences.segment[correspondences.weight > 0]
    counts = np.bincount(seg, minlength=len(JOINTS))
    phi = np.ones(NUM_BODY_KEYPOINTS)
    for l_idx, segs in enumerate(_KEYPOINT_SEGMENTS):
        if counts[list(segs)].sum() >= min_points:
            phi[l_idx] = observed
    return phi


# --- interpolation --------------------------------------------------------------------------


def interpolate_poses(pose_start: npt.ArrayLike, pose_end: npt.ArrayLike, *, n: int) -> F64:
    """Poses ``(n+1, 33)`` from ``pose_start`` (frame 0) to ``pose_end`` (frame ``n``).

    The root rotation is slerped (scipy ``Slerp``), the root translation and the 27 angles are
    interpolated linearly (they stay within the limits when both ends are).

    Raises:
        ValidationError: wrong shapes, non-finite values or ``n < 1``.
    """
    if int(n) < 1:
        msg = f"interpolate_poses needs n >= 1 frames between the ends, got {n}"
        raise ValidationError(msg)
    a = np.asarray(check_finite(check_shape(pose_start, [POSE_DIM], name="pose_start")), float)
    b = np.asarray(check_finite(check_shape(pose_end, [POSE_DIM], name="pose_end")), float)
    s = np.linspace(0.0, 1.0, int(n) + 1)
    out = (1.0 - s)[:, None] * a + s[:, None] * b
    slerp = Slerp([0.0, 1.0], Rotation.from_rotvec(np.stack([a[:3], b[:3]])))
    out[:, :3] = slerp(s).as_rotvec()
    out[0], out[-1] = a, b  # exact ends (as_rotvec may pick the other 2π representative)
    return np.asarray(out, dtype=np.float64)


# --- the problem ----------------------------------------------------------------------------


@dataclass(slots=True)
class _State:
    """Solver state: root rotation matrices, root translation, angles, ``t′`` (all tensors)."""

    root_r: torch.Tensor  # (F, 3, 3)
    root_t: torch.Tensor  # (F, 3) m
    angles: torch.Tensor  # (F, 27) rad
    tprime: torch.Tensor  # (T, 3) m

    def poses(self) -> F64:
        rv = Rotation.from_matrix(self.root_r.numpy()).as_rotvec()
        out = np.concatenate([rv, self.root_t.numpy(), self.angles.numpy()], axis=1)
        return np.asarray(out, dtype=np.float64)


def _state_from_poses(poses: F64, tprime: F64) -> _State:
    return _State(
        root_r=torch.from_numpy(rotvec_to_matrix(poses[:, :3])),
        root_t=torch.from_numpy(poses[:, 3:6].copy()),
        angles=torch.from_numpy(poses[:, ROOT_DIM:].copy()),
        tprime=torch.from_numpy(tprime.copy()),
    )


def _axis_angle_exp(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) of axis-angle vectors (..., 3), smooth at 0."""
    theta2 = (w * w).sum(-1)
    small = theta2 < 1e-12
    theta = torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / (theta * theta))
    k = skew_torch(w)
    eye = torch.eye(3, dtype=w.dtype).expand(k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


# Segment of each keypoint: the 15 body joints ride on their own frames, the face on the head.
_KEYPOINT_SEGMENT = torch.tensor(
    [*EVENTCAP_KEYPOINT_JOINTS, *([JOINTS.index("Head")] * (NUM_KEYPOINTS - NUM_BODY_KEYPOINTS))]
)


def _projection_jacobian(
    pc: torch.Tensor, K: torch.Tensor, dist: torch.Tensor | None
) -> torch.Tensor:
    """d(u, v)/d(camera point) (..., 2, 3) of :func:`calib.camera_model.project_camera_torch`."""
    x, y, z = pc[..., 0], pc[..., 1], pc[..., 2]
    a, b = x / z, y / z
    if dist is None:
        daa, dab = torch.ones_like(a), torch.zeros_like(a)
        dba, dbb = dab, daa
    else:
        k1, k2, p1, p2, k3 = (dist[i] for i in range(5))
        r2 = a * a + b * b
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dr = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        daa = radial + 2.0 * a * a * dr + 2.0 * p1 * b + 6.0 * p2 * a
        dab = 2.0 * a * b * dr + 2.0 * p1 * a + 2.0 * p2 * b
        dba = dab
        dbb = radial + 2.0 * b * b * dr + 6.0 * p1 * b + 2.0 * p2 * a
    # (u, v) from the distorted (a, b): u = fx·a + s·b + cx, v = fy·b + cy.
    fx, sk, fy = K[0, 0], K[0, 1], K[1, 1]
    du_da, du_db = fx * daa + sk * dba, fx * dab + sk * dbb
    dv_da, dv_db = fy * dba, fy * dbb
    iz = 1.0 / z
    # (a, b) from the point: da = (dx − a·dz)/z, db = (dy − b·dz)/z.
    row_u = torch.stack([du_da * iz, du_db * iz, -(du_da * a + du_db * b) * iz], dim=-1)
    row_v = torch.stack([dv_da * iz, dv_db * iz, -(dv_da * a + dv_db * b) * iz], dim=-1)
    return torch.stack([row_u, row_v], dim=-2)


@dataclass(frozen=True, slots=True)
class _Posed:
    """The model at one state: skeleton, keypoints and projected points."""

    pos: torch.Tensor  # (F, 26, 3) world joint positions, m
    rot: torch.Tensor  # (F, 26, 3, 3) world joint rotations
    root_r: torch.Tensor  # (F, 3, 3)
    root_t: torch.Tensor  # (F, 3) m
    angles: torch.Tensor  # (F, 27) rad
    kp: torch.Tensor  # (F, 19, 3) keypoints, m
    cor_x: torch.Tensor  # (C, 3) correspondence points, world, m
    cor_px: torch.Tensor  # (C, 2)
    kp_det: torch.Tensor  # (D, 19, 3) keypoints at the detection frames, m
    det_px: torch.Tensor  # (D, 19, 2)


class _Problem:
    """Tensors of one fit: the model, the data, the weights and the free-parameter mask."""

    def __init__(
        self,
        *,
        num_frames: int,
        correspondences: Correspondences,
        detections: Sequence[FrameDetections],
        camera: EventCamera,
        shape: BodyShape,
        options: BatchFitOptions,
        phi: F64,
        association_poses: F64,
    ) -> None:
        t = torch.from_numpy
        self.F = num_frames
        self.shape = shape
        self.opt = options
        self.offsets = t(rest_offsets(shape))
        self.K = t(np.array(camera.K))
        self.dist = t(np.array(camera.distortion)) if np.any(camera.distortion) else None
        r_wc = camera.R_world_cam
        self.r_cw = t(r_wc.T.copy())
        self.cam_centre = t(np.array(camera.T_world_cam[:3, 3]))
        self.relative = options.correspondence_model == "relative"
        keep = correspondences.weight > 0
        fi, fj = correspondences.frame_i[keep], correspondences.frame_j[keep]
        # Rows sorted by frame pair (j, i), padded per pair: (pairs, M) row indices, or C (a
        # zero row appended) past a pair's end, so each pair's blocks are one batched product.
        key = fj * num_frames + fi
        order = np.argsort(key, kind="stable")
        pairs, counts = np.unique(key, return_counts=True)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        width = int(counts.max()) if counts.size else 0
        slot = np.arange(width)[None, :]
        pad = np.where(slot < counts[:, None], starts[:, None] + slot, int(counts.sum()))
        self.cor_pad = t(pad.astype(np.int64))
        self.pair_j = t((pairs // num_frames).astype(np.int64))
        self.pair_i = t((pairs % num_frames).astype(np.int64))
        self.cor_frame = t(fj[order])
        self.cor_frame_i = t(fi[order])
        self.cor_seg = t(correspondences.segment[keep][order])
        self.cor_local = t(correspondences.local_m[keep][order])
        self.cor_target = t(correspondences.target_px[keep][order])
        self.cor_tau = t(correspondences.weight[keep][order])
        # Where each point was seen: on its segment at the association poses, frame i (m).
        kin = forward_kinematics(association_poses[fi[order]], shape)
        seg = correspondences.segment[keep][order]
        rows = np.arange(seg.size)
        self.cor_anchor = t(
            np.einsum("cij,cj->ci", kin.rotations[rows, seg], self.cor_local.numpy())
            + kin.positions_m[rows, seg]
        )
        dets = list(detections)
        self.det_frame = t(np.array([d.frame for d in dets], dtype=np.int64))
        self.det_obs = t(
            np.stack([d.keypoints2d_px for d in dets]) if dets else np.zeros((0, 19, 2))
        )
        self.det_conf = t(np.stack([d.confidence for d in dets]) if dets else np.zeros((0, 19)))
        with3d = [k for k, d in enumerate(dets) if d.keypoints3d_mm is not None]
        self.d3_det = t(np.array(with3d, dtype=np.int64))
        self.d3_frame = self.det_frame[self.d3_det]
        p3 = [np.asarray(dets[k].keypoints3d_mm)[:NUM_BODY_KEYPOINTS] @ r_wc.T for k in with3d]
        self.d3_world_mm = t(np.stack(p3) if p3 else np.zeros((0, NUM_BODY_KEYPOINTS, 3)))
        w3 = [dets[k].confidence3d[:NUM_BODY_KEYPOINTS] for k in with3d]
        self.d3_w = t(np.stack(w3) if w3 else np.zeros((0, NUM_BODY_KEYPOINTS)))
        if not with3d:
            self.T = 0
        elif options.translation_3d == "shared":
            self.T = 1
        else:
            self.T = len(with3d)
        self.d3_t = torch.zeros(len(with3d), dtype=torch.int64)
        if options.translation_3d == "per_detection":
            self.d3_t = torch.arange(len(with3d))
        self.phi = t(np.asarray(phi, dtype=np.float64))
        self.lo = t(DOF_LIMITS_RAD[:, 0].copy())
        self.hi = t(DOF_LIMITS_RAD[:, 1].copy())
        self.n = POSE_DIM * num_frames + 3 * self.T
        self.free = torch.ones(self.n, dtype=torch.bool)
        # Frames further apart than this share no term (E_temp: neighbours; E_cor: its pairs):
        # the frames' part of JᵀWJ is a band of that many blocks either side of the diagonal.
        reach = int(np.abs(fi - fj).max()) if fi.size else 0
        self.frame_reach = max(reach, 1 if num_frames > 1 else 0)

    # -- model evaluation ---------------------------------------------------------------------

    def quantities(self, s: _State, delta: torch.Tensor) -> _Posed:
        """Everything the residuals need at ``s`` moved by ``delta`` (F, 33) (or (33,), the
        same step for every frame): root rotation ``exp(δω)·R``, root translation ``t + δt``,
        angles ``θ + δθ`` (unclipped)."""
        delta = delta.expand(self.F, POSE_DIM)
        root_r = _axis_angle_exp(delta[:, 0:3]) @ s.root_r
        root_t = s.root_t + delta[:, 3:6]
        angles = s.angles + delta[:, ROOT_DIM:]
        # Chain at the identity root, then one rigid map: the root rotation enters as a
        # matrix, so no axis-angle is differentiated through.
        local = torch.cat([torch.zeros_like(delta[:, :ROOT_DIM]), angles], dim=1)
        pos_b, rot_b = forward_kinematics_torch(local, self.offsets)
        pos = (root_r[:, None] @ pos_b[..., None])[..., 0] + root_t[:, None]
        rot = root_r[:, None] @ rot_b
        kp = eventcap_keypoints_torch(pos, rot, self.shape)
        f, sg = self.cor_frame, self.cor_seg
        if self.relative:
            # The anchor in the segment frame at the current S_i, carried to S_j.
            fi = self.cor_frame_i
            local = ((self.cor_anchor - pos[fi, sg])[..., None, :] @ rot[fi, sg])[
                ..., 0, :
            ]  # R_iᵀ (X − p_i)
        else:
            local = self.cor_local
        cor_x = (rot[f, sg] @ local[..., None])[..., 0] + pos[f, sg]
        kp_det = kp[self.det_frame]
        return _Posed(
            pos=pos,
            rot=rot,
            root_r=root_r,
            root_t=root_t,
            angles=angles,
            kp=kp,
            cor_x=cor_x,
            cor_px=self._project(cor_x),
            kp_det=kp_det,
            det_px=self._project(kp_det),
        )

    def _to_camera(self, x_world: torch.Tensor) -> torch.Tensor:
        return (x_world - self.cam_centre) @ self.r_cw.T

    def _project(self, x_world: torch.Tensor) -> torch.Tensor:
        # No depth test: the solver needs finite residuals everywhere.
        return project_camera_torch(self._to_camera(x_world), self.K, self.dist, min_depth_m=None)

    def raw_residuals(
        self, s: _State, q: _Posed, dt: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Unweighted residuals: cor (C, 2) px, 2D (D, 19, 2) px, 3D (D3, 15, 3) mm, temp mm."""
        r_cor = q.cor_px - self.cor_target
        r_2d = q.det_px - self.det_obs
        body = q.kp[:, :NUM_BODY_KEYPOINTS] * _MM_PER_M
        tp = (s.tprime + dt)[self.d3_t] * _MM_PER_M
        r_3d = body[self.d3_frame] - self.d3_world_mm - tp[:, None]
        r_temp = body[:-1] - body[1:]
        return r_cor, r_2d, r_3d, r_temp

    def _robust(self, e2: torch.Tensor, k: float) -> tuple[torch.Tensor, torch.Tensor]:
        """ρ(e²) and the IRLS weight ρ′(e²) of squared norms."""
        if self.opt.robust == "none":
            return e2, torch.ones_like(e2)
        e = torch.sqrt(e2)
        inlier = e <= k
        rho = torch.where(inlier, e2, 2.0 * k * e - k * k)
        w = torch.where(inlier, torch.ones_like(e), k / torch.where(inlier, torch.ones_like(e), e))
        return rho, w

    def weights(
        self, r: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]
    ) -> tuple[EnergyTerms, tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]:
        """The energy terms and the per-residual-vector weights (λ·τ·ρ′, ...) at ``r``."""
        r_cor, r_2d, r_3d, r_temp = r
        o = self.opt
        rho_c, w_c = self._robust((r_cor * r_cor).sum(-1), o.huber_cor_px)
        rho_2, w_2 = self._robust((r_2d * r_2d).sum(-1), o.huber_2d_px)
        e3 = (r_3d * r_3d).sum(-1)
        et = (r_temp * r_temp).sum(-1)
        terms = EnergyTerms(
            cor=float(o.lambda_cor * (self.cor_tau * rho_c).sum()),
            d2=float(o.lambda_2d * (self.det_conf * rho_2).sum()),
            d3=float(o.lambda_3d * (self.d3_w * e3).sum()),
            temp=float(o.lambda_temp * (self.phi * et).sum()),
        )
        w = (
            o.lambda_cor * self.cor_tau * w_c,
            o.lambda_2d * self.det_conf * w_2,
            o.lambda_3d * self.d3_w,
            (o.lambda_temp * self.phi).expand(r_temp.shape[:-1]),
        )
        return terms, w

    def energy(self, s: _State) -> EnergyTerms:
        zero = torch.zeros(POSE_DIM, dtype=torch.float64)
        q = self.quantities(s, zero)
        return self.weights(self.raw_residuals(s, q, torch.zeros_like(s.tprime)))[0]

    # -- normal equations ---------------------------------------------------------------------

    def normal_equations(self, s: _State) -> tuple[torch.Tensor, torch.Tensor, EnergyTerms]:
        """``JᵀWJ`` (n, n), ``JᵀWr`` (n,) and the energy at ``s``, assembled from frame blocks.

        One forward-mode pass differentiates every per-frame quantity with respect to the
        same 33-vector increment applied to all frames; since each quantity depends on its own
        frame's pose only, that yields all per-frame Jacobian blocks at once.
        """
        zero = torch.zeros(POSE_DIM, dtype=torch.float64)
        q = self.quantities(s, zero)
        r = self.raw_residuals(s, q, torch.zeros_like(s.tprime))
        terms, w = self.weights(r)
        r_cor, r_2d, r_3d, r_temp = r
        w_cor, w_2d, w_3d, w_temp = w
        geo = pose_geometry(q.pos, q.rot, q.root_r, q.root_t, q.angles)
        frames = torch.arange(self.F)[:, None].expand(self.F, NUM_KEYPOINTS)
        d_kp = point_jacobian(geo, frames, _KEYPOINT_SEGMENT.expand_as(frames), q.kp)
        j_cor = point_jacobian(geo, self.cor_frame, self.cor_seg, q.cor_x)
        d_cor = self._pixel_jacobian(q.cor_x, j_cor)
        d_cor_i = None
        if self.relative:
            # Moving S_i moves the anchor in the segment frame by −R_iᵀ·(its attached motion),
            # which S_j carries as R_j·R_iᵀ: dx_j/dS_i = −R_j·R_iᵀ·J_point(i, anchor).
            fi, sg = self.cor_frame_i, self.cor_seg
            j_anchor = point_jacobian(geo, fi, sg, self.cor_anchor)
            carry = q.rot[self.cor_frame, sg] @ q.rot[fi, sg].transpose(-1, -2)
            d_cor_i = -self._pixel_jacobian(q.cor_x, carry @ j_anchor)
        d_det = self._pixel_jacobian(q.kp_det, d_kp[self.det_frame])
        F, P = self.F, POSE_DIM
        blocks = torch.zeros(F, F, P, P, dtype=torch.float64)  # [row frame, column frame]
        g_frames = torch.zeros(F, P, dtype=torch.float64)
        diag = torch.arange(F)
        diag_blocks = torch.zeros(F, P, P, dtype=torch.float64)
        cor_off = None
        if self.cor_pad.shape[1]:
            # E_cor: rows gathered per frame pair (zero-padded), one batched product each.
            def padded(x: torch.Tensor) -> torch.Tensor:
                """Rows (C, 2, k) -> (pairs, 2M, k), zero past each pair's end."""
                zero_row = torch.zeros(1, *x.shape[1:], dtype=torch.float64)
                out = torch.cat([x, zero_row])[self.cor_pad]
                return out.reshape(len(self.pair_j), -1, x.shape[-1])

            wsq = torch.sqrt(w_cor)[:, None, None]
            jj = padded(d_cor * wsq)
            rp = padded(r_cor[..., None] * wsq)
            diag_blocks.index_add_(0, self.pair_j, jj.transpose(1, 2) @ jj)
            g_frames.index_add_(0, self.pair_j, (jj.transpose(1, 2) @ rp)[..., 0])
            if d_cor_i is not None:
                ji = padded(d_cor_i * wsq)
                diag_blocks.index_add_(0, self.pair_i, ji.transpose(1, 2) @ ji)
                g_frames.index_add_(0, self.pair_i, (ji.transpose(1, 2) @ rp)[..., 0])
                cor_off = ji.transpose(1, 2) @ jj  # block (i, j)
        # E_2D: one detection frame each.
        jw2 = d_det * w_2d[..., None, None]
        diag_blocks.index_add_(0, self.det_frame, torch.einsum("dlip,dliq->dpq", jw2, d_det))
        g_frames.index_add_(0, self.det_frame, torch.einsum("dlip,dli->dp", jw2, r_2d))
        # E_temp: J = A_i (frame i) and -A_{i+1}; mm per unit of the increment.
        a_kp = d_kp[:, :NUM_BODY_KEYPOINTS] * _MM_PER_M  # (F, 15, 3, P)
        if F > 1:
            wa = a_kp[:-1] * w_temp[..., None, None]
            wb = a_kp[1:] * w_temp[..., None, None]
            diag_blocks[:-1] += torch.einsum("flip,fliq->fpq", wa, a_kp[:-1])
            diag_blocks[1:] += torch.einsum("flip,fliq->fpq", wb, a_kp[1:])
            off = -torch.einsum("flip,fliq->fpq", wa, a_kp[1:])
            blocks[diag[:-1], diag[1:]] = off
            blocks[diag[1:], diag[:-1]] = off.transpose(1, 2)
            g_frames[:-1] += torch.einsum("flip,fli->fp", wa, r_temp)
            g_frames[1:] -= torch.einsum("flip,fli->fp", wb, r_temp)
        if cor_off is not None:
            blocks.index_put_((self.pair_i, self.pair_j), cor_off, accumulate=True)
            blocks.index_put_((self.pair_j, self.pair_i), cor_off.transpose(1, 2), accumulate=True)
        # E_3D: frame block, t′ block (-1000·I per joint) and their coupling.
        h = torch.zeros(self.n, self.n, dtype=torch.float64)
        g = torch.zeros(self.n, dtype=torch.float64)
        if self.T:
            a3 = a_kp[self.d3_frame]  # (D3, 15, 3, P)
            w3a = a3 * w_3d[..., None, None]
            diag_blocks.index_add_(0, self.d3_frame, torch.einsum("dlip,dliq->dpq", w3a, a3))
            g_frames.index_add_(0, self.d3_frame, torch.einsum("dlip,dli->dp", w3a, r_3d))
            base = F * P
            for k in range(int(self.d3_det.shape[0])):
                f = int(self.d3_frame[k])
                ti = base + 3 * int(self.d3_t[k])
                wsum = float(w_3d[k].sum())
                cross = -_MM_PER_M * w3a[k].sum(0)  # (3, P): Σ_l w_l A_lᵀ(-1000 I), transposed
                h[ti : ti + 3, ti : ti + 3] += torch.eye(3, dtype=torch.float64) * (
                    wsum * _MM_PER_M**2
                )
                h[ti : ti + 3, P * f : P * f + P] += cross
                h[P * f : P * f + P, ti : ti + 3] += cross.T
                g[ti : ti + 3] += -_MM_PER_M * (w_3d[k][:, None] * r_3d[k]).sum(0)
        blocks[diag, diag] += diag_blocks
        h[: F * P, : F * P] += blocks.transpose(1, 2).reshape(F * P, F * P)
        g[: F * P] += g_frames.reshape(-1)
        return h, g, terms

    def _pixel_jacobian(self, x_world: torch.Tensor, j_world: torch.Tensor) -> torch.Tensor:
        """Pixel Jacobians (..., 2, P) from world-point Jacobians (..., 3, P)."""
        j_proj = _projection_jacobian(self._to_camera(x_world), self.K, self.dist)
        return (j_proj @ self.r_cw) @ j_world

    # -- steps ----------------------------------------------------------------------------

    def solve(self, a: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor | None:
        """``a⁻¹·rhs`` for a damped ``JᵀWJ`` (n, n) of this problem, or None when ``a`` is not
        positive definite.

        A batch's frames are coupled to their neighbours only (:attr:`frame_reach` blocks)
        and to the few ``t′``: its frame part is solved as a band (LAPACK ``pbtrf``, cost
        ∝ n·band² instead of n³) and the ``t′`` through their Schur complement. Problems
        of a few frames are solved densely.
        """
        m = POSE_DIM * self.F
        band = (self.frame_reach + 1) * POSE_DIM - 1
        if 3 * band >= m:
            chol, info = torch.linalg.cholesky_ex(a)
            if int(info) != 0:
                return None
            return torch.cholesky_solve(rhs[:, None], chol)[:, 0]
        a_np, b_np = a.numpy(), rhs.numpy()
        frames = a_np[:m, :m]
        lower = np.zeros((band + 1, m))
        for k in range(band + 1):
            lower[k, : m - k] = np.diagonal(frames, -k)
        try:
            factor = scipy.linalg.cholesky_banded(lower, lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            return None
        coupling = a_np[:m, m:]
        sol = scipy.linalg.cho_solve_banded(
            (factor, True), np.column_stack([b_np[:m], coupling]), check_finite=False
        )
        x = sol[:, 0]
        if a_np.shape[0] == m:
            return torch.from_numpy(x)
        schur = a_np[m:, m:] - coupling.T @ sol[:, 1:]
        try:
            y = scipy.linalg.cho_solve(
                scipy.linalg.cho_factor(schur, lower=True, check_finite=False),
                b_np[m:] - coupling.T @ x,
                check_finite=False,
            )
        except np.linalg.LinAlgError:
            return None
        return torch.from_numpy(np.concatenate([x - sol[:, 1:] @ y, y]))

    def apply(self, s: _State, step: torch.Tensor) -> _State:
        """The state after ``step`` (n,), angles projected onto the limits."""
        fp = step[: self.F * POSE_DIM].reshape(self.F, POSE_DIM)
        return _State(
            root_r=_axis_angle_exp(fp[:, 0:3]) @ s.root_r,
            root_t=s.root_t + fp[:, 3:6],
            angles=torch.clamp(s.angles + fp[:, ROOT_DIM:], self.lo, self.hi),
            tprime=s.tprime + step[self.F * POSE_DIM :].reshape(self.T, 3),
        )


@dataclass(frozen=True, slots=True)
class _LmOutcome:
    state: _State
    initial: EnergyTerms
    final: EnergyTerms
    history: tuple[float, ...]
    iterations: int
    converged: bool


def _marquardt_system(
    h: torch.Tensor, g: torch.Tensor, free: torch.Tensor, mu: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The damped system of one LM step: ``h + μ·diag(d)`` with ``d`` Marquardt's scaling
    (``h``'s diagonal floored at 1e-9 of its largest, 0 on held parameters), held rows and
    columns made identity, and ``-g`` (0 where held, so δ = 0 there). ``h`` (..., m, m),
    ``g`` and ``free`` (..., m), ``mu`` (...) -> ``(a, rhs, d)``."""
    d = torch.diagonal(h, dim1=-2, dim2=-1)
    d = torch.maximum(d, 1e-9 * d.amax(dim=-1, keepdim=True).clamp(min=1e-300))
    d = torch.where(free, d, torch.zeros_like(d))
    a = h + torch.diag_embed(mu[..., None] * d)
    fixed = ~free
    if bool(fixed.any()):
        eye = torch.eye(h.shape[-1], dtype=h.dtype)
        a = torch.where(fixed[..., :, None] | fixed[..., None, :], eye, a)
    return a, torch.where(free, -g, torch.zeros_like(g)), d


def _levenberg_marquardt(
    prob: _Problem, state: _State, *, max_iterations: int, rtol: float, mu_init: float
) -> _LmOutcome:
    """Damped Gauss–Newton with Marquardt scaling and Nielsen's damping update.

    Angles are projected onto their limits after each step; a step is kept only when the
    energy drops, so the energy never increases.
    """
    h, g, terms = prob.normal_equations(state)
    if not np.isfinite(terms.total):
        msg = (
            f"batch fit: the initial energy is not finite ({terms}); a keypoint or surface "
            "point lies in the camera's centre plane: check the camera pose and initial poses"
        )
        raise ProcessingError(msg)
    initial = terms
    history = [terms.total]
    mu, nu = mu_init, 2.0
    free = prob.free
    converged = False
    it = 0
    while it < max_iterations:
        it += 1
        a, rhs, d = _marquardt_system(h, g, free, torch.tensor(mu, dtype=torch.float64))
        step = prob.solve(a, rhs)
        if step is None:  # not positive definite: damp more
            mu, nu = mu * nu, nu * 2.0
            continue
        trial = prob.apply(state, step)
        trial_terms = prob.energy(trial)
        actual = terms.total - trial_terms.total
        if actual > 0.0:
            # Gain ratio against the Gauss–Newton model of Σ w·r² (cost 2δᵀg + δᵀHδ).
            predicted = float(-(step @ g) + mu * (step * d * step).sum())
            rho = actual / max(predicted, 1e-300)
            mu, nu = mu * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), 2.0
            state = trial
            h, g, terms = prob.normal_equations(state)
            history.append(terms.total)
            if actual < rtol * history[-2]:
                converged = True
                break
        else:
            mu, nu = mu * nu, nu * 2.0
            if mu > 1e12:
                break
    _log.debug(
        "LM: %d iterations, energy %.6g -> %.6g (%s)",
        it,
        initial.total,
        terms.total,
        "converged" if converged else "stopped",
    )
    return _LmOutcome(state, initial, terms, tuple(history), it, converged)


def _frame_energies(prob: _Problem, s: _State) -> torch.Tensor:
    """E_2D and E_3D of each frame (F, 2) at ``s``, for a problem of independent frames (no
    E_cor pairs, no E_temp weight): then the energy is their sum, frame by frame."""
    zero = torch.zeros(POSE_DIM, dtype=torch.float64)
    _, r_2d, r_3d, _ = prob.raw_residuals(s, prob.quantities(s, zero), torch.zeros_like(s.tprime))
    o = prob.opt
    rho_2, _ = prob._robust((r_2d * r_2d).sum(-1), o.huber_2d_px)
    out = torch.zeros(prob.F, 2, dtype=torch.float64)
    out[:, 0].index_add_(0, prob.det_frame, o.lambda_2d * (prob.det_conf * rho_2).sum(-1))
    e3 = o.lambda_3d * (prob.d3_w * (r_3d * r_3d).sum(-1)).sum(-1)
    out[:, 1].index_add_(0, prob.d3_frame, e3)
    return out


def _levenberg_marquardt_frames(
    prob: _Problem, state: _State, *, max_iterations: int, rtol: float, mu_init: float
) -> list[_LmOutcome]:
    """:func:`_levenberg_marquardt` run on each frame of a problem of independent frames at
    once: one model evaluation per iteration for all of them, each frame with its own
    damping, steps, acceptance and stop. Frame ``k``'s outcome is what the single-frame
    problem (its pose block and its ``t′``, ``translation_3d="per_detection"``) would give,
    to float rounding; its state is that single-frame problem's.

    Raises:
        ValidationError: the problem couples its frames (E_cor pairs, an E_temp weight, or a
            ``t′`` shared by several frames).
        ProcessingError: a frame's initial energy is not finite.
    """
    f_count, p = prob.F, POSE_DIM
    if prob.cor_pad.shape[1] or bool((prob.phi != 0).any()) or prob.T not in (0, f_count):
        msg = "frames fitted at once must be independent: no E_cor, no E_temp, one t′ each"
        raise ValidationError(msg)
    # Parameter indices of each frame's own problem: its pose block, then its t′.
    idx = torch.arange(f_count)[:, None] * p + torch.arange(p)
    if prob.T:
        t_idx = f_count * p + 3 * torch.arange(f_count)[:, None] + torch.arange(3)
        idx = torch.cat([idx, t_idx], dim=1)
    rows, cols = idx[:, :, None], idx[:, None, :]
    free = prob.free[idx]  # (F, m)

    def model(s: _State) -> tuple[torch.Tensor, torch.Tensor]:
        h_full, g_full, _ = prob.normal_equations(s)
        return h_full[rows, cols], g_full[idx]

    h, g = model(state)
    energies = _frame_energies(prob, state)
    totals = energies.sum(1)
    if not bool(torch.isfinite(totals).all()):
        msg = (
            f"batch fit: the initial energy is not finite ({energies.tolist()}); a keypoint or "
            "surface point lies in the camera's centre plane: check the camera pose and "
            "initial poses"
        )
        raise ProcessingError(msg)
    initial = energies.clone()
    history = [[float(t)] for t in totals]
    mu = torch.full((f_count,), float(mu_init), dtype=torch.float64)
    nu = torch.full((f_count,), 2.0, dtype=torch.float64)
    active = torch.ones(f_count, dtype=torch.bool)
    converged = torch.zeros(f_count, dtype=torch.bool)
    its = torch.zeros(f_count, dtype=torch.int64)
    while bool(active.any()):
        its += active.long()
        a, rhs, d = _marquardt_system(h, g, free, mu)
        chol, info = torch.linalg.cholesky_ex(a)
        ok = (info == 0) & active
        failed = (info != 0) & active
        mu, nu = torch.where(failed, mu * nu, mu), torch.where(failed, nu * 2.0, nu)
        step = torch.zeros_like(g)
        if bool(ok.any()):
            step[ok] = torch.cholesky_solve(rhs[ok, :, None], chol[ok])[..., 0]
            full = torch.zeros(prob.n, dtype=torch.float64)
            full[idx] = step
            trial = prob.apply(state, full)
            trial_energies = _frame_energies(prob, trial)
            actual = totals - trial_energies.sum(1)
            accept = ok & (actual > 0.0)
            reject = ok & ~accept
            if bool(accept.any()):
                predicted = -(step * g).sum(1) + mu * (step * d * step).sum(1)
                rho = actual / predicted.clamp(min=1e-300)
                scale = torch.clamp(1.0 - (2.0 * rho - 1.0) ** 3, min=1.0 / 3.0)
                mu = torch.where(accept, mu * scale, mu)
                nu = torch.where(accept, torch.full_like(nu, 2.0), nu)
                state = _select_frames(accept, trial, state)
                h_new, g_new = model(state)
                h = torch.where(accept[:, None, None], h_new, h)
                g = torch.where(accept[:, None], g_new, g)
                energies = torch.where(accept[:, None], trial_energies, energies)
                totals = energies.sum(1)
                for k in torch.nonzero(accept).flatten().tolist():
                    history[k].append(float(totals[k]))
                    if float(actual[k]) < rtol * history[k][-2]:
                        converged[k] = True
            mu, nu = torch.where(reject, mu * nu, mu), torch.where(reject, nu * 2.0, nu)
            active &= ~converged & ~(reject & (mu > 1e12))
        active &= its < max_iterations
    out = []
    for k in range(f_count):
        one = _State(
            root_r=state.root_r[k : k + 1],
            root_t=state.root_t[k : k + 1],
            angles=state.angles[k : k + 1],
            tprime=state.tprime[k : k + 1] if prob.T else state.tprime,
        )

        def terms(e: torch.Tensor) -> EnergyTerms:
            return EnergyTerms(cor=0.0, d2=float(e[0]), d3=float(e[1]), temp=0.0)

        out.append(
            _LmOutcome(
                one,
                terms(initial[k]),
                terms(energies[k]),
                tuple(history[k]),
                int(its[k]),
                bool(converged[k]),
            )
        )
    return out


def _select_frames(take: torch.Tensor, a: _State, b: _State) -> _State:
    """Frames (and their ``t′``, one per frame) of ``a`` where ``take`` (F,), else of ``b``."""
    tp = torch.where(take[:, None], a.tprime, b.tprime) if a.tprime.shape[0] else b.tprime
    return _State(
        root_r=torch.where(take[:, None, None], a.root_r, b.root_r),
        root_t=torch.where(take[:, None], a.root_t, b.root_t),
        angles=torch.where(take[:, None], a.angles, b.angles),
        tprime=tp,
    )


# --- per-frame fit (root first) -------------------------------------------------------------

# Torso keypoints that fix the root's orientation: pelvis, neck, shoulders, hips.
_TORSO = tuple(EVENTCAP_KEYPOINTS.index(n) for n in (
    "pelvis", "neck", "right_shoulder", "left_shoulder", "right_hip", "left_hip",
))  # fmt: skip


def _root_candidates(
    det: FrameDetections, camera: EventCamera, shape: BodyShape, angles: F64
) -> list[F64]:
    """Initial root guesses (poses (33,)) for a frame: upright at four headings, and the
    rotation aligning the 3D torso (when given), each placed on the pelvis ray at the depth
    that matches the torso's pixel size."""
    pose0 = np.concatenate([np.zeros(ROOT_DIM), angles])
    kp_body = eventcap_keypoints(forward_kinematics(pose0, shape), shape)  # root at origin
    conf = det.confidence[list(_TORSO)]
    obs = det.keypoints2d_px[list(_TORSO)]
    ok = conf > 0
    r_wc = camera.R_world_cam
    centre = camera.T_world_cam[:3, 3]
    fx = float(camera.K[0, 0])
    # Depth from size: pixel spread of the torso vs its metric spread.
    if ok.sum() >= 2:
        px = obs[ok] - obs[ok].mean(0)
        m = kp_body[list(_TORSO)][ok]
        m = m - m.mean(0)
        depth = fx * float(np.sqrt((m**2).sum() / max((px**2).sum(), 1e-9)))
        target_px = obs[ok].mean(0)
        body_offset = kp_body[list(_TORSO)][ok].mean(0)
    else:
        depth, target_px, body_offset = 3.0, np.asarray(camera.K[:2, 2]), np.zeros(3)
    ray_cam = np.linalg.solve(camera.K, np.array([target_px[0], target_px[1], 1.0]))
    torso_centre = centre + r_wc @ (ray_cam * depth)
    rotations: list[F64] = []
    to_cam = centre - torso_centre
    heading = np.arctan2(to_cam[1], to_cam[0]) - np.pi / 2  # +Y (forward) toward the camera
    for k in range(4):
        rotations.append(Rotation.from_euler("z", heading + k * np.pi / 2).as_matrix())
    if det.keypoints3d_mm is not None:
        w = det.confidence3d[list(_TORSO)]
        if np.count_nonzero(w) >= 3:
            src = kp_body[list(_TORSO)] - kp_body[list(_TORSO)][w > 0].mean(0)
            dst = det.keypoints3d_mm[list(_TORSO)] @ r_wc.T / _MM_PER_M
            dst = dst - dst[w > 0].mean(0)
            rot, _ = Rotation.align_vectors(dst[w > 0], src[w > 0], weights=w[w > 0])
            rotations.append(rot.as_matrix())
    out = []
    for r in rotations:
        pose = pose0.copy()
        pose[:3] = Rotation.from_matrix(r).as_rotvec()
        pose[3:6] = torso_centre - r @ body_offset
        out.append(pose)
    return out


def _closed_form_tprime(prob: _Problem, poses: F64) -> F64:
    """The ``t′`` minimising E_3D for fixed poses (weighted mean offset), ``(T, 3)`` m."""
    if prob.T == 0:
        return np.zeros((0, 3))
    kp = eventcap_keypoints(forward_kinematics(poses, prob.shape), prob.shape)
    body = kp[:, :NUM_BODY_KEYPOINTS] * _MM_PER_M
    frames = prob.d3_frame.numpy()
    diff = body[frames] - prob.d3_world_mm.numpy()  # (D3, 15, 3)
    w = prob.d3_w.numpy()
    idx = prob.d3_t.numpy()
    out = np.zeros((prob.T, 3))
    for t in range(prob.T):
        sel = idx == t
        ws = w[sel][..., None]
        out[t] = (ws * diff[sel]).sum((0, 1)) / max(float(ws.sum()), 1e-12) / _MM_PER_M
    return out


def _fit_single(
    det: FrameDetections,
    camera: EventCamera,
    shape: BodyShape,
    options: BatchFitOptions,
    initial_pose: F64 | None,
) -> tuple[_State, _Problem, EnergyTerms, int]:
    local = FrameDetections(
        frame=0,
        keypoints2d_px=det.keypoints2d_px,
        confidence=det.confidence,
        keypoints3d_mm=det.keypoints3d_mm,
        confidence3d=det.confidence3d,
    )
    prob = _Problem(
        num_frames=1,
        correspondences=Correspondences.empty(),
        detections=[local],
        camera=camera,
        shape=shape,
        options=options,
        phi=np.zeros(NUM_BODY_KEYPOINTS),
        association_poses=np.zeros((1, POSE_DIM)),
    )
    angles = np.zeros(NUM_DOF) if initial_pose is None else initial_pose[ROOT_DIM:]
    angles = np.clip(angles, DOF_LIMITS_RAD[:, 0], DOF_LIMITS_RAD[:, 1])
    candidates = _root_candidates(local, camera, shape, angles)
    if initial_pose is not None:
        candidates.insert(0, np.asarray(initial_pose, dtype=np.float64))
    # Stage 1: the root (and t′) with the angles held, from every candidate; keep the best.
    # The candidates are independent problems, solved at once as the frames of one problem
    # (each its own t′): the model's cost is in its many small steps, not in its size.
    poses = np.array(candidates, dtype=np.float64)
    poses[:, ROOT_DIM:] = np.clip(poses[:, ROOT_DIM:], DOF_LIMITS_RAD[:, 0], DOF_LIMITS_RAD[:, 1])
    stage1 = _Problem(
        num_frames=len(poses),
        correspondences=Correspondences.empty(),
        detections=[replace(local, frame=k) for k in range(len(poses))],
        camera=camera,
        shape=shape,
        options=replace(options, translation_3d="per_detection"),
        phi=np.zeros(NUM_BODY_KEYPOINTS),
        association_poses=np.zeros((len(poses), POSE_DIM)),
    )
    root_free = torch.zeros(stage1.F, POSE_DIM, dtype=torch.bool)
    root_free[:, :ROOT_DIM] = True
    stage1.free = torch.cat([root_free.reshape(-1), torch.ones(3 * stage1.T, dtype=torch.bool)])
    fits = _levenberg_marquardt_frames(
        stage1,
        _state_from_poses(poses, _closed_form_tprime(stage1, poses)),
        max_iterations=options.max_iterations,
        rtol=options.rtol,
        mu_init=options.mu_init,
    )
    best = min(fits, key=lambda f: f.final.total)
    iterations = sum(f.iterations for f in fits)
    # Stage 2: everything.
    prob.free = torch.ones(prob.n, dtype=torch.bool)
    out = _levenberg_marquardt(
        prob,
        best.state,
        max_iterations=options.max_iterations,
        rtol=options.rtol,
        mu_init=options.mu_init,
    )
    return out.state, prob, out.final, iterations + out.iterations


def _check_detection_energy(det: FrameDetections) -> None:
    if np.count_nonzero(det.confidence) < 4:
        msg = (
            f"FrameDetections at frame {det.frame} has {np.count_nonzero(det.confidence)} "
            "keypoints with confidence > 0; a per-frame fit needs at least 4"
        )
        raise ValidationError(msg)


def fit_frame(
    detections: FrameDetections,
    camera: EventCamera,
    shape: BodyShape,
    *,
    initial_pose: npt.ArrayLike | None = None,
    options: BatchFitOptions | None = None,
) -> FrameFitResult:
    """Fit one pose to one frame's detections (E_2D + E_3D), root first, within the limits.

    Stage 1 fits the root (6 DoF) and ``t′`` with the angles held (at ``initial_pose``'s or
    0), from several initial roots (upright at four headings, the 3D torso alignment, and
    ``initial_pose`` if given), keeping the best; stage 2 frees all 33 DoF.

    Args:
        detections: the frame's keypoints (its ``frame`` index is ignored).
        camera: the camera.
        shape: the subject's body.
        initial_pose: an optional guess (33,), e.g. the previous frame's pose.
        options: weights and solver settings (E_cor/E_temp settings are unused).

    Returns:
        :class:`FrameFitResult`.

    Raises:
        ValidationError: fewer than 4 keypoints with confidence, or a bad ``initial_pose``.
        ProcessingError: a non-finite energy (a point in the camera's centre plane).
    """
    t0 = time.perf_counter()
    opt = options if options is not None else BatchFitOptions()
    _check_detection_energy(detections)
    init = None
    if initial_pose is not None:
        init = np.asarray(check_finite(check_shape(initial_pose, [POSE_DIM], name="initial_pose")))
    state, prob, energy, iterations = _fit_single(detections, camera, shape, opt, init)
    pose = state.poses()[0]
    tprime = state.tprime.numpy()[0].copy() if prob.T else None
    return FrameFitResult(
        pose=pose,
        translation_3d_m=tprime,
        energy=energy,
        iterations=iterations,
        seconds=time.perf_counter() - t0,
    )


def linear_baseline(
    detections_start: FrameDetections,
    detections_end: FrameDetections,
    camera: EventCamera,
    shape: BodyShape,
    *,
    n: int,
    options: BatchFitOptions | None = None,
) -> F64:
    """The ``*_linear`` baseline: per-frame fits at both APS frames, interpolated to ``(n+1, 33)``.

    Raises:
        ValidationError: as :func:`fit_frame` and :func:`interpolate_poses`.
    """
    a = fit_frame(detections_start, camera, shape, options=options)
    b = fit_frame(detections_end, camera, shape, options=options)
    return interpolate_poses(a.pose, b.pose, n=n)


# --- the batch fit --------------------------------------------------------------------------


def fit_batch(
    correspondences: Correspondences,
    detections: Sequence[FrameDetections],
    camera: EventCamera,
    shape: BodyShape,
    *,
    n: int = 40,
    initial_poses: npt.ArrayLike | None = None,
    phi: npt.ArrayLike | None = None,
    options: BatchFitOptions | None = None,
    reassociate: Callable[[F64], Correspondences] | None = None,
    rounds: int = 1,
) -> BatchFitResult:
    """Fit the poses of tracking frames ``0..n`` to events and detections (paper Eqs. 3–8).

    Args:
        correspondences: E_cor rows (frames within ``0..n``), associated at the initial poses
            (``initial_poses``, or the root-first initialisation when ``reassociate`` is
            given): with the ``"relative"`` model the point seen at frame ``i`` is anchored
            where that association put it.
        detections: keypoints at some frames (the APS frames 0 and ``n``); without
            ``initial_poses`` frames 0 and ``n`` must both be present.
        camera: the event camera.
        shape: the subject's body.
        n: number of tracking intervals in the batch (poses ``n + 1``).
        initial_poses: ``(n+1, 33)`` initial state; default: root-first per-frame fits at 0
            and ``n`` (:func:`fit_frame`) interpolated by :func:`interpolate_poses`.
        phi: ``(15,)`` E_temp weights; default :func:`temporal_weights` of the correspondences
            (with ``options.phi_observed``).
        options: weights and solver settings.
        reassociate: ICP-style refresh of E_cor: called with the current poses ``(n+1, 33)``
            before rounds 2..``rounds``, it returns new correspondences (e.g. the tracked
            pixels of frame ``i`` looked up on the body rendered at pose ``S_i``).
        rounds: number of solves, each but the first after a refresh (without
            ``reassociate`` one solve, with the correspondences as given).

    Returns:
        :class:`BatchFitResult`; with several rounds, ``initial_energy`` is the first round's
        and ``energy_history``/``final_energy`` the last round's (each round has its own
        correspondences, so energies of different rounds do not compare).

    Raises:
        ValidationError: frames outside ``0..n``, missing end detections, wrong shapes,
            ``rounds < 1``.
        ProcessingError: a non-finite energy (a point in the camera's centre plane).
    """
    t0 = time.perf_counter()
    opt = options if options is not None else BatchFitOptions()
    if int(n) < 1 or int(rounds) < 1:
        msg = f"fit_batch needs n >= 1 and rounds >= 1, got n={n}, rounds={rounds}"
        raise ValidationError(msg)
    n = int(n)
    dets = list(detections)
    if any(d.frame > n for d in dets):
        msg = f"FrameDetections frame outside the batch 0..{n}"
        raise ValidationError(msg)
    phi_given = None
    if phi is not None:
        phi_given = np.asarray(check_finite(check_shape(phi, [NUM_BODY_KEYPOINTS], name="phi")))

    def check_frames(cor: Correspondences) -> Correspondences:
        frames_c = np.concatenate([cor.frame_i, cor.frame_j])
        if frames_c.size and (frames_c.min() < 0 or frames_c.max() > n):
            msg = f"Correspondences reference frames outside the batch 0..{n}; slice per batch"
            raise ValidationError(msg)
        return cor

    check_frames(correspondences)

    def problem(cor: Correspondences, association_poses: F64) -> _Problem:
        return _Problem(
            num_frames=n + 1,
            correspondences=cor,
            detections=dets,
            camera=camera,
            shape=shape,
            options=opt,
            phi=(
                temporal_weights(cor, observed=opt.phi_observed) if phi_given is None else phi_given
            ),
            association_poses=association_poses,
        )

    if initial_poses is None:
        by_frame = {d.frame: d for d in dets}
        if 0 not in by_frame or n not in by_frame:
            msg = (
                f"fit_batch needs detections at frames 0 and {n} to initialise, got frames "
                f"{sorted(by_frame)}; pass initial_poses otherwise"
            )
            raise ValidationError(msg)
        _check_detection_energy(by_frame[0])
        _check_detection_energy(by_frame[n])
        start = fit_frame(by_frame[0], camera, shape, options=opt)
        end = fit_frame(by_frame[n], camera, shape, options=opt)
        poses0 = interpolate_poses(start.pose, end.pose, n=n)
    else:
        poses0 = np.asarray(
            check_finite(check_shape(initial_poses, [n + 1, POSE_DIM], name="initial_poses")),
            dtype=np.float64,
        )
    poses0 = poses0.copy()
    poses0[:, ROOT_DIM:] = np.clip(poses0[:, ROOT_DIM:], DOF_LIMITS_RAD[:, 0], DOF_LIMITS_RAD[:, 1])
    prob = problem(correspondences, poses0)
    state = _state_from_poses(poses0, _closed_form_tprime(prob, poses0))
    initial: EnergyTerms | None = None
    iterations = 0
    for k in range(int(rounds)):
        if k > 0 and reassociate is not None:
            current = state.poses()
            prob = problem(check_frames(reassociate(current)), current)
        out = _levenberg_marquardt(
            prob, state, max_iterations=opt.max_iterations, rtol=opt.rtol, mu_init=opt.mu_init
        )
        state, iterations = out.state, iterations + out.iterations
        initial = out.initial if initial is None else initial
        _log.debug("batch fit round %d: energy %.4g -> %.4g", k, out.initial.total, out.final.total)
        if reassociate is None:
            break
    seconds = time.perf_counter() - t0
    _log.info(
        "batch fit: %d frames, %d correspondences, energy %.4g in %d iterations, %.2f s",
        n + 1,
        int(prob.cor_frame.shape[0]),
        out.final.total,
        iterations,
        seconds,
    )
    return BatchFitResult(
        poses=state.poses(),
        translation_3d_m=state.tprime.numpy().copy(),
        initial_energy=out.initial if initial is None else initial,
        final_energy=out.final,
        energy_history=out.history,
        iterations=iterations,
        converged=out.converged,
        seconds=seconds,
    )
