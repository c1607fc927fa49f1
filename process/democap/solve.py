"""Skeleton solve: the articulated body model fitted to the fused marker cloud.

The network labels the cloud and regresses 53 markers and 19 joints frame by frame; its
joints are not bound to a skeleton and it straightens or swaps what it rarely saw. The solve
does what a marker-based capture system does after labelling: it fits the body model of
:mod:`mocaprig.process.body` (26 joints, the 27 bounded angles, the 53-marker set, 15
segment lengths and a girth) to the observed points, from the network's estimates.

Unknowns per frame (50): the root rotation and translation, the 27 angles (kept within
``DOF_LIMITS_RAD``), and the shape ``z = (h, g, δ_1..15)``: every length of the reference
body (:meth:`BodyShape.from_height` 1.75 m) times ``h·(1 + δ_k)``, every radius times ``h·g``.
Rest offsets are linear in the lengths (exact); marker offsets are linearised about the
reference body (over 300 sampled bodies the worst marker is off by 1 mm at the median body,
7 mm at the 95th percentile, 11 mm at worst) and scale with ``h`` exactly (the placement is
scale-equivariant).

Energy, metres (Geman–McClure ``ρ_c(d) = c²d²/(c²+d²)``, bounded, so a stray point or a
missing marker costs at most ``c²``)::

    E = Σ_markers ρ_c(d(M_m, cloud)) / σ_d²  +  Σ_points ρ_c(d(p, markers)) / σ_d²
      + Σ_joints ρ_cp(‖J_j − Ĵ_j‖) / σ_J²  +  Σ_markers ρ_cp(‖M_m − M̂_m‖) / σ_M²
      + shape prior  +  pose prior

The first two terms tie the model to the observed points both ways (each model marker to its
nearest point, each point to its nearest model marker; nearest neighbours are found anew at
every step, ICP-style), the next two keep it near the network's estimate ``Ĵ, M̂`` where the
cloud says nothing (a hidden hand), the last keeps the body plausible (height 0.86–1.14 of
the reference's, lengths ±4 %), and the **pose prior** (``pose_prior``, :mod:`.pose_prior`:
a Gaussian mixture over the 27 angles of real motion, at ``pose_prior_weight``) holds what
neither the cloud nor the network pins down (a forearm whose markers were missed, a hand
above every view). The gate ``c`` shrinks from ``gate_start_m`` to ``gate_m``
over the iterations (coarse to fine).

Solver: Levenberg–Marquardt with IRLS weights in torch float64, every frame an independent
problem with its own damping, batched; analytic Jacobians (:mod:`process.body.jacobian` for
the pose, the shape's in closed form); a step is kept only when the energy drops. Each
frame starts from the network's estimate: every rigid group of the skeleton (a joint with
DoF and what rides on it) is turned onto its estimated markers and joints (Kabsch), the
angles are read off the groups' relative rotations (of the two Euler solutions the one
within the limits: an arm over the head is abduction, not a flipped twist), then an inverse
kinematics fit onto the estimate refines angles and shape. It is solved once per
**hypothesis**: the ensemble's estimate and each single turn's (:class:`DemocapPredictor`),
and once more from each of them bent forward at the hips (``bend_starts_rad``: the
network's known failure is to straighten a body bent over). All starts take the first
``prune_after`` steps; only the ``keep_starts`` best of each frame take the rest.
The hypothesis whose solution explains the cloud best (the first two terms at
``selection_gate_m``, no network prior) wins: the turns disagree most where the network is
unsure, and the cloud decides. Last, the **limb search** (``limb_search``): each limb of the
winner in turn is set to every configuration of a coarse grid of its main angles and kept
where it explains the cloud best, a few more steps follow, and the result replaces the
winner where it explains the cloud better (a limb the network put elsewhere sits in a
minimum no gradient step leaves; solved from the truth, such frames reach a lower energy).

What it assumes: the subject is one of our bodies (proportions near Drillis & Contini,
markers where :class:`MarkerSet` puts them, rigid on their segments). The ``off-model``
evaluation protocol measures what it costs when they are not (docs/democap.md).

**Subject calibration** (:func:`calibrate_subject`): frames of one subject, each solved on
its own, tell their segment lengths and where their markers sit (the medians over the frames
the solve explains best); a solve given the :class:`SubjectCalibration` (``subjects``) holds
the shape within ``subject_shape_sigma`` of it (instead of the body model's ±4 %) and moves
each marker by its offset (in the segment's frame, not solved for: ``_State.m_fix``). A
marker moved along its bone is indistinguishable from a longer bone and is found only in
part; across it, in full.
"""

from __future__ import annotations

import functools
import itertools
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
import torch
from scipy.spatial.transform import Rotation

from mocaprig.calib.registration import kabsch_batch
from mocaprig.errors import ValidationError
from mocaprig.process.body.jacobian import JOINT_SEGMENT, point_jacobian, pose_geometry
from mocaprig.process.body.kinematics import (
    EULER_MAP,
    forward_kinematics,
    forward_kinematics_torch,
    neutral_pose,
    rotvec_to_matrix_torch,
    subtree_joints,
    subtree_kinematics_torch,
)
from mocaprig.process.body.markers import NUM_MARKERS, MarkerSet
from mocaprig.process.body.shape import (
    LENGTH_FIELDS,
    RADIUS_FIELDS,
    VERTICAL_CHAIN,
    BodyShape,
    rest_offsets,
)
from mocaprig.process.body.skeleton import (
    DEMOCAP_JOINT_INDEX,
    DEMOCAP_JOINTS,
    DOF_LIMITS_RAD,
    DOF_NAMES,
    JOINTS,
    NUM_DOF,
    PARENTS,
    ROOT_DIM,
)
from mocaprig.process.democap.simdata import Box, Camera, check_crop_box, in_frustum_torch
from mocaprig.validation import check_finite, check_positive, check_shape

if TYPE_CHECKING:
    from mocaprig.process.democap.pose_prior import PosePrior

__all__ = [
    "REFERENCE_HEIGHT_M",
    "SHAPE_DIM",
    "SolveOptions",
    "SolveResult",
    "SubjectCalibration",
    "calibrate_subject",
    "solve_skeleton",
]

_log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

#: Standing height of the reference body the shape is measured against (m).
REFERENCE_HEIGHT_M = 1.75
_NL = len(LENGTH_FIELDS)
#: Shape unknowns: h, g, then one relative change per length.
_NS = 2 + _NL
#: Shape unknowns per frame (``SolveResult.shape_z``): h, g, then one change per length.
SHAPE_DIM = _NS
_NP = ROOT_DIM + NUM_DOF + _NS
#: Frames solved at once (bounds the memory of the derivative operators, ~50 kB a frame).
_CHUNK = 512
_FAR_M = 1.0e3


