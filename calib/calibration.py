"""The rig calibration: cameras (intrinsics, pose in the world) and device clock mappings.

One :class:`Calibration` is what ``mocaprig calibrate`` writes and what ``process/`` reads. It is
stored as TOML (``.toml``) or JSON (``.json``) with a ``format_version``, and as an attachment
(``calibration.toml``) in a recording.

Frames and units:
    world: the reference system's frame (Vicon's when calibrated against Vicon), metres.
    camera: OpenCV (+Z forward, +X right, +Y down). ``T_world_cam`` (4×4) maps camera to world,
        ``X_world = R·X_cam + t`` with ``t`` in metres (the camera centre).
    time: a :class:`ClockMapping` maps a device's clock (integer ns) onto the reference clock
        (integer ns): ``t_ref = t_dev + offset_ns + round(drift_ppm·1e-6·(t_dev − anchor_ns))``.
"""

from __future__ import annotations

import json
import math
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, Literal

import numpy as np
import numpy.typing as npt

from mocaprig.errors import CalibrationError

__all__ = [
    "FORMAT_VERSION",
    "Calibration",
    "CameraCalibration",
    "CameraKind",
    "ClockMapping",
    "calibration_bytes",
    "calibration_from_dict",
    "calibration_to_dict",
    "cameras_of_kind",
    "read_calibration",
    "write_calibration",
]

#: Version of the file layout; readers refuse files with a newer one.
FORMAT_VERSION: Final = 1

#: The devices a camera entry can describe.
CameraKind = Literal["d415", "davis"]
_KINDS: Final = ("d415", "davis")

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]


def _array(value: Any, shape: tuple[int, ...], what: str) -> F64:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        msg = f"{what}: expected numbers of shape {shape}, got {value!r}"
        raise CalibrationError(msg) from err
    if arr.shape != shape or not np.all(np.isfinite(arr)):
        msg = f"{what}: expected finite numbers of shape {shape}, got shape {arr.shape}"
        raise CalibrationError(msg)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, slots=True)
class ClockMapping:
    """How one device's clock maps onto the reference clock.

    ``t_ref_ns = t_dev_ns + offset_ns + round(drift_ppm·1e-6·(t_dev_ns − anchor_ns))``.

    Attributes:
        device: Device label, e.g. ``"d415/819612070593"``, ``"davis/02460013"``, ``"vicon"``.
        reference: The clock mapped onto (normally ``"vicon"``).
        offset_ns: Reference minus device time at ``t_dev = anchor_ns`` (ns).
        drift_ppm: Rate of the reference clock relative to the device clock, minus one (ppm).
        anchor_ns: Device time (ns) at which ``offset_ns`` holds; keeps the drift term small.
        offset_sigma_ns: 1σ uncertainty of ``offset_ns`` (ns); NaN when unknown.
        drift_sigma_ppm: 1σ uncertainty of ``drift_ppm``; NaN when unknown.
        method: How it was found (``"clap"``, ``"clap+xcorr"``, ``"pulses"``, ``"identity"``).
    """

    device: str
    reference: str
    offset_ns: int
    drift_ppm: float = 0.0
    anchor_ns: int = 0
    offset_sigma_ns: float = math.nan
    drift_sigma_ppm: float = math.nan
    method: str = ""

    def __post_init__(self) -> None:
        if not self.device or not self.reference:
            msg = "ClockMapping needs a device and a reference name"
            raise CalibrationError(msg)
        if not math.isfinite(self.drift_ppm) or abs(self.drift_ppm) >= 1e4:
            msg = (
                f"clock mapping {self.device!r}: drift_ppm must be finite and below 1e4 in "
                f"magnitude, got {self.drift_ppm!r} (wrong units?)"
            )
            raise CalibrationError(msg)
        object.__setattr__(self, "offset_ns", int(self.offset_ns))
        object.__setattr__(self, "anchor_ns", int(self.anchor_ns))

    def to_reference_ns(self, t_dev_ns: npt.ArrayLike) -> I64:
        """Reference times (int ns) of device times (int ns); any shape."""
        t = np.asarray(t_dev_ns, dtype=np.int64)
        drift = np.round((t - self.anchor_ns).astype(np.float64) * (self.drift_ppm * 1e-6))
        out: I64 = t + self.offset_ns + drift.astype(np.int64)
        return out

    def from_reference_ns(self, t_ref_ns: npt.ArrayLike) -> I64:
        """Device times (int ns) of reference times (int ns): the inverse of the mapping."""
        t = np.asarray(t_ref_ns, dtype=np.int64)
        rel = (t - self.offset_ns - self.anchor_ns).astype(np.float64)
        out: I64 = self.anchor_ns + np.round(rel / (1.0 + self.drift_ppm * 1e-6)).astype(np.int64)
        return out


