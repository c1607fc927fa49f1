"""The structure of a C3D file, walked in pure Python with bounds checks: header, parameters,
POINT and ANALOG layout.

:func:`validate_c3d` rejects broken files with a clear :class:`ViconFileError` before any native
code sees them and describes the file as a :class:`C3DLayout`; :func:`analog_layout` checks the
ANALOG group (USED, RATE, SCALE, OFFSET, GEN_SCALE) against the header.

Frame count. The C3D header stores the last frame in 16 bits, and Vicon writes 65535 there (and in
POINT:FRAMES) for longer trials; ``ezc3d`` 1.7.2 then returns only 65,535 frames. When the
declared count is saturated, the layout takes TRIAL:ACTUAL_END_FIELD − ACTUAL_START_FIELD + 1
(two 16-bit words each) when present and consistent, else the length of the data section, and
the readers decode the point block themselves with numpy.
"""

from __future__ import annotations

import logging
import math
import os
import struct
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Literal

import numpy as np
import numpy.typing as npt

from mocaprig.calib.vicon_records import FloatArray, ViconFileError

__all__ = [
    "AnalogLayout",
    "C3DLayout",
    "Processor",
    "analog_layout",
    "dec_to_ieee",
    "validate_c3d",
    "validate_c3d_bytes",
]

_log = logging.getLogger(__name__)

Processor = Literal["intel", "dec", "sgi"]
"""The C3D processor type (byte 4 of the parameter section): fixes endianness and float format."""

_MODEL_OUTPUT_LISTS = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS", "REACTIONS")

_BLOCK = 512
_PROCESSORS: dict[int, Processor] = {84: "intel", 85: "dec", 86: "sgi"}
_MAX_PARAMETER_RECORDS = 65_536
_MAX_RATE_HZ = 1e6
_SATURATED_FRAMES = 65_535


@dataclass(frozen=True, slots=True)
class _Param:
    type_code: int  # -1 char, 1 byte, 2 int16, 4 float
    dims: tuple[int, ...]
    data: bytes
    offset: int = 0  # of ``data`` in the file, bytes


@dataclass(frozen=True, slots=True)
class C3DLayout:
    """What :func:`validate_c3d` found in a C3D file's header and parameter section.

    Attributes:
        path: the file.
        file_size: bytes.
        processor: ``"intel"``, ``"dec"`` or ``"sgi"`` (big-endian).
        parameter_block: 1-based block of the parameter section (header byte 1).
        n_parameter_blocks: blocks declared by the parameter section.
        data_start_block: 1-based block where the 3D/analog data begin (POINT:DATA_START).
        n_points: POINT:USED.
        n_frames: frames to read (see ``frames_source``).
        frames_source: where ``n_frames`` came from: ``"POINT:FRAMES"``, ``"header"``,
            ``"TRIAL:ACTUAL_END_FIELD"`` or ``"data section length"``.
        first_frame: 1-based capture frame of the first sample.
        rate_hz: POINT:RATE.
        scale: POINT:SCALE (< 0: 32-bit float data; > 0: 16-bit integers × scale).
        analog_words_per_frame: analog values stored per 3D frame (channels × subframes).
        frame_bytes: bytes per frame in the data section.
        labels: POINT:LABELS (+ LABELS2…), stripped, ``n_points`` of them.
        units_raw: POINT:UNITS as written, or None when absent.
        model_outputs: labels listed in POINT:ANGLES/FORCES/MOMENTS/POWERS/SCALARS/REACTIONS.
        strings: selected string parameters (``MANUFACTURER:COMPANY`` …).
        parameter_offsets: ``"GROUP:NAME"`` -> byte offset of the parameter's values in the file
            (for writers that patch a value in place, e.g. the frame count).
    """

    path: str
    file_size: int
    processor: Processor
    parameter_block: int
    n_parameter_blocks: int
    data_start_block: int
    n_points: int
    n_frames: int
    frames_source: str
    first_frame: int
    rate_hz: float
    scale: float
    analog_words_per_frame: int
    frame_bytes: int
    labels: tuple[str, ...]
    units_raw: str | None
    model_outputs: frozenset[str]
    strings: Mapping[str, str]
    parameter_offsets: Mapping[str, int] = field(default_factory=dict)

    @property
    def is_float(self) -> bool:
        """True when the data section holds 32-bit floats (POINT:SCALE < 0)."""
        return self.scale < 0

    @property
    def data_offset(self) -> int:
        """Byte offset of the data section."""
        return (self.data_start_block - 1) * _BLOCK


