"""The 53-marker DeMoCap set: names in canonical order, segments and skin-surface offsets.

Canonical order (democap-method.md §6.1): indices 0–50 are the 51 markers every subject has,
alphabetical; 51–52 are the two waist markers of the subject's variant, ``MBWT, MFWT`` (S1, S4)
or ``LMWT, RMWT`` (S2, S3).

Placement follows the standard Vicon full-body labels as read in the method notes. Each marker
rides on one joint frame and sits on the skin of one body capsule (:mod:`process.body.surface`):
it is placed where a ray from an anatomical anchor inside the body leaves that capsule, then
moved out along the skin normal by the marker radius (default 7 mm). The rest pose has the
palms facing the thighs (thumbs forward), so the radial (thumb-side, "outer") wrist and hand
markers OWR/OHAND point forward and the ulnar (inner) ones IWR/IHAND backwards; ELB/KNE/ANK are
lateral, IEL/KNI medial.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
import numpy.typing as npt
import torch

from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body._capsule_math import closest_on_segment, ray_capsule
from mocaprig.process.body.kinematics import Kinematics, forward_kinematics
from mocaprig.process.body.shape import BodyShape, rest_joint_positions
from mocaprig.process.body.skeleton import JOINT_INDEX
from mocaprig.process.body.surface import CAPSULE_INDEX, capsule_template
from mocaprig.validation import check_positive, check_shape

__all__ = [
    "COMMON_MARKERS",
    "MARKER_NAMES",
    "NUM_MARKERS",
    "WAIST_VARIANTS",
    "MarkerSet",
    "WaistVariant",
    "marker_positions",
    "marker_positions_torch",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: The 51 markers every subject has, in canonical (alphabetical) order, indices 0–50.
COMMON_MARKERS: tuple[str, ...] = (
    "ARIEL", "C7", "CLAV",
    "LANK", "LBHD", "LBSH", "LBWT", "LELB", "LFHD", "LFRM", "LFSH", "LFWT", "LHEL", "LIEL",
    "LIHAND", "LIWR", "LKNE", "LKNI", "LMT1", "LMT5", "LOHAND", "LOWR", "LSHN", "LTHI", "LTOE",
    "LUPA",
    "RANK", "RBHD", "RBSH", "RBWT", "RELB", "RFHD", "RFRM", "RFSH", "RFWT", "RHEL", "RIEL",
    "RIHAND", "RIWR", "RKNE", "RKNI", "RMT1", "RMT5", "ROHAND", "ROWR", "RSHN", "RTHI", "RTOE",
    "RUPA",
    "STRN", "T10",
)  # fmt: skip

WaistVariant = Literal["MBWT_MFWT", "LMWT_RMWT"]
#: The two subject-specific waist markers (indices 51, 52) of each variant.
WAIST_VARIANTS: dict[WaistVariant, tuple[str, str]] = {
    "MBWT_MFWT": ("MBWT", "MFWT"),
    "LMWT_RMWT": ("LMWT", "RMWT"),
}
#: The default 53 names (waist variant ``MBWT_MFWT``).
MARKER_NAMES: tuple[str, ...] = COMMON_MARKERS + WAIST_VARIANTS["MBWT_MFWT"]
NUM_MARKERS = 53

# Placement table: name (right side for bilateral markers, "R" prefix) -> (joint, capsule,
# anchor, outward direction). The anchor is a point inside the capsule, in the rest-pose body
# frame: ``("axis", t)`` is the capsule axis at fraction t from a to b; ``("joint", name)``
# a joint's rest position; either plus a small shift in capsule radii.
_Anchor = tuple[str, float | str, tuple[float, float, float]]
_NONE = (0.0, 0.0, 0.0)
_PLACEMENT: dict[str, tuple[str, str, _Anchor, tuple[float, float, float]]] = {
    # head
    "ARIEL": ("Head", "head", ("axis", 1.0, _NONE), (0.0, 0.0, 1.0)),
    "RFHD": ("Head", "head", ("axis", 1.0, (0.0, 0.0, -0.3)), (0.45, 0.85, 0.2)),
    "RBHD": ("Head", "head", ("axis", 1.0, (0.0, 0.0, -0.3)), (0.45, -0.85, 0.2)),
    # trunk: C7 and the jugular notch ride on the chest, just below the neck base
    "C7": ("Spine2", "chest", ("joint", "Neck", (0.0, 0.0, -0.25)), (0.0, -1.0, 0.25)),
    "CLAV": ("Spine2", "chest", ("joint", "Neck", (0.0, 0.0, -0.25)), (0.0, 1.0, 0.1)),
    "STRN": ("Spine2", "chest", ("joint", "Spine2", (0.0, 0.0, 0.3)), (0.0, 1.0, 0.0)),
    "T10": ("Spine1", "thorax", ("axis", 0.5, _NONE), (0.0, -1.0, 0.0)),
    # pelvis: ASIS (FWT), PSIS (BWT), mid front/back and sides of the waist
    "RFWT": ("Hips", "pelvis", ("axis", 1.0, (0.0, 0.0, 0.3)), (0.3, 1.0, 0.0)),
    "RBWT": ("Hips", "pelvis", ("axis", 0.75, (0.0, 0.0, 0.3)), (0.15, -1.0, 0.0)),
    "MFWT": ("Hips", "abdomen", ("axis", 0.0, (0.0, 0.0, 0.3)), (0.0, 1.0, 0.0)),
    "MBWT": ("Hips", "abdomen", ("axis", 0.0, (0.0, 0.0, 0.3)), (0.0, -1.0, 0.0)),
    "RMWT": ("Hips", "pelvis", ("axis", 1.0, (0.0, 0.0, 0.3)), (1.0, 0.0, 0.0)),
    # shoulder girdle (fixed to the chest in this skeleton)
    "RFSH": ("RightShoulder", "right_clavicle", ("axis", 0.8, _NONE), (0.15, 1.0, 0.35)),
    "RBSH": ("RightShoulder", "right_clavicle", ("axis", 0.8, _NONE), (0.15, -1.0, 0.35)),
    # arm: lateral upper arm; epicondyles on the humerus at the elbow axis
    "RUPA": ("RightArm", "right_upper_arm", ("axis", 0.5, _NONE), (1.0, -0.35, 0.0)),
    "RELB": ("RightArm", "right_upper_arm", ("axis", 1.0, _NONE), (1.0, 0.0, 0.0)),
    "RIEL": ("RightArm", "right_upper_arm", ("axis", 1.0, _NONE), (-1.0, 0.0, 0.0)),
    "RFRM": ("RightForeArm", "right_forearm", ("axis", 0.55, _NONE), (1.0, -0.35, 0.0)),
    "ROWR": ("RightForeArm", "right_forearm", ("axis", 1.0, _NONE), (0.0, 1.0, 0.0)),
    "RIWR": ("RightForeArm", "right_forearm", ("axis", 1.0, _NONE), (0.0, -1.0, 0.0)),
    "ROHAND": ("RightHand", "right_hand", ("joint", "RightHandEnd", _NONE), (0.4, 1.0, 0.0)),
    "RIHAND": ("RightHand", "right_hand", ("joint", "RightHandEnd", _NONE), (0.4, -1.0, 0.0)),
    # leg: lateral thigh (lower third, below the fingertips); femoral epicondyles on the knee
    # sphere of the shank capsule, which is centred on the knee axis and so rigid with the
    # thigh too; shin; lateral malleolus
    "RTHI": ("RightUpLeg", "right_thigh", ("joint", "RightLeg", (0.0, 0.0, 1.2)), (1.0, 0.25, 0.0)),
    "RKNE": ("RightUpLeg", "right_shank", ("axis", 0.0, _NONE), (1.0, 0.0, 0.0)),
    "RKNI": ("RightUpLeg", "right_shank", ("axis", 0.0, _NONE), (-1.0, 0.0, 0.0)),
    "RSHN": ("RightLeg", "right_shank", ("axis", 0.45, _NONE), (0.3, 1.0, 0.0)),
    "RANK": ("RightLeg", "right_shank", ("axis", 1.0, _NONE), (1.0, 0.0, 0.0)),
    # foot: heel, 1st/5th metatarsal heads (medial/lateral, on top), toes
    "RHEL": ("RightFoot", "right_foot", ("axis", 0.0, _NONE), (0.0, -1.0, 0.35)),
    "RMT1": ("RightFoot", "right_foot", ("axis", 1.0, _NONE), (-1.0, 0.3, 0.6)),
    "RMT5": ("RightFoot", "right_foot", ("axis", 1.0, _NONE), (1.0, 0.3, 0.6)),
    "RTOE": ("RightToeBase", "right_toe", ("axis", 0.5, _NONE), (0.0, 0.2, 1.0)),
}


def _spec(name: str) -> tuple[str, bool]:
    """The placement-table key of a marker and whether it mirrors that entry (left side)."""
    if name in _PLACEMENT:
        return name, False
    if name.startswith("L") and "R" + name[1:] in _PLACEMENT:
        return "R" + name[1:], True
    msg = f"no placement for marker {name!r}"  # pragma: no cover - table typo
    raise ProcessingError(msg)


def _mirror_name(name: str) -> str:
    return name.replace("Right", "Left").replace("right_", "left_")


@dataclass(frozen=True, slots=True, eq=False)
class MarkerSet:
    """A marker set placed on one body shape.

    Attributes:
        names: marker names (M,) in canonical order (M = 53 for the DeMoCap set).
        joint_index: joint each marker rides on (M,).
        offsets_m: marker centre in its joint's frame (M, 3), metres.
        normals: unit outward skin normal under each marker, joint frame (M, 3).
        capsule_index: the body capsule whose skin the marker sits on (M,).
        surface_a_m, surface_b_m, surface_radius_m: that capsule in the marker's joint frame
            ((M, 3), (M, 3), (M,)), metres; it moves rigidly with the marker's joint.
        marker_radius_m: marker sphere radius; centres sit this far off the skin (m).

    Raises:
        ValidationError: inconsistent array shapes.
    """

    names: tuple[str, ...]
    joint_index: IntArray
    offsets_m: FloatArray
    normals: FloatArray
    capsule_index: IntArray
    surface_a_m: FloatArray
    surface_b_m: FloatArray
    surface_radius_m: FloatArray
    marker_radius_m: float

    def __post_init__(self) -> None:
        m = len(self.names)
        check_shape(self.joint_index, [m], name="MarkerSet.joint_index")
        check_shape(self.offsets_m, [m, 3], name="MarkerSet.offsets_m")
        check_shape(self.normals, [m, 3], name="MarkerSet.normals")
        check_shape(self.capsule_index, [m], name="MarkerSet.capsule_index")
        check_shape(self.surface_a_m, [m, 3], name="MarkerSet.surface_a_m")
        check_shape(self.surface_b_m, [m, 3], name="MarkerSet.surface_b_m")
        check_shape(self.surface_radius_m, [m], name="MarkerSet.surface_radius_m")
        if len(set(self.names)) != m:
            msg = "MarkerSet.names has duplicates"
            raise ValidationError(msg)

    @classmethod
    def for_shape(
        cls,
        shape: BodyShape,
        *,
        waist: WaistVariant = "MBWT_MFWT",
        marker_radius_m: float = 0.007,
    ) -> MarkerSet:
        """The 53 DeMoCap markers on ``shape``'s skin, in canonical order.

        Args:
            shape: the subject.
            waist: which pair stands at indices 51–52: ``"MBWT_MFWT"`` or ``"LMWT_RMWT"``.
            marker_radius_m: marker sphere radius (m).

        Raises:
            ValidationError: unknown ``waist`` or a non-positive radius.
            ProcessingError: an anchor falls outside its capsule (a degenerate shape).
        """
        if waist not in WAIST_VARIANTS:
            msg = f"waist must be one of {sorted(WAIST_VARIANTS)}, got {waist!r}"
            raise ValidationError(msg)
        mr = check_positive(float(marker_radius_m), name="marker_radius_m")
        names = COMMON_MARKERS + WAIST_VARIANTS[waist]
        tmpl = capsule_template(shape)
        rest = rest_joint_positions(shape)
        # Rest-pose capsules in the body frame (all joint frames are axis-aligned at rest).
        cap_a = rest[tmpl.joint] + tmpl.a_local_m
        cap_b = rest[tmpl.joint] + tmpl.b_local_m
        joints, offsets, normals, cap_ids = [], [], [], []
        flip = np.array([-1.0, 1.0, 1.0])
        for name in names:
            key, mirrored = _spec(name)
            joint, cap_name, (kind, where, shift), direction = _PLACEMENT[key]
            # Place the right-side marker, then mirror its anchor and direction in x: the rest
            # body is symmetric, so the left marker is the mirror image.
            c = CAPSULE_INDEX[cap_name]
            a, b = cap_a[c], cap_b[c]
            if kind == "axis":
                anchor = a + float(where) * (b - a)
            else:
                anchor = rest[JOINT_INDEX[str(where)]].copy()
            anchor = anchor + float(tmpl.radius_m[c]) * np.asarray(shift)
            d = np.asarray(direction, dtype=np.float64)
            if mirrored:
                joint, cap_name = _mirror_name(joint), _mirror_name(cap_name)
                c = CAPSULE_INDEX[cap_name]
                anchor, d = anchor * flip, d * flip
            a, b, r = cap_a[c], cap_b[c], float(tmpl.radius_m[c])
            if np.linalg.norm(anchor - closest_on_segment(anchor, a, b)) >= r:
                msg = f"marker {name}: anchor lies outside capsule {cap_name}; check the shape"
                raise ProcessingError(msg)
            d = d / np.linalg.norm(d)
            t = ray_capsule(anchor, d[None], a, b, r, 0.0)[0]
            skin = anchor + t * d
            n = skin - closest_on_segment(skin, a, b)
            n = n / np.linalg.norm(n)
            j = JOINT_INDEX[joint]
            joints.append(j)
            offsets.append(skin + mr * n - rest[j])
            normals.append(n)
            cap_ids.append(c)
        joint_arr = np.array(joints, dtype=np.int64)
        cap_arr = np.array(cap_ids, dtype=np.int64)
        return cls(
            names=names,
            joint_index=joint_arr,
            offsets_m=np.array(offsets),
            normals=np.array(normals),
            capsule_index=cap_arr,
            surface_a_m=cap_a[cap_arr] - rest[joint_arr],
            surface_b_m=cap_b[cap_arr] - rest[joint_arr],
            surface_radius_m=tmpl.radius_m[cap_arr].copy(),
            marker_radius_m=mr,
        )

    def jittered(self, rng: np.random.Generator, *, sigma_m: float = 0.01) -> MarkerSet:
        """A copy with each marker moved along the skin by a random tangential offset.

        The offset is Gaussian (``sigma_m`` per tangential axis, m); the marker is then put
        back at ``marker_radius_m`` off its capsule's skin, so it stays on the body.
        """
        sigma = float(sigma_m)
        if not np.isfinite(sigma) or sigma < 0:
            msg = f"sigma_m must be a finite number >= 0, got {sigma_m!r}"
            raise ValidationError(msg)
        g = rng.normal(0.0, sigma, self.offsets_m.shape)
        g = g - np.sum(g * self.normals, axis=-1, keepdims=True) * self.normals
        p = self.offsets_m + g
        q = closest_on_segment(p, self.surface_a_m, self.surface_b_m)
        n = p - q
        norm = np.linalg.norm(n, axis=-1, keepdims=True)
        n = np.where(norm > 1e-9, n / np.where(norm > 0, norm, 1.0), self.normals)
        offsets = q + n * (self.surface_radius_m + self.marker_radius_m)[:, None]
        return replace(self, offsets_m=offsets, normals=n)


def marker_positions(
    kin_or_pose: Kinematics | npt.ArrayLike, shape: BodyShape, markers: MarkerSet
) -> FloatArray:
    """World marker positions (..., M, 3), m, from a :class:`Kinematics` or poses (..., 33).

    ``shape`` is used to run forward kinematics when poses are given; the marker offsets come
    from ``markers`` (built for that shape).
    """
    kin = (
        kin_or_pose
        if isinstance(kin_or_pose, Kinematics)
        else forward_kinematics(kin_or_pose, shape)
    )
    j = markers.joint_index
    rot = kin.rotations[..., j, :, :]
    return np.asarray(kin.positions_m[..., j, :] + (rot @ markers.offsets_m[..., None])[..., 0])


def marker_positions_torch(
    positions: torch.Tensor, rotations: torch.Tensor, markers: MarkerSet
) -> torch.Tensor:
    """:func:`marker_positions` from :func:`forward_kinematics_torch` outputs -> (..., M, 3)."""
    off = torch.as_tensor(markers.offsets_m, dtype=positions.dtype, device=positions.device)
    j = torch.as_tensor(markers.joint_index, device=positions.device)
    rot = rotations.index_select(-3, j)
    return positions.index_select(-2, j) + (rot @ off[..., None])[..., 0]
