"""Export one topic of a recording to files: npz (array topics), RPG text (events), PNG and
MP4 (images).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.recording_format import EventPacket, ImageMsg, ImuPacket, TriggerPacket
from mocaprig.acquire.rpg_text import export_events_txt
from mocaprig.errors import RecordingError

__all__ = ["ExportFormat", "ExportResult", "export_topic"]

ExportFormat = Literal["npz", "txt", "png", "mp4"]
"""The file formats of :func:`export_topic`."""


@dataclasses.dataclass(frozen=True, slots=True)
class ExportResult:
    """What :func:`export_topic` wrote.

    Attributes:
        out: The file written (the folder for ``png``).
        fmt: Its format.
        count: Events (``txt``), PNG files (``png``) or frames (``mp4``); 0 for ``npz``.
        shapes: ``npz``: (array name, shape) of each array, in file order; empty otherwise.
        fps: ``mp4``: the frame rate; 0.0 otherwise.
    """

    out: Path
    fmt: ExportFormat
    count: int = 0
    shapes: tuple[tuple[str, tuple[int, ...]], ...] = ()
    fps: float = 0.0


def export_topic(
    path: Path,
    *,
    topic_name: str,
    fmt: ExportFormat,
    out: Path,
    fps: float = 30.0,
    txt_header: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> ExportResult:
    """Export one topic of the recording ``path`` to npz / txt (events) / png (images) / mp4
    (images).

    ``txt`` writes RPG ``t x y p`` lines with the stored ns times (9 decimals) and, only with
    ``txt_header``, a first ``width height`` line. ``png`` writes one file per image into the
    folder ``out`` (16-bit for 16-bit images); ``mp4`` scales each frame to 8 bits.

    ``progress`` is called as ``(images_written, 0)`` after each image (``png``, ``mp4``: the
    count is not known ahead) and ``(count, count)`` when the export is written.

    Raises:
        RecordingError: ``out`` exists (a PNG file of the export, for ``png``), no such topic, or
            the format does not fit the topic's schema.
    """
    from mocaprig.acquire.recording import Recording

    if out.exists() and fmt != "png":
        msg = f"{out} exists already; not overwriting (choose another --out)"
        raise RecordingError(msg)
    with Recording(path) as rec:
        ch = rec.channels.get(topic_name)
        if ch is None:
            msg = f"{path} has no topic {topic_name!r}; topics: {', '.join(rec.topics)}"
            raise RecordingError(msg)
        schema = ch.schema_name
        if fmt == "txt":
            if schema != EventPacket.SCHEMA.name:
                msg = f"--format txt is for event topics; {topic_name} holds {schema}"
                raise RecordingError(msg)
            ev, t_ns = rec.events_ns(topic_name)
            w, h = _event_size(rec, topic_name)
            header = (w, h) if txt_header and w is not None and h is not None else None
            with out.open("x", encoding="ascii") as f:
                export_events_txt(ev, f, t_ns=t_ns, header=header)
            _report(progress, int(ev.size), int(ev.size))
            return ExportResult(out, fmt, count=int(ev.size))
        if fmt == "npz":
            arrays = _topic_arrays(rec, topic_name, schema)
            with out.open("xb") as f:
                np.savez_compressed(f, **arrays)  # type: ignore[arg-type]
            shapes = tuple((k, tuple(int(n) for n in v.shape)) for k, v in arrays.items())
            _report(progress, len(arrays), len(arrays))
            return ExportResult(out, fmt, shapes=shapes)
        if schema != ImageMsg.SCHEMA.name:
            msg = f"--format {fmt} is for image topics; {topic_name} holds {schema}"
            raise RecordingError(msg)
        n = _export_images(rec, topic_name, fmt, out, fps, progress)
        _report(progress, n, n)
        return ExportResult(out, fmt, count=n, fps=fps if fmt == "mp4" else 0.0)


def _report(progress: Callable[[int, int], None] | None, done: int, total: int) -> None:
    if progress is not None:
        progress(done, total)


def _event_size(rec: Any, topic_name: str) -> tuple[int | None, int | None]:
    for _, p in rec.decoded(topic_name):
        return int(p.width), int(p.height)
    return None, None


def _topic_arrays(rec: Any, topic_name: str, schema: str) -> dict[str, npt.NDArray[Any]]:
    if schema == EventPacket.SCHEMA.name:
        ev = rec.events(topic_name)
        return {k: ev[k] for k in ("t", "x", "y", "p")}
    if schema == ImuPacket.SCHEMA.name:
        s = rec.imu(topic_name)
        return {k: s[k] for k in s.dtype.names}
    if schema == TriggerPacket.SCHEMA.name:
        s = rec.triggers(topic_name)
        return {k: s[k] for k in s.dtype.names}
    if schema == ImageMsg.SCHEMA.name:
        times, stamps, imgs = [], [], []
        for t, m in rec.images(topic_name):
            times.append(t)
            stamps.append(m.timestamp_ns)
            imgs.append(m.image)
        return {
            "log_time_ns": np.asarray(times, np.int64),
            "timestamp_ns": np.asarray(stamps, np.int64),
            "images": np.stack(imgs) if imgs else np.empty((0, 0, 0)),
        }
    msg = f"--format npz does not handle {schema} topics; use the Python reader"
    raise RecordingError(msg)


def _to8(img: npt.NDArray[Any]) -> npt.NDArray[np.uint8]:
    if img.dtype == np.uint8:
        return img
    hi = float(img.max()) if img.size else 0.0
    return (img.astype(np.float64) * (255.0 / hi if hi > 0 else 0.0)).astype(np.uint8)


def _export_images(
    rec: Any,
    topic_name: str,
    fmt: str,
    out: Path,
    fps: float,
    progress: Callable[[int, int], None] | None,
) -> int:
    """Write the images of ``topic_name`` as PNG files into the folder ``out`` or as an MP4
    video; return the number of files or frames (``progress(n, 0)`` after each)."""
    import cv2

    n = 0
    if fmt == "png":
        out.mkdir(parents=True, exist_ok=True)
        for t, m in rec.images(topic_name):
            p = out / f"{n:06d}_{t}.png"
            if p.exists():
                msg = f"{p} exists already; export into an empty folder"
                raise RecordingError(msg)
            cv2.imwrite(str(p), m.image)  # 16-bit PNG for mono16/16UC1
            n += 1
            _report(progress, n, 0)
        return n
    writer: Any = None
    try:
        for _, m in rec.images(topic_name):
            frame = _to8(m.image)
            if writer is None:
                h, w = frame.shape
                fourcc = cv2.VideoWriter_fourcc(*"mp4v")  # type: ignore[attr-defined]
                writer = cv2.VideoWriter(str(out), fourcc, fps, (w, h), isColor=False)
                if not writer.isOpened():
                    msg = f"OpenCV cannot write {out} (mp4v codec missing?)"
                    raise RecordingError(msg)
            writer.write(frame)
            n += 1
            _report(progress, n, 0)
    finally:
        if writer is not None:
            writer.release()
    return n
