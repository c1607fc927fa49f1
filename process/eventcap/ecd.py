"""Event-camera takes in the RPG Event-Camera Dataset layout (ECD text + PNG frames).

A folder holds ``events.txt`` (``t x y p`` per line, t in s; read by
:func:`mocaprig.acquire.rpg_text.read_events_txt`), ``images.txt`` (``t path`` per frame) and
the frames as 8-bit PNGs. ECD gives no exposure times: each frame is then taken as the image at
its time (a zero-length exposure). An optional ``frames.txt`` (``index t exposure_begin
exposure_end frame_begin frame_end``, seconds, as our export of AEDAT4 files writes it) gives
the real exposure windows. Times become integer µs on the events' clock.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from mocaprig.acquire.rpg_text import read_events_txt
from mocaprig.errors import RecordingError
from mocaprig.process.eventcap.pipeline import ApsFrame

__all__ = ["EcdTake", "read_ecd_take"]


@dataclass(frozen=True, slots=True, eq=False)
class EcdTake:
    """Events and APS frames of one ECD-layout folder.

    Attributes:
        events: Events (canonical dtype, µs), file order.
        frames: APS frames in time order, DN (8-bit grey as float).
        shape_hw: Sensor size (rows, columns), from the frames.
        exposure_known: Whether ``frames.txt`` gave real exposure windows.
    """

    events: npt.NDArray[np.void] = field(repr=False)
    frames: tuple[ApsFrame, ...] = field(repr=False)
    shape_hw: tuple[int, int]
    exposure_known: bool


def _us(seconds: str, where: str) -> int:
    try:
        return round(float(seconds) * 1e6)
    except ValueError as err:
        msg = f"{where}: {seconds!r} is not a time in seconds"
        raise RecordingError(msg) from err


def _read_frame(path: Path) -> npt.NDArray[np.float64]:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        msg = f"cannot read the frame {path}: missing or not an image"
        raise RecordingError(msg)
    return np.asarray(img, dtype=np.float64)


def read_ecd_take(folder: str | Path) -> EcdTake:
    """Read an ECD-layout folder (module doc).

    Raises:
        RecordingError: a missing or malformed file, frames of different sizes, or exposure
            rows that do not match the frames.
    """
    root = Path(folder)
    for name in ("events.txt", "images.txt"):
        if not (root / name).is_file():
            msg = f"{root}: no {name}; an ECD folder holds events.txt, images.txt and the frames"
            raise RecordingError(msg)
    events = read_events_txt(root / "events.txt").events
    rows = [r.split() for r in (root / "images.txt").read_text(encoding="utf-8").splitlines()]
    rows = [r for r in rows if r and not r[0].startswith("#")]
    if any(len(r) != 2 for r in rows):
        msg = f"{root / 'images.txt'}: every line must be 't path'"
        raise RecordingError(msg)
    times = [_us(t, str(root / "images.txt")) for t, _ in rows]
    images = [_read_frame(root / p) for _, p in rows]
    if len({img.shape for img in images}) > 1:
        msg = f"{root}: the frames differ in size"
        raise RecordingError(msg)
    windows = [(t, t) for t in times]
    known = (root / "frames.txt").is_file()
    if known:
        where = str(root / "frames.txt")
        lines = (root / "frames.txt").read_text(encoding="utf-8").splitlines()
        cols = [r.split() for r in lines if r.strip() and not r.startswith("#")]
        if len(cols) != len(images) or any(len(c) < 4 for c in cols):
            msg = f"{where}: expected {len(images)} rows 'index t exposure_begin exposure_end …'"
            raise RecordingError(msg)
        windows = [(_us(c[2], where), _us(c[3], where)) for c in cols]
    frames = tuple(ApsFrame(a, b, img) for (a, b), img in zip(windows, images, strict=True))
    shape = images[0].shape if images else (0, 0)
    return EcdTake(
        events=events, frames=frames, shape_hw=(int(shape[0]), int(shape[1])), exposure_known=known
    )
