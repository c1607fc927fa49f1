"""Body shape: segment lengths and capsule radii from standing height, and the rest offsets.

Proportions follow Drillis & Contini as reproduced in Winter, *Biomechanics and Motor Control of
Human Movement*, Fig. 4.1 (fractions of the standing height H). The figure's landmark heights
are consistent with its segment lengths and fix the vertical chain::

    ankle 0.039H  knee 0.285H  hip (trochanter) 0.530H  shoulder (acromion) 0.818H
    chin 0.870H   eye 0.936H   top of head 1.000H

    upper arm 0.186H = 0.818 - 0.632 (elbow ~0.630H)   forearm 0.146H   hand 0.108H
    thigh 0.245H = 0.530 - 0.285                      shank 0.246H = 0.285 - 0.039
    foot length 0.152H, shoulder width 0.259H, hip width 0.191H

The figure does not split the trunk, neck and head; our split (fractions of H) puts the pelvis
centre 0.025H above the hip joints (0.555H), Spine1 at 0.655H (lumbar 0.100H), Spine2 at 0.735H
(thorax 0.080H, about nipple height 0.72H), Neck at C7 0.830H (chest 0.095H, just above the
acromion), Head at the atlanto-occipital joint 0.910H (neck 0.080H, ear level between chin and
eye) and HeadEnd at 1.000H (head 0.090H). These sum to exactly 1, so the rest pose stands
``height_m`` tall, floor to HeadEnd, with flat feet.

All lengths are metres. Rest offsets are expressed in the parent joint's frame; every joint
frame is aligned with the body axes in the rest pose (+X subject's right, +Y forward, +Z up), so
at rest the parent frame and the body frame coincide.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields

import numpy as np
import numpy.typing as npt

from mocaprig.errors import ValidationError
from mocaprig.process.body.skeleton import JOINT_INDEX, JOINTS, PARENTS
from mocaprig.validation import check_positive

__all__ = [
    "DRILLIS_CONTINI_FRACTIONS",
    "HEEL_FRACTION",
    "LENGTH_FIELDS",
    "RADIUS_FIELDS",
    "VERTICAL_CHAIN",
    "BodyShape",
    "rest_joint_positions",
    "rest_offsets",
]

#: Segment lengths as fractions of the standing height (Drillis & Contini; trunk split ours).
DRILLIS_CONTINI_FRACTIONS: Mapping[str, float] = {
    "ankle_height_m": 0.039,
    "shank_length_m": 0.246,
    "thigh_length_m": 0.245,
    "pelvis_height_m": 0.025,
    "lumbar_length_m": 0.100,
    "thorax_length_m": 0.080,
    "chest_length_m": 0.095,
    "neck_length_m": 0.080,
    "head_length_m": 0.090,
    "hip_width_m": 0.191,
    "shoulder_width_m": 0.259,
    "upper_arm_length_m": 0.186,
    "forearm_length_m": 0.146,
    "hand_length_m": 0.108,
    "foot_length_m": 0.152,
}

#: Capsule radii as fractions of the standing height (ours, fitted to adult girths:
#: head 17 cm wide, upper arm 9 cm, thigh 16 cm, calf 10.5 cm for H = 1.75 m).
_RADIUS_FRACTIONS: Mapping[str, float] = {
    "head_radius_m": 0.050,
    "neck_radius_m": 0.028,
    "chest_radius_m": 0.066,
    "abdomen_radius_m": 0.062,
    "pelvis_radius_m": 0.058,
    "clavicle_radius_m": 0.022,
    "upper_arm_radius_m": 0.025,
    "forearm_radius_m": 0.020,
    "hand_radius_m": 0.014,
    "thigh_radius_m": 0.045,
    "shank_radius_m": 0.030,
    "foot_radius_m": 0.018,
    "toe_radius_m": 0.012,
}

#: The segments stacked floor -> HeadEnd in the rest pose; their sum is the standing height.
VERTICAL_CHAIN: tuple[str, ...] = (
    "ankle_height_m",
    "shank_length_m",
    "thigh_length_m",
    "pelvis_height_m",
    "lumbar_length_m",
    "thorax_length_m",
    "chest_length_m",
    "neck_length_m",
    "head_length_m",
)
LENGTH_FIELDS: tuple[str, ...] = tuple(DRILLIS_CONTINI_FRACTIONS)
RADIUS_FIELDS: tuple[str, ...] = tuple(_RADIUS_FRACTIONS)

# Fixed fractions of the foot length: heel behind the ankle, ball of the foot (MTP joints) in
# front of it, toes beyond (heel-to-MTP ~0.72 of the foot length in adults).
HEEL_FRACTION = 0.20
BALL_FRACTION = 0.52
TOE_FRACTION = 0.28
# Hip joint centres sit 0.55 of the bi-trochanteric width apart (~0.18 m at H = 1.75 m);
# gleno-humeral centres 0.80 of the shoulder width apart (~0.36 m).
HIP_JOINT_SPACING_FRACTION = 0.55
SHOULDER_JOINT_SPACING_FRACTION = 0.80
# Knuckles (MCP joints, the HandEnd joint) along the wrist-to-fingertip hand length.
KNUCKLE_FRACTION = 0.55


@dataclass(frozen=True, slots=True)
class BodyShape:
    """Segment lengths and capsule radii of one subject (metres).

    ``height_m`` is the standing height of the rest pose, floor to HeadEnd with flat feet; it
    must equal the sum of :data:`VERTICAL_CHAIN` (checked to 1 mm). Widths are full widths:
    ``hip_width_m`` bi-trochanteric, ``shoulder_width_m`` bi-acromial (deltoid) breadth.
    ``hand_length_m`` runs wrist to fingertip, ``foot_length_m`` heel to toe tip.

    Raises:
        ValidationError: a value is not a finite positive number, the vertical chain does not
            add up to ``height_m``, or the foot radii do not fit under the ankle.
    """

    height_m: float
    ankle_height_m: float
    shank_length_m: float
    thigh_length_m: float
    pelvis_height_m: float
    lumbar_length_m: float
    thorax_length_m: float
    chest_length_m: float
    neck_length_m: float
    head_length_m: float
    hip_width_m: float
    shoulder_width_m: float
    upper_arm_length_m: float
    forearm_length_m: float
    hand_length_m: float
    foot_length_m: float
    head_radius_m: float
    neck_radius_m: float
    chest_radius_m: float
    abdomen_radius_m: float
    pelvis_radius_m: float
    clavicle_radius_m: float
    upper_arm_radius_m: float
    forearm_radius_m: float
    hand_radius_m: float
    thigh_radius_m: float
    shank_radius_m: float
    foot_radius_m: float
    toe_radius_m: float

    def __post_init__(self) -> None:
        for f in fields(self):
            check_positive(float(getattr(self, f.name)), name=f"BodyShape.{f.name}")
        chain = sum(float(getattr(self, name)) for name in VERTICAL_CHAIN)
        if abs(chain - self.height_m) > 1e-3:
            msg = (
                f"BodyShape: the vertical chain {'+'.join(VERTICAL_CHAIN)} sums to "
                f"{chain:.4f} m but height_m is {self.height_m:.4f} m; build shapes with "
                "BodyShape.from_height or keep the chain consistent"
            )
            raise ValidationError(msg)
        if not self.toe_radius_m <= self.foot_radius_m < self.ankle_height_m:
            msg = (
                "BodyShape: need toe_radius_m <= foot_radius_m < ankle_height_m so the sole "
                f"fits under the ankle, got {self.toe_radius_m:.4f}, {self.foot_radius_m:.4f}, "
                f"{self.ankle_height_m:.4f} m"
            )
            raise ValidationError(msg)

    @classmethod
    def from_height(
        cls,
        height_m: float,
        *,
        segment_scale: Mapping[str, float] | None = None,
        radius_scale: float | Mapping[str, float] = 1.0,
    ) -> BodyShape:
        """The Drillis & Contini body of standing height ``height_m`` (m).

        Args:
            height_m: standing height, floor to top of the head (m).
            segment_scale: optional factor per length field (names in :data:`LENGTH_FIELDS`);
                the vertical chain is renormalised afterwards so the standing height stays
                ``height_m``.
            radius_scale: one factor for every radius (girth), or a factor per radius field
                (names in :data:`RADIUS_FIELDS`, missing ones 1).

        Raises:
            ValidationError: ``height_m`` is not positive, or an unknown field name is given.
        """
        h = check_positive(float(height_m), name="height_m")
        seg = dict(segment_scale or {})
        rad = (
            dict(radius_scale)
            if isinstance(radius_scale, Mapping)
            else dict.fromkeys(RADIUS_FIELDS, float(radius_scale))
        )
        for name, known in (("segment_scale", LENGTH_FIELDS), ("radius_scale", RADIUS_FIELDS)):
            unknown = sorted(set(seg if name == "segment_scale" else rad) - set(known))
            if unknown:
                msg = f"{name} has unknown field(s) {unknown}; known: {list(known)}"
                raise ValidationError(msg)
        lengths = {k: f * h * float(seg.get(k, 1.0)) for k, f in DRILLIS_CONTINI_FRACTIONS.items()}
        # Renormalise the floor-to-HeadEnd chain so per-segment variation keeps the height.
        chain = sum(lengths[k] for k in VERTICAL_CHAIN)
        for k in VERTICAL_CHAIN:
            lengths[k] *= h / chain
        radii = {k: f * h * float(rad.get(k, 1.0)) for k, f in _RADIUS_FRACTIONS.items()}
        return cls(height_m=h, **lengths, **radii)

    @classmethod
    def sample(
        cls,
        rng: np.random.Generator,
        *,
        height_range_m: tuple[float, float] = (1.55, 1.95),
        segment_variation: float = 0.05,
        girth_range: tuple[float, float] = (0.9, 1.15),
        radius_variation: float = 0.05,
    ) -> BodyShape:
        """A random plausible subject.

        Height is uniform in ``height_range_m``; each segment length varies uniformly by
        ±``segment_variation`` (relative) around Drillis & Contini, the standing height kept;
        radii get one girth factor (uniform in ``girth_range``) times ±``radius_variation``
        each.

        Raises:
            ValidationError: an empty or non-positive range, a variation outside [0, 0.3], or
                a draw whose foot radii do not fit under the ankle (extreme ranges only).
        """
        lo, hi = (float(v) for v in height_range_m)
        g_lo, g_hi = (float(v) for v in girth_range)
        if not (0 < lo <= hi and 0 < g_lo <= g_hi):
            msg = (
                f"height_range_m {height_range_m!r} and girth_range {girth_range!r} must be "
                "positive (low, high) pairs"
            )
            raise ValidationError(msg)
        for name, v in (
            ("segment_variation", segment_variation),
            ("radius_variation", radius_variation),
        ):
            if not 0.0 <= v <= 0.3:
                msg = f"{name} must lie in [0, 0.3], got {v!r}"
                raise ValidationError(msg)
        height = float(rng.uniform(lo, hi))
        seg = {
            k: float(s)
            for k, s in zip(
                LENGTH_FIELDS,
                rng.uniform(1 - segment_variation, 1 + segment_variation, len(LENGTH_FIELDS)),
                strict=True,
            )
        }
        girth = float(rng.uniform(g_lo, g_hi))
        rad = {
            k: girth * float(s)
            for k, s in zip(
                RADIUS_FIELDS,
                rng.uniform(1 - radius_variation, 1 + radius_variation, len(RADIUS_FIELDS)),
                strict=True,
            )
        }
        return cls.from_height(height, segment_scale=seg, radius_scale=rad)

    # -- derived dimensions ------------------------------------------------------------------

    @property
    def hips_height_m(self) -> float:
        """Height of the Hips joint (pelvis centre) above the floor in the rest pose (m)."""
        return (
            self.ankle_height_m + self.shank_length_m + self.thigh_length_m + self.pelvis_height_m
        )

    @property
    def hip_joint_spacing_m(self) -> float:
        """Distance between the two hip joint centres (m)."""
        return HIP_JOINT_SPACING_FRACTION * self.hip_width_m

    @property
    def shoulder_joint_spacing_m(self) -> float:
        """Distance between the two gleno-humeral joint centres (m)."""
        return SHOULDER_JOINT_SPACING_FRACTION * self.shoulder_width_m

    @property
    def head_forward_m(self) -> float:
        """How far the head's centre line sits in front of the neck axis (m)."""
        return 0.2 * self.head_radius_m