class _Walker:
    """Bounds-checked reads of a C3D byte buffer with the file's endianness."""

    def __init__(self, buf: bytes, path: str) -> None:
        self.buf = buf
        self.path = path
        self.end = "<"

    def fail(self, what: str, todo: str = "") -> ViconFileError:
        advice = todo or "re-export the trial from Vicon Nexus or repair the file"
        return ViconFileError(
            f"{self.path}: not a readable C3D file: {what}; {advice}", path=self.path
        )

    def need(self, pos: int, n: int, what: str) -> None:
        if pos < 0 or pos + n > len(self.buf):
            msg = f"{what} at byte {pos} runs past the end of the file ({len(self.buf)} bytes)"
            raise self.fail(
                msg,
                "the file is truncated or corrupt; copy it again from the capture machine",
            )

    def u8(self, pos: int) -> int:
        self.need(pos, 1, "a byte")
        return self.buf[pos]

    def i8(self, pos: int) -> int:
        v = self.u8(pos)
        return v - 256 if v > 127 else v

    def u16(self, pos: int) -> int:
        self.need(pos, 2, "a 16-bit word")
        return int(struct.unpack_from(self.end + "H", self.buf, pos)[0])

    def f32(self, pos: int, processor: Processor) -> float:
        self.need(pos, 4, "a float")
        return _decode_floats(self.buf[pos : pos + 4], processor)[0]


def _decode_floats(raw: bytes, processor: Processor) -> list[float]:
    """Decode 32-bit floats in the processor's format (DEC: VAX F-float)."""
    n = len(raw) // 4
    if processor == "sgi":
        return [float(x) for x in np.frombuffer(raw, dtype=">f4", count=n)]
    if processor == "dec":
        return [float(x) for x in dec_to_ieee(np.frombuffer(raw, dtype=np.uint8, count=4 * n))]
    return [float(x) for x in np.frombuffer(raw, dtype="<f4", count=n)]


def dec_to_ieee(raw: npt.NDArray[np.uint8]) -> npt.NDArray[np.float32]:
    """VAX F-float bytes (b0 b1 b2 b3) → IEEE: swap the 16-bit halves, read LE, divide by 4."""
    b = raw.reshape(-1, 4)[:, [2, 3, 0, 1]].copy()
    out: npt.NDArray[np.float32] = (b.view("<f4").reshape(-1) / np.float32(4.0)).astype(np.float32)
    return out


def _param_numbers(p: _Param, processor: Processor) -> list[float]:
    end = ">" if processor == "sgi" else "<"
    if p.type_code == 1:
        return [float(x) for x in p.data]
    if p.type_code == 2:
        return [float(x) for x in np.frombuffer(p.data, dtype=end + "i2")]
    if p.type_code == 4:
        return _decode_floats(p.data, processor)
    return []


def _param_strings(p: _Param) -> list[str]:
    if p.type_code != -1:
        return []
    text = p.data.decode("utf-8", errors="replace")
    if len(p.dims) <= 1:
        return [text.strip().strip("\x00").strip()]
    width = p.dims[0]
    if width == 0:
        return []
    return [text[i : i + width].strip().strip("\x00").strip() for i in range(0, len(text), width)]


