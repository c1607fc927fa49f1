"""Serialise DAVIS240C sensor activity into the 16-bit word stream of bulk endpoint 0x82.

Written from ``davis240c-usb.md`` (the "note"), not from the driver, so that a test can catch the
driver and the mock disagreeing. The encoder plays the part of the device logic's multiplexer
(note §6, §7.1, §12): it takes :class:`~drivers_mock.davis_activity.DavisActivity` windows in
device µs and emits little-endian 16-bit words:

* DVS (§8): per row and timestamp one Y word then one X word per event (code 3 = ON,
  2 = OFF); a Y word is never sent without an X word.
* APS (§9.1, global shutter): frame start (special 8), three MISC10 exposure words (ADC cycles,
  low slice first), eight MISC8 ROI words, a reset read per ROI column (special 11, one ADC word
  per ROI row top first, special 13), exposure start / end (specials 14 / 15) at the exposure's
  own times, the signal read (special 12 ... 13), frame end (special 10).
* IMU (§10): special 5, the MISC8 info word, big-endian int16 bytes in register order
  (accel, temperature, gyro), special 7.
* External input (§6.3, §11.2): specials 3 (rising), 2 (falling), 4 (pulse) per the detector
  configuration.
* Timestamps (§7.1): a 15-bit timestamp word only before a Y, SPECIAL or ext-input word and
  only if the time differs from the one the host already holds; never a zero timestamp word;
  a WRAP word (``0x7000 | pending``) at every 32768 µs rollover, ahead of data at the same µs;
  the 0xFFFF case when a word is latched in the rollover cycle before the wrap goes out
  (``wrap_race``); a forced timestamp reset when 4096 wraps are pending (output blocked).

Because the stream must be monotonic and an APS frame starts (frame start word, reset read)
before its exposure, while a source reports an exposure only in the window where it *ends*, the
encoder holds words back by ``latency_us`` of device time and emits, for each window, the words
older than ``window end - latency_us``. :meth:`DavisWordEncoder.flush` emits the rest.
"""

from __future__ import annotations

import bisect
import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.events import EVENT_DTYPE
from mocaprig.drivers_mock.davis_activity import ApsExposure, DavisActivity, ExtInputEdge
from mocaprig.errors import ValidationError

__all__ = [
    "DAVIS240C_COLUMNS",
    "DAVIS240C_ROWS",
    "TIMESTAMP_WRAP_US",
    "DavisWordEncoder",
    "EncoderConfig",
    "encode_stream",
]

_log = logging.getLogger(__name__)

U16 = npt.NDArray[np.uint16]
I64 = npt.NDArray[np.int64]

#: Sensor size (note §13).
DAVIS240C_COLUMNS = 240
DAVIS240C_ROWS = 180

#: The 15-bit µs counter rolls over every 2**15 µs (note §7.1).
TIMESTAMP_WRAP_US = 1 << 15

# Word layout (note §6.1-6.4); written out here, independent of the driver.
_TS_FLAG = 0x8000
_CODE_SPECIAL = 0x0000
_CODE_Y = 0x1000
_CODE_X_OFF = 0x2000
_CODE_X_ON = 0x3000
_CODE_ADC = 0x4000
_CODE_MISC8 = 0x5000
_CODE_MISC10 = 0x6000
_CODE_WRAP = 0x7000

# SPECIAL sub-types (note §6.3, device numbering).
_SP_TS_RESET = 1
_SP_EXT_FALLING = 2
_SP_EXT_RISING = 3
_SP_EXT_PULSE = 4
_SP_IMU_START6 = 5
_SP_IMU_END = 7
_SP_FRAME_START_GS = 8
_SP_FRAME_END = 10
_SP_RESET_COL_START = 11
_SP_SIGNAL_COL_START = 12
_SP_COL_END = 13
_SP_EXPOSURE_START = 14
_SP_EXPOSURE_END = 15

# MISC8 / MISC10 sub-codes (note §6.4).
_M8_IMU_DATA = 0
_M8_ROI_HI = 1
_M8_ROI_LO = 2
_M8_IMU_INFO = 3
_M10_EXPOSURE = 0

#: The pending-wrap counter is 12 bits wide (note §6.2 code 7, §7.1).
_MAX_PENDING_WRAPS = 4095

#: ADC clock of the FX2 DAVIS240C (note §2.1: ADC = USB clock = 30 MHz).
_ADC_MHZ = 30

# APS readout timing (note §9.3, [I]): 1 µs column settle + 1/3 µs row settle plus ADC overhead,
# ≈ 75 µs per full 180-row column. Modelled as 30 + 12·rows ADC cycles per column.
_COL_SETTLE_CYCLES = 30
_ROW_CYCLES = 12