@dataclass(frozen=True, slots=True)
class CameraCalibration:
    """One camera: intrinsics, pose in the world and how well they are known.

    Attributes:
        name: Label, e.g. ``"d415/819612070593"`` or ``"davis/02460013"``.
        kind: ``"d415"`` (left IR = depth frame) or ``"davis"`` (APS/DVS pixel grid).
        serial: Device serial number.
        width: Image width (px).
        height: Image height (px).
        K: ``(3, 3)`` intrinsic matrix (px).
        distortion: ``(5,)`` Brown–Conrady ``(k1, k2, p1, p2, k3)`` (OpenCV order).
        T_world_cam: ``(4, 4)`` camera-to-world transform, translation in metres.
        residuals: Fit statistics (``reprojection_rms_px``, ``inliers``, ``rotation_sigma_deg``,
            ``translation_sigma_mm``...), plain floats.
        source: What produced the pose (``"vicon"``, ``"charuco"``, ``"factory"``).
    """

    name: str
    kind: CameraKind
    serial: str
    width: int
    height: int
    K: F64 = field(repr=False)
    distortion: F64 = field(repr=False)
    T_world_cam: F64 = field(repr=False)
    residuals: Mapping[str, float] = field(default_factory=dict)
    source: str = ""

    def __post_init__(self) -> None:
        what = f"camera {self.name!r}"
        if self.kind not in _KINDS:
            msg = f"{what}: kind must be one of {_KINDS}, got {self.kind!r}"
            raise CalibrationError(msg)
        if int(self.width) <= 0 or int(self.height) <= 0:
            msg = f"{what}: image size must be positive, got {self.width}×{self.height}"
            raise CalibrationError(msg)
        k = _array(self.K, (3, 3), f"{what} K")
        if k[0, 0] <= 0 or k[1, 1] <= 0 or not np.allclose(k[2], (0.0, 0.0, 1.0)):
            msg = f"{what}: K needs fx, fy > 0 and a last row (0, 0, 1)"
            raise CalibrationError(msg)
        t = _array(self.T_world_cam, (4, 4), f"{what} T_world_cam")
        r = t[:3, :3]
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or not np.isclose(
            np.linalg.det(r), 1.0, atol=1e-6
        ):
            msg = f"{what}: T_world_cam's rotation is not a rotation (R·Rᵀ ≠ I or det ≠ 1)"
            raise CalibrationError(msg)
        if not np.allclose(t[3], (0.0, 0.0, 0.0, 1.0)):
            msg = f"{what}: T_world_cam's last row must be (0, 0, 0, 1)"
            raise CalibrationError(msg)
        if np.abs(t[:3, 3]).max() > 100.0:
            msg = (
                f"{what}: camera centre {t[:3, 3].tolist()} is over 100 m from the origin; "
                "T_world_cam's translation is in metres (millimetres given?)"
            )
            raise CalibrationError(msg)
        object.__setattr__(self, "K", k)
        object.__setattr__(self, "distortion", _array(self.distortion, (5,), f"{what} distortion"))
        object.__setattr__(self, "T_world_cam", t)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "residuals", {str(k): float(v) for k, v in self.residuals.items()})

    @property
    def T_cam_world(self) -> F64:
        """``(4, 4)`` world-to-camera transform (metres)."""
        out = np.eye(4)
        r, t = self.T_world_cam[:3, :3], self.T_world_cam[:3, 3]
        out[:3, :3] = r.T
        out[:3, 3] = -r.T @ t
        return out