def _walk_parameters(
    w: _Walker, start: int, limit: int
) -> tuple[dict[int, str], list[tuple[int, str, _Param]]]:
    """Walk group/parameter records from ``start``; every record must end before ``limit``."""
    groups: dict[int, str] = {}
    params: list[tuple[int, str, _Param]] = []
    pos = start
    for _ in range(_MAX_PARAMETER_RECORDS):
        if pos + 2 > limit:
            msg = (
                f"parameter records run past the parameter section (byte {pos}, section ends at "
                f"{limit}) without an end marker"
            )
            raise w.fail(msg)
        n_chars = abs(w.i8(pos))
        gid = w.i8(pos + 1)
        if n_chars == 0 or gid == 0:
            return groups, params
        name_end = pos + 2 + n_chars
        if name_end + 2 > limit:
            msg = f"parameter record at byte {pos} runs past the parameter section"
            raise w.fail(msg)
        name = w.buf[pos + 2 : name_end].decode("ascii", errors="replace").strip().upper()
        offset = w.u16(name_end)
        body = name_end + 2
        next_pos = name_end + offset if offset else None
        if next_pos is not None and (next_pos <= pos or next_pos > limit):
            msg = (
                f"record {name!r} at byte {pos} points to the next record at byte {next_pos}, "
                f"outside the parameter section ({start}..{limit})"
            )
            raise w.fail(msg)
        rec_end = limit if next_pos is None else next_pos
        if gid < 0:
            n_desc = w.u8(body) if body < rec_end else 0
            if body + 1 + n_desc > limit:
                msg = f"group {name!r} at byte {pos}: description runs past the section"
                raise w.fail(msg)
            groups[-gid] = name
        else:
            if body + 2 > rec_end:
                msg = f"parameter {name!r} at byte {pos} is cut short"
                raise w.fail(msg)
            type_code = w.i8(body)
            n_dims = w.u8(body + 1)
            if type_code not in (-1, 1, 2, 4):
                msg = f"parameter {name!r} at byte {pos} has unknown data type {type_code}"
                raise w.fail(msg)
            if n_dims > 7:
                msg = f"parameter {name!r} at byte {pos} has {n_dims} dimensions (max 7)"
                raise w.fail(msg)
            if body + 2 + n_dims > rec_end:
                msg = f"parameter {name!r} at byte {pos}: dimensions run past the record"
                raise w.fail(msg)
            dims = tuple(w.buf[body + 2 : body + 2 + n_dims])
            count = math.prod(dims) if n_dims else 1
            data_start = body + 2 + n_dims
            data_end = data_start + count * abs(type_code)
            if data_end > rec_end:
                msg = (
                    f"parameter {name!r} at byte {pos} declares {count} values of "
                    f"{abs(type_code)} bytes, more than its record holds"
                )
                raise w.fail(msg)
            prm = _Param(type_code, dims, w.buf[data_start:data_end], data_start)
            params.append((gid, name, prm))
        if next_pos is None:
            return groups, params
        pos = next_pos
    msg = f"more than {_MAX_PARAMETER_RECORDS} parameter records"
    raise w.fail(msg)


def validate_c3d(path: str | os.PathLike[str]) -> C3DLayout:
    """Check a C3D file's structure in pure Python and describe its layout.

    Checks: the header block and key byte (0x50), the parameter-section pointer and processor type,
    every group/parameter record (bounds, types, dimensions, forward links, known group ids),
    POINT:USED/FRAMES/DATA_START/SCALE/RATE and their header copies, POINT:LABELS, and that the data
    section for the frame count fits in the file. Nothing here runs native code.

    Raises:
        ViconFileError: the file is missing, unreadable or malformed; the message says what and what
            to do.
    """
    p = str(path)
    try:
        buf = Path(p).read_bytes()
    except OSError as err:
        msg = f"{p}: cannot read the file ({err.strerror or err}); check the path and permissions"
        raise ViconFileError(msg, path=p) from err
    return validate_c3d_bytes(buf, p)


