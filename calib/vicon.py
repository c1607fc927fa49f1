"""Vicon reference files: C3D and Nexus CSV trajectory exports as one typed record in metres.

Every reader returns a :class:`MarkerTrajectories`: labels, rate, positions in **metres** with NaN
gaps, residuals, the source's first frame number, its length unit and a read-only metadata map.

Readers:

* :func:`read_c3d` — C3D files. The file is first checked by :func:`validate_c3d`, a pure-Python
  structural walk (header, parameter records with bounds checks, POINT sanity, data-section length
  against the file size) that rejects broken files with a clear :class:`ViconFileError` before any
  native code sees them. Intel and DEC files are then decoded by ``ezc3d``; SGI/MIPS (big-endian)
  files, which ``ezc3d`` 1.7.2 rejects, by the pure-Python ``c3d`` package (py-c3d). With
  ``isolate=True`` (the default) the decoder runs in a child interpreter (``python -c``, not
  ``multiprocessing``, whose spawn/forkserver children re-import the caller's ``__main__``), so a
  crash inside ``ezc3d`` (it segfaults on some malformed parameter sections) becomes a
  ``ViconFileError`` instead of killing the caller. Residuals are always decoded from the raw
  bytes per c3d.org (see "Residual byte" below).
* :func:`read_nexus_csv` — Nexus "Trajectories" CSV exports, parsed by section and line role (never
  by line number), in the modern Nexus layout and the older Workstation layout.
* :func:`read_trajectories` — picks one of the two from the file's first bytes.
* :func:`read_c3d_analogs` — the analog channels of a C3D file (:class:`AnalogChannels`, physical
  units, sampled on the Vicon clock), through the same structural check and isolated decoder.

Analog channels. ANALOG:USED channels are stored after the points of each frame,
ANALOG:RATE / POINT:RATE samples per frame (header word 10), each sample one value per channel.
Physical value = (stored − ANALOG:OFFSET) × ANALOG:SCALE × ANALOG:GEN_SCALE (c3d.org).
``ezc3d`` 1.7.2 returns values already scaled that way, except that it uses |OFFSET| (measured,
and so is its source: negative offsets are made positive), so :func:`read_c3d_analogs` takes
ezc3d's values (isolated child, Intel/DEC float files) and restores the signed offset; SGI files,
integer files (ANALOG:FORMAT may say UNSIGNED) and frames beyond 65,535 are decoded from the raw
bytes with numpy. USED, RATE, SCALE, OFFSET and GEN_SCALE are checked against the header and one
another before any native code runs.

Missing samples. A sample is missing when any coordinate is NaN, its residual is negative (C3D's
−1), or all three coordinates are exactly 0.0 (the convention of BTK-era tools). Missing samples are
NaN in both ``positions_m`` and ``residuals_m``.

Which trajectories are kept. By default only labelled physical markers are returned:

* model outputs are dropped: labels listed in POINT:ANGLES, FORCES, MOMENTS, POWERS, SCALARS or
  REACTIONS, and (for CSV exports, which carry no such lists) labels ending in ``Angle(s)``,
  ``Force(s)``, ``Moment(s)`` or ``Power(s)``;
* virtual points are dropped: Plug-in Gait "bones" (a segment code PEL, HED, TRX, CSP, SAC or
  L/R + FE, TI, FO, TO, CL, HU, RA, HN, followed by O, A, L or P — e.g. ``PELO``, ``RFEA``) and
  ``CentreOfMass``/``CentreOfMassFloor``;
* unlabelled trajectories named ``*<number>`` (Nexus' ``*115``…) are real reconstructions without
  an identity; they are dropped unless ``keep_unlabeled=True``.

``keep_virtual=True`` keeps model outputs and virtual points. Subject prefixes (``Daphnee:``) are
ignored by these rules and stripped from the labels only with ``strip_subject_prefix=True``.

Frame count. The C3D header stores the last frame in 16 bits, and Vicon writes 65535 there (and in
POINT:FRAMES) for longer trials; ``ezc3d`` 1.7.2 then returns only 65,535 frames. When the
declared count is saturated, the reader takes TRIAL:ACTUAL_END_FIELD − ACTUAL_START_FIELD + 1
(two 16-bit words each) when present and consistent, else the length of the data section, and
decodes the point block itself with numpy.

Residual byte. The fourth word of a point holds the camera mask in its high byte and
residual / |POINT:SCALE| in its low byte (c3d.org; py-c3d agrees). ``ezc3d`` 1.7.2 reads and
writes the two bytes the other way round (measured), so :func:`read_c3d` decodes residuals itself
and :func:`write_c3d` rewrites the words ezc3d wrote. Vicon Nexus writes residual 0 ("processed")
for every valid sample, so Nexus files read the same either way.
"""

from __future__ import annotations

import contextlib
import csv
import io
import logging
import math
import os
import re
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Literal, TypeAlias

import numpy as np
import numpy.typing as npt

from mocaprig.errors import CalibrationError, ValidationError

__all__ = [
    "AnalogChannels",
    "C3DLayout",
    "LengthUnit",
    "MarkerTrajectories",
    "Processor",
    "ViconFileError",
    "parse_length_unit",
    "read_c3d",
    "read_c3d_analogs",
    "read_nexus_csv",
    "read_trajectories",
    "validate_c3d",
    "write_c3d",
]

_log = logging.getLogger(__name__)

FloatArray: TypeAlias = npt.NDArray[np.float64]
BoolArray: TypeAlias = npt.NDArray[np.bool_]

LengthUnit = Literal["mm", "cm", "m"]
"""A length unit of coordinates in a source file."""

Processor = Literal["intel", "dec", "sgi"]
"""The C3D processor type (byte 4 of the parameter section): fixes endianness and float format."""

_METRES_PER_UNIT: dict[str, float] = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}
_UNIT_SPELLINGS: dict[LengthUnit, tuple[str, ...]] = {
    "mm": ("mm", "millimeter", "millimeters", "millimetre", "millimetres"),
    "cm": ("cm", "centimeter", "centimeters", "centimetre", "centimetres"),
    "m": ("m", "meter", "meters", "metre", "metres"),
}

_MODEL_OUTPUT_LISTS = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS", "REACTIONS")
_BONE_RE = re.compile(r"^(PEL|HED|TRX|CSP|SAC|[LR](FE|TI|FO|TO|CL|HU|RA|HN))[OALP]$")
_MODEL_SUFFIX_RE = re.compile(r"(Angles?|Forces?|Moments?|Powers?)$")
_CENTRE_OF_MASS = frozenset(
    {"CentreOfMass", "CentreOfMassFloor", "CenterOfMass", "CenterOfMassFloor"}
)
_UNLABELED_RE = re.compile(r"^\*\d+$")

_BLOCK = 512
_PROCESSORS: dict[int, Processor] = {84: "intel", 85: "dec", 86: "sgi"}
_MAX_PARAMETER_RECORDS = 65_536
_MAX_RATE_HZ = 1e6
_SATURATED_FRAMES = 65_535
# Isolated parses get this long before the child is killed: generous for slow disks, finite for
# hostile files that would make a native parser loop.
_ISOLATE_TIMEOUT_BASE_S = 60.0
_ISOLATE_TIMEOUT_PER_MB_S = 2.0


class ViconFileError(CalibrationError):
    """A Vicon reference file (C3D or CSV) is unreadable, malformed or inconsistent.

    Attributes:
        path: the file, as given.
    """

    def __init__(self, message: str, *, path: str | os.PathLike[str] | None = None) -> None:
        super().__init__(message)
        self.path = None if path is None else str(path)