def _right_side_offsets(shape: BodyShape) -> dict[str, tuple[float, float, float]]:
    """Rest offsets of the right-side joints (parent frame, m); the left side mirrors x."""
    s = shape
    # Sterno-clavicular joint: front of the upper chest, just below the neck base; the
    # gleno-humeral joint 1.2 % H below C7 (acromion level of the figure, 0.818H).
    sc = (0.08 * s.shoulder_width_m, 0.35 * s.chest_radius_m, 0.85 * s.chest_length_m)
    gh = (0.5 * s.shoulder_joint_spacing_m, 0.0, 0.875 * s.chest_length_m)
    fl = s.foot_length_m
    return {
        "RightShoulder": sc,
        "RightArm": (gh[0] - sc[0], gh[1] - sc[1], gh[2] - sc[2]),
        "RightForeArm": (0.0, 0.0, -s.upper_arm_length_m),
        "RightHand": (0.0, 0.0, -s.forearm_length_m),
        "RightHandEnd": (0.0, 0.0, -KNUCKLE_FRACTION * s.hand_length_m),
        "RightUpLeg": (0.5 * s.hip_joint_spacing_m, 0.0, -s.pelvis_height_m),
        "RightLeg": (0.0, 0.0, -s.thigh_length_m),
        "RightFoot": (0.0, 0.0, -s.shank_length_m),
        # The ball of the foot sits one foot radius above the floor so the foot capsule's
        # sole touches it; the toe tip one toe radius above it.
        "RightToeBase": (0.0, BALL_FRACTION * fl, s.foot_radius_m - s.ankle_height_m),
        "RightToeEnd": (0.0, TOE_FRACTION * fl, s.toe_radius_m - s.foot_radius_m),
    }


