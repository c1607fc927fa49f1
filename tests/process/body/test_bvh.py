"""BVH reading, native forward kinematics and retargeting onto our skeleton."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body.bvh import (
    BvhClip,
    bvh_forward_kinematics,
    bvh_global_positions,
    bvh_rest_positions,
    bvh_to_body_frame,
    parse_bvh,
    read_bvh,
    resolve_joint_map,
    retarget_bvh,
    retarget_errors,
)
from mocaprig.process.body.kinematics import forward_kinematics, within_limits
from mocaprig.process.body.procedural import floor_clearance_m, make_motion
from mocaprig.process.body.shape import BodyShape
from tests.process.body._body_helpers import BVH_TO_BODY, motion_as_bvh


def _chain_bvh(order_root: str, order_mid: str, frames: list[list[float]]) -> str:
    """A 3-joint chain (root, mid, tip) plus an End Site, in metres."""
    lines = [
        "HIERARCHY",
        "ROOT Root",
        "{",
        "  OFFSET 0.0 0.0 0.0",
        f"  CHANNELS 6 Xposition Yposition Zposition {order_root}",
        "  JOINT Mid",
        "  {",
        "    OFFSET 0.0 0.5 0.1",
        f"    CHANNELS 3 {order_mid}",
        "    JOINT Tip",
        "    {",
        "      OFFSET 0.3 0.0 0.0",
        "      CHANNELS 3 Xrotation Yrotation Zrotation",
        "      End Site",
        "      {",
        "        OFFSET 0.0 0.0 0.2",
        "      }",
        "    }",
        "  }",
        "}",
        "MOTION",
        f"Frames: {len(frames)}",
        "Frame Time: 0.01",
    ]
    lines += [" ".join(f"{v:.6f}" for v in row) for row in frames]
    return "\n".join(lines) + "\n"


def _euler(order_words: str, values: list[float]) -> Rotation:
    """Independent reference: intrinsic Euler rotation in the listed channel order."""
    seq = "".join(w[0].upper() for w in order_words.split())
    return Rotation.from_euler(seq, values, degrees=True)


@pytest.mark.parametrize(
    ("order_root", "order_mid"),
    [
        ("Zrotation Yrotation Xrotation", "Zrotation Xrotation Yrotation"),
        ("Xrotation Yrotation Zrotation", "Yrotation Zrotation Xrotation"),
        ("Yrotation Xrotation Zrotation", "Xrotation Zrotation Yrotation"),
    ],
)
def test_global_positions_match_hand_composed_chain(order_root: str, order_mid: str) -> None:
    rng = np.random.default_rng(7)
    rows = []
    for _ in range(3):
        rows.append(
            [round(float(v), 6) for v in (*rng.normal(size=3), *rng.uniform(-170, 170, size=9))]
        )
    clip = parse_bvh(_chain_bvh(order_root, order_mid, rows), unit_scale=1.0)
    got_pos, got_rot = bvh_forward_kinematics(clip)
    assert clip.joint_names == ("Root", "Mid", "Tip", "Tip_End")
    assert clip.parents == (-1, 0, 1, 2)
    for f, row in enumerate(rows):
        r0 = _euler(order_root, row[3:6])
        r1 = r0 * _euler(order_mid, row[6:9])
        r2 = r1 * _euler("Xrotation Yrotation Zrotation", row[9:12])
        p0 = np.array(row[0:3])
        p1 = p0 + r0.apply([0.0, 0.5, 0.1])
        p2 = p1 + r1.apply([0.3, 0.0, 0.0])
        p3 = p2 + r2.apply([0.0, 0.0, 0.2])
        np.testing.assert_allclose(got_pos[f], [p0, p1, p2, p3], atol=1e-9)
        np.testing.assert_allclose(got_rot[f, 2], r2.as_matrix(), atol=1e-9)


def test_zero_frame_equals_rest_pose() -> None:
    clip = parse_bvh(
        _chain_bvh("Zrotation Yrotation Xrotation", "Zrotation Xrotation Yrotation", [[0.0] * 12])
    )
    np.testing.assert_allclose(bvh_global_positions(clip)[0], bvh_rest_positions(clip))
    np.testing.assert_allclose(bvh_rest_positions(clip)[3], [0.3, 0.5, 0.3])


def test_channel_columns_and_rate() -> None:
    clip = parse_bvh(
        _chain_bvh(
            "Zrotation Yrotation Xrotation", "Zrotation Xrotation Yrotation", [[0.0] * 12] * 4
        )
    )
    assert clip.channel_start == (0, 6, 9, 12)
    assert clip.num_frames == 4
    assert clip.rate_hz == pytest.approx(100.0)
    assert clip.channels[3] == ()


def test_unit_scale_scales_offsets_and_positions() -> None:
    row = [10.0, 20.0, 30.0] + [0.0] * 9
    text = _chain_bvh("Zrotation Yrotation Xrotation", "Zrotation Xrotation Yrotation", [row])
    clip = parse_bvh(text, unit_scale=0.01)
    np.testing.assert_allclose(clip.frames[0, :3], [0.1, 0.2, 0.3])
    np.testing.assert_allclose(clip.offsets_m[1], [0.0, 0.005, 0.001])


def _scaled_skeleton_bvh(leg: float) -> str:
    return "\n".join(
        [
            "HIERARCHY",
            "ROOT Hips",
            "{",
            "  OFFSET 0 0 0",
            "  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation",
            "  JOINT Head",
            "  {",
            f"    OFFSET 0 {leg} 0",
            "    CHANNELS 3 Zrotation Xrotation Yrotation",
            "    End Site",
            "    {",
            f"      OFFSET 0 {leg / 8} 0",
            "    }",
            "  }",
            "  JOINT Foot",
            "  {",
            f"    OFFSET 0 {-leg} 0",
            "    CHANNELS 3 Zrotation Xrotation Yrotation",
            "    End Site",
            "    {",
            "      OFFSET 0 0 1",
            "    }",
            "  }",
            "}",
            "MOTION",
            "Frames: 1",
            "Frame Time: 0.0083333",
            " ".join(["0"] * 12),
        ]
    )


@pytest.mark.parametrize(("leg", "scale"), [(0.85, 1.0), (85.0, 0.01), (850.0, 0.001)])
def test_unit_is_detected_from_skeleton_size(
    leg: float, scale: float, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.INFO, logger="mocaprig.process.body.bvh"):
        clip = parse_bvh(_scaled_skeleton_bvh(leg))
    assert clip.unit_scale == scale
    assert "reading lengths as" in caplog.text
    extent = np.ptp(bvh_rest_positions(clip)[:, 1])
    assert extent == pytest.approx(leg * 2.125 * scale)


def test_implausible_size_asks_for_unit_scale() -> None:
    with pytest.raises(ProcessingError, match="pass unit_scale="):
        parse_bvh(_scaled_skeleton_bvh(1e5))


def test_bad_unit_scale_is_rejected() -> None:
    with pytest.raises(ValidationError, match="unit_scale"):
        parse_bvh(_scaled_skeleton_bvh(0.85), unit_scale=-1.0)


_GOOD = _chain_bvh(
    "Zrotation Yrotation Xrotation", "Zrotation Xrotation Yrotation", [[0.0] * 12] * 2
)


@pytest.mark.parametrize(
    ("broken", "match"),
    [
        (_GOOD.replace("HIERARCHY", "HIERARCHX"), r"line 1: expected 'HIERARCHY'"),
        (_GOOD.replace("OFFSET 0.0 0.5 0.1", "OFFSET 0.0 zz 0.1"), r"line 8: expected a number"),
        (
            _GOOD.replace("CHANNELS 3 Zrotation", "CHANNELS 3 Wrotation"),
            r"line 9: .*unknown channel 'Wrotation'",
        ),
        (_GOOD.replace("CHANNELS 3 Zrotation", "CHANNELS x Zrotation"), r"line 9: .*channel count"),
        (_GOOD.replace("Frames: 2", "Frames: 3"), r"declares 3 frames, found 2"),
        (_GOOD.replace("Frames: 2", "Frames: 1"), r"more frame lines than the 1"),
        (_GOOD.replace("Frame Time: 0.01", "Frame Time: -1"), r"Frame Time must be > 0"),
        (_GOOD.replace("Frame Time: 0.01", "Frame Time: inf"), r"Frame Time must be > 0"),
        (_GOOD.replace("Frames: 2", "Frames: nan"), r"Frames must be a positive integer"),
        (_GOOD.replace("Frames: 2", "Frames: 1e999"), r"Frames must be a positive integer"),
        # A hostile count is refused before anything the size of it is allocated.
        (
            _GOOD.replace("Frames: 2", "Frames: 9223372036854775808"),
            r"declares \d+ frames, found 2",
        ),
        (
            _GOOD.replace("Frame Time: 0.01", "Frametime 0.01"),
            r"line 23: expected 'Frame Time: <number>'",
        ),
        (
            _GOOD.rstrip("\n") + " 1.0\n",
            r"line 25: frame 1 has 13 values, the hierarchy declares 12",
        ),
        (_GOOD.replace("MOTION", "}\nMOTION"), r"line 21: expected 'ROOT', found '}'"),
        (_GOOD.split("MOTION")[0], r"no MOTION section"),
        (
            _GOOD.replace(" ".join(["0.000000"] * 12) + "\n", "0 0 0 0 0 0 0 0 0 0 0 nan\n", 1),
            r"non-finite",
        ),
    ],
)
def test_malformed_bvh_names_source_line_and_problem(broken: str, match: str) -> None:
    with pytest.raises(ProcessingError, match=match) as info:
        parse_bvh(broken, unit_scale=1.0, source="walk.bvh")
    assert "walk.bvh" in str(info.value)


def test_unclosed_joint_is_reported() -> None:
    text = _GOOD.replace("      }\n    }\n  }\n}\nMOTION", "      }\n    }\nMOTION")
    with pytest.raises(ProcessingError, match="closing joint"):
        parse_bvh(text, unit_scale=1.0)


def test_missing_file_is_a_processing_error(tmp_path: Path) -> None:
    with pytest.raises(ProcessingError, match="cannot read BVH file"):
        read_bvh(tmp_path / "nope.bvh")


def test_clip_is_read_only() -> None:
    clip = parse_bvh(_GOOD, unit_scale=1.0)
    assert isinstance(clip, BvhClip)
    with pytest.raises(ValueError, match="read-only"):
        clip.frames[0, 0] = 1.0


def test_cmu_131_01_reads_995_frames_at_120_hz(shared_data: Path) -> None:
    clip = read_bvh(shared_data / "motion" / "cmu_131_01_scaled.bvh")
    assert clip.num_frames == 995
    assert clip.rate_hz == pytest.approx(120.0, rel=1e-3)
    assert clip.unit_scale == 1.0
    assert len(clip.joint_names) == 31 + 7  # 31 joints + 7 End Sites
    pos = bvh_global_positions(clip)
    feet = pos[:, [clip.joint_index("LeftToe_End"), clip.joint_index("RightToe_End")], 1]
    assert -0.05 < feet.min() < 0.05  # the floor is y = 0


# --------------------------------------------------------------------------------------------
# Retargeting

_C = BVH_TO_BODY


def test_our_skeleton_round_trips_through_bvh_positions() -> None:
    shape = BodyShape.from_height(1.7)
    motion = make_motion(
        "karate", seconds=0.5, rng=np.random.default_rng(0), rate_hz=60.0, shape=shape
    )
    clip = motion_as_bvh(np.array(motion.poses), shape, 60.0)
    got = bvh_global_positions(clip) @ _C.T
    want = forward_kinematics(motion.poses, shape).positions_m
    np.testing.assert_allclose(got, want, atol=1e-9)


def test_retarget_recovers_our_own_motion() -> None:
    shape = BodyShape.from_height(1.7)
    motion = make_motion(
        "punch_kick", seconds=1.0, rng=np.random.default_rng(1), rate_hz=30.0, shape=shape
    )
    clip = motion_as_bvh(np.array(motion.poses), shape, 30.0)
    ends = {f"{s}{e}": f"{s}{e}" for s in ("Left", "Right") for e in ("HandEnd", "ToeEnd")}
    got = retarget_bvh(clip, shape, joint_map={"HeadEnd": "HeadEnd", **ends}, iterations=100)
    assert got.num_frames == motion.num_frames
    assert got.rate_hz == pytest.approx(30.0)
    assert within_limits(got.poses).all()
    mine = forward_kinematics(got.poses, shape).positions_m
    want = forward_kinematics(motion.poses, shape).positions_m
    assert np.mean(np.linalg.norm(mine - want, axis=-1)) < 0.01
    report = retarget_errors(clip, got, shape, joint_map={"HeadEnd": "HeadEnd", **ends})
    assert report.bone_angle_error_deg < 1.0
    assert report.scale == pytest.approx(1.0, abs=0.01)


def test_cmu_axes_map_to_z_up_facing_plus_y(shared_data: Path) -> None:
    clip = read_bvh(shared_data / "motion" / "cmu_131_01_scaled.bvh")
    np.testing.assert_array_equal(bvh_to_body_frame(clip), _C)
    names = {k: clip.joint_names[v] for k, v in resolve_joint_map(clip).items()}
    assert names["LeftArm"] == "LeftShoulder"
    assert names["LeftShoulder"] == "LeftCollar"
    assert names["RightUpLeg"] == "RightHip"
    assert names["Spine2"] == "Chest2"


def test_unmappable_skeleton_asks_for_a_joint_map() -> None:
    clip = parse_bvh(_GOOD, unit_scale=1.0)
    with pytest.raises(ProcessingError, match="joint_map="):
        resolve_joint_map(clip)


def test_cmu_131_01_retargets_within_measured_error(shared_data: Path) -> None:
    """Measured on the full clip (995 frames, 60 L-BFGS iterations): mean bone-direction error
    ~7 deg, bone-normalised MPJPE ~5.5 cm (mostly the fixed clavicles and wrists); every 10th
    frame is used here to stay fast."""
    full = read_bvh(shared_data / "motion" / "cmu_131_01_scaled.bvh")
    clip = replace(full, frames=full.frames[::10], frame_time_s=full.frame_time_s * 10)
    shape = BodyShape.from_height(1.75)
    motion = retarget_bvh(clip, shape)
    assert within_limits(motion.poses).all()
    report = retarget_errors(clip, motion, shape)
    assert report.bone_angle_error_deg < 10.0
    assert report.mpjpe_bone_normalised_m < 0.07
    kin = forward_kinematics(motion.poses, shape)
    clearance = floor_clearance_m(kin, shape)
    assert abs(float(np.median(clearance))) < 1e-3  # lifted crouch frames move it slightly
    # the clip crouches deeper than our ankles allow; no sole may sink through the floor
    assert clearance.min() > -1e-9
    # upright: the pelvis' up axis (body +Z) points up (the subject leans up to ~40 deg)
    assert np.all(kin.rotations[:, 0, 2, 2] > 0.6)
