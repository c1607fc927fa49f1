"""Decoder of the DAVIS240C bulk stream (EP 0x82, logic 18): 16-bit LE words -> data.

The word format is in ``docs/davis240c-usb.md`` §6-§11 (shared docs). :class:`DavisDecoder`
keeps all parser state between USB packets (wrap epoch, last timestamp, row address, frames and
IMU samples split over packets, an odd trailing byte), so an endless stream is decoded packet by
packet in bounded memory.

The polarity-dominated path is vectorised: words are classified through a 16-entry table on the
top nibble; timestamps (with wrap epochs) and row addresses are forward-filled over the few
"state" words and gathered for the X words. The rare words (SPECIAL, APS ADC, MISC8, MISC10) go
through a small state machine in which whole runs of ADC samples are handled as numpy slices.

Output units: event and special times are int64 µs of the device clock (64-bit, so the 2^31 µs
"big wrap" is transparent), APS pixels are uint16 in 0..1023 (the DAVIS240 ADC samples doubled,
then reset - signal, clamped; ``<< 6`` gives libcaer's 16-bit value), IMU acceleration in g,
angular rate in °/s, temperature in °C (MPU-6050: raw / 340 + 35).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, fields
from enum import IntEnum
from typing import Any

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.events import EVENT_DTYPE, empty_events

__all__ = [
    "DAVIS240C_APS_COLUMNS",
    "DAVIS240C_APS_ROWS",
    "DAVIS240C_DVS_COLUMNS",
    "DAVIS240C_DVS_ROWS",
    "IMU_SAMPLE_DTYPE",
    "SPECIAL_DTYPE",
    "ApsFrame",
    "DavisDecoder",
    "DavisPacket",
    "DecodeStats",
    "DeviceSpecial",
    "DroppedWords",
    "SensorOrientation",
    "SpecialType",
    "decode_words",
    "scan_dropped",
]

_log = logging.getLogger(__name__)

DAVIS240C_DVS_COLUMNS = 240
DAVIS240C_DVS_ROWS = 180
DAVIS240C_APS_COLUMNS = 240
DAVIS240C_APS_ROWS = 180

#: One IMU sample (same layout as the simulator hand-off): ``t`` µs (the IMU-end word),
#: ``accel_g`` (3,) in g, ``gyro_dps`` (3,) in °/s, ``temp_c`` in °C. Axes: camera X right,
#: Y up, Z along the optical axis (libcaer ``imu6.h``).
IMU_SAMPLE_DTYPE = np.dtype(
    [("t", "<i8"), ("accel_g", "<f8", (3,)), ("gyro_dps", "<f8", (3,)), ("temp_c", "<f8")]
)

#: One special event: ``t`` µs, ``type`` a :class:`SpecialType` (libcaer numbering), ``data``.
SPECIAL_DTYPE = np.dtype([("t", "<i8"), ("type", "u1"), ("data", "<u4")])


class SpecialType(IntEnum):
    """Exported special-event types, numbered as libcaer ``special.h`` (note §14.1)."""

    TIMESTAMP_WRAP = 0  # only the 2^31 µs big wrap is exported
    TIMESTAMP_RESET = 1
    EXTERNAL_INPUT_RISING_EDGE = 2
    EXTERNAL_INPUT_FALLING_EDGE = 3
    EXTERNAL_INPUT_PULSE = 4
    EXTERNAL_GENERATOR_RISING_EDGE = 12
    EXTERNAL_GENERATOR_FALLING_EDGE = 13
    APS_FRAME_START = 14
    APS_FRAME_END = 15
    APS_EXPOSURE_START = 16
    APS_EXPOSURE_END = 17


class DeviceSpecial(IntEnum):
    """Data field of a SPECIAL (code 0) word as the device sends it (note §6.3)."""

    RESERVED = 0
    TIMESTAMP_RESET = 1
    EXT_INPUT_FALLING = 2
    EXT_INPUT_RISING = 3
    EXT_INPUT_PULSE = 4
    IMU_START6 = 5
    IMU_START9 = 6
    IMU_END = 7
    APS_FRAME_START_GS = 8
    APS_FRAME_START_RS = 9
    APS_FRAME_END = 10
    APS_RESET_COLUMN_START = 11
    APS_SIGNAL_COLUMN_START = 12
    APS_COLUMN_END = 13
    APS_EXPOSURE_START = 14
    APS_EXPOSURE_END = 15
    EXT_GENERATOR_FALLING = 16
    EXT_GENERATOR_RISING = 17


_SPECIAL_EXPORT = {
    DeviceSpecial.EXT_INPUT_FALLING: SpecialType.EXTERNAL_INPUT_FALLING_EDGE,
    DeviceSpecial.EXT_INPUT_RISING: SpecialType.EXTERNAL_INPUT_RISING_EDGE,
    DeviceSpecial.EXT_INPUT_PULSE: SpecialType.EXTERNAL_INPUT_PULSE,
    DeviceSpecial.EXT_GENERATOR_FALLING: SpecialType.EXTERNAL_GENERATOR_FALLING_EDGE,
    DeviceSpecial.EXT_GENERATOR_RISING: SpecialType.EXTERNAL_GENERATOR_RISING_EDGE,
}

_NO_INDEX: npt.NDArray[np.intp] = np.empty(0, np.intp)
_IMU_WORDS = 17  # IMU start, info, 14 data bytes, IMU end (all sensors on)
_WRAP_US = 0x8000
_BIG_WRAP_US = 1 << 31
_ACCEL_LSB_PER_G = (16384.0, 8192.0, 4096.0, 2048.0)
_GYRO_LSB_PER_DPS = tuple(65536.0 / (500.0 * 2**fs) for fs in range(4))
_READ_RESET, _READ_SIGNAL = 0, 1


@dataclass(frozen=True, slots=True)
class DecodeStats:
    """What a :class:`DavisDecoder` has seen so far (counters since construction).

    Attributes:
        bytes_in: Bytes given to :meth:`DavisDecoder.decode`.
        words: Whole 16-bit words parsed.
        events: Polarity events produced.
        frames: APS frames produced.
        frames_dropped: Frames ended with a wrong column count (reset or signal read).
        imu_samples: IMU samples produced.
        imu_samples_dropped: IMU samples ended incomplete.
        specials: Special events produced.
        timestamp_resets: TS-reset words.
        big_wraps: 2^31 µs epoch crossings.
        non_monotonic_timestamps: Timestamp/wrap words not later than the previous time.
        x_without_row: X words before any row address (dropped).
        x_out_of_range: X words with a column >= 240 (dropped).
        y_out_of_range: Y words with a row >= 180 (ignored; the previous row is kept).
        aps_words_skipped: APS words outside a frame, while parsing is suspended, beyond the
            ROI, or malformed.
        aps_row_count_mismatches: Columns whose ADC count differed from the ROI height.
        imu_words_skipped: IMU words outside a sample or while parsing is suspended.
        unknown_words: Reserved/unknown SPECIAL, MISC8 or MISC10 words.
        odd_trailing_bytes: Times a packet ended mid-word (the byte is kept for the next one).
        gaps: Times the caller said data were lost (:meth:`DavisDecoder.decode_gap`).
        gap_bytes: Bytes in those gaps (when the caller said how many).
        gap_wraps: Timestamp wraps found in the lost data and applied (time stays exact).
        gap_timestamp_resets: Timestamp resets found in the lost data and applied.
    """

    bytes_in: int = 0
    words: int = 0
    events: int = 0
    frames: int = 0
    frames_dropped: int = 0
    imu_samples: int = 0
    imu_samples_dropped: int = 0
    specials: int = 0
    timestamp_resets: int = 0
    big_wraps: int = 0
    non_monotonic_timestamps: int = 0
    x_without_row: int = 0
    x_out_of_range: int = 0
    y_out_of_range: int = 0
    aps_words_skipped: int = 0
    aps_row_count_mismatches: int = 0
    imu_words_skipped: int = 0
    unknown_words: int = 0
    odd_trailing_bytes: int = 0
    gaps: int = 0
    gap_bytes: int = 0
    gap_wraps: int = 0
    gap_timestamp_resets: int = 0

    @property
    def skipped_words(self) -> int:
        """Words that produced nothing because they were malformed or out of place."""
        return (
            self.x_without_row
            + self.x_out_of_range
            + self.y_out_of_range
            + self.aps_words_skipped
            + self.imu_words_skipped
            + self.unknown_words
        )

    def as_dict(self) -> dict[str, int]:
        """The counters as a plain dict (plus ``skipped_words``)."""
        out = {f.name: int(getattr(self, f.name)) for f in fields(self)}
        out["skipped_words"] = self.skipped_words
        return out


@dataclass(frozen=True, slots=True, eq=False)
class ApsFrame:
    """One APS frame, as libcaer builds it (note §9.2).

    Attributes:
        t_start_frame_us: Frame-start word time, device µs.
        t_end_frame_us: Frame-end word time.
        t_start_exposure_us: Exposure-start word time.
        t_end_exposure_us: Exposure-end word time.
        exposure_cycles: Exposure register value from the MISC10 words (ADC clock cycles;
            30 per µs on the DAVIS240C).
        position_x: ROI start column.
        position_y: ROI start row.
        pixels: (rows, columns) uint16 in 0..1023, row 0 = top; reset - signal after the
            DAVIS240 doubling, clamped, saturated pixels (reset < 384 or signal == 0) = 1023.
        global_shutter: True for a global-shutter frame start (SPECIAL 8), False for rolling.
    """

    t_start_frame_us: int
    t_end_frame_us: int
    t_start_exposure_us: int
    t_end_exposure_us: int
    exposure_cycles: int
    position_x: int
    position_y: int
    pixels: npt.NDArray[np.uint16] = field(repr=False)
    global_shutter: bool = True

    @property
    def pixels_16bit(self) -> npt.NDArray[np.uint16]:
        """libcaer's normalised 16-bit image (``pixels << 6``), e.g. for a mono16 image."""
        out: npt.NDArray[np.uint16] = np.left_shift(self.pixels, np.uint16(6))
        return out

    @property
    def t_us(self) -> int:
        """libcaer's frame timestamp: exposure start + half the exposure (µs)."""
        return self.t_start_exposure_us + (self.t_end_exposure_us - self.t_start_exposure_us) // 2