def validate_c3d_bytes(buf: bytes, p: str) -> C3DLayout:
    """:func:`validate_c3d` on the bytes ``buf`` of the file ``p`` (named in the errors)."""
    w = _Walker(buf, p)
    size = len(buf)
    if size < 2 * _BLOCK:
        msg = f"it has {size} bytes, less than a header and a parameter block (1024 bytes)"
        raise w.fail(
            msg,
            "the file is truncated or not a C3D file",
        )
    param_block = buf[0]
    if buf[1] != 0x50:
        msg = f"header byte 2 is 0x{buf[1]:02X}, not the C3D key 0x50"
        raise w.fail(
            msg,
            "check that this is a C3D file (a CSV export needs read_nexus_csv)",
        )
    if param_block < 2:
        msg = f"the header points the parameter section to block {param_block} (must be ≥ 2)"
        raise w.fail(msg)
    param_start = (param_block - 1) * _BLOCK
    if param_start + 4 > size:
        msg = (
            f"the header points the parameter section to block {param_block} (byte {param_start}), "
            f"past the end of the file ({size} bytes)"
        )
        raise w.fail(msg)
    n_param_blocks = buf[param_start + 2]
    proc_byte = buf[param_start + 3]
    if proc_byte not in _PROCESSORS:
        msg = (
            f"unknown processor type {proc_byte} at byte {param_start + 3} of the parameter "
            "section (expected 84 Intel, 85 DEC or 86 SGI/MIPS)"
        )
        raise w.fail(msg)
    processor = _PROCESSORS[proc_byte]
    w.end = ">" if processor == "sgi" else "<"
    if n_param_blocks == 0:
        msg = "the parameter section declares 0 blocks"
        raise w.fail(msg)
    param_end = param_start + n_param_blocks * _BLOCK
    if param_end > size:
        msg = (
            f"the parameter section declares {n_param_blocks} blocks, ending at byte {param_end}, "
            f"past the end of the file ({size} bytes)"
        )
        raise w.fail(
            msg,
            "the file is truncated; copy it again from the capture machine",
        )
    groups, records = _walk_parameters(w, param_start + 4, param_end)
    params: dict[str, dict[str, _Param]] = {}
    for gid, name, prm in records:
        if gid not in groups:
            msg = f"parameter {name!r} belongs to group id {gid}, which is not defined"
            raise w.fail(msg)
        params.setdefault(groups[gid], {})[name] = prm
    if "POINT" not in params:
        msg = "there is no POINT group"
        raise w.fail(msg)
    point = params["POINT"]

    def number(group: str, name: str) -> float | None:
        prm = params.get(group, {}).get(name)
        if prm is None:
            return None
        vals = _param_numbers(prm, processor)
        return vals[0] if vals else None

    def uint16_param(name: str) -> int | None:
        prm = point.get(name)
        if prm is None:
            return None
        if prm.type_code == 2 and len(prm.data) >= 2:
            return int(struct.unpack_from(w.end + "H", prm.data, 0)[0])
        vals = _param_numbers(prm, processor)
        if not vals or not math.isfinite(vals[0]) or vals[0] < 0:
            msg = f"POINT:{name} is {vals[:1]}, not a count"
            raise w.fail(msg)
        return int(vals[0])

    hdr_points = w.u16(2)
    hdr_analog_words = w.u16(4)
    hdr_first = w.u16(6)
    hdr_last = w.u16(8)
    hdr_scale = w.f32(12, processor)
    hdr_data_start = w.u16(16)
    hdr_analog_per_frame = w.u16(18)
    hdr_rate = w.f32(20, processor)

    used = uint16_param("USED")
    if used is None:
        msg = "POINT:USED is missing"
        raise w.fail(msg)
    if used != hdr_points:
        msg = f"the header says {hdr_points} points but POINT:USED says {used}"
        raise w.fail(msg)
    data_start = uint16_param("DATA_START") or hdr_data_start
    if data_start != hdr_data_start and hdr_data_start:
        msg = (
            f"the header says the data start at block {hdr_data_start} "
            f"but POINT:DATA_START says {data_start}"
        )
        raise w.fail(msg)
    if data_start < param_block + n_param_blocks:
        msg = (
            f"the data section (block {data_start}) overlaps the parameter section "
            f"(blocks {param_block}..{param_block + n_param_blocks - 1})"
        )
        raise w.fail(msg)
    scale = number("POINT", "SCALE")
    scale = hdr_scale if scale is None else scale
    if not math.isfinite(scale) or scale == 0.0:
        msg = f"POINT:SCALE is {scale}; it must be a finite, non-zero number"
        raise w.fail(msg)
    if math.isfinite(hdr_scale) and hdr_scale != 0.0 and (hdr_scale < 0) != (scale < 0):
        msg = (
            f"the header scale ({hdr_scale}) and POINT:SCALE ({scale}) disagree on whether the "
            "data are floats or integers"
        )
        raise w.fail(msg)
    rate = number("POINT", "RATE")
    rate = hdr_rate if rate is None else rate
    if not (math.isfinite(rate) and 0 < rate <= _MAX_RATE_HZ):
        msg = f"POINT:RATE is {rate}; it must lie in (0, {_MAX_RATE_HZ:g}] Hz"
        raise w.fail(msg)

    labels: list[str] = []
    for key in ["LABELS", *[f"LABELS{i}" for i in range(2, 256)]]:
        if key not in point:
            break
        labels.extend(_param_strings(point[key]))
    if len(labels) < used:
        msg = f"POINT:USED says {used} points but POINT:LABELS holds {len(labels)} labels"
        raise w.fail(
            msg,
            "the POINT:USED value is absurd or the labels were lost; re-export the trial",
        )
    labels = labels[:used]

    if hdr_analog_words and (
        hdr_analog_per_frame == 0 or hdr_analog_words % hdr_analog_per_frame != 0
    ):
        msg = (
            f"the header declares {hdr_analog_words} analog values per frame but "
            f"{hdr_analog_per_frame} analog samples per frame, which do not divide"
        )
        raise w.fail(msg)
    word = 4 if scale < 0 else 2
    frame_bytes = (4 * used + hdr_analog_words) * word
    data_offset = (data_start - 1) * _BLOCK
    data_end = size
    rot_start = number("ROTATION", "DATA_START")
    if rot_start is not None and math.isfinite(rot_start) and rot_start > data_start:
        data_end = min(size, (int(rot_start) - 1) * _BLOCK)
    capacity = max(0, data_end - data_offset) // frame_bytes if frame_bytes else 0

    hdr_frames = hdr_last - hdr_first + 1 if hdr_last >= hdr_first and hdr_last > 0 else 0
    pf = uint16_param("FRAMES")
    declared, source = (pf, "POINT:FRAMES") if pf is not None else (hdr_frames, "header")
    trial = params.get("TRIAL", {})
    trial_first = trial_frames = None
    if "ACTUAL_START_FIELD" in trial and "ACTUAL_END_FIELD" in trial:
        s = _two_word_int(trial["ACTUAL_START_FIELD"], processor)
        e = _two_word_int(trial["ACTUAL_END_FIELD"], processor)
        if s is not None and e is not None and e >= s >= 1:
            trial_first, trial_frames = s, e - s + 1
    if frame_bytes and (declared >= _SATURATED_FRAMES or hdr_frames >= _SATURATED_FRAMES):
        if trial_frames is not None and declared <= trial_frames <= capacity:
            declared, source = trial_frames, "TRIAL:ACTUAL_END_FIELD"
        else:
            declared = _trim_padding(buf, data_offset, frame_bytes, capacity)
            source = "data section length"
        _log.info(
            "%s: the 16-bit frame count is saturated (65535); reading %d frames (%s)",
            p,
            declared,
            source,
        )
    n_frames = declared if used or hdr_analog_words else 0
    if n_frames and data_offset >= size:
        msg = (
            f"POINT:DATA_START points to block {data_start} (byte {data_offset}), past the end of "
            f"the file ({size} bytes)"
        )
        raise w.fail(
            msg,
            "the file is truncated; copy it again from the capture machine",
        )
    if n_frames > capacity:
        msg = (
            f"{n_frames} frames of {frame_bytes} bytes from byte {data_offset} need "
            f"{n_frames * frame_bytes} bytes, but the data section holds "
            f"{max(0, data_end - data_offset)}"
        )
        raise w.fail(
            msg,
            "the file is truncated or its POINT:USED/FRAMES are wrong; copy or re-export it",
        )
    first_frame = trial_first if trial_first is not None else max(hdr_first, 1)

    units_raw: str | None = None
    if "UNITS" in point:
        units = _param_strings(point["UNITS"])
        units_raw = units[0] if units else ""
    plates = params.get("FORCE_PLATFORM", {})
    if "USED" in plates:
        # The native reader builds one plate per FORCE_PLATFORM:USED from its TYPE, CORNERS...
        # (a damaged count of 802 kept ezc3d busy for 15 s on a 2.5 kB file): the count must
        # fit the TYPE list it indexes.
        used_fp = number("FORCE_PLATFORM", "USED")
        types = plates.get("TYPE")
        n_types = len(_param_numbers(types, processor)) if types is not None else 0
        if used_fp is None or not math.isfinite(used_fp) or not 0 <= used_fp <= n_types:
            msg = (
                f"FORCE_PLATFORM:USED is {used_fp} but FORCE_PLATFORM:TYPE describes {n_types} "
                "plates"
            )
            raise w.fail(msg)
    model_outputs: set[str] = set()
    for key in _MODEL_OUTPUT_LISTS:
        if key in point:
            model_outputs.update(x for x in _param_strings(point[key]) if x)
    strings: dict[str, str] = {}
    for group, name in (
        ("MANUFACTURER", "COMPANY"),
        ("MANUFACTURER", "SOFTWARE"),
        ("MANUFACTURER", "VERSION_LABEL"),
        ("SUBJECTS", "NAMES"),
    ):
        sprm = params.get(group, {}).get(name)
        if sprm is not None:
            vals = [x for x in _param_strings(sprm) if x]
            if vals:
                strings[f"{group}:{name}"] = ", ".join(vals)
    return C3DLayout(
        path=p,
        file_size=size,
        processor=processor,
        parameter_block=param_block,
        n_parameter_blocks=n_param_blocks,
        data_start_block=data_start,
        n_points=used,
        n_frames=n_frames,
        frames_source=source,
        first_frame=first_frame,
        rate_hz=float(rate),
        scale=float(scale),
        analog_words_per_frame=hdr_analog_words,
        frame_bytes=frame_bytes,
        labels=tuple(labels),
        units_raw=units_raw,
        model_outputs=frozenset(model_outputs),
        strings=MappingProxyType(strings),
        parameter_offsets=MappingProxyType(
            {f"{g}:{n}": prm.offset for g, group in params.items() for n, prm in group.items()}
        ),
    )