# Merge priorities at equal µs: wraps first (note §7.1), then ext input, APS, IMU, and DVS last.
_PRI_LATCHED = -1
_PRI_WRAP = 0
_PRI_EXT = 1
_PRI_APS = 2
_PRI_IMU = 3

# Accelerometer LSB/g and gyro LSB/(°/s) by full-scale code (note §10).
_ACCEL_LSB_PER_G = (16384.0, 8192.0, 4096.0, 2048.0)
_GYRO_LSB_PER_DPS = (131.072, 65.536, 32.768, 16.384)


@dataclass(frozen=True, slots=True)
class EncoderConfig:
    """The device settings that shape the word stream (register names of note §3).

    Attributes:
        roi: APS ROI 0 ``(START_COLUMN_0, START_ROW_0, END_COLUMN_0, END_ROW_0)``, inclusive.
        accel_full_scale: IMU ACCEL_FULL_SCALE code 0-3 (±2/4/8/16 g).
        gyro_full_scale: IMU GYRO_FULL_SCALE code 0-3 (±250/500/1000/2000 °/s).
        run_accelerometer: IMU RUN_ACCELEROMETER (its bytes are in the sample).
        run_gyroscope: IMU RUN_GYROSCOPE.
        run_temperature: IMU RUN_TEMPERATURE.
        detect_rising_edges: EXTINPUT DETECT_RISING_EDGES (special 3).
        detect_falling_edges: EXTINPUT DETECT_FALLING_EDGES (special 2).
        detect_pulses: EXTINPUT DETECT_PULSES (special 4).
        pulse_active_high: EXTINPUT DETECT_PULSE_POLARITY (1 = active-high).
        pulse_min_length_us: EXTINPUT DETECT_PULSE_LENGTH in µs.
        drop_dvs_on_transfer_stall: MUX DROP_DVS_ON_TRANSFER_STALL.
        drop_extinput_on_transfer_stall: MUX DROP_EXTINPUT_ON_TRANSFER_STALL.
        bandwidth_bytes_per_s: USB throughput cap; DVS events beyond it are dropped (when
            DROP_DVS is set) per 1 ms bin. ``None`` = unlimited.
        reset_level_adc: Mean raw reset-read ADC value (before the host's ×2; note §9.2).
        reset_noise_adc: Standard deviation of the reset level across pixels and frames.
        dvs_invert_xy: DVS ORIENTATION_INFO bit 2: the chip's axes are swapped, so Y words
            carry the image column and X words the image row (note §3.2, §8).
        aps_invert_xy: APS ORIENTATION_INFO bit 2: readout columns are image rows.
        aps_flip_x: APS ORIENTATION_INFO bit 1: readout columns run right to left.
        aps_flip_y: APS ORIENTATION_INFO bit 0: samples within a column run bottom to top.
    """

    roi: tuple[int, int, int, int] = (0, 0, DAVIS240C_COLUMNS - 1, DAVIS240C_ROWS - 1)
    accel_full_scale: int = 1
    gyro_full_scale: int = 1
    run_accelerometer: bool = True
    run_gyroscope: bool = True
    run_temperature: bool = True
    detect_rising_edges: bool = False
    detect_falling_edges: bool = False
    detect_pulses: bool = True
    pulse_active_high: bool = True
    pulse_min_length_us: int = 10
    drop_dvs_on_transfer_stall: bool = True
    drop_extinput_on_transfer_stall: bool = True
    bandwidth_bytes_per_s: float | None = None
    reset_level_adc: float = 600.0
    reset_noise_adc: float = 6.0
    dvs_invert_xy: bool = False
    aps_invert_xy: bool = False
    aps_flip_x: bool = False
    aps_flip_y: bool = False

    def __post_init__(self) -> None:
        c0, r0, c1, r1 = self.roi
        if not (0 <= c0 <= c1 < DAVIS240C_COLUMNS and 0 <= r0 <= r1 < DAVIS240C_ROWS):
            msg = f"EncoderConfig.roi {self.roi} is not inside 240x180 with start <= end"
            raise ValidationError(msg)
        if not (0 <= self.accel_full_scale <= 3 and 0 <= self.gyro_full_scale <= 3):
            msg = "EncoderConfig accel/gyro full-scale codes must be 0..3"
            raise ValidationError(msg)
        # The saturation rule (§9.2): a reset below 384 after the host's ×2 reads as white.
        if not 192.0 + 4 * self.reset_noise_adc < self.reset_level_adc <= 1023.0:
            msg = (
                f"EncoderConfig.reset_level_adc {self.reset_level_adc} must keep the reset read "
                "above 192 raw (384 after the host's x2) and within 10 bits"
            )
            raise ValidationError(msg)


