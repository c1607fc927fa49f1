"""Decoding the data section of a C3D file: numpy decoders, the native backends and isolation.

* :func:`decode_point_block` / :func:`decode_analog_block` decode the raw bytes with numpy (SGI
  files, frames beyond 65,535, residuals).
* :func:`read_points_native` decodes the points with ``ezc3d`` (Intel, DEC) or the pure-Python
  ``c3d`` package (SGI/MIPS, which ``ezc3d`` 1.7.2 rejects); :func:`read_analogs_ezc3d` the analog
  channels with ``ezc3d``.
* :func:`read_points_isolated` and :func:`run_isolated` run those decoders in a child interpreter
  (``python -c``, not ``multiprocessing``, whose spawn/forkserver children re-import the caller's
  ``__main__``), so a crash inside ``ezc3d`` (it segfaults on some malformed parameter sections)
  becomes a :class:`ViconFileError` instead of killing the caller. On Linux the child's address
  space is capped at what it has mapped after its imports plus :func:`isolate_memory_budget`
  (256 MiB + 64 × the file size; ezc3d needs ≈ 7 × the file size on a real Nexus file): a
  damaged count that sends ezc3d after 12 GB for a 2.5 kB file (fuzz inputs: ROTATION:RATIO
  −1, a parameter's type or dimension count changed) fails at once instead of filling memory.

Residual byte. The fourth word of a point holds the camera mask in its high byte and
residual / |POINT:SCALE| in its low byte (c3d.org; py-c3d agrees). ``ezc3d`` 1.7.2 reads and
writes the two bytes the other way round (measured), so the residuals are always decoded here
from the raw bytes (:func:`decode_point_block`).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt

from mocaprig.calib.c3d_layout import AnalogLayout, C3DLayout, Processor, dec_to_ieee
from mocaprig.calib.vicon_records import FloatArray, ViconFileError

__all__ = [
    "decode_analog_block",
    "decode_point_block",
    "isolate_timeout_s",
    "read_analogs_ezc3d",
    "read_points_isolated",
    "read_points_native",
    "run_isolated",
]

# Isolated parses get this long before the child is killed: generous for slow disks, finite for
# hostile files that would make a native parser loop.
_ISOLATE_TIMEOUT_BASE_S = 60.0
_ISOLATE_TIMEOUT_PER_MB_S = 2.0


def isolate_timeout_s(n_bytes: int) -> float:
    """How long (s) an isolated decoder may take on a file of ``n_bytes`` before it is killed."""
    return _ISOLATE_TIMEOUT_BASE_S + _ISOLATE_TIMEOUT_PER_MB_S * n_bytes / 1e6


_ISOLATE_MEMORY_BASE_BYTES = 256 << 20
_ISOLATE_MEMORY_PER_BYTE = 64


def isolate_memory_budget(n_bytes: int) -> int:
    """Bytes an isolated decoder may map beyond its interpreter and libraries for a file of
    ``n_bytes``."""
    return _ISOLATE_MEMORY_BASE_BYTES + _ISOLATE_MEMORY_PER_BYTE * int(n_bytes)


def _cap_address_space(n_bytes: int) -> int | None:  # pragma: no cover - child
    """Cap this (child) process's address space at its present size plus the budget of a file
    of ``n_bytes`` (Linux; elsewhere nothing is capped and None is returned)."""
    try:
        import resource

        statm = Path("/proc/self/statm").read_text(encoding="ascii")
        mapped = int(statm.split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except (ImportError, OSError, ValueError):
        return None
    budget = isolate_memory_budget(n_bytes)
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    limit = mapped + budget
    if hard != resource.RLIM_INFINITY:
        limit = min(limit, hard)
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    return budget


def _f4_to_f8(raw: bytes, end: str) -> FloatArray:
    # A signalling NaN (a damaged file) raises the FPU's invalid flag when widened; it stays a
    # NaN, which the readers treat as a gap, so the flag is no news worth a RuntimeWarning.
    with np.errstate(invalid="ignore"):
        out: FloatArray = np.frombuffer(raw, dtype=end + "f4").astype(np.float64)
    return out


def decode_point_block(layout: C3DLayout, buf: bytes) -> tuple[FloatArray, FloatArray]:
    """Decode the POINT block with numpy: (F, N, 3) coordinates and (F, N) residuals (source unit).

    Residuals follow the c3d.org text: negative fourth word → −1 (gap), else low byte × |SCALE|.
    """
    n, f = layout.n_points, layout.n_frames
    start, fb = layout.data_offset, layout.frame_bytes
    raw = buf[start : start + f * fb]
    if layout.is_float:
        if layout.processor == "dec":
            vals = dec_to_ieee(np.frombuffer(raw, dtype=np.uint8)).astype(np.float64)
        else:
            end = ">" if layout.processor == "sgi" else "<"
            vals = _f4_to_f8(raw, end)
        rec = vals.reshape(f, fb // 4)[:, : 4 * n].reshape(f, n, 4)
        xyz = rec[..., :3].copy()
        # The fourth word holds a 16-bit integer (camera mask, residual); anything else
        # (NaN, inf, a huge float in a damaged file) is a gap rather than an undefined cast.
        w4 = rec[..., 3]
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(w4) & (w4 >= -32768.0) & (w4 <= 65535.0)
        word = np.where(valid, w4, -1.0).astype(np.int64)
    else:
        end = ">" if layout.processor == "sgi" else "<"
        ints = np.frombuffer(raw, dtype=end + "i2").reshape(f, fb // 2)[:, : 4 * n]
        rec_i = ints.reshape(f, n, 4).astype(np.int64)
        xyz = rec_i[..., :3].astype(np.float64) * layout.scale
        word = rec_i[..., 3]
    residual = np.where(word < 0, -1.0, (word & 0xFF) * abs(layout.scale)).astype(np.float64)
    return xyz, residual


def decode_analog_block(layout: C3DLayout, alay: AnalogLayout, buf: bytes) -> FloatArray:
    """The stored analog values with numpy: (F·samples per frame, C), before any scaling."""
    f, n, c, spf = layout.n_frames, layout.n_points, alay.n_channels, alay.samples_per_frame
    start, fb = layout.data_offset, layout.frame_bytes
    raw = buf[start : start + f * fb]
    end = ">" if layout.processor == "sgi" else "<"
    if layout.is_float:
        if layout.processor == "dec":
            vals = dec_to_ieee(np.frombuffer(raw, dtype=np.uint8)).astype(np.float64)
        else:
            vals = _f4_to_f8(raw, end)
        words = vals.reshape(f, fb // 4)
    else:
        kind = "u2" if alay.unsigned else "i2"
        words = np.frombuffer(raw, dtype=end + kind).reshape(f, fb // 2).astype(np.float64)
    out: FloatArray = words[:, 4 * n : 4 * n + spf * c].reshape(f * spf, c)
    return out


def read_analogs_ezc3d(path: str) -> tuple[FloatArray, str]:
    """Decode the analog channels of ``path`` with ezc3d in this process: (S, C) values as ezc3d
    scales them (with |ANALOG:OFFSET|) and the reader's name."""
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


