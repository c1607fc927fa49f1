"""Tests of process.democap.model: shapes, CoM3D, fusion and losses."""

from __future__ import annotations

import dataclasses
import math
from typing import Literal, cast

import pytest
import torch

from mocaprig.errors import ValidationError
from mocaprig.process.democap.config import CONFIGS, DemocapConfig, config_by_name
from mocaprig.process.democap.model import (
    DemocapNet,
    com3d,
    democap_loss,
    fuse_views_torch,
    gaussian_targets,
    js_divergence,
    wing_loss,
)


def test_net_output_shapes_for_every_config(tiny_config: DemocapConfig) -> None:
    torch.manual_seed(0)
    net = DemocapNet(tiny_config).eval()
    out = net(torch.rand(2, 1, 64, 64))
    assert out.markers.shape == (2, 53, 16, 16)
    assert out.joints.shape == (2, 19, 16, 16)
    assert (out.markers >= 0).all()  # ReLU heads: zMean is non-negative


def test_lite_is_small_and_paper_is_hrnet_w32_sized() -> None:
    lite = sum(p.numel() for p in DemocapNet(CONFIGS["lite"]).parameters())
    paper = sum(p.numel() for p in DemocapNet(CONFIGS["paper"]).parameters())
    assert lite < 1_000_000
    assert 20_000_000 < paper < 80_000_000


def test_second_super_stage_sees_features_and_marker_maps(tiny_config: DemocapConfig) -> None:
    net = DemocapNet(tiny_config)
    first = cast(torch.nn.Sequential, net.joints.start[0])[0]
    assert isinstance(first, torch.nn.Conv2d)
    assert first.in_channels == tiny_config.feature_channels + 53


def test_com3d_of_a_peaked_map_is_the_pixel_centre_and_z_the_mean() -> None:
    h = torch.zeros(1, 1, 40, 40)
    h[0, 0, 10, 30] = 1000.0  # row 10, column 30
    xyz, p = com3d(h)
    assert xyz[0, 0, 0].item() == pytest.approx(30.5 / 40, abs=1e-6)
    assert xyz[0, 0, 1].item() == pytest.approx(10.5 / 40, abs=1e-6)
    assert xyz[0, 0, 2].item() == pytest.approx(1000.0 / 1600)
    assert p.sum().item() == pytest.approx(1.0)


def test_com3d_of_a_flat_map_is_the_centre() -> None:
    xyz, _ = com3d(torch.full((1, 2, 8, 8), 0.3))
    assert torch.allclose(xyz[0, :, :2], torch.full((2, 2), 0.5))
    assert torch.allclose(xyz[0, :, 2], torch.full((2,), 0.3))


def test_fusion_maps_back_view_into_front() -> None:
    front = torch.tensor([[0.2, 0.3, 0.4]])
    back = torch.tensor([[0.8, 0.3, 0.6]])  # the same point seen from the back
    assert torch.allclose(fuse_views_torch(front, back), front)


def test_wing_loss_uses_the_log_branch_below_w() -> None:
    pred = torch.tensor([[[0.3, 0.4, 0.0]]])  # distance 0.5
    value = wing_loss(pred, torch.zeros(1, 1, 3), w=10.0, eps=2.0)
    assert value.item() == pytest.approx(10.0 * math.log(1.0 + 0.5 / 2.0), rel=1e-5)
    far = wing_loss(torch.tensor([[[12.0, 0.0, 0.0]]]), torch.zeros(1, 1, 3), w=10.0, eps=2.0)
    c = 10.0 - 10.0 * math.log(1.0 + 10.0 / 2.0)
    assert far.item() == pytest.approx(12.0 - c, rel=1e-5)


def test_gaussian_targets_and_js_divergence() -> None:
    g = gaussian_targets(torch.tensor([[[0.5, 0.25]]]), 40, 1.0)
    assert g.sum().item() == pytest.approx(1.0)
    row, col = divmod(int(g.flatten().argmax()), 40)
    assert (row, col) in {(9, 19), (9, 20), (10, 19), (10, 20)}
    assert js_divergence(g, g).item() == pytest.approx(0.0, abs=1e-6)
    far = gaussian_targets(torch.tensor([[[0.1, 0.1]]]), 40, 1.0)
    assert js_divergence(g, far).item() == pytest.approx(math.log(2.0), rel=1e-3)  # disjoint


def test_loss_backpropagates_and_decreases(tiny_config: DemocapConfig) -> None:
    torch.manual_seed(1)
    net = DemocapNet(tiny_config)
    x = torch.rand(4, 1, 64, 64)
    gm, gj = torch.rand(4, 53, 3) * 0.8 + 0.1, torch.rand(4, 19, 3) * 0.8 + 0.1
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    losses = []
    for _ in range(15):
        loss, parts = democap_loss(net(x), net(x.flip(-1)), gm, gj, tiny_config)
        opt.zero_grad()
        loss.backward()  # type: ignore[no-untyped-call]
        opt.step()
        losses.append(loss.item())
    assert set(parts) == {"wing_markers", "wing_joints", "js_front", "js_back"}
    assert losses[-1] < losses[0]


def test_config_round_trip_and_errors() -> None:
    cfg = config_by_name("paper")
    assert DemocapConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValidationError, match="unknown DeMoCap config"):
        config_by_name("huge")
    with pytest.raises(ValidationError, match="unknown keys"):
        DemocapConfig.from_dict({**cfg.to_dict(), "depth": 3})
    with pytest.raises(ValidationError, match="one branch"):
        DemocapConfig(name="bad", stage_branches=(4,), stage_modules=(1,), stage_units=(1,))


def test_config_without_head_key_is_the_papers_relu_head() -> None:
    # Checkpoints written before the option existed carry no "head" key.
    d = config_by_name("lite").to_dict()
    del d["head"]
    assert DemocapConfig.from_dict(d).head == "relu"
    with pytest.raises(ValidationError, match="head must be"):
        DemocapConfig(name="bad", head=cast(Literal["relu", "softplus"], "tanh"))


def _head_bias(net: DemocapNet) -> torch.Tensor:
    bias = cast(torch.nn.Conv2d, net.joints.head[0]).bias
    assert bias is not None
    return bias


def test_softplus_head_keeps_a_gradient_where_relu_is_dead(tiny_config: DemocapConfig) -> None:
    torch.manual_seed(0)
    cfg_relu = dataclasses.replace(tiny_config, head="relu")
    cfg_soft = dataclasses.replace(tiny_config, head="softplus")
    x = torch.rand(2, 1, tiny_config.input_px, tiny_config.input_px)
    nets = {}
    for cfg in (cfg_relu, cfg_soft):
        net = DemocapNet(cfg).eval()
        # A head bias well below zero is what a dead ReLU channel looks like.
        with torch.no_grad():
            _head_bias(net).fill_(-8.0)
        nets[cfg.head] = net
    with torch.no_grad():
        dead = nets["relu"](x).joints
        alive = nets["softplus"](x).joints
    assert float(dead.abs().max()) == 0.0
    assert float(alive.min()) > 0.0
    # Softplus keeps a gradient: a step on a loss of the maps changes the bias.
    net = nets["softplus"].train()
    out = net(x).joints
    out.sum().backward()
    grad = _head_bias(net).grad
    assert grad is not None
    assert float(grad.abs().sum()) > 0.0
