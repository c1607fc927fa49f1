"""The records of the Vicon reference files: trajectories, analog channels, units, the error.

:class:`MarkerTrajectories` (labels, rate, positions in metres with NaN gaps, residuals, first
frame, source unit, read-only metadata) is what every reader of :mod:`mocaprig.calib.vicon`
returns; :class:`AnalogChannels` is what :func:`mocaprig.calib.c3d_read.read_c3d_analogs`
returns. :class:`ViconFileError` is raised for unreadable, malformed or inconsistent files, and
:func:`parse_length_unit` normalises the unit spellings found in them.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Literal, TypeAlias

import numpy as np
import numpy.typing as npt

from mocaprig.errors import CalibrationError, ValidationError

__all__ = [
    "METRES_PER_UNIT",
    "AnalogChannels",
    "BoolArray",
    "FloatArray",
    "LengthUnit",
    "MarkerTrajectories",
    "ViconFileError",
    "bare_label",
    "parse_length_unit",
]

FloatArray: TypeAlias = npt.NDArray[np.float64]
"""A float64 array (positions, residuals, samples)."""
BoolArray: TypeAlias = npt.NDArray[np.bool_]
"""A boolean array (masks of valid or missing samples)."""

LengthUnit = Literal["mm", "cm", "m"]
"""A length unit of coordinates in a source file."""

METRES_PER_UNIT: dict[str, float] = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}
"""Metres in one of each :data:`LengthUnit`."""
_UNIT_SPELLINGS: dict[LengthUnit, tuple[str, ...]] = {
    "mm": ("mm", "millimeter", "millimeters", "millimetre", "millimetres"),
    "cm": ("cm", "centimeter", "centimeters", "centimetre", "centimetres"),
    "m": ("m", "meter", "meters", "metre", "metres"),
}


class ViconFileError(CalibrationError):
    """A Vicon reference file (C3D or CSV) is unreadable, malformed or inconsistent.

    Attributes:
        path: the file, as given.
    """

    def __init__(self, message: str, *, path: str | os.PathLike[str] | None = None) -> None:
        super().__init__(message)
        self.path = None if path is None else str(path)


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
        if self.source_unit not in METRES_PER_UNIT:
            msg = f"source_unit must be one of {sorted(METRES_PER_UNIT)}, got {self.source_unit!r}"
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
        hits = [i for i, x in enumerate(self.labels) if bare_label(x) == label]
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
        stripped = tuple(bare_label(x) for x in self.labels)
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


def bare_label(label: str) -> str:
    """``label`` without its ``Subject:`` prefix."""
    return label.rsplit(":", 1)[-1]