# --------------------------------------------------------------------------------------------
# The record
# --------------------------------------------------------------------------------------------


def _unique_labels(labels: Iterable[object], what: str) -> tuple[str, ...]:
    """``labels`` as strings; duplicates raise ``ValidationError`` naming them."""
    out = tuple(str(x) for x in labels)
    if len(set(out)) != len(out):
        dupes = sorted({x for x in out if out.count(x) > 1})
        msg = f"{what} labels must be unique; duplicated: {dupes}"
        raise ValidationError(msg)
    return out


def _positive_rate(rate_hz: float) -> float:
    """``rate_hz`` as a finite float > 0, else ``ValidationError``."""
    rate = float(rate_hz)
    if not (math.isfinite(rate) and rate > 0):
        msg = f"rate_hz must be a finite number > 0, got {rate_hz!r}"
        raise ValidationError(msg)
    return rate


def _freeze_provenance(record: MarkerTrajectories | AnalogChannels) -> None:
    """Check and normalise the fields both records share: ``first_frame`` (an int),
    ``source`` (a str) and ``metadata`` (a read-only str -> str mapping)."""
    first_frame = record.first_frame
    if isinstance(first_frame, bool) or int(first_frame) != first_frame:
        msg = f"first_frame must be an int, got {first_frame!r}"
        raise ValidationError(msg)
    object.__setattr__(record, "first_frame", int(first_frame))
    object.__setattr__(record, "source", str(record.source))
    meta = MappingProxyType({str(k): str(v) for k, v in record.metadata.items()})
    object.__setattr__(record, "metadata", meta)


@dataclass(frozen=True, slots=True, eq=False)
class MarkerTrajectories:
    """Marker trajectories of one trial, in metres, with NaN gaps.

    Attributes:
        labels: marker labels, unique, in column order (N).
        rate_hz: sampling rate of the trajectories (Hz, > 0).
        positions_m: (F, N, 3) float64 positions in metres in the source's frame (Vicon: Z up);
            NaN where the sample is missing.
        residuals_m: (F, N) float64 reconstruction residuals in metres: > 0 the mean ray residual,
            0 a sample the source marks as processed/interpolated/filtered (Nexus writes 0 for every
            valid sample), NaN where the sample is missing *or* the source stores no residual (CSV).
        first_frame: the source's frame number of row 0 (1-based capture numbering: C3D
            TRIAL:ACTUAL_START_FIELD, else the header's first frame; CSV the first Frame value).
        source_unit: the length unit of the coordinates in the source file.
        source: the path the data was read from ("" when built in memory).
        metadata: read-only strings about the source, e.g. ``format``, ``reader``, ``processor``,
            ``manufacturer``, ``software``, ``software_version``, ``units_raw``.

    Arrays are copied on construction and read-only; methods return new objects.
    """

    labels: tuple[str, ...]
    rate_hz: float
    positions_m: FloatArray = field(repr=False)
    residuals_m: FloatArray = field(repr=False)
    first_frame: int = 1
    source_unit: LengthUnit = "m"
    source: str = ""
    metadata: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        labels = _unique_labels(self.labels, "marker")
        rate = _positive_rate(self.rate_hz)
        pos = np.array(self.positions_m, dtype=np.float64, copy=True)
        if pos.ndim != 3 or pos.shape[1:] != (len(labels), 3):
            msg = (
                "positions_m has the wrong shape\n"
                f"  expected: (F, {len(labels)}, 3)\n  actual:   {pos.shape}"
            )
            raise ValidationError(msg)
        res = np.array(self.residuals_m, dtype=np.float64, copy=True)
        if res.shape != pos.shape[:2]:
            msg = (
                "residuals_m has the wrong shape\n"
                f"  expected: {pos.shape[:2]}\n  actual:   {res.shape}"
            )
            raise ValidationError(msg)
        if np.isinf(pos).any() or np.isinf(res).any():
            msg = "positions_m and residuals_m must not hold infinities (use NaN for gaps)"
            raise ValidationError(msg)
        missing = np.isnan(pos).any(axis=-1)
        pos[missing] = np.nan
        res[missing] = np.nan
        if self.source_unit not in _METRES_PER_UNIT:
            msg = f"source_unit must be one of {sorted(_METRES_PER_UNIT)}, got {self.source_unit!r}"
            raise ValidationError(msg)
        _freeze_provenance(self)
        pos.setflags(write=False)
        res.setflags(write=False)
        object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "rate_hz", rate)
        object.__setattr__(self, "positions_m", pos)
        object.__setattr__(self, "residuals_m", res)

    @property
    def n_frames(self) -> int:
        """Number of frames F."""
        return int(self.positions_m.shape[0])

    @property
    def n_markers(self) -> int:
        """Number of markers N."""
        return len(self.labels)

    @property
    def times_s(self) -> FloatArray:
        """(F,) time (s) of each frame from the capture's frame 1: (first_frame − 1 + i) / rate."""
        t: FloatArray = (self.first_frame - 1 + np.arange(self.n_frames, dtype=np.float64)) / (
            self.rate_hz
        )
        return t

    @property
    def duration_s(self) -> float:
        """Length of the recording in seconds: F / rate."""
        return self.n_frames / self.rate_hz

    @property
    def valid(self) -> BoolArray:
        """(F, N) True where the sample is present."""
        ok: BoolArray = np.logical_not(np.isnan(self.positions_m).any(axis=-1))
        return ok

    @property
    def gap_fraction(self) -> float:
        """Fraction of (frame, marker) samples that are missing, in [0, 1] (0.0 when empty)."""
        total = self.n_frames * self.n_markers
        return 0.0 if total == 0 else 1.0 - float(np.count_nonzero(self.valid)) / total

    @property
    def extent_m(self) -> float:
        """Diagonal (m) of the bounding box of all valid samples of all markers; NaN if none."""
        pts = self.positions_m[self.valid]
        if pts.shape[0] == 0:
            return math.nan
        return float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))

    def index(self, label: str) -> int:
        """Column of ``label``: exact match, else a unique match ignoring subject prefixes."""
        if label in self.labels:
            return self.labels.index(label)
        hits = [i for i, x in enumerate(self.labels) if _strip_prefix(x) == label]
        if len(hits) == 1:
            return hits[0]
        if hits:
            options = [self.labels[i] for i in hits]
            msg = f"marker {label!r} is ambiguous in {self.source or 'trajectories'}: {options}"
            raise ValidationError(msg)
        msg = (
            f"marker {label!r} is not in {self.source or 'trajectories'}; "
            f"available: {list(self.labels)}"
        )
        raise ValidationError(msg)

    def marker(self, label: str) -> FloatArray:
        """(F, 3) read-only positions of one marker in metres (see :meth:`index`)."""
        out: FloatArray = self.positions_m[:, self.index(label), :]
        return out

    def select(self, labels: Iterable[str]) -> MarkerTrajectories:
        """A new record holding only ``labels``, in that order (see :meth:`index` for matching)."""
        cols = [self.index(x) for x in labels]
        return MarkerTrajectories(
            labels=tuple(self.labels[i] for i in cols),
            rate_hz=self.rate_hz,
            positions_m=self.positions_m[:, cols, :],
            residuals_m=self.residuals_m[:, cols],
            first_frame=self.first_frame,
            source_unit=self.source_unit,
            source=self.source,
            metadata=self.metadata,
        )

    def strip_subject_prefixes(self) -> MarkerTrajectories:
        """A new record whose labels lose their ``Subject:`` prefix.

        Raises:
            ValidationError: two subjects share a marker name, so stripping would merge them.
        """
        stripped = tuple(_strip_prefix(x) for x in self.labels)
        if len(set(stripped)) != len(stripped):
            dupes = sorted({x for x in stripped if stripped.count(x) > 1})
            msg = (
                f"cannot strip subject prefixes in {self.source or 'trajectories'}: "
                f"{dupes} occur for more than one subject; select one subject's markers first"
            )
            raise ValidationError(msg)
        return MarkerTrajectories(
            labels=stripped,
            rate_hz=self.rate_hz,
            positions_m=self.positions_m,
            residuals_m=self.residuals_m,
            first_frame=self.first_frame,
            source_unit=self.source_unit,
            source=self.source,
            metadata=self.metadata,
        )