@dataclass(frozen=True, slots=True, eq=False)
class DavisPacket:
    """Everything decoded from one chunk of the bulk stream.

    Attributes:
        events: Polarity events, :data:`mocaprig.acquire.events.EVENT_DTYPE`, in stream order.
        frames: APS frames completed in this chunk.
        imu: IMU samples, :data:`IMU_SAMPLE_DTYPE`.
        specials: Special events, :data:`SPECIAL_DTYPE` (TS reset, ext input, APS markers...).
        host_time_ns: Host receive time of the USB read (``time.time_ns()``), 0 for files.
    """

    events: npt.NDArray[np.void] = field(repr=False)
    frames: tuple[ApsFrame, ...] = ()
    imu: npt.NDArray[np.void] = field(
        default_factory=lambda: np.empty(0, IMU_SAMPLE_DTYPE), repr=False
    )
    specials: npt.NDArray[np.void] = field(
        default_factory=lambda: np.empty(0, SPECIAL_DTYPE), repr=False
    )
    host_time_ns: int = 0

    @property
    def empty(self) -> bool:
        """True when the chunk produced nothing."""
        return not (self.events.size or self.frames or self.imu.size or self.specials.size)


@dataclass(frozen=True, slots=True)
class SensorOrientation:
    """How the logic's addresses map to image coordinates (the ORIENTATION_INFO registers).

    Applied as libcaer 3.3 does (``davisCommonInit`` / ``apsUpdateFrame``; note §3.2-§3.4):

    Attributes:
        dvs_invert_xy: DVS ORIENTATION_INFO bit 2: X words carry the row and Y words the
            column; events are swapped back. Bits 1..0 of that register give the chip's
            origin, which the logic already turns into an upper-left one, so (like libcaer)
            they are not applied.
        aps_invert_xy: APS ORIENTATION_INFO bit 2: the readout's "columns" are image rows.
        aps_flip_x: APS ORIENTATION_INFO bit 1: readout columns run right to left.
        aps_flip_y: APS ORIENTATION_INFO bit 0: samples within a column run bottom to top.
        imu_flip: IMU ORIENTATION_INFO bits 2, 1, 0: negate accel and gyro x, y, z.
    """

    dvs_invert_xy: bool = False
    aps_invert_xy: bool = False
    aps_flip_x: bool = False
    aps_flip_y: bool = False
    imu_flip: tuple[bool, bool, bool] = (False, False, False)

    @classmethod
    def from_registers(cls, dvs: int, aps: int, imu: int) -> SensorOrientation:
        """From DVS, APS and IMU ORIENTATION_INFO register values."""
        return cls(
            dvs_invert_xy=bool(dvs & 4),
            aps_invert_xy=bool(aps & 4),
            aps_flip_x=bool(aps & 2),
            aps_flip_y=bool(aps & 1),
            imu_flip=(bool(imu & 4), bool(imu & 2), bool(imu & 1)),
        )