@dataclass(frozen=True, slots=True)
class SolveOptions:
    """Weights and schedule of the skeleton solve (module doc); lengths in metres.

    Attributes:
        data_sigma_m: spread of an observed point about its marker (σ_d).
        gate_start_m, gate_m: the data terms' gate ``c``, shrunk geometrically from the first
            to the second over the iterations.
        selection_gate_m: the gate of the energy that picks the hypothesis.
        joint_prior_sigma_m, marker_prior_sigma_m: trust in the network's joints and markers.
        prior_gate_m: the network terms' gate (a wrong network joint stops pulling).
        height_sigma: prior spread of ``h`` (relative to the reference body), within
            ``height_range``; length_sigma: of each ``δ``; girth_mean, girth_sigma: of ``g``.
        init_iterations: inverse-kinematics steps onto the network's estimate.
        iterations: steps of the solve proper.
        bend_starts_rad: further starts made from every hypothesis with the body above the
            hips bent forward by each angle (rad) about the hip axis: the network's known
            failure is to straighten a body bent over (docs/democap.md); () for none.
        prune_after, keep_starts: after ``prune_after`` steps of the solve only the
            ``keep_starts`` starts of each frame that explain its cloud best go on (the others
            mostly end where one of them does; the cost of the rest is theirs alone).
        limb_search: after the solve, each limb of the winner in turn is set to every
            configuration of a coarse grid of its angles (216 per arm, 180 per leg, 15 for
            the head) and scored by how well it explains the cloud at the gate
            ``limb_gate_m`` (wide: a grid node is decimetres from the truth at the hand);
            the ``limb_keep[0]`` best are moved by ± half a grid step per angle and scored at
            ``limb_fine_gate_m``, the ``limb_keep[1]`` best of those by ± a quarter step,
            and so on, and the best of the last round is kept; then
            ``refine_iterations`` steps follow (the gate ``refine_gate_start_m`` ->
            ``gate_m``), and the result replaces the winner only where it explains the cloud
            better (at ``selection_gate_m``). A limb the network put on the wrong side of
            the body (a hand by the shin of a body bent over) sits in a minimum that no
            gradient step leaves.
        subject_shape_sigma: with a subject's calibration, the spread its shape is held in.
        pose_prior_weight: with a pose prior (``solve_skeleton(pose_prior=)``), the weight
            ``w`` of its energy (:mod:`.pose_prior`); on the validation stream 0.25–1 gave
            the same figures within a draw's spread, 3 worse (docs/democap.md).
    """

    data_sigma_m: float = 0.015
    gate_start_m: float = 0.15
    gate_m: float = 0.045
    selection_gate_m: float = 0.03
    joint_prior_sigma_m: float = 0.05
    marker_prior_sigma_m: float = 0.08
    prior_gate_m: float = 0.10
    height_sigma: float = 0.065
    height_range: tuple[float, float] = (0.86, 1.14)
    length_sigma: float = 0.04
    girth_mean: float = 1.02
    girth_sigma: float = 0.08
    init_iterations: int = 8
    iterations: int = 30
    bend_starts_rad: tuple[float, ...] = (0.8,)
    prune_after: int = 10
    keep_starts: int = 2
    limb_search: bool = True
    limb_gate_m: float = 0.25
    limb_fine_gate_m: float = 0.10
    refine_iterations: int = 12
    refine_gate_start_m: float = 0.10
    limb_keep: tuple[int, ...] = (8, 2)
    subject_shape_sigma: float = 0.01
    pose_prior_weight: float = 0.5

    def __post_init__(self) -> None:
        for name in (
            "data_sigma_m",
            "gate_start_m",
            "gate_m",
            "selection_gate_m",
            "joint_prior_sigma_m",
            "marker_prior_sigma_m",
            "prior_gate_m",
            "height_sigma",
            "length_sigma",
            "girth_mean",
            "girth_sigma",
            "refine_gate_start_m",
            "limb_gate_m",
            "limb_fine_gate_m",
            "subject_shape_sigma",
            "pose_prior_weight",
        ):
            check_positive(float(getattr(self, name)), name=f"SolveOptions.{name}")
        lo, hi = self.height_range
        if not 0 < lo < 1 < hi:
            msg = f"SolveOptions.height_range must be (low < 1 < high), got {self.height_range}"
            raise ValidationError(msg)
        if min(self.init_iterations, self.iterations, self.prune_after, self.refine_iterations) < 0:
            msg = (
                "SolveOptions.init_iterations, .iterations, .prune_after and "
                ".refine_iterations must be >= 0"
            )
            raise ValidationError(msg)
        if not self.limb_keep or min(self.limb_keep) < 1:
            msg = f"SolveOptions.limb_keep must be one or more counts >= 1, got {self.limb_keep}"
            raise ValidationError(msg)
        if self.keep_starts < 1:
            msg = f"SolveOptions.keep_starts must be >= 1, got {self.keep_starts}"
            raise ValidationError(msg)


@dataclass(frozen=True, slots=True)
class SolveResult:
    """The solved skeleton of B frames, world frame, metres.

    Attributes:
        markers_m: (B, 53, 3) model markers; joints_m: (B, 19, 3) DeMoCap joints.
        poses: (B, 33) pose vectors (:mod:`process.body.skeleton`) of the solved body.
        height_m: (B,) its standing height.
        energy: (B,) the selection energy of the winning hypothesis (lower: the cloud is
            explained better; a sum of bounded terms, one per marker and per point).
        hypothesis: (B,) index of the winning hypothesis; ``H·(1 + a) + h`` for hypothesis
            ``h`` bent by the ``a``-th angle of :attr:`SolveOptions.bend_starts_rad`.
    """

    markers_m: FloatArray
    joints_m: FloatArray
    poses: FloatArray
    height_m: FloatArray
    energy: FloatArray
    hypothesis: npt.NDArray[np.int64]
    #: (B, 17) the solved shapes: ``h, g, δ_1..15`` (module doc)
    shape_z: FloatArray


@dataclass(frozen=True, slots=True)
class SubjectCalibration:
    """One subject's body as their own frames show it (:func:`calibrate_subject`).

    Attributes:
        shape_z: (17,) the shape unknowns ``h, g, δ_1..15`` (module doc); a solve given the
            calibration holds each within ``SolveOptions.subject_shape_sigma`` of it.
        marker_offsets_m: (53, 3) where each marker sits on its segment against where the
            marker set puts it, segment frame, m (0 where the frames did not tell).
        frames: frames the calibration was made from.
    """

    shape_z: FloatArray
    marker_offsets_m: FloatArray
    frames: int

    def __post_init__(self) -> None:
        check_shape(check_finite(self.shape_z, name="shape_z"), [_NS], name="shape_z")
        check_shape(
            check_finite(self.marker_offsets_m, name="marker_offsets_m"),
            [NUM_MARKERS, 3],
            name="marker_offsets_m",
        )
        if self.shape_z[0] <= 0 or self.shape_z[1] <= 0 or (self.shape_z[2:] <= -1).any():
            msg = (
                "a subject's scale and girth must be > 0 and every length > 0, got shape_z "
                f"{np.round(self.shape_z, 4).tolist()}"
            )
            raise ValidationError(msg)
        if isinstance(self.frames, bool) or int(self.frames) != self.frames or self.frames < 0:
            msg = f"frames must be an integer >= 0, got {self.frames!r}"
            raise ValidationError(msg)

    @property
    def scale(self) -> float:
        """``h``: every length of the reference body (:data:`REFERENCE_HEIGHT_M`) times it."""
        return float(self.shape_z[0])

    @property
    def girth(self) -> float:
        """``g``: every radius of the reference body times ``h·g``."""
        return float(self.shape_z[1])

    @property
    def standing_height_m(self) -> float:
        """Standing height (m): the vertical chain of the lengths, floor to head top."""
        return float(_standing_height_m(torch.from_numpy(self.shape_z[None].copy()))[0])

    @property
    def segment_lengths_m(self) -> dict[str, float]:
        """Each of the body model's lengths (``BodyShape`` field -> m)."""
        f0 = _basis().f0.numpy()[:_NL]
        lengths = f0 * self.shape_z[0] * (1.0 + self.shape_z[2:])
        return {k: float(v) for k, v in zip(LENGTH_FIELDS, lengths, strict=True)}

    @classmethod
    def from_lengths(
        cls,
        *,
        scale: float,
        girth: float,
        segment_lengths_m: Mapping[str, float],
        marker_offsets_m: npt.ArrayLike,
        frames: int,
    ) -> SubjectCalibration:
        """The calibration of a body given by its lengths (m; every ``BodyShape`` length field,
        no other), ``scale`` (``h``) and ``girth`` (``g``): the inverse of
        :attr:`segment_lengths_m`.

        Raises:
            ValidationError: a length missing, unknown, not finite or not > 0; a scale or
                girth not > 0; offsets not (53, 3).
        """
        missing = sorted(set(LENGTH_FIELDS) - set(segment_lengths_m))
        unknown = sorted(set(segment_lengths_m) - set(LENGTH_FIELDS))
        if missing or unknown:
            msg = f"segment lengths: missing {missing}, unknown {unknown}"
            raise ValidationError(msg)
        lengths = np.array([float(segment_lengths_m[k]) for k in LENGTH_FIELDS])
        check_finite(lengths, name="segment lengths")
        if not (lengths > 0).all():
            msg = f"every segment length must be > 0 m, got {lengths.round(4).tolist()}"
            raise ValidationError(msg)
        h = check_positive(float(scale), name="scale")
        g = check_positive(float(girth), name="girth")
        f0 = _basis().f0.numpy()[:_NL]
        return cls(
            shape_z=np.concatenate([[h, g], lengths / (f0 * h) - 1.0]),
            marker_offsets_m=np.asarray(marker_offsets_m, np.float64),
            frames=frames,
        )


@dataclass(frozen=True, slots=True)
class _Basis:
    """The reference body and the shape's linear maps (module doc)."""

    f0: torch.Tensor  # (28,) reference lengths then radii, m
    d_off: torch.Tensor  # (28, 26, 3): rest offsets per field (exactly linear)
    m_off0: torch.Tensor  # (53, 3) reference marker offsets, m
    d_moff: torch.Tensor  # (28, 53, 3): marker offsets per field (linearised)
    marker_joint: torch.Tensor  # (53,)
    joint_index: torch.Tensor  # (19,) DeMoCap joints in our skeleton
    joint_segment: torch.Tensor  # (19,) the segment each rides on
    groups: tuple[_Group, ...]  # the rigid groups of the first guess, root first
    rest_points_m: FloatArray  # (72, 3) markers then DeMoCap joints, neutral pose, body frame
    rest_root_m: FloatArray  # (3,) the root joint in that pose
    leg_points: npt.NDArray[np.bool_]  # (72,) points on the thighs and below
    hip_joints: tuple[int, int]  # the DeMoCap indices of the right and left hip joints
    lo: torch.Tensor  # (27,) angle limits, rad
    hi: torch.Tensor


