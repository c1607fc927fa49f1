"""DAVIS240C sensor simulator: DVS events, APS exposures, IMU samples and trigger edges.

The defaults are set so that the output's statistics match real DAVIS recordings
(``docs/davis-sim.md``, ``benchmarks/davis_sim_realism.py``): same-pixel intervals of ≥ 1.5 ms,
40–50 % ON events, 0.1 Hz of background activity per pixel, and fewer events than
``contrast / C`` on fast high-contrast edges. The sensor size is the rig's DAVIS camera's,
240×180 (DAVIS240C) or 346×260 (DAVIS346).

Implements :class:`drivers_mock.davis_activity.DavisActivitySource` from the simulated world
(:class:`mocaprig.drivers_mock.scenario.Scenario`), seen through :class:`DavisRenderer`
(``davis240c_render.py``: textured capsule body, clapperboard, textured room, Lambert light).

**DVS** (ESIM, eventcap-method.md §4.1 and §4.4):

* Rendering is sampled adaptively (ESIM method 1): the world is probed every
  ``probe_interval_us`` and a render is placed whenever the largest image motion of any surface
  point since the last render reaches ``motion_step_px`` (subdividing a probe interval when the
  motion inside it is larger), and at least every ``max_render_interval_us``; renders are also
  placed at every APS exposure start and end. The schedule sits on a fixed grid from the reset
  instant, so the output does not depend on how the caller splits time into windows.
* Each pixel compares ``L = log(1e-3 + I)`` with its memorised level ``ref``; ``L`` is linear
  between renders. A crossing of ``ref + C_on`` (ON) or ``ref − C_off`` (OFF) is an event at
  the interpolated time. Thresholds are drawn once per pixel from N(C, σ_C), clamped at
  ≥ 0.01 (v2e-style fixed-pattern mismatch, §4.4 step 5). Defaults C_on = 0.22, C_off = 0.18,
  σ_C = 0.03: the practical band of §4.3 (the chip's best-case 11 % ≈ 0.10 ln needs ideal
  biases) with the ON threshold higher, so a scene that returns to its start gives
  C_off / (C_on + C_off) = 45 % ON events (RPG ECD DAVIS240C recordings: 42–45 %; the
  shapes file here: 41.6 %).
* **Dead time** (refractory period): after an event the pixel's reset switch holds its
  differencing amplifier for ``refractory_us`` (per pixel, log-normal spread
  ``refractory_spread``), during which the memorised level follows the input; on release the
  pixel memorises the level ``L`` has *then*. So a fast high-contrast edge gives fewer events
  than its contrast / C (the change during the dead time is lost), and no pixel fires twice
  within its dead time. Default 1.6 ms: the real DAVIS240C recording's shortest same-pixel
  interval is 1.67 ms (1st percentile 4.4 ms); the DAVIS346 file's start at ≈ 1.25 ms (1st
  percentile 1.9 ms). ``refractory_us = 0`` is ESIM's ideal ``ref ± C`` per event.
* After a reset (or a gap between windows) each pixel's ``ref`` starts at a fixed random
  point of ``(L − C_on, L + C_off)`` (between its firing levels), so pixels do not fire in lockstep.
* **Pixel bandwidth**: the photoreceptor low-pass (``cutoff_hz``, default 300 Hz at
  irradiance 1, §4.3: 100–300 Hz in good light; 0 = off): ``L`` goes through a first-order
  filter whose cutoff scales with the pixel's irradiance (v2e), solved exactly between renders;
  events are generated on the filtered ``L``.
* Events get a pixel latency (``latency_us``, default 12 µs: "~12 µs at 1 klux",
  davis240c-usb.md §13) plus Gaussian **timestamp jitter** (``jitter_us``, σ default 10 µs; the
  total latency is cut at ≥ 0) and are floored to integer µs.
* **Global-shutter burst** (``aps_burst_fraction``, default 0): at each APS exposure start
  (global reset, OFF) and end (charge transfer, ON) a fraction of the pixels fire one event.
  The real DAVIS346 recording shows none (its events in the 500 µs after an exposure edge are
  ≈ 1–2 *below* its mean rate, ±0.5), so it is off; it is there for setups that show one.
* Noise (:class:`DvsNoise`): shot noise (random polarity) and leak events (ON only, the
  reference leaking down, v2e §4.2), independent Poisson processes per pixel whose rates spread
  log-normally across pixels (0.1 decade, v2e's ``noise_rate_cov_decades``); 0.05 Hz each by
  default, 0.1 Hz per pixel in all. They are drawn in fixed 10 ms blocks keyed by the block
  index, so they too are independent of the windowing. They do not reset the pixel (a
  simplification: at 0.1 Hz they rarely meet signal events).

**APS** (§4.4 step 6, davis240c-usb.md §9): global-shutter exposures of ``exposure_us``
starting at ``exposure_offset_us + k·frame_interval_us`` (device µs, ``k = 0, 1, …``). The frame
is the time average of the linear irradiance over the exposure (trapezoidal over the renders,
which include both ends), i.e. motion blur; then ``cds = gain · Ī · exposure / 4 ms`` with a
per-pixel 0.5 % gain mismatch (Brandli et al.: 0.5 % FPN), Gaussian read noise of 2.9 counts
(51 dB of a 10-bit range) and rounding/clipping to [0, 1023].

**IMU** (davis240c-usb.md §10): samples every ``1e6 / imu_rate_hz`` µs (1 kHz default).
Assumed mounting: the IMU axes are the camera's x (right), −y (up) and −z (out of the lens
towards the viewer), a right-handed frame "in the camera plane: X right, Y up" as libcaer's
``imu6.h`` describes. The rig's cameras are static, so the accelerometer reads the specific
force ``+1 g`` up (gravity reaction) and the gyroscope 0, plus a constant per-seed bias
(σ 10 mg, 0.5 °/s) and white noise (5 mg, 0.07 °/s rms: MPU-6050 densities of 400 µg/√Hz and
0.005 °/s/√Hz over the 184 Hz DLPF). Temperature 30–35 °C (per seed) with a slow 0.2 °C drift.

**External input** (davis240c-usb.md §11, realsense-d415.md §2.2): the D415 sync master pulses
its sync pin once per frame, ~50 µs high. By default pulse ``k`` rises when the master's own
clock reads ``k · 1e9 / rate_hz`` ns (or wherever ``sync_source`` says, e.g. the mock D415
master's timeline); the edges are mapped master clock → session → DAVIS device µs and
reported as :attr:`ExtInputEdge.RISING` / :attr:`ExtInputEdge.FALLING`. Deciding which of them
the device reports (the detector config, pulse detection) is the device logic's job.

**Time.** Device time is integer µs from the last :meth:`DavisSimulator.reset`; a session time
``s`` (ns) is device time ``(s − s_reset) · (1 + drift_ppm·1e-6) / 1000`` µs with the DAVIS
clock's drift (its offset only sets the reset instant). The clock's stamping jitter is not
applied: the µs counter *is* the sensor's timestamp.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from mocaprig.acquire.events import make_events
from mocaprig.drivers_mock.clock import _hash_normal, hash_normal
from mocaprig.drivers_mock.davis240c_render import (
    DAVIS_SHAPE,
    DavisLook,
    DavisRenderer,
    log_intensity,
)
from mocaprig.drivers_mock.davis_activity import (
    EXT_INPUT_DTYPE,
    IMU_DTYPE,
    ApsExposure,
    DavisActivity,
    ExtInputEdge,
)
from mocaprig.drivers_mock.scenario import Scenario
from mocaprig.errors import ValidationError
from mocaprig.validation import check_range

__all__ = [
    "DavisSimulator",
    "DvsNoise",
    "EdgeScore",
    "edge_fraction",
    "photoreceptor_lowpass",
    "simulate_davis",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: Pixels of the largest supported sensor (DAVIS346, 346×260): the bound on hot pixels.
_MAX_PIX = 346 * 260
#: Noise events are drawn in blocks of this many device µs (keyed by block index).
_NOISE_BLOCK_US = 10_000
#: Reference exposure of the APS gain (the libcaer default, davis240c-usb.md §9.3).
_APS_REF_EXPOSURE_US = 4000
#: APS read noise: 51 dB dynamic range of a 10-bit range (Brandli et al. 2014) → 1023 / 10^2.55.
_APS_READ_NOISE = 1023.0 / 10.0 ** (51.0 / 20.0)
#: APS fixed-pattern gain noise (0.5 % FPN, Brandli et al. 2014).
_APS_FPN = 0.005


@dataclass(frozen=True, slots=True)
class DvsNoise:
    """DVS noise rates (eventcap-method.md §4.3: shot 0.001–1 Hz, leak 0.01–0.1 Hz per pixel).

    The defaults give 0.1 Hz of background activity per pixel, what the real DAVIS240C
    recording shows in good light (docs/davis-sim.md: 0.11 Hz of isolated events per pixel,
    an upper bound since some of them are sparse edge events).

    Attributes:
        shot_hz: Mean shot-noise rate per pixel (Hz), half ON, half OFF.
        leak_hz: Mean leak-event rate per pixel (Hz), all ON.
        spread_decades: σ of log10 of the per-pixel rates (v2e ``noise_rate_cov_decades``).
        hot_pixels: Number of hot pixels (random places per seed), firing random-polarity
            events at ``hot_pixel_hz`` each (§4.4 step 5 "optional hot pixels"; off by default).
        hot_pixel_hz: Event rate of a hot pixel (Hz).
    """

    shot_hz: float = 0.05
    leak_hz: float = 0.05
    spread_decades: float = 0.1
    hot_pixels: int = 0
    hot_pixel_hz: float = 50.0

    def __post_init__(self) -> None:
        check_range(self.shot_hz, 0.0, 1e3, name="DvsNoise.shot_hz")
        check_range(self.leak_hz, 0.0, 1e3, name="DvsNoise.leak_hz")
        check_range(self.spread_decades, 0.0, 2.0, name="DvsNoise.spread_decades")
        check_range(self.hot_pixels, 0, _MAX_PIX, name="DvsNoise.hot_pixels")
        check_range(self.hot_pixel_hz, 0.0, 1e5, name="DvsNoise.hot_pixel_hz")

    @classmethod
    def none(cls) -> DvsNoise:
        """No background activity (signal events only)."""
        return cls(shot_hz=0.0, leak_hz=0.0, hot_pixels=0)

    @property
    def total_hz(self) -> float:
        """Expected noise events per second over a whole 240×180 (DAVIS240C) array."""
        return self.rate_hz(DAVIS_SHAPE[0] * DAVIS_SHAPE[1])

    def rate_hz(self, pixels: int) -> float:
        """Expected noise events per second over an array of ``pixels`` pixels."""
        return (self.shot_hz + self.leak_hz) * pixels + self.hot_pixels * self.hot_pixel_hz


@dataclass(slots=True, eq=False)
class _Exposure:
    start_us: int
    end_us: int
    start_ns: int
    end_ns: int
    acc: F64 = field(repr=False)


@dataclass(slots=True, eq=False)
class _EventBuffer:
    t: list[I64] = field(default_factory=list)
    idx: list[I64] = field(default_factory=list)
    pol: list[npt.NDArray[np.bool_]] = field(default_factory=list)

    def add(self, t: I64, idx: I64, pol: npt.NDArray[np.bool_]) -> None:
        if t.size:
            self.t.append(t)
            self.idx.append(idx)
            self.pol.append(pol)

    def pop_before(self, t1_us: int) -> tuple[I64, I64, npt.NDArray[np.bool_]]:
        if not self.t:
            return np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, bool)
        t = np.concatenate(self.t)
        idx = np.concatenate(self.idx)
        pol = np.concatenate(self.pol)
        now = t < t1_us
        self.t, self.idx, self.pol = [t[~now]], [idx[~now]], [pol[~now]]
        return t[now], idx[now], pol[now]


def _check_int(value: Any, name: str, *, low: int = 0) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        msg = f"{name} must be an integer, got {value!r}"
        raise ValidationError(msg)
    if int(value) < low:
        msg = f"{name} must be >= {low}, got {value}"
        raise ValidationError(msg)
    return int(value)


def photoreceptor_lowpass(x0: F64, x1: F64, y0: F64, dt_us: float, tau_us: F64 | float) -> F64:
    """First-order low-pass ``τ·dy/dt = x − y`` over one interval, exact for ``x`` linear in time.

    With ``x`` going from ``x0`` to ``x1`` over ``dt_us`` and the output starting at ``y0``:
    ``y1 = x1 − m·τ·(1 − a) + (y0 − x0)·a`` with ``m = (x1 − x0)/dt`` and ``a = exp(−dt/τ)``
    (eventcap-method.md §4.4 step 4; unlike v2e's Euler step it stays exact for ``dt ≫ τ``).
    """
    if dt_us <= 0:
        return np.asarray(y0, dtype=np.float64).copy()
    tau = np.asarray(tau_us, dtype=np.float64)
    a = np.exp(-dt_us / tau)
    out: F64 = x1 - (x1 - x0) * (tau / dt_us) * (1.0 - a) + (y0 - x0) * a
    return out


def _dvs_step(
    l0: F64,
    l1: F64,
    u0: float,
    u1: float,
    ref: F64,
    c_on: F64,
    c_off: F64,
    dead_until: F64,
    dead_us: F64,
) -> tuple[F64, I64, npt.NDArray[np.bool_]]:
    """Events of every pixel for ``L`` linear from ``l0`` at ``u0`` to ``l1`` at ``u1`` (µs).

    A pixel fires when ``L`` reaches ``ref + C_on`` (ON) or ``ref − C_off`` (OFF), at the
    interpolated time ``t``; its reset switch then holds it for ``dead_us`` and, on release at
    ``t + dead_us``, it memorises the level ``L`` has then (module doc: dead time). With
    ``dead_us = 0`` this is ESIM's ``ref ± C``. Updates ``ref`` and ``dead_until`` (each pixel's
    release time, µs) in place. Returns event times (float device µs), flat pixel indices and
    polarities (True = ON).
    """
    span = u1 - u0
    if span <= 0:
        return np.empty(0), np.empty(0, np.int64), np.empty(0, bool)
    slope = (l1 - l0) / span
    # Pixels released inside this interval memorise the level at their release.
    rel = np.flatnonzero((dead_until >= u0) & (dead_until < u1))
    ref[rel] = l0[rel] + slope[rel] * (dead_until[rel] - u0)
    # L is linear, so a pixel responsive before u1 fires iff L(u1) lies outside its band.
    cand = np.flatnonzero(dead_until < u1)
    cand = cand[(l1[cand] >= ref[cand] + c_on[cand]) | (l1[cand] <= ref[cand] - c_off[cand])]
    ts: list[F64] = []
    ids: list[I64] = []
    ps: list[npt.NDArray[np.bool_]] = []
    while cand.size:
        up = l1[cand] > ref[cand]
        level = np.where(up, ref[cand] + c_on[cand], ref[cand] - c_off[cand])
        start = np.maximum(dead_until[cand], u0)
        t = np.clip(u0 + (level - l0[cand]) / slope[cand], start, u1)
        ts.append(t)
        ids.append(cand)
        ps.append(up)
        free = t + dead_us[cand]
        dead_until[cand] = free
        inside = free < u1
        # Released before u1: the memorised level is L at release (exactly ``level`` when
        # there is no dead time).
        ref[cand] = np.where(dead_us[cand] > 0.0, l0[cand] + slope[cand] * (free - u0), level)
        cand = cand[inside]
        cand = cand[(l1[cand] >= ref[cand] + c_on[cand]) | (l1[cand] <= ref[cand] - c_off[cand])]
    if not ts:
        return np.empty(0), np.empty(0, np.int64), np.empty(0, bool)
    return np.concatenate(ts), np.concatenate(ids), np.concatenate(ps)


class DavisSimulator:
    """A DAVIS240C rendering the simulated world (module doc for the models and numbers).

    Args:
        scenario: The world. Random draws come from ``scenario.rng("davis")`` (thresholds, FPN,
            noise, IMU) and ``scenario.rng("davis-texture")`` (the body texture).
        exposure_us: APS exposure (µs, ≥ 1; libcaer default 4000).
        frame_interval_us: APS frame interval (µs; default 40000 = 25 fps).
        exposure_offset_us: Device time of the first exposure start after a reset (µs); default
            18000, the global-shutter reset read of 240 columns at ≈ 75 µs each (§9.3).
        contrast_on: Mean ON threshold (ln units).
        contrast_off: Mean OFF threshold (ln units).
        contrast_sigma: Per-pixel threshold mismatch σ (ln units).
        refractory_us: Median per-pixel dead time (µs; module doc; the real recordings give
            1.2–1.7 ms, a bias setting on a real chip; 0 = ESIM's ideal pixel).
        refractory_spread: σ of the log of the per-pixel dead time (0–1).
        latency_us: Pixel latency added to every DVS event (µs).
        jitter_us: σ of the Gaussian timestamp jitter on top of the latency (µs; tens of µs in
            good light, up to ms in the dark).
        cutoff_hz: Photoreceptor 3 dB cutoff at irradiance 1 (Hz; §4.3: 100–300 Hz in good
            light), scaled down in proportion to a pixel's irradiance (v2e); 0 = off.
        aps_burst_fraction: Fraction of pixels firing one event at each exposure start and end
            (module doc; 0 = off, the default).
        noise: DVS background activity (default :class:`DvsNoise`).
        imu_rate_hz: IMU sample rate (default 1 kHz).
        sync_pulse_us: Width of the D415 master's sync pulse (µs; ~50 µs, realsense-d415.md §2.2).
        motion_step_px: Largest image motion between two renders (px; §4.4: 0.3–0.5 px).
        max_render_interval_us: Longest time between renders (µs).
        probe_interval_us: Period at which the image motion is probed (µs).
        look: Scene appearance.
        reset_session_ns: The session instant of device time 0 until :meth:`reset` says
            otherwise.
        sync_source: The sync master's pulse timeline, ``f(t_ns) ->`` the first rising edge
            at or after session time ``t_ns`` (ns), or ``None`` when there are no more (e.g.
            the master :class:`mocaprig.drivers_mock.d415.MockD415`'s ``pulse_at_or_after``, so the
            DAVIS sees the pulses the mock D415s use). Default: the master streams for the
            whole session with pulse ``k`` at ``k · 1e9 / rate_hz`` ns of its own clock.

    Raises:
        ValidationError: an option out of range.
    """

    def __init__(
        self,
        scenario: Scenario,
        *,
        exposure_us: int = 4000,
        frame_interval_us: int = 40_000,
        exposure_offset_us: int = 18_000,
        contrast_on: float = 0.22,
        contrast_off: float = 0.18,
        contrast_sigma: float = 0.03,
        refractory_us: int = 1600,
        refractory_spread: float = 0.05,
        latency_us: int = 12,
        jitter_us: float = 10.0,
        cutoff_hz: float = 300.0,
        aps_burst_fraction: float = 0.0,
        noise: DvsNoise | None = None,
        imu_rate_hz: float = 1000.0,
        sync_pulse_us: int = 50,
        motion_step_px: float = 0.5,
        max_render_interval_us: int = 5000,
        probe_interval_us: int = 1000,
        look: DavisLook | None = None,
        reset_session_ns: int = 0,
        sync_source: Callable[[int], int | None] | None = None,
    ) -> None:
        self.scenario = scenario
        #: False while the DVS module is off (``configure(dvs_enabled=...)``).
        self.dvs_enabled = True
        self._readapt = False
        self.exposure_us = 0
        self.frame_interval_us = 0
        self.imu_rate_hz = 0.0
        self.configure(
            exposure_us=exposure_us, frame_interval_us=frame_interval_us, imu_rate_hz=imu_rate_hz
        )
        self.exposure_offset_us = _check_int(exposure_offset_us, "exposure_offset_us")
        check_range(contrast_on, 0.01, 5.0, name="contrast_on")
        check_range(contrast_off, 0.01, 5.0, name="contrast_off")
        check_range(contrast_sigma, 0.0, 1.0, name="contrast_sigma")
        self.refractory_us = _check_int(refractory_us, "refractory_us")
        check_range(refractory_spread, 0.0, 1.0, name="refractory_spread")
        self.latency_us = _check_int(latency_us, "latency_us")
        self.jitter_us = float(check_range(jitter_us, 0.0, 1e4, name="jitter_us"))
        self.cutoff_hz = float(check_range(cutoff_hz, 0.0, 1e5, name="cutoff_hz"))
        self.aps_burst_fraction = float(
            check_range(aps_burst_fraction, 0.0, 1.0, name="aps_burst_fraction")
        )
        self.noise = DvsNoise() if noise is None else noise
        self.sync_pulse_us = _check_int(sync_pulse_us, "sync_pulse_us", low=1)
        self._sync_source = sync_source
        self.motion_step_px = float(check_range(motion_step_px, 0.05, 10.0, name="motion_step_px"))
        self.max_render_interval_us = _check_int(
            max_render_interval_us, "max_render_interval_us", low=1
        )
        self.probe_interval_us = _check_int(probe_interval_us, "probe_interval_us", low=10)
        self.renderer = DavisRenderer(scenario, look=look)
        #: Sensor shape (rows, columns), the rig's DAVIS camera's (180×240 or 260×346).
        self.shape: tuple[int, int] = self.renderer.shape
        self._npix = self.shape[0] * self.shape[1]
        if self.noise.hot_pixels > self._npix:
            msg = f"DvsNoise.hot_pixels ({self.noise.hot_pixels}) exceeds the {self._npix} pixels"
            raise ValidationError(msg)
        self._clock = scenario.clocks["davis"]
        masters = [d for d in scenario.rig.d415 if d.role == "master"]
        self._master = masters[0] if masters else None

        rng = scenario.rng("davis")
        npix = self._npix
        self.c_on = np.maximum(rng.normal(contrast_on, contrast_sigma, npix), 0.01)
        self.c_off = np.maximum(rng.normal(contrast_off, contrast_sigma, npix), 0.01)
        #: Per-pixel dead time (µs): log-normal about ``refractory_us`` (transistor mismatch).
        self.dead_us = float(self.refractory_us) * np.exp(rng.normal(0.0, refractory_spread, npix))
        self._ref_phase = rng.random(npix)
        spread = np.log(10.0) * self.noise.spread_decades
        lognorm = np.exp(rng.normal(-0.5 * spread**2, spread, (2, npix)))  # mean 1
        self._shot_p = lognorm[0] / lognorm[0].sum()
        self._leak_p = lognorm[1] / lognorm[1].sum()
        self._noise_seed = int(rng.integers(0, 2**62))
        self._hot = rng.permutation(npix)[: self.noise.hot_pixels].astype(np.int64)
        self._fpn = 1.0 + rng.normal(0.0, _APS_FPN, self.shape)
        self._aps_seed = int(rng.integers(0, 2**62))
        self._imu_seed = int(rng.integers(0, 2**62))
        self._accel_bias_g = rng.normal(0.0, 0.01, 3)
        self._gyro_bias_dps = rng.normal(0.0, 0.5, 3)
        self._temp0_c = float(rng.uniform(30.0, 35.0))
        self._temp_phase = float(rng.uniform(0.0, 2.0 * np.pi))
        self._jitter_seed = int(rng.integers(0, 2**62))
        #: Renders done since construction (for profiling).
        self.render_count = 0
        self.reset(session_ns=reset_session_ns)

    # ----------------------------------------------------------------------------------------
    # time

    def reset(self, *, session_ns: int) -> None:
        """Device time 0 is now session time ``session_ns`` (a timestamp reset)."""
        self._reset_ns = _check_int(session_ns, "session_ns", low=-(2**62))
        self._rate = self._clock.rate
        self._cursor_us = 0
        self._started = False
        self._events = _EventBuffer()
        self._exposures: list[_Exposure] = []
        self._done: list[ApsExposure] = []
        self._next_start_us = self.exposure_offset_us
        self._noise_cache: dict[int, tuple[I64, I64, npt.NDArray[np.bool_]]] = {}

    def configure(
        self,
        *,
        exposure_us: int | None = None,
        frame_interval_us: int | None = None,
        imu_rate_hz: float | None = None,
        dvs_enabled: bool | None = None,
    ) -> None:
        """Change APS, IMU or DVS settings (the USB mock's register writes); ``None`` keeps one.

        ``dvs_enabled=False`` (the DVS module is off) skips the DVS model: no events, no motion
        probing; renders only at APS exposure starts and ends (about a tenth of the cost with
        the default 4 ms exposure every 40 ms). When it comes back on, every pixel re-adapts to
        the scene (as after a reset).

        Exposures already scheduled keep their settings (the simulator plans up to 20 probe
        intervals, 20 ms by default, ahead of the last window); the next one starts one new
        ``frame_interval_us`` after the last scheduled start. The IMU's sample grid is
        ``k · 1e6 / imu_rate_hz`` µs from the reset.

        Raises:
            ValidationError: ``exposure_us < 1``, an exposure longer than the interval, or an
                IMU rate outside [1, 8000] Hz (the MPU-6050's 8 kHz gyro rate at most).
        """
        exp = (
            self.exposure_us
            if exposure_us is None
            else _check_int(exposure_us, "exposure_us", low=1)
        )
        interval = (
            self.frame_interval_us
            if frame_interval_us is None
            else _check_int(frame_interval_us, "frame_interval_us", low=1)
        )
        if exp > interval:
            msg = f"exposure_us ({exp}) must not exceed frame_interval_us ({interval})"
            raise ValidationError(msg)
        if imu_rate_hz is not None:
            self.imu_rate_hz = float(check_range(imu_rate_hz, 1.0, 8000.0, name="imu_rate_hz"))
        if self.frame_interval_us and interval != self.frame_interval_us:
            self._next_start_us += interval - self.frame_interval_us
        self.exposure_us, self.frame_interval_us = exp, interval
        if dvs_enabled is not None:
            enabled = bool(dvs_enabled)
            if enabled and not getattr(self, "dvs_enabled", True):
                self._readapt = True
            self.dvs_enabled = enabled

    def session_ns(self, t_us: npt.ArrayLike) -> I64:
        """Session times (int ns) of device times (µs, int or float)."""
        u = np.asarray(t_us, dtype=np.float64)
        out: I64 = self._reset_ns + np.round(u * 1000.0 / self._rate).astype(np.int64)
        return out

    def device_us(self, t_ns: npt.ArrayLike) -> F64:
        """Device times (float µs, not floored) of session times (ns)."""
        s = np.asarray(t_ns, dtype=np.float64)
        out: F64 = (s - self._reset_ns) * self._rate / 1000.0
        return out

    # ----------------------------------------------------------------------------------------
    # truth

    def render_intensity(self, t_ns: int) -> F64:
        """The linear irradiance the pixels see at a session time (ns), ``(180, 240)``."""
        return self.renderer.render(int(t_ns))

    def edge_map(self, t_ns: int, *, threshold: float = 0.05) -> npt.NDArray[np.bool_]:
        """True intensity edges at a session time (:meth:`DavisRenderer.edge_map`)."""
        return self.renderer.edge_map(int(t_ns), threshold=threshold)

    # ----------------------------------------------------------------------------------------
    # the activity source

    def activity(self, t0_us: int, t1_us: int) -> DavisActivity:
        """Everything the sensor does in ``[t0_us, t1_us)`` device µs.

        Windows must come in order; a window may start after the previous one ended (the
        pixels then re-adapt to the scene at ``t0_us`` and exposures that began in the gap are
        lost) but not before.

        Raises:
            ValidationError: non-integer bounds, ``t1_us < t0_us`` or an overlap with the
                previous window.
        """
        t0 = _check_int(t0_us, "t0_us")
        t1 = _check_int(t1_us, "t1_us")
        if t1 < t0:
            msg = f"activity window ends ({t1} µs) before it starts ({t0} µs)"
            raise ValidationError(msg)
        if t0 < self._cursor_us:
            msg = (
                f"activity windows must not overlap: this one starts at {t0} µs, the previous "
                f"one ended at {self._cursor_us} µs; reset() to start again"
            )
            raise ValidationError(msg)
        if not self._started or t0 > self._cursor_us:
            self._restart(t0)
        self._cursor_us = t1
        if t1 == t0:
            return DavisActivity(t0_us=t0, t1_us=t1, events=make_events([], [], [], []))
        self._advance(int(self.session_ns(t1)))
        t, idx, pol = self._events.pop_before(t1)
        if self.dvs_enabled:
            nt, nidx, npol = self._noise(t0, t1)
        else:
            nt, nidx, npol = np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, bool)
        t = np.concatenate([t, nt])
        idx = np.concatenate([idx, nidx])
        pol = np.concatenate([pol, npol])
        order = np.lexsort((idx, t))
        t, idx, pol = t[order], idx[order], pol[order]
        w = self.shape[1]
        events = make_events(t, idx % w, idx // w, pol)
        done = [e for e in self._done if e.end_us < t1]
        self._done = [e for e in self._done if e.end_us >= t1]
        done = [e for e in done if e.end_us >= t0]
        return DavisActivity(
            t0_us=t0,
            t1_us=t1,
            events=events,
            exposures=tuple(done),
            imu=self._imu(t0, t1),
            ext_input=self._ext_input(t0, t1),
        )

    # ----------------------------------------------------------------------------------------
    # DVS

    def _restart(self, t0_us: int) -> None:
        """Adapt every pixel to the scene at device time ``t0_us`` (start or after a gap)."""
        s0 = int(self.session_ns(t0_us))
        probe_ns = self.probe_interval_us * 1000
        # The render/probe grid is anchored at the reset instant (window-independent).
        self._grid_i = (s0 - self._reset_ns) // probe_ns
        self._r_ns = s0
        self._i_prev = self.renderer.render(s0)
        self.render_count += 1
        self._l_prev = log_intensity(self._i_prev).ravel()
        self._x_prev = self._l_prev.copy()
        self._u_prev = float(self.device_us(s0))
        # Anywhere strictly between the two firing levels: L - C_on < ref < L + C_off.
        self.ref = self._l_prev - self.c_on + self._ref_phase * (self.c_on + self.c_off)
        #: Device time (µs) at which each pixel's reset switch releases it (module doc).
        self.dead_until = np.full(self._npix, -np.inf)
        self._acc_px = 0.0
        self._last_render_ns = s0
        self._exposures = []
        self._events = _EventBuffer()
        k = max(0, -(-(t0_us - self.exposure_offset_us) // self.frame_interval_us))
        self._next_start_us = self.exposure_offset_us + k * self.frame_interval_us
        self._started = True

    def _grid_ns(self, i: int) -> int:
        return self._reset_ns + i * self.probe_interval_us * 1000

    def _advance(self, s_target: int) -> None:
        """Render and emit events until the state's time reaches ``s_target`` (session ns)."""
        chunk = 20
        while self._r_ns < s_target:
            g0 = self._grid_i
            n_needed = -(-(s_target - self._grid_ns(g0)) // (self.probe_interval_us * 1000))
            n = int(min(max(n_needed, 1), chunk))
            grid = np.array([self._grid_ns(g0 + i) for i in range(n + 1)], dtype=np.int64)
            grid[0] = max(int(grid[0]), self._r_ns)
            times = self._plan(grid)
            self._grid_i = g0 + n
            self._render_through(times)

    def _plan(self, grid: I64) -> I64:
        """Render times in ``(grid[0], grid[-1]]`` (module doc: adaptive sampling)."""
        lam = self.motion_step_px
        max_ns = self.max_render_interval_us * 1000
        out: list[int] = []
        # DVS off: no motion probing, renders at the APS exposure bounds only.
        disp = self.renderer.max_motion_px(grid) if self.dvs_enabled else np.zeros(0)
        for a, b, d in zip(grid[:-1], grid[1:], disp, strict=False):
            a_i, b_i, d_f = int(a), int(b), float(d)
            if d_f > lam:
                k = min(int(np.ceil(d_f / lam)), max((b_i - a_i) // 10_000, 1))
                out.extend(a_i + (b_i - a_i) * j // k for j in range(1, k + 1))
                self._acc_px = 0.0
                self._last_render_ns = b_i
                continue
            self._acc_px += d_f
            if self._acc_px >= lam or b_i - self._last_render_ns >= max_ns:
                out.append(b_i)
                self._acc_px = 0.0
                self._last_render_ns = b_i
        # APS exposures starting in this stretch; their start and end are render times.
        lo, hi = int(grid[0]), int(grid[-1])
        while True:
            start_us = self._next_start_us
            start_ns = int(self.session_ns(start_us))
            if start_ns > hi:
                break
            end_us = start_us + self.exposure_us
            self._next_start_us += self.frame_interval_us
            if start_ns < self._r_ns:
                continue  # scheduled before the pixels' current time (a settings change): lost
            self._exposures.append(
                _Exposure(
                    start_us, end_us, start_ns, int(self.session_ns(end_us)), np.zeros(self.shape)
                )
            )
            if self.dvs_enabled and self.aps_burst_fraction > 0:
                self._events.add(*self._burst(start_us, end_us))
        for e in self._exposures:
            out.extend(t for t in (e.start_ns, e.end_ns) if lo < t <= hi)
        times = np.unique(np.array(out, dtype=np.int64))
        result: I64 = times[times > self._r_ns]
        return result

    def _render_through(self, times: I64) -> None:
        batch = 16
        for b0 in range(0, times.size, batch):
            ts = times[b0 : b0 + batch]
            imgs = self.renderer.render_batch(ts)
            self.render_count += ts.size
            for t_ns, img in zip(ts, imgs, strict=True):
                self._step(int(t_ns), img)

    def _step(self, t_ns: int, img: F64) -> None:
        x1 = log_intensity(img).ravel()
        u1 = float(self.device_us(t_ns))
        if self.cutoff_hz > 0:
            # v2e: the photoreceptor's bandwidth scales with the light it gets.
            bright = np.clip(img.ravel(), 0.01, 1.0)
            tau_us = 1e6 / (2.0 * np.pi * self.cutoff_hz) / bright
            l1 = photoreceptor_lowpass(self._x_prev, x1, self._l_prev, u1 - self._u_prev, tau_us)
        else:
            l1 = x1
        if self._readapt and self.dvs_enabled:
            # The DVS came back on: every pixel starts between its firing levels again.
            self.ref = self._l_prev - self.c_on + self._ref_phase * (self.c_on + self.c_off)
            self.dead_until = np.full(self._npix, -np.inf)
            self._readapt = False
        if self.dvs_enabled:
            t, idx, pol = _dvs_step(
                self._l_prev,
                l1,
                self._u_prev,
                u1,
                self.ref,
                self.c_on,
                self.c_off,
                self.dead_until,
                self.dead_us,
            )
        else:
            t = np.empty(0)
        if t.size:
            self._events.add(self._stamp(t, u1), idx, pol)
        # APS: exposures covering [r_prev, t_ns] integrate the trapezoid of the irradiance.
        still: list[_Exposure] = []
        for e in self._exposures:
            if e.start_ns <= self._r_ns and t_ns <= e.end_ns:
                e.acc += 0.5 * (self._i_prev + img) * float(t_ns - self._r_ns)
            if t_ns >= e.end_ns:
                self._done.append(self._finish_exposure(e))
            else:
                still.append(e)
        self._exposures = still
        self._i_prev, self._l_prev, self._u_prev, self._r_ns = img, l1, u1, t_ns
        self._x_prev = x1

    def _stamp(self, t: F64, u1: float) -> I64:
        """Integer µs timestamps of crossings at float device µs ``t`` (latency and jitter).

        The jitter is a Gaussian of σ ``jitter_us`` on top of the fixed latency, cut so the
        total latency is never negative (an event is never stamped before its crossing, so
        events stay within their window). The draws are keyed by the render's end time, so
        they do not depend on the windowing.
        """
        out = t + self.latency_us
        if self.jitter_us > 0:
            key = round(u1 * 1000.0)
            rng = np.random.default_rng([self._jitter_seed, key & 0xFFFFFFFF, (key >> 32) & 0xFFFF])
            out = t + np.maximum(self.latency_us + rng.normal(0.0, self.jitter_us, t.size), 0.0)
        stamped: I64 = np.floor(out).astype(np.int64)
        return stamped

    def _burst(self, start_us: int, end_us: int) -> tuple[I64, I64, npt.NDArray[np.bool_]]:
        """Events the global-shutter reset and transfer of one exposure cause (module doc).

        At the exposure start (global photodiode reset) and end (global charge transfer) each
        pixel fires one event with probability ``aps_burst_fraction``, OFF at the start and ON
        at the end, within the pixel latency plus ``|N(0, 2·jitter)|`` of the edge.
        """
        rng = np.random.default_rng([self._jitter_seed ^ 0x5A5A, start_us & 0xFFFFFFFF])
        ts: list[I64] = []
        ids: list[I64] = []
        ps: list[npt.NDArray[np.bool_]] = []
        for edge_us, on in ((start_us, False), (end_us, True)):
            idx = np.flatnonzero(rng.random(self._npix) < self.aps_burst_fraction)
            lag = self.latency_us + np.abs(rng.normal(0.0, 2.0 * self.jitter_us + 1.0, idx.size))
            ts.append(np.floor(edge_us + lag).astype(np.int64))
            ids.append(idx.astype(np.int64))
            ps.append(np.full(idx.size, on))
        return np.concatenate(ts), np.concatenate(ids), np.concatenate(ps)

    def _finish_exposure(self, e: _Exposure) -> ApsExposure:
        mean = e.acc / float(max(e.end_ns - e.start_ns, 1))
        gain = 900.0 * (e.end_us - e.start_us) / _APS_REF_EXPOSURE_US
        rng = np.random.default_rng([self._aps_seed, e.start_us & 0xFFFFFFFF, e.start_us >> 32])
        cds = gain * mean * self._fpn + rng.normal(0.0, _APS_READ_NOISE, self.shape)
        return ApsExposure(
            start_us=e.start_us, end_us=e.end_us, cds=np.clip(np.round(cds), 0.0, 1023.0)
        )

    def _noise_block(self, b: int) -> tuple[I64, I64, npt.NDArray[np.bool_]]:
        cached = self._noise_cache.get(b)
        if cached is not None:
            return cached
        rng = np.random.default_rng([self._noise_seed, b & 0xFFFFFFFF, (b >> 32) & 0xFFFFFFFF])
        dur_s = _NOISE_BLOCK_US * 1e-6
        npix = self._npix
        n_shot = int(rng.poisson(self.noise.shot_hz * npix * dur_s))
        n_leak = int(rng.poisson(self.noise.leak_hz * npix * dur_s))
        idx = np.concatenate(
            [
                rng.choice(npix, size=n_shot, p=self._shot_p),
                rng.choice(npix, size=n_leak, p=self._leak_p),
            ]
        ).astype(np.int64)
        n_hot = rng.poisson(self.noise.hot_pixel_hz * dur_s, self._hot.size)
        idx = np.concatenate([idx, np.repeat(self._hot, n_hot)])
        pol = np.concatenate(
            [
                rng.random(n_shot) < 0.5,  # shot noise: either polarity
                np.ones(n_leak, bool),  # leak: the reference drifts down, so ON
                rng.random(int(n_hot.sum())) < 0.5,
            ]
        )
        t = b * _NOISE_BLOCK_US + rng.integers(0, _NOISE_BLOCK_US, idx.size)
        out = (t.astype(np.int64), idx, pol)
        if len(self._noise_cache) > 4:
            self._noise_cache.clear()
        self._noise_cache[b] = out
        return out

    def _noise(self, t0: int, t1: int) -> tuple[I64, I64, npt.NDArray[np.bool_]]:
        if self.noise.total_hz <= 0:
            return np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, bool)
        ts, ids, ps = [], [], []
        for b in range(t0 // _NOISE_BLOCK_US, (t1 - 1) // _NOISE_BLOCK_US + 1):
            t, idx, pol = self._noise_block(b)
            sel = (t >= t0) & (t < t1)
            ts.append(t[sel])
            ids.append(idx[sel])
            ps.append(pol[sel])
        return np.concatenate(ts), np.concatenate(ids), np.concatenate(ps)

    # ----------------------------------------------------------------------------------------
    # IMU and external input

    def imu_axes_in_camera(self) -> F64:
        """``R_cam_imu`` (3×3): columns are the IMU's x, y, z axes in the camera frame."""
        return np.diag([1.0, -1.0, -1.0])

    def _imu(self, t0: int, t1: int) -> npt.NDArray[np.void]:
        period = 1e6 / self.imu_rate_hz
        k0 = max(1, int(np.ceil(t0 / period)))
        k = np.arange(k0, int(np.ceil(t1 / period)) + 1, dtype=np.int64)
        t = np.round(k * period).astype(np.int64)
        k, t = k[(t >= t0) & (t < t1)], t[(t >= t0) & (t < t1)]
        out = np.empty(k.size, dtype=IMU_DTYPE)
        if not k.size:
            return out
        r_world_cam = self.scenario.rig.davis.camera.T_world_cam[:3, :3]
        r_imu_world = self.imu_axes_in_camera().T @ r_world_cam.T
        # A static camera: specific force = +1 g along world up, no rotation.
        accel = r_imu_world @ np.array([0.0, 0.0, 1.0]) + self._accel_bias_g
        noise = np.stack([_hash_normal(self._imu_seed + j, k) for j in range(7)], axis=1)
        out["t"] = t
        out["accel_g"] = accel + 0.005 * noise[:, 0:3]
        out["gyro_dps"] = self._gyro_bias_dps + 0.07 * noise[:, 3:6]
        secs = self.session_ns(t).astype(np.float64) * 1e-9
        out["temp_c"] = (
            self._temp0_c
            + 0.2 * np.sin(2.0 * np.pi * secs / 600.0 + self._temp_phase)
            + 0.02 * noise[:, 6]
        )
        return out

    def _stamp_ext(self, edges_ns: I64) -> I64:
        """Device µs stamps of external-input edges (session ns): floored, plus the world's
        trigger stamping jitter (``WorldParams.davis_trigger_jitter_us``, 0 in the nominal
        world), a function of the edge instant so any window gives the same stamp."""
        t = self.device_us(edges_ns)
        sigma = self.scenario.world_params.davis_trigger_jitter_us
        if sigma > 0:
            t = t + sigma * hash_normal(self._jitter_seed ^ 0x7716, edges_ns)
        return np.floor(t).astype(np.int64)

    def _ext_input(self, t0: int, t1: int) -> npt.NDArray[np.void]:
        if self._sync_source is not None:
            return self._ext_input_from(self._sync_source, t0, t1)
        if self._master is None:
            return np.empty(0, EXT_INPUT_DTYPE)
        clock = self.scenario.clocks[self._master.name]
        period_ns = 1e9 / self._master.rate_hz
        s0, s1 = int(self.session_ns(t0)), int(self.session_ns(t1))
        m0, m1 = clock.device_ns(np.array([s0, s1]))
        width_ns = self.sync_pulse_us * 1000
        k = np.arange(int(np.floor((m0 - width_ns) / period_ns)), int(np.ceil(m1 / period_ns)) + 1)
        rise_m = np.round(k * period_ns).astype(np.int64)
        edges_m = np.stack([rise_m, rise_m + width_ns], axis=1).ravel()
        kinds = np.tile([int(ExtInputEdge.RISING), int(ExtInputEdge.FALLING)], k.size)
        u = self._stamp_ext(clock.session_ns(edges_m, unit_ns=1))
        sel = (u >= t0) & (u < t1)
        out = np.empty(int(sel.sum()), dtype=EXT_INPUT_DTYPE)
        out["t"] = u[sel]
        out["edge"] = kinds[sel]
        return out

    def _ext_input_from(
        self, source: Callable[[int], int | None], t0: int, t1: int
    ) -> npt.NDArray[np.void]:
        """Edges of pulses whose rising edges (session ns) come from ``source``."""
        s0, s1 = int(self.session_ns(t0)), int(self.session_ns(t1))
        width_ns = self.sync_pulse_us * 1000
        rises: list[int] = []
        t = s0 - width_ns - 1000
        while (p := source(t)) is not None and p < s1:
            rises.append(int(p))
            t = int(p) + 1
        r = np.array(rises, dtype=np.int64)
        edges = np.stack([r, r + width_ns], axis=1).ravel()
        kinds = np.tile([int(ExtInputEdge.RISING), int(ExtInputEdge.FALLING)], r.size)
        u = self._stamp_ext(edges)
        sel = (u >= t0) & (u < t1)
        out = np.empty(int(sel.sum()), dtype=EXT_INPUT_DTYPE)
        out["t"] = u[sel]
        out["edge"] = kinds[sel]
        return out


# --------------------------------------------------------------------------------------------
# conveniences and the acceptance measure


def simulate_davis(scenario: Scenario, *, t0_us: int, t1_us: int, **options: Any) -> DavisActivity:
    """The activity of a fresh :class:`DavisSimulator` (device 0 = session 0) in one window.

    ``options`` are :class:`DavisSimulator`'s keyword options.
    """
    return DavisSimulator(scenario, **options).activity(t0_us, t1_us)


@dataclass(frozen=True, slots=True)
class EdgeScore:
    """How well events sit on true intensity edges.

    Attributes:
        fraction: Fraction of events within ``radius_px`` of a true edge pixel of their slice.
        chance: Mean fraction of the image within ``radius_px`` of a true edge pixel (what
            events scattered uniformly over the image would score).
        events: Number of events scored.
    """

    fraction: float
    chance: float
    events: int


def edge_fraction(
    sim: DavisSimulator,
    events: npt.NDArray[np.void],
    *,
    t0_us: int,
    t1_us: int,
    slice_us: int = 2000,
    radius_px: int = 2,
    threshold: float = 0.1,
    kind: str = "changed",
) -> EdgeScore:
    """Score events against the true edges of the noise-free scene (the acceptance measure).

    Events are cut into ``slice_us`` slices of device time; slice ``[a, b)`` is scored against
    a map of true edge pixels dilated by a disc of ``radius_px``:

    * ``kind="changed"`` (default): the *moving* intensity edges, pixels whose noise-free log
      intensity ``log(1e-3 + I)`` differs by more than ``threshold`` (default 0.1 ln, half the
      nominal contrast threshold) between the renders at ``a`` and ``b``. A static textured
      background has none, so the chance level stays low.
    * ``kind="gradient"``: pixels where ``|∇ log(1e-3 + I)|`` of the render at the slice's
      midpoint exceeds ``threshold`` ln/px (:meth:`DavisRenderer.edge_map`); in a textured
      room most of the image is near such an edge, so the chance level is high.

    Raises:
        ValidationError: an unknown ``kind`` or a bad slice or radius.
    """
    if kind not in ("changed", "gradient"):
        msg = f"kind must be 'changed' or 'gradient', got {kind!r}"
        raise ValidationError(msg)
    _check_int(slice_us, "slice_us", low=1)
    r = _check_int(radius_px, "radius_px")
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    bounds = [*range(int(t0_us), int(t1_us), slice_us), int(t1_us)]
    if kind == "changed":
        logs = log_intensity(sim.renderer.render_batch(sim.session_ns(np.array(bounds))))
    hits = 0
    total = 0
    cover: list[float] = []
    for i, (a, b) in enumerate(itertools.pairwise(bounds)):
        ev = events[(events["t"] >= a) & (events["t"] < b)]
        if kind == "changed":
            edge = np.abs(logs[i + 1] - logs[i]) > threshold
        else:
            mid = int(sim.session_ns(0.5 * (a + b)))
            edge = sim.edge_map(mid, threshold=threshold)
        near = cv2.dilate(edge.astype(np.uint8), disc) > 0
        cover.append(float(near.mean()))
        hits += int(near[ev["y"].astype(np.intp), ev["x"].astype(np.intp)].sum())
        total += int(ev.size)
    return EdgeScore(
        fraction=hits / total if total else float("nan"),
        chance=float(np.mean(cover)) if cover else float("nan"),
        events=total,
    )
