"""The rig file (``rig.toml``): which devices a recording opens and how they are set up.

Format (docs/rig-file.md has a commented example)::

    format_version = 1
    mock = false                  # true: dry-run on the simulated rig's mock devices

    [session]                     # optional
    name = "lab-a"
    notes = "..."

    [[d415]]                      # one table per camera; exactly one master
    serial = "819612070593"       # 12 digits, a string
    role = "master"               # "master" | "slave"
    mode = "848x480@30"           # "848x480@30" | "1280x720@30" | "848x480@90" (same for all)
    exposure_us = 8500            # optional, 1..165000 and <= the frame period
    gain = 16                     # optional, 16..248
    laser_power_mw = 150          # optional, 0..360 in steps of 30
    emitter = true                # optional

    [davis]                       # optional
    serial = "02460045"           # 8 characters
    bias_preset = "default"       # "default" | "legacy" | "pyaer"

    [syncbox]                     # optional
    port = "/dev/ttyACM0"
    mode = "listen"               # "listen" (count the D415 master) | "generate" (drive)
    rate_hz = 30                  # 1..1000
    width_us = 100                # 10..half the period

:func:`load_rig_file` reads and validates it; every problem is a
:class:`~mocaprig.errors.ValidationError` naming the key, the value and what is allowed.
"""

from __future__ import annotations

import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, Literal

from mocaprig.acquire.davis240c_config import BiasPreset
from mocaprig.acquire.depth_camera import ALLOWED_MODES, SensorOptions, StreamConfig
from mocaprig.errors import ValidationError

__all__ = [
    "RIG_FILE_VERSION",
    "D415Entry",
    "DavisEntry",
    "RigFile",
    "SyncBoxEntry",
    "load_rig_file",
    "parse_rig_file",
]

RIG_FILE_VERSION: Final[int] = 1
"""The ``format_version`` this mocaprig reads."""

_TOP_KEYS: Final = ("format_version", "mock", "session", "d415", "davis", "syncbox")
_SESSION_KEYS: Final = ("name", "notes")
_D415_KEYS: Final = ("serial", "role", "mode", "exposure_us", "gain", "laser_power_mw", "emitter")
_DAVIS_KEYS: Final = ("serial", "bias_preset")
_SYNCBOX_KEYS: Final = ("port", "mode", "rate_hz", "width_us")
_ROLES: Final = ("master", "slave")
_SYNC_MODES: Final = ("listen", "generate")


@dataclass(frozen=True, slots=True)
class D415Entry:
    """One ``[[d415]]`` table.

    Attributes:
        serial: 12-digit serial number.
        role: ``master`` (drives the sync line) or ``slave`` (triggered).
        stream: IR + depth mode (every camera of a rig runs the same one).
        options: Exposure (µs), gain, laser power (mW), emitter.
    """

    serial: str
    role: Literal["master", "slave"]
    stream: StreamConfig
    options: SensorOptions


@dataclass(frozen=True, slots=True)
class DavisEntry:
    """The ``[davis]`` table: serial (8 characters) and bias preset."""

    serial: str
    bias_preset: BiasPreset


@dataclass(frozen=True, slots=True)
class SyncBoxEntry:
    """The ``[syncbox]`` table: serial port, mode, pulse rate (Hz) and width (µs)."""

    port: str
    mode: Literal["listen", "generate"]
    rate_hz: int
    width_us: int


@dataclass(frozen=True, slots=True)
class RigFile:
    """A validated rig file.

    Attributes:
        format_version: The file's ``format_version``.
        mock: Dry-run on the simulated rig's mock devices instead of the real ones.
        d415: Cameras in file order (the master first is not required).
        davis: The event camera, or None.
        syncbox: The sync box, or None.
        session_name: ``[session] name`` ("" when absent).
        session_notes: ``[session] notes`` ("" when absent).
        text: The file's text as read (stored as the recording's ``rig.toml`` attachment).
        source: Where it was read from (for messages).
    """

    format_version: int
    mock: bool
    d415: tuple[D415Entry, ...]
    davis: DavisEntry | None
    syncbox: SyncBoxEntry | None
    session_name: str
    session_notes: str
    text: str
    source: str

    @property
    def master(self) -> D415Entry | None:
        """The master camera, or None without cameras."""
        return next((c for c in self.d415 if c.role == "master"), None)

    def metadata(self) -> dict[str, str]:
        """The ``rig`` metadata record of a recording (flat strings)."""
        out = {
            "format_version": str(self.format_version),
            "source": self.source,
            "mock": str(self.mock).lower(),
            "session_name": self.session_name,
            "session_notes": self.session_notes,
            "d415_count": str(len(self.d415)),
        }
        for i, c in enumerate(self.d415):
            o = c.options
            out[f"d415.{i}.serial"] = c.serial
            out[f"d415.{i}.role"] = c.role
            out[f"d415.{i}.mode"] = str(c.stream)
            out[f"d415.{i}.exposure_us"] = str(o.exposure_us)
            out[f"d415.{i}.gain"] = str(o.gain)
            out[f"d415.{i}.laser_power_mw"] = str(o.laser_power_mw)
            out[f"d415.{i}.emitter"] = str(o.emitter_enabled).lower()
        if self.davis is not None:
            out["davis.serial"] = self.davis.serial
            out["davis.bias_preset"] = self.davis.bias_preset.value
        if self.syncbox is not None:
            s = self.syncbox
            out["syncbox.port"] = s.port
            out["syncbox.mode"] = s.mode
            out["syncbox.rate_hz"] = str(s.rate_hz)
            out["syncbox.width_us"] = str(s.width_us)
        return out


