"""The sessions of a batch run and what each method needs from them, found by convention.

A session is given as a recording (``take.mcap``) or a folder: ``DIR/session.mcap`` (what
``mocaprig simulate`` and ``record`` write) or ``DIR/session/session.mcap`` (``mocaprig demo``'s
output folder). Its **side files** sit in that folder (the session folder; the ``.mcap``'s folder
when a file is given), named as ``mocaprig demo`` names them:

* ``calib.toml`` — the session's own calibration (``mocaprig calibrate vicon``); used instead
  of ``--calib`` for every method;
* ``eventcap_calib.toml`` — the calibration with the DAVIS entry (``mocaprig calibrate board``),
  used by EventCap before ``calib.toml`` and ``--calib``;
* ``democap_subject.json`` — the actor's subject file (``mocaprig democap subject``): DeMoCap
  solves every instant as that body; without it, every instant on its own;
* ``eventcap_detections.json`` (our JSON or a COCO keypoint JSON) or ``eventcap_detections/``
  (an OpenPose ``--write_json`` folder) — EventCap's detections, one per take, required;
* ``eventcap_shape.json`` — the actor's template (BodyShape fields, or a simulated
  ``truth/scenario.json``); else ``--height``.

Locations may be local paths or fsspec URLs (``s3://``, ``gs://``, ``http://``...): they are
resolved here (existence only, nothing is read) and read by the task that needs them, on its
worker (:func:`local_path`), never shipped through the scheduler.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Final

from mocaprig.errors import ValidationError

__all__ = [
    "CALIB_NAME",
    "DETECTIONS_NAME",
    "EVENTCAP_CALIB_NAME",
    "SHAPE_NAME",
    "SUBJECT_NAME",
    "SessionInputs",
    "find_sessions",
    "is_url",
    "local_path",
]

_log = logging.getLogger(__name__)

CALIB_NAME: Final = "calib.toml"
EVENTCAP_CALIB_NAME: Final = "eventcap_calib.toml"
DETECTIONS_NAME: Final = "eventcap_detections"
SHAPE_NAME: Final = "eventcap_shape.json"
SUBJECT_NAME: Final = "democap_subject.json"
_RECORDING_NAME: Final = "session.mcap"


def is_url(location: str | Path) -> bool:
    """Whether ``location`` is an fsspec URL (``proto://...``) rather than a local path."""
    return "://" in str(location) and not str(location).startswith("file://")


def _strip_file(location: str) -> str:
    return location.removeprefix("file://")


def local_path(location: str | Path) -> Path:
    """A local path to read ``location`` from: the path itself, or for an fsspec URL a copy in
    the local cache (fsspec ``simplecache``), fetched by the process that reads it.

    Raises:
        ValidationError: fsspec cannot open the URL (unknown protocol, missing file).
    """
    if not is_url(location):
        return Path(_strip_file(str(location)))
    import fsspec  # type: ignore[import-untyped]

    try:
        return Path(fsspec.open_local(f"simplecache::{location}"))
    except (OSError, ValueError, ImportError) as err:
        msg = f"{location}: cannot fetch it through fsspec ({err}); check the URL and its access"
        raise ValidationError(msg) from err


class _Place:
    """A folder given as a local path or an fsspec URL: join, exists, is a folder."""

    def __init__(self, location: str) -> None:
        self.url = is_url(location)
        self.location = location.rstrip("/") if self.url else _strip_file(location)
        if self.url:
            from fsspec.core import url_to_fs  # type: ignore[import-untyped]

            self._fs, _ = url_to_fs(self.location)

    def join(self, *parts: str) -> str:
        if self.url:
            return "/".join([self.location, *parts])
        return str(Path(self.location, *parts))

    def exists(self, location: str) -> bool:
        return bool(self._fs.exists(location)) if self.url else Path(location).exists()

    def is_dir(self, location: str) -> bool:
        return bool(self._fs.isdir(location)) if self.url else Path(location).is_dir()

    def parent_and_name(self) -> tuple[str, str]:
        if self.url:
            head, _, name = self.location.rpartition("/")
            return head, name
        p = Path(self.location)
        return str(p.parent), p.name


@dataclass(frozen=True, slots=True)
class SessionInputs:
    """One session of a batch run: where its recording and side files are (paths or URLs).

    Attributes:
        name: The session's name in the output folder (the session folder's name, or the
            recording's stem when it is not ``session.mcap``).
        recording: The recording (``.mcap``).
        folder: Where its side files are.
        calibration: The calibration of the D415s (``calib.toml`` beside it, else ``--calib``).
        eventcap_calibration: The calibration with the DAVIS entry (``eventcap_calib.toml``,
            else :attr:`calibration`).
        detections: EventCap's detections, or None when the session has none.
        shape: EventCap's template file, or None (``--height`` then).
        subject: DeMoCap's subject file, or None (every instant on its own).
    """

    name: str
    recording: str
    folder: str
    calibration: str | None
    eventcap_calibration: str | None
    detections: str | None
    shape: str | None
    subject: str | None = None


def _find_one(location: str, calib: str | None) -> SessionInputs:
    place = _Place(location)
    loc = place.location
    if loc.lower().endswith(".mcap"):
        if not place.exists(loc):
            msg = f"{location}: no such recording; give a .mcap or a session folder"
            raise ValidationError(msg)
        folder, file_name = place.parent_and_name()
        recording = loc
        stem = PurePosixPath(file_name).stem
        name = PurePosixPath(folder.rstrip("/")).name if file_name == _RECORDING_NAME else stem
    else:
        folder = loc
        recording = next(
            (
                p
                for p in (place.join(_RECORDING_NAME), place.join("session", _RECORDING_NAME))
                if place.exists(p)
            ),
            "",
        )
        if not recording:
            msg = (
                f"{location}: no {_RECORDING_NAME} in this folder or in its session/ folder; "
                "give a recording (.mcap) or a folder from mocaprig record/simulate/demo"
            )
            raise ValidationError(msg)
        name = PurePosixPath(loc.rstrip("/")).name
    side = _Place(folder)

    def found(file_name: str) -> str | None:
        p = side.join(file_name)
        return p if side.exists(p) else None

    own_calib = found(CALIB_NAME)
    calibration = own_calib if own_calib is not None else calib
    ec_calib = found(EVENTCAP_CALIB_NAME)
    det_dir = side.join(DETECTIONS_NAME)
    detections = found(f"{DETECTIONS_NAME}.json") or (det_dir if side.is_dir(det_dir) else None)
    return SessionInputs(
        name=name,
        recording=recording,
        folder=folder,
        calibration=calibration,
        eventcap_calibration=ec_calib if ec_calib is not None else calibration,
        detections=detections,
        shape=found(SHAPE_NAME),
        subject=found(SUBJECT_NAME),
    )


def find_sessions(
    locations: Sequence[str | Path], *, calib: str | Path | None = None
) -> tuple[SessionInputs, ...]:
    """The sessions at ``locations`` (module doc), with ``calib`` for those without their own.

    Raises:
        ValidationError: no session given, a location that is not a session, or two sessions
            with one name (their outputs would collide).
    """
    if not locations:
        msg = "give at least one session (a .mcap or a session folder)"
        raise ValidationError(msg)
    calib_s = None if calib is None else str(calib)
    if calib_s is not None and not is_url(calib_s) and not Path(_strip_file(calib_s)).is_file():
        msg = f"--calib {calib_s}: no such file; give a calibration (mocaprig calibrate vicon)"
        raise ValidationError(msg)
    sessions = tuple(_find_one(str(loc), calib_s) for loc in locations)
    seen: dict[str, str] = {}
    for s in sessions:
        if s.name in seen:
            msg = (
                f"sessions {seen[s.name]} and {s.recording} have the same name {s.name!r}, so "
                "their outputs would collide; give them distinct folder names"
            )
            raise ValidationError(msg)
        seen[s.name] = s.recording
    _log.info("%d sessions: %s", len(sessions), ", ".join(seen))
    return sessions
