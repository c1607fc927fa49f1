"""Network and training configurations: ``lite`` (trains on 2 CPU cores) and ``paper``.

``paper`` follows the DeMoCap HRNet-8 markers-to-pose model (democap-method.md §2.1–2.2): a stem
to 256 features at 40×40, two super-stages of 4 heat-map stages each (start transition, then
HRNet stages 2, 3, 4 with 1, 4, 3 exchange blocks of 4 residual units per branch, widths 32, 64,
128, 256). ``lite`` keeps the structure (stem, two super-stages, multi-resolution exchange,
per-stage heads summed, feature concatenation between super-stages) at a size that trains in
tens of minutes on a laptop CPU and runs at ≥ 30 fps.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Literal

from mocaprig.errors import ValidationError

__all__ = [
    "CONFIGS",
    "VARIANTS",
    "ConfigName",
    "DemocapConfig",
    "HeadActivation",
    "Variant",
    "config_by_name",
]

ConfigName = Literal["lite", "paper"]
HeadActivation = Literal["relu", "softplus"]
Variant = Literal["markers-to-pose", "pose", "markers+pose", "regression"]
#: The network variants (paper §5.3.1, Table 2, plus a direct-regression baseline).
VARIANTS: tuple[Variant, ...] = ("markers-to-pose", "pose", "markers+pose", "regression")


@dataclass(frozen=True, slots=True)
class DemocapConfig:
    """One network + training configuration.

    Attributes:
        name: configuration name.
        input_px: rendered view size (px); the heat maps are ``input_px // 4``.
        stem_channels: channels of the two stride-2 stem convolutions.
        feature_channels: channels of the stem feature map F (after the bottleneck units).
        stem_units: bottleneck residual units in the stem.
        width: channels of the highest-resolution branch (doubling per lower branch).
        stage_branches: number of branches of each HRNet stage after the start transition.
        stage_modules: exchange blocks per stage.
        stage_units: residual units per branch per exchange block.
        sigma_px: std of the Gaussian heat-map targets (heat-map pixels).
        lr: Adam learning rate.
        lr_decay: multiplicative decay applied every ``lr_decay_epochs`` epochs.
        lr_decay_epochs: epochs between decays.
        batch_size: samples per step (each sample gives a front and a back view).
        samples_per_epoch: training samples per epoch.
        wing_w, wing_eps: Wing loss parameters (paper: 10, 2).
        coord_weight, heatmap_weight: λ1, λ2 of paper Eq. 10 (2, 1).
        head: activation of the heat-map head. ``"relu"`` is the paper's; a ReLU channel can
            die early in training (its softmax goes flat and the joint lands at the cloud
            centre), so ``lite`` uses ``"softplus"``, which keeps zMean positive and keeps a
            gradient where a ReLU has none.
            Checkpoints without the key are ReLU.
        variant: what the network predicts and how (paper §5.3.1; :mod:`.model`):
            ``"markers-to-pose"`` (DeMoCap: 53 marker maps, then 19 joint maps from F and
            the marker maps), ``"pose"`` (only the 19 joint maps, one stack of stages as deep
            as both super-stages), ``"markers+pose"`` (both super-stages predict all 72 maps)
            or ``"regression"`` (no heat maps: a conv encoder, global pooling and fully
            connected layers regress the 72 normalised coordinates per view). The last three
            are baselines. Checkpoints without the key are markers-to-pose.
    """

    name: str
    input_px: int = 160
    stem_channels: int = 16
    feature_channels: int = 48
    stem_units: int = 1
    width: int = 16
    stage_branches: tuple[int, ...] = (2, 3)
    stage_modules: tuple[int, ...] = (1, 1)
    stage_units: tuple[int, ...] = (1, 1)
    sigma_px: float = 1.0
    lr: float = 1e-3
    lr_decay: float = 0.95
    lr_decay_epochs: int = 4
    batch_size: int = 16
    samples_per_epoch: int = 1024
    wing_w: float = 10.0
    wing_eps: float = 2.0
    coord_weight: float = 2.0
    heatmap_weight: float = 1.0
    head: HeadActivation = "relu"
    variant: Variant = "markers-to-pose"

    def __post_init__(self) -> None:
        n = len(self.stage_branches)
        if n == 0 or len(self.stage_modules) != n or len(self.stage_units) != n:
            msg = (
                f"config {self.name!r}: stage_branches, stage_modules and stage_units must be "
                "non-empty and of equal length"
            )
            raise ValidationError(msg)
        prev = 2
        for b in self.stage_branches:
            if b < prev or b > prev + 1:
                msg = (
                    f"config {self.name!r}: each stage keeps or adds one branch (start: 2), "
                    f"got {self.stage_branches}"
                )
                raise ValidationError(msg)
            prev = b
        if self.head not in ("relu", "softplus"):
            msg = f"config {self.name!r}: head must be 'relu' or 'softplus', got {self.head!r}"
            raise ValidationError(msg)
        if self.variant not in VARIANTS:
            msg = (
                f"config {self.name!r}: variant must be one of {', '.join(VARIANTS)}, "
                f"got {self.variant!r}"
            )
            raise ValidationError(msg)
        if self.input_px % 4 or self.input_px < 32:
            msg = f"config {self.name!r}: input_px must be a multiple of 4, >= 32"
            raise ValidationError(msg)

    @property
    def heatmap_px(self) -> int:
        """Heat-map side (px): the input side over 4."""
        return self.input_px // 4

    @property
    def num_stages(self) -> int:
        """Heat-map stages per super-stage: the start transition plus the HRNet stages."""
        return 1 + len(self.stage_branches)

    @property
    def predicts_markers(self) -> bool:
        """Whether the variant estimates the 53 markers (all but ``"pose"``)."""
        return self.variant != "pose"

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form (tuples become lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> DemocapConfig:
        """Inverse of :meth:`to_dict`.

        Raises:
            ValidationError: unknown or missing keys.
        """
        fields = set(cls.__dataclass_fields__)
        unknown = set(d) - fields
        if unknown:
            msg = f"DeMoCap config has unknown keys {sorted(unknown)}; is it from a newer version?"
            raise ValidationError(msg)
        kw: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
        return cls(**kw)


CONFIGS: dict[str, DemocapConfig] = {
    "lite": DemocapConfig(name="lite", head="softplus"),
    "paper": DemocapConfig(
        name="paper",
        stem_channels=64,
        feature_channels=256,
        stem_units=2,
        width=32,
        stage_branches=(2, 3, 4),
        stage_modules=(1, 4, 3),
        stage_units=(4, 4, 4),
        lr=1e-4,
        samples_per_epoch=8165,
    ),
}


def config_by_name(name: str) -> DemocapConfig:
    """The named configuration.

    Raises:
        ValidationError: unknown name.
    """
    if name not in CONFIGS:
        msg = f"unknown DeMoCap config {name!r}; choose one of {', '.join(CONFIGS)}"
        raise ValidationError(msg)
    return CONFIGS[name]
