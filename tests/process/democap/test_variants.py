"""Tests of the network variants (paper Table 2 baselines and direct regression): build,
shapes, loss, checkpoints, decoding, evaluation and the CLI."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import cast

import numpy as np
import pytest
import torch

from mocaprig.cli import main
from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.democap.checkpoint import load_checkpoint
from mocaprig.process.democap.commands import VARIANT_CHOICES
from mocaprig.process.democap.config import CONFIGS, VARIANTS, DemocapConfig, Variant
from mocaprig.process.democap.dataset import make_pool, make_sample
from mocaprig.process.democap.evaluate import evaluate
from mocaprig.process.democap.infer import DemocapPredictor, decode
from mocaprig.process.democap.model import (
    CoordsOutput,
    DemocapNet,
    DemocapOutput,
    JointsOutput,
    MarkersPoseNet,
    NetOutput,
    PoseNet,
    RegressionNet,
    build_network,
    democap_loss,
)
from mocaprig.process.democap.replay import run_replay
from mocaprig.process.democap.train import TrainOptions, train

_CLASSES = {
    "markers-to-pose": DemocapNet,
    "pose": PoseNet,
    "markers+pose": MarkersPoseNet,
    "regression": RegressionNet,
}
_PARTS: dict[str, set[str]] = {
    "markers-to-pose": {"wing_markers", "wing_joints", "js_front", "js_back"},
    "pose": {"wing_joints", "js_front", "js_back"},
    "markers+pose": {"wing_markers", "wing_joints", "js_front", "js_back"},
    "regression": {"wing_markers", "wing_joints"},
}


def _variant(cfg: DemocapConfig, variant: str) -> DemocapConfig:
    return dataclasses.replace(cfg, variant=cast(Variant, variant))


def _train_tiny(tmp_path: Path, cfg: DemocapConfig) -> Path:
    out = tmp_path / "v.pt"
    train(out, TrainOptions(epochs=1, takes=2, threads=1), config=cfg)
    return out


def test_variant_lists_agree() -> None:
    assert tuple(VARIANT_CHOICES) == VARIANTS
    assert set(_CLASSES) == set(VARIANTS)


def test_config_without_variant_key_is_markers_to_pose() -> None:
    d = CONFIGS["lite"].to_dict()
    del d["variant"]
    assert DemocapConfig.from_dict(d).variant == "markers-to-pose"
    with pytest.raises(ValidationError, match="variant must be one of"):
        DemocapConfig(name="bad", variant=cast(Variant, "hourglass"))


@pytest.mark.parametrize("variant", VARIANTS)
def test_every_variant_builds_with_its_output_shapes(
    variant: str, tiny_config: DemocapConfig
) -> None:
    torch.manual_seed(0)
    net = build_network(_variant(tiny_config, variant)).eval()
    assert isinstance(net, _CLASSES[variant])
    out: DemocapOutput = net(torch.rand(2, 1, 64, 64))
    if variant == "regression":
        assert isinstance(out, CoordsOutput)
        assert out.markers.shape == (2, 53, 3)
        assert out.joints.shape == (2, 19, 3)
    elif variant == "pose":
        assert isinstance(out, JointsOutput)
        assert out.joints.shape == (2, 19, 16, 16)
    else:
        assert isinstance(out, NetOutput)
        assert out.markers.shape == (2, 53, 16, 16)
        assert out.joints.shape == (2, 19, 16, 16)
        stages = 1 if variant == "markers+pose" else 0
        assert len(out.intermediate) == stages
        for first in out.intermediate:
            assert first.markers.shape == (2, 53, 16, 16)
            assert first.joints.shape == (2, 19, 16, 16)


@pytest.mark.parametrize("variant", VARIANTS)
def test_decode_gives_markers_except_for_pose(variant: str, tiny_config: DemocapConfig) -> None:
    torch.manual_seed(0)
    net = build_network(_variant(tiny_config, variant)).eval()
    x = torch.rand(3, 1, 64, 64)
    with torch.inference_mode():
        m, j = decode(net, x, x.flip(-1))
    assert m.shape == (3, 53, 3)
    assert j.shape == (3, 19, 3)
    assert torch.isfinite(j).all()
    if variant == "pose":
        assert torch.isnan(m).all()
    else:
        assert torch.isfinite(m).all()


def test_direct_class_refuses_another_variant(tiny_config: DemocapConfig) -> None:
    with pytest.raises(ValidationError, match="build_network"):
        DemocapNet(_variant(tiny_config, "pose"))
    with pytest.raises(ValidationError, match="build_network"):
        RegressionNet(tiny_config)


def _exchange_blocks(net: torch.nn.Module) -> int:
    return sum(type(m).__name__ == "_Exchange" for m in net.modules())


def test_pose_stack_is_as_deep_as_both_super_stages() -> None:
    m2p = build_network(CONFIGS["lite"])
    pose = build_network(_variant(CONFIGS["lite"], "pose"))
    assert _exchange_blocks(pose) == _exchange_blocks(m2p) == 4
    n_m2p = sum(p.numel() for p in m2p.parameters())
    n_pose = sum(p.numel() for p in pose.parameters())
    assert 0.8 < n_pose / n_m2p < 1.0  # no second start transition, no marker head


def test_markers_pose_second_super_stage_reads_features_and_all_maps(
    tiny_config: DemocapConfig,
) -> None:
    net = build_network(_variant(tiny_config, "markers+pose"))
    assert isinstance(net, MarkersPoseNet)
    first = cast(torch.nn.Sequential, net.second.start[0])[0]
    assert isinstance(first, torch.nn.Conv2d)
    assert first.in_channels == tiny_config.feature_channels + 53 + 19


@pytest.mark.parametrize("variant", VARIANTS)
def test_loss_backpropagates_for_every_variant(variant: str, tiny_config: DemocapConfig) -> None:
    torch.manual_seed(1)
    cfg = _variant(tiny_config, variant)
    net = build_network(cfg)
    x = torch.rand(4, 1, 64, 64)
    gm, gj = torch.rand(4, 53, 3) * 0.8 + 0.1, torch.rand(4, 19, 3) * 0.8 + 0.1
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    losses = []
    for step in range(8):
        loss, parts = democap_loss(net(x), net(x.flip(-1)), gm, gj, cfg)
        opt.zero_grad()
        loss.backward()  # type: ignore[no-untyped-call]
        if step == 0:
            # the gradient reaches the first layer and every supervised head
            ends = [n for n, _ in net.named_parameters() if "head" in n or "regressor" in n]
            assert len(ends) == (2 if variant == "pose" else 4)
            dead = [
                n
                for n, p in net.named_parameters()
                if n in {"stem.0.0.weight", *ends} and (p.grad is None or not p.grad.any())
            ]
            assert not dead, f"parameters without a gradient: {dead}"
        opt.step()
        losses.append(loss.item())
    assert set(parts) == _PARTS[variant]
    assert all(np.isfinite(losses))
    assert losses[-1] < losses[0]


def test_loss_refuses_outputs_of_two_variants(tiny_config: DemocapConfig) -> None:
    x = torch.rand(1, 1, 64, 64)
    a = build_network(tiny_config)(x)
    b = build_network(_variant(tiny_config, "regression"))(x)
    with pytest.raises(ValidationError, match="different variants"):
        democap_loss(a, b, torch.rand(1, 53, 3), torch.rand(1, 19, 3), tiny_config)


@pytest.mark.parametrize("variant", VARIANTS)
def test_checkpoint_of_every_variant_round_trips_and_decodes(
    variant: str, tmp_path: Path, tiny_config: DemocapConfig
) -> None:
    cfg = _variant(tiny_config, variant)
    path = _train_tiny(tmp_path, cfg)
    ck = load_checkpoint(path)
    assert ck.config == cfg
    assert isinstance(ck.model, _CLASSES[variant])
    pred = DemocapPredictor(path)
    assert pred.predicts_markers == (variant != "pose")
    pool = make_pool(0, "test", takes=1, seconds=0.5)
    s = make_sample(pool[0], 3, np.random.default_rng(0), augment=False, size_px=64)
    out = pred.predict(s.raw_m)
    assert out.markers_m.shape == (53, 3)
    assert out.joints_m.shape == (19, 3)
    lo, hi = s.raw_m.min(axis=0) - 0.5, s.raw_m.max(axis=0) + 0.5
    assert np.all((out.joints_m > lo) & (out.joints_m < hi))
    assert np.isnan(out.markers_m).all() == (variant == "pose")


def test_old_checkpoint_without_variant_loads_as_markers_to_pose(
    tmp_path: Path, tiny_config: DemocapConfig
) -> None:
    path = _train_tiny(tmp_path, tiny_config)
    data = torch.load(path, weights_only=True)
    del data["config"]["variant"]  # written before the option existed
    old = tmp_path / "old.pt"
    torch.save(data, old)
    ck = load_checkpoint(old)
    assert ck.config.variant == "markers-to-pose"
    assert isinstance(ck.model, DemocapNet)
    for a, b in zip(ck.model.state_dict().values(), data["model"].values(), strict=True):
        torch.testing.assert_close(a, b)


def test_pose_evaluation_reports_no_marker_figures(
    tmp_path: Path, tiny_config: DemocapConfig
) -> None:
    path = _train_tiny(tmp_path, _variant(tiny_config, "pose"))
    rep = evaluate(DemocapPredictor(path), seed=1, num_cameras=4, frames_per_take=1)
    d = json.loads(json.dumps(rep.to_dict()))
    assert d["variant"] == "pose"
    assert d["mpjpe_mm"] > 0
    for key in ("mpmpe_mm", "rmspmpe_mm", "mpjae_deg", "rmspjae_deg"):
        assert d[key] is None


def test_replay_refuses_a_checkpoint_without_markers(
    tmp_path: Path, tiny_config: DemocapConfig
) -> None:
    pred = DemocapPredictor(_train_tiny(tmp_path, _variant(tiny_config, "pose")))
    with pytest.raises(ProcessingError, match="estimates no markers"):
        run_replay(
            tmp_path / "s.mcap", tmp_path / "c.toml", out=tmp_path / "r.mcap", predictor=pred
        )
    assert not list(tmp_path.glob("r.*"))  # refused before anything is read or written


@pytest.mark.parametrize("variant", ["pose", "regression"])
@pytest.mark.slow
def test_cli_train_variant_then_eval(
    variant: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ck = tmp_path / "cli.pt"
    base = ["democap", "train", "--out", str(ck), "--takes", "1", "--samples-per-epoch", "2"]
    base += ["--batch-size", "2", "--threads", "1", "--no-corpus"]
    assert main([*base, "--variant", variant, "--epochs", "1", "--json"]) == 0
    first = json.loads(capsys.readouterr().out)
    assert (first["variant"], first["epochs"]) == (variant, 1)
    assert load_checkpoint(ck).config.variant == variant
    # resuming keeps the variant; naming another one is refused
    assert main([*base, "--variant", "markers+pose", "--epochs", "2", "--resume"]) == 1
    assert "applies to new runs only" in capsys.readouterr().err
    assert main(["democap", "eval", "--ckpt", str(ck), "--frames", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["variant"] == variant
    assert out["mpjpe_mm"] > 0
    assert (out["mpmpe_mm"] is None) == (variant == "pose")
    assert main(["democap", "eval", "--ckpt", str(ck), "--frames", "1"]) == 0
    text = capsys.readouterr().out
    assert "4 cameras: MPJPE" in text
    assert ("MPMPE n/a" in text) == (variant == "pose")
