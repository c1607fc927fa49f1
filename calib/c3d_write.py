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
    BoolArray,
    FloatArray,
    MarkerTrajectories,
    ViconFileError,
)
from mocaprig.errors import ValidationError

__all__ = ["C3DFrameWriter", "write_c3d"]

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


def _point_words(
    residuals_m: FloatArray,
    valid: BoolArray,
    per_m: float,
    scale: float,
    *,
    warn: Path | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Residuals (m, NaN: none) in the file's unit clipped to ``[0, 255·scale]``, and the
    points' fourth words: the residual in ``scale`` steps, -1 where a point is not ``valid``.
    ``warn`` names the file in a warning when residuals were clipped."""
    res_file = np.where(np.isnan(residuals_m), 0.0, residuals_m * per_m)
    max_res = 255 * scale
    if warn is not None and np.any(res_file > max_res):
        _log.warning("%s: residuals above %.2f mm clipped", warn, max_res / per_m * 1e3)
    res_file = np.clip(res_file, 0.0, max_res)
    # c3d.org layout of the fourth word (a float holding an integer): camera byte high (0 here),
    # residual / |SCALE| low; -1 for a gap.
    words = np.where(valid, np.rint(res_file / scale), -1.0)
    return res_file, words


def _replace_tmp(tmp: Path, out: Path, *, overwrite: bool) -> None:
    """Move the finished ``tmp`` to ``out``, unless ``out`` appeared meanwhile and may not be
    replaced (:class:`ViconFileError`)."""
    if out.exists() and not overwrite:
        msg = f"{out}: the file appeared while writing; pass overwrite=True to replace it"
        raise ViconFileError(msg, path=out)
    tmp.replace(out)


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
    # ezc3d 1.7.2 swaps the fourth word's bytes, so the words are rewritten after ezc3d has
    # written the file.
    res_file, words = _point_words(t.residuals_m, valid, per_m, scale, warn=out)
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
        _replace_tmp(tmp, out, overwrite=overwrite)
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


class C3DFrameWriter:
    """Write an Intel float C3D of point trajectories block by block (memory bounded by a block).

    For outputs too long to hold (EventCap's 1 kHz keypoints over a whole take): the header and
    parameter section are written by :func:`write_c3d` (ezc3d) for one frame, the frames are
    appended as they come, and on :meth:`close` the frame count (header, POINT:FRAMES,
    TRIAL:ACTUAL_END_FIELD) is set and the data padded to a whole block, giving the same bytes as
    :func:`write_c3d` on all the frames at once. The file is written beside ``path`` and moved
    into place on :meth:`close`; leaving the ``with`` block on an exception removes it.

    Args:
        path: The C3D to write.
        labels: The point labels (M).
        rate_hz: Frame rate.
        first_frame: 1-based capture frame of the first frame written.
        unit: POINT:UNITS of the file.
        source: Named in the file's records (what the points came from).
        overwrite: Replace an existing ``path``.

    Raises:
        ViconFileError: ``path`` exists and ``overwrite`` is False, or a write failed.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        labels: tuple[str, ...],
        rate_hz: float,
        first_frame: int = 1,
        unit: Literal["mm", "m"] = "mm",
        source: str = "",
        overwrite: bool = False,
    ) -> None:
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            msg = f"{self.path}: the file exists; pass overwrite=True to replace it"
            raise ViconFileError(msg, path=self.path)
        if first_frame < 1:
            msg = f"first_frame must be >= 1, got {first_frame}"
            raise ValidationError(msg)
        self._overwrite = overwrite
        self._n_points = len(labels)
        self._first = first_frame
        self._per_m = 1.0 / METRES_PER_UNIT[unit]
        self._scale = 0.01 * 1e-3 * self._per_m
        self._frames = 0
        self._closed = False
        self._tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.part.c3d")
        gap = MarkerTrajectories(
            labels=labels,
            rate_hz=rate_hz,
            positions_m=np.full((1, len(labels), 3), np.nan),
            residuals_m=np.full((1, len(labels)), np.nan),
            first_frame=first_frame,
            source_unit=unit,
            source=source,
            metadata={},
        )
        try:
            write_c3d(self._tmp, gap, unit=unit, overwrite=True)
            layout = validate_c3d(self._tmp)
            self._data_offset = layout.data_offset
            self._frames_at = layout.parameter_offsets["POINT:FRAMES"]
            self._end_at = layout.parameter_offsets["TRIAL:ACTUAL_END_FIELD"]
            self._rotation_at = layout.parameter_offsets.get("ROTATION:DATA_START")
            self._data_block = layout.data_start_block
            self._fh = self._tmp.open("r+b")
            self._fh.truncate(self._data_offset)
            self._fh.seek(self._data_offset)
        except Exception:
            self._tmp.unlink(missing_ok=True)
            raise

    def __enter__(self) -> C3DFrameWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.discard()

    @property
    def frames(self) -> int:
        """Frames written so far."""
        return self._frames

    def write(self, positions_m: FloatArray, residuals_m: FloatArray | None = None) -> None:
        """Append frames: positions ``(F, M, 3)`` m (NaN: a gap), residuals ``(F, M)`` m."""
        pos = np.asarray(positions_m, dtype=np.float64)
        if pos.ndim != 3 or pos.shape[1:] != (self._n_points, 3):
            msg = f"{self.path}: positions must be (F, {self._n_points}, 3), got {pos.shape}"
            raise ValidationError(msg)
        res = np.zeros(pos.shape[:2]) if residuals_m is None else np.asarray(residuals_m)
        valid = np.asarray(np.isfinite(pos).all(axis=-1), dtype=bool)
        block = np.empty((pos.shape[0], self._n_points, 4), dtype="<f4")
        block[..., :3] = np.where(valid[..., None], pos * self._per_m, 0.0)
        block[..., 3] = _point_words(res, valid, self._per_m, self._scale)[1]
        try:
            self._fh.write(block.tobytes())
        except OSError as err:
            self.discard()
            msg = f"{self.path}: writing the C3D frames failed ({err}); check free space"
            raise ViconFileError(msg, path=self.path) from err
        self._frames += pos.shape[0]

    def close(self) -> Path:
        """Set the frame count, pad the data to a whole block and move the file into place."""
        if self._closed:
            return self.path
        if self._frames == 0:
            self.discard()
            msg = f"{self.path}: no frames were written; a C3D needs at least one"
            raise ViconFileError(msg, path=self.path)
        last = self._first + self._frames - 1
        try:
            # ezc3d pads the data with 512 - n % 512 bytes (a whole block when n fills its
            # blocks) and points ROTATION:DATA_START past them; the same bytes here.
            n = self._fh.tell() - self._data_offset
            pad = 512 - n % 512
            self._fh.write(b"\0" * pad)
            if self._rotation_at is not None:
                block = self._data_block + (n + pad) // 512
                self._fh.seek(self._rotation_at)
                # A block number past 16 bits cannot be stored; 0 says "no rotation section".
                self._fh.write(struct.pack("<H", block if block <= 65535 else 0))
            self._fh.seek(8)
            self._fh.write(struct.pack("<H", min(last, 65535)))
            self._fh.seek(self._frames_at)
            self._fh.write(struct.pack("<H", min(self._frames, 65535)))
            self._fh.seek(self._end_at)
            self._fh.write(struct.pack("<HH", last % 65536, last // 65536))
            self._fh.close()
            _replace_tmp(self._tmp, self.path, overwrite=self._overwrite)
        except ViconFileError:
            self.discard()
            raise
        except OSError as err:
            self.discard()
            msg = f"{self.path}: finishing the C3D file failed ({err}); check free space"
            raise ViconFileError(msg, path=self.path) from err
        self._closed = True
        _log.info("wrote %s (%d points x %d frames)", self.path, self._n_points, self._frames)
        return self.path

    def discard(self) -> None:
        """Stop and remove the partial file (nothing is left at ``path``)."""
        self._closed = True
        with contextlib.suppress(OSError):
            self._fh.close()
        self._tmp.unlink(missing_ok=True)
