"""The staged markers-to-pose network, CoM3D decoding, dual-view fusion and the losses.

Architecture (democap-method.md §2.1–2.2, paper §4.1 and Eq. 3), as the paper describes it:

* stem (super-stage 1 only): two 3×3 stride-2 convolutions (conv, BN, ReLU) then bottleneck
  residual units -> F, ``feature_channels``×40×40;
* a super-stage: a start transition to two branches (40×40 and 20×20), then HRNet stages that
  keep or add one lower-resolution branch, each made of exchange blocks (residual units per
  branch, then every branch fused into every other: 1×1 conv + bilinear up-sampling from
  lower resolutions, strided 3×3 convs from higher ones). Fusion reads a frozen copy of the
  branches (original HRNet), not the in-place updated list of the authors' framework (§2.2).
* one shared 1×1 conv + ReLU (or softplus, ``DemocapConfig.head``) head reads the top branch
  after the transition and after every stage; the heads are summed into the aggregated heat
  maps H̄ (Eq. 3, all stages, unlike the implementation's ``2×stage2 + stage3 + stage4``);
* super-stage 1 predicts the 53 marker maps; its output F ⊕ H̄_M feeds super-stage 2, which
  predicts the 19 joint maps.

CoM3D (§3, paper Eq. 5–6): ``z = mean(H̄)`` over the heat-map pixels, ``(x, y)`` = softmax
centre of mass on a grid of pixel *centres* ``(j + 0.5) / W`` (the authors' ``j / W`` grid
shifts every estimate by half a pixel). Dual-view fusion is paper Eq. 7.

Losses (paper Eq. 8–10): Wing (w = 10, ε = 2) on the 3D Euclidean distance of each fused
keypoint to the truth, and the Jensen–Shannon divergence between each view's softmax map and
a normalised Gaussian (σ = 1 px) at the truth, summed over pixels; total
``λ1 (Wing_M + Wing_J) + λ2 (JS_front + JS_back)`` with λ1 = 2, λ2 = 1.

Variants (``DemocapConfig.variant``; paper §5.3.1 and Table 2; :func:`build_network`):

* ``"markers-to-pose"`` (:class:`DemocapNet`): the above.
* ``"pose"`` (:class:`PoseNet`): the stem and one stack of heat-map stages predicting only the
  19 joint maps. Its depth matches both super-stages together: after the start transition it
  runs the configured stage schedule twice, the second time from the top two branches (the
  lower ones, already fused into them, are dropped), just as the second super-stage restarts
  from its two-branch start transition. Same exchange blocks, units and branch widths in the
  same order; what it lacks is the second start transition and the marker head. The heads of
  all its stages are summed (Eq. 3). Only the joints are supervised.
* ``"markers+pose"`` (:class:`MarkersPoseNet`): both super-stages predict all 72 maps (53
  markers then 19 joints); the second reads F ⊕ the first's 72 maps (the authors'
  ``hrnet_e2e.py``, democap-method.md §2.2). Both super-stages are supervised (Eq. 10 each,
  summed); the second one's maps are the output.
* ``"regression"`` (:class:`RegressionNet`): the same stem, a small strided conv encoder,
  global average pooling and two fully connected layers regress the 72 normalised ``(x, y,
  z)`` of each view directly (no heat maps, no CoM3D); the views are fused by Eq. 7 and the
  loss is the Wing term alone.
"""

from __future__ import annotations

from typing import TypeAlias, cast

import torch
import torch.nn.functional as F
from torch import nn

from mocaprig.errors import ValidationError
from mocaprig.process.democap.config import DemocapConfig

__all__ = [
    "CoordsOutput",
    "DemocapModel",
    "DemocapNet",
    "DemocapOutput",
    "JointsOutput",
    "MarkersPoseNet",
    "NetOutput",
    "PoseNet",
    "RegressionNet",
    "build_network",
    "com3d",
    "democap_loss",
    "fuse_views_torch",
    "gaussian_targets",
    "js_divergence",
    "view_keypoints",
    "wing_loss",
]

#: One HRNet stage: (branches, exchange blocks, residual units per branch per block).
_Stage = tuple[int, int, int]


