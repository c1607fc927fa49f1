"""Reading Vicon Nexus (and Workstation) "Trajectories" CSV exports (:func:`read_nexus_csv`).

The file is parsed by section and line role, never by line number, in the modern Nexus layout and
the older Workstation layout; the trajectories are filtered and converted to metres as the C3D
reader's (:mod:`mocaprig.calib.vicon_build`).
"""

from __future__ import annotations

import csv
import io
import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mocaprig.calib.vicon_build import build_trajectories, resolve_unit
from mocaprig.calib.vicon_records import MarkerTrajectories, ViconFileError
from mocaprig.errors import ValidationError

__all__ = ["read_nexus_csv"]

_log = logging.getLogger(__name__)


def _is_blank(row: Sequence[str]) -> bool:
    return all(not c.strip() for c in row)


def _to_float(cell: str) -> float:
    c = cell.strip()
    v = math.nan if not c else float(c)
    if math.isinf(v):
        msg = f"{c!r} is infinite (gaps are empty cells)"
        raise ValueError(msg)
    return v


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
    length_unit, units_raw_s = resolve_unit(units_raw, unit, path=p, where="the units row")

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
        except OverflowError as err:
            msg = f"the frame number {first!r} is not a finite number"
            raise fail(msg, j) from err
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
    if n_frames > 2 * len(frames) + 100:
        # Absent rows become gaps; this many means damaged frame numbers, not a few lost rows.
        msg = (
            f"the frame numbers run from {first_frame} to {frames[-1]} over only {len(frames)} "
            "rows; the file is damaged"
        )
        raise fail(msg)
    xyz = np.full((n_frames, len(labels), 3), np.nan)
    idx = np.asarray(frames) - first_frame
    xyz[idx] = np.asarray(values, dtype=np.float64).reshape(len(frames), len(labels), 3)
    if len(frames) != n_frames:
        _log.warning("%s: %d frame rows are absent; treated as gaps", p, n_frames - len(frames))
    residual = np.full((n_frames, len(labels)), np.nan)
    style = "nexus" if has_subframe else "workstation"
    try:
        return build_trajectories(
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
    except ValidationError as err:
        raise fail(str(err)) from err
