"""The subject file: one subject's calibration (:class:`~.solve.SubjectCalibration`) on disk.

What a marker-based system keeps of an actor between sessions (Vicon's subject, the ``.vsk``
made from a range-of-motion trial), for DeMoCap's skeleton solve: the segment lengths, the
girth, and where each marker sits on its segment. ``mocaprig democap subject`` makes one from
a recording of the actor (:func:`~.replay.fit_subject`); ``democap run --subject`` and
``democap live --solve --subject`` solve every instant with it
(:class:`~.infer.DemocapPredictor` ``subject=``).

JSON, so that a person can read it and any tool can open it (format version 1)::

    {
      "format": "mocaprig-democap-subject",
      "format_version": 1,
      "source": "session.mcap: 40 of 300 instants",
      "frames": 40,
      "standing_height_m": 1.7712,          # floor to head top, from the lengths
      "scale": 1.0121, "girth": 0.9987,     # h and g of the body model (docs/democap.md)
      "segment_lengths_m": {"ankle_height_m": 0.0702, ...},   # every BodyShape length
      "marker_offsets_mm": {"LFHD": [0.4, -1.2, 3.0], ...}    # segment frame, all 53
    }

The solve reads ``scale``, ``girth``, ``segment_lengths_m`` and ``marker_offsets_mm``;
``standing_height_m`` is written for people and checked on reading (a length edited by hand
without it is refused rather than half-applied).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Final

import numpy as np

from mocaprig.errors import CalibrationError, ValidationError
from mocaprig.process.body import MARKER_NAMES
from mocaprig.process.democap.solve import SubjectCalibration

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "check_subject_path",
    "load_subject",
    "save_subject",
    "subject_document",
]

#: The ``format`` field of a subject file.
FORMAT: Final = "mocaprig-democap-subject"
#: The version this code writes and reads.
FORMAT_VERSION: Final = 1
#: How far the written standing height may be from the lengths' (m): the file's rounding.
_HEIGHT_TOLERANCE_M = 1e-4


def subject_document(subject: SubjectCalibration, *, source: str = "") -> dict[str, Any]:
    """The subject file's JSON object (module doc)."""
    offsets_mm = subject.marker_offsets_m * 1e3
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "source": str(source),
        "frames": int(subject.frames),
        "standing_height_m": subject.standing_height_m,
        "scale": subject.scale,
        "girth": subject.girth,
        "segment_lengths_m": subject.segment_lengths_m,
        "marker_offsets_mm": {
            name: [float(v) for v in offsets_mm[i]] for i, name in enumerate(MARKER_NAMES)
        },
    }


def check_subject_path(path: str | Path, *, overwrite: bool) -> Path:
    """``path`` as a subject file may be written there (before the work that makes it).

    Raises:
        CalibrationError: not ``.json``, or it exists and ``overwrite`` is False.
    """
    p = Path(path)
    if p.suffix != ".json":
        msg = f"{p}: a subject file is .json"
        raise CalibrationError(msg)
    if p.exists() and not overwrite:
        msg = f"subject file {p} exists; pass overwrite=True (--overwrite) to replace it"
        raise CalibrationError(msg)
    return p


def save_subject(
    subject: SubjectCalibration, path: str | Path, *, source: str = "", overwrite: bool = False
) -> Path:
    """Write ``subject`` as a subject file (``.json``, module doc); returns the path.

    Written beside as ``<name>.part`` and moved into place, so a crash leaves the old file or
    none, never half of one.

    Raises:
        CalibrationError: not ``.json``, the file exists and ``overwrite`` is False, or it
            cannot be written.
    """
    p = check_subject_path(path, overwrite=overwrite)
    tmp = p.with_name(p.name + ".part")
    try:
        tmp.write_text(json.dumps(subject_document(subject, source=source), indent=2) + "\n")
        tmp.replace(p)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        msg = f"subject file {p} cannot be written ({err})"
        raise CalibrationError(msg) from err
    return p


def load_subject(path: str | Path) -> SubjectCalibration:
    """Read a subject file written by :func:`save_subject` (or by hand, module doc).

    Raises:
        CalibrationError: the file is missing, not JSON, not a subject file, of another
            format version, or its values are incomplete or implausible (the message names
            the file and the field).
    """
    p = Path(path)
    remedy = "make one with `mocaprig democap subject SESSION.mcap --calib CALIB --out FILE`"
    try:
        doc = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        msg = f"subject file {p} cannot be read ({err}); {remedy}"
        raise CalibrationError(msg) from err
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        msg = f'{p} is not a subject file (no "format": {FORMAT!r}); {remedy}'
        raise CalibrationError(msg)
    if doc.get("format_version") != FORMAT_VERSION:
        msg = (
            f"subject file {p}: format_version {doc.get('format_version')!r}, this code reads "
            f"{FORMAT_VERSION}; {remedy}"
        )
        raise CalibrationError(msg)
    try:
        offsets = doc["marker_offsets_mm"]
        unknown = sorted(set(offsets) - set(MARKER_NAMES))
        missing = [m for m in MARKER_NAMES if m not in offsets]
        if unknown or missing:
            msg = f"marker_offsets_mm: missing {missing}, unknown {unknown}"
            raise ValidationError(msg)
        offsets_m = np.array([offsets[m] for m in MARKER_NAMES], dtype=np.float64) / 1e3
        subject = SubjectCalibration.from_lengths(
            scale=float(doc["scale"]),
            girth=float(doc["girth"]),
            segment_lengths_m={str(k): float(v) for k, v in doc["segment_lengths_m"].items()},
            marker_offsets_m=offsets_m,
            frames=int(doc.get("frames", 0)),
        )
        written = float(doc["standing_height_m"])
    except KeyError as err:
        msg = f"subject file {p}: field {err} is missing; {remedy}"
        raise CalibrationError(msg) from err
    except (TypeError, ValueError, AttributeError) as err:
        msg = f"subject file {p}: {err}"
        raise CalibrationError(msg) from err
    if not math.isclose(written, subject.standing_height_m, abs_tol=_HEIGHT_TOLERANCE_M):
        msg = (
            f"subject file {p}: standing_height_m {written:.4f} disagrees with its segment "
            f"lengths ({subject.standing_height_m:.4f} m); edit both or neither"
        )
        raise CalibrationError(msg)
    return subject
