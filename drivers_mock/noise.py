"""Noise settings of a simulated scenario (the knobs that are not device specifications).

Device-intrinsic figures live with the device (e.g. the Vicon marker noise σ in
:class:`drivers_mock.rig.ViconSpec`); the settings here say how much of each effect a scenario
switches on. :meth:`NoiseSettings.none` gives a noise-free world for exact-match tests.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from mocaprig.errors import ValidationError

__all__ = ["NoiseSettings"]


@dataclass(frozen=True, slots=True)
class NoiseSettings:
    """How noisy a scenario is.

    Attributes:
        marker_placement_sigma_m: σ (m) of each body marker's placement error on the actor
            (a fixed offset per marker for the whole session, as a real marker placement).
        vicon_noise_scale: Multiplies the Vicon spec's marker noise σ (0 = noise-free).
        vicon_gap_fraction: Target fraction of Vicon samples lost to occlusion gaps.
        vicon_gap_max_frames: Longest gap (frames); lengths are log-uniform in [1, max].
        vicon_facing_weight: How much more often a marker facing away from the Vicon cameras
            drops out: a sample seen by no camera is ``1 + weight`` times as likely to start a
            gap as one facing all of them.
        clock_jitter: Whether device clocks stamp with jitter.
    """

    marker_placement_sigma_m: float = 0.005
    vicon_noise_scale: float = 1.0
    vicon_gap_fraction: float = 0.01
    vicon_gap_max_frames: int = 70
    vicon_facing_weight: float = 4.0
    clock_jitter: bool = True

    def __post_init__(self) -> None:
        if not (0.0 <= self.marker_placement_sigma_m < 0.05):
            msg = (
                "NoiseSettings.marker_placement_sigma_m must lie in [0, 0.05) m, got "
                f"{self.marker_placement_sigma_m!r}"
            )
            raise ValidationError(msg)
        if not (0.0 <= self.vicon_noise_scale <= 100.0):
            msg = (
                "NoiseSettings.vicon_noise_scale must lie in [0, 100], got "
                f"{self.vicon_noise_scale!r}"
            )
            raise ValidationError(msg)
        if not (0.0 <= self.vicon_gap_fraction < 0.5):
            msg = (
                "NoiseSettings.vicon_gap_fraction must lie in [0, 0.5), got "
                f"{self.vicon_gap_fraction!r}"
            )
            raise ValidationError(msg)
        if self.vicon_gap_max_frames < 1:
            msg = "NoiseSettings.vicon_gap_max_frames must be >= 1"
            raise ValidationError(msg)
        if self.vicon_facing_weight < 0:
            msg = "NoiseSettings.vicon_facing_weight must be >= 0"
            raise ValidationError(msg)

    @classmethod
    def none(cls) -> NoiseSettings:
        """A noise-free world: exact placement, no Vicon noise or gaps, no clock jitter."""
        return cls(
            marker_placement_sigma_m=0.0,
            vicon_noise_scale=0.0,
            vicon_gap_fraction=0.0,
            vicon_facing_weight=0.0,
            clock_jitter=False,
        )

    def to_dict(self) -> dict[str, object]:
        """A JSON-ready description."""
        return asdict(self)