@dataclass(frozen=True, slots=True)
class DroppedWords:
    """What a lost stretch of the word stream did to the parser's time state.

    Built by :func:`scan_dropped` from the bytes that were dropped (a cheap vectorised scan),
    and applied by :meth:`DavisDecoder.decode_gap` so that time stays exact across the gap.

    Attributes:
        n_bytes: Bytes lost.
        timestamp_reset: The lost data held a timestamp-reset word.
        wraps: Wrap count (sum of the WRAP words' data) after the last reset in the lost data.
        last_timestamp: The last 15-bit timestamp after the last wrap/reset in the lost data,
            0 when a wrap or reset came after it, None when the lost data changed neither.
        last_row: The last valid DVS row address in the lost data, or None.
    """

    n_bytes: int = 0
    timestamp_reset: bool = False
    wraps: int = 0
    last_timestamp: int | None = None
    last_row: int | None = None


def scan_dropped(words: npt.NDArray[np.uint16], *, dvs_rows: int = 180) -> DroppedWords:
    """Scan lost 16-bit words (aligned) for resets, wraps, the last timestamp and row.

    ``dvs_rows`` is the range of the Y words' addresses (the chip's native rows).
    """
    w = np.asarray(words, dtype=np.uint16).ravel()
    n_bytes = 2 * int(w.size)
    resets = np.flatnonzero(w == DeviceSpecial.TIMESTAMP_RESET)
    reset = resets.size > 0
    if reset:
        w = w[int(resets[-1]) + 1 :]
    hi = w >> 12
    wrap_at = np.flatnonzero(hi == 7)
    ts_at = np.flatnonzero(w >= 0x8000)
    wraps = int((w[wrap_at] & 0x0FFF).astype(np.int64).sum())
    last_ts: int | None = None
    last_wrap = int(wrap_at[-1]) if wrap_at.size else -1
    if ts_at.size and int(ts_at[-1]) > last_wrap:
        last_ts = int(w[ts_at[-1]] & 0x7FFF)
    elif wrap_at.size or reset:
        last_ts = 0
    y_at = np.flatnonzero((hi == 1) & ((w & 0x0FFF) < dvs_rows))
    last_row = int(w[y_at[-1]] & 0x0FFF) if y_at.size else None
    return DroppedWords(
        n_bytes=n_bytes,
        timestamp_reset=reset,
        wraps=wraps,
        last_timestamp=last_ts,
        last_row=last_row,
    )