@dataclass(frozen=True, slots=True)
class Calibration:
    """A whole rig's calibration.

    Attributes:
        cameras: One entry per camera, names unique.
        clocks: One mapping per device clock, onto ``reference_clock``; names unique.
        reference_clock: The clock every mapping maps onto (normally ``"vicon"``).
        world_frame: Name of the world frame (``"vicon"``, ``"board"``...).
        statistics: Whole-calibration figures (plain floats).
        software_version: ``mocaprig`` version that wrote it.
        created_utc: ISO-8601 creation time.
        format_version: File layout version (:data:`FORMAT_VERSION`).
    """

    cameras: tuple[CameraCalibration, ...] = ()
    clocks: tuple[ClockMapping, ...] = ()
    reference_clock: str = "vicon"
    world_frame: str = "vicon"
    statistics: Mapping[str, float] = field(default_factory=dict)
    software_version: str = ""
    created_utc: str = ""
    format_version: int = FORMAT_VERSION

    def __post_init__(self) -> None:
        object.__setattr__(self, "cameras", tuple(self.cameras))
        object.__setattr__(self, "clocks", tuple(self.clocks))
        for what, names in (
            ("camera", [c.name for c in self.cameras]),
            ("clock", [c.device for c in self.clocks]),
        ):
            dup = sorted({n for n in names if names.count(n) > 1})
            if dup:
                msg = f"calibration lists the {what} {dup} more than once"
                raise CalibrationError(msg)
        for c in self.clocks:
            if c.reference != self.reference_clock:
                msg = (
                    f"clock mapping {c.device!r} maps onto {c.reference!r}, but the "
                    f"calibration's reference clock is {self.reference_clock!r}"
                )
                raise CalibrationError(msg)
        object.__setattr__(
            self, "statistics", {str(k): float(v) for k, v in self.statistics.items()}
        )

    def camera(self, key: str) -> CameraCalibration:
        """The camera with this name or serial.

        Raises:
            CalibrationError: no such camera (the message lists the known ones).
        """
        for c in self.cameras:
            if key in (c.name, c.serial):
                return c
        msg = f"no camera {key!r} in the calibration; it has {[c.name for c in self.cameras]}"
        raise CalibrationError(msg)

    def clock(self, device: str) -> ClockMapping:
        """The mapping of a device's clock (by device label or the serial in it).

        Raises:
            CalibrationError: no mapping for it (the message lists the known ones).
        """
        for c in self.clocks:
            if device == c.device or c.device.endswith("/" + device):
                return c
        known = [c.device for c in self.clocks]
        msg = f"no clock mapping for {device!r}; the calibration has {known}"
        raise CalibrationError(msg)


def _nan_to_none(x: float) -> float | None:
    return None if math.isnan(x) else x


def calibration_to_dict(cal: Calibration) -> dict[str, Any]:
    """Plain TOML/JSON-ready view (NaN uncertainties are left out; TOML has no null)."""

    def clock(c: ClockMapping) -> dict[str, Any]:
        d: dict[str, Any] = {
            "device": c.device,
            "reference": c.reference,
            "offset_ns": c.offset_ns,
            "drift_ppm": c.drift_ppm,
            "anchor_ns": c.anchor_ns,
            "method": c.method,
        }
        for key in ("offset_sigma_ns", "drift_sigma_ppm"):
            value = _nan_to_none(getattr(c, key))
            if value is not None:
                d[key] = value
        return d

    return {
        "format_version": cal.format_version,
        "software_version": cal.software_version,
        "created_utc": cal.created_utc,
        "reference_clock": cal.reference_clock,
        "world_frame": cal.world_frame,
        "statistics": dict(cal.statistics),
        "cameras": [
            {
                "name": c.name,
                "kind": c.kind,
                "serial": c.serial,
                "width": c.width,
                "height": c.height,
                "K": c.K.tolist(),
                "distortion": c.distortion.tolist(),
                "T_world_cam": c.T_world_cam.tolist(),
                "residuals": dict(c.residuals),
                "source": c.source,
            }
            for c in cal.cameras
        ],
        "clocks": [clock(c) for c in cal.clocks],
    }