def load_rig_file(path: Path) -> RigFile:
    """Read and validate a rig file.

    Raises:
        ValidationError: missing/unreadable file, TOML syntax error, or an invalid key/value
            (the message names the key, the value and what is allowed).
    """
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        msg = f"rig file {path} cannot be read ({err.strerror}); check the path"
        raise ValidationError(msg) from err
    except UnicodeDecodeError as err:
        msg = f"rig file {path} is not UTF-8 text; save it as UTF-8 TOML"
        raise ValidationError(msg) from err
    return parse_rig_file(text, source=str(path))


def parse_rig_file(text: str, *, source: str = "rig.toml") -> RigFile:
    """Validate rig-file ``text`` (see the module doc); ``source`` names it in messages.

    Raises:
        ValidationError: as :func:`load_rig_file`.
    """
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        msg = f"{source}: not valid TOML ({err}); see docs/rig-file.md for an example"
        raise ValidationError(msg) from err
    _no_unknown(doc, _TOP_KEYS, source, "")
    if "format_version" not in doc:
        msg = f"{source}: 'format_version' is missing; add `format_version = {RIG_FILE_VERSION}`"
        raise ValidationError(msg)
    version = doc["format_version"]
    if version != RIG_FILE_VERSION or isinstance(version, bool):
        msg = (
            f"{source}: format_version {version!r} is not supported; this mocaprig reads "
            f"format_version = {RIG_FILE_VERSION}"
        )
        raise ValidationError(msg)
    mock = _get(doc, "mock", bool, source, "", default=False)

    session = _table(doc, "session", source)
    _no_unknown(session, _SESSION_KEYS, source, "session.")
    name = _get(session, "name", str, source, "session.", default="")
    notes = _get(session, "notes", str, source, "session.", default="")

    raw_cams = doc.get("d415", [])
    if not isinstance(raw_cams, list) or not all(isinstance(c, dict) for c in raw_cams):
        msg = f"{source}: 'd415' must be an array of tables ([[d415]] sections)"
        raise ValidationError(msg)
    cams = tuple(_d415(c, source, i) for i, c in enumerate(raw_cams))
    _check_cameras(cams, source)

    davis = None
    if "davis" in doc:
        davis = _davis(_table(doc, "davis", source), source)
    syncbox = None
    if "syncbox" in doc:
        syncbox = _syncbox(_table(doc, "syncbox", source), source)
    if not cams and davis is None and syncbox is None:
        msg = f"{source}: lists no device; add [[d415]], [davis] or [syncbox] sections"
        raise ValidationError(msg)
    return RigFile(
        format_version=RIG_FILE_VERSION,
        mock=mock,
        d415=cams,
        davis=davis,
        syncbox=syncbox,
        session_name=name,
        session_notes=notes,
        text=text,
        source=source,
    )


# -- helpers -----------------------------------------------------------------------------------


def _no_unknown(table: Mapping[str, Any], allowed: tuple[str, ...], source: str, at: str) -> None:
    for key in table:
        if key not in allowed:
            msg = f"{source}: unknown key '{at}{key}'; allowed keys: {', '.join(allowed)}"
            raise ValidationError(msg)


def _table(doc: Mapping[str, Any], key: str, source: str) -> dict[str, Any]:
    value = doc.get(key, {})
    if not isinstance(value, dict):
        msg = f"{source}: '{key}' must be a table ([{key}] section), got {value!r}"
        raise ValidationError(msg)
    return value


def _get(
    table: Mapping[str, Any], key: str, kind: type, source: str, at: str, *, default: Any = None
) -> Any:
    if key not in table:
        if default is None:
            msg = f"{source}: '{at}{key}' is missing; see docs/rig-file.md"
            raise ValidationError(msg)
        return default
    value = table[key]
    # bool is an int in Python; TOML keeps them apart, so do we.
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        msg = f"{source}: '{at}{key}' must be {kind.__name__}, got {value!r}"
        raise ValidationError(msg)
    if isinstance(value, int) and not -(2**63) <= value < 2**63:  # TOML: 64-bit; tomllib: any
        msg = f"{source}: '{at}{key}' = {value} is beyond a 64-bit integer; see docs/rig-file.md"
        raise ValidationError(msg)
    return value


