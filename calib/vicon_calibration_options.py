"""The options of the Vicon calibration (:func:`mocaprig.calib.vicon_calibration.calibrate_vicon`).

:class:`CalibrationOptions` is read by every step of the calibration (reading, registration, the
clocks, the refusal), so it sits below them all; :data:`MAX_RMS_PX` is the default refusal
threshold. :class:`D415PulseTiming` is the D415 sync-timing convention the calibration assumes
(where the master's pulse falls, a slave's trigger-to-exposure delay): undocumented for the
D415, so a parameter with both published readings available (docs/d415-timing.md §3).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Final, Literal, get_args

from mocaprig.errors import ValidationError
from mocaprig.validation import check_positive

__all__ = [
    "D415_PULSE_CONVENTIONS",
    "MAX_RMS_PX",
    "SLAVE_TRIGGER_DELAY_US",
    "CalibrationOptions",
    "D415PulseAt",
    "D415PulseTiming",
]

#: Default refusal threshold on a camera's reprojection RMS (px). The simulated rig gives
#: 0.2–0.4 px; a wrong registration gives several px.
MAX_RMS_PX: Final = 1.5

#: Where the D415 master's pin-5 sync pulse falls: at its exposure start, or at its readout
#: start (= the end of its exposure).
D415PulseAt = Literal["exposure-start", "readout-start"]

#: The conventions, in the order the CLI lists them (the first is the default).
D415_PULSE_CONVENTIONS: Final[tuple[D415PulseAt, ...]] = get_args(D415PulseAt)

#: A slave's trigger-to-exposure delay (µs) each published convention comes with:
#: ``exposure-start``, the mock's long-standing assumption (100 µs); ``readout-start``, Intel's
#: answers for the D4xx family (0.77 ms; librealsense #9220 measured 0.79–0.88 ms on a D435).
SLAVE_TRIGGER_DELAY_US: Final[Mapping[D415PulseAt, float]] = MappingProxyType(
    {"exposure-start": 100.0, "readout-start": 770.0}
)


@dataclass(frozen=True, slots=True)
class D415PulseTiming:
    """The D415 sync timing the calibration assumes, resolved from :class:`CalibrationOptions`.

    A D415 stamps a frame (``sensor_timestamp``) at the middle of its exposure. Where that
    stamp falls relative to the master's sync pulse, which the Vicon sync channel and the
    DAVIS trigger input record, is not documented for the D415 (docs/d415-timing.md §3):

    * ``"exposure-start"``: the pulse marks the master's exposure start, so the master's stamp
      is the pulse + exposure/2;
    * ``"readout-start"``: the pulse marks its readout start, i.e. the end of its exposure, so
      its stamp is the pulse − exposure/2.

    A slave starts exposing ``slave_trigger_delay_us`` after the edge whatever the convention,
    so its stamp is the pulse + delay + its exposure/2.

    Attributes:
        pulse_at: Where the master's pulse falls.
        slave_trigger_delay_us: A slave's exposure start after the edge (µs).
    """

    pulse_at: D415PulseAt = "exposure-start"
    slave_trigger_delay_us: float = SLAVE_TRIGGER_DELAY_US["exposure-start"]

    def __post_init__(self) -> None:
        if self.pulse_at not in D415_PULSE_CONVENTIONS:
            msg = (
                f"D415 pulse timing: pulse_at must be one of {list(D415_PULSE_CONVENTIONS)}, got "
                f"{self.pulse_at!r}; see docs/d415-timing.md §4 to measure which one a rig has"
            )
            raise ValidationError(msg)
        if not math.isfinite(self.slave_trigger_delay_us):
            msg = (
                "D415 pulse timing: slave_trigger_delay_us must be a finite number of µs, got "
                f"{self.slave_trigger_delay_us!r}"
            )
            raise ValidationError(msg)

    @classmethod
    def preset(cls, pulse_at: D415PulseAt) -> D415PulseTiming:
        """A published convention with its slave delay (:data:`SLAVE_TRIGGER_DELAY_US`)."""
        if pulse_at not in SLAVE_TRIGGER_DELAY_US:
            return cls(pulse_at)  # refused, with the message, by __post_init__
        return cls(pulse_at, SLAVE_TRIGGER_DELAY_US[pulse_at])

    def master_frame_delay_ns(self, exposure_ns: float) -> int:
        """The master's frame stamp minus its pulse (ns): +exposure/2 (``exposure-start``) or
        −exposure/2 (``readout-start``)."""
        half = round(0.5 * exposure_ns)
        return half if self.pulse_at == "exposure-start" else -half

    def pulse_lag_ns(self, master_exposure_ns: float) -> float:
        """The master's pulse after its exposure start (ns): 0, or its exposure when the pulse
        marks its readout start. A slave's exposure starts the trigger delay after the pulse,
        so this is also how much later than the master's a slave exposes beyond that delay
        (and half their exposure difference)."""
        return float(master_exposure_ns) if self.pulse_at == "readout-start" else 0.0

    def slave_delay_ns(self, master_exposure_ns: float, exposure_ns: float) -> float:
        """A slave's frame stamp minus the master's stamp of the same pulse (ns): the trigger
        delay plus half the exposure difference, plus the master's whole exposure when the
        pulse comes at its readout start (the master exposes before the edge, the slave
        after it)."""
        delay = self.slave_trigger_delay_us * 1e3 + 0.5 * (exposure_ns - master_exposure_ns)
        if self.pulse_at == "readout-start":
            delay += master_exposure_ns
        return delay

    def describe(self) -> str:
        """One line for the notes, e.g. ``pulse at the master's exposure start, slave exposure
        100 µs after the edge``."""
        where = "exposure start" if self.pulse_at == "exposure-start" else "readout start"
        return (
            f"pulse at the D415 master's {where}, slave exposure "
            f"{self.slave_trigger_delay_us:g} µs after the edge"
        )


@dataclass(frozen=True, slots=True)
class CalibrationOptions:
    """Options of :func:`calibrate_vicon`.

    Attributes:
        head_window_s: How much of the recording's start is measured: the static start, the
            motion onset (coarse clock) and usually the first clap (s).
        clock_method: ``"reprojection"``: offsets of the Vicon markers' reprojection over
            chunks of frames, a line through them; ``"claps+speed"``: that as the prior, then
            :mod:`mocaprig.calib.time_align` (claps, speed cross-correlation).
        max_marker_speed_m_s: Markers moving faster are left out of the final bundle
            adjustment (m/s).
        min_area_ratio: Blobs whose area × depth² is below this fraction of the camera's median
            (partly occluded markers) are left out of the final bundle adjustment; 0 keeps all.
        extra_windows: Further 0.6 s windows read for the clock fit, as fractions of the
            session (the windows around the Vicon claps are always read); beside each, the
            0.6 s within ±5 % of the session where the Vicon markers move fastest.
        static_tolerance_m: Vicon markers within this of the first frames count as still (m).
        static_tolerance_px: D415 blobs within this of the first frame count as still (px).
        min_static_frames: Fewest still D415 frames a camera needs.
        max_rms_px: Refusal threshold on the reprojection RMS (px).
        min_inliers: Refusal threshold on the inlier observations per camera.
        force: Write the calibration even above the thresholds (the figures are kept), or
            with a D415 pulse phase the recording cannot tell (the assumed one, noted).
        cameras: ``"d415/<serial>"`` labels to calibrate; None = every D415 of the recording.
        seed: Seed of the coarse alignment's sampling.
        unit: Length unit of the Vicon file when it does not say (``"mm"``, ``"cm"``, ``"m"``).
        sync_pulse_us: Width of the D415 master's sync pulse (µs): a DAVIS reporting whole
            pulses (special type 4, stamped at the trailing edge) is moved back by it to the
            rising edge (the pulse); rising-edge events (type 2) need no correction.
        sync_channel: Label of the Vicon analog channel carrying the D415 master's pulses (the
            sync box's toggle output: one edge per pulse, docs/wiring.md §7); matched exactly,
            else ignoring case. None: do not look for one (video clocks only).
        sync_latency_us: The wiring's delay from the master's pulse to the channel's edge (µs):
            the sync box's interrupt latency, ≈ 2 µs (assumed; measure it with a scope).
        d415_pulse_at: Where the D415 master's sync pulse falls, used wherever a frame's
            ``sensor_timestamp`` (mid-exposure) is related to a pulse (the sync channel's
            edges, the DAVIS trigger input, the slaves' delays): ``"exposure-start"`` (the
            default, the mock's long-standing assumption: stamp = pulse + exposure/2) or
            ``"readout-start"`` (Intel's answers for the D4xx family: the pulse at the end of
            the exposure, stamp = pulse − exposure/2). Undocumented for the D415: measure it
            (LED test, docs/d415-timing.md §4); a wrong one moves the D415 and DAVIS clocks by
            about one exposure or makes the pulses unpairable.
        slave_trigger_delay_us: A D415 slave's exposure start after the pulse (µs), for slaves
            mapped through the sync channel. None (the default): the convention's published
            value (:data:`SLAVE_TRIGGER_DELAY_US`: 100 µs with ``exposure-start``, 770 µs with
            ``readout-start``). Undocumented for the D415 (realsense-d415.md §2.2): measure
            it (LED flash test) for a real rig.
        measure_pulse_phase: Make the clocks under both conventions and keep the one the
            data tell (with the sync channel: the master's own video clock, else its
            reprojection cost; without: the pooled video clock's fit); they differ by one whole
            exposure. When nothing tells and a slave or a DAVIS depends on it, the calibration
            is refused (``force``: ``d415_pulse_at`` stays, noted). False: always
            ``d415_pulse_at``. The slave trigger delay is never measured (a video clock
            is ≈ 0.1–0.5 ms good, the delay's range a few hundred µs): it stays an assumption.
    """

    head_window_s: float = 2.2
    clock_method: Literal["reprojection", "claps+speed"] = "reprojection"
    max_marker_speed_m_s: float = 0.3
    min_area_ratio: float = 0.85
    extra_windows: tuple[float, ...] = (0.1, 0.33, 0.67, 0.9)
    static_tolerance_m: float = 0.003
    static_tolerance_px: float = 0.6
    min_static_frames: int = 5
    max_rms_px: float = MAX_RMS_PX
    min_inliers: int = 30
    force: bool = False
    cameras: tuple[str, ...] | None = None
    seed: int = 0
    unit: str | None = None
    sync_pulse_us: float = 50.0
    sync_channel: str | None = "D415_SYNC"
    sync_latency_us: float = 2.0
    d415_pulse_at: D415PulseAt = "exposure-start"
    slave_trigger_delay_us: float | None = None
    measure_pulse_phase: bool = True

    def __post_init__(self) -> None:
        check_positive(self.head_window_s, name="head_window_s")
        check_positive(self.sync_pulse_us, name="sync_pulse_us")
        for name in ("sync_latency_us", "slave_trigger_delay_us"):
            value = getattr(self, name)
            if value is not None and not math.isfinite(value):
                msg = f"{name} must be a finite number of µs, got {value!r}"
                raise ValidationError(msg)
        if self.d415_pulse_at not in D415_PULSE_CONVENTIONS:
            msg = (
                f"d415_pulse_at must be one of {list(D415_PULSE_CONVENTIONS)}, got "
                f"{self.d415_pulse_at!r}; measure which one the rig has (docs/d415-timing.md §4)"
            )
            raise ValidationError(msg)
        check_positive(self.static_tolerance_m, name="static_tolerance_m")
        check_positive(self.static_tolerance_px, name="static_tolerance_px")
        check_positive(self.max_rms_px, name="max_rms_px")

    @property
    def pulse_timing(self) -> D415PulseTiming:
        """The D415 pulse timing assumed: ``d415_pulse_at`` with ``slave_trigger_delay_us``,
        or that convention's published slave delay when it is None."""
        if self.slave_trigger_delay_us is None:
            return D415PulseTiming.preset(self.d415_pulse_at)
        return D415PulseTiming(self.d415_pulse_at, float(self.slave_trigger_delay_us))

    def pulse_timings(self) -> tuple[D415PulseTiming, ...]:
        """The pulse timings to try: :attr:`pulse_timing` first, then, with
        ``measure_pulse_phase``, the other published convention (:meth:`D415PulseTiming.preset`)."""
        assumed = self.pulse_timing
        if not self.measure_pulse_phase:
            return (assumed,)
        other: D415PulseAt = (
            "readout-start" if assumed.pulse_at == "exposure-start" else "exposure-start"
        )
        return (assumed, D415PulseTiming.preset(other))