class _Frame:
    """A frame being assembled (mutable parser state)."""

    __slots__ = (
        "count_x",
        "count_y",
        "exposure_cycles",
        "exposure_slices",
        "global_shutter",
        "invert_xy",
        "pixels",
        "read",
        "reset",
        "roi",
        "roi_hi",
        "t_end_exposure",
        "t_start_exposure",
        "t_start_frame",
    )

    def __init__(self, t_us: int, *, global_shutter: bool, invert_xy: bool = False) -> None:
        self.invert_xy = invert_xy
        self.t_start_frame = t_us
        self.t_start_exposure = t_us
        self.t_end_exposure = t_us
        self.global_shutter = global_shutter
        self.exposure_cycles = 0
        self.exposure_slices = 0
        self.roi: list[int] = []
        self.roi_hi: int | None = None
        self.count_x = [0, 0]
        self.count_y = [0, 0]
        self.read: int | None = None
        self.reset: npt.NDArray[np.int32] | None = None  # (columns, rows), doubled samples
        self.pixels: npt.NDArray[np.int32] | None = None  # (columns, rows)

    def shape(self) -> tuple[int, int, int, int]:
        """(start column, start row, columns, rows) from the ROI words, or the full frame."""
        if len(self.roi) >= 4:
            sx, sy, ex, ey = self.roi[:4]
            if sx <= ex < DAVIS240C_APS_COLUMNS and sy <= ey < DAVIS240C_APS_ROWS:
                return sx, sy, ex - sx + 1, ey - sy + 1
        return 0, 0, DAVIS240C_APS_COLUMNS, DAVIS240C_APS_ROWS

    def readout(self) -> tuple[int, int]:
        """(columns, samples per column) of the readout: the ROI, swapped if invert_xy."""
        _, _, cols, rows = self.shape()
        return (rows, cols) if self.invert_xy else (cols, rows)

    def buffers(self) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.int32]]:
        if self.reset is None or self.pixels is None:
            shape = self.readout()
            self.reset = np.zeros(shape, np.int32)
            self.pixels = np.zeros(shape, np.int32)
        return self.reset, self.pixels