def _choice(table: Mapping[str, Any], key: str, allowed: tuple[str, ...], source: str,
            at: str, *, default: str | None = None) -> str:  # fmt: skip
    value: str = _get(table, key, str, source, at, default=default)
    if value not in allowed:
        msg = f"{source}: '{at}{key}' = {value!r} is not allowed; choose one of {list(allowed)}"
        raise ValidationError(msg)
    return value


def _parse_mode(text: str, source: str, at: str) -> StreamConfig:
    allowed = [f"{w}x{h}@{f}" for w, h, f in sorted(ALLOWED_MODES)]
    try:
        size, fps = text.split("@")
        w, h = size.lower().split("x")
        return StreamConfig(int(w), int(h), int(fps))
    except (ValueError, ValidationError) as err:
        msg = f"{source}: '{at}mode' = {text!r} is not allowed; choose one of {allowed}"
        raise ValidationError(msg) from err


def _d415(table: dict[str, Any], source: str, index: int) -> D415Entry:
    at = f"d415[{index}]."
    _no_unknown(table, _D415_KEYS, source, at)
    serial = _get(table, "serial", str, source, at)
    if len(serial) != 12 or not serial.isdigit():
        msg = f"{source}: '{at}serial' = {serial!r} must be the 12-digit D415 serial, in quotes"
        raise ValidationError(msg)
    role = _choice(table, "role", _ROLES, source, at)
    stream = _parse_mode(_get(table, "mode", str, source, at, default="848x480@30"), source, at)
    defaults = SensorOptions()
    try:
        options = SensorOptions(
            exposure_us=_get(table, "exposure_us", int, source, at, default=defaults.exposure_us),
            gain=_get(table, "gain", int, source, at, default=defaults.gain),
            laser_power_mw=_get(
                table, "laser_power_mw", int, source, at, default=defaults.laser_power_mw
            ),
            emitter_enabled=_get(table, "emitter", bool, source, at, default=True),
        )
        options.check_fits(stream)
    except ValidationError as err:
        msg = f"{source}: d415[{index}] (serial {serial}): {err}"
        raise ValidationError(msg) from err
    return D415Entry(serial, role, stream, options)  # type: ignore[arg-type]


def _check_cameras(cams: tuple[D415Entry, ...], source: str) -> None:
    if not cams:
        return
    serials = [c.serial for c in cams]
    dup = sorted({s for s in serials if serials.count(s) > 1})
    if dup:
        msg = f"{source}: D415 serial(s) {dup} listed more than once; list each camera once"
        raise ValidationError(msg)
    masters = [c.serial for c in cams if c.role == "master"]
    if len(masters) != 1:
        msg = (
            f'{source}: exactly one [[d415]] must have role = "master", found '
            f'{len(masters)} ({masters}); the others are "slave"'
        )
        raise ValidationError(msg)
    modes = {str(c.stream) for c in cams}
    if len(modes) > 1:
        msg = f"{source}: every D415 must use the same mode, found {sorted(modes)}"
        raise ValidationError(msg)


def _davis(table: dict[str, Any], source: str) -> DavisEntry:
    _no_unknown(table, _DAVIS_KEYS, source, "davis.")
    serial = _get(table, "serial", str, source, "davis.")
    if len(serial) != 8:
        msg = f"{source}: 'davis.serial' = {serial!r} must be the 8-character DAVIS serial"
        raise ValidationError(msg)
    presets = tuple(p.value for p in BiasPreset)
    preset = _choice(table, "bias_preset", presets, source, "davis.", default="default")
    return DavisEntry(serial, BiasPreset(preset))


def _syncbox(table: dict[str, Any], source: str) -> SyncBoxEntry:
    _no_unknown(table, _SYNCBOX_KEYS, source, "syncbox.")
    port = _get(table, "port", str, source, "syncbox.")
    if not port:
        msg = f"{source}: 'syncbox.port' is empty; give the serial port, e.g. \"/dev/ttyACM0\""
        raise ValidationError(msg)
    mode = _choice(table, "mode", _SYNC_MODES, source, "syncbox.", default="listen")
    rate = _get(table, "rate_hz", int, source, "syncbox.", default=30)
    if not 1 <= rate <= 1000:
        msg = f"{source}: 'syncbox.rate_hz' = {rate} is out of range; allowed 1..1000"
        raise ValidationError(msg)
    width = _get(table, "width_us", int, source, "syncbox.", default=100)
    high = int(1e6 / rate / 2)
    if not 10 <= width <= high:
        msg = (
            f"{source}: 'syncbox.width_us' = {width} is out of range; allowed 10..{high} "
            f"(half the period at {rate} Hz)"
        )
        raise ValidationError(msg)
    return SyncBoxEntry(port, mode, rate, width)  # type: ignore[arg-type]