def _two_word_int(p: _Param, processor: Processor) -> int | None:
    """A TRIAL field: two unsigned 16-bit words, low word first (value = lo + 65536·hi)."""
    if p.type_code == 2 and len(p.data) >= 4:
        lo, hi = struct.unpack_from((">" if processor == "sgi" else "<") + "HH", p.data, 0)
        return int(lo) + 65536 * int(hi)
    vals = _param_numbers(p, processor)
    if len(vals) >= 2 and all(math.isfinite(v) and v >= 0 for v in vals[:2]):
        return int(vals[0]) + 65536 * int(vals[1])
    return None


def _trim_padding(buf: bytes, offset: int, frame_bytes: int, capacity: int) -> int:
    """Frames in the data section, minus all-zero frames inside the last block's padding."""
    n = capacity
    pad_start = len(buf) - (_BLOCK - 1)
    while n > 0:
        a = offset + (n - 1) * frame_bytes
        if a < pad_start or any(buf[a : a + frame_bytes]):
            break
        n -= 1
    return n


@dataclass(frozen=True, slots=True)
class AnalogLayout:
    """The ANALOG parameters of a C3D file, checked against its header."""

    n_channels: int
    samples_per_frame: int
    rate_hz: float
    labels: tuple[str, ...]
    units: tuple[str, ...]
    scale: FloatArray
    offset: FloatArray
    gen_scale: float
    unsigned: bool


