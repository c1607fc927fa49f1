"""Reading C3D files: marker trajectories (:func:`read_c3d`) and analog channels
(:func:`read_c3d_analogs`).

Both first check the file's structure in pure Python (:mod:`mocaprig.calib.c3d_layout`), then
decode the data with ``ezc3d`` or py-c3d, by default in a child interpreter
(:mod:`mocaprig.calib.c3d_decode`), and with numpy where those fall short.

Processor types and storage. Intel, DEC (VAX floats) and SGI/MIPS (big-endian) files, each with
float or 16-bit integer storage (× POINT:SCALE), read to the same values: tested on the six
variants of one file made by py-c3d's writer and a byte-level converter, and of the real Nexus
file (``tests/calib/test_c3d_variants.py``). SGI points are py-c3d's checked against the numpy
decoder and taken from numpy: py-c3d scales integer words in float32, ezc3d and numpy in float64,
and the variants must agree.

Analog channels. ANALOG:USED channels are stored after the points of each frame,
ANALOG:RATE / POINT:RATE samples per frame (header word 10), each sample one value per channel.
Physical value = (stored − ANALOG:OFFSET) × ANALOG:SCALE × ANALOG:GEN_SCALE (c3d.org).
``ezc3d`` 1.7.2 returns values already scaled that way, except that it uses |OFFSET| (measured,
and so is its source: negative offsets are made positive), so :func:`read_c3d_analogs` takes
ezc3d's values (isolated child, Intel/DEC float files) and restores the signed offset; SGI files,
integer files (ANALOG:FORMAT may say UNSIGNED) and frames beyond 65,535 are decoded from the raw
bytes with numpy. USED, RATE, SCALE, OFFSET and GEN_SCALE are checked against the header and one
another before any native code runs.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import numpy as np

from mocaprig.calib.c3d_decode import (
    decode_analog_block,
    decode_point_block,
    isolate_timeout_s,
    read_analogs_ezc3d,
    read_points_isolated,
    read_points_native,
    run_isolated,
)
from mocaprig.calib.c3d_layout import analog_layout, validate_c3d_bytes
from mocaprig.calib.vicon_build import build_trajectories, resolve_unit
from mocaprig.calib.vicon_records import (
    AnalogChannels,
    FloatArray,
    MarkerTrajectories,
    ViconFileError,
)

__all__ = ["read_c3d", "read_c3d_analogs"]

_log = logging.getLogger(__name__)


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
        keep_virtual: keep model outputs and virtual points (see
            :mod:`mocaprig.calib.vicon_build`).
        keep_unlabeled: keep unlabelled ``*NN`` trajectories.
        strip_subject_prefix: drop ``Subject:`` from labels (fails if that merges two markers).
        isolate: run the native decoder in a fresh child interpreter so that a crash inside
            ezc3d cannot take the caller down (default True). It costs about 0.16–0.19 s per call
            (measured on 2 cores: 2 kB file 1 ms → 160 ms; the 2.25 MB Nexus file 50 ms →
            234 ms), negligible next to a calibration run; pass False for files you wrote
            yourself in tight loops. The structural check runs in-process either way (< 1 ms).

    Returns:
        The trajectories; ``metadata`` holds ``format="c3d"``, ``reader``, ``processor``
        (``intel``/``dec``/``sgi``), ``storage`` (``float``/``int``), ``point_scale``
        (|POINT:SCALE|, file units), ``units_raw``, ``frames_source`` and the MANUFACTURER
        strings when present.

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
    layout = validate_c3d_bytes(buf, p)
    length_unit, units_raw = resolve_unit(layout.units_raw, unit, path=p, where="POINT:UNITS")
    if layout.n_points == 0 or layout.n_frames == 0:
        xyz = np.zeros((layout.n_frames, layout.n_points, 3))
        reader = "none (no point data)"
    elif isolate:
        timeout = isolate_timeout_s(layout.file_size)
        xyz, _, reader = read_points_isolated(layout.processor, p, timeout_s=timeout)
    else:
        try:
            xyz, _, reader = read_points_native(layout.processor, p)
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
    np_xyz, residual = decode_point_block(layout, buf)
    if layout.processor == "sgi" and xyz.shape == np_xyz.shape:
        # py-c3d multiplies integer words by POINT:SCALE in float32, ezc3d and numpy in float64;
        # the numpy values are kept so that the six variants of a file read the same.
        _check_same_points(p, xyz, np_xyz, residual, layout.scale, reader)
        xyz = np_xyz
        reader = f"{reader} + numpy"
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
        "storage": "float" if layout.is_float else "int",
        "point_scale": str(np.float32(abs(layout.scale))),  # as stored, without float64 noise
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
    traj = build_trajectories(
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


def _check_same_points(
    path: str, a: FloatArray, b: FloatArray, residual: FloatArray, scale: float, reader: str
) -> None:
    """Raise when two decoders of one point block disagree beyond float32 rounding."""
    valid = residual >= 0
    tol = 1e-6 * np.maximum(np.abs(b), abs(scale))
    with np.errstate(invalid="ignore"):
        same = (a == b) | (np.abs(a - b) <= tol) | (np.isnan(a) & np.isnan(b))
    bad = valid[..., None] & ~same
    if np.any(bad):
        f, i, _ = (int(x[0]) for x in np.nonzero(bad))
        msg = (
            f"{path}: {reader} and the numpy decoder read frame {f + 1}, point {i + 1} as "
            f"{a[f, i].tolist()} and {b[f, i].tolist()}; the file is inconsistent; re-export it, "
            "or report the file to the maintainers"
        )
        raise ViconFileError(msg, path=path)


def read_c3d_analogs(path: str | os.PathLike[str], *, isolate: bool = True) -> AnalogChannels:
    """Read the analog channels of a C3D file, in physical units (see the module docstring).

    Args:
        path: the ``.c3d`` file.
        isolate: decode with ezc3d in a fresh child interpreter (as :func:`read_c3d`; default).

    Returns:
        The channels (none when the file has no analog data); ``metadata`` holds ``reader``,
        ``processor``, ``storage``, ``format`` (``signed``/``unsigned``) and the raw
        ``gen_scale``.

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
    layout = validate_c3d_bytes(buf, p)
    alay = analog_layout(buf, layout)
    n_samples = layout.n_frames * alay.samples_per_frame
    k = alay.scale * alay.gen_scale
    if alay.n_channels == 0 or n_samples == 0:
        values = np.zeros((n_samples, alay.n_channels))
        reader = "none (no analog data)"
    else:
        raw = decode_analog_block(layout, alay, buf)
        values = (raw - alay.offset) * k
        reader = "numpy"
        if layout.is_float and layout.processor in ("intel", "dec"):
            if isolate:
                timeout = isolate_timeout_s(len(buf))
                data = run_isolated("analogs", layout.processor, p, timeout_s=timeout)
                ez = np.asarray(data["analogs"], dtype=np.float64)
                ez_reader = str(data["reader"])
            else:
                try:
                    ez, ez_reader = read_analogs_ezc3d(p)
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
            "storage": "float" if layout.is_float else "int",
            "gen_scale": repr(alay.gen_scale),
            "format": "unsigned" if alay.unsigned else "signed",
        },
    )