@dataclass(slots=True, order=True)
class _Unit:
    """Words the mux sends together; the first one is timestamped when ``stamped``."""

    t_us: int
    pri: int
    seq: int
    words: U16 = field(compare=False)
    stamped: bool = field(default=True, compare=False)
    #: Host time after this unit when it is not stamped (wraps): the new epoch start.
    host_after_us: int = field(default=0, compare=False)
    #: The 0xFFFF case: stamped as ``t_us - 1`` because it was latched before the wrap.
    latched: bool = field(default=False, compare=False)


def _unit_time(unit: _Unit) -> int:
    return unit.t_us


def _unit_key(unit: _Unit) -> tuple[int, int, int]:
    return (unit.t_us, unit.pri, unit.seq)


def _stamp_of(unit: _Unit) -> int:
    """The time a unit's timestamp word carries (or, for a wrap, the time the host holds)."""
    if not unit.stamped:
        return unit.host_after_us
    return unit.t_us - 1 if unit.latched else unit.t_us


def _check_window_events(ev: npt.NDArray[np.void], t0_us: int, t1_us: int) -> None:
    """The encoder relies on sorted, in-window, on-sensor events (DavisActivity's contract)."""
    t = ev["t"]
    if t[0] < t0_us or t[-1] >= t1_us or np.any(t[1:] < t[:-1]):
        msg = (
            f"DavisActivity events must be sorted by t and inside [{t0_us}, {t1_us}); got "
            f"t from {int(t.min())} to {int(t.max())}"
        )
        raise ValidationError(msg)
    if int(ev["x"].max()) >= DAVIS240C_COLUMNS or int(ev["y"].max()) >= DAVIS240C_ROWS:
        msg = "DavisActivity events must have x < 240 and y < 180 (DAVIS240C pixels)"
        raise ValidationError(msg)


def _special(code: int) -> int:
    return _CODE_SPECIAL | code