def rest_offsets(shape: BodyShape) -> npt.NDArray[np.float64]:
    """Rest-pose offset of every joint from its parent, in the parent's frame (26, 3), m.

    Row ``j`` is the position of joint ``j`` relative to ``PARENTS[j]`` in the rest pose; the
    root row is zero (the root translation comes from the pose vector).
    """
    s = shape
    out = np.zeros((len(JOINTS), 3))
    out[JOINT_INDEX["Spine1"]] = (0.0, 0.0, s.lumbar_length_m)
    out[JOINT_INDEX["Spine2"]] = (0.0, 0.0, s.thorax_length_m)
    out[JOINT_INDEX["Neck"]] = (0.0, 0.0, s.chest_length_m)
    out[JOINT_INDEX["Head"]] = (0.0, 0.0, s.neck_length_m)
    out[JOINT_INDEX["HeadEnd"]] = (0.0, s.head_forward_m, s.head_length_m)
    for name, (x, y, z) in _right_side_offsets(shape).items():
        out[JOINT_INDEX[name]] = (x, y, z)
        out[JOINT_INDEX["Left" + name.removeprefix("Right")]] = (-x, y, z)
    return out


def rest_joint_positions(shape: BodyShape) -> npt.NDArray[np.float64]:
    """World joint positions (26, 3) of the rest pose standing on the floor at the origin, m.

    The body faces +Y, the Hips joint is at ``(0, 0, shape.hips_height_m)``.
    """
    off = rest_offsets(shape)
    pos = np.zeros_like(off)
    pos[0] = (0.0, 0.0, shape.hips_height_m)
    for j in range(1, len(JOINTS)):
        pos[j] = pos[PARENTS[j]] + off[j]
    return pos


if not math.isclose(sum(DRILLIS_CONTINI_FRACTIONS[k] for k in VERTICAL_CHAIN), 1.0):
    msg = "the vertical chain fractions must sum to 1"  # pragma: no cover - table typo
    raise RuntimeError(msg)
