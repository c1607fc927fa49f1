"""From a source's decoded columns to :class:`MarkerTrajectories`: unit, kept trajectories, gaps.

Shared by the C3D and the Nexus CSV readers.

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
"""

from __future__ import annotations

import logging
import re
from collections.abc import Mapping, Sequence

import numpy as np

from mocaprig.calib.vicon_records import (
    METRES_PER_UNIT,
    BoolArray,
    FloatArray,
    LengthUnit,
    MarkerTrajectories,
    ViconFileError,
    bare_label,
    parse_length_unit,
)
from mocaprig.errors import ValidationError

__all__ = ["build_trajectories", "resolve_unit"]

_log = logging.getLogger(__name__)

_BONE_RE = re.compile(r"^(PEL|HED|TRX|CSP|SAC|[LR](FE|TI|FO|TO|CL|HU|RA|HN))[OALP]$")
_MODEL_SUFFIX_RE = re.compile(r"(Angles?|Forces?|Moments?|Powers?)$")
_CENTRE_OF_MASS = frozenset(
    {"CentreOfMass", "CentreOfMassFloor", "CenterOfMass", "CenterOfMassFloor"}
)
_UNLABELED_RE = re.compile(r"^\*\d+$")


def resolve_unit(
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


def _classify(label: str, model_outputs: frozenset[str], *, check_suffix: bool) -> str:
    """Return 'marker', 'unlabeled' or 'virtual' for a trajectory label."""
    bare = bare_label(label)
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


def build_trajectories(
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
    scale = METRES_PER_UNIT[unit]
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
