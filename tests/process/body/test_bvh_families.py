"""BVH files from the common exporters (cgspeed CMU, CMU ASF, Mixamo, Vicon Blade/Shogun, any
other through a joint map) retarget onto our skeleton as their own skeleton says."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body.bvh import (
    BvhClip,
    load_joint_map,
    map_bvh_joints,
    parse_bvh,
    read_bvh,
    resolve_joint_map,
    retarget_bvh,
)
from mocaprig.process.body.bvh_names import detect_family, spelling_key
from mocaprig.process.body.kinematics import forward_kinematics
from mocaprig.process.body.motion import Motion
from mocaprig.process.body.procedural import make_motion
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.body.skeleton import DOF_JOINT, JOINT_INDEX, JOINTS, ROOT_DIM
from tests.process.body._body_helpers import motion_as_bvh

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class _Layout:
    """How an exporter lays out a skeleton we hold as a BvhClip: joint names, joints inserted
    halfway along a bone (zero rotation, so every other joint keeps its position), childless
    joints written as ``End Site`` of their parent, joints removed (their rotation must be the
    identity in every frame; children re-attached with the offsets summed) and a namespace."""

    rename: Mapping[str, str] = field(default_factory=dict)
    insert: Mapping[str, str | tuple[str, ...]] = field(default_factory=dict)
    end_sites: frozenset[str] = frozenset()
    remove: frozenset[str] = frozenset()
    prefix: str = ""


def _bvh_text(clip: BvhClip, layout: _Layout) -> str:
    """The clip as BVH text (metres), laid out as ``layout`` says."""
    kids: dict[int, list[int]] = {}
    for j, p in enumerate(clip.parents):
        kids.setdefault(p, []).append(j)
    start = clip.channel_start
    lines = ["HIERARCHY"]
    cols: list[F64] = []
    zeros = np.zeros((clip.num_frames, 3))

    def name(j: int) -> str:
        base = clip.joint_names[j]
        return layout.prefix + layout.rename.get(base, base)

    def channels(j: int) -> None:
        ch = clip.channels[j]
        lines.append(f"CHANNELS {len(ch)} {' '.join(ch)}")
        cols.append(clip.frames[:, start[j] : start[j] + len(ch)])

    def joint(j: int, offset: F64, *, root: bool = False, split: bool = False) -> None:
        base = clip.joint_names[j]
        if base in layout.remove:
            assert not clip.channels[j][0].endswith("position")
            for c in kids.get(j, []):
                joint(c, offset + clip.offsets_m[c])
            return
        if base in layout.insert and not (root or split):
            added = layout.insert[base]
            added = (added,) if isinstance(added, str) else added
            part = offset / (len(added) + 1)
            for new in added:
                lines.extend([f"JOINT {layout.prefix}{new}", "{"])
                lines.append("OFFSET " + " ".join(f"{v:.9f}" for v in part))
                lines.append("CHANNELS 3 Zrotation Xrotation Yrotation")
                cols.append(zeros)
            joint(j, offset - len(added) * part, split=True)
            lines.extend(["}"] * len(added))
            return
        if base in layout.end_sites:
            lines.extend(["End Site", "{", "OFFSET " + " ".join(f"{v:.9f}" for v in offset), "}"])
            return
        lines.extend([f"{'ROOT' if root else 'JOINT'} {name(j)}", "{"])
        lines.append("OFFSET " + " ".join(f"{v:.9f}" for v in offset))
        channels(j)
        children = kids.get(j, [])
        for c in children:
            joint(c, clip.offsets_m[c])
        if not children:
            lines.extend(["End Site", "{", "OFFSET 0 0 0", "}"])
        lines.append("}")

    joint(0, clip.offsets_m[0], root=True)
    data = np.concatenate(cols, axis=1)
    lines += ["MOTION", f"Frames: {clip.num_frames}", f"Frame Time: {clip.frame_time_s:.9f}"]
    lines += [" ".join(f"{v:.9f}" for v in row) for row in data]
    return "\n".join(lines) + "\n"


def _sides(table: Mapping[str, str]) -> dict[str, str]:
    return {
        f"{side}{ours}": theirs.format(s=s, S=s.upper(), side=side)
        for side, s in (("Left", "l"), ("Right", "r"))
        for ours, theirs in table.items()
    }


#: Each family's layout of our skeleton, as that exporter names and shapes it.
_FAMILIES: dict[str, _Layout] = {
    "cgspeed": _Layout(
        rename={
            "Spine1": "Spine",
            "Spine2": "Spine1",
            **_sides({"HandEnd": "{side}FingerBase"}),
        },
        insert={
            "Spine1": "LowerBack",
            "Head": "Neck1",
            "LeftUpLeg": "LHipJoint",
            "RightUpLeg": "RHipJoint",
        },
        end_sites=frozenset({"HeadEnd", "LeftToeEnd", "RightToeEnd"}),
    ),
    "cmu-asf": _Layout(
        rename={
            "Hips": "hip",
            "Spine1": "upperback",
            "Spine2": "thorax",
            "Neck": "lowerneck",
            "Head": "head",
            **_sides(
                {
                    "Shoulder": "{s}clavicle",
                    "Arm": "{s}humerus",
                    "ForeArm": "{s}radius",
                    "Hand": "{s}wrist",
                    "HandEnd": "{s}hand",
                    "UpLeg": "{s}femur",
                    "Leg": "{s}tibia",
                    "Foot": "{s}foot",
                    "ToeBase": "{s}toes",
                }
            ),
        },
        insert={
            "Spine1": "lowerback",
            "Head": "upperneck",
            "LeftUpLeg": "lhipjoint",
            "RightUpLeg": "rhipjoint",
        },
        end_sites=frozenset({"HeadEnd", "LeftToeEnd", "RightToeEnd"}),
    ),
    "mixamo": _Layout(
        rename={
            "HeadEnd": "HeadTop_End",
            **_sides({"HandEnd": "{side}HandMiddle1", "ToeEnd": "{side}Toe_End"}),
        },
        insert={"Spine1": "Spine"},
        prefix="mixamorig:",
    ),
    "vicon": _Layout(
        rename={
            "Spine1": "Spine",
            "Spine2": "Spine1",
            "LeftUpLeg": "LeftThigh",
            "RightUpLeg": "R_Femur",
            "RightLeg": "R_Tibia",
        },
        end_sites=frozenset(
            {"HeadEnd", "LeftHandEnd", "RightHandEnd", "LeftToeEnd", "RightToeEnd"}
        ),
    ),
}

#: An odd naming (3ds Max Biped-like) that no table knows, and the joint map that reads it.
_BIPED = _Layout(
    rename={
        "Hips": "Bip01_Pelvis",
        "Spine1": "Bip01_Spine",
        "Spine2": "Bip01_Spine1",
        "Neck": "Bip01_Neck",
        "Head": "Bip01_Head",
        "HeadEnd": "Bip01_HeadNub",
        **_sides(
            {
                "Shoulder": "Bip01_{S}_Clavicle",
                "Arm": "Bip01_{S}_UpperArm",
                "ForeArm": "Bip01_{S}_Forearm",
                "Hand": "Bip01_{S}_Palm",
                "HandEnd": "Bip01_{S}_Finger0",
                "UpLeg": "Bip01_{S}_Thigh",
                "Leg": "Bip01_{S}_Calf",
                "Foot": "Bip01_{S}_Foot",
                "ToeBase": "Bip01_{S}_Toe0",
                "ToeEnd": "Bip01_{S}_Toe0Nub",
            }
        ),
    }
)


@pytest.fixture(scope="module")
def shape() -> BodyShape:
    return BodyShape.from_height(1.7)


@pytest.fixture(scope="module")
def ours(shape: BodyShape) -> BvhClip:
    """Our own punch/kick motion as a BVH clip (Y up), the spine's lower joint held straight
    so that a skeleton without it is exact."""
    motion = make_motion(
        "punch_kick", seconds=0.2, rng=np.random.default_rng(5), rate_hz=30.0, shape=shape
    )
    poses = np.array(motion.poses)
    for k, j in enumerate(DOF_JOINT):
        if j == JOINT_INDEX["Spine1"]:
            poses[:, ROOT_DIM + k] = 0.0
    return motion_as_bvh(poses, shape, 30.0)


@pytest.fixture(scope="module")
def reference(ours: BvhClip, shape: BodyShape) -> F64:
    """Joint positions (m) of the retargeted clip under our own names."""
    clip = parse_bvh(_bvh_text(ours, _Layout()), unit_scale=1.0)
    return _retargeted_positions(clip, shape)


def _retargeted_positions(clip: BvhClip, shape: BodyShape) -> F64:
    motion: Motion = retarget_bvh(clip, shape, iterations=20)
    return np.asarray(forward_kinematics(motion.poses, shape).positions_m)


@pytest.mark.parametrize(
    ("name", "key"),
    [
        ("mixamorig:LeftUpLeg", "leftupleg"),
        ("mixamorig1:Hips", "hips"),
        ("mixamorig_RightArm", "rightarm"),
        ("L_Femur", "leftfemur"),
        ("l_femur", "leftfemur"),
        ("LHipJoint", "lefthipjoint"),
        ("Thigh_R", "rightthigh"),
        ("left-up leg", "leftupleg"),
        ("Head_End", "headend"),
        ("lfemur", "lfemur"),
        ("lowerback", "lowerback"),
        ("LOWERBACK", "lowerback"),
        ("Root", "root"),
        ("LeftToe_End", "lefttoeend"),
    ],
)
def test_spelling_key_ignores_exporter_spelling(name: str, key: str) -> None:
    assert spelling_key(name) == key


@pytest.mark.parametrize("family", sorted(_FAMILIES))
def test_each_exporter_family_retargets_as_its_skeleton_says(
    family: str,
    ours: BvhClip,
    shape: BodyShape,
    reference: F64,
    caplog: pytest.LogCaptureFixture,
) -> None:
    text = _bvh_text(ours, _FAMILIES[family])
    clip = parse_bvh(text, unit_scale=1.0, source=f"{family}.bvh")
    assert detect_family(clip.joint_names)[0].name == family
    mapping = map_bvh_joints(clip)
    assert set(mapping.names) == set(JOINTS)
    with caplog.at_level(logging.INFO, logger="mocaprig.process.body.bvh"):
        got = _retargeted_positions(clip, shape)
    assert f"{family} joint names" in caplog.text
    np.testing.assert_allclose(got, reference, atol=1e-6)


def test_mixamo_names_map_onto_the_same_bvh_joints_as_ours(ours: BvhClip) -> None:
    clip = parse_bvh(_bvh_text(ours, _FAMILIES["mixamo"]), unit_scale=1.0)
    names = {k: clip.joint_names[v] for k, v in resolve_joint_map(clip).items()}
    assert names["LeftArm"] == "mixamorig:LeftArm"
    assert names["LeftShoulder"] == "mixamorig:LeftShoulder"
    assert names["Spine1"] == "mixamorig:Spine1"
    assert names["HeadEnd"] == "mixamorig:HeadTop_End"
    assert names["RightToeEnd"] == "mixamorig:RightToe_End"


def test_vicon_shogun_chest_is_found_by_structure_not_by_name(
    ours: BvhClip, shape: BodyShape, reference: F64
) -> None:
    # Shogun: Hips -> Spine -> Spine1 -> Spine2 -> Spine3 (chest) -> Neck; the name "Spine2"
    # is not our Spine2 here, and our Spine1 is the joint below the chest.
    layout = _Layout(
        rename={"Spine1": "Spine2", "Spine2": "Spine3"}, insert={"Spine1": ("Spine", "Spine1")}
    )
    clip = parse_bvh(_bvh_text(ours, layout), unit_scale=1.0)
    names = {k: clip.joint_names[v] for k, v in resolve_joint_map(clip).items()}
    assert (names["Spine2"], names["Spine1"]) == ("Spine3", "Spine2")
    np.testing.assert_allclose(_retargeted_positions(clip, shape), reference, atol=1e-6)


def test_missing_lower_spine_is_derived_on_the_hips_to_chest_bone(
    ours: BvhClip, shape: BodyShape, reference: F64
) -> None:
    layout = _Layout(remove=frozenset({"Spine1"}), rename={"Spine2": "Chest"})
    clip = parse_bvh(_bvh_text(ours, layout), unit_scale=1.0)
    mapping = map_bvh_joints(clip)
    spine1 = mapping.joints["Spine1"]
    assert spine1.how == "derived"
    assert (clip.joint_names[spine1.joint], clip.joint_names[spine1.toward]) == ("Hips", "Chest")
    assert "Spine1" not in resolve_joint_map(clip)
    np.testing.assert_allclose(_retargeted_positions(clip, shape), reference, atol=1e-6)


def test_odd_naming_retargets_through_a_toml_joint_map(
    tmp_path: Path, ours: BvhClip, shape: BodyShape, reference: F64
) -> None:
    bvh = tmp_path / "biped.bvh"
    bvh.write_text(_bvh_text(ours, _BIPED))
    with pytest.raises(ProcessingError, match=r"--joint-map FILE\.toml"):
        retarget_bvh(read_bvh(bvh, unit_scale=1.0), shape)
    toml = tmp_path / "biped.toml"
    toml.write_text("".join(f'{o} = "{t}"\n' for o, t in _BIPED.rename.items()))
    clip = read_bvh(bvh, unit_scale=1.0, joint_map=load_joint_map(toml))
    # replace() (as the training-data code thins clips) keeps the map
    thin = replace(clip, frames=clip.frames)
    np.testing.assert_allclose(_retargeted_positions(thin, shape), reference, atol=1e-6)


def test_simulated_scenario_reads_its_bvh_through_the_joint_map(
    tmp_path: Path, ours: BvhClip
) -> None:
    from mocaprig.drivers_mock.scenario import build_scenario

    bvh = tmp_path / "biped.bvh"
    bvh.write_text(_bvh_text(ours, _BIPED))
    with pytest.raises(ProcessingError, match="cannot map our joint"):
        build_scenario(seed=0, seconds=3.0, motion_path=bvh)
    joint_map = dict(_BIPED.rename)
    world = build_scenario(seed=0, seconds=3.0, motion_path=bvh, joint_map=joint_map)
    assert world.motion.num_frames == ours.num_frames


def test_unmappable_file_lists_both_skeletons_and_the_map_to_write(ours: BvhClip) -> None:
    clip = parse_bvh(_bvh_text(ours, _BIPED), unit_scale=1.0, source="biped.bvh")
    with pytest.raises(ProcessingError) as info:
        map_bvh_joints(clip)
    msg = str(info.value)
    assert "biped.bvh" in msg
    # the root is taken for the hips; nothing else is known by name or structure
    assert "cannot map our joint(s) LeftUpLeg, RightUpLeg, Spine2 " in msg
    assert "Our joints: Hips, Spine1, Spine2, Neck" in msg
    assert "Its joints: Bip01_Pelvis, Bip01_Spine, " in msg
    assert "--joint-map FILE.toml" in msg
    assert 'e.g. LeftUpLeg = "Bip01_L_Thigh"' in msg


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ('LeftUpLeg = "Thigh"\nLeftKnee = "Calf"\n', "'LeftKnee' is not one of our joints"),
        ("LeftUpLeg = 3\n", "the value must be the BVH joint's name"),
        ("LeftUpLeg = Thigh\n", "is not TOML"),
    ],
)
def test_bad_joint_map_file_names_the_file_and_entry(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "map.toml"
    path.write_text(text)
    with pytest.raises(ProcessingError, match=match) as info:
        load_joint_map(path)
    assert str(path) in str(info.value)


def test_joint_map_naming_a_missing_bvh_joint_is_refused(ours: BvhClip) -> None:
    text = _bvh_text(ours, _Layout())
    with pytest.raises(ValidationError, match="has no joint 'Thigh'"):
        parse_bvh(text, unit_scale=1.0, joint_map={"LeftUpLeg": "Thigh"})
    with pytest.raises(ValidationError, match="several of our joints"):
        parse_bvh(text, unit_scale=1.0, joint_map={"LeftUpLeg": "Hips", "RightUpLeg": "Hips"})


# --------------------------------------------------------------------------------------------
# From a real corpus clip (cgspeed names): the same motion under other exporters' layouts

_CGSPEED_TO_ASF = {
    "Hips": "hip",
    "LowerBack": "lowerback",
    "Spine": "upperback",
    "Spine1": "thorax",
    "Neck": "lowerneck",
    "Neck1": "upperneck",
    "Head": "head",
    **_sides(
        {
            "HipJoint": "{s}hipjoint",
            "UpLeg": "{s}femur",
            "Leg": "{s}tibia",
            "Foot": "{s}foot",
            "ToeBase": "{s}toes",
            "Shoulder": "{s}clavicle",
            "Arm": "{s}humerus",
            "ForeArm": "{s}radius",
            "Hand": "{s}wrist",
            "FingerBase": "{s}hand",
            "HandIndex1": "{s}fingers",
        }
    ),
    "LHipJoint": "lhipjoint",
    "RHipJoint": "rhipjoint",
    "LThumb": "lthumb",
    "RThumb": "rthumb",
}


@pytest.fixture(scope="module")
def corpus_clip() -> BvhClip:
    from tests.conftest import SHARED_DATA

    path = SHARED_DATA / "motion" / "corpus" / "cmu_02_01.bvh"
    if not path.is_file():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (only the project's CI has it)")
    full = read_bvh(path)
    return replace(full, frames=full.frames[::40], frame_time_s=full.frame_time_s * 40)


@pytest.fixture(scope="module")
def corpus_poses(corpus_clip: BvhClip) -> F64:
    """The corpus clip retargeted as it is (cgspeed names)."""
    return np.asarray(retarget_bvh(corpus_clip, BodyShape.from_height(1.75), iterations=20).poses)


def test_corpus_clip_with_asf_names_retargets_to_the_identical_pose(
    corpus_clip: BvhClip, corpus_poses: F64, shared_data: Path
) -> None:
    def asf(name: str) -> str:
        base = name.removesuffix("_End")
        return _CGSPEED_TO_ASF.get(base, base) + name[len(base) :]

    clip = replace(corpus_clip, joint_names=tuple(asf(n) for n in corpus_clip.joint_names))
    assert "lfemur" in clip.joint_names
    assert "ltoes_End" in clip.joint_names
    assert map_bvh_joints(clip).family.name == "cmu-asf"
    got = retarget_bvh(clip, BodyShape.from_height(1.75), iterations=20).poses
    np.testing.assert_array_equal(got, corpus_poses)


def test_corpus_clip_in_a_shogun_layout_retargets_to_the_same_pose(
    corpus_clip: BvhClip, corpus_poses: F64, shared_data: Path
) -> None:
    # Vicon Shogun spine: LowerBack -> Spine, split by an inserted Spine1, then Spine2 and the
    # chest Spine3; the hip joints dropped (CMU never rotates them).
    hipjoints = [corpus_clip.joint_index(n) for n in ("LHipJoint", "RHipJoint")]
    start = corpus_clip.channel_start
    assert not np.any(corpus_clip.frames[:, [start[j] + k for j in hipjoints for k in range(3)]])
    layout = _Layout(
        rename={"LowerBack": "Spine", "Spine": "Spine2", "Spine1": "Spine3"},
        insert={"Spine": "Spine1"},
        remove=frozenset({"LHipJoint", "RHipJoint"}),
    )
    clip = parse_bvh(_bvh_text(corpus_clip, layout), unit_scale=1.0)
    names = {k: clip.joint_names[v] for k, v in resolve_joint_map(clip).items()}
    assert (names["Spine2"], names["Spine1"]) == ("Spine3", "Spine2")
    shape = BodyShape.from_height(1.75)
    got = retarget_bvh(clip, shape, iterations=20).poses
    mine = forward_kinematics(got, shape).positions_m
    want = forward_kinematics(corpus_poses, shape).positions_m
    np.testing.assert_allclose(mine, want, atol=1e-6)


def test_cgspeed_corpus_clip_maps_as_it_always_did(corpus_clip: BvhClip) -> None:
    mapping = map_bvh_joints(corpus_clip)
    assert mapping.family.name == "cgspeed"
    names = {k: corpus_clip.joint_names[v] for k, v in resolve_joint_map(corpus_clip).items()}
    same = ("Shoulder", "Arm", "ForeArm", "Hand", "UpLeg", "Leg", "Foot", "ToeBase")
    assert names == {
        "Hips": "Hips",
        "Spine1": "Spine",
        "Spine2": "Spine1",
        "Neck": "Neck",
        "Head": "Head",
        "HeadEnd": "Head_End",
        **_sides({j: f"{{side}}{j}" for j in same}),
        **_sides({"HandEnd": "{side}FingerBase", "ToeEnd": "{side}ToeBase_End"}),
    }