@dataclass(frozen=True, slots=True)
class _Group:
    """Points that turn together with one joint's DoF (the joint and its descendants up to
    the next joint with DoF of its own), for the first guess of the angles.

    ``points`` index the 72 points (53 markers, then the 19 DeMoCap joints); ``parent`` is
    the group whose rotation the angles are relative to (-1: the world, the root's group);
    ``dofs`` and ``coeff`` (K, 3) say which DoF turn it about which local axis, per radian.
    """

    joint: int
    parent: int
    points: npt.NDArray[np.int64]
    dofs: npt.NDArray[np.int64]
    coeff: FloatArray


def _groups(marker_joint: npt.NDArray[np.int64]) -> tuple[_Group, ...]:
    """The rigid groups (:class:`_Group`) of the skeleton, parents before children.

    The spine's three DoF turn Spine1 and Spine2 half each; the chest (Spine2 and the fixed
    clavicles) is taken as one group turned by their whole sum from the pelvis.
    """
    has_dof = np.abs(EULER_MAP).sum(axis=(0, 2)) > 0
    spine1 = JOINTS.index("Spine1")
    owner = [0] * len(JOINTS)  # the group joint each joint's frame turns with
    for j in range(1, len(JOINTS)):
        owner[j] = j if has_dof[j] and j != spine1 else owner[PARENTS[j]]
    heads = [0, *(j for j in range(1, len(JOINTS)) if owner[j] == j)]
    seg = [JOINT_SEGMENT[j] for j in DEMOCAP_JOINT_INDEX]
    out = []
    for g in heads:
        pts = [i for i, j in enumerate(marker_joint) if owner[int(j)] == g]
        pts += [NUM_MARKERS + k for k, s in enumerate(seg) if owner[s] == g]
        # the group's own pivot, a DeMoCap joint riding on its parent
        pts += [NUM_MARKERS + k for k, j in enumerate(DEMOCAP_JOINT_INDEX) if j == g]
        coeff = EULER_MAP[:, g, :] + (EULER_MAP[:, spine1, :] if g == spine1 + 1 else 0.0)
        dofs = np.flatnonzero(np.abs(coeff).sum(axis=1) > 0)
        par = -1 if g == 0 else heads.index(owner[PARENTS[g]])
        out.append(_Group(g, par, np.array(sorted(set(pts))), dofs, coeff[dofs]))
    return tuple(out)


def _subtree(*tops: str) -> npt.NDArray[np.bool_]:
    """(26,): which joints are one of ``tops`` or below one of them."""
    under = np.zeros(len(JOINTS), dtype=bool)
    for t in tops:
        under[list(subtree_joints(JOINTS.index(t)))] = True
    return under


def _leg_points(marker_joint: npt.NDArray[np.int64]) -> npt.NDArray[np.bool_]:
    """(72,): which of the 53 markers and 19 DeMoCap joints are on a leg (hip joint down)."""
    legs = _subtree("RightUpLeg", "LeftUpLeg")
    return np.concatenate([legs[marker_joint], legs[list(DEMOCAP_JOINT_INDEX)]])


def _bent(
    markers_m: FloatArray, joints_m: FloatArray, angle_rad: float, b: _Basis
) -> tuple[FloatArray, FloatArray]:
    """Estimates (B, 53, 3), (B, 19, 3) with everything above the hips turned forward by
    ``angle_rad`` about the line through the hip joints (the legs stay)."""
    pts = np.concatenate([markers_m, joints_m], axis=1)
    r_hip, l_hip = joints_m[:, b.hip_joints[0]], joints_m[:, b.hip_joints[1]]
    axis = r_hip - l_hip
    axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-9)
    pivot = 0.5 * (r_hip + l_hip)
    # about the subject's right-pointing axis, a negative turn brings the head forward
    rot = Rotation.from_rotvec(-angle_rad * axis).as_matrix()  # (B, 3, 3)
    turned = np.einsum("bij,bkj->bki", rot, pts - pivot[:, None]) + pivot[:, None]
    out = np.where(b.leg_points[None, :, None], pts, turned)
    return out[:, :NUM_MARKERS], out[:, NUM_MARKERS:]


def _shape_from_fields(f: FloatArray) -> BodyShape:
    d = dict(zip(LENGTH_FIELDS + RADIUS_FIELDS, (float(v) for v in f), strict=True))
    return BodyShape(height_m=sum(d[k] for k in VERTICAL_CHAIN), **d)


@functools.cache
def _basis() -> _Basis:
    ref = BodyShape.from_height(REFERENCE_HEIGHT_M)
    names = LENGTH_FIELDS + RADIUS_FIELDS
    f0 = np.array([getattr(ref, k) for k in names])
    ms = MarkerSet.for_shape(ref)
    o0, r0 = ms.offsets_m, rest_offsets(ref)
    d_off, d_moff = [], []
    for k in range(len(names)):
        # Rest offsets are linear in the fields: the unit response is exact; the marker
        # offsets are smooth in them: a central difference.
        e = 1e-4 * f0[k]
        lo, hi = f0.copy(), f0.copy()
        lo[k] -= e
        hi[k] += e
        s_lo, s_hi = _shape_from_fields(lo), _shape_from_fields(hi)
        d_off.append((rest_offsets(s_hi) - rest_offsets(s_lo)) / (2 * e))
        d_moff.append(
            (MarkerSet.for_shape(s_hi).offsets_m - MarkerSet.for_shape(s_lo).offsets_m) / (2 * e)
        )
    d_off_a = np.array(d_off)
    if np.abs(np.tensordot(f0, d_off_a, 1) - r0).max() > 1e-9:  # pragma: no cover - model change
        msg = "rest offsets are no longer linear in the shape fields; the solve needs a new basis"
        raise RuntimeError(msg)
    rest = neutral_pose(ref)
    kin = forward_kinematics(rest, ref)
    rest_markers = kin.positions_m[ms.joint_index] + np.einsum(
        "mij,mj->mi", kin.rotations[ms.joint_index], o0
    )
    rest_points = np.concatenate([rest_markers, kin.positions_m[list(DEMOCAP_JOINT_INDEX)]])
    t = torch.from_numpy
    return _Basis(
        f0=t(f0),
        d_off=t(d_off_a),
        m_off0=t(o0.copy()),
        d_moff=t(np.array(d_moff)),
        marker_joint=t(ms.joint_index.copy()),
        joint_index=torch.tensor(DEMOCAP_JOINT_INDEX),
        joint_segment=torch.tensor([JOINT_SEGMENT[j] for j in DEMOCAP_JOINT_INDEX]),
        groups=_groups(ms.joint_index),
        rest_points_m=rest_points,
        rest_root_m=kin.positions_m[0].copy(),
        leg_points=_leg_points(ms.joint_index),
        hip_joints=(DEMOCAP_JOINTS.index("RightUpLeg"), DEMOCAP_JOINTS.index("LeftUpLeg")),
        lo=t(DOF_LIMITS_RAD[:, 0].copy()),
        hi=t(DOF_LIMITS_RAD[:, 1].copy()),
    )


