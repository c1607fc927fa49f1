"""``process.body.bvh_export``: our poses as BVH, read back by our own BVH reader."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body.bvh import bvh_global_positions, parse_bvh, read_bvh
from mocaprig.process.body.bvh_export import (
    Y_UP_FROM_Z_UP,
    BvhWriter,
    bvh_joint_name,
    bvh_text,
    write_bvh,
)
from mocaprig.process.body.kinematics import clamp_to_limits, forward_kinematics
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.body.skeleton import JOINTS


def _poses(seed: int, frames: int = 12) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = rng.normal(0.0, 0.7, (frames, 33))
    q[:, 3:6] = rng.normal(0.0, 1.0, (frames, 3))
    return clamp_to_limits(q)


def _positions(clip_text: str, up: str) -> np.ndarray:
    clip = parse_bvh(clip_text, unit_scale=0.01)
    pos = bvh_global_positions(clip)
    if up == "y":
        pos = pos @ Y_UP_FROM_Z_UP  # back to our Z-up world
    idx = [clip.joint_index(bvh_joint_name(j)) for j in range(len(JOINTS))]
    return pos[:, idx]


@pytest.mark.parametrize("up", ["y", "z"])
def test_bvh_reads_back_to_our_forward_kinematics(up: str) -> None:
    shape = BodyShape.from_height(1.72)
    q = _poses(seed=1)
    got = _positions(bvh_text(q, shape, rate_hz=1000.0, up=up), up)  # type: ignore[arg-type]
    want = forward_kinematics(q, shape).positions_m
    assert np.abs(got - want).max() < 1e-6  # 6 decimals of cm and degrees


def test_y_up_file_stands_the_body_upright_along_y() -> None:
    shape = BodyShape.from_height(1.8)
    q = np.zeros((1, 33))
    q[0, 3:6] = (0.0, 0.0, shape.hips_height_m)
    clip = parse_bvh(bvh_text(q, shape, rate_hz=100.0), unit_scale=0.01)
    pos = bvh_global_positions(clip)[0]
    head = pos[clip.joint_index(bvh_joint_name(JOINTS.index("HeadEnd")))]
    assert head[1] == pytest.approx(1.8, abs=0.01)  # standing height along +Y


def test_hierarchy_has_every_joint_and_the_rate() -> None:
    shape = BodyShape.from_height(1.6)
    clip = parse_bvh(bvh_text(_poses(seed=2, frames=3), shape, rate_hz=1000.0))
    assert clip.num_joints == len(JOINTS)
    assert clip.num_frames == 3
    assert clip.rate_hz == pytest.approx(1000.0)
    assert clip.unit_scale == pytest.approx(0.01)  # centimetres detected on reading
    assert bvh_joint_name(JOINTS.index("HeadEnd")) == "Head_End"
    assert clip.channels[0][:3] == ("Xposition", "Yposition", "Zposition")


def test_write_bvh_refuses_to_overwrite_and_keeps_the_poses(tmp_path: Path) -> None:
    shape = BodyShape.from_height(1.75)
    q = _poses(seed=3, frames=4)
    before = q.copy()
    path = write_bvh(tmp_path / "a.bvh", q, shape, rate_hz=1000.0)
    np.testing.assert_array_equal(q, before)
    assert read_bvh(path).num_frames == 4
    with pytest.raises(ProcessingError, match="--overwrite"):
        write_bvh(path, q, shape, rate_hz=1000.0)
    write_bvh(path, q[:2], shape, rate_hz=1000.0, overwrite=True)
    assert read_bvh(path).num_frames == 2


def test_bad_poses_are_rejected() -> None:
    shape = BodyShape.from_height(1.75)
    with pytest.raises(ValidationError):
        bvh_text(np.zeros((3, 32)), shape, rate_hz=100.0)
    with pytest.raises(ValidationError, match="no poses"):
        bvh_text(np.zeros((0, 33)), shape, rate_hz=100.0)
    q = np.zeros((2, 33))
    q[1, 4] = np.nan
    with pytest.raises(ValidationError):
        bvh_text(q, shape, rate_hz=100.0)


def test_bvh_written_in_blocks_is_the_text_of_all_poses(tmp_path: Path) -> None:
    shape = BodyShape.from_height(1.7)
    q = _poses(7, frames=7)
    path = tmp_path / "blocks.bvh"
    with BvhWriter(path, shape, rate_hz=1000.0) as w:
        for i0, i1 in ((0, 3), (3, 4), (4, 7)):
            w.write(q[i0:i1])
    assert path.read_text() == bvh_text(q, shape, rate_hz=1000.0)
    assert [p.name for p in tmp_path.iterdir()] == ["blocks.bvh"]  # no partial files left


def test_an_interrupted_bvh_leaves_no_file(tmp_path: Path) -> None:
    shape = BodyShape.from_height(1.7)

    def interrupted() -> None:
        with BvhWriter(tmp_path / "r.bvh", shape, rate_hz=100.0) as w:
            w.write(_poses(2, frames=2))
            raise RuntimeError("stopped")

    with pytest.raises(RuntimeError, match="stopped"):
        interrupted()
    assert list(tmp_path.iterdir()) == []
    empty = BvhWriter(tmp_path / "e.bvh", shape, rate_hz=100.0)
    with pytest.raises(ValidationError, match="no poses"):
        empty.close()
    assert list(tmp_path.iterdir()) == []