def read_points_native(processor: Processor, path: str) -> tuple[FloatArray, FloatArray, str]:
    """Decode the points of ``path`` in this process: (F, N, 3) coordinates, (F, N) residuals (as
    the backend reads them) and the reader's name; ezc3d for Intel/DEC, py-c3d for SGI files."""
    return _BACKENDS[processor](path)


def _child_entry(
    processor: str, path: str, out_npz: str, kind: str = "points"
) -> int:  # pragma: no cover - child
    """Entry point of the isolated child: decode ``path`` (its points, or with ``kind`` =
    ``"analogs"`` its analog channels), save arrays to ``out_npz``."""
    budget = None
    try:
        # The native readers are imported before the cap, which bounds what the file makes
        # them allocate, not the libraries.
        if processor in ("intel", "dec") or kind == "analogs":
            import ezc3d  # noqa: F401
        budget = _cap_address_space(Path(path).stat().st_size)
        if kind == "analogs":
            analogs, reader = read_analogs_ezc3d(path)
            np.savez(out_npz, analogs=analogs, reader=np.array(reader))
        else:
            xyz, residual, reader = _BACKENDS[processor](path)
            np.savez(out_npz, xyz=xyz, residual=residual, reader=np.array(reader))
    except BaseException as err:
        reason = f"{type(err).__name__}: {err}"
        # ezc3d's std::bad_alloc reaches Python as a RuntimeError naming it.
        if isinstance(err, MemoryError) or "bad_alloc" in str(err):
            size = Path(path).stat().st_size
            what = f"more than {budget >> 20} MiB" if budget else "more memory than there is"
            reason = (
                f"ViconFileError: {path}: its parameters ask the C3D reader for {what} for a "
                f"file of {size} bytes ({reason}); a count or a parameter's type in the "
                "parameter section is damaged; re-export it from Vicon Nexus"
            )
        sys.stderr.write(f"\n{_CHILD_ERROR_TAG}{reason}\n")
        return _CHILD_ERROR_EXIT
    return 0


_CHILD_ERROR_TAG = "mocaprig-c3d-error: "
_CHILD_ERROR_EXIT = 3
_CHILD_CODE = (
    "import sys; from calib.c3d_decode import _child_entry; sys.exit(_child_entry(*sys.argv[1:]))"
)


def read_points_isolated(
    processor: Processor, path: str, *, timeout_s: float
) -> tuple[FloatArray, FloatArray, str]:
    """Decode the points in a child interpreter (:func:`run_isolated`)."""
    data = run_isolated("points", processor, path, timeout_s=timeout_s)
    return (
        np.asarray(data["xyz"], dtype=np.float64),
        np.asarray(data["residual"], dtype=np.float64),
        str(data["reader"]),
    )


def run_isolated(
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