class DavisWordEncoder:
    """Stateful encoder of activity windows into EP 0x82 bytes (see the module doc).

    Args:
        config: Device settings; change them later with :meth:`configure`.
        latency_us: Device µs by which output lags the newest window (covers an APS frame's
            reset read and exposure, which precede the window its exposure ends in).
        wrap_race: Model the one-cycle race of note §7.1: the first stamped word due exactly at
            a rollover is latched before the WRAP goes out and is stamped 0xFFFF (or not at all
            when 0xFFFF was the last timestamp sent).
        seed: Seed of the APS reset-level noise.
    """

    def __init__(
        self,
        config: EncoderConfig | None = None,
        *,
        latency_us: int = 50_000,
        wrap_race: bool = False,
        seed: int = 0,
    ) -> None:
        if latency_us < 0:
            msg = f"latency_us must be >= 0, got {latency_us}"
            raise ValidationError(msg)
        self._config = config or EncoderConfig()
        self._latency_us = int(latency_us)
        self._wrap_race = bool(wrap_race)
        self._rng = np.random.default_rng(seed)
        self._seq = 0
        # Caller time of internal time 0 (moves on a forced reset; the caller keeps its base).
        self._base_us = 0
        self.dvs_dropped = 0
        """DVS events dropped (output blocked or bandwidth cap, with DROP_DVS set)."""
        self.extinput_dropped = 0
        """External-input events dropped (output blocked, with DROP_EXTINPUT set)."""
        self.forced_resets = 0
        """Timestamp resets forced by a pending-wrap overflow."""
        self._clear_time_state()

    # -- state ---------------------------------------------------------------------------------

    def _clear_time_state(self) -> None:
        self._now_us = 0  # end of the newest window (device µs since the last reset)
        self._emitted_us = 0  # every word before this time has been produced
        self._host_us = 0  # the time the host holds after the words produced so far
        self._next_wrap_us = TIMESTAMP_WRAP_US
        self._pending_wraps = 0
        self._pending_wrap_epoch_us = 0
        self._reset_due = False
        self._units: list[_Unit] = []  # held words, sorted by (time, priority, sequence)
        # Words that came due while the output was stalled, in arrival order; they are sent,
        # stamped with the stall's end, when it clears. Kept apart from ``_units`` so that a
        # long stall costs each step only its new words (not a re-sort of all that wait).
        self._stalled: list[_Unit] = []
        # Held DVS events: chunks in time order, each sorted by ``t`` (internal µs).
        self._events: list[npt.NDArray[np.void]] = []
        self._pulse_start_us: int | None = None
        self._aps_free_us = 0

    @property
    def config(self) -> EncoderConfig:
        """The current settings."""
        return self._config

    def configure(self, config: EncoderConfig) -> None:
        """Apply new settings to everything encoded from now on."""
        self._config = config

    @property
    def now_us(self) -> int:
        """End of the newest window, device µs since the last timestamp reset."""
        return self._now_us

    def _next_seq(self) -> int:
        self._seq += 1
        return self._seq

    # -- public encoding -------------------------------------------------------------------------

    def encode(self, activity: DavisActivity, *, output_blocked: bool = False) -> bytes:
        """Add a window and return the bytes older than ``activity.t1_us - latency_us``.

        Args:
            activity: The next window (``t0_us`` at or after the previous window's end).
            output_blocked: The USB output was stalled during the time being emitted: DVS and
                ext-input words are dropped (or held when their DROP flag is clear), APS and
                IMU words wait, and wraps accumulate in the 12-bit pending counter.

        Raises:
            ValidationError: the window starts before the previous one ended.
        """
        t0 = activity.t0_us - self._base_us
        t1 = activity.t1_us - self._base_us
        if t0 < self._now_us:
            msg = (
                f"DavisActivity window [{activity.t0_us}, {activity.t1_us}) starts before the "
                f"previous window ended ({self._now_us + self._base_us} µs); windows must be "
                "consecutive"
            )
            raise ValidationError(msg)
        self._add_ext(activity, t0)
        self._add_imu(activity)
        for exposure in activity.exposures:
            self._add_frame(exposure)
        if activity.events.size:
            ev = activity.events
            _check_window_events(ev, activity.t0_us, activity.t1_us)
            if self._base_us or self._config.dvs_invert_xy:
                ev = ev.copy()
                ev["t"] -= self._base_us
                if self._config.dvs_invert_xy:
                    ev["x"], ev["y"] = activity.events["y"], activity.events["x"]
            self._events.append(ev)
        self._now_us = max(self._now_us, t1)
        horizon = max(self._emitted_us, self._now_us - self._latency_us)
        return self._emit_until(horizon, blocked=output_blocked)

    def advance_idle(self, t1_us: int) -> None:
        """Let device time run to ``t1_us`` with the multiplexer off (MUX RUN = 0).

        Everything held is thrown away (note §3.1: the input FIFOs are drained) and no wraps
        are sent; the counter still runs, so the host resynchronises only at the next
        timestamp reset.
        """
        t1 = t1_us - self._base_us
        self._units.clear()
        self._stalled.clear()
        self._events = []
        self._now_us = max(self._now_us, t1)
        self._emitted_us = max(self._emitted_us, self._now_us)
        while self._next_wrap_us <= self._emitted_us:
            self._next_wrap_us += TIMESTAMP_WRAP_US
        self._pending_wraps = 0

    def flush(self) -> bytes:
        """Emit everything held, including APS frame tails that end after the newest window."""
        last = max([u.t_us for u in self._units], default=self._now_us)
        if self._events:
            last = max(last, int(self._events[-1]["t"][-1]))
        return self._emit_until(max(last + 1, self._now_us, self._emitted_us), blocked=False)

    def reset_timestamps(self) -> bytes:
        """A timestamp reset at the newest window's end (MUX TIMESTAMP_RESET, note §3.1).

        Returns the words due before it, then the reset word (special 1, sent alone and never
        timestamped). Parts of APS frames that would come later are discarded (the host drops
        that frame anyway, note §7.2). Device time restarts at 0 for the next window.
        """
        out = self._emit_until(max(self._emitted_us, self._now_us), blocked=False)
        self._clear_time_state()
        self._base_us = 0
        return out + np.array([_special(_SP_TS_RESET)], "<u2").tobytes()

    # -- producers -------------------------------------------------------------------------------

    def _add_unit(self, t_us: int, pri: int, words: U16) -> None:
        bisect.insort(self._units, _Unit(int(t_us), pri, self._next_seq(), words), key=_unit_key)

    def _add_ext(self, activity: DavisActivity, t0: int) -> None:
        cfg = self._config
        edges = activity.ext_input
        for t_caller, kind in zip(edges["t"].tolist(), edges["edge"].tolist(), strict=True):
            t = int(t_caller) - self._base_us
            t = max(t, t0)
            codes: list[int] = []
            if kind == ExtInputEdge.PULSE:
                # The source reports a detected pulse itself.
                if cfg.detect_pulses:
                    codes.append(_SP_EXT_PULSE)
            else:
                rising = kind == ExtInputEdge.RISING
                if rising and cfg.detect_rising_edges:
                    codes.append(_SP_EXT_RISING)
                if not rising and cfg.detect_falling_edges:
                    codes.append(_SP_EXT_FALLING)
                # Pulse detector (§11.2): an active phase at least DETECT_PULSE_LENGTH long is
                # reported when it ends (the note does not say when; see the report).
                starts_pulse = rising == cfg.pulse_active_high
                if starts_pulse:
                    self._pulse_start_us = t
                elif self._pulse_start_us is not None:
                    length = t - self._pulse_start_us
                    if cfg.detect_pulses and length >= cfg.pulse_min_length_us:
                        codes.append(_SP_EXT_PULSE)
                    self._pulse_start_us = None
            for code in codes:
                self._add_unit(t, _PRI_EXT, np.array([_special(code)], np.uint16))

    def _add_imu(self, activity: DavisActivity) -> None:
        imu = activity.imu
        n = imu.shape[0]
        cfg = self._config
        if n == 0 or not (cfg.run_accelerometer or cfg.run_gyroscope or cfg.run_temperature):
            return
        cols: list[npt.NDArray[np.int64]] = []
        if cfg.run_accelerometer:
            lsb = _ACCEL_LSB_PER_G[cfg.accel_full_scale]
            cols.append(np.clip(np.rint(imu["accel_g"] * lsb), -32768, 32767).astype(np.int64))
        if cfg.run_temperature:
            # libcaer: temperature = raw/340 + 35 °C (note §10).
            raw_t = np.clip(np.rint((imu["temp_c"] - 35.0) * 340.0), -32768, 32767)
            cols.append(raw_t.astype(np.int64)[:, None])
        if cfg.run_gyroscope:
            lsb = _GYRO_LSB_PER_DPS[cfg.gyro_full_scale]
            cols.append(np.clip(np.rint(imu["gyro_dps"] * lsb), -32768, 32767).astype(np.int64))
        values = np.concatenate(cols, axis=1).astype(np.int16)  # (n, k) in register order
        data = values.astype(">i2").view(np.uint8).reshape(n, -1).astype(np.uint16)
        info = (
            (int(cfg.run_accelerometer) << 7)
            | (int(cfg.run_gyroscope) << 6)
            | (int(cfg.run_temperature) << 5)
            | (cfg.accel_full_scale << 2)
            | cfg.gyro_full_scale
        )
        words = np.empty((n, data.shape[1] + 3), np.uint16)
        words[:, 0] = _special(_SP_IMU_START6)
        words[:, 1] = _CODE_MISC8 | (_M8_IMU_INFO << 8) | info
        words[:, 2:-1] = _CODE_MISC8 | (_M8_IMU_DATA << 8) | data
        words[:, -1] = _special(_SP_IMU_END)
        # The host stamps an IMU sample at its END word (§10), so start and end share the time.
        for t_caller, w in zip(imu["t"].tolist(), words, strict=True):
            self._add_unit(int(t_caller) - self._base_us, _PRI_IMU, w)

    def _add_frame(self, exposure: ApsExposure) -> None:
        cfg = self._config
        c0, r0, c1, r1 = cfg.roi
        ncols, nrows = c1 - c0 + 1, r1 - r0 + 1
        if cfg.aps_invert_xy:
            ncols, nrows = nrows, ncols
        col_us = (_COL_SETTLE_CYCLES + _ROW_CYCLES * nrows) / _ADC_MHZ
        read_us = math.ceil(ncols * col_us)
        start = exposure.start_us - self._base_us
        end = exposure.end_us - self._base_us
        earliest = max(self._emitted_us, self._aps_free_us)
        frame_start = start - read_us - 1
        shift = 0
        if frame_start < earliest:
            # The reset read should have begun before words were already sent: start late.
            shift = max(0, earliest + read_us + 1 - start)
            frame_start = earliest
            if shift:
                _log.warning(
                    "APS exposure at %d µs (%d µs long) cannot have its reset read before it "
                    "(previous frame still reading out, or longer than the %d µs encoder "
                    "latency); its frame is sent %d µs late",
                    exposure.start_us,
                    exposure.end_us - exposure.start_us,
                    self._latency_us,
                    shift,
                )
        start += shift
        end += shift

        exposure_cycles = (exposure.end_us - exposure.start_us) * _ADC_MHZ
        head = [_special(_SP_FRAME_START_GS)]
        head += [
            _CODE_MISC10 | (_M10_EXPOSURE << 10) | ((exposure_cycles >> s) & 0x3FF)
            for s in (0, 10, 20)
        ]
        for value in (c0, r0, c1, r1):
            head.append(_CODE_MISC8 | (_M8_ROI_HI << 8) | ((value >> 8) & 0xFF))
            head.append(_CODE_MISC8 | (_M8_ROI_LO << 8) | (value & 0xFF))
        self._add_unit(frame_start, _PRI_APS, np.array(head, np.uint16))

        # Raw ADC reads (§9.2): the host doubles them, then CDS = reset - signal = ``cds``.
        roi_image = np.asarray(exposure.cds, np.float64)[r0 : r1 + 1, c0 : c1 + 1]
        cds = self._readout_order(roi_image)
        reset = np.rint(self._rng.normal(cfg.reset_level_adc, cfg.reset_noise_adc, cds.shape))
        reset = np.clip(reset, 193, 1023)
        signal = np.clip(reset - np.rint(np.clip(cds, 0.0, 1023.0) / 2.0), 1, 1023)
        # A white (saturated) pixel: the signal sample hits 0 (§9.2 saturation rule).
        signal[cds >= 1022.5] = 0
        reset_words = self._columns(_SP_RESET_COL_START, reset)
        signal_words = self._columns(_SP_SIGNAL_COL_START, signal)
        col_end = np.array([_special(_SP_COL_END)], np.uint16)
        for k in range(ncols):
            self._add_unit(frame_start + 1 + math.floor(k * col_us), _PRI_APS, reset_words[k])
            self._add_unit(frame_start + 1 + math.floor((k + 1) * col_us), _PRI_APS, col_end)
        self._add_unit(
            max(start, frame_start + read_us + 1),
            _PRI_APS,
            np.array([_special(_SP_EXPOSURE_START)], np.uint16),
        )
        end = max(end, start)
        self._add_unit(end, _PRI_APS, np.array([_special(_SP_EXPOSURE_END)], np.uint16))
        for k in range(ncols):
            self._add_unit(end + 1 + math.floor(k * col_us), _PRI_APS, signal_words[k])
            self._add_unit(end + 1 + math.floor((k + 1) * col_us), _PRI_APS, col_end)
        frame_end = end + read_us + 2
        self._add_unit(frame_end, _PRI_APS, np.array([_special(_SP_FRAME_END)], np.uint16))
        self._aps_free_us = frame_end + 1

    def _readout_order(self, image: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """An ROI image (rows, columns) as the logic reads it out: (sample, readout column).

        The inverse of the host's placement (note §9.2: x = flipX ? n-1-column : column, y
        likewise, swapped when invertXY).
        """
        cfg = self._config
        by_column = image if cfg.aps_invert_xy else image.T  # (readout column, sample)
        if cfg.aps_flip_x:
            by_column = by_column[::-1, :]
        if cfg.aps_flip_y:
            by_column = by_column[:, ::-1]
        out: npt.NDArray[np.float64] = np.ascontiguousarray(by_column.T)
        return out

    @staticmethod
    def _columns(special: int, values: npt.NDArray[np.float64]) -> U16:
        """Per ROI column: the column-start special, then one ADC word per row, top first."""
        nrows, ncols = values.shape
        words = np.empty((ncols, nrows + 1), np.uint16)
        words[:, 0] = _special(special)
        words[:, 1:] = _CODE_ADC | values.T.astype(np.uint16)
        return words

    # -- emission --------------------------------------------------------------------------------

    def _emit_until(self, horizon: int, *, blocked: bool) -> bytes:
        """Produce the words with times before ``horizon`` (see :meth:`encode`)."""
        if horizon < self._emitted_us:
            return b""
        cfg = self._config
        # Units and events that are due.
        split = bisect.bisect_left(self._units, horizon, key=_unit_time)
        due, self._units = self._units[:split], self._units[split:]
        dvs = self._take_events_before(horizon)
        n_wraps = 0
        while self._next_wrap_us < horizon:
            n_wraps += 1
            self._next_wrap_us += TIMESTAMP_WRAP_US

        if blocked:
            self._block(due, dvs, n_wraps, horizon)
            return b""

        units: list[_Unit] = []
        if self._reset_due:
            # The forced reset is sent alone; host and device restart at 0 (§7.1).
            self._reset_due = False
            out_head = np.array([_special(_SP_TS_RESET)], np.uint16)
        else:
            out_head = np.empty(0, np.uint16)
        if self._pending_wraps:
            units.append(
                _Unit(
                    self._emitted_us,
                    _PRI_WRAP,
                    self._next_seq(),
                    np.array([_CODE_WRAP | self._pending_wraps], np.uint16),
                    stamped=False,
                    host_after_us=self._pending_wrap_epoch_us,
                )
            )
            self._pending_wraps = 0
        first_wrap = self._next_wrap_us - n_wraps * TIMESTAMP_WRAP_US
        for k in range(n_wraps):
            t_wrap = first_wrap + k * TIMESTAMP_WRAP_US
            units.append(
                _Unit(
                    t_wrap,
                    _PRI_WRAP,
                    self._next_seq(),
                    np.array([_CODE_WRAP | 1], np.uint16),
                    stamped=False,
                    host_after_us=t_wrap,
                )
            )
        if self._stalled:
            for u in self._stalled:
                u.t_us = self._emitted_us  # the stall ended here; stamped when sent
            units.extend(self._stalled)
            self._stalled = []
        units.extend(due)
        if cfg.bandwidth_bytes_per_s is not None and dvs.size:
            dvs = self._apply_bandwidth_cap(dvs, units, horizon, cfg.bandwidth_bytes_per_s)
        if self._wrap_race and n_wraps:
            dvs = self._latch_at_wraps(units, dvs)
        units.sort(key=_unit_key)
        words = self._assemble(units, dvs)
        self._emitted_us = horizon
        if out_head.size:
            words = np.concatenate([out_head, words])
        return words.astype("<u2").tobytes()

    def _take_events_before(self, horizon: int) -> npt.NDArray[np.void]:
        """Remove and return the held DVS events before ``horizon`` (chunks are sorted)."""
        taken: list[npt.NDArray[np.void]] = []
        while self._events:
            chunk = self._events[0]
            if chunk["t"][-1] < horizon:
                taken.append(self._events.pop(0))
                continue
            cut = int(np.searchsorted(chunk["t"], horizon, side="left"))
            if cut:
                taken.append(chunk[:cut])
                self._events[0] = chunk[cut:]
            break
        if not taken:
            return np.empty(0, EVENT_DTYPE)
        return taken[0] if len(taken) == 1 else np.concatenate(taken)

    def _block(
        self, due: list[_Unit], dvs: npt.NDArray[np.void], n_wraps: int, horizon: int
    ) -> None:
        """Output stalled over ``[emitted, horizon)`` (note §7.1, "When USB is stalled")."""
        cfg = self._config
        if dvs.size:
            if cfg.drop_dvs_on_transfer_stall:
                self.dvs_dropped += int(dvs.size)
            else:
                held = dvs.copy()
                held["t"] = horizon
                self._events.insert(0, held)
        for u in due:
            if u.pri == _PRI_EXT and cfg.drop_extinput_on_transfer_stall:
                self.extinput_dropped += 1
                continue
            self._stalled.append(u)  # APS/IMU wait (WAIT_ON_TRANSFER_STALL)
        if n_wraps:
            self._pending_wraps += n_wraps
            self._pending_wrap_epoch_us = self._next_wrap_us - TIMESTAMP_WRAP_US
        self._emitted_us = horizon
        if self._pending_wraps > _MAX_PENDING_WRAPS:
            # 12-bit pending-wrap counter overflow: the device resets the timestamp (§7.1).
            overflow_at = self._pending_wrap_epoch_us
            self.forced_resets += 1
            _log.warning(
                "DAVIS mock: %d timestamp wraps pending with the output stalled; forcing a "
                "timestamp reset (note §7.1)",
                self._pending_wraps,
            )
            base = self._base_us + overflow_at
            now = self._now_us - overflow_at
            self._clear_time_state()
            self._base_us = base
            self._now_us = self._emitted_us = max(0, now)
            self._next_wrap_us = TIMESTAMP_WRAP_US
            while self._next_wrap_us <= self._emitted_us:
                self._pending_wraps += 1
                self._pending_wrap_epoch_us = self._next_wrap_us
                self._next_wrap_us += TIMESTAMP_WRAP_US
            self._reset_due = True

    def _apply_bandwidth_cap(
        self,
        dvs: npt.NDArray[np.void],
        units: list[_Unit],
        horizon: int,
        bytes_per_s: float,
    ) -> npt.NDArray[np.void]:
        """Drop DVS events beyond the USB throughput, per 1 ms bin (DROP_DVS semantics)."""
        if not self._config.drop_dvs_on_transfer_stall:
            return dvs
        bin_us = 1000
        t0 = self._emitted_us
        nbins = max(1, -(-(horizon - t0) // bin_us))
        budget = np.full(nbins, bytes_per_s * bin_us * 1e-6)
        for u in units:
            b = min(max((u.t_us - t0) // bin_us, 0), nbins - 1)
            budget[b] -= 2 * (u.words.size + 1)
        order = np.lexsort((dvs["y"], dvs["t"]))
        dvs = dvs[order]
        t, y = dvs["t"], dvs["y"]
        first = np.ones(dvs.size, bool)
        first[1:] = (t[1:] != t[:-1]) | (y[1:] != y[:-1])
        cost = 2 + 4 * first.astype(np.int64)  # X word, plus Y and timestamp for a new row
        b = np.clip((t - t0) // bin_us, 0, nbins - 1)
        csum = np.cumsum(cost)
        bin_first = np.searchsorted(b, np.arange(nbins), side="left")
        before = np.where(bin_first > 0, csum[np.maximum(bin_first - 1, 0)], 0)
        in_bin = csum - before[b]
        keep = in_bin <= budget[b]
        dropped = int(dvs.size - keep.sum())
        if dropped:
            self.dvs_dropped += dropped
        kept: npt.NDArray[np.void] = dvs[keep]
        return kept

    def _latch_at_wraps(
        self, units: list[_Unit], dvs: npt.NDArray[np.void]
    ) -> npt.NDArray[np.void]:
        """The 0xFFFF case: the first stamped word due at a rollover goes out before the wrap."""
        wraps = [u for u in units if u.pri == _PRI_WRAP and u.host_after_us == u.t_us]
        for w in wraps:
            candidates = [u for u in units if u.t_us == w.t_us and u.pri > _PRI_WRAP]
            if candidates:
                u = min(candidates)
                u.pri, u.latched = _PRI_LATCHED, True
                continue
            if dvs.size == 0:
                continue
            at = np.flatnonzero(dvs["t"] == w.t_us)
            if at.size == 0:
                continue
            row = dvs["y"][at[0]]
            take = at[dvs["y"][at] == row]
            group = dvs[take]
            words = np.empty(group.size + 1, np.uint16)
            words[0] = _CODE_Y | int(row)
            words[1:] = np.where(group["p"] != 0, _CODE_X_ON, _CODE_X_OFF) | group["x"]
            units.append(_Unit(w.t_us, _PRI_LATCHED, self._next_seq(), words, latched=True))
            dvs = np.delete(dvs, take)
        out: npt.NDArray[np.void] = dvs
        return out

    def _assemble(self, units: list[_Unit], dvs: npt.NDArray[np.void]) -> U16:
        """Merge sorted units with DVS row groups and insert the timestamp words."""
        # DVS row groups: same µs and row, in a stable order (§8, burst-mode readout).
        n = dvs.size
        if n:
            order = np.lexsort((dvs["y"], dvs["t"]))
            t_e = dvs["t"][order]
            y_e = dvs["y"][order].astype(np.uint16)
            x_e = dvs["x"][order].astype(np.uint16)
            p_e = dvs["p"][order]
            brk = np.flatnonzero((t_e[1:] != t_e[:-1]) | (y_e[1:] != y_e[:-1])) + 1
            gstart = np.concatenate([[0], brk]).astype(np.int64)
            gcount = np.diff(np.concatenate([gstart, [n]]))
            gt = t_e[gstart]
        else:
            gstart = gcount = gt = np.empty(0, np.int64)
        n_groups, n_units = gt.size, len(units)

        ut = np.array([u.t_us for u in units], np.int64)
        # Units go before DVS groups of the same µs.
        pos = np.searchsorted(gt, ut, side="left")
        unit_idx = pos + np.arange(n_units)
        group_idx = np.arange(n_groups) + np.searchsorted(pos, np.arange(n_groups), side="right")
        total = n_groups + n_units

        # The time the host holds after each merged element, and whether it is stamped.
        host_after = np.empty(total, np.int64)
        stamp = np.empty(total, np.int64)
        stamped = np.ones(total, bool)
        host_after[group_idx] = gt
        stamp[group_idx] = gt
        u_stamp = np.array(
            [
                (u.t_us - 1 if u.latched else u.t_us) if u.stamped else u.host_after_us
                for u in units
            ],
            np.int64,
        )
        stamp[unit_idx] = u_stamp
        host_after[unit_idx] = u_stamp
        stamped[unit_idx] = np.array([u.stamped for u in units], bool)
        prev = np.empty(total, np.int64)
        if total:
            prev[0] = self._host_us
            prev[1:] = host_after[:-1]
            self._host_us = int(host_after[-1])
        # §7.1: a timestamp word only when the host's time would be wrong without it. After a
        # wrap or a reset the host holds the epoch start, so a zero timestamp is never sent.
        need = stamped & (stamp != prev)

        lengths = np.empty(total, np.int64)
        lengths[group_idx] = need[group_idx] + 1 + gcount
        unit_len = np.array([u.words.size for u in units], np.int64)
        lengths[unit_idx] = need[unit_idx] + unit_len
        offsets = np.zeros(total + 1, np.int64)
        np.cumsum(lengths, out=offsets[1:])
        out = np.empty(int(offsets[-1]), np.uint16)

        if n_groups:
            g_off = offsets[group_idx]
            g_need = need[group_idx]
            ts_at = g_off[g_need]
            out[ts_at] = _TS_FLAG | (gt[g_need] & 0x7FFF)
            y_at = g_off + g_need
            out[y_at] = _CODE_Y | y_e[gstart]
            x_at = np.repeat(y_at + 1 - gstart, gcount) + np.arange(n)
            out[x_at] = np.where(p_e != 0, _CODE_X_ON, _CODE_X_OFF).astype(np.uint16) | x_e
        u_off = offsets[unit_idx].tolist()
        u_need = need[unit_idx].tolist()
        for u, o, nd, s in zip(units, u_off, u_need, u_stamp.tolist(), strict=True):
            if nd:
                out[o] = _TS_FLAG | (s & 0x7FFF)
            out[o + nd : o + nd + u.words.size] = u.words
        return out


def encode_stream(
    windows: Iterable[DavisActivity],
    *,
    config: EncoderConfig | None = None,
    wrap_race: bool = False,
    seed: int = 0,
) -> bytes:
    """Encode consecutive windows into one complete EP 0x82 byte stream (flushed at the end)."""
    encoder = DavisWordEncoder(config, wrap_race=wrap_race, seed=seed)
    parts = [encoder.encode(w) for w in windows]
    parts.append(encoder.flush())
    return b"".join(parts)
