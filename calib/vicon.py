"""Vicon reference files: C3D and Nexus CSV trajectory exports as one typed record in metres.

Every reader returns a :class:`MarkerTrajectories`: labels, rate, positions in **metres** with NaN
gaps, residuals, the source's first frame number, its length unit and a read-only metadata map.
This module is the entry point of the Vicon I/O; the work is done in modules named after what
they hold:

* :mod:`~mocaprig.calib.vicon_records` — the records (:class:`MarkerTrajectories`,
  :class:`AnalogChannels`), :class:`ViconFileError` and the length units;
* :mod:`~mocaprig.calib.vicon_build` — from decoded columns to the record: which trajectories are
  kept (model outputs, virtual points, unlabelled ``*NN``), the gap rule, the unit;
* :mod:`~mocaprig.calib.c3d_layout` — the pure-Python structural walk of a C3D file
  (:func:`validate_c3d`, :class:`C3DLayout`, the ANALOG group);
* :mod:`~mocaprig.calib.c3d_decode` — numpy decoders of the data section, the ezc3d/py-c3d
  backends and the isolated child interpreter;
* :mod:`~mocaprig.calib.c3d_read` — :func:`read_c3d` and :func:`read_c3d_analogs`;
* :mod:`~mocaprig.calib.nexus_csv` — :func:`read_nexus_csv`;
* :mod:`~mocaprig.calib.c3d_write` — :func:`write_c3d`.

Readers:

* :func:`read_c3d` — C3D files. The file is first checked by :func:`validate_c3d`, a pure-Python
  structural walk (header, parameter records with bounds checks, POINT sanity, data-section length
  against the file size) that rejects broken files with a clear :class:`ViconFileError` before any
  native code sees them. Intel and DEC files are then decoded by ``ezc3d``; SGI/MIPS (big-endian)
  files, which ``ezc3d`` 1.7.2 rejects, by the pure-Python ``c3d`` package (py-c3d), checked
  against the numpy decoder. Float and integer storage of every processor type read alike. With
  ``isolate=True`` (the default) the decoder runs in a child interpreter (``python -c``, not
  ``multiprocessing``, whose spawn/forkserver children re-import the caller's ``__main__``), so a
  crash inside ``ezc3d`` (it segfaults on some malformed parameter sections) becomes a
  ``ViconFileError`` instead of killing the caller. Residuals are always decoded from the raw
  bytes per c3d.org (:mod:`~mocaprig.calib.c3d_decode`).
* :func:`read_nexus_csv` — Nexus "Trajectories" CSV exports, parsed by section and line role (never
  by line number), in the modern Nexus layout and the older Workstation layout.
* :func:`read_trajectories` — picks one of the two from the file's first bytes.
* :func:`read_c3d_analogs` — the analog channels of a C3D file (:class:`AnalogChannels`, physical
  units, sampled on the Vicon clock), through the same structural check and isolated decoder.
"""

from __future__ import annotations

import os
from pathlib import Path

from mocaprig.calib.c3d_decode import decode_analog_block, decode_point_block
from mocaprig.calib.c3d_layout import C3DLayout, Processor, analog_layout, validate_c3d
from mocaprig.calib.c3d_read import read_c3d, read_c3d_analogs
from mocaprig.calib.c3d_write import write_c3d
from mocaprig.calib.nexus_csv import read_nexus_csv
from mocaprig.calib.vicon_records import (
    AnalogChannels,
    LengthUnit,
    MarkerTrajectories,
    ViconFileError,
    parse_length_unit,
)

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

# The numpy decoders under the names the tests have always used (tests/calib/test_vicon*.py).
_decode_point_block = decode_point_block
_decode_analog_block = decode_analog_block
_analog_layout = analog_layout


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