class DavisDecoder:
    """Stateful decoder of a DAVIS240C (logic 18) word stream, fed packet by packet.

    ``orientation`` applies the ORIENTATION_INFO registers (:class:`SensorOrientation`);
    ``imu_flip`` (kept for callers that only know the IMU register) overrides its IMU part.
    Parsing of APS and IMU words starts at the first frame / IMU start (note §5.3) and is
    suspended again after a timestamp reset or a big wrap.
    """

    def __init__(
        self,
        *,
        imu_flip: tuple[bool, bool, bool] | None = None,
        orientation: SensorOrientation | None = None,
    ) -> None:
        o = orientation if orientation is not None else SensorOrientation()
        if imu_flip is not None:
            o = SensorOrientation(
                dvs_invert_xy=o.dvs_invert_xy,
                aps_invert_xy=o.aps_invert_xy,
                aps_flip_x=o.aps_flip_x,
                aps_flip_y=o.aps_flip_y,
                imu_flip=imu_flip,
            )
        self.orientation = o
        # Address ranges of the X and Y words (the chip's native axes).
        self._x_range = DAVIS240C_DVS_ROWS if o.dvs_invert_xy else DAVIS240C_DVS_COLUMNS
        self._y_range = DAVIS240C_DVS_COLUMNS if o.dvs_invert_xy else DAVIS240C_DVS_ROWS
        self._imu_sign = np.where(np.asarray(o.imu_flip, dtype=bool), -1.0, 1.0)
        self._counts: dict[str, int] = dict.fromkeys((f.name for f in fields(DecodeStats)), 0)
        self._pending = b""
        # Timestamp state: epoch = all wraps since the last reset (µs), ts15 = last timestamp
        # word in this epoch (0 right after a wrap or reset), row = last valid Y (-1 = none).
        self._epoch = 0
        self._ts15 = 0
        self._row = -1
        self._last_time = -1
        # APS / IMU state.
        self._aps_parse = False
        self._frame: _Frame | None = None
        self._imu_parse = False
        self._imu_bytes: list[int] | None = None
        self._imu_slots: tuple[int, ...] = tuple(range(14))
        self._imu_scale = (1, 1)
        # Output of the current call.
        self._specials: list[tuple[int, int, int]] = []
        self._frames: list[ApsFrame] = []
        self._imu_out: list[tuple[int, tuple[float, ...], tuple[float, ...], float]] = []

    @property
    def stats(self) -> DecodeStats:
        """A snapshot of the counters."""
        return DecodeStats(**self._counts)

    @property
    def time_us(self) -> int:
        """The current device time (µs since the last timestamp reset)."""
        return self._epoch + self._ts15

    def decode(self, data: bytes | bytearray | memoryview | npt.NDArray[Any]) -> DavisPacket:
        """Decode the next chunk of the stream (bytes as read from EP 0x82, or a uint16 array).

        An odd trailing byte is kept and prepended to the next chunk. The input is not modified.
        """
        if isinstance(data, np.ndarray) and data.dtype.kind == "u" and data.dtype.itemsize == 2:
            data = data.astype("<u2", copy=False)  # words, whatever their byte order
        if isinstance(data, np.ndarray) and data.dtype == np.dtype("<u2") and not self._pending:
            words = data.ravel()
            self._counts["bytes_in"] += 2 * words.size
        else:
            if isinstance(data, np.ndarray):
                raw = data.tobytes()
            else:
                raw = data if isinstance(data, bytes) else bytes(data)
            self._counts["bytes_in"] += len(raw)
            if self._pending:
                raw = self._pending + raw
                self._pending = b""
            if len(raw) % 2:
                self._pending = raw[-1:]
                raw = raw[:-1]
                self._counts["odd_trailing_bytes"] += 1
            words = np.frombuffer(raw, dtype="<u2")
        return self._decode_words(words)

    def decode_gap(self, lost: DroppedWords | None = None, *, pending: bytes = b"") -> DavisPacket:
        """Say that stream data were lost: the partial frame / IMU sample is dropped and APS/IMU
        parsing waits for the next start word.

        With ``lost`` (:func:`scan_dropped` of the lost words) the timestamp resets, wraps, the
        last timestamp and row address of the lost data are applied, so later times stay exact;
        without it, time stays right only if no wrap was lost. ``pending`` is the odd byte that
        ended the lost data (the first half of the word the next chunk completes). Returns the
        special events the gap produced (a timestamp reset, a big wrap).
        """
        self._counts["gaps"] += 1
        self._pending = bytes(pending[-1:])
        self._specials, self._frames, self._imu_out = [], [], []
        self._suspend_composites()
        if lost is not None:
            c = self._counts
            c["gap_bytes"] += lost.n_bytes
            if lost.timestamp_reset:
                c["gap_timestamp_resets"] += 1
                self._timestamp_reset()
                self._row = -1
            c["gap_wraps"] += lost.wraps
            if lost.wraps:
                new_epoch = self._epoch + lost.wraps * _WRAP_US
                for k in range((self._epoch >> 31) + 1, (new_epoch >> 31) + 1):
                    self._big_wrap(k << 31)
                self._epoch = new_epoch
            if lost.last_timestamp is not None:
                self._ts15 = lost.last_timestamp
            if lost.last_row is not None:
                self._row = lost.last_row
            self._last_time = self._epoch + self._ts15
        specials = np.array(self._specials, dtype=SPECIAL_DTYPE)
        self._specials = []
        self._counts["specials"] += specials.size
        return DavisPacket(events=empty_events(), specials=specials)

    # -- the word stream -----------------------------------------------------------------------

    def _decode_words(self, w: npt.NDArray[np.uint16]) -> DavisPacket:
        self._specials, self._frames, self._imu_out = [], [], []
        n = int(w.size)
        self._counts["words"] += n
        if n == 0:
            return DavisPacket(events=empty_events())
        # Classify on the top nibble: 1 = Y, 2/3 = X, 7 = wrap, 8..15 = timestamp, else rare.
        hi = w >> 12
        x_mask = (hi - np.uint16(2)) < 2
        st_mask = (hi >= 7) | (hi == 1)
        n_fast = int(np.count_nonzero(x_mask)) + int(np.count_nonzero(st_mask))
        rare_idx: npt.NDArray[np.intp] = _NO_INDEX
        resets = _NO_INDEX
        if n_fast < n:
            rare_idx = np.flatnonzero(~(x_mask | st_mask))
            resets = rare_idx[w[rare_idx] == DeviceSpecial.TIMESTAMP_RESET]
        if resets.size == 0:
            events = self._segment(w, x_mask, st_mask, rare_idx)
        else:
            parts = []
            start = 0
            for r in [*resets.tolist(), n]:
                seg = slice(start, r)
                rare = rare_idx[(rare_idx >= start) & (rare_idx < r)] - start
                parts.append(self._segment(w[seg], x_mask[seg], st_mask[seg], rare))
                if r < n:
                    self._timestamp_reset()
                start = r + 1
            events = np.concatenate(parts)
        specials = np.array(self._specials, dtype=SPECIAL_DTYPE)
        imu = np.empty(len(self._imu_out), IMU_SAMPLE_DTYPE)
        for i, (t, acc, gyr, temp) in enumerate(self._imu_out):
            imu[i] = (t, acc, gyr, temp)
        self._counts["events"] += events.size
        self._counts["specials"] += specials.size
        return DavisPacket(events=events, frames=tuple(self._frames), imu=imu, specials=specials)

    def _timestamp_reset(self) -> None:
        self._counts["timestamp_resets"] += 1
        self._epoch = 0
        self._ts15 = 0
        self._last_time = -1
        self._suspend_composites()
        self._specials.append((0, SpecialType.TIMESTAMP_RESET, 0))

    def _suspend_composites(self) -> None:
        if self._frame is not None:
            self._counts["frames_dropped"] += 1
        if self._imu_bytes is not None:
            self._counts["imu_samples_dropped"] += 1
        self._frame = None
        self._imu_bytes = None
        self._aps_parse = False
        self._imu_parse = False

    def _segment(
        self,
        w: npt.NDArray[np.uint16],
        x_mask: npt.NDArray[np.bool_],
        st_mask: npt.NDArray[np.bool_],
        rare_idx: npt.NDArray[np.intp],
    ) -> npt.NDArray[np.void]:
        """Decode words that contain no TS reset; returns the polarity events.

        ``x_mask`` marks X words, ``st_mask`` state words (Y, wrap, timestamp), ``rare_idx``
        the positions of every other word (SPECIAL, ADC, MISC8, MISC10; no TS reset).
        """
        n = int(w.size)
        if n == 0:
            return empty_events()
        st_idx = np.flatnonzero(st_mask)
        x_idx = np.flatnonzero(x_mask)
        k, m = int(st_idx.size), int(x_idx.size)
        # -- per state word: time and row after it (index 0 = the state before the segment).
        t0 = self._epoch + self._ts15
        if k:
            sw = w[st_idx]
            is_ts = sw >= 0x8000
            shi = sw >> 12
            is_wrap = shi == 7
            is_y = shi == 1
            wraps = np.where(is_wrap, (sw & 0x0FFF).astype(np.int64) * _WRAP_US, 0)
            epoch = np.cumsum(wraps)
            epoch += self._epoch
            upd = is_ts | is_wrap
            pos = np.arange(k, dtype=np.int64)
            last = np.maximum.accumulate(np.where(upd, pos, -1))
            tsval = np.where(is_ts, sw & 0x7FFF, 0).astype(np.int64)
            ts15 = np.where(last >= 0, tsval[np.maximum(last, 0)], self._ts15)
            times = np.empty(k + 1, np.int64)
            times[0] = t0
            np.add(epoch, ts15, out=times[1:])
            yv = (sw & 0x0FFF).astype(np.int16)
            bad_y = is_y & (yv >= self._y_range)
            if bad_y.any():
                self._counts["y_out_of_range"] += int(np.count_nonzero(bad_y))
                is_y = is_y & ~bad_y
            lasty = np.maximum.accumulate(np.where(is_y, pos, -1))
            rows = np.empty(k + 1, np.int16)
            rows[0] = self._row
            rows[1:] = np.where(lasty >= 0, yv[np.maximum(lasty, 0)], self._row)
            self._monotonic_check(times[1:][upd])
            if (epoch[-1] >> 31) != (self._epoch >> 31):
                big = self._big_wrap_positions(epoch, st_idx)
            else:
                big = []
            self._epoch = int(epoch[-1])
            self._ts15 = int(ts15[-1])
            self._row = int(rows[-1])
        else:
            times = np.array([t0], np.int64)
            rows = np.array([self._row], np.int16)
            big = []
        # -- polarity events: gather the state in force at each X word.
        if m:
            # State words before each X = its position - X words before it - rare words before.
            j = x_idx - np.arange(m, dtype=np.intp)
            if rare_idx.size * 32 < n:
                if rare_idx.size:
                    j -= np.searchsorted(rare_idx, x_idx)
            else:
                j = np.cumsum(st_mask, dtype=np.intp)[x_idx]
            xw = w[x_idx]
            ev = np.empty(m, EVENT_DTYPE)
            ev["t"] = times[j]
            yy = rows[j]
            ev["y"] = yy
            xx = xw & 0x0FFF
            ev["x"] = xx
            ev["p"] = (xw >> 12) & 1
            if yy.size and (yy.min() < 0 or xx.max() >= self._x_range):
                no_row = yy < 0
                bad_x = xx >= self._x_range
                self._counts["x_without_row"] += int(np.count_nonzero(no_row))
                self._counts["x_out_of_range"] += int(np.count_nonzero(bad_x & ~no_row))
                ev = ev[~(no_row | bad_x)]
            if self.orientation.dvs_invert_xy:
                ev["x"], ev["y"] = ev["y"].copy(), ev["x"].copy()
        else:
            ev = empty_events()
        if rare_idx.size or big:
            self._rare(w, rare_idx, st_idx, times, big)
        return ev

    def _monotonic_check(self, t: npt.NDArray[np.int64]) -> None:
        if t.size == 0:
            return
        bad = int(np.count_nonzero(t[1:] <= t[:-1])) + int(t[0] <= self._last_time)
        if bad:
            self._counts["non_monotonic_timestamps"] += bad
            _log.debug("%d non-monotonic timestamp word(s)", bad)
        self._last_time = int(t[-1])

    def _big_wrap_positions(
        self, epoch: npt.NDArray[np.int64], st_idx: npt.NDArray[np.intp]
    ) -> list[tuple[int, int]]:
        """(word position, first µs of the new 2^31 epoch) of every big wrap in ``epoch``."""
        prev = np.empty_like(epoch)
        prev[0] = self._epoch
        prev[1:] = epoch[:-1]
        hit = np.flatnonzero((epoch >> 31) != (prev >> 31))
        return [(int(st_idx[i]), int(epoch[i] >> 31) << 31) for i in hit]

    # -- rare words: SPECIAL, APS ADC, MISC8, MISC10 --------------------------------------------

    def _rare(
        self,
        w: npt.NDArray[np.uint16],
        rare_idx: npt.NDArray[np.intp],
        st_idx: npt.NDArray[np.intp],
        times: npt.NDArray[np.int64],
        big: list[tuple[int, int]],
    ) -> None:
        rw = w[rare_idx]
        is_adc = (rw >> 12) == 4
        ctl = np.flatnonzero(~is_adc)  # positions within rare_idx of non-ADC rare words
        ctl_pos = rare_idx[ctl]
        ctl_times = times[np.searchsorted(st_idx, ctl_pos)]
        ctl_words = rw[ctl]
        imu_blocks = {} if big else self._complete_imu_samples(ctl, ctl_words, ctl_times)
        ctl_t = ctl_times.tolist()
        ctl_w = ctl_words.tolist()
        ctl_list = ctl.tolist()
        ctl_pos_list = ctl_pos.tolist()
        big_i = 0
        prev = -1
        q = 0
        n_ctl = len(ctl_list)
        while q < n_ctl:
            i, pos = ctl_list[q], ctl_pos_list[q]
            while big_i < len(big) and big[big_i][0] < pos:
                self._big_wrap(big[big_i][1])
                big_i += 1
            if i > prev + 1:
                self._adc(rw[prev + 1 : i])
            block = imu_blocks.get(q)
            if block is not None:
                self._imu_sample(*block)
                prev = ctl_list[q + _IMU_WORDS - 1]
                q += _IMU_WORDS
                continue
            prev = i
            self._control(ctl_w[q], ctl_t[q])
            q += 1
        if prev + 1 < rw.size:
            self._adc(rw[prev + 1 :])
        while big_i < len(big):
            self._big_wrap(big[big_i][1])
            big_i += 1

    def _complete_imu_samples(
        self,
        ctl: npt.NDArray[np.intp],
        words: npt.NDArray[np.uint16],
        times: npt.NDArray[np.int64],
    ) -> dict[int, tuple[int, tuple[float, ...], tuple[float, ...], float, tuple[int, int]]]:
        """Vectorised fast path for whole 6-axis IMU samples with every sensor on.

        A sample is 17 consecutive rare words (start, info, 14 data bytes, end) with no ADC
        word in between. Returns {index of its start in ``words``: (t, accel, gyro, temp,
        scales)}; anything else goes through the word-by-word state machine.
        """
        n = int(words.size) - (_IMU_WORDS - 1)
        if n <= 0:
            return {}
        starts = np.flatnonzero(words[:n] == DeviceSpecial.IMU_START6)
        if starts.size == 0:
            return {}
        ends = starts + (_IMU_WORDS - 1)
        ok = (words[ends] == DeviceSpecial.IMU_END) & (ctl[ends] - ctl[starts] == _IMU_WORDS - 1)
        ok &= (words[starts + 1] & 0xFFE0) == 0x53E0  # info word, all three sensors on
        body = words[starts[:, None] + np.arange(2, 16)]
        ok &= ((body >> 8) == 0x50).all(axis=1)
        if not ok.any():
            return {}
        starts, ends, body = starts[ok], ends[ok], body[ok]
        raw = (body & 0xFF).astype(np.uint8).view(">i2").astype(np.float64)  # (n, 7)
        info = words[starts + 1] & 0xFF
        a_lsb = np.asarray(_ACCEL_LSB_PER_G)[(info >> 2) & 3]
        g_lsb = np.asarray(_GYRO_LSB_PER_DPS)[info & 3]
        acc = raw[:, 0:3] / a_lsb[:, None] * self._imu_sign
        gyr = raw[:, 4:7] / g_lsb[:, None] * self._imu_sign
        temp = raw[:, 3] / 340.0 + 35.0
        return {
            int(s): (int(t), tuple(a), tuple(g), float(tc), ((int(i) >> 2) & 3, int(i) & 3))
            for s, t, a, g, tc, i in zip(
                starts.tolist(),
                times[ends].tolist(),
                acc.tolist(),
                gyr.tolist(),
                temp.tolist(),
                info.tolist(),
                strict=True,
            )
        }

    def _imu_sample(
        self,
        t: int,
        acc: tuple[float, ...],
        gyr: tuple[float, ...],
        temp: float,
        scales: tuple[int, int],
    ) -> None:
        """A whole IMU sample from the fast path (same bookkeeping as start ... end)."""
        if self._imu_bytes is not None:
            self._counts["imu_samples_dropped"] += 1
        self._imu_parse = True
        self._imu_bytes = None
        self._imu_scale = scales
        self._imu_out.append((t, acc, gyr, temp))
        self._counts["imu_samples"] += 1

    def _big_wrap(self, epoch_start: int) -> None:
        self._counts["big_wraps"] += 1
        self._suspend_composites()
        self._specials.append((epoch_start - 1, SpecialType.TIMESTAMP_WRAP, 0))

    def _control(self, word: int, t: int) -> None:
        code = word >> 12
        data = word & 0x0FFF
        if code == 0:
            self._special(data, t)
        elif code == 5:
            self._misc8(data >> 8, data & 0xFF)
        elif code == 6:
            if data >> 10 == 0:
                if self._frame is not None and self._frame.exposure_slices < 3:
                    f = self._frame
                    f.exposure_cycles |= (data & 0x3FF) << (10 * f.exposure_slices)
                    f.exposure_slices += 1
                else:
                    self._counts["aps_words_skipped"] += 1
            else:
                self._counts["unknown_words"] += 1
        else:  # pragma: no cover - the classifier only routes codes 0, 4, 5, 6 here
            self._counts["unknown_words"] += 1

    def _special(self, data: int, t: int) -> None:
        if data in _SPECIAL_EXPORT:
            self._specials.append((t, _SPECIAL_EXPORT[DeviceSpecial(data)], 0))
        elif data in (DeviceSpecial.APS_FRAME_START_GS, DeviceSpecial.APS_FRAME_START_RS):
            if self._frame is not None:
                self._counts["frames_dropped"] += 1
            self._aps_parse = True
            gs = data == DeviceSpecial.APS_FRAME_START_GS
            self._frame = _Frame(t, global_shutter=gs, invert_xy=self.orientation.aps_invert_xy)
            self._specials.append((t, SpecialType.APS_FRAME_START, 0))
        elif DeviceSpecial.APS_FRAME_END <= data <= DeviceSpecial.APS_EXPOSURE_END:
            self._aps_special(data, t)
        elif data == DeviceSpecial.IMU_START6:
            if self._imu_bytes is not None:
                self._counts["imu_samples_dropped"] += 1
            self._imu_parse = True
            self._imu_bytes = []
            self._imu_slots = tuple(range(14))
        elif data == DeviceSpecial.IMU_END:
            self._imu_end(t)
        else:  # reserved 0, IMU_START9, and anything above 17
            self._counts["unknown_words"] += 1

    def _aps_special(self, data: int, t: int) -> None:
        f = self._frame
        if f is None or not self._aps_parse:
            self._counts["aps_words_skipped"] += 1
            return
        if data == DeviceSpecial.APS_FRAME_END:
            self._frame = None
            self._end_frame(f, t)
        elif data == DeviceSpecial.APS_RESET_COLUMN_START:
            f.read = _READ_RESET
            f.count_y[_READ_RESET] = 0
        elif data == DeviceSpecial.APS_SIGNAL_COLUMN_START:
            f.read = _READ_SIGNAL
            f.count_y[_READ_SIGNAL] = 0
        elif data == DeviceSpecial.APS_COLUMN_END:
            if f.read is None:
                self._counts["aps_words_skipped"] += 1
                return
            if f.count_y[f.read] != f.readout()[1]:
                self._counts["aps_row_count_mismatches"] += 1
            f.count_x[f.read] += 1
            f.read = None
        elif data == DeviceSpecial.APS_EXPOSURE_START:
            f.t_start_exposure = t
            self._specials.append((t, SpecialType.APS_EXPOSURE_START, 0))
        else:  # APS_EXPOSURE_END
            f.t_end_exposure = t
            self._specials.append((t, SpecialType.APS_EXPOSURE_END, 0))

    def _end_frame(self, f: _Frame, t: int) -> None:
        sx, sy, _, _ = f.shape()
        cols = f.readout()[0]
        self._specials.append((t, SpecialType.APS_FRAME_END, 0))
        if f.count_x[_READ_RESET] != cols or f.count_x[_READ_SIGNAL] != cols:
            self._counts["frames_dropped"] += 1
            _log.debug(
                "APS frame dropped: %d reset / %d signal columns, expected %d",
                f.count_x[0],
                f.count_x[1],
                cols,
            )
            return
        _, readout = f.buffers()
        # libcaer apsUpdateFrame: x = flipX ? n-1-column : column, y likewise, then swapped
        # when invertXY; the buffer is (readout column, sample), the image (row, column).
        o = self.orientation
        if o.aps_flip_x:
            readout = readout[::-1, :]
        if o.aps_flip_y:
            readout = readout[:, ::-1]
        pixels = readout if o.aps_invert_xy else readout.T
        self._frames.append(
            ApsFrame(
                t_start_frame_us=f.t_start_frame,
                t_end_frame_us=t,
                t_start_exposure_us=f.t_start_exposure,
                t_end_exposure_us=f.t_end_exposure,
                exposure_cycles=f.exposure_cycles,
                position_x=sx,
                position_y=sy,
                pixels=np.ascontiguousarray(pixels, dtype=np.uint16),
                global_shutter=f.global_shutter,
            )
        )
        self._counts["frames"] += 1

    def _adc(self, run: npt.NDArray[np.uint16]) -> None:
        """A run of consecutive (within the APS substream) ADC words."""
        f = self._frame
        if f is None or not self._aps_parse or f.read is None:
            self._counts["aps_words_skipped"] += int(run.size)
            return
        cols, rows = f.readout()
        read = f.read
        c = f.count_x[read]
        r = f.count_y[read]
        f.count_y[read] = r + int(run.size)
        n = max(0, min(int(run.size), rows - r))
        if c >= cols or n == 0:
            self._counts["aps_words_skipped"] += int(run.size)
            return
        self._counts["aps_words_skipped"] += int(run.size) - n
        vals = (run[:n] & 0x03FF).astype(np.int32) << 1  # DAVIS240: samples doubled
        reset, pixels = f.buffers()
        if read == _READ_RESET:
            reset[c, r : r + n] = vals
        else:
            rst = reset[c, r : r + n]
            pix = np.clip(rst - vals, 0, 1023)
            pix[(rst < 384) | (vals == 0)] = 1023
            pixels[c, r : r + n] = pix

    def _misc8(self, sub: int, byte: int) -> None:
        if sub == 0:  # IMU data byte
            if self._imu_bytes is None or not self._imu_parse:
                self._counts["imu_words_skipped"] += 1
            elif len(self._imu_bytes) < len(self._imu_slots):
                self._imu_bytes.append(byte)
            else:
                self._counts["imu_words_skipped"] += 1
        elif sub in (1, 2):  # APS ROI high / low byte
            f = self._frame
            if f is None or not self._aps_parse:
                self._counts["aps_words_skipped"] += 1
            elif sub == 1:
                f.roi_hi = byte
            else:
                f.roi.append(((f.roi_hi or 0) << 8) | byte)
                f.roi_hi = None
        elif sub == 3:  # IMU info: sensor mask + scales
            if self._imu_bytes is None or not self._imu_parse:
                self._counts["imu_words_skipped"] += 1
                return
            accel, gyro, temp = bool(byte & 0x80), bool(byte & 0x40), bool(byte & 0x20)
            slots: list[int] = []
            if accel:
                slots += range(6)
            if temp:
                slots += range(6, 8)
            if gyro:
                slots += range(8, 14)
            self._imu_slots = tuple(slots)
            self._imu_scale = ((byte >> 2) & 3, byte & 3)
        else:
            self._counts["unknown_words"] += 1

    def _imu_end(self, t: int) -> None:
        got = self._imu_bytes
        if got is None or not self._imu_parse:
            self._counts["imu_words_skipped"] += 1
            return
        self._imu_bytes = None
        if len(got) != len(self._imu_slots):
            self._counts["imu_samples_dropped"] += 1
            return
        regs = [0] * 14
        for slot, b in zip(self._imu_slots, got, strict=True):
            regs[slot] = b
        raw = [int.from_bytes(bytes(regs[i : i + 2]), "big", signed=True) for i in range(0, 14, 2)]
        a_lsb = _ACCEL_LSB_PER_G[self._imu_scale[0]]
        g_lsb = _GYRO_LSB_PER_DPS[self._imu_scale[1]]
        sign = self._imu_sign
        acc = tuple(float(v / a_lsb * s) for v, s in zip(raw[0:3], sign, strict=True))
        gyr = tuple(float(v / g_lsb * s) for v, s in zip(raw[4:7], sign, strict=True))
        self._imu_out.append((t, acc, gyr, raw[3] / 340.0 + 35.0))
        self._counts["imu_samples"] += 1


def decode_words(data: bytes | npt.NDArray[np.uint16]) -> DavisPacket:
    """Decode a complete stream in one call (a fresh :class:`DavisDecoder`)."""
    return DavisDecoder().decode(data)