def calibration_from_dict(data: Mapping[str, Any], *, source: str = "calibration") -> Calibration:
    """Build a :class:`Calibration` from its plain view (what :func:`calibration_to_dict` gives).

    Raises:
        CalibrationError: missing keys, a newer ``format_version``, or invalid values; the
            message names ``source`` and the entry.
    """
    version = data.get("format_version")
    if not isinstance(version, int):
        msg = f"{source}: no integer format_version; is this a mocaprig calibration file?"
        raise CalibrationError(msg)
    if version > FORMAT_VERSION:
        msg = (
            f"{source}: format_version {version} is newer than this mocaprig reads "
            f"({FORMAT_VERSION}); upgrade mocaprig"
        )
        raise CalibrationError(msg)
    try:
        cameras = tuple(
            CameraCalibration(
                name=str(c["name"]),
                kind=c["kind"],
                serial=str(c["serial"]),
                width=int(c["width"]),
                height=int(c["height"]),
                K=c["K"],
                distortion=c["distortion"],
                T_world_cam=c["T_world_cam"],
                residuals=c.get("residuals", {}),
                source=str(c.get("source", "")),
            )
            for c in data.get("cameras", [])
        )
        clocks = tuple(
            ClockMapping(
                device=str(c["device"]),
                reference=str(c["reference"]),
                offset_ns=int(c["offset_ns"]),
                drift_ppm=float(c.get("drift_ppm", 0.0)),
                anchor_ns=int(c.get("anchor_ns", 0)),
                offset_sigma_ns=float(c.get("offset_sigma_ns", math.nan)),
                drift_sigma_ppm=float(c.get("drift_sigma_ppm", math.nan)),
                method=str(c.get("method", "")),
            )
            for c in data.get("clocks", [])
        )
        return Calibration(
            cameras=cameras,
            clocks=clocks,
            reference_clock=str(data.get("reference_clock", "vicon")),
            world_frame=str(data.get("world_frame", "vicon")),
            statistics=data.get("statistics", {}),
            software_version=str(data.get("software_version", "")),
            created_utc=str(data.get("created_utc", "")),
            format_version=version,
        )
    except KeyError as err:
        msg = f"{source}: an entry lacks the key {err.args[0]!r}"
        raise CalibrationError(msg) from err
    except (TypeError, ValueError, OverflowError, AttributeError) as err:
        msg = f"{source}: invalid value: {err}"
        raise CalibrationError(msg) from err
    except CalibrationError as err:
        msg = f"{source}: {err}"
        raise CalibrationError(msg) from err


def _encode(cal: Calibration, suffix: str) -> bytes:
    data = calibration_to_dict(cal)
    if suffix == ".json":
        return (json.dumps(data, indent=2) + "\n").encode()
    import tomli_w

    return tomli_w.dumps(data).encode()


def write_calibration(cal: Calibration, path: str | Path, *, overwrite: bool = False) -> Path:
    """Write ``cal`` as TOML (``.toml``) or JSON (``.json``); returns the path.

    Raises:
        CalibrationError: another suffix, or the file exists and ``overwrite`` is False.
    """
    p = Path(path)
    if p.suffix not in (".toml", ".json"):
        msg = f"{p}: a calibration file is .toml or .json"
        raise CalibrationError(msg)
    if p.exists() and not overwrite:
        msg = f"{p} exists; pass overwrite=True (--overwrite) to replace it"
        raise CalibrationError(msg)
    tmp = p.with_name(p.name + ".part")
    tmp.write_bytes(_encode(cal, p.suffix))
    # A crash mid-write leaves the old file (or none), never a truncated one.
    tmp.replace(p)
    return p


def calibration_bytes(cal: Calibration, *, fmt: Literal["toml", "json"] = "toml") -> bytes:
    """The file's bytes, e.g. for a recording attachment (``calibration.toml``)."""
    return _encode(cal, "." + fmt)


def read_calibration(
    source: str | Path | bytes, *, fmt: Literal["toml", "json"] | None = None
) -> Calibration:
    """Read a calibration from a ``.toml``/``.json`` file, or from bytes (an attachment).

    Raises:
        CalibrationError: unreadable, not TOML/JSON, or invalid (the message names the file).
    """
    if isinstance(source, bytes):
        name, raw, kind = "calibration attachment", source, fmt or "toml"
    else:
        p = Path(source)
        name = str(p)
        try:
            raw = p.read_bytes()
        except OSError as err:
            msg = f"cannot read calibration file {p}: {err.strerror or err}"
            raise CalibrationError(msg) from err
        kind = fmt or ("json" if p.suffix == ".json" else "toml")
    try:
        data = json.loads(raw) if kind == "json" else tomllib.loads(raw.decode())
    except (ValueError, UnicodeDecodeError, RecursionError) as err:
        msg = f"{name} is not valid {kind.upper()}: {err}"
        raise CalibrationError(msg) from err
    if not isinstance(data, Mapping):
        msg = f"{name}: expected a table at the top level"
        raise CalibrationError(msg)
    return calibration_from_dict(data, source=name)


def cameras_of_kind(cal: Calibration, kind: CameraKind) -> Sequence[CameraCalibration]:
    """The cameras of one kind, in file order."""
    return [c for c in cal.cameras if c.kind == kind]
