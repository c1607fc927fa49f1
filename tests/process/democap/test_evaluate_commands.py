"""Tests of evaluation (orientations, metrics on the committed model) and the CLI."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocaprig.cli import main
from mocaprig.process.democap import demo_figures
from mocaprig.process.democap.checkpoint import DEFAULT_CHECKPOINT
from mocaprig.process.democap.config import DemocapConfig
from mocaprig.process.democap.dataset import make_pool
from mocaprig.process.democap.evaluate import (
    EVAL_JOINTS,
    SEGMENTS,
    evaluate,
    segment_quaternions,
    torso_tilt_deg,
)
from mocaprig.process.democap.infer import DemocapPredictor
from mocaprig.process.democap.train import TrainOptions, train
from mocaprig.process.metrics import quaternion_angle_deg

needs_ckpt = pytest.mark.skipif(
    not DEFAULT_CHECKPOINT.is_file(), reason="the committed lite checkpoint is absent"
)


def test_eval_joints_drop_the_toes() -> None:
    assert len(EVAL_JOINTS) == 17
    assert 14 not in EVAL_JOINTS
    assert 18 not in EVAL_JOINTS


def test_segment_orientations_follow_a_rigid_rotation() -> None:
    pool = make_pool(0, "test", takes=1, seconds=0.2)
    j, m = pool[0].joints_m[:1], pool[0].markers_m[:1]
    q0 = segment_quaternions(j, m)
    assert q0.shape == (1, len(SEGMENTS), 4)
    rot = Rotation.from_euler("z", 25.0, degrees=True).as_matrix()
    q1 = segment_quaternions(j @ rot.T, m @ rot.T)
    np.testing.assert_allclose(quaternion_angle_deg(q1, q0), 25.0, atol=1e-6)
    # moving a marker across the segment twists the frame; the angle is seen
    m2 = m.copy()
    m2[0, 30] += [0.0, 0.0, 0.05]  # RELB, the upper arm's marker pair
    assert quaternion_angle_deg(segment_quaternions(j, m2), q0).max() > 1.0


def test_evaluate_reports_all_figures_for_a_tiny_model(
    tmp_path: Path, tiny_config: DemocapConfig
) -> None:
    ck = train(tmp_path / "t.pt", TrainOptions(epochs=1, takes=2, threads=1), config=tiny_config)
    rep = evaluate(DemocapPredictor(ck), seed=1, num_cameras=3, frames_per_take=2)
    d = rep.to_dict()
    assert d["frames"] == 12
    assert d["num_cameras"] == 3
    assert set(d["per_action_mm"]) == {
        "clap",
        "jumping_jacks",
        "punch_kick",
        "squat",
        "wave",
        "karate",
    }
    assert len(d["per_joint_mm"]) == 17
    assert len(d["pck_curve"]) == 31
    assert d["mpjpe_mm"] > 0
    assert 0 <= d["pck50"] <= 1
    assert d["mpjae_deg"] >= 0
    assert 0.5 < d["markers_seen"] <= 1.0


# The committed checkpoint (449 epochs on CPU) on these small sets (48 frames, seeds 11-13,
# one torch thread, 2026-12-07): the network alone, single shot 32.2 / 33.6 / 44.3 mm MPJPE,
# PCK@50 0.843 / 0.828 / 0.767, its 3-turn rotation ensemble 23.7 / 23.2 / 29.7 mm, >= 0.897;
# with the skeleton solve (the default; the bank, the re-solve, the rig's views and crop box)
# 8.6 / 8.9 / 9.7 mm, >= 0.993 from the single shot and 8.2 / 8.8 / 8.9 mm, >= 0.993 from the
# ensemble (an earlier solve with the 377-epoch network, as this test first measured it:
# 10.8 / 12.4 / 17.4 and 10.5 / 9.1 / 11.9 mm). The bounds leave about 20 % over
# the worst of those, so a worse checkpoint, a broken solve or a broken pipeline fails; the
# network alone keeps its own bounds (the live path runs it without the solve).
_BOUNDS = {  # (rotations, solve) -> (MPJPE bound mm, PCK@50 floor)
    (1, False): (53.0, 0.64),
    (3, False): (36.0, 0.84),
    (1, True): (12.0, 0.98),
    (3, True): (11.0, 0.98),
}


@needs_ckpt
@pytest.mark.parametrize(("rotations", "solve"), list(_BOUNDS))
@pytest.mark.parametrize("seed", [11, 12, 13])
@pytest.mark.slow
def test_committed_lite_model_accuracy_on_held_out_data(
    seed: int, rotations: int, solve: bool
) -> None:
    rep = evaluate(
        DemocapPredictor(rotations=rotations, solve=solve),
        seed=seed,
        num_cameras=4,
        frames_per_take=8,
    )
    bound_mm, pck_floor = _BOUNDS[rotations, solve]
    assert rep.metrics.mpjpe_mm < bound_mm
    assert rep.metrics.pck50 > pck_floor


@needs_ckpt
def test_demo_figures_are_quick_and_complete() -> None:
    calls: list[tuple[str, int, int]] = []
    d = demo_figures(frames_per_take=4, progress=lambda *call: calls.append(call))
    assert {"mpjpe_mm", "mpmpe_mm", "pck50", "mpjae_deg", "frames"} <= set(d)
    assert d["frames"] == 24
    assert d["config"] == "lite"
    # each inference's frames, from none to all, in the order they run
    assert [c for c in calls if c[1] in (0, 24)] == [
        (name, done, 24) for name in ("solve", "network", "single shot") for done in (0, 24)
    ]


@needs_ckpt
def test_cli_eval_json(capsys: pytest.CaptureFixture[str]) -> None:
    # the JSON's shape, not the solve's accuracy (the accuracy tests run the solve)
    args = ["democap", "eval", "--frames", "2", "--all-cameras", "--no-solve", "--json"]
    assert main(args) == 0
    out = json.loads(capsys.readouterr().out)
    assert {"mpjpe_mm", "mpmpe_mm", "pck50"} <= set(out)
    assert set(out["by_cameras"]) == {"4", "3", "2"}


@needs_ckpt
def test_cli_eval_draws_each_figures_frames_as_they_are_estimated(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # stderr is no terminal under pytest: --progress always draws anyway
    args = ["democap", "eval", "--frames", "1", "--all-cameras", "--no-solve"]
    assert main(["--progress", "always", *args]) == 0
    err = capsys.readouterr().err
    for k in (4, 3, 2):  # one line per figure, ending at its 6 frames (1 per take)
        assert re.search(rf"democap eval: in-distribution, {k} cameras \[#+\] 6/6", err), err
    assert main(["--progress", "always", *args, "--json"]) == 0
    assert "\r" not in capsys.readouterr().err


@needs_ckpt
def test_evaluate_reports_the_frames_estimated_after_each_batch() -> None:
    calls: list[tuple[int, int]] = []
    rep = evaluate(
        DemocapPredictor(rotations=1, solve=False),
        pool=make_pool(0, "test", takes=1, seconds=0.5),
        frames_per_take=5,
        batch=2,
        progress=lambda done, total: calls.append((done, total)),
    )
    n = rep.frames_requested - rep.skipped_frames
    assert calls == [(0, n), *((k, n) for k in range(2, n, 2)), (n, n)]


def test_torso_tilt_is_the_hips_to_neck_angle_from_the_vertical() -> None:
    from mocaprig.process.body import DEMOCAP_JOINTS

    j = np.zeros((3, len(DEMOCAP_JOINTS), 3))
    hips, neck = DEMOCAP_JOINTS.index("Hips"), DEMOCAP_JOINTS.index("Neck")
    j[:, hips] = [0.0, 0.0, 1.0]
    j[0, neck] = [0.0, 0.0, 1.5]  # upright
    j[1, neck] = [0.0, 0.3, 1.3]  # bent forward 45 degrees
    j[2, neck] = [0.5, 0.0, 1.0]  # bent double, sideways
    np.testing.assert_allclose(torso_tilt_deg(j), [0.0, 45.0, 90.0], atol=1e-9)
    assert torso_tilt_deg(j).shape == (3,)
    assert j[1, neck, 1] == 0.3  # the input is untouched


@needs_ckpt
def test_cli_eval_gives_figures_by_torso_tilt_over_every_frame_and_inside(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # the bins' bookkeeping, whatever the estimator (the network alone: quicker)
    args = ["democap", "eval", "--freestyle", "--frames", "4", "--no-solve", "--json"]
    assert main(args) == 0
    out = json.loads(capsys.readouterr().out)
    bins, inside = out["per_torso_tilt"], out["inside_volume"]["per_torso_tilt"]
    assert list(bins) == ["0-20", "20-40", "40-60", "60-180"]
    assert sum(b["frames"] for b in bins.values()) == out["frames"]
    assert sum(b["frames"] for b in inside.values()) == out["inside_volume"]["frames"]
    for b in bins.values():
        assert (b["mpjpe_mm"] is None) == (b["frames"] == 0)
    # the frame-weighted bins give back the overall MPJPE
    total = sum(b["mpjpe_mm"] * b["frames"] for b in bins.values() if b["frames"])
    assert total / out["frames"] == pytest.approx(out["mpjpe_mm"], rel=1e-9)
    assert main(["democap", "eval", "--freestyle", "--frames", "2", "--no-solve"]) == 0
    assert "by the torso's tilt from the vertical" in capsys.readouterr().out


@needs_ckpt
def test_cli_eval_on_held_out_random_key_poses(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["democap", "eval", "--freestyle", "--frames", "2", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["motion"] == "freestyle (held-out)"
    assert out["motion_trained_on"] is False
    assert set(out["per_action_mm"]) == {"freestyle"}
    bad = ["democap", "eval", "--freestyle", "--motion", "x.bvh", "--frames", "1"]
    assert main(bad) != 0
    assert "x.bvh" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_train_then_resume_then_eval(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ck = tmp_path / "cli.pt"
    base = ["democap", "train", "--out", str(ck), "--takes", "1", "--samples-per-epoch", "2"]
    base += ["--batch-size", "2", "--threads", "1", "--no-corpus"]
    assert main([*base, "--epochs", "1", "--json"]) == 0
    first = json.loads(capsys.readouterr().out)
    assert first["epochs"] == 1
    assert first["config"] == "lite"
    assert main([*base, "--epochs", "1"]) == 1  # exists: refused, nothing overwritten
    capsys.readouterr()
    assert main([*base, "--epochs", "2", "--resume", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["epochs"] == 2
    assert main(["democap", "eval", "--ckpt", str(ck), "--frames", "1"]) == 0
    assert "in-distribution, 4 cameras: MPJPE" in capsys.readouterr().out


@pytest.mark.slow
def test_cli_eval_on_a_bvh_motion(shared_data: Path, capsys: pytest.CaptureFixture[str]) -> None:
    if not DEFAULT_CHECKPOINT.is_file():
        pytest.skip("the committed lite checkpoint is absent")
    bvh = shared_data / "motion" / "cmu_131_02_scaled.bvh"
    assert main(["democap", "eval", "--motion", str(bvh), "--frames", "8", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["frames"] == 8
    assert out["mpjpe_mm"] > 0


def test_evaluate_calibrates_each_takes_subject_when_the_predictor_does() -> None:
    calls: list[tuple[int, int]] = []
    rep = evaluate(
        DemocapPredictor(rotations=1, pose_bank=False, subject_calibration=1),
        pool=make_pool(0, "test", takes=2, seconds=0.5),
        frames_per_take=4,
        progress=lambda done, total: calls.append((done, total)),
    )
    n = rep.frames_requested - rep.skipped_frames
    assert rep.subject_calibration == 1
    assert rep.to_dict()["subject_calibration"] == 1
    assert calls[0] == (0, n)
    assert calls[-1] == (n, n)
    assert len(calls) == 3  # once per take
    assert rep.metrics.mpjpe_mm < 60.0
    # the same run's first solve, every frame on its own, is what the plain predictor gives
    plain = evaluate(
        DemocapPredictor(rotations=1, pose_bank=False),
        pool=make_pool(0, "test", takes=2, seconds=0.5),
        frames_per_take=4,
    )
    first = rep.to_dict()["frame_by_frame"]
    assert first["mpjpe_mm"] == pytest.approx(plain.metrics.mpjpe_mm, abs=1e-3)
    assert first["inside_volume"]["share"] == rep.inside_share
    assert "frame_by_frame" not in plain.to_dict()


def test_cli_eval_refuses_a_subject_calibration_without_the_solve(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["democap", "eval", "--subject-calibration", "1", "--no-solve"]) != 0
    assert "--subject-calibration" in capsys.readouterr().err
