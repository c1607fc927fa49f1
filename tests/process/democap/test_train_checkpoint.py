"""Tests of training (determinism, resume) and checkpoints (round trip, mismatch errors)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body import BodyShape, BvhClip, make_motion
from mocaprig.process.democap.checkpoint import (
    DEFAULT_CHECKPOINT,
    FORMAT_VERSION,
    load_checkpoint,
    save_checkpoint,
)
from mocaprig.process.democap.config import DemocapConfig
from mocaprig.process.democap.dataset import (
    TRAIN_ACTIONS,
    jittered_observation,
    make_batch,
    make_pool,
    make_sample,
    pool_from_bvh,
)
from mocaprig.process.democap.infer import DemocapPredictor
from mocaprig.process.democap.simdata import NOMINAL_OBSERVATION, PERTURBATION_KNOBS
from mocaprig.process.democap.train import TrainOptions, resolve_device, train
from tests.process.body._body_helpers import motion_as_bvh

_OPTS = TrainOptions(epochs=2, seed=3, takes=2, threads=1)


def _weights(path: Path) -> list[torch.Tensor]:
    return [t.clone() for t in load_checkpoint(path).model.state_dict().values()]


def test_training_is_deterministic_and_resume_matches(
    tmp_path: Path, tiny_config: DemocapConfig
) -> None:
    full = tmp_path / "full.pt"
    train(full, _OPTS, config=tiny_config)
    part = tmp_path / "part.pt"
    train(part, TrainOptions(epochs=1, seed=3, takes=2, threads=1), config=tiny_config)
    ck = train(part, _OPTS, resume=True)
    assert ck.epoch == 2
    assert len(ck.history) == 2
    for a, b in zip(_weights(full), _weights(part), strict=True):
        torch.testing.assert_close(a, b)
    hist = load_checkpoint(full).history
    assert {"loss", "val_mpjpe_mm", "lr"} <= set(hist[-1])


def test_resume_with_a_learning_rate_restarts_the_decay_from_it(
    tmp_path: Path, tiny_config: DemocapConfig
) -> None:
    out = tmp_path / "ft.pt"
    train(out, TrainOptions(epochs=1, seed=3, takes=2, threads=1), config=tiny_config)
    with pytest.raises(ValidationError, match="lr must be > 0"):
        train(out, TrainOptions(epochs=2, seed=3, takes=2, threads=1, lr=0.0), resume=True)
    ck = train(out, TrainOptions(epochs=2, seed=3, takes=2, threads=1, lr=5e-4), resume=True)
    decayed = 2 % tiny_config.lr_decay_epochs == 0
    expected = 5e-4 * (tiny_config.lr_decay if decayed else 1.0)
    assert ck.history[-1]["lr"] == pytest.approx(expected)
    assert ck.history[0]["lr"] != pytest.approx(expected)


@pytest.mark.slow
def test_batches_simulated_in_worker_processes_train_the_same_weights(
    tmp_path: Path, tiny_config: DemocapConfig
) -> None:
    here = tmp_path / "here.pt"
    train(here, TrainOptions(epochs=1, seed=3, takes=2, threads=1), config=tiny_config)
    there = tmp_path / "there.pt"
    opts = TrainOptions(epochs=1, seed=3, takes=2, threads=1, data_workers=2)
    train(there, opts, config=tiny_config)
    for a, b in zip(_weights(here), _weights(there), strict=True):
        torch.testing.assert_close(a, b)


def test_training_device_choices() -> None:
    assert resolve_device("cpu") == torch.device("cpu")
    want = "cuda" if torch.cuda.is_available() else "cpu"
    assert resolve_device("auto").type == want
    if not torch.cuda.is_available():
        with pytest.raises(ValidationError, match="no CUDA device"):
            resolve_device("cuda")
    with pytest.raises(ValidationError, match="device must be"):
        resolve_device("tpu")  # type: ignore[arg-type]


def test_train_refuses_to_overwrite(tmp_path: Path, tiny_config: DemocapConfig) -> None:
    out = tmp_path / "x.pt"
    out.write_bytes(b"")
    with pytest.raises(ValidationError, match="exists"):
        train(out, _OPTS, config=tiny_config)


def test_checkpoint_round_trip_and_mismatches(tmp_path: Path, tiny_config: DemocapConfig) -> None:
    out = tmp_path / "c.pt"
    ck = train(out, TrainOptions(epochs=1, seed=0, takes=2, threads=1), config=tiny_config)
    back = load_checkpoint(out)
    assert back.config == tiny_config
    assert back.epoch == 1
    data = torch.load(out, weights_only=True)
    for key, value, pattern in (
        ("format_version", FORMAT_VERSION + 1, "format version"),
        ("marker_names", ["A"] * 53, "marker names"),
        ("joint_names", ["J"] * 19, "joint names"),
        ("format", "other", "not a DeMoCap checkpoint"),
    ):
        bad = dict(data)
        bad[key] = value
        p = tmp_path / f"bad_{key}.pt"
        torch.save(bad, p)
        with pytest.raises(ProcessingError, match=pattern):
            load_checkpoint(p)
    bad = dict(data)
    bad["config"] = {**data["config"], "width": 8}
    torch.save(bad, tmp_path / "w.pt")
    with pytest.raises(ProcessingError, match="do not match the stored config"):
        load_checkpoint(tmp_path / "w.pt")
    with pytest.raises(ProcessingError, match="does not exist"):
        load_checkpoint(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_text("not torch")
    with pytest.raises(ProcessingError, match="cannot be read"):
        load_checkpoint(tmp_path / "junk.pt")
    save_checkpoint(ck, tmp_path / "again.pt")
    assert load_checkpoint(tmp_path / "again.pt").epoch == 1


def test_batches_are_deterministic_and_normalised() -> None:
    pool = make_pool(0, "train", takes=2, seconds=1.0)
    a = make_batch(pool, np.random.default_rng(1), 3)
    b = make_batch(pool, np.random.default_rng(1), 3)
    torch.testing.assert_close(a.front, b.front)
    torch.testing.assert_close(a.joints, b.joints)
    assert a.front.shape == (3, 1, 160, 160)
    assert 0.0 < float(a.joints.mean()) < 1.0


def test_observation_jitter_gives_each_sample_its_own_d415_model() -> None:
    pool = make_pool(0, "train", takes=2, seconds=1.0)
    plain = make_batch(pool, np.random.default_rng(1), 4)
    # jitter 0 is the nominal model and draws no numbers: the batches do not move
    zero = make_batch(pool, np.random.default_rng(1), 4, observation_jitter=0.0)
    torch.testing.assert_close(plain.front, zero.front)
    a = make_batch(pool, np.random.default_rng(1), 4, observation_jitter=0.3)
    b = make_batch(pool, np.random.default_rng(1), 4, observation_jitter=0.3)
    torch.testing.assert_close(a.front, b.front)
    assert not torch.equal(a.front, plain.front)
    with pytest.raises(ValidationError, match="observation jitter must be in"):
        make_batch(pool, np.random.default_rng(1), 1, observation_jitter=1.0)


def test_jittered_observation_stays_in_its_range_and_moves_every_knob() -> None:
    rng = np.random.default_rng(5)
    state = rng.bit_generator.state
    assert jittered_observation(rng, 0.0) is NOMINAL_OBSERVATION
    assert rng.bit_generator.state == state
    draws = [jittered_observation(rng, 0.25) for _ in range(200)]
    for knob in PERTURBATION_KNOBS:
        v = np.array([getattr(d, knob) for d in draws])
        assert v.min() >= 0.75
        assert v.max() <= 1.25
        assert v.std() > 0.1
    for bad in (-0.1, 1.0):
        with pytest.raises(ValidationError, match="observation jitter"):
            jittered_observation(rng, bad)


def test_train_records_its_observation_jitter_and_refuses_a_bad_one(
    tmp_path: Path, tiny_config: DemocapConfig
) -> None:
    out = tmp_path / "j.pt"
    opts = TrainOptions(epochs=1, seed=3, takes=2, threads=1, observation_jitter=0.3)
    ck = train(out, opts, config=tiny_config)
    assert ck.history[-1]["observation_jitter"] == pytest.approx(0.3)
    bad = TrainOptions(epochs=1, observation_jitter=-0.5)
    with pytest.raises(ValidationError, match="observation_jitter must be in"):
        train(tmp_path / "k.pt", bad, config=tiny_config)


def test_train_and_test_pools_use_different_bodies() -> None:
    tr = make_pool(0, "train", takes=3, seconds=0.5)
    te = make_pool(0, "test", takes=3, seconds=0.5)
    for t in tr:
        for s in te:
            assert not np.allclose(t.caps_radius_m, s.caps_radius_m)


def test_predictor_inverts_the_normalisation(tiny_config: DemocapConfig, tmp_path: Path) -> None:
    """Whatever the (untrained) network says, outputs land in the cloud's world box."""
    ck = train(tmp_path / "t.pt", TrainOptions(epochs=1, takes=2, threads=1), config=tiny_config)
    pred = DemocapPredictor(ck)
    pool = make_pool(0, "test", takes=1, seconds=0.5)
    s = make_sample(pool[0], 3, np.random.default_rng(0), augment=False, size_px=64)
    out = pred.predict(s.raw_m)
    assert out.markers_m.shape == (53, 3)
    assert out.joints_m.shape == (19, 3)
    lo, hi = s.raw_m.min(axis=0) - 0.2, s.raw_m.max(axis=0) + 0.2
    assert np.all((out.joints_m > lo) & (out.joints_m < hi))
    with pytest.raises(ValidationError, match="at least 2"):
        pred.predict(np.zeros((1, 3)))


