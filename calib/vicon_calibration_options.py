"""The options of the Vicon calibration (:func:`mocaprig.calib.vicon_calibration.calibrate_vicon`).

:class:`CalibrationOptions` is read by every step of the calibration (reading, registration, the
clocks, the refusal), so it sits below them all; :data:`MAX_RMS_PX` is the default refusal
threshold.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final, Literal

from mocaprig.errors import ValidationError
from mocaprig.validation import check_positive

__all__ = ["MAX_RMS_PX", "CalibrationOptions"]

#: Default refusal threshold on a camera's reprojection RMS (px). The simulated rig gives
#: 0.2–0.4 px; a wrong registration gives several px.
MAX_RMS_PX: Final = 1.5


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
            session (the windows around the Vicon claps are always read).
        static_tolerance_m: Vicon markers within this of the first frames count as still (m).
        static_tolerance_px: D415 blobs within this of the first frame count as still (px).
        min_static_frames: Fewest still D415 frames a camera needs.
        max_rms_px: Refusal threshold on the reprojection RMS (px).
        min_inliers: Refusal threshold on the inlier observations per camera.
        force: Write the calibration even above the thresholds (the figures are kept).
        cameras: ``"d415/<serial>"`` labels to calibrate; None = every D415 of the recording.
        seed: Seed of the coarse alignment's sampling.
        unit: Length unit of the Vicon file when it does not say (``"mm"``, ``"cm"``, ``"m"``).
        sync_pulse_us: Width of the D415 master's sync pulse (µs): a DAVIS reporting whole
            pulses (special type 4, stamped at the trailing edge) is moved back by it to the
            rising edge (the exposure start); rising-edge events (type 2) need no correction.
        sync_channel: Label of the Vicon analog channel carrying the D415 master's pulses (the
            sync box's toggle output: one edge per pulse, docs/wiring.md §7); matched exactly,
            else ignoring case. None: do not look for one (video clocks only).
        sync_latency_us: The wiring's delay from the master's pulse to the channel's edge (µs):
            the sync box's interrupt latency, ≈ 2 µs (assumed; measure it with a scope).
        slave_trigger_delay_us: A D415 slave's exposure start after the pulse (µs), for slaves
            mapped through the sync channel. Undocumented by Intel (realsense-d415.md §2.2);
            100 µs is the mock's assumption: measure it (LED flash test) for a real rig.
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
    slave_trigger_delay_us: float = 100.0

    def __post_init__(self) -> None:
        check_positive(self.head_window_s, name="head_window_s")
        check_positive(self.sync_pulse_us, name="sync_pulse_us")
        for name in ("sync_latency_us", "slave_trigger_delay_us"):
            if not math.isfinite(getattr(self, name)):
                msg = f"{name} must be a finite number of µs, got {getattr(self, name)!r}"
                raise ValidationError(msg)
        check_positive(self.static_tolerance_m, name="static_tolerance_m")
        check_positive(self.static_tolerance_px, name="static_tolerance_px")
        check_positive(self.max_rms_px, name="max_rms_px")