@dataclass(frozen=True, slots=True, eq=False)
class AnalogChannels:
    """The analog channels of one trial, in physical units, sampled on the Vicon clock.

    Attributes:
        labels: channel labels, in column order (C); unique.
        rate_hz: sampling rate (Hz): an integer multiple of ``point_rate_hz``.
        values: (S, C) float64 samples in the channels' units (ANALOG:UNITS), S = frames ×
            samples per frame.
        units: unit of each channel (C), e.g. ``"V"``; ``""`` when the file does not say.
        point_rate_hz: the trial's frame rate (POINT:RATE, Hz).
        first_frame: the capture's frame number of the trial's first frame (1-based, as
            :attr:`MarkerTrajectories.first_frame`); sample 0 is taken with that frame.
        source: the path read ("" when built in memory).
        metadata: read-only strings about the source (``reader``, ``processor``…).

    Sample ``s`` is at ``(first_frame − 1)/point_rate + s/rate`` s of the Vicon clock (the
    first sample of a frame is taken with the frame). Arrays are copied and read-only.
    """

    labels: tuple[str, ...]
    rate_hz: float
    values: FloatArray = field(repr=False)
    units: tuple[str, ...] = ()
    point_rate_hz: float = 0.0
    first_frame: int = 1
    source: str = ""
    metadata: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        labels = _unique_labels(self.labels, "analog")
        rate = _positive_rate(self.rate_hz)
        point_rate = float(self.point_rate_hz) or rate
        spf = rate / point_rate if point_rate > 0 else math.nan
        if not (math.isfinite(spf) and spf >= 1 and abs(spf - round(spf)) < 1e-6):
            msg = (
                f"the analog rate ({rate:g} Hz) must be an integer multiple of the frame rate "
                f"({self.point_rate_hz!r} Hz)"
            )
            raise ValidationError(msg)
        values = np.array(self.values, dtype=np.float64, copy=True)
        if values.ndim != 2 or values.shape[1] != len(labels):
            msg = (
                "values has the wrong shape\n"
                f"  expected: (S, {len(labels)})\n  actual:   {values.shape}"
            )
            raise ValidationError(msg)
        units = tuple(str(u) for u in self.units) or ("",) * len(labels)
        if len(units) != len(labels):
            msg = f"{len(units)} units for {len(labels)} analog channels"
            raise ValidationError(msg)
        _freeze_provenance(self)
        values.setflags(write=False)
        object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "rate_hz", rate)
        object.__setattr__(self, "point_rate_hz", point_rate)
        object.__setattr__(self, "values", values)
        object.__setattr__(self, "units", units)

    @property
    def n_channels(self) -> int:
        """Number of channels C."""
        return len(self.labels)

    @property
    def n_samples(self) -> int:
        """Samples per channel S."""
        return int(self.values.shape[0])

    @property
    def samples_per_frame(self) -> int:
        """Analog samples per trajectory frame (ANALOG:RATE / POINT:RATE)."""
        return round(self.rate_hz / self.point_rate_hz)

    @property
    def times_s(self) -> FloatArray:
        """(S,) Vicon-clock time (s) of every sample (see the class doc)."""
        n = (self.first_frame - 1) * self.samples_per_frame + np.arange(self.n_samples)
        t: FloatArray = n.astype(np.float64) / self.rate_hz
        return t

    def index(self, label: str) -> int:
        """Column of ``label``: exact match, else a unique case-insensitive match.

        Raises:
            ValidationError: no such channel (the message lists the channels), or ambiguous.
        """
        if label in self.labels:
            return self.labels.index(label)
        hits = [i for i, x in enumerate(self.labels) if x.casefold() == label.casefold()]
        if len(hits) == 1:
            return hits[0]
        where = self.source or "analog channels"
        if hits:
            options = [self.labels[i] for i in hits]
            msg = f"analog channel {label!r} is ambiguous in {where}: {options}"
            raise ValidationError(msg)
        shown = list(self.labels[:12]) + (["..."] if self.n_channels > 12 else [])
        msg = f"no analog channel {label!r} in {where}; channels: {shown or 'none'}"
        raise ValidationError(msg)

    def channel(self, label: str) -> FloatArray:
        """(S,) read-only samples of one channel (see :meth:`index`)."""
        out: FloatArray = self.values[:, self.index(label)]
        return out


# --------------------------------------------------------------------------------------------
# Units and labels
# --------------------------------------------------------------------------------------------


def parse_length_unit(text: str) -> LengthUnit | None:
    """Normalise a unit spelling to ``"mm"``, ``"cm"`` or ``"m"``; ``None`` when unknown.

    Case, surrounding spaces/NULs and a trailing dot are ignored. Full spellings (``millimetres``,
    ``meters``…) and their truncations of 3+ letters (``mete``, ``millim``) are accepted, since
    C3D string fields are fixed width and some writers cut them.
    """
    t = text.strip().strip("\x00").strip().lower().rstrip(".")
    for unit, spellings in _UNIT_SPELLINGS.items():
        if t in spellings:
            return unit
    if len(t) >= 3:
        for unit, spellings in _UNIT_SPELLINGS.items():
            if any(s.startswith(t) for s in spellings[1:]):
                return unit
    return None


def _resolve_unit(
    raw: str | None, override: str | None, *, path: str, where: str
) -> tuple[LengthUnit, str]:
    """Return (unit, raw spelling) from the file's unit field and the caller's override."""
    file_unit = parse_length_unit(raw) if raw is not None else None
    if override is not None:
        unit = parse_length_unit(override)
        if unit is None:
            msg = f"unit={override!r} is not a length unit; pass 'mm', 'cm' or 'm'"
            raise ValidationError(msg)
        if file_unit is not None and file_unit != unit:
            _log.warning(
                "%s: %s says %r but unit=%r was passed; using %r", path, where, raw, override, unit
            )
        return unit, "" if raw is None else raw
    if file_unit is None:
        what = "is missing" if raw is None else f"is {raw!r}, which is not a known length unit"
        msg = (
            f"{path}: {where} {what}, so the coordinates' unit is unknown; "
            "pass unit='mm', 'cm' or 'm' (CLI: --unit) if you know it"
        )
        raise ViconFileError(msg, path=path)
    return file_unit, raw or ""


def _strip_prefix(label: str) -> str:
    return label.rsplit(":", 1)[-1]