@pytest.mark.skipif(not DEFAULT_CHECKPOINT.is_file(), reason="no committed lite checkpoint")
def test_committed_checkpoint_loads_with_lite_config() -> None:
    ck = load_checkpoint(DEFAULT_CHECKPOINT)
    assert ck.config.name == "lite"
    assert ck.epoch >= 1
    assert DEFAULT_CHECKPOINT.stat().st_size < 8 * 2**20


def test_training_pool_mixes_random_key_poses_and_the_test_pool_does_not() -> None:
    train_actions = [t.action for t in make_pool(0, "train", takes=9, seconds=0.5)]
    test_actions = [t.action for t in make_pool(0, "test", takes=9, seconds=0.5)]
    assert train_actions[:6] == list(TRAIN_ACTIONS)
    assert train_actions[6:] == ["freestyle"] * 3
    assert "freestyle" not in test_actions
    assert set(test_actions) == set(TRAIN_ACTIONS)


def _clip(name: str) -> BvhClip:
    shape = BodyShape.from_height(1.7)
    motion = make_motion("wave", seconds=1.0, rng=np.random.default_rng(1), rate_hz=60.0)
    return motion_as_bvh(np.array(motion.poses), shape, 60.0, name=name)


@pytest.mark.slow
def test_bvh_clips_join_the_training_pool_and_the_checkpoint_names_them(
    tmp_path: Path, tiny_config: DemocapConfig
) -> None:
    clip = _clip("kata")
    out = tmp_path / "bvh.pt"
    opts = TrainOptions(epochs=1, seed=0, takes=2, threads=1, motions=(clip,), motion_subjects=2)
    ck = train(out, opts, config=tiny_config)
    assert ck.train_motions == ["kata"]
    assert load_checkpoint(out).train_motions == ["kata"]
    # a resumed run may not silently lose a clip it was trained with
    with pytest.raises(ValidationError, match="kata"):
        train(out, TrainOptions(epochs=2, seed=0, takes=2, threads=1), resume=True)
    # training bodies of a clip are not the held-out bodies of the same clip
    tr = pool_from_bvh(clip, 0, subjects=2, split="train")
    te = pool_from_bvh(clip, 0, subjects=2, split="test")
    assert tr[0].action == te[0].action == "kata"
    assert not np.allclose(tr[0].markers_m, te[0].markers_m)