@dataclass(frozen=True, slots=True)
class _State:
    root_r: torch.Tensor  # (P, 3, 3)
    root_t: torch.Tensor  # (P, 3)
    angles: torch.Tensor  # (P, 27)
    z: torch.Tensor  # (P, 17)
    # (P, 53, 3) the subject's marker corrections, segment frames, m (held, not solved for)
    m_fix: torch.Tensor

    def step(self, d: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> _State:
        """The state moved by increments ``d`` (P, 50), angles projected onto the limits."""
        return _State(
            root_r=rotvec_to_matrix_torch(d[:, 0:3]) @ self.root_r,
            root_t=self.root_t + d[:, 3:6],
            angles=torch.clamp(self.angles + d[:, ROOT_DIM : ROOT_DIM + NUM_DOF], lo, hi),
            z=self.z + d[:, ROOT_DIM + NUM_DOF :],
            m_fix=self.m_fix,
        )

    def where(self, keep: torch.Tensor, other: _State) -> _State:
        """Per problem: this state where ``keep``, else ``other``."""
        k1, k2 = keep[:, None], keep[:, None, None]
        return _State(
            root_r=torch.where(k2, self.root_r, other.root_r),
            root_t=torch.where(k1, self.root_t, other.root_t),
            angles=torch.where(k1, self.angles, other.angles),
            z=torch.where(k1, self.z, other.z),
            m_fix=torch.where(k2, self.m_fix, other.m_fix),
        )

    def take(self, idx: torch.Tensor) -> _State:
        """The problems ``idx``."""
        return _State(
            self.root_r[idx], self.root_t[idx], self.angles[idx], self.z[idx], self.m_fix[idx]
        )

    @staticmethod
    def cat(states: Sequence[_State]) -> _State:
        """The problems of ``states``, in order."""
        return _State(
            torch.cat([x.root_r for x in states]),
            torch.cat([x.root_t for x in states]),
            torch.cat([x.angles for x in states]),
            torch.cat([x.z for x in states]),
            torch.cat([x.m_fix for x in states]),
        )

    def poses(self) -> FloatArray:
        """(P, 33) pose vectors."""
        rv = Rotation.from_matrix(self.root_r.numpy()).as_rotvec()
        return np.concatenate([rv, self.root_t.numpy(), self.angles.numpy()], axis=1)


@dataclass(frozen=True, slots=True)
class _Posed:
    pos: torch.Tensor  # (P, 26, 3)
    rot: torch.Tensor  # (P, 26, 3, 3)
    markers: torch.Tensor  # (P, 53, 3)
    joints: torch.Tensor  # (P, 19, 3)
    rel: torch.Tensor  # (P, 28) the fields at unit height scale
    m_off: torch.Tensor  # (P, 53, 3) marker offsets, m


def _pose(s: _State, b: _Basis) -> _Posed:
    h, g, dl = s.z[:, 0:1], s.z[:, 1:2], s.z[:, 2:]
    rel = torch.cat([b.f0[:_NL] * (1.0 + dl), b.f0[_NL:] * g], dim=1)
    off = h[..., None] * torch.tensordot(rel, b.d_off, 1)
    m_off = h[..., None] * (b.m_off0 + torch.tensordot(rel - b.f0, b.d_moff, 1)) + s.m_fix
    local = torch.cat([torch.zeros(s.angles.shape[0], ROOT_DIM, dtype=s.angles.dtype), s.angles], 1)
    pos_b, rot_b = forward_kinematics_torch(local, off)
    pos = (s.root_r[:, None] @ pos_b[..., None])[..., 0] + s.root_t[:, None]
    rot = s.root_r[:, None] @ rot_b
    mj = b.marker_joint
    markers = pos[:, mj] + (rot[:, mj] @ m_off[..., None])[..., 0]
    return _Posed(pos, rot, markers, pos[:, b.joint_index], rel, m_off)


def _shape_jacobians(s: _State, q: _Posed, b: _Basis) -> tuple[torch.Tensor, torch.Tensor]:
    """d(markers)/dz (P, 53, 3, 17) and d(DeMoCap joints)/dz (P, 19, 3, 17)."""
    h = s.z[:, 0]
    p_n = s.z.shape[0]
    # d(rest offsets)/dz (P, 26, 3, 17): h scales everything, g the radii, δ_k one length.
    unit = torch.tensordot(q.rel, b.d_off, 1)  # offsets at h = 1
    d_off = torch.zeros(p_n, len(JOINTS), 3, _NS, dtype=torch.float64)
    d_off[..., 0] = unit
    d_off[..., 1] = h[:, None, None] * torch.tensordot(b.f0[_NL:], b.d_off[_NL:], 1)
    d_off[..., 2:] = h[:, None, None, None] * (b.f0[:_NL, None, None] * b.d_off[:_NL]).permute(
        1, 2, 0
    )
    d_mo = torch.zeros(p_n, NUM_MARKERS, 3, _NS, dtype=torch.float64)
    d_mo[..., 0] = (q.m_off - s.m_fix) / h[:, None, None]
    d_mo[..., 1] = h[:, None, None] * torch.tensordot(b.f0[_NL:], b.d_moff[_NL:], 1)
    d_mo[..., 2:] = h[:, None, None, None] * (b.f0[:_NL, None, None] * b.d_moff[:_NL]).permute(
        1, 2, 0
    )
    # A joint moves with its own offset (in its parent's frame) and with every ancestor's.
    par_rot = q.rot[:, list(JOINT_SEGMENT)]
    moved = par_rot @ d_off  # (P, 26, 3, 17)
    chain = [moved[:, 0] * 0.0]
    for j in range(1, len(JOINTS)):
        chain.append(chain[PARENTS[j]] + moved[:, j])
    d_joint = torch.stack(chain, dim=1)  # (P, 26, 3, 17)
    mj = b.marker_joint
    d_markers = d_joint[:, mj] + q.rot[:, mj] @ d_mo
    return d_markers, d_joint[:, b.joint_index]


def _gm(d2: torch.Tensor, c: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Geman–McClure of squared distances: energy ``c²d²/(c²+d²)`` and IRLS weight."""
    c2 = c * c
    return c2 * d2 / (c2 + d2), (c2 / (c2 + d2)) ** 2


@dataclass(frozen=True, slots=True)
class _Data:
    cloud: torch.Tensor  # (P, N, 3), padded far away
    mask: torch.Tensor  # (P, N) 1 for a real point
    tm: torch.Tensor  # (P, 53, 3) the network's markers
    tj: torch.Tensor  # (P, 19, 3) and joints
    prior: _Prior  # the shape prior per problem
    views: _Views | None = None  # the rig's cameras per problem (None: everything is seen)

    def seen(self, pts: torch.Tensor) -> torch.Tensor:
        """1.0 where a point (P, ..., 3) lies in some camera's view of its problem, else 0.0
        (P, ...); all ones without views."""
        if self.views is None:
            return torch.ones(pts.shape[:-1], dtype=pts.dtype)
        return self.views.seen(pts)

    def rows(self, lo: int, hi: int) -> _Data:
        """Problems ``lo:hi``."""
        return _Data(
            self.cloud[lo:hi],
            self.mask[lo:hi],
            self.tm[lo:hi],
            self.tj[lo:hi],
            self.prior.rows(lo, hi),
            None if self.views is None else self.views.rows(lo, hi),
        )


@dataclass(frozen=True, slots=True)
class _Prior:
    """Per problem: the shape prior's mean ``z0`` and weights ``zw`` (1/σ², P × 17) and the
    marker corrections ``m_fix`` (P, 53, 3) a start is built with (the subject's, else
    the body model's: mean ``(1, girth_mean, 0, ...)``, no corrections)."""

    z0: torch.Tensor
    zw: torch.Tensor
    m_fix: torch.Tensor
    z_start: torch.Tensor  # (P, 17) where a start's shape begins
    # the pose prior's means (K, 27), weighted precisions (K, 27, 27) and weighted costs
    # (K,), the same for every problem; None: no pose prior
    pose: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None

    @staticmethod
    def of(
        subjects: Sequence[SubjectCalibration | None],
        opt: SolveOptions,
        pose_prior: PosePrior | None = None,
    ) -> _Prior:
        n = len(subjects)
        z0 = np.zeros((n, _NS))
        z0[:, 0], z0[:, 1] = 1.0, opt.girth_mean
        sig = np.empty((n, _NS))
        sig[:, 0], sig[:, 1], sig[:, 2:] = opt.height_sigma, opt.girth_sigma, opt.length_sigma
        fix = np.zeros((n, NUM_MARKERS, 3))
        start = np.zeros((n, _NS))
        start[:, 0:2] = 1.0
        for i, c in enumerate(subjects):
            if c is not None:
                z0[i], sig[i], fix[i] = c.shape_z, opt.subject_shape_sigma, c.marker_offsets_m
                start[i] = c.shape_z
        t = torch.from_numpy
        pose = None
        if pose_prior is not None:
            w = opt.pose_prior_weight
            pose = (t(pose_prior.means), t(w * pose_prior.precisions), t(w * pose_prior.costs))
        return _Prior(t(z0), t(1.0 / sig**2), t(fix), t(start), pose)

    def rows(self, lo: int, hi: int) -> _Prior:
        return _Prior(
            self.z0[lo:hi], self.zw[lo:hi], self.m_fix[lo:hi], self.z_start[lo:hi], self.pose
        )

    def take(self, idx: npt.NDArray[np.intp]) -> _Prior:
        i = torch.from_numpy(np.asarray(idx, np.int64))
        return _Prior(self.z0[i], self.zw[i], self.m_fix[i], self.z_start[i], self.pose)


@dataclass(frozen=True, slots=True)
class _Views:
    """Each problem's cameras, padded to the largest rig with cameras of focal 0, and the
    crop box the clouds were cut to (one for every problem)."""

    centre: torch.Tensor  # (P, K, 3) world, m
    r_cw: torch.Tensor  # (P, K, 3, 3) world -> camera
    focal: torch.Tensor  # (P, K) px; 0 for a padded camera
    principal: torch.Tensor  # (P, K, 2) px
    size: torch.Tensor  # (P, K, 2) image width, height, px
    box: torch.Tensor | None = None  # (3, 2) world, m: (low, high) per axis; None: no crop

    @staticmethod
    def of(views: Sequence[Sequence[Camera]], box: Box | None = None) -> _Views:
        p_n, k = len(views), max((len(v) for v in views), default=0)
        c, r, f = np.zeros((p_n, k, 3)), np.tile(np.eye(3), (p_n, k, 1, 1)), np.zeros((p_n, k))
        pp, wh = np.zeros((p_n, k, 2)), np.zeros((p_n, k, 2))
        for i, v in enumerate(views):
            for j, cam in enumerate(v):
                c[i, j], r[i, j], f[i, j] = cam.centre_m, cam.r_cw, cam.focal_px
                pp[i, j], wh[i, j] = cam.principal_px, cam.size_px
        crop = None if box is None else torch.tensor(box, dtype=torch.float64)
        t = [torch.from_numpy(a) for a in (c, r, f, pp, wh)]
        return _Views(t[0], t[1], t[2], t[3], t[4], crop)

    def rows(self, lo: int, hi: int) -> _Views:
        return replace(self, **{n: getattr(self, n)[lo:hi] for n in _VIEW_FIELDS})

    def take(self, idx: npt.NDArray[np.intp]) -> _Views:
        i = torch.from_numpy(np.asarray(idx, np.int64))
        return replace(self, **{n: getattr(self, n)[i] for n in _VIEW_FIELDS})

    def seen(self, pts: torch.Tensor) -> torch.Tensor:
        """1.0 where a point (P, ..., 3) lies in some camera's view of its problem and inside
        the crop box (P, ...)."""
        shape = pts.shape
        flat = pts.reshape(shape[0], -1, 3)
        inside = in_frustum_torch(
            flat,
            self.centre,
            self.r_cw,
            self.focal,
            principal_px=self.principal,
            size_px=self.size,
        ).any(-1)
        if self.box is not None:
            inside &= ((flat >= self.box[:, 0]) & (flat <= self.box[:, 1])).all(-1)
        return inside.to(pts.dtype).reshape(shape[:-1])


_VIEW_FIELDS = ("centre", "r_cw", "focal", "principal", "size")


def _nearest(
    q: _Posed, data: _Data
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each model marker's nearest cloud point (distance, index; (P, 53)) and each cloud
    point's nearest model marker (distance, index; (P, N))."""
    d = torch.cdist(q.markers, data.cloud)
    d_m, nn_m = d.min(dim=2)
    d_c, nn_c = d.min(dim=1)
    return d_m, nn_m, d_c, nn_c


def _nearest_d2(q: _Posed, data: _Data) -> tuple[torch.Tensor, torch.Tensor]:
    """Squared distances of :func:`_nearest` without the indices (P, 53) and (P, N): ``amin``,
    about half the time of torch's min-with-indices on these shapes."""
    d = torch.cdist(q.markers, data.cloud)
    return d.amin(dim=2).square_(), d.amin(dim=1).square_()


@dataclass(frozen=True, slots=True)
class _Weights:
    """Which terms a run uses and how (the init stage: network only, no gate)."""

    data: bool
    gate_m: float
    sigma_d: float
    sigma_j: float
    sigma_m: float
    prior_gate_m: float | None


def _energy_terms(
    q: _Posed, s: _State, data: _Data, w: _Weights, opt: SolveOptions
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Energy (P,) and the per-point IRLS weights and targets of the normal equations."""
    aux: dict[str, torch.Tensor] = {}
    e = torch.zeros(q.markers.shape[0], dtype=torch.float64)
    if w.data:
        d_m, nn_m, d_c, nn_c = _nearest(q, data)
        e_m, w_m = _gm(d_m * d_m, w.gate_m)
        # a model marker no camera can see is not missing from the cloud: no cost
        seen = data.seen(q.markers)
        e_m, w_m = e_m * seen, w_m * seen
        e_c, w_c = _gm(d_c * d_c, w.gate_m)
        w_c = w_c * data.mask
        e = e + (e_m.sum(1) + (e_c * data.mask).sum(1)) / w.sigma_d**2
        # Per marker: the total weight and the weighted sum of its targets, both ways.
        tgt = torch.gather(data.cloud, 1, nn_m[..., None].expand(-1, -1, 3)) * w_m[..., None]
        wsum = w_m.clone()
        wsum.scatter_add_(1, nn_c, w_c)
        tgt.scatter_add_(1, nn_c[..., None].expand(-1, -1, 3), data.cloud * w_c[..., None])
        aux["data_w"] = wsum / w.sigma_d**2
        aux["data_t"] = tgt / w.sigma_d**2
    for key, pts, target, sigma in (
        ("joint", q.joints, data.tj, w.sigma_j),
        ("marker", q.markers, data.tm, w.sigma_m),
    ):
        r2 = ((pts - target) ** 2).sum(-1)
        if w.prior_gate_m is None:
            en, wt = r2, torch.ones_like(r2)
        else:
            en, wt = _gm(r2, w.prior_gate_m)
        e = e + en.sum(1) / sigma**2
        aux[key] = wt / sigma**2
    z = s.z
    lo, hi = opt.height_range
    over = torch.relu(z[:, 0] - hi) + torch.relu(lo - z[:, 0])
    e = e + ((z - data.prior.z0) ** 2 * data.prior.zw).sum(1) + (over / 0.005) ** 2
    if w.data and data.prior.pose is not None:
        # the component that costs least now (the mixture's bound, as IRLS picks its weights)
        mu, prec, cost = data.prior.pose
        d = s.angles[:, None, :] - mu[None]  # (P, K, 27)
        en = torch.einsum("pki,kij,pkj->pk", d, prec, d) + cost[None]
        best = en.argmin(1)
        rows = torch.arange(len(best))
        e = e + en[rows, best]
        aux["pose_prec"] = prec[best]
        aux["pose_d"] = d[rows, best]
    return e, aux


def _normal_equations(
    s: _State, q: _Posed, aux: dict[str, torch.Tensor], data: _Data, opt: SolveOptions, b: _Basis
) -> tuple[torch.Tensor, torch.Tensor]:
    """``JᵀWJ`` (P, 50, 50) and ``JᵀWr`` (P, 50) at ``s`` (IRLS weights from ``aux``)."""
    p_n = s.z.shape[0]
    geo = pose_geometry(q.pos, q.rot, s.root_r, s.root_t, s.angles)
    frames = torch.arange(p_n)[:, None]
    jm_pose = point_jacobian(
        geo, frames.expand(-1, NUM_MARKERS), b.marker_joint.expand(p_n, -1), q.markers
    )
    jj_pose = point_jacobian(
        geo, frames.expand(-1, len(b.joint_index)), b.joint_segment.expand(p_n, -1), q.joints
    )
    jm_shape, jj_shape = _shape_jacobians(s, q, b)
    jm = torch.cat([jm_pose, jm_shape], dim=-1)  # (P, 53, 3, 50)
    jj = torch.cat([jj_pose, jj_shape], dim=-1)  # (P, 19, 3, 50)
    # Per point: a scalar weight and a residual; Σ w‖x − t‖² for every term at once.
    wm = aux["marker"]
    rm = wm[..., None] * (q.markers - data.tm)
    if "data_w" in aux:
        wm = wm + aux["data_w"]
        rm = rm + aux["data_w"][..., None] * q.markers - aux["data_t"]
    wj = aux["joint"]
    rj = wj[..., None] * (q.joints - data.tj)
    # JᵀWJ as one product of the weighted Jacobians of all points (P, 3·72, 50).
    jw = torch.cat(
        [
            (jm * wm.sqrt()[..., None, None]).reshape(p_n, -1, _NP),
            (jj * wj.sqrt()[..., None, None]).reshape(p_n, -1, _NP),
        ],
        dim=1,
    )
    a = jw.transpose(1, 2) @ jw
    g = (jm.reshape(p_n, -1, _NP).transpose(1, 2) @ rm.reshape(p_n, -1, 1))[..., 0]
    g = g + (jj.reshape(p_n, -1, _NP).transpose(1, 2) @ rj.reshape(p_n, -1, 1))[..., 0]
    # The shape prior's rows (their derivatives are constants).
    z = s.z
    lo, hi = opt.height_range
    o = ROOT_DIM + NUM_DOF
    idx = torch.arange(o, _NP)
    a[:, idx, idx] += data.prior.zw
    g[:, o:] += data.prior.zw * (z - data.prior.z0)
    over = (z[:, 0] > hi).double() + (z[:, 0] < lo).double()
    wb = over / 0.005**2
    a[:, o, o] += wb
    g[:, o] += wb * (z[:, 0] - torch.clamp(z[:, 0], lo, hi))
    if "pose_prec" in aux:
        ang = slice(ROOT_DIM, ROOT_DIM + NUM_DOF)
        a[:, ang, ang] += aux["pose_prec"]
        g[:, ang] += (aux["pose_prec"] @ aux["pose_d"][..., None])[..., 0]
    return a, g


def _levenberg_marquardt(
    s: _State, data: _Data, weights: Sequence[_Weights], opt: SolveOptions, b: _Basis
) -> _State:
    """One LM step per entry of ``weights`` (the schedule), every problem damped on its own."""
    p_n = s.z.shape[0]
    lam = torch.full((p_n,), 1e-2, dtype=torch.float64)
    eye = torch.eye(_NP, dtype=torch.float64)
    q = _pose(s, b)
    for w in weights:
        e, aux = _energy_terms(q, s, data, w, opt)
        a, g = _normal_equations(s, q, aux, data, opt, b)
        diag = torch.diagonal(a, dim1=1, dim2=2).clamp_min(1e-9)
        sys_ = a + lam[:, None, None] * torch.diag_embed(diag) + 1e-12 * eye
        step = torch.linalg.solve(sys_, -g[..., None])[..., 0]
        cand = s.step(step, b.lo, b.hi)
        qc = _pose(cand, b)
        ec, _ = _energy_terms(qc, cand, data, w, opt)
        ok = torch.isfinite(ec) & (ec < e)
        s = cand.where(ok, s)
        q = _Posed(
            pos=torch.where(ok[:, None, None], qc.pos, q.pos),
            rot=torch.where(ok[:, None, None, None], qc.rot, q.rot),
            markers=torch.where(ok[:, None, None], qc.markers, q.markers),
            joints=torch.where(ok[:, None, None], qc.joints, q.joints),
            rel=torch.where(ok[:, None], qc.rel, q.rel),
            m_off=torch.where(ok[:, None, None], qc.m_off, q.m_off),
        )
        lam = torch.where(ok, lam * 0.3, lam * 10.0).clamp(1e-7, 1e7)
    return s


def _angles_from_local(local: FloatArray, g: _Group) -> FloatArray:
    """The group's DoF (P, K) that best give local rotations (P, 3, 3): of the two Euler
    (X, Y, Z) solutions, the one nearer the joint limits, clipped to them."""
    lo, hi = DOF_LIMITS_RAD[g.dofs, 0], DOF_LIMITS_RAD[g.dofs, 1]
    e1 = Rotation.from_matrix(local).as_euler("XYZ")
    e2 = np.stack([e1[:, 0] + np.pi, np.pi - e1[:, 1], e1[:, 2] + np.pi], axis=1)
    # each DoF reads the local axis it turns about (its largest coefficient), per radian
    axis = np.argmax(np.abs(g.coeff), axis=1)
    per_rad = g.coeff[np.arange(len(axis)), axis]
    cands = [(((e + np.pi) % (2 * np.pi) - np.pi)[:, axis] / per_rad) for e in (e1, e2)]
    cost = [(np.maximum(th - hi, 0.0) + np.maximum(lo - th, 0.0)).sum(axis=1) for th in cands]
    best = np.where((cost[1] < cost[0])[:, None], cands[1], cands[0])
    return np.asarray(np.clip(best, lo, hi))


def _initial_state(
    markers_m: FloatArray, joints_m: FloatArray, b: _Basis, prior: _Prior | None = None
) -> _State:
    """The reference body placed on each estimate: every rigid group's rotation from its
    estimated points (Kabsch), the angles from the groups' relative rotations, the root on
    the pelvis; the inverse kinematics that follows refines it."""
    pts = np.concatenate([markers_m, joints_m], axis=1)  # (P, 72, 3)
    p_n = len(pts)
    rots: list[FloatArray] = []
    angles = np.zeros((p_n, NUM_DOF))
    root_t = np.zeros((p_n, 3))
    for g in b.groups:
        rest = np.broadcast_to(b.rest_points_m[g.points], (p_n, len(g.points), 3))
        t_group = kabsch_batch(rest, pts[:, g.points])  # (P, 4, 4): rest body -> estimate
        r = t_group[:, :3, :3]
        rots.append(r)
        if g.parent >= 0:
            local = np.swapaxes(rots[g.parent], 1, 2) @ r
            angles[:, g.dofs] = _angles_from_local(local, g)
        else:  # the root's group carries the root joint to where the estimate has it
            root_t = np.einsum("pij,j->pi", r, b.rest_root_m) + t_group[:, :3, 3]
    if prior is None:
        prior = _Prior.of([None] * p_n, SolveOptions())
    return _State(
        root_r=torch.from_numpy(np.ascontiguousarray(rots[0])),
        root_t=torch.from_numpy(root_t),
        angles=torch.from_numpy(angles),
        z=prior.z_start.clone(),
        m_fix=prior.m_fix,
    )


def _standing_height_m(z: torch.Tensor) -> FloatArray:
    """The solved bodies' standing heights (P,), m: the vertical chain of their lengths."""
    b = _basis()
    chain = torch.tensor([LENGTH_FIELDS.index(k) for k in VERTICAL_CHAIN])
    lengths = b.f0[chain] * (1.0 + z[:, 2:][:, chain])
    return np.asarray((z[:, 0] * lengths.sum(1)).numpy())


def _selection_energy(q: _Posed, data: _Data, c: float) -> torch.Tensor:
    """The data terms at gate ``c``, unscaled (P,): how well each solution explains its cloud."""
    d2_m, d2_c = _nearest_d2(q, data)
    e_m, _ = _gm(d2_m, c)
    e_c, _ = _gm(d2_c, c)
    return ((e_m * data.seen(q.markers)).sum(1) + (e_c * data.mask).sum(1)) / (c * c)


#: The limb search's grids: per limb, the joint whose subtree moves, the DoF and the values
#: (degrees) of each, every combination tried; the other DoF of the limb (forearm
#: pronation, the ankle) keep their values. The head last (after the arms and legs).
_LIMB_GRIDS: tuple[tuple[str, tuple[tuple[str, tuple[float, ...]], ...]], ...] = (
    *(
        (
            f"{side.capitalize()}{'Arm' if arm else 'UpLeg'}",
            (
                (f"{side}_shoulder_flexion", (-30.0, 0.0, 45.0, 90.0, 135.0, 180.0)),
                (f"{side}_shoulder_abduction", (0.0, 45.0, 90.0, 135.0)),
                (f"{side}_shoulder_internal_rotation", (-60.0, 0.0, 60.0)),
                (f"{side}_elbow_flexion", (0.0, 60.0, 120.0)),
            )
            if arm
            else (
                (f"{side}_hip_flexion", (-20.0, 0.0, 40.0, 80.0, 120.0)),
                (f"{side}_hip_abduction", (-15.0, 0.0, 30.0)),
                (f"{side}_hip_internal_rotation", (-40.0, 0.0, 30.0)),
                (f"{side}_knee_flexion", (0.0, 45.0, 90.0, 135.0)),
            ),
        )
        for arm in (True, False)
        for side in ("left", "right")
    ),
    (
        "Neck",
        (
            ("neck_flexion", (-30.0, 0.0, 30.0)),
            ("neck_axial_rotation", (-60.0, -30.0, 0.0, 30.0, 60.0)),
        ),
    ),
)
#: Frames per batch of the limb search (each frame poses every candidate of a limb).
_LIMB_CHUNK = 16


@dataclass(frozen=True, slots=True)
class _Limb:
    dofs: torch.Tensor  # (K,) the DoF the grid sets
    grid: torch.Tensor  # (C, K) rad, within the limits
    # (1 + F, K) rad: none, then ± half the grid's step per DoF, every combination
    fine: torch.Tensor
    markers: torch.Tensor  # (53,) bool: the markers that move with the limb
    top: int  # the joint whose subtree moves
    marker_rows: torch.Tensor  # (m,): per moving marker, its joint's row in subtree_joints(top)


@functools.cache
def _limbs() -> tuple[_Limb, ...]:
    marker_joint = _basis().marker_joint.numpy()
    out = []
    for top, table in _LIMB_GRIDS:
        dofs = [DOF_NAMES.index(name) for name, _ in table]
        grid = np.deg2rad(np.array(list(itertools.product(*(v for _, v in table)))))
        grid = np.clip(grid, DOF_LIMITS_RAD[dofs, 0], DOF_LIMITS_RAD[dofs, 1])
        half = [np.deg2rad(np.diff(v).min() / 2.0) for _, v in table]
        fine = np.array(list(itertools.product(*((-h, 0.0, h) for h in half))))
        # "as it is" first, then every move
        fine = np.concatenate([np.zeros((1, len(dofs))), fine[np.abs(fine).sum(axis=1) > 0]])
        moving = _subtree(top)[marker_joint]
        row = {j: k for k, j in enumerate(subtree_joints(JOINTS.index(top)))}
        out.append(
            _Limb(
                dofs=torch.tensor(dofs),
                grid=torch.from_numpy(grid),
                fine=torch.from_numpy(fine),
                markers=torch.from_numpy(moving),
                top=JOINTS.index(top),
                marker_rows=torch.tensor([row[int(j)] for j in marker_joint[moving]]),
            )
        )
    return tuple(out)


def _limb_search(
    s: _State, data: _Data, coarse_gate_m: float, fine_gate_m: float, keep: tuple[int, ...]
) -> _State:
    """Each limb in turn: its grid's configurations (the limb as it is among them) scored by
    how well its markers explain the cloud at gate ``coarse_gate_m`` (the selection energy;
    the other markers held); the ``keep[0]`` best each moved by ± half a grid step per angle
    and scored at ``fine_gate_m``; the ``keep[1]`` best of those by ± a quarter step, and so
    on; the best of the last round kept."""
    b = _basis()
    angles = s.angles
    for limb in _limbs():
        # (P, 1 + C, 27): candidate 0 is the limb as it is
        cand = angles[:, None].repeat(1, limb.grid.shape[0] + 1, 1)
        cand[:, 1:, limb.dofs] = limb.grid
        e = _limb_energies(s, cand, data, limb, coarse_gate_m)
        for level, k in enumerate(keep):
            best = e.topk(min(k, cand.shape[1]), dim=1, largest=False).indices
            top = torch.gather(cand, 1, best[..., None].expand(-1, -1, NUM_DOF))
            moved = top[:, :, None].repeat(1, 1, limb.fine.shape[0], 1)
            moved[..., limb.dofs] = torch.clamp(
                moved[..., limb.dofs] + limb.fine * 0.5**level, b.lo[limb.dofs], b.hi[limb.dofs]
            )
            cand = moved.reshape(moved.shape[0], -1, NUM_DOF)
            e = _limb_energies(s, cand, data, limb, fine_gate_m)
        angles = cand[torch.arange(cand.shape[0]), e.argmin(dim=1)]
    return _State(s.root_r, s.root_t, angles, s.z, s.m_fix)


def _limb_energies(
    s: _State, cand: torch.Tensor, data: _Data, limb: _Limb, c: float
) -> torch.Tensor:
    """The selection energy at gate ``c`` (P, C) of candidate angles ``cand`` (P, C, 27) that
    differ from each other only in the limb's DoF (its markers move, the others are those of
    candidate 0)."""
    b = _basis()
    p_n, n_c = cand.shape[:2]
    out = torch.empty(p_n, n_c, dtype=torch.float64)
    parent = PARENTS[limb.top]
    for lo in range(0, p_n, _LIMB_CHUNK):
        hi = min(lo + _LIMB_CHUNK, p_n)
        p = hi - lo
        # Only the limb's subtree differs between candidates: the rest is posed once.
        base = _State(s.root_r[lo:hi], s.root_t[lo:hi], cand[lo:hi, 0], s.z[lo:hi], s.m_fix[lo:hi])
        q0 = _pose(base, b)
        off = base.z[:, 0:1, None] * torch.tensordot(q0.rel, b.d_off, 1)
        pos, rot = subtree_kinematics_torch(
            cand[lo:hi],
            off[:, None],
            q0.pos[:, None, parent],
            q0.rot[:, None, parent],
            top=limb.top,
        )
        r = limb.marker_rows
        m_off = q0.m_off[:, None, limb.markers]  # (p, 1, m, 3)
        moving = pos[:, :, r] + (rot[:, :, r] @ m_off[..., None])[..., 0]  # (p, C, m, 3)
        part = data.rows(lo, hi)
        cloud, mask = part.cloud, part.mask
        d = torch.cdist(moving.reshape(p, -1, 3), cloud).reshape(p, n_c, -1, cloud.shape[1])
        # each point's nearest marker: the held markers' (the same for every candidate)
        # (amin: torch's min-with-indices takes about twice as long)
        held = torch.cdist(q0.markers[:, ~limb.markers], cloud).amin(dim=1)  # (p, N)
        d_c = torch.minimum(d.amin(dim=2), held[:, None])
        e_m, _ = _gm(d.amin(dim=3) ** 2, c)
        e_c, _ = _gm(d_c**2, c)
        out[lo:hi] = (e_m * part.seen(moving)).sum(2) + (e_c * mask[:, None]).sum(2)
    return out


def _data(
    clouds: Sequence[FloatArray],
    tm: FloatArray,
    tj: FloatArray,
    views: _Views | None = None,
    prior: _Prior | None = None,
) -> _Data:
    """Problems' tensors; clouds padded with far points that no term sees (``prior``: the
    shape prior per problem, default the body model's)."""
    p_n = len(clouds)
    n = max(len(c) for c in clouds)
    cloud = np.full((p_n, n, 3), _FAR_M)
    mask = np.zeros((p_n, n))
    for i, c in enumerate(clouds):
        cloud[i, : len(c)] = c
        mask[i, : len(c)] = 1.0
    return _Data(
        cloud=torch.from_numpy(cloud),
        mask=torch.from_numpy(mask),
        tm=torch.from_numpy(np.ascontiguousarray(tm)),
        tj=torch.from_numpy(np.ascontiguousarray(tj)),
        prior=_Prior.of([None] * p_n, SolveOptions()) if prior is None else prior,
        views=views,
    )


def _schedule(
    opt: SolveOptions, *, gate_start_m: float | None = None, iterations: int | None = None
) -> list[_Weights]:
    """The solve's steps (``iterations``, default ``opt.iterations``): the gate shrinking
    geometrically from ``gate_start_m`` (default ``opt.gate_start_m``) to ``opt.gate_m``."""
    start = opt.gate_start_m if gate_start_m is None else gate_start_m
    n = opt.iterations if iterations is None else iterations
    k = max(n - 1, 1)
    return [
        _Weights(
            True,
            start * (opt.gate_m / start) ** min(i / k, 1.0),
            opt.data_sigma_m,
            opt.joint_prior_sigma_m,
            opt.marker_prior_sigma_m,
            opt.prior_gate_m,
        )
        for i in range(n)
    ]


def _run(
    clouds: Sequence[FloatArray],
    tm: FloatArray,
    tj: FloatArray,
    steps: Sequence[_Weights],
    opt: SolveOptions,
    prior: _Prior,
    *,
    start: _State | None = None,
    search_limbs: bool = False,
    views: _Views | None = None,
) -> tuple[_State, torch.Tensor]:
    """``steps`` of LM on each problem, in chunks, from ``start`` (None: the first guess and
    the inverse kinematics; ``search_limbs``: the limb search first) -> the states and their
    selection energies."""
    b = _basis()
    states, energies = [], []
    for lo in range(0, len(clouds), _CHUNK):
        hi = min(lo + _CHUNK, len(clouds))
        rig = None if views is None else views.rows(lo, hi)
        part = prior.rows(lo, hi)
        data = _data(clouds[lo:hi], tm[lo:hi], tj[lo:hi], rig, part)
        if start is None:
            s = _initial_state(tm[lo:hi], tj[lo:hi], b, part)
            init = _Weights(False, 0.0, 1.0, 0.03, 0.03, None)
            s = _levenberg_marquardt(s, data, [init] * opt.init_iterations, opt, b)
        else:
            s = start.take(torch.arange(lo, hi))
        if search_limbs:
            s = _limb_search(s, data, opt.limb_gate_m, opt.limb_fine_gate_m, opt.limb_keep)
        s = _levenberg_marquardt(s, data, steps, opt, b)
        states.append(s)
        energies.append(_selection_energy(_pose(s, b), data, opt.selection_gate_m))
    return _State.cat(states), torch.cat(energies)


def solve_skeleton(
    clouds: Sequence[npt.ArrayLike],
    markers_m: npt.ArrayLike,
    joints_m: npt.ArrayLike,
    *,
    options: SolveOptions | None = None,
    views: Sequence[Sequence[Camera]] | None = None,
    crop_box_m: Box | None = None,
    subjects: Sequence[SubjectCalibration | None] | None = None,
    pose_prior: PosePrior | None = None,
) -> SolveResult:
    """Fit the body model to each fused cloud from H hypotheses of the network (module doc).

    Args:
        clouds: B fused clouds (N_i, 3), world, m (at least 2 points each).
        markers_m: (H, B, 53, 3) the hypotheses' markers, world, m.
        joints_m: (H, B, 19, 3) their DeMoCap joints.
        options: weights and schedule (default :class:`SolveOptions`).
        views: per cloud, the calibrated cameras that made it (the rig): a model marker
            outside every camera's view is not charged for having no point near it (hands
            over the head above the view's top edge). None: every marker counts as seen.
        crop_box_m: with ``views``, the world box ``((x0, x1), (y0, y1), (z0, z1))`` (m) the
            clouds were cropped to: a marker outside it is not charged either (no point of
            it could have survived the crop). None: no crop.
        subjects: per cloud, its subject's calibration (:func:`calibrate_subject`) or None.
        pose_prior: the prior over the joint angles (:mod:`.pose_prior`), added at
            ``options.pose_prior_weight`` to every step that sees the cloud; None: none.

    Raises:
        ValidationError: shapes that do not match, non-finite values, a cloud with fewer
            than 2 points, ``views`` not one entry per cloud, or a ``crop_box_m`` that is not
            three (low < high) pairs or comes without ``views``.
    """
    opt = options or SolveOptions()
    if subjects is not None and len(subjects) != len(clouds):
        msg = f"subjects has {len(subjects)} entries for {len(clouds)} clouds; give one per cloud"
        raise ValidationError(msg)
    if crop_box_m is not None:
        check_crop_box(crop_box_m)
        if views is None:
            msg = "crop_box_m needs views: the crop box is tested with the rig's cameras"
            raise ValidationError(msg)
    pts = [
        np.asarray(check_finite(check_shape(c, ["N", 3], name="cloud")), np.float64) for c in clouds
    ]
    n_b = len(pts)
    tm = np.asarray(
        check_finite(check_shape(markers_m, ["H", n_b, NUM_MARKERS, 3], name="markers_m")),
        np.float64,
    )
    tj = np.asarray(
        check_finite(
            check_shape(joints_m, [tm.shape[0], n_b, len(DEMOCAP_JOINT_INDEX), 3], name="joints_m")
        ),
        np.float64,
    )
    if views is not None and len(views) != n_b:
        msg = f"views has {len(views)} entries for {n_b} clouds; give one camera list per cloud"
        raise ValidationError(msg)
    for i, p in enumerate(pts):
        if p.shape[0] < 2:
            msg = f"cloud {i} has {p.shape[0]} point(s); the skeleton solve needs at least 2"
            raise ValidationError(msg)
    if n_b and opt.bend_starts_rad:
        b = _basis()
        extra = [_bent(tm[h], tj[h], a, b) for a in opt.bend_starts_rad for h in range(len(tm))]
        tm = np.concatenate([tm, np.stack([e[0] for e in extra])])
        tj = np.concatenate([tj, np.stack([e[1] for e in extra])])
    n_h = tm.shape[0]
    if n_b == 0:
        empty = np.zeros((0,))
        return SolveResult(
            markers_m=np.zeros((0, NUM_MARKERS, 3)),
            joints_m=np.zeros((0, len(DEMOCAP_JOINT_INDEX), 3)),
            poses=np.zeros((0, ROOT_DIM + NUM_DOF)),
            height_m=empty,
            energy=empty,
            hypothesis=np.zeros((0,), np.int64),
            shape_z=np.zeros((0, _NS)),
        )
    # Problems: every (start, frame) pair, start-major. All starts take the first steps; then
    # only the ``keep_starts`` best of each frame go on (most starts end where another does).
    frames = np.tile(np.arange(n_b), n_h)
    flat_clouds = [pts[i] for i in frames]
    rig = None if views is None else _Views.of(views, crop_box_m)  # (B, K) cameras, once
    flat_views = None if rig is None else rig.take(frames)
    flat_m, flat_j = tm.reshape(n_h * n_b, NUM_MARKERS, 3), tj.reshape(n_h * n_b, -1, 3)
    prior = _Prior.of(list(subjects) if subjects is not None else [None] * n_b, opt, pose_prior)
    flat_prior = prior.take(frames)
    steps = _schedule(opt)
    cut = min(opt.prune_after, len(steps)) if n_h > opt.keep_starts else len(steps)
    s_all, e_all = _run(flat_clouds, flat_m, flat_j, steps[:cut], opt, flat_prior, views=flat_views)
    alive = np.arange(n_h * n_b)
    if cut < len(steps):
        order = np.argsort(e_all.numpy().reshape(n_h, n_b), axis=0, kind="stable")
        alive = np.sort((order[: opt.keep_starts] * n_b + np.arange(n_b)).reshape(-1))
        sel = torch.from_numpy(alive)
        s_all, e_alive = _run(
            [flat_clouds[i] for i in alive],
            flat_m[alive],
            flat_j[alive],
            steps[cut:],
            opt,
            flat_prior.take(alive),
            start=s_all.take(sel),
            views=None if flat_views is None else flat_views.take(alive),
        )
        e_all = torch.full((n_h * n_b,), float("inf"), dtype=torch.float64)
        e_all[sel] = e_alive
    else:
        s_all = s_all.take(torch.from_numpy(alive))
    energy = e_all.numpy().reshape(n_h, n_b)
    best = np.argmin(energy, axis=0)
    # the winners' rows among the survivors
    won = best * n_b + np.arange(n_b)
    s_best = s_all.take(torch.from_numpy(np.searchsorted(alive, won)))
    e_best = torch.from_numpy(energy[best, np.arange(n_b)].copy())
    if opt.limb_search:
        s_best, e_best = _search_limbs(
            pts, flat_m[won], flat_j[won], s_best, e_best, opt, prior, views=rig
        )
    q = _pose(s_best, _basis())
    return SolveResult(
        markers_m=q.markers.numpy(),
        joints_m=q.joints.numpy(),
        poses=s_best.poses(),
        height_m=_standing_height_m(s_best.z),
        energy=e_best.numpy(),
        hypothesis=best.astype(np.int64),
        shape_z=s_best.z.numpy().copy(),
    )


def calibrate_subject(
    clouds: Sequence[npt.ArrayLike],
    result: SolveResult,
    *,
    views: Sequence[Sequence[Camera]] | None = None,
    crop_box_m: Box | None = None,
    previous: SubjectCalibration | None = None,
    match_m: float = 0.03,
) -> SubjectCalibration:
    """One subject's calibration from frames of them solved one by one (``result`` of
    :func:`solve_skeleton` on ``clouds``; ``previous``: the calibration that solve was given).

    What a marker-based system does with a range-of-motion take, from any frames: the half
    of the frames whose clouds the solve explains best (energy per point) vote; the shape is
    the median of their segment lengths, girth and height; each marker's offset is moved by
    the median, over the frames where it is matched, of its residual to the cloud point
    nearest it (within ``match_m``, the point's nearest marker being it too, where a camera
    sees it), in its segment's frame. A marker matched in fewer than a third of the voting
    frames (at least 2) keeps its offset.

    Raises:
        ValidationError: fewer than 3 frames, or ``result`` not of these clouds.
    """
    pts = [
        np.asarray(check_finite(check_shape(c, ["N", 3], name="cloud")), np.float64) for c in clouds
    ]
    n = len(pts)
    if n < 3:
        msg = f"a subject calibration needs at least 3 solved frames, got {n}"
        raise ValidationError(msg)
    if result.shape_z.shape != (n, _NS):
        msg = f"result holds {len(result.shape_z)} frames for {n} clouds; give the solve of these"
        raise ValidationError(msg)
    score = result.energy / np.array([len(p) for p in pts])
    vote = np.flatnonzero(score <= np.median(score))
    b = _basis()
    z = result.shape_z[vote]
    f0 = b.f0.numpy()
    h = float(np.median(z[:, 0]))
    lengths = np.median(f0[:_NL] * z[:, :1] * (1.0 + z[:, 2:]), axis=0)
    girth = float(np.median(z[:, 0] * z[:, 1])) / h
    shape = np.concatenate([[h, girth], lengths / (f0[:_NL] * h) - 1.0])
    fix = np.zeros((NUM_MARKERS, 3)) if previous is None else previous.marker_offsets_m.copy()
    poses = result.poses[vote]
    state = _State(
        root_r=torch.from_numpy(Rotation.from_rotvec(poses[:, :3]).as_matrix()),
        root_t=torch.from_numpy(poses[:, 3:6].copy()),
        angles=torch.from_numpy(poses[:, ROOT_DIM:].copy()),
        z=torch.from_numpy(z.copy()),
        m_fix=torch.from_numpy(np.broadcast_to(fix, (len(vote), NUM_MARKERS, 3)).copy()),
    )
    q = _pose(state, b)
    picked = [pts[int(i)] for i in vote]
    rig = None if views is None else _Views.of([views[int(i)] for i in vote], crop_box_m)
    data = _data(picked, q.markers.numpy(), q.joints.numpy(), rig)
    d_m, nn_m, _, nn_c = _nearest(q, data)
    mutual = torch.gather(nn_c, 1, nn_m) == torch.arange(NUM_MARKERS)
    ok = (mutual & (d_m < match_m) & (data.seen(q.markers) > 0)).numpy()
    near = torch.gather(data.cloud, 1, nn_m[..., None].expand(-1, -1, 3))
    rot = q.rot[:, b.marker_joint]  # (V, 53, 3, 3)
    local = (rot.transpose(-1, -2) @ (near - q.markers)[..., None])[..., 0].numpy()
    need = max(2, int(np.ceil(len(vote) / 3)))
    for m in range(NUM_MARKERS):
        rows = ok[:, m]
        if rows.sum() >= need:
            fix[m] += np.median(local[rows, m], axis=0)
    return SubjectCalibration(shape_z=shape, marker_offsets_m=fix, frames=n)


def _search_limbs(
    clouds: Sequence[FloatArray],
    tm: FloatArray,
    tj: FloatArray,
    s: _State,
    energy: torch.Tensor,
    opt: SolveOptions,
    prior: _Prior,
    *,
    views: _Views | None = None,
) -> tuple[_State, torch.Tensor]:
    """The limb search and its refinement (:attr:`SolveOptions.limb_search`) from the
    solutions ``s`` with selection energies ``energy`` (B,); a frame keeps the better."""
    steps = _schedule(opt, gate_start_m=opt.refine_gate_start_m, iterations=opt.refine_iterations)
    s_new, e_new = _run(clouds, tm, tj, steps, opt, prior, start=s, search_limbs=True, views=views)
    better = e_new < energy
    return s_new.where(better, s), torch.where(better, e_new, energy)