def _conv_bn(cin: int, cout: int, k: int, stride: int = 1, relu: bool = True) -> nn.Sequential:
    layers: list[nn.Module] = [
        nn.Conv2d(cin, cout, k, stride=stride, padding=k // 2, bias=False),
        nn.BatchNorm2d(cout),
    ]
    if relu:
        layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


class _Bottleneck(nn.Module):
    """1×1 -> 3×3 -> 1×1 residual unit with BN (stem units)."""

    def __init__(self, cin: int, cout: int, mid: int) -> None:
        super().__init__()
        self.body = nn.Sequential(
            _conv_bn(cin, mid, 1), _conv_bn(mid, mid, 3), _conv_bn(mid, cout, 1, relu=False)
        )
        self.short: nn.Module = nn.Identity() if cin == cout else _conv_bn(cin, cout, 1, relu=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(self.body(x) + self.short(x))


class _Basic(nn.Module):
    """Two 3×3 convs with BN and an identity shortcut (HRNet branch unit)."""

    def __init__(self, c: int) -> None:
        super().__init__()
        self.body = nn.Sequential(_conv_bn(c, c, 3), _conv_bn(c, c, 3, relu=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(self.body(x) + x)


class _Exchange(nn.Module):
    """Residual units on every branch, then all-to-all fusion from a frozen copy."""

    def __init__(self, widths: list[int], units: int) -> None:
        super().__init__()
        self.branches = nn.ModuleList(
            nn.Sequential(*[_Basic(w) for _ in range(units)]) for w in widths
        )
        n = len(widths)
        fuse: list[nn.ModuleList] = []
        for i in range(n):
            row: list[nn.Module] = []
            for j in range(n):
                if j == i:
                    row.append(nn.Identity())
                elif j > i:
                    row.append(_conv_bn(widths[j], widths[i], 1, relu=False))
                else:
                    steps: list[nn.Module] = []
                    for s in range(i - j):
                        last = s == i - j - 1
                        cout = widths[i] if last else widths[j]
                        steps.append(_conv_bn(widths[j], cout, 3, stride=2, relu=not last))
                    row.append(nn.Sequential(*steps))
            fuse.append(nn.ModuleList(row))
        self.fuse = nn.ModuleList(fuse)

    def forward(self, xs: list[torch.Tensor]) -> list[torch.Tensor]:
        ys = [b(x) for b, x in zip(self.branches, xs, strict=True)]
        out: list[torch.Tensor] = []
        for i in range(len(self.fuse)):
            row = cast(nn.ModuleList, self.fuse[i])
            acc = ys[i]
            for j in range(len(row)):
                f = row[j]
                if j == i:
                    continue
                z = f(ys[j])
                if j > i:
                    z = F.interpolate(
                        z, size=ys[i].shape[-2:], mode="bilinear", align_corners=False
                    )
                acc = acc + z
            out.append(torch.relu(acc))
        return out


def _schedule(cfg: DemocapConfig) -> tuple[_Stage, ...]:
    return tuple(zip(cfg.stage_branches, cfg.stage_modules, cfg.stage_units, strict=True))


class _SuperStage(nn.Module):
    """Start transition + HRNet stages; returns the summed per-stage heads.

    ``schedule`` defaults to the config's stages. A stage with more branches than the one
    before grows a new branch from the lowest; one with fewer keeps the top branches.
    """

    def __init__(
        self, cin: int, k: int, cfg: DemocapConfig, schedule: tuple[_Stage, ...] | None = None
    ) -> None:
        super().__init__()
        w = cfg.width
        self.start = nn.ModuleList([_conv_bn(cin, w, 3), _conv_bn(cin, 2 * w, 3, stride=2)])
        stages: list[nn.ModuleList] = []
        grow: list[nn.Module] = []
        nb = 2
        plan = _schedule(cfg) if schedule is None else schedule
        for branches, modules, units in plan:
            if branches > nb:
                grow.append(_conv_bn(w * 2 ** (nb - 1), w * 2**nb, 3, stride=2))
            else:
                grow.append(nn.Identity())
            nb = branches
            widths = [w * 2**b for b in range(nb)]
            stages.append(nn.ModuleList(_Exchange(widths, units) for _ in range(modules)))
        self.grow = nn.ModuleList(grow)
        self.stages = nn.ModuleList(stages)
        self.branch_counts = tuple(b for b, _, _ in plan)
        act: nn.Module = nn.Softplus() if cfg.head == "softplus" else nn.ReLU(inplace=False)
        self.head = nn.Sequential(nn.Conv2d(w, k, 1), act)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        xs = [m(x) for m in self.start]
        total: torch.Tensor = self.head(xs[0])
        for grow, stage, nb in zip(self.grow, self.stages, self.branch_counts, strict=True):
            if nb > len(xs):
                xs = [*xs, grow(xs[-1])]
            elif nb < len(xs):
                xs = xs[:nb]
            for block in cast(nn.ModuleList, stage):
                xs = block(xs)
            total = total + self.head(xs[0])
        out: torch.Tensor = total
        return out


def _stem(cfg: DemocapConfig) -> nn.Sequential:
    """Two stride-2 convs and the bottleneck units: (B, 1, S, S) -> F (B, fc, S/4, S/4)."""
    c = cfg.stem_channels
    fc = cfg.feature_channels
    units: list[nn.Module] = [_Bottleneck(c, fc, max(fc // 4, 8))]
    units += [_Bottleneck(fc, fc, max(fc // 4, 8)) for _ in range(cfg.stem_units - 1)]
    return nn.Sequential(_conv_bn(1, c, 3, stride=2), _conv_bn(c, c, 3, stride=2), *units)


def _check_variant(cfg: DemocapConfig, expected: str, cls: str) -> None:
    if cfg.variant != expected:
        msg = (
            f"{cls} is the {expected!r} network, the config asks for {cfg.variant!r}; "
            "use build_network(config)"
        )
        raise ValidationError(msg)


class NetOutput:
    """Raw aggregated heat maps of one forward pass: markers (B, 53, H, W), joints (B, 19, H, W).

    ``intermediate`` holds earlier supervised outputs (``"markers+pose"``: the first
    super-stage's maps); empty for markers-to-pose.
    """

    __slots__ = ("intermediate", "joints", "markers")

    def __init__(
        self,
        markers: torch.Tensor,
        joints: torch.Tensor,
        intermediate: tuple[NetOutput, ...] = (),
    ) -> None:
        self.markers = markers
        self.joints = joints
        self.intermediate = intermediate


class JointsOutput:
    """Raw aggregated joint heat maps (B, 19, H, W) of the ``"pose"`` variant (no markers)."""

    __slots__ = ("joints",)

    def __init__(self, joints: torch.Tensor) -> None:
        self.joints = joints


class CoordsOutput:
    """Directly regressed normalised coordinates in the view's frame (``"regression"``):
    markers (B, 53, 3), joints (B, 19, 3), ``(x, y, z)`` as CoM3D gives them."""

    __slots__ = ("joints", "markers")

    def __init__(self, markers: torch.Tensor, joints: torch.Tensor) -> None:
        self.markers = markers
        self.joints = joints


#: What a network of any variant returns for a batch of views.
DemocapOutput: TypeAlias = NetOutput | JointsOutput | CoordsOutput


class DemocapNet(nn.Module):
    """DeMoCap markers-to-pose network: depth image (B, 1, S, S) -> aggregated heat maps.

    Raises:
        ValidationError: the config's variant is not ``"markers-to-pose"`` (use
            :func:`build_network`).
    """

    def __init__(self, cfg: DemocapConfig, *, num_markers: int = 53, num_joints: int = 19) -> None:
        super().__init__()
        _check_variant(cfg, "markers-to-pose", "DemocapNet")
        self.num_markers = num_markers
        self.num_joints = num_joints
        fc = cfg.feature_channels
        self.stem = _stem(cfg)
        self.markers = _SuperStage(fc, num_markers, cfg)
        self.joints = _SuperStage(fc + num_markers, num_joints, cfg)

    def forward(self, x: torch.Tensor) -> NetOutput:
        f = self.stem(x)
        hm = self.markers(f)
        hj = self.joints(torch.cat([f, hm], dim=1))
        return NetOutput(hm, hj)


class PoseNet(nn.Module):
    """``"pose"`` baseline: stem + one stack of stages, twice the configured schedule (module
    doc) -> joint heat maps only."""

    def __init__(self, cfg: DemocapConfig, *, num_markers: int = 53, num_joints: int = 19) -> None:
        super().__init__()
        _check_variant(cfg, "pose", "PoseNet")
        self.num_markers = num_markers
        self.num_joints = num_joints
        self.stem = _stem(cfg)
        self.joints = _SuperStage(cfg.feature_channels, num_joints, cfg, _schedule(cfg) * 2)

    def forward(self, x: torch.Tensor) -> JointsOutput:
        return JointsOutput(self.joints(self.stem(x)))


class MarkersPoseNet(nn.Module):
    """``"markers+pose"`` baseline: two super-stages, each predicting all 53 + 19 maps."""

    def __init__(self, cfg: DemocapConfig, *, num_markers: int = 53, num_joints: int = 19) -> None:
        super().__init__()
        _check_variant(cfg, "markers+pose", "MarkersPoseNet")
        self.num_markers = num_markers
        self.num_joints = num_joints
        k = num_markers + num_joints
        fc = cfg.feature_channels
        self.stem = _stem(cfg)
        self.first = _SuperStage(fc, k, cfg)
        self.second = _SuperStage(fc + k, k, cfg)

    def forward(self, x: torch.Tensor) -> NetOutput:
        f = self.stem(x)
        h1 = self.first(f)
        h2 = self.second(torch.cat([f, h1], dim=1))
        m = self.num_markers
        first = NetOutput(h1[:, :m], h1[:, m:])
        return NetOutput(h2[:, :m], h2[:, m:], intermediate=(first,))


class RegressionNet(nn.Module):
    """``"regression"`` baseline: stem -> three 3×3 stride-2 conv units (2w, 4w, 8w channels,
    a residual unit after the first two) -> global average pooling -> FC (16w) -> ReLU -> FC
    to 72 × 3 normalised coordinates (offset by 0.5, the cuboid's centre)."""

    def __init__(self, cfg: DemocapConfig, *, num_markers: int = 53, num_joints: int = 19) -> None:
        super().__init__()
        _check_variant(cfg, "regression", "RegressionNet")
        self.num_markers = num_markers
        self.num_joints = num_joints
        w = cfg.width
        self.stem = _stem(cfg)
        self.encoder = nn.Sequential(
            _conv_bn(cfg.feature_channels, 2 * w, 3, stride=2),
            _Basic(2 * w),
            _conv_bn(2 * w, 4 * w, 3, stride=2),
            _Basic(4 * w),
            _conv_bn(4 * w, 8 * w, 3, stride=2),
        )
        self.regressor = nn.Sequential(
            nn.Linear(8 * w, 16 * w),
            nn.ReLU(inplace=True),
            nn.Linear(16 * w, 3 * (num_markers + num_joints)),
        )

    def forward(self, x: torch.Tensor) -> CoordsOutput:
        z = self.encoder(self.stem(x)).mean(dim=(2, 3))
        c = self.regressor(z).reshape(x.shape[0], -1, 3) + 0.5
        return CoordsOutput(c[:, : self.num_markers], c[:, self.num_markers :])


#: A network of any variant.
DemocapModel: TypeAlias = DemocapNet | PoseNet | MarkersPoseNet | RegressionNet


def build_network(
    cfg: DemocapConfig, *, num_markers: int = 53, num_joints: int = 19
) -> DemocapModel:
    """The network of ``cfg.variant`` (module doc)."""
    kw = {"num_markers": num_markers, "num_joints": num_joints}
    if cfg.variant == "pose":
        return PoseNet(cfg, **kw)
    if cfg.variant == "markers+pose":
        return MarkersPoseNet(cfg, **kw)
    if cfg.variant == "regression":
        return RegressionNet(cfg, **kw)
    return DemocapNet(cfg, **kw)


def _grid(n: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    return (torch.arange(n, device=device, dtype=dtype) + 0.5) / n


def com3d(h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """CoM3D decoding of raw heat maps (B, K, H, W).

    Returns:
        ``(xyz (B, K, 3), softmax maps (B, K, H, W))`` with x the column and y the row centre
        of mass on pixel-centre coordinates in [0, 1] and z the map's spatial mean.
    """
    b, k, hh, ww = h.shape
    z = h.mean(dim=(2, 3))
    p = torch.softmax(h.reshape(b, k, hh * ww), dim=-1).reshape(b, k, hh, ww)
    x = (p.sum(dim=2) * _grid(ww, h.device, h.dtype)).sum(dim=-1)
    y = (p.sum(dim=3) * _grid(hh, h.device, h.dtype)).sum(dim=-1)
    return torch.stack([x, y, z], dim=-1), p


def fuse_views_torch(front: torch.Tensor, back: torch.Tensor) -> torch.Tensor:
    """Paper Eq. 7 on tensors (..., 3): average front and back mapped into the front frame."""
    flip = torch.stack([1.0 - back[..., 0], back[..., 1], 1.0 - back[..., 2]], dim=-1)
    return 0.5 * (front + flip)


def wing_loss(pred: torch.Tensor, target: torch.Tensor, *, w: float, eps: float) -> torch.Tensor:
    """Mean Wing loss of the Euclidean distances between (..., 3) keypoints (paper Eq. 8)."""
    d = torch.sqrt(((pred - target) ** 2).sum(dim=-1) + 1e-12)
    c = w - w * torch.log1p(torch.tensor(w / eps, dtype=d.dtype))
    return torch.where(d < w, w * torch.log1p(d / eps), d - c).mean()


def gaussian_targets(xy: torch.Tensor, size: int, sigma_px: float) -> torch.Tensor:
    """Normalised Gaussians (B, K, size, size) centred at ``xy`` (B, K, 2) in [0, 1]."""
    g = _grid(size, xy.device, xy.dtype)
    s = sigma_px / size
    gx = torch.exp(-((g[None, None, :] - xy[..., 0:1]) ** 2) / (2 * s * s))
    gy = torch.exp(-((g[None, None, :] - xy[..., 1:2]) ** 2) / (2 * s * s))
    m = gy[..., :, None] * gx[..., None, :]
    return m / m.sum(dim=(-2, -1), keepdim=True).clamp_min(1e-30)


def js_divergence(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Jensen–Shannon divergence of maps (B, K, H, W), summed over pixels, mean over B × K."""
    m = 0.5 * (p + q)
    tiny = 1e-12
    kl_pm = (p * (torch.log(p + tiny) - torch.log(m + tiny))).sum(dim=(-2, -1))
    kl_qm = (q * (torch.log(q + tiny) - torch.log(m + tiny))).sum(dim=(-2, -1))
    return (0.5 * (kl_pm + kl_qm)).mean()


def view_keypoints(out: DemocapOutput) -> tuple[torch.Tensor | None, torch.Tensor]:
    """One view's normalised keypoints: markers (B, 53, 3) or None (``"pose"``), joints
    (B, 19, 3); CoM3D of the heat maps, or the regressed coordinates."""
    if isinstance(out, CoordsOutput):
        return out.markers, out.joints
    if isinstance(out, JointsOutput):
        return None, com3d(out.joints)[0]
    return com3d(out.markers)[0], com3d(out.joints)[0]


def _back_xy(t: torch.Tensor) -> torch.Tensor:
    return torch.stack([1.0 - t[..., 0], t[..., 1]], dim=-1)


def _map_terms(
    front: torch.Tensor, back: torch.Tensor, gt: torch.Tensor, cfg: DemocapConfig
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Wing of the fused CoM3D keypoints and JS of the front and back maps, one keypoint set."""
    size = front.shape[-1]
    f, pf = com3d(front)
    b, pb = com3d(back)
    wing = wing_loss(fuse_views_torch(f, b), gt, w=cfg.wing_w, eps=cfg.wing_eps)
    js_f = js_divergence(pf, gaussian_targets(gt[..., :2], size, cfg.sigma_px))
    js_b = js_divergence(pb, gaussian_targets(_back_xy(gt), size, cfg.sigma_px))
    return wing, js_f, js_b


def _coords_loss(
    front: CoordsOutput,
    back: CoordsOutput,
    mgt: torch.Tensor,
    jgt: torch.Tensor,
    cfg: DemocapConfig,
) -> tuple[torch.Tensor, dict[str, float]]:
    pm = fuse_views_torch(front.markers, back.markers)
    pj = fuse_views_torch(front.joints, back.joints)
    wing_m = wing_loss(pm, mgt, w=cfg.wing_w, eps=cfg.wing_eps)
    wing_j = wing_loss(pj, jgt, w=cfg.wing_w, eps=cfg.wing_eps)
    loss = cfg.coord_weight * (wing_m + wing_j)
    return loss, {"wing_markers": float(wing_m.detach()), "wing_joints": float(wing_j.detach())}


def _joints_loss(
    front: JointsOutput, back: JointsOutput, jgt: torch.Tensor, cfg: DemocapConfig
) -> tuple[torch.Tensor, dict[str, float]]:
    wing_j, js_f, js_b = _map_terms(front.joints, back.joints, jgt, cfg)
    loss = cfg.coord_weight * wing_j + cfg.heatmap_weight * (js_f + js_b)
    parts = {
        "wing_joints": float(wing_j.detach()),
        "js_front": float(js_f.detach()),
        "js_back": float(js_b.detach()),
    }
    return loss, parts


def _maps_loss(
    front: NetOutput, back: NetOutput, mgt: torch.Tensor, jgt: torch.Tensor, cfg: DemocapConfig
) -> tuple[torch.Tensor, dict[str, float]]:
    def terms(f: NetOutput, b: NetOutput) -> tuple[torch.Tensor, ...]:
        wm, jfm, jbm = _map_terms(f.markers, b.markers, mgt, cfg)
        wj, jfj, jbj = _map_terms(f.joints, b.joints, jgt, cfg)
        return wm, wj, jfm + jfj, jbm + jbj

    wing_m, wing_j, js_f, js_b = terms(front, back)
    for f, b in zip(front.intermediate, back.intermediate, strict=True):
        wm, wj, jf, jb = terms(f, b)
        wing_m, wing_j, js_f, js_b = wing_m + wm, wing_j + wj, js_f + jf, js_b + jb
    loss = cfg.coord_weight * (wing_m + wing_j) + cfg.heatmap_weight * (js_f + js_b)
    parts = {
        "wing_markers": float(wing_m.detach()),
        "wing_joints": float(wing_j.detach()),
        "js_front": float(js_f.detach()),
        "js_back": float(js_b.detach()),
    }
    return loss, parts


def democap_loss(
    front: DemocapOutput,
    back: DemocapOutput,
    markers_gt: torch.Tensor,
    joints_gt: torch.Tensor,
    cfg: DemocapConfig,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Paper Eq. 10 for a batch; ground truth is front-frame normalised (B, 53, 3), (B, 19, 3).

    Per variant (module doc): heat maps give ``λ1 (Wing_M + Wing_J) + λ2 (JS_front +
    JS_back)``, summed over the supervised super-stages (``"markers+pose"``: both); ``"pose"``
    has no marker terms; ``"regression"`` has only ``λ1 (Wing_M + Wing_J)`` on the fused
    coordinates.

    Returns:
        ``(loss, parts)`` with the parts as floats for logging: ``wing_markers`` (not for
        ``"pose"``), ``wing_joints``, ``js_front`` and ``js_back`` (not for ``"regression"``).

    Raises:
        ValidationError: ``front`` and ``back`` are outputs of different variants.
    """
    if isinstance(front, NetOutput) and isinstance(back, NetOutput):
        return _maps_loss(front, back, markers_gt, joints_gt, cfg)
    if isinstance(front, JointsOutput) and isinstance(back, JointsOutput):
        return _joints_loss(front, back, joints_gt, cfg)
    if isinstance(front, CoordsOutput) and isinstance(back, CoordsOutput):
        return _coords_loss(front, back, markers_gt, joints_gt, cfg)
    msg = (
        f"front and back are outputs of different variants ({type(front).__name__}, "
        f"{type(back).__name__}); pass both views through the same network"
    )
    raise ValidationError(msg)
