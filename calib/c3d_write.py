"""Writing C3D files: trajectories and analog channels to an Intel float C3D (:func:`write_c3d`).

ezc3d writes the file; the residual words are then rewritten in the c3d.org byte order (ezc3d
1.7.2 swaps the camera and residual bytes, see :mod:`mocaprig.calib.c3d_decode`) and the header
scale made to agree with POINT:SCALE.
"""

from __future__ import annotations

import contextlib
import logging
import os
import struct
from pathlib import Path
from typing import Literal

import numpy as np

from mocaprig.calib.c3d_layout import validate_c3d
from mocaprig.calib.vicon_records import (
    METRES_PER_UNIT,
    AnalogChannels,
    FloatArray,
    MarkerTrajectories,
    ViconFileError,
)
from mocaprig.errors import ValidationError

__all__ = ["write_c3d"]

_log = logging.getLogger(__name__)


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
    per_m = 1.0 / METRES_PER_UNIT[unit]
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
