"""Which BVH joint stands for each of our joints: the exporters' naming tables and the match.

BVH files name their joints after the tool that wrote them. Four families are known by their
tables (:data:`FAMILIES`): the CMU conversions by Bruce Hahne (cgspeed), the CMU ASF/AMC bone
names, Mixamo (``mixamorig:`` namespace) and Vicon Blade/Shogun (the HumanIK names, with the
common ``LeftThigh`` / ``L_Femur`` spellings). Names are compared by :func:`spelling_key`, so
spellings that differ only in case, ``_``/``-``/space/``.``, a ``prefix:`` namespace or the side
written ``Left``/``L``/``l_``/``_L`` match each other.

Retargeting fits bone *directions* between joint positions, so one of our joints stands for a
point of the BVH skeleton: a BVH joint, or (``derived``) a point on the bone between two BVH
joints, ``(1 - t) p[joint] + t p[toward]``. A point on a bone moves rigidly with the bone's
joint (the child's offset is fixed in that joint's frame), so the blend is exact whatever the
rotations are. The spine is matched by structure, since its names disagree most between
exporters: ``Spine2`` (our chest, where the clavicles attach) is the lowest common ancestor of
the two upper arms, ``Spine1`` its parent; when that parent is the hips, ``Spine1`` is derived
halfway along the hips -> chest bone. Missing ends (``HeadEnd``, ``*HandEnd``, ``*ToeEnd``) take
the only child of their parent's BVH joint, and a missing ``Neck`` the joint after the chest on
the way to the head. A user mapping (our name -> BVH name, exact) wins over all of it.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body.skeleton import JOINT_INDEX, JOINTS

__all__ = [
    "DEFAULT_JOINT_CANDIDATES",
    "FAMILIES",
    "REQUIRED_JOINTS",
    "ExporterFamily",
    "JointMapping",
    "MappedJoint",
    "MatchKind",
    "NamingFamily",
    "check_joint_map",
    "detect_family",
    "map_joints",
    "spelling_key",
]

_log = logging.getLogger(__name__)

ExporterFamily = Literal["cgspeed", "cmu-asf", "mixamo", "vicon"]
MatchKind = Literal["joint map", "name", "structure", "derived"]

#: Our joints without which a clip cannot be put into our frame (root, hips line, up axis).
REQUIRED_JOINTS: tuple[str, ...] = ("Hips", "LeftUpLeg", "RightUpLeg", "Spine2")

_SIDES = (("Right", "R", "r"), ("Left", "L", "l"))


def _sided(
    table: Iterable[tuple[str, tuple[str, ...]]], *, asf: bool = False
) -> dict[str, tuple[str, ...]]:
    """Both sides of a one-side table: ``{side}`` in a name is ``Left``/``Right`` (or, with
    ``asf``, the ASF's lowercase ``l``/``r``)."""
    return {
        f"{side}{ours}": tuple(n.format(side=low if asf else side) for n in names)
        for side, _, low in _SIDES
        for ours, names in table
    }


#: The cgspeed/Hahne CMU conversion (plain and 3ds Max-friendly namings, e.g. ``LeftHip``,
#: ``Chest2``, ``LeftCollar``) and similar rigs: our joint -> candidate names, best first. The
#: order of the joints matters ("first unused match wins"): ``Arm`` comes before ``Shoulder`` so
#: that a clavicle called ``LeftShoulder`` does not shadow ``LeftArm``.
DEFAULT_JOINT_CANDIDATES: Mapping[str, tuple[str, ...]] = {
    "Hips": ("Hips", "Hip", "Pelvis", "Root"),
    "Spine2": ("Spine2", "Chest2", "Spine1", "Chest"),
    "Spine1": ("Chest", "Spine1", "Spine"),
    "Neck": ("Neck", "Neck1", "LowerNeck"),
    "Head": ("Head",),
    "HeadEnd": ("Head_End", "HeadTop_End", "HeadEnd", "HeadTop"),
    **{
        f"{side}{ours}": tuple(f"{pre}{name}" for pre, name in cands)
        for side, short, _ in _SIDES
        for ours, cands in (
            ("Arm", ((side, "Arm"), (side, "UpArm"), (side, "Shoulder"))),
            ("Shoulder", ((side, "Shoulder"), (side, "Collar"), (side, "Clavicle"))),
            ("ForeArm", ((side, "ForeArm"), (side, "Elbow"), (side, "LowArm"))),
            ("Hand", ((side, "Hand"), (side, "Wrist"))),
            (
                "HandEnd",
                (
                    (side, "HandMiddle1"),
                    (side, "FingerBase"),
                    (short, "Fingers"),
                    (side, "HandIndex1"),
                    (side, "Hand_End"),
                    (side, "Wrist_End"),
                ),
            ),
            ("UpLeg", ((side, "UpLeg"), (side, "Hip"), (side, "Thigh"), (side, "UpperLeg"))),
            ("Leg", ((side, "Leg"), (side, "Knee"), (side, "Shin"), (side, "LowerLeg"))),
            ("Foot", ((side, "Foot"), (side, "Ankle"))),
            ("ToeBase", ((side, "ToeBase"), (side, "Toe"), (side, "Toes"))),
            (
                "ToeEnd",
                ((side, "ToeBase_End"), (side, "Toe_End"), (side, "Toes_End"), (side, "ToeEnd")),
            ),
        )
    },
}

# CMU ASF bones, as the ASF/AMC -> BVH converters name the joints: a BVH joint sits at the start
# of the bone it is named after, so e.g. our knee (LeftLeg) is ``ltibia``. ``lowerback`` is the
# lumbar bone; the chest is ``thorax`` (the cgspeed conversion calls the same bones LowerBack,
# Spine, Spine1).
_ASF: Mapping[str, tuple[str, ...]] = {
    "Hips": ("hip", "root", "hips"),
    "Spine2": ("thorax",),
    "Spine1": ("upperback",),
    "Neck": ("lowerneck", "neck"),
    "Head": ("head",),
    "HeadEnd": ("head_End",),
    **_sided(
        (
            ("Arm", ("{side}humerus",)),
            ("Shoulder", ("{side}clavicle",)),
            ("ForeArm", ("{side}radius",)),
            ("Hand", ("{side}wrist", "{side}hand")),
            ("HandEnd", ("{side}hand", "{side}fingers", "{side}hand_End", "{side}wrist_End")),
            ("UpLeg", ("{side}femur",)),
            ("Leg", ("{side}tibia",)),
            ("Foot", ("{side}foot",)),
            ("ToeBase", ("{side}toes",)),
            ("ToeEnd", ("{side}toes_End", "{side}foot_End")),
        ),
        asf=True,
    ),
}

# Mixamo, the namespace (``mixamorig:``, ``mixamorig1:`` …) stripped by spelling_key.
_MIXAMO: Mapping[str, tuple[str, ...]] = {
    "Hips": ("Hips",),
    "Spine2": ("Spine2",),
    "Spine1": ("Spine1",),
    "Neck": ("Neck",),
    "Head": ("Head",),
    "HeadEnd": ("HeadTop_End", "Head_End"),
    **_sided(
        (
            ("Arm", ("{side}Arm",)),
            ("Shoulder", ("{side}Shoulder",)),
            ("ForeArm", ("{side}ForeArm",)),
            ("Hand", ("{side}Hand",)),
            ("HandEnd", ("{side}HandMiddle1", "{side}HandIndex1", "{side}Hand_End")),
            ("UpLeg", ("{side}UpLeg",)),
            ("Leg", ("{side}Leg",)),
            ("Foot", ("{side}Foot",)),
            ("ToeBase", ("{side}ToeBase",)),
            ("ToeEnd", ("{side}Toe_End", "{side}ToeBase_End")),
        )
    ),
}

# Vicon Blade/Shogun: HumanIK names (Spine … Spine3), with the thigh/femur spellings its users'
# skeleton templates carry (``L_Femur`` matches ``LeftFemur`` through spelling_key).
_VICON: Mapping[str, tuple[str, ...]] = {
    "Hips": ("Hips", "Root", "Pelvis"),
    "Spine2": ("Spine3", "Spine2", "Spine1", "Chest"),
    "Spine1": ("Spine2", "Spine1", "Spine"),
    "Neck": ("Neck", "Neck1"),
    "Head": ("Head",),
    "HeadEnd": ("Head_End", "HeadEnd", "HeadTop_End"),
    **_sided(
        (
            ("Arm", ("{side}Arm", "{side}UpperArm", "{side}Humerus")),
            ("Shoulder", ("{side}Shoulder", "{side}Clavicle")),
            ("ForeArm", ("{side}ForeArm", "{side}LowerArm", "{side}Radius", "{side}Elbow")),
            ("Hand", ("{side}Hand", "{side}Wrist")),
            ("HandEnd", ("{side}HandMiddle1", "{side}Hand_End", "{side}FingerBase")),
            ("UpLeg", ("{side}UpLeg", "{side}Thigh", "{side}Femur", "{side}UpperLeg")),
            ("Leg", ("{side}Leg", "{side}Shin", "{side}Tibia", "{side}LowerLeg", "{side}Knee")),
            ("Foot", ("{side}Foot", "{side}Ankle")),
            ("ToeBase", ("{side}ToeBase", "{side}Toe", "{side}Toes")),
            ("ToeEnd", ("{side}ToeBase_End", "{side}Toe_End", "{side}ToeEnd")),
        )
    ),
}


@dataclass(frozen=True, slots=True)
class NamingFamily:
    """One exporter's joint naming.

    Attributes:
        name: Short name (logged, and in :class:`JointMapping`).
        description: What writes it.
        signature: Names (as :func:`spelling_key` gives them) that this family writes and the
            others do not; they decide the family when several tables fit.
        candidates: Our joint -> that exporter's names for it, best first.
    """

    name: ExporterFamily
    description: str
    signature: tuple[str, ...]
    candidates: Mapping[str, tuple[str, ...]]


#: The known families; on a tie (no signature name, as many table matches) the first wins.
FAMILIES: tuple[NamingFamily, ...] = (
    NamingFamily(
        "cgspeed",
        "CMU motion capture as converted by Bruce Hahne (cgspeed)",
        ("lefthipjoint", "righthipjoint", "leftfingerbase", "leftthumb", "chest2", "leftcollar"),
        DEFAULT_JOINT_CANDIDATES,
    ),
    NamingFamily(
        "cmu-asf",
        "CMU ASF/AMC bone names (ASF/AMC -> BVH converters)",
        ("lfemur", "rfemur", "ltibia", "lhumerus", "lradius", "upperback", "thorax"),
        _ASF,
    ),
    NamingFamily(
        "mixamo",
        "Mixamo (mixamorig: namespace)",
        ("mixamorig", "headtopend", "lefttoeend", "righttoeend"),
        _MIXAMO,
    ),
    NamingFamily(
        "vicon",
        "Vicon Blade/Shogun (HumanIK names: Hips, Spine…, LeftUpLeg or LeftThigh/L_Femur)",
        ("spine3", "leftthigh", "rightthigh", "leftfemur", "rightfemur", "leftshin"),
        _VICON,
    ),
)

_SEPARATORS = re.compile(r"[\s_\-.]+")
_MIXAMO_PREFIX = re.compile(r"^mixamorig\d*_", re.IGNORECASE)


def spelling_key(name: str) -> str:
    """A joint name with the spelling that exporters vary taken out.

    Drops a ``prefix:`` namespace (and Blender's ``mixamorig_``), writes the side as ``left`` /
    ``right`` whether it was ``Left``, ``L`` before a separator or a capitalised word
    (``LHipJoint``, ``L_Femur``, ``l_hip``) or ``_L`` / ``.l`` at the end, removes ``_``, ``-``,
    ``.`` and spaces, and lowercases. ASF's ``lfemur`` stays as it is (``lowerback`` would be
    ambiguous), so its table spells it the same way.
    """
    base = _MIXAMO_PREFIX.sub("", name.rsplit(":", 1)[-1])
    side = ""
    if m := re.match(r"(?i)(left|right)", base):
        side, base = m.group(1).lower(), base[m.end() :]
    elif m := re.match(r"([LRlr])[\s_\-.]+|([LR])(?=[A-Z][a-z])", base):
        side = "left" if (m.group(1) or m.group(2)) in "Ll" else "right"
        base = base[m.end() :]
    elif m := re.search(r"[\s_\-.]+(left|right|[lr])$", base, flags=re.IGNORECASE):
        side = "left" if m.group(1).lower().startswith("l") else "right"
        base = base[: m.start()]
    return side + _SEPARATORS.sub("", base).lower()


@dataclass(frozen=True, slots=True)
class MappedJoint:
    """Where one of our joints sits on a BVH skeleton: the point ``(1 - fraction) p[joint] +
    fraction p[toward]`` (a BVH joint itself when ``fraction`` is 0 and ``toward == joint``).

    Attributes:
        joint: BVH joint index.
        toward: BVH joint index of the bone's other end (a child of ``joint``), or ``joint``.
        fraction: Position along the bone, 0..1.
        how: ``"joint map"`` (the user's mapping), ``"name"`` (a naming table), ``"structure"``
            (the hierarchy) or ``"derived"`` (a point on a bone).
    """

    joint: int
    toward: int
    fraction: float
    how: MatchKind

    @property
    def exact(self) -> bool:
        """Whether this is a BVH joint itself."""
        return self.fraction == 0.0


@dataclass(frozen=True, slots=True)
class JointMapping:
    """Our joints on one BVH skeleton.

    Attributes:
        family: The naming family detected (also when a user mapping completed it).
        joints: Our joint name -> where it sits, in our joint order; unmapped joints are absent.
    """

    family: NamingFamily
    joints: Mapping[str, MappedJoint]

    @property
    def names(self) -> tuple[str, ...]:
        """Our mapped joints, in our joint order."""
        return tuple(self.joints)

    def column(self, name: str) -> int:
        """Position of our joint ``name`` in :meth:`points`' joint axis."""
        return self.names.index(name)

    def indices(self) -> dict[str, int]:
        """Our joint name -> BVH joint index, for the joints that are BVH joints themselves."""
        return {n: m.joint for n, m in self.joints.items() if m.exact}

    def points(self, positions: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Our mapped joints' positions from the BVH joint positions ``(..., J, 3)``; shape
        ``(..., len(names), 3)``."""
        p = np.asarray(positions, dtype=np.float64)
        a = [m.joint for m in self.joints.values()]
        b = [m.toward for m in self.joints.values()]
        t = np.array([m.fraction for m in self.joints.values()])[:, None]
        return np.asarray((1.0 - t) * p[..., a, :] + t * p[..., b, :])


def detect_family(joint_names: Sequence[str]) -> tuple[NamingFamily, int]:
    """The naming family a skeleton's names fit best, and how many of our joints its table
    matches by name. Families are ranked by the signature names present, then by matches."""
    keys = {spelling_key(n) for n in joint_names}
    if any(n.lower().startswith("mixamorig") for n in joint_names):
        keys.add("mixamorig")
    best: tuple[int, int, int] = (-1, -1, 0)
    for k, fam in enumerate(FAMILIES):
        hits = sum(1 for s in fam.signature if s in keys)
        matched = sum(
            1 for cands in fam.candidates.values() if any(spelling_key(c) in keys for c in cands)
        )
        if (hits, matched) > best[:2]:
            best = (hits, matched, k)
    return FAMILIES[best[2]], best[1]


def check_joint_map(
    joint_map: Mapping[str, str], joint_names: Sequence[str], *, source: str = "<string>"
) -> None:
    """Check that a joint map pairs our joints with joints of the BVH, one to one.

    Raises:
        ValidationError: a key is not one of our joints, a value not a joint of the BVH, or
            one BVH joint stands for two of ours.
    """
    for ours, theirs in joint_map.items():
        if ours not in JOINT_INDEX:
            msg = f"joint map: {ours!r} is not one of our joints ({', '.join(JOINTS)})"
            raise ValidationError(msg)
        if theirs not in joint_names:
            msg = (
                f"joint map: {ours} = {theirs!r}, but BVH {source} has no joint {theirs!r} "
                f"(its joints: {', '.join(joint_names)})"
            )
            raise ValidationError(msg)
    twice = sorted({t for t in joint_map.values() if list(joint_map.values()).count(t) > 1})
    if twice:
        msg = f"joint map: BVH joint(s) {', '.join(twice)} given for several of our joints"
        raise ValidationError(msg)


def _ancestors(j: int, parents: Sequence[int]) -> list[int]:
    """``j`` and its ancestors, ``j`` first."""
    out = []
    while j >= 0:
        out.append(j)
        j = parents[j]
    return out


def map_joints(
    joint_names: Sequence[str],
    parents: Sequence[int],
    *,
    joint_map: Mapping[str, str] | None = None,
    source: str = "<string>",
) -> JointMapping:
    """Match our joints onto a BVH skeleton (see the module docstring for the rules).

    Args:
        joint_names: The BVH's joint names (End Sites ``<parent>_End``).
        parents: Parent index of each BVH joint (-1 for a root).
        joint_map: Our joint name -> BVH joint name (exact), applied first.
        source: The file, for messages.

    Raises:
        ValidationError: ``joint_map`` names a joint that is not ours or not in the BVH.
        ProcessingError: one of :data:`REQUIRED_JOINTS` cannot be matched; the message lists
            both skeletons' joints and the mapping file to write.
    """
    family, _ = detect_family(joint_names)
    by_key: dict[str, list[int]] = {}
    for i, n in enumerate(joint_names):
        by_key.setdefault(spelling_key(n), []).append(i)
    found: dict[str, MappedJoint] = {}
    used: set[int] = set()

    def put(ours: str, idx: int, how: MatchKind) -> None:
        found[ours] = MappedJoint(idx, idx, 0.0, how)
        used.add(idx)

    check_joint_map(joint_map or {}, joint_names, source=source)
    for ours, theirs in (joint_map or {}).items():
        put(ours, list(joint_names).index(theirs), "joint map")
    tables = (family, *(f for f in FAMILIES if f is not family))

    def by_name(ours: str) -> None:
        if ours in found:
            return
        for fam in tables:
            for cand in fam.candidates.get(ours, ()):
                for idx in by_key.get(spelling_key(cand), ()):
                    if idx not in used:
                        put(ours, idx, "name")
                        return

    def only_child(ours: str, parent: str) -> None:
        if ours in found or parent not in found or not found[parent].exact:
            return
        kids = [c for c, p in enumerate(parents) if p == found[parent].joint]
        if len(kids) == 1 and kids[0] not in used:
            put(ours, kids[0], "structure")

    by_name("Hips")
    if "Hips" not in found and parents and sum(1 for p in parents if p < 0) == 1:
        put("Hips", 0, "structure")
    limbs = [n for n in DEFAULT_JOINT_CANDIDATES if n.startswith(("Left", "Right"))]
    for ours in limbs:
        by_name(ours)
    _spine(found, used, parents)
    for ours in ("Spine2", "Spine1", "Neck", "Head", "HeadEnd"):
        by_name(ours)
    _neck(found, used, parents)
    only_child("HeadEnd", "Head")
    for side in ("Left", "Right"):
        only_child(f"{side}HandEnd", f"{side}Hand")
        only_child(f"{side}ToeEnd", f"{side}ToeBase")
    missing = [n for n in REQUIRED_JOINTS if n not in found]
    if missing:
        raise ProcessingError(_unmappable_message(source, missing, joint_names, family))
    ordered = {n: found[n] for n in JOINTS if n in found}
    _log.debug(
        "BVH %s: %s names; %s",
        source,
        family.name,
        ", ".join(f"{n}={_describe(m, joint_names)}" for n, m in ordered.items()),
    )
    return JointMapping(family, ordered)


def _spine(found: dict[str, MappedJoint], used: set[int], parents: Sequence[int]) -> None:
    """The chest: the upper arms' lowest common ancestor above the hips; Spine1: below it."""
    if "Hips" not in found or not all(f"{s}Arm" in found for s in ("Left", "Right")):
        return
    hips = found["Hips"].joint
    left = _ancestors(found["LeftArm"].joint, parents)
    right = set(_ancestors(found["RightArm"].joint, parents))
    lca = next((j for j in left if j in right), -1)
    if lca < 0 or hips not in _ancestors(lca, parents)[1:]:
        return
    if "Spine2" not in found and lca not in used:
        found["Spine2"] = MappedJoint(lca, lca, 0.0, "structure")
        used.add(lca)
    spine2 = found.get("Spine2")
    if "Spine1" in found or spine2 is None or not spine2.exact:
        return
    below = parents[spine2.joint]
    if below == hips:
        found["Spine1"] = MappedJoint(hips, spine2.joint, 0.5, "derived")
    elif below >= 0 and below not in used and hips in _ancestors(below, parents):
        found["Spine1"] = MappedJoint(below, below, 0.0, "structure")
        used.add(below)


def _neck(found: dict[str, MappedJoint], used: set[int], parents: Sequence[int]) -> None:
    """A missing neck: the joint after the chest on the way up to the head."""
    if "Neck" in found or "Spine2" not in found or "Head" not in found:
        return
    chest, head = found["Spine2"].joint, found["Head"].joint
    path = _ancestors(head, parents)
    if chest in path[1:]:
        nxt = path[path.index(chest) - 1]
        if nxt != head and nxt not in used:
            found["Neck"] = MappedJoint(nxt, nxt, 0.0, "structure")
            used.add(nxt)


def _describe(m: MappedJoint, names: Sequence[str]) -> str:
    if m.exact:
        return names[m.joint]
    return f"{m.fraction:g} of {names[m.joint]}->{names[m.toward]}"


#: Words that suggest which BVH joint a missing one of ours is, for the example line only.
_HINTS: Mapping[str, tuple[str, ...]] = {
    "Hips": ("pelvis", "hip", "root"),
    "LeftUpLeg": ("thigh", "upleg", "upperleg", "femur"),
    "RightUpLeg": ("thigh", "upleg", "upperleg", "femur"),
    "Spine2": ("chest", "thorax", "spine"),
}


def _example(ours: str, joint_names: Sequence[str]) -> str:
    """A plausible BVH joint for ``ours`` (a hint word and, for a side, its side) for the error
    message's example line, else a fill-in (``<its Hips joint>``) for the user to replace."""
    side = "left" if ours.startswith("Left") else "right" if ours.startswith("Right") else ""
    for n in joint_names:
        low = n.lower()
        if n.endswith("_End") or not any(h in low for h in _HINTS.get(ours, ())):
            continue
        marks = {spelling_key(n)[:4], *re.findall(r"(?<![a-z])(l|r|left|right)(?![a-z])", low)}
        if not side or side[0] in {m[0] for m in marks if m[:1] in ("l", "r")}:
            return n
    return f"<its {ours} joint>"


def _unmappable_message(
    source: str, missing: Sequence[str], joint_names: Sequence[str], family: NamingFamily
) -> str:
    example = f'{missing[0]} = "{_example(missing[0], joint_names)}"'
    return (
        f"BVH {source}: cannot map our joint(s) {', '.join(missing)} onto its skeleton (no "
        f"known naming fits; closest: {family.name}, {family.description}). "
        f"Our joints: {', '.join(JOINTS)}. Its joints: {', '.join(joint_names)}. "
        "Write a joint map, a TOML file of lines 'our joint = \"its joint\"' (at least "
        f"{', '.join(REQUIRED_JOINTS)}), e.g. {example}, "
        "and pass it with --joint-map FILE.toml (joint_map= in Python)"
    )