def _classify(label: str, model_outputs: frozenset[str], *, check_suffix: bool) -> str:
    """Return 'marker', 'unlabeled' or 'virtual' for a trajectory label."""
    bare = _strip_prefix(label)
    if _UNLABELED_RE.match(bare):
        return "unlabeled"
    if label in model_outputs or bare in model_outputs:
        return "virtual"
    if _BONE_RE.match(bare) or bare in _CENTRE_OF_MASS:
        return "virtual"
    if check_suffix and _MODEL_SUFFIX_RE.search(bare):
        return "virtual"
    return "marker"


def _keep_columns(
    labels: Sequence[str],
    model_outputs: frozenset[str],
    *,
    keep_virtual: bool,
    keep_unlabeled: bool,
    check_suffix: bool,
) -> list[int]:
    keep: list[int] = []
    for i, label in enumerate(labels):
        kind = _classify(label, model_outputs, check_suffix=check_suffix)
        if (
            kind == "marker"
            or (kind == "virtual" and keep_virtual)
            or (kind == "unlabeled" and keep_unlabeled)
        ):
            keep.append(i)
    return keep


def _missing_mask(xyz: FloatArray, residual: FloatArray) -> BoolArray:
    """(F, N) True where a sample is missing: NaN coordinate, residual < 0, or exactly (0, 0, 0)."""
    with np.errstate(invalid="ignore"):
        mask: BoolArray = np.isnan(xyz).any(axis=-1) | (residual < 0) | (xyz == 0.0).all(axis=-1)
    return mask


def _build(
    *,
    labels: Sequence[str],
    xyz: FloatArray,
    residual: FloatArray,
    rate_hz: float,
    first_frame: int,
    unit: LengthUnit,
    source: str,
    metadata: Mapping[str, str],
    model_outputs: frozenset[str],
    keep_virtual: bool,
    keep_unlabeled: bool,
    strip_subject_prefix: bool,
    check_suffix: bool,
) -> MarkerTrajectories:
    """Filter columns, apply the gap rule, convert to metres and build the record."""
    cols = _keep_columns(
        labels,
        model_outputs,
        keep_virtual=keep_virtual,
        keep_unlabeled=keep_unlabeled,
        check_suffix=check_suffix,
    )
    dropped = len(labels) - len(cols)
    if dropped:
        _log.debug("%s: dropped %d model-output/virtual/unlabelled trajectories", source, dropped)
    sel_xyz = np.asarray(xyz, dtype=np.float64)[:, cols, :]
    sel_res = np.asarray(residual, dtype=np.float64)[:, cols]
    missing = _missing_mask(sel_xyz, sel_res)
    scale = _METRES_PER_UNIT[unit]
    pos = sel_xyz * scale
    res = sel_res * scale
    pos[missing] = np.nan
    res[missing] = np.nan
    kept = [labels[i] for i in cols]
    if len(set(kept)) != len(kept):
        dupes = sorted({x for x in kept if kept.count(x) > 1})
        msg = f"{source}: trajectory labels {dupes} occur more than once; rename them in Nexus"
        raise ViconFileError(msg, path=source)
    traj = MarkerTrajectories(
        labels=tuple(kept),
        rate_hz=rate_hz,
        positions_m=pos,
        residuals_m=res,
        first_frame=first_frame,
        source_unit=unit,
        source=source,
        metadata=metadata,
    )
    if strip_subject_prefix:
        try:
            traj = traj.strip_subject_prefixes()
        except ValidationError as err:
            raise ViconFileError(str(err), path=source) from err
    return traj


# --------------------------------------------------------------------------------------------
# C3D structure (pure Python, bounds-checked)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Param:
    type_code: int  # -1 char, 1 byte, 2 int16, 4 float
    dims: tuple[int, ...]
    data: bytes


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
        return [float(x) for x in _dec_to_ieee(np.frombuffer(raw, dtype=np.uint8, count=4 * n))]
    return [float(x) for x in np.frombuffer(raw, dtype="<f4", count=n)]


def _dec_to_ieee(raw: npt.NDArray[np.uint8]) -> npt.NDArray[np.float32]:
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
            params.append((gid, name, _Param(type_code, dims, w.buf[data_start:data_end])))
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
    return _validate_bytes(buf, p)


def _validate_bytes(buf: bytes, p: str) -> C3DLayout:
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
class _AnalogLayout:
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


