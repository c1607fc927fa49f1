"""The pose prior: built from clips, saved and read, and what it does to the solve."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mocaprig.cli import main
from mocaprig.errors import ProcessingError, RecordingError, ValidationError
from mocaprig.process.body import (
    DOF_LIMITS_RAD,
    DOF_NAMES,
    MARKER_NAMES,
    MarkerSet,
    make_motion,
)
from mocaprig.process.body.bvh import BvhClip, parse_bvh
from mocaprig.process.body.bvh_export import bvh_text
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.body.skeleton import ROOT_DIM
from mocaprig.process.democap import solve as S
from mocaprig.process.democap.corpus import load_split
from mocaprig.process.democap.pose_prior import (
    DEFAULT_POSE_PRIOR,
    PosePrior,
    build_pose_prior,
    load_pose_prior,
    save_pose_prior,
)
from mocaprig.process.democap.simdata import pose_frames


def _clip(name: str, seed: int) -> BvhClip:
    shape = BodyShape.from_height(1.7)
    poses = make_motion(name, seconds=3.0, rng=np.random.default_rng(seed), rate_hz=30.0).poses
    return parse_bvh(bvh_text(poses, shape, rate_hz=30.0), unit_scale=0.01)


def test_a_built_prior_is_likeliest_on_the_poses_it_was_made_from() -> None:
    clips = [_clip("squat", 1), _clip("wave", 2)]
    prior = build_pose_prior(clips, components=2, rate_hz=30.0, seed=0)
    assert 1 <= len(prior) <= 2
    assert prior.source == tuple(c.name for c in clips)
    assert prior.costs.min() == 0.0
    lo, hi = DOF_LIMITS_RAD[:, 0], DOF_LIMITS_RAD[:, 1]
    assert ((prior.means >= lo - 1e-9) & (prior.means <= hi + 1e-9)).all()
    seen = make_motion("squat", seconds=1.0, rng=np.random.default_rng(1), rate_hz=10.0)
    odd = np.tile((lo + hi) / 2, (len(seen.poses), 1))
    odd[:, DOF_NAMES.index("right_elbow_flexion")] = hi[DOF_NAMES.index("right_elbow_flexion")]
    odd[:, DOF_NAMES.index("left_shoulder_abduction")] = hi[
        DOF_NAMES.index("left_shoulder_abduction")
    ]
    assert np.median(prior.energy(seen.poses[:, ROOT_DIM:])) < prior.energy(odd).min()
    # the same clips and seed give the same prior
    again = build_pose_prior(clips, components=2, rate_hz=30.0, seed=0)
    np.testing.assert_array_equal(again.means, prior.means)


def test_building_a_prior_from_too_little_is_refused() -> None:
    with pytest.raises(ValidationError, match="at least one clip"):
        build_pose_prior([])
    with pytest.raises(ValidationError, match="components must be"):
        build_pose_prior([_clip("squat", 1)], components=0)
    with pytest.raises(ValidationError, match="too few"):
        build_pose_prior([_clip("squat", 1)], components=2, rate_hz=5.0)


def test_a_prior_that_is_not_one_is_refused() -> None:
    good = load_pose_prior()
    with pytest.raises(ValidationError, match="positive definite"):
        PosePrior(good.means, -good.precisions, good.costs, good.source)
    with pytest.raises(ValidationError, match="precisions"):
        PosePrior(good.means, good.precisions[:, :5], good.costs, good.source)


def test_a_prior_round_trips_and_is_not_overwritten(tmp_path: Path) -> None:
    prior = load_pose_prior()
    path = save_pose_prior(prior, tmp_path / "prior.npz")
    back = load_pose_prior(path)
    np.testing.assert_array_equal(back.precisions, prior.precisions)
    assert back.source == prior.source
    with pytest.raises(RecordingError, match="exists"):
        save_pose_prior(prior, path)
    save_pose_prior(prior, path, overwrite=True)


def test_a_corrupt_prior_file_is_named(tmp_path: Path) -> None:
    bad = tmp_path / "prior.npz"
    bad.write_bytes(b"not a prior")
    with pytest.raises(ProcessingError, match=r"prior\.npz.*pose-prior"):
        load_pose_prior(bad)


def test_the_committed_prior_is_the_train_split_s() -> None:
    prior = load_pose_prior(DEFAULT_POSE_PRIOR)
    assert len(prior) == 8
    assert set(prior.source) == {c.name for c in load_split().in_split("train")}


def _hidden_forearm() -> tuple[list[np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
    """Frames of a body whose right forearm and hand left no point in the cloud, and an
    estimate whose right elbow is bent the wrong way round: (clouds, markers (1, B, 53, 3),
    joints (1, B, 19, 3), the seen markers (53,) bool)."""
    rng = np.random.default_rng(4)
    shape = BodyShape.from_height(1.75)
    ms = MarkerSet.for_shape(shape)
    motion = make_motion("punch_kick", seconds=1.0, rng=rng, rate_hz=5.0, shape=shape)
    pf = pose_frames(motion, shape, ms)
    hidden = np.isin(MARKER_NAMES, ("RFRM", "RIWR", "ROWR", "RIHAND", "ROHAND"))
    clouds = [m[~hidden] + rng.normal(0.0, 0.003, m[~hidden].shape) for m in pf.markers_m]
    bent = motion.poses.copy()
    k = ROOT_DIM + DOF_NAMES.index("right_elbow_flexion")
    bent[:, k] = DOF_LIMITS_RAD[k - ROOT_DIM, 1]
    wrong = pose_frames(replace(motion, poses=bent), shape, ms)
    return clouds, wrong.markers_m[None], wrong.joints_m[None], ~hidden


def test_the_prior_holds_a_limb_nothing_sees_and_leaves_the_seen_ones() -> None:
    clouds, mk, jt, seen = _hidden_forearm()
    opt = S.SolveOptions(limb_search=False, bend_starts_rad=())
    prior = load_pose_prior()
    plain = S.solve_skeleton(clouds, mk, jt, options=opt)
    held = S.solve_skeleton(clouds, mk, jt, options=opt, pose_prior=prior)
    assert (
        prior.energy(held.poses[:, ROOT_DIM:]).mean()
        < prior.energy(plain.poses[:, ROOT_DIM:]).mean()
    )
    # the seen markers stay where the cloud has them
    moved = np.linalg.norm(held.markers_m[:, seen] - plain.markers_m[:, seen], axis=-1)
    assert np.median(moved) < 0.002


def test_the_command_refuses_to_replace_a_prior_and_needs_the_corpus_s_clips(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "prior.npz"
    out.write_bytes(b"keep me")
    assert main(["democap", "pose-prior", "--out", str(out), "--corpus", str(tmp_path)]) == 1
    assert "--overwrite" in capsys.readouterr().err
    assert out.read_bytes() == b"keep me"
    fresh = tmp_path / "new.npz"
    assert main(["democap", "pose-prior", "--out", str(fresh), "--corpus", str(tmp_path)]) == 1
    assert "cmu_" in capsys.readouterr().err
    assert not fresh.exists()