def _numbered(params: Mapping[str, _Param], name: str) -> list[_Param]:
    """``NAME``, ``NAME2``, ``NAME3``… (C3D continues lists beyond 255 entries that way)."""
    out = []
    for key in [name, *[f"{name}{i}" for i in range(2, 256)]]:
        if key not in params:
            break
        out.append(params[key])
    return out


def analog_layout(buf: bytes, layout: C3DLayout) -> AnalogLayout:
    """Parse and check the ANALOG group of a validated file (pure Python).

    Raises:
        ViconFileError: ANALOG:USED, RATE, SCALE, OFFSET or GEN_SCALE missing or inconsistent
            with the header's analog words and samples per frame.
    """
    p = layout.path
    w = _Walker(buf, p)
    w.end = ">" if layout.processor == "sgi" else "<"
    start = (layout.parameter_block - 1) * _BLOCK
    groups, records = _walk_parameters(w, start + 4, start + layout.n_parameter_blocks * _BLOCK)
    analog = {name: prm for gid, name, prm in records if groups.get(gid) == "ANALOG"}
    proc = layout.processor

    def fail(what: str) -> ViconFileError:
        return ViconFileError(
            f"{p}: malformed analog parameters: {what}; re-export the trial with its analog "
            "channels from Vicon Nexus, or repair the ANALOG group",
            path=p,
        )

    def numbers(name: str) -> list[float]:
        return [v for prm in _numbered(analog, name) for v in _param_numbers(prm, proc)]

    def strings(name: str) -> list[str]:
        return [v for prm in _numbered(analog, name) for v in _param_strings(prm)]

    words = layout.analog_words_per_frame
    spf = w.u16(18)
    used_vals = numbers("USED")
    if "USED" in analog and analog["USED"].type_code == 2 and len(analog["USED"].data) >= 2:
        used_vals = [float(struct.unpack_from(w.end + "H", analog["USED"].data, 0)[0])]
    used = int(used_vals[0]) if used_vals and math.isfinite(used_vals[0]) else None
    if words == 0:
        if used:
            msg = f"ANALOG:USED says {used} channels but the header stores no analog values"
            raise fail(msg)
        empty = np.zeros(0)
        rates = numbers("RATE")
        rate = rates[0] if rates and math.isfinite(rates[0]) and rates[0] > 0 else layout.rate_hz
        return AnalogLayout(0, max(spf, 1), rate, (), (), empty, empty, 1.0, False)
    channels = words // spf  # validate_c3d_bytes checked that spf divides words
    if used is None:
        msg = f"ANALOG:USED is missing or not a number, but the header stores {channels} channels"
        raise fail(msg)
    if used != channels:
        msg = (
            f"ANALOG:USED says {used} channels but the header stores {words} analog values per "
            f"frame in {spf} samples, i.e. {channels} channels"
        )
        raise fail(msg)
    rates = numbers("RATE")
    expected = spf * layout.rate_hz
    if not rates:
        _log.info("%s: ANALOG:RATE is missing; using %g Hz from the header", p, expected)
        rate = expected
    else:
        rate = rates[0]
        if not (math.isfinite(rate) and abs(rate - expected) <= 1e-3 * expected):
            msg = (
                f"ANALOG:RATE is {rate:g} Hz but the header stores {spf} samples per "
                f"{layout.rate_hz:g} Hz frame ({expected:g} Hz)"
            )
            raise fail(msg)
        rate = expected  # the samples per frame define the sampling; RATE is a rounded copy
    scale = np.array(numbers("SCALE"), dtype=np.float64)
    if scale.size < channels or not np.all(np.isfinite(scale[:channels])):
        msg = (
            f"ANALOG:SCALE holds {scale.size} values"
            + (" (some not finite)" if scale.size >= channels else "")
            + f" for {channels} channels"
        )
        raise fail(msg)
    offset = np.array(numbers("OFFSET"), dtype=np.float64)
    if offset.size < channels:
        msg = f"ANALOG:OFFSET holds {offset.size} values for {channels} channels"
        raise fail(msg)
    gen = numbers("GEN_SCALE")
    if not gen or not math.isfinite(gen[0]) or gen[0] == 0.0:
        what = "missing" if not gen else f"{gen[0]}, not a finite non-zero number"
        msg = f"ANALOG:GEN_SCALE is {what}"
        raise fail(msg)
    fmt = strings("FORMAT")
    unsigned = bool(fmt) and fmt[0].upper().startswith("UNSIGNED")
    if unsigned:
        offset = np.mod(offset, 65536.0)
    labels = strings("LABELS")[:channels]
    if len(labels) < channels:
        _log.warning(
            "%s: ANALOG:LABELS names %d of %d channels; the others are called channel<N>",
            p,
            len(labels),
            channels,
        )
    labels += [f"channel{i + 1}" for i in range(len(labels), channels)]
    seen: dict[str, int] = {}
    unique = []
    for i, lab in enumerate(labels):
        name = lab or f"channel{i + 1}"
        seen[name] = seen.get(name, 0) + 1
        unique.append(name if seen[name] == 1 else f"{name}#{seen[name]}")
    units = (strings("UNITS") + [""] * channels)[:channels]
    return AnalogLayout(
        n_channels=channels,
        samples_per_frame=spf,
        rate_hz=float(rate),
        labels=tuple(unique),
        units=tuple(units),
        scale=scale[:channels],
        offset=offset[:channels],
        gen_scale=float(gen[0]),
        unsigned=unsigned,
    )