def _analog_layout(buf: bytes, layout: C3DLayout) -> _AnalogLayout:
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
        return _AnalogLayout(0, max(spf, 1), rate, (), (), empty, empty, 1.0, False)
    channels = words // spf  # _validate_bytes checked that spf divides words
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
    return _AnalogLayout(
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


# --------------------------------------------------------------------------------------------
# C3D data decoding (backends) and isolation
# --------------------------------------------------------------------------------------------


def _decode_point_block(layout: C3DLayout, buf: bytes) -> tuple[FloatArray, FloatArray]:
    """Decode the POINT block with numpy: (F, N, 3) coordinates and (F, N) residuals (source unit).

    Residuals follow the c3d.org text: negative fourth word → −1 (gap), else low byte × |SCALE|.
    """
    n, f = layout.n_points, layout.n_frames
    start, fb = layout.data_offset, layout.frame_bytes
    raw = buf[start : start + f * fb]
    if layout.is_float:
        if layout.processor == "dec":
            vals = _dec_to_ieee(np.frombuffer(raw, dtype=np.uint8)).astype(np.float64)
        else:
            end = ">" if layout.processor == "sgi" else "<"
            vals = np.frombuffer(raw, dtype=end + "f4").astype(np.float64)
        rec = vals.reshape(f, fb // 4)[:, : 4 * n].reshape(f, n, 4)
        xyz = rec[..., :3].copy()
        with np.errstate(invalid="ignore"):
            fourth = np.where(np.isfinite(rec[..., 3]), rec[..., 3], -1.0)
        word = fourth.astype(np.int64)
    else:
        end = ">" if layout.processor == "sgi" else "<"
        ints = np.frombuffer(raw, dtype=end + "i2").reshape(f, fb // 2)[:, : 4 * n]
        rec_i = ints.reshape(f, n, 4).astype(np.int64)
        xyz = rec_i[..., :3].astype(np.float64) * layout.scale
        word = rec_i[..., 3]
    residual = np.where(word < 0, -1.0, (word & 0xFF) * abs(layout.scale)).astype(np.float64)
    return xyz, residual


def _decode_analog_block(layout: C3DLayout, alay: _AnalogLayout, buf: bytes) -> FloatArray:
    """The stored analog values with numpy: (F·samples per frame, C), before any scaling."""
    f, n, c, spf = layout.n_frames, layout.n_points, alay.n_channels, alay.samples_per_frame
    start, fb = layout.data_offset, layout.frame_bytes
    raw = buf[start : start + f * fb]
    end = ">" if layout.processor == "sgi" else "<"
    if layout.is_float:
        if layout.processor == "dec":
            vals = _dec_to_ieee(np.frombuffer(raw, dtype=np.uint8)).astype(np.float64)
        else:
            vals = np.frombuffer(raw, dtype=end + "f4").astype(np.float64)
        words = vals.reshape(f, fb // 4)
    else:
        kind = "u2" if alay.unsigned else "i2"
        words = np.frombuffer(raw, dtype=end + kind).reshape(f, fb // 2).astype(np.float64)
    out: FloatArray = words[:, 4 * n : 4 * n + spf * c].reshape(f * spf, c)
    return out


def _read_analogs_ezc3d(path: str) -> tuple[FloatArray, str]:
    import ezc3d

    c = ezc3d.c3d(path)
    a = np.asarray(c["data"]["analogs"], dtype=np.float64)  # (1, C, S), already scaled
    return np.ascontiguousarray(a[0].T), f"ezc3d {ezc3d.__version__}"


def _read_points_ezc3d(path: str) -> tuple[FloatArray, FloatArray, str]:
    import ezc3d

    c = ezc3d.c3d(path)
    pts = np.asarray(c["data"]["points"], dtype=np.float64)  # (4, N, F)
    res = np.asarray(c["data"]["meta_points"]["residuals"], dtype=np.float64)  # (1, N, F)
    xyz = np.ascontiguousarray(np.transpose(pts[:3], (2, 1, 0)))
    residual = np.ascontiguousarray(res[0].T)
    return xyz, residual, f"ezc3d {ezc3d.__version__}"


def _read_points_pyc3d(path: str) -> tuple[FloatArray, FloatArray, str]:
    import warnings

    try:
        import c3d
    except ImportError as err:
        msg = (
            f"{path}: this is an SGI/MIPS (big-endian) C3D file, which ezc3d cannot read, and the "
            "fallback reader is not installed; run `pip install c3d` or re-export the file on a PC"
        )
        raise ViconFileError(msg, path=path) from err
    frames_xyz: list[FloatArray] = []
    frames_res: list[FloatArray] = []
    with Path(path).open("rb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reader = c3d.Reader(fh)
        for _, points, _analog in reader.read_frames(copy=True, check_nan=True):
            arr = np.asarray(points, dtype=np.float64)
            frames_xyz.append(arr[:, :3])
            frames_res.append(arr[:, 3])
    version = getattr(c3d, "__version__", "")
    if not frames_xyz:
        n = 0
        return np.zeros((0, n, 3)), np.zeros((0, n)), f"py-c3d {version}".strip()
    return np.stack(frames_xyz), np.stack(frames_res), f"py-c3d {version}".strip()


_Backend = Callable[[str], tuple[FloatArray, FloatArray, str]]
_BACKENDS: dict[str, _Backend] = {
    "intel": _read_points_ezc3d,
    "dec": _read_points_ezc3d,
    "sgi": _read_points_pyc3d,
}


def _child_entry(
    processor: str, path: str, out_npz: str, kind: str = "points"
) -> int:  # pragma: no cover - child
    """Entry point of the isolated child: decode ``path`` (its points, or with ``kind`` =
    ``"analogs"`` its analog channels), save arrays to ``out_npz``."""
    try:
        if kind == "analogs":
            analogs, reader = _read_analogs_ezc3d(path)
            np.savez(out_npz, analogs=analogs, reader=np.array(reader))
        else:
            xyz, residual, reader = _BACKENDS[processor](path)
            np.savez(out_npz, xyz=xyz, residual=residual, reader=np.array(reader))
    except BaseException as err:
        sys.stderr.write(f"\n{_CHILD_ERROR_TAG}{type(err).__name__}: {err}\n")
        return _CHILD_ERROR_EXIT
    return 0


_CHILD_ERROR_TAG = "mocaprig-c3d-error: "
_CHILD_ERROR_EXIT = 3
_CHILD_CODE = (
    "import sys; from calib.vicon import _child_entry; sys.exit(_child_entry(*sys.argv[1:]))"
)


def _read_isolated(
    processor: Processor, path: str, *, timeout_s: float
) -> tuple[FloatArray, FloatArray, str]:
    """Decode the points in a child interpreter (:func:`_run_isolated`)."""
    data = _run_isolated("points", processor, path, timeout_s=timeout_s)
    return (
        np.asarray(data["xyz"], dtype=np.float64),
        np.asarray(data["residual"], dtype=np.float64),
        str(data["reader"]),
    )


def _run_isolated(
    kind: Literal["points", "analogs"], processor: Processor, path: str, *, timeout_s: float
) -> dict[str, npt.NDArray[np.generic]]:
    """Run a decoder in a child interpreter; a crash, hang or error becomes a ViconFileError.

    A fresh ``python -c`` child (not ``multiprocessing``): spawn/forkserver children re-import the
    caller's ``__main__``, which fails for stdin/REPL callers and re-runs unguarded scripts.
    Returns the arrays the child saved.
    """
    with tempfile.TemporaryDirectory(prefix="mocaprig-c3d-") as tmp:
        out_npz = str(Path(tmp) / f"{kind}.npz")
        cmd = [sys.executable, "-c", _CHILD_CODE, processor, path, out_npz, kind]
        # The child must import this very package, even when the caller runs from a source tree.
        env = dict(os.environ)
        root = str(Path(__file__).resolve().parents[1])
        env["PYTHONPATH"] = os.pathsep.join(x for x in (root, env.get("PYTHONPATH", "")) if x)
        try:
            done = subprocess.run(
                cmd,
                capture_output=True,
                timeout=timeout_s,
                check=False,
                stdin=subprocess.DEVNULL,
                env=env,
            )
        except subprocess.TimeoutExpired as err:
            msg = (
                f"{path}: the C3D reader did not finish within {timeout_s:.0f} s (killed); the "
                "file is probably malformed; re-export it from Vicon Nexus"
            )
            raise ViconFileError(msg, path=path) from err
        stderr = done.stderr.decode("utf-8", errors="replace")
        if done.returncode == _CHILD_ERROR_EXIT and _CHILD_ERROR_TAG in stderr:
            reason = stderr.rsplit(_CHILD_ERROR_TAG, 1)[1].strip()
            if reason.startswith("ViconFileError: "):
                raise ViconFileError(reason.removeprefix("ViconFileError: "), path=path)
            msg = (
                f"{path}: the C3D reader rejected the file: {reason}; re-export it from Vicon Nexus"
            )
            raise ViconFileError(msg, path=path)
        if done.returncode != 0:
            code = done.returncode
            how = f"killed by signal {-code}" if code < 0 else f"exit code {code}"
            tail = " ".join(stderr.strip().splitlines()[-2:])[-300:]
            msg = (
                f"{path}: the native C3D reader crashed on this file ({how}"
                f"{'; ' + tail if tail else ''}); the file is malformed; re-export it from Vicon "
                "Nexus or send it to the maintainers"
            )
            raise ViconFileError(msg, path=path)
        with np.load(out_npz, allow_pickle=False) as data:
            return {key: np.asarray(data[key]) for key in data.files}


def read_c3d(
    path: str | os.PathLike[str],
    *,
    unit: str | None = None,
    keep_virtual: bool = False,
    keep_unlabeled: bool = False,
    strip_subject_prefix: bool = False,
    isolate: bool = True,
) -> MarkerTrajectories:
    """Read the marker trajectories of a C3D file, in metres.

    Args:
        path: the ``.c3d`` file.
        unit: the coordinates' unit when POINT:UNITS is missing or wrong (``"mm"``, ``"cm"``,
            ``"m"``); overrides POINT:UNITS (with a warning when they disagree).
        keep_virtual: keep model outputs and virtual points (see the module docstring).
        keep_unlabeled: keep unlabelled ``*NN`` trajectories.
        strip_subject_prefix: drop ``Subject:`` from labels (fails if that merges two markers).
        isolate: run the native decoder in a fresh child interpreter so that a crash inside
            ezc3d cannot take the caller down (default True). It costs about 0.16–0.19 s per call
            (measured on 2 cores: 2 kB file 1 ms → 160 ms; the 2.25 MB Nexus file 50 ms →
            234 ms), negligible next to a calibration run; pass False for files you wrote
            yourself in tight loops. The structural check runs in-process either way (< 1 ms).

    Returns:
        The trajectories; ``metadata`` holds ``format="c3d"``, ``reader``, ``processor``,
        ``units_raw``, ``frames_source`` and the MANUFACTURER strings when present.

    Raises:
        ViconFileError: the file is malformed, truncated, hostile, or its unit is unknown.
        ValidationError: ``unit`` is not a length unit.
    """
    p = str(path)
    t0 = time.perf_counter()
    try:
        buf = Path(p).read_bytes()
    except OSError as err:
        msg = f"{p}: cannot read the file ({err.strerror or err}); check the path and permissions"
        raise ViconFileError(msg, path=p) from err
    layout = _validate_bytes(buf, p)
    length_unit, units_raw = _resolve_unit(layout.units_raw, unit, path=p, where="POINT:UNITS")
    if layout.n_points == 0 or layout.n_frames == 0:
        xyz = np.zeros((layout.n_frames, layout.n_points, 3))
        reader = "none (no point data)"
    elif isolate:
        timeout = _ISOLATE_TIMEOUT_BASE_S + _ISOLATE_TIMEOUT_PER_MB_S * layout.file_size / 1e6
        xyz, _, reader = _read_isolated(layout.processor, p, timeout_s=timeout)
    else:
        try:
            xyz, _, reader = _BACKENDS[layout.processor](p)
        except ViconFileError:
            raise
        except Exception as err:
            msg = f"{p}: the C3D reader rejected the file: {err}; re-export it from Vicon Nexus"
            raise ViconFileError(msg, path=p) from err
    if xyz.shape[1] != layout.n_points or xyz.shape[0] > layout.n_frames:
        msg = (
            f"{p}: the C3D reader returned {xyz.shape[1]} points × {xyz.shape[0]} frames but "
            f"the parameters declare {layout.n_points} × {layout.n_frames}; the file is "
            "inconsistent; re-export it"
        )
        raise ViconFileError(msg, path=p)
    # Residuals (and camera bytes) are decoded here per c3d.org: ezc3d 1.7.2 swaps the two bytes.
    np_xyz, residual = _decode_point_block(layout, buf)
    if xyz.shape[0] < layout.n_frames:
        _log.info(
            "%s: %s returned %d of %d frames (16-bit frame-count quirk); the point block is "
            "decoded with numpy",
            p,
            reader,
            xyz.shape[0],
            layout.n_frames,
        )
        xyz = np_xyz
        reader = f"{reader} + numpy (frames beyond 65535)"
    meta = {
        "format": "c3d",
        "reader": reader,
        "processor": layout.processor,
        "units_raw": units_raw,
        "frames_source": layout.frames_source,
    }
    for key, name in (
        ("MANUFACTURER:COMPANY", "manufacturer"),
        ("MANUFACTURER:SOFTWARE", "software"),
        ("MANUFACTURER:VERSION_LABEL", "software_version"),
        ("SUBJECTS:NAMES", "subjects"),
    ):
        if key in layout.strings:
            meta[name] = layout.strings[key]
    traj = _build(
        labels=layout.labels,
        xyz=xyz,
        residual=residual,
        rate_hz=layout.rate_hz,
        first_frame=layout.first_frame,
        unit=length_unit,
        source=p,
        metadata=meta,
        model_outputs=layout.model_outputs,
        keep_virtual=keep_virtual,
        keep_unlabeled=keep_unlabeled,
        strip_subject_prefix=strip_subject_prefix,
        check_suffix=False,
    )
    _log.debug("%s: read %s in %.3f s", p, traj, time.perf_counter() - t0)
    return traj


def read_c3d_analogs(path: str | os.PathLike[str], *, isolate: bool = True) -> AnalogChannels:
    """Read the analog channels of a C3D file, in physical units (see the module docstring).

    Args:
        path: the ``.c3d`` file.
        isolate: decode with ezc3d in a fresh child interpreter (as :func:`read_c3d`; default).

    Returns:
        The channels (none when the file has no analog data); ``metadata`` holds ``reader``,
        ``processor`` and the raw ``gen_scale``.

    Raises:
        ViconFileError: the file is malformed or truncated, its ANALOG parameters are missing or
            disagree with the header (USED, RATE, SCALE, OFFSET, GEN_SCALE), or the decoder
            crashed or rejected it.
    """
    p = str(path)
    try:
        buf = Path(p).read_bytes()
    except OSError as err:
        msg = f"{p}: cannot read the file ({err.strerror or err}); check the path and permissions"
        raise ViconFileError(msg, path=p) from err
    layout = _validate_bytes(buf, p)
    alay = _analog_layout(buf, layout)
    n_samples = layout.n_frames * alay.samples_per_frame
    k = alay.scale * alay.gen_scale
    if alay.n_channels == 0 or n_samples == 0:
        values = np.zeros((n_samples, alay.n_channels))
        reader = "none (no analog data)"
    else:
        raw = _decode_analog_block(layout, alay, buf)
        values = (raw - alay.offset) * k
        reader = "numpy"
        if layout.is_float and layout.processor in ("intel", "dec"):
            if isolate:
                timeout = _ISOLATE_TIMEOUT_BASE_S + _ISOLATE_TIMEOUT_PER_MB_S * len(buf) / 1e6
                data = _run_isolated("analogs", layout.processor, p, timeout_s=timeout)
                ez = np.asarray(data["analogs"], dtype=np.float64)
                ez_reader = str(data["reader"])
            else:
                try:
                    ez, ez_reader = _read_analogs_ezc3d(p)
                except Exception as err:
                    msg = f"{p}: the C3D reader rejected the file: {err}; re-export it"
                    raise ViconFileError(msg, path=p) from err
            if ez.shape == values.shape:
                # ezc3d applies |OFFSET|; c3d.org's OFFSET is signed.
                values = ez + (np.abs(alay.offset) - alay.offset) * k
                reader = ez_reader
            elif ez.ndim == 2 and ez.shape[1] == alay.n_channels and ez.shape[0] < n_samples:
                _log.info(
                    "%s: %s returned %d of %d analog samples; decoded with numpy",
                    p,
                    ez_reader,
                    ez.shape[0],
                    n_samples,
                )
            else:
                msg = (
                    f"{p}: the C3D reader returned analogs of shape {ez.shape} but the "
                    f"parameters declare {values.shape}; the file is inconsistent; re-export it"
                )
                raise ViconFileError(msg, path=p)
    return AnalogChannels(
        labels=alay.labels,
        rate_hz=alay.rate_hz,
        values=values,
        units=alay.units,
        point_rate_hz=layout.rate_hz,
        first_frame=layout.first_frame,
        source=p,
        metadata={
            "reader": reader,
            "processor": layout.processor,
            "gen_scale": repr(alay.gen_scale),
            "format": "unsigned" if alay.unsigned else "signed",
        },
    )


# --------------------------------------------------------------------------------------------
# Nexus CSV
# --------------------------------------------------------------------------------------------


def _is_blank(row: Sequence[str]) -> bool:
    return all(not c.strip() for c in row)


def _to_float(cell: str) -> float:
    c = cell.strip()
    return math.nan if not c else float(c)


def read_nexus_csv(
    path: str | os.PathLike[str],
    *,
    unit: str | None = None,
    keep_virtual: bool = False,
    keep_unlabeled: bool = False,
    strip_subject_prefix: bool = False,
) -> MarkerTrajectories:
    """Read the ``Trajectories`` section of a Vicon Nexus (or Workstation) CSV export, in metres.

    Layout, found by line role rather than line number: a section line ``Trajectories`` (any case),
    a rate line (``100`` or ``100,Hz``), a names row with ``Subject:marker`` at each marker's X
    column, a column row (``Frame,Sub Frame,X,Y,Z,…`` or Workstation ``Field #,X,Y,Z,…``), an
    optional units row (``mm``…), then data rows until a blank line, the next section or the end.
    Empty cells are gaps. Without a units row (Workstation), ``unit=`` is required. Residuals are
    not exported, so ``residuals_m`` is NaN.

    Raises:
        ViconFileError: no Trajectories section, a malformed header, a bad number or frame order,
            or an unknown unit.
    """
    p = str(path)
    try:
        text = Path(p).read_text(encoding="utf-8-sig", errors="replace")
    except OSError as err:
        msg = f"{p}: cannot read the file ({err.strerror or err}); check the path and permissions"
        raise ViconFileError(msg, path=p) from err
    rows = list(csv.reader(io.StringIO(text)))

    def fail(what: str, line: int | None = None) -> ViconFileError:
        where = f" (line {line + 1})" if line is not None else ""
        return ViconFileError(
            f"{p}: not a readable Nexus CSV trajectories export{where}: {what}; export "
            "Trajectories from Nexus as CSV (File > Export > CSV) and try again",
            path=p,
        )

    sec = next(
        (
            i
            for i, r in enumerate(rows)
            if r and r[0].strip().lower() == "trajectories" and _is_blank(r[1:])
        ),
        None,
    )
    if sec is None:
        found = sorted(
            {
                r[0].strip()
                for i, r in enumerate(rows)
                if r
                and r[0].strip()
                and _is_blank(r[1:])
                and (i == 0 or _is_blank(rows[i - 1]))
                and not r[0].strip().replace(".", "").isdigit()
            }
        )
        shown = [x[:40] for x in found[:5]] + (["..."] if len(found) > 5 else [])
        msg = f"there is no Trajectories section (sections found: {shown or 'none'})"
        raise fail(msg)
    i = sec + 1
    if i >= len(rows) or not rows[i] or not rows[i][0].strip():
        msg = "the rate line after 'Trajectories' is missing"
        raise fail(msg, i)
    try:
        rate = float(rows[i][0])
    except ValueError as err:
        msg = f"the rate line reads {rows[i][0]!r}, not a number"
        raise fail(msg, i) from err
    if not (math.isfinite(rate) and rate > 0):
        msg = f"the rate is {rate}, not a positive number"
        raise fail(msg, i)
    names_i, cols_i = i + 1, i + 2
    if cols_i >= len(rows):
        msg = "the names and column rows are missing"
        raise fail(msg, names_i)
    names, cols = rows[names_i], rows[cols_i]
    head = cols[0].strip().lower() if cols else ""
    if head not in ("frame", "field #", "field#", "field"):
        msg = f"expected a 'Frame' or 'Field #' column row, found {cols[:3]!r}"
        raise fail(msg, cols_i)
    has_subframe = len(cols) > 1 and cols[1].strip().lower() == "sub frame"
    labels: list[str] = []
    xcols: list[int] = []
    for c, role in enumerate(cols):
        if role.strip().upper() != "X":
            continue
        ok = c + 2 < len(cols) and [x.strip().upper() for x in cols[c + 1 : c + 3]] == ["Y", "Z"]
        name = names[c].strip() if c < len(names) else ""
        if not ok or not name:
            msg = f"column {c + 1} starts an X,Y,Z triple without a marker name"
            raise fail(msg, cols_i)
        labels.append(name)
        xcols.append(c)
    if not labels:
        msg = "the column row holds no X,Y,Z triples"
        raise fail(msg, cols_i)
    data_i = cols_i + 1
    units_raw: str | None = None
    if data_i < len(rows) and rows[data_i] and not rows[data_i][0].strip():
        unit_cells = {
            rows[data_i][c + k].strip()
            for c in xcols
            for k in range(3)
            if c + k < len(rows[data_i])
        }
        unit_cells.discard("")
        if len(unit_cells) > 1:
            msg = f"the units row mixes units {sorted(unit_cells)}"
            raise fail(msg, data_i)
        units_raw = unit_cells.pop() if unit_cells else None
        data_i += 1
    length_unit, units_raw_s = _resolve_unit(units_raw, unit, path=p, where="the units row")

    frames: list[int] = []
    values: list[list[float]] = []
    need = xcols[-1] + 3
    for j in range(data_i, len(rows)):
        row = rows[j]
        if _is_blank(row):
            break
        first = row[0].strip()
        try:
            frame = int(float(first))
        except ValueError:
            break  # next section header
        if has_subframe and len(row) > 1 and row[1].strip() not in ("", "0"):
            msg = f"sub frame {row[1].strip()!r} in a trajectories section"
            raise fail(msg, j)
        cells = row + [""] * (need - len(row))
        try:
            values.append([_to_float(cells[c + k]) for c in xcols for k in range(3)])
        except ValueError as err:
            msg = f"a cell is not a number ({err})"
            raise fail(msg, j) from err
        if frames and frame <= frames[-1]:
            msg = f"frame {frame} follows frame {frames[-1]}"
            raise fail(msg, j)
        frames.append(frame)
    if not frames:
        msg = "the trajectories section holds no data rows"
        raise fail(msg, data_i)
    first_frame = frames[0]
    n_frames = frames[-1] - first_frame + 1
    xyz = np.full((n_frames, len(labels), 3), np.nan)
    idx = np.asarray(frames) - first_frame
    xyz[idx] = np.asarray(values, dtype=np.float64).reshape(len(frames), len(labels), 3)
    if len(frames) != n_frames:
        _log.warning("%s: %d frame rows are absent; treated as gaps", p, n_frames - len(frames))
    residual = np.full((n_frames, len(labels)), np.nan)
    style = "nexus" if has_subframe else "workstation"
    return _build(
        labels=labels,
        xyz=xyz,
        residual=residual,
        rate_hz=rate,
        first_frame=first_frame,
        unit=length_unit,
        source=p,
        metadata={"format": f"{style}-csv", "reader": "mocaprig csv", "units_raw": units_raw_s},
        model_outputs=frozenset(),
        keep_virtual=keep_virtual,
        keep_unlabeled=keep_unlabeled,
        strip_subject_prefix=strip_subject_prefix,
        check_suffix=True,
    )


def read_trajectories(
    path: str | os.PathLike[str],
    *,
    unit: str | None = None,
    keep_virtual: bool = False,
    keep_unlabeled: bool = False,
    strip_subject_prefix: bool = False,
    isolate: bool = True,
) -> MarkerTrajectories:
    """Read a C3D or Nexus CSV file, chosen from its first bytes (C3D key byte 0x50).

    Options are those of :func:`read_c3d` (``isolate`` only applies to C3D).

    Raises:
        ViconFileError: unreadable or malformed file.
    """
    p = str(path)
    try:
        with Path(p).open("rb") as fh:
            head = fh.read(2)
    except OSError as err:
        msg = f"{p}: cannot read the file ({err.strerror or err}); check the path and permissions"
        raise ViconFileError(msg, path=p) from err
    if len(head) == 2 and head[1] == 0x50 and (p.lower().endswith(".c3d") or head[0] < 0x20):
        return read_c3d(
            p,
            unit=unit,
            keep_virtual=keep_virtual,
            keep_unlabeled=keep_unlabeled,
            strip_subject_prefix=strip_subject_prefix,
            isolate=isolate,
        )
    return read_nexus_csv(
        p,
        unit=unit,
        keep_virtual=keep_virtual,
        keep_unlabeled=keep_unlabeled,
        strip_subject_prefix=strip_subject_prefix,
    )


# --------------------------------------------------------------------------------------------
# Writer
# --------------------------------------------------------------------------------------------


def _rewrite_point_words(path: Path, words: FloatArray) -> None:
    """Overwrite the fourth word of every (frame, point) of an Intel float C3D with ``words``."""
    layout = validate_c3d(path)
    n_frames, n_points = words.shape
    if layout.n_frames != n_frames or layout.n_points != n_points or not layout.is_float:
        msg = (
            f"{path}: ezc3d wrote {layout.n_points} points × {layout.n_frames} frames, "
            f"expected {n_points} × {n_frames}"
        )
        raise ViconFileError(msg, path=path)
    size = n_frames * layout.frame_bytes
    with path.open("r+b") as fh:
        fh.seek(layout.data_offset)
        vals = np.frombuffer(fh.read(size), dtype="<f4").reshape(n_frames, -1).copy()
        vals[:, 3 : 4 * n_points : 4] = words
        fh.seek(layout.data_offset)
        fh.write(vals.astype("<f4").tobytes())


def write_c3d(
    path: str | os.PathLike[str],
    trajectories: MarkerTrajectories,
    *,
    unit: Literal["mm", "m"] = "mm",
    overwrite: bool = False,
    analogs: AnalogChannels | None = None,
) -> Path:
    """Write trajectories (and optionally analog channels) to an Intel, float-format C3D file
    with ezc3d.

    The file has POINT:UNITS ``unit``, POINT:RATE, POINT:LABELS, POINT:SCALE = −0.01 mm (residual
    resolution 0.01 mm, maximum 2.55 mm; larger residuals are clipped), gaps as (0, 0, 0) with
    residual −1, TRIAL:ACTUAL_START/END_FIELD and the header first frame from ``first_frame``, and
    MANUFACTURER:COMPANY/SOFTWARE = ``mocaprig``. With ``analogs``: ANALOG:RATE, LABELS, UNITS,
    SCALE 1, OFFSET 0, GEN_SCALE 1 and the samples (float32). The file is written beside
    ``path`` and moved into place, so a failed write leaves nothing behind.

    Returns:
        The path written.

    Raises:
        ViconFileError: ``path`` exists and ``overwrite`` is False, or the write failed.
        ValidationError: ``unit`` is not ``"mm"`` or ``"m"``; ``analogs`` do not fit the
            trajectories (frame rate, first frame, samples per frame × frames).
    """
    if unit not in ("mm", "m"):
        msg = f"unit must be 'mm' or 'm', got {unit!r}"
        raise ValidationError(msg)
    if analogs is not None and analogs.n_channels:
        a, tr = analogs, trajectories
        if (
            a.point_rate_hz != tr.rate_hz
            or a.first_frame != tr.first_frame
            or a.n_samples != tr.n_frames * a.samples_per_frame
        ):
            msg = (
                f"analogs do not fit the trajectories: {a.n_samples} samples at {a.rate_hz:g} Hz "
                f"for frames from {a.first_frame} at {a.point_rate_hz:g} Hz, but the "
                f"trajectories have {tr.n_frames} frames from {tr.first_frame} at "
                f"{tr.rate_hz:g} Hz (need {tr.n_frames * a.samples_per_frame} samples)"
            )
            raise ValidationError(msg)
    out = Path(path)
    if out.exists() and not overwrite:
        msg = f"{out}: the file exists; pass overwrite=True to replace it, or choose another path"
        raise ViconFileError(msg, path=out)
    import ezc3d
    from ezc3d import ezc3d as ezc3d_core

    from mocaprig import __version__

    t = trajectories
    per_m = 1.0 / _METRES_PER_UNIT[unit]
    scale = 0.01 * 1e-3 * per_m  # 0.01 mm in the file's unit
    valid = t.valid
    pts = np.zeros((4, t.n_markers, t.n_frames))
    pts[3] = 1.0
    coords = np.where(valid[..., None], t.positions_m * per_m, np.nan)
    pts[:3] = np.transpose(coords, (2, 1, 0))
    res_file = np.where(np.isnan(t.residuals_m), 0.0, t.residuals_m * per_m)
    max_res = 255 * scale
    if np.any(res_file > max_res):
        _log.warning("%s: residuals above %.2f mm clipped", out, max_res / per_m * 1e3)
    res_file = np.clip(res_file, 0.0, max_res)
    # c3d.org layout of the fourth word (a float holding an integer): camera byte high (0 here),
    # residual / |SCALE| low; -1 for a gap. ezc3d 1.7.2 swaps the bytes, so the words are
    # rewritten after ezc3d has written the file.
    words = np.where(valid, np.rint(res_file / scale), -1.0)
    res_file = np.where(valid, res_file, -1.0)
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [t.rate_hz]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(t.labels)
    c["parameters"]["POINT"]["UNITS"]["value"] = [unit]
    c["parameters"]["POINT"]["SCALE"]["value"] = [-scale]
    c["data"]["points"] = pts
    c["data"]["meta_points"] = {"residuals": res_file.T[None, :, :]}
    c["header"]["points"]["first_frame"] = max(t.first_frame - 1, 0)
    if analogs is not None and analogs.n_channels:
        c["parameters"]["ANALOG"]["RATE"]["value"] = [analogs.rate_hz]
        c["parameters"]["ANALOG"]["LABELS"]["value"] = tuple(analogs.labels)
        c["parameters"]["ANALOG"]["UNITS"]["value"] = tuple(analogs.units)
        c["parameters"]["ANALOG"]["SCALE"]["value"] = [1.0] * analogs.n_channels
        c["parameters"]["ANALOG"]["GEN_SCALE"]["value"] = [1.0]
        c["data"]["analogs"] = np.ascontiguousarray(analogs.values.T[None, :, :])
    last = t.first_frame + t.n_frames - 1
    c.add_parameter(
        "TRIAL",
        "ACTUAL_START_FIELD",
        ezc3d_core.VecInt([t.first_frame % 65536, t.first_frame // 65536]),
    )
    c.add_parameter("TRIAL", "ACTUAL_END_FIELD", ezc3d_core.VecInt([last % 65536, last // 65536]))
    c.add_parameter("MANUFACTURER", "COMPANY", ["mocaprig"])
    c.add_parameter("MANUFACTURER", "SOFTWARE", ["mocaprig"])
    c.add_parameter("MANUFACTURER", "VERSION_LABEL", [__version__])
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp.c3d")  # ezc3d appends .c3d otherwise
    try:
        c.write(str(tmp))
        # ezc3d leaves the header scale at -1 whatever POINT:SCALE says; make them agree.
        with tmp.open("r+b") as fh:
            fh.seek(12)
            fh.write(struct.pack("<f", -scale))
        _rewrite_point_words(tmp, words)
        if out.exists() and not overwrite:
            msg = f"{out}: the file appeared while writing; pass overwrite=True to replace it"
            raise ViconFileError(msg, path=out)
        tmp.replace(out)
    except ViconFileError:
        raise
    except Exception as err:
        msg = f"{out}: writing the C3D file failed ({err}); check the folder and free space"
        raise ViconFileError(msg, path=out) from err
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()
    _log.info(
        "wrote %s (%d markers x %d frames, %s; %d analog channels)",
        out,
        t.n_markers,
        t.n_frames,
        unit,
        0 if analogs is None else analogs.n_channels,
    )
    return out
