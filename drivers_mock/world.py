"""Hidden world parameters: what a real rig may do that the calibration is never told.

:class:`WorldParams` collects the parameters of the simulated world that the calibration used to
share with the mocks by construction (issue 16): the sync box's latency, where the D415 master's
pulse falls and a slave's trigger delay, the Vicon sync input's analog front end, the
clapperboard's closing law, the DAVIS's trigger timestamp jitter, frames the master drops at
its start, the clocks' drift ranges and how often the body hides a marker from the Vicon.

Two kinds (``mocaprig simulate --world``):

* ``"nominal"`` (:meth:`WorldParams.nominal`): the values the simulator always had, drawn by the
  same streams as before, so a nominal session is bit for bit the session of earlier versions
  (the tests and the demo keep their figures);
* ``"random"`` (:meth:`WorldParams.draw`): every parameter drawn from the range a real rig can
  have, from the scenario's ``"world"`` stream (so the same seed gives the same hidden world, and
  no other stream's draws move).

The drawn values are ground truth: ``truth/scenario.json`` records them under ``world``, and
nothing the calibration reads (the recording, the C3D) carries them.

Ranges of the random world (sources in ``../shared/docs``):

=============================  ==============================================================
sync box latency               0–50 µs (interrupt latency of the box; ±1 µs jitter per edge)
D415 pulse phase               the master's pulse at its exposure start or at its readout start
                               (realsense-d415.md §2.2: undocumented; D435i: end of exposure)
slave trigger delay            exposure-start: 0–200 µs; readout-start: 700–900 µs (#9220:
                               0.79–0.88 ms measured on a D435)
Vicon sync input               RC τ 150–1000 µs (±5 % parts), a 2-pole Butterworth anti-alias
                               filter at 0.5–5 kHz (or none), 12 or 16 bits over ±5 or ±10 V,
                               an offset of ±50 mV, 1–5 mV of noise
clapperboard                   closing 30–300 ms, angle law θmax·(1 − s^p) with p 1.2–4, a
                               bounce of 1–4° for 20–60 ms in half the worlds
DAVIS trigger stamps           Gaussian jitter σ 1–2 µs
master's first frames          0–5 captures lost before the first one recorded
clock drift                    D415, DAVIS and Vicon: ±50 ppm
occlusion by the body (Vicon)  gap fraction 0.5–4 %, facing weight 2–12
=============================  ==============================================================
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Final, Literal, get_args

import numpy as np

from mocaprig.drivers_mock.rig import PulseAt
from mocaprig.errors import ValidationError

__all__ = ["WORLD_KINDS", "WorldKind", "WorldParams"]

#: ``nominal``: the simulator's long-standing values; ``random``: drawn per session.
WorldKind = Literal["nominal", "random"]
#: The kinds, in the order the CLI lists them.
WORLD_KINDS: Final[tuple[WorldKind, ...]] = get_args(WorldKind)


@dataclass(frozen=True, slots=True)
class WorldParams:
    """The hidden parameters of one simulated world (module doc for the ranges).

    Attributes:
        kind: ``"nominal"`` or ``"random"``.
        sync_latency_us: The sync box's mean delay from the master's pulse to the toggle (µs).
        sync_latency_jitter_us: Uniform jitter of that delay, ± (µs).
        pulse_at: Where the D415 master's pulse falls (``D415Timing.pulse_at``); None keeps
            the rig's own (the nominal world, and ``simulate --d415-timing``).
        slave_trigger_delay_us: A slave's exposure start after the edge (µs); None keeps the
            rig's.
        sync_tau_us: Nominal RC time constant of the Vicon sync input (µs).
        antialias_hz: Cut-off of the sync input's 2-pole Butterworth anti-alias filter (Hz);
            None: no filter (the nominal world: a pure first-order RC).
        adc_bits: Resolution of the Vicon analog input.
        adc_range_v: Its full scale, ± (V).
        adc_offset_v: Its offset (V).
        sync_noise_v: Gaussian noise on the input (V RMS).
        clap_closing_s: Range of a clap's closing duration (s), drawn per clap.
        clap_power: Exponent ``p`` of the closing law ``θ = θmax·(1 − s^p)`` (2: constant
            angular acceleration).
        clap_bounce_rad: Reopening after contact (rad); 0: none.
        clap_bounce_s: Duration of that bounce (s).
        davis_trigger_jitter_us: σ of the DAVIS's stamping jitter on its trigger input (µs).
        master_dropped_frames: Captures the D415 master loses at its start (its pulses still
            go out, so the first recorded frame is not the first pulse).
        d415_drift_ppm: Each D415 clock's drift (ppm), in rig order; None: the clock stream's.
        davis_drift_ppm: The DAVIS clock's drift (ppm); None: the clock stream's.
        vicon_drift_ppm: The Vicon clock's drift (ppm); None: the clock stream's.
        vicon_gap_fraction: Fraction of Vicon samples lost to occlusion; None: the noise's.
        vicon_facing_weight: How much more often a marker the body turns away drops out;
            None: the noise's.

    Raises:
        ValidationError: a value out of its range.
    """

    kind: WorldKind = "nominal"
    sync_latency_us: float = 2.0
    sync_latency_jitter_us: float = 1.0
    pulse_at: PulseAt | None = None
    slave_trigger_delay_us: float | None = None
    sync_tau_us: float = 470.0
    antialias_hz: float | None = None
    adc_bits: int = 16
    adc_range_v: float = 10.0
    adc_offset_v: float = 0.0
    sync_noise_v: float = 0.002
    clap_closing_s: tuple[float, float] = (0.06, 0.12)
    clap_power: float = 2.0
    clap_bounce_rad: float = 0.0
    clap_bounce_s: float = 0.0
    davis_trigger_jitter_us: float = 0.0
    master_dropped_frames: int = 0
    d415_drift_ppm: tuple[float, ...] | None = None
    davis_drift_ppm: float | None = None
    vicon_drift_ppm: float | None = None
    vicon_gap_fraction: float | None = None
    vicon_facing_weight: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in WORLD_KINDS:
            msg = f"WorldParams.kind must be one of {list(WORLD_KINDS)}, got {self.kind!r}"
            raise ValidationError(msg)
        checks: list[tuple[str, float | None, float, float]] = [
            ("sync_latency_us", self.sync_latency_us, 0.0, 1000.0),
            ("sync_latency_jitter_us", self.sync_latency_jitter_us, 0.0, 100.0),
            ("slave_trigger_delay_us", self.slave_trigger_delay_us, 0.0, 5000.0),
            ("sync_tau_us", self.sync_tau_us, 1.0, 10_000.0),
            ("antialias_hz", self.antialias_hz, 10.0, 1e6),
            ("adc_range_v", self.adc_range_v, 0.1, 100.0),
            ("adc_offset_v", self.adc_offset_v, -1.0, 1.0),
            ("sync_noise_v", self.sync_noise_v, 0.0, 1.0),
            ("clap_power", self.clap_power, 1.0, 10.0),
            ("clap_bounce_rad", self.clap_bounce_rad, 0.0, 0.2),
            ("clap_bounce_s", self.clap_bounce_s, 0.0, 0.2),
            ("davis_trigger_jitter_us", self.davis_trigger_jitter_us, 0.0, 1000.0),
            ("davis_drift_ppm", self.davis_drift_ppm, -1000.0, 1000.0),
            ("vicon_drift_ppm", self.vicon_drift_ppm, -1000.0, 1000.0),
            ("vicon_gap_fraction", self.vicon_gap_fraction, 0.0, 0.49),
            ("vicon_facing_weight", self.vicon_facing_weight, 0.0, 100.0),
        ]
        checks += [("d415_drift_ppm", d, -1000.0, 1000.0) for d in self.d415_drift_ppm or ()]
        for name, value, lo, hi in checks:
            if value is not None and not (math.isfinite(value) and lo <= value <= hi):
                msg = f"WorldParams.{name} must lie in [{lo:g}, {hi:g}], got {value!r}"
                raise ValidationError(msg)
        if self.pulse_at not in (None, "exposure-start", "readout-start"):
            msg = (
                "WorldParams.pulse_at must be None, 'exposure-start' or 'readout-start', got "
                f"{self.pulse_at!r}"
            )
            raise ValidationError(msg)
        if self.adc_bits not in range(8, 25):
            msg = f"WorldParams.adc_bits must lie in 8..24, got {self.adc_bits!r}"
            raise ValidationError(msg)
        lo_s, hi_s = self.clap_closing_s
        if not (0.0 < lo_s <= hi_s <= 0.5):
            msg = (
                "WorldParams.clap_closing_s must be an increasing range within (0, 0.5] s, got "
                f"{self.clap_closing_s!r}"
            )
            raise ValidationError(msg)
        if not (0 <= self.master_dropped_frames <= 1000):
            msg = (
                "WorldParams.master_dropped_frames must lie in 0..1000, got "
                f"{self.master_dropped_frames!r}"
            )
            raise ValidationError(msg)

    @classmethod
    def nominal(cls) -> WorldParams:
        """The simulator's long-standing world (every default; bit for bit the old sessions)."""
        return cls()

    @classmethod
    def draw(cls, rng: np.random.Generator, *, num_d415: int = 4) -> WorldParams:
        """A random world from the ranges of the module doc.

        Args:
            rng: The scenario's ``"world"`` stream (consumed).
            num_d415: D415 clocks to draw a drift for.
        """
        pulse_at: PulseAt = "readout-start" if rng.random() < 0.5 else "exposure-start"
        delay = (
            rng.uniform(700.0, 900.0) if pulse_at == "readout-start" else rng.uniform(0.0, 200.0)
        )
        antialias = None if rng.random() < 0.25 else float(rng.uniform(500.0, 5000.0))
        bounce = rng.random() < 0.5
        return cls(
            kind="random",
            sync_latency_us=float(rng.uniform(0.0, 50.0)),
            sync_latency_jitter_us=1.0,
            pulse_at=pulse_at,
            slave_trigger_delay_us=float(delay),
            sync_tau_us=float(rng.uniform(150.0, 1000.0)),
            antialias_hz=antialias,
            adc_bits=int(rng.choice([12, 16])),
            adc_range_v=float(rng.choice([5.0, 10.0])),
            adc_offset_v=float(rng.uniform(-0.05, 0.05)),
            sync_noise_v=float(rng.uniform(0.001, 0.005)),
            clap_closing_s=(0.03, 0.3),
            clap_power=float(rng.uniform(1.2, 4.0)),
            clap_bounce_rad=float(np.radians(rng.uniform(1.0, 4.0))) if bounce else 0.0,
            clap_bounce_s=float(rng.uniform(0.02, 0.06)) if bounce else 0.0,
            davis_trigger_jitter_us=float(rng.uniform(1.0, 2.0)),
            master_dropped_frames=int(rng.integers(0, 6)),
            d415_drift_ppm=tuple(float(v) for v in rng.uniform(-50.0, 50.0, num_d415)),
            davis_drift_ppm=float(rng.uniform(-50.0, 50.0)),
            vicon_drift_ppm=float(rng.uniform(-50.0, 50.0)),
            vicon_gap_fraction=float(rng.uniform(0.005, 0.04)),
            vicon_facing_weight=float(rng.uniform(2.0, 12.0)),
        )

    def to_dict(self) -> dict[str, object]:
        """A JSON-ready description (the truth's ``world``)."""
        out = asdict(self)
        out["clap_closing_s"] = list(self.clap_closing_s)
        if self.d415_drift_ppm is not None:
            out["d415_drift_ppm"] = list(self.d415_drift_ppm)
        return out
