"""Ground truth of a simulated session: writer and typed reader.

Layout (``docs/simulated-world.md`` has the full description)::

    <out>/truth/truth.npz         the world sampled on a regular session-time grid
        t_ns            (T,)        int64   session time (ns), 0, 1e9/rate_hz, ...
        pose            (T, 33)     float64 pose vectors (process.body.skeleton layout)
        joints_m        (T, 26, 3)  float64 joint positions, world frame (m)
        markers_m       (T, M, 3)   float64 body marker centres, world frame (m)
        clapper_m       (T, 2, 3)   float64 clapperboard markers TOP, BOTTOM (m)
        clapper_angle_rad (T,)      float64 clapperboard opening angle (rad)
        joint_names (26,) marker_names (M,) clapper_marker_names (2,)   str
    <out>/truth/scenario.json     seed, software version, units and frames, rig cameras (K,
                                  distortion, T_world_cam, serials), clocks, clapperboard and
                                  clap times, body shape, marker set, noise settings, Vicon window
    <out>/truth/vicon_truth.npz   (optional, written with the Vicon capture) per C3D frame:
        frame_t_ns (F,) int64 true session time; clean_m (F, N, 3) noise-free positions (m);
        labels (N,) str; start_field () int64 (TRIAL:ACTUAL_START_FIELD)
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from mocaprig import __version__
from mocaprig.drivers_mock.clock import DeviceClock
from mocaprig.drivers_mock.rig import PinholeCamera
from mocaprig.errors import RecordingError, ValidationError

if TYPE_CHECKING:
    from mocaprig.drivers_mock.scenario import Scenario
    from mocaprig.drivers_mock.vicon import ViconCapture

__all__ = [
    "TRUTH_FORMAT_VERSION",
    "Truth",
    "ViconTruth",
    "democap_truth_at",
    "read_truth",
    "scenario_description",
    "write_truth",
    "write_vicon_truth",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
Progress = Callable[[int, int], None]

TRUTH_FORMAT_VERSION = 1
TRUTH_DIR = "truth"
TRUTH_NPZ = "truth.npz"
SCENARIO_JSON = "scenario.json"
VICON_TRUTH_NPZ = "vicon_truth.npz"

#: Samples evaluated per block (bounds memory, drives the progress callback).
_BLOCK = 2000


@dataclass(frozen=True, slots=True, eq=False)
class ViconTruth:
    """The true timing and noise-free positions of every frame of the simulated C3D.

    Attributes:
        frame_t_ns: Session time of each C3D frame (int64 ns), shape ``(F,)``.
        clean_m: Noise-free positions (m), shape ``(F, N, 3)``, in the C3D's label order.
        labels: The C3D point labels.
        start_field: ``TRIAL:ACTUAL_START_FIELD`` of the C3D.
    """

    frame_t_ns: I64 = field(repr=False)
    clean_m: F64 = field(repr=False)
    labels: tuple[str, ...]
    start_field: int


@dataclass(frozen=True, slots=True, eq=False)
class Truth:
    """Ground truth read back by :func:`read_truth`.

    Attributes:
        t_ns: Session times (int64 ns), shape ``(T,)``.
        pose: ``(T, 33)``.
        joints_m: ``(T, 26, 3)`` m.
        markers_m: ``(T, M, 3)`` m.
        clapper_m: ``(T, 2, 3)`` m.
        clapper_angle_rad: ``(T,)`` rad.
        joint_names: The 26 joint names.
        marker_names: The ``M`` body marker names.
        clapper_marker_names: ``("TOP", "BOTTOM")``.
        meta: ``scenario.json`` as a dict.
        vicon: The Vicon frame truth, when it was written.
    """

    t_ns: I64 = field(repr=False)
    pose: F64 = field(repr=False)
    joints_m: F64 = field(repr=False)
    markers_m: F64 = field(repr=False)
    clapper_m: F64 = field(repr=False)
    clapper_angle_rad: F64 = field(repr=False)
    joint_names: tuple[str, ...]
    marker_names: tuple[str, ...]
    clapper_marker_names: tuple[str, ...]
    meta: Mapping[str, Any] = field(repr=False)
    vicon: ViconTruth | None = field(default=None, repr=False)

    @property
    def seed(self) -> int:
        """The scenario seed."""
        return int(self.meta["seed"])

    @property
    def scenario_name(self) -> str:
        """The scenario name."""
        return str(self.meta["scenario"])

    @property
    def seconds(self) -> float:
        """Session length (s)."""
        return int(self.meta["duration_ns"]) * 1e-9

    @property
    def clap_times_ns(self) -> tuple[int, ...]:
        """Clapperboard contact instants (session ns)."""
        return tuple(int(t) for t in self.meta["clapperboard"]["clap_times_ns"])

    @property
    def clocks(self) -> dict[str, DeviceClock]:
        """Every device clock by device name."""
        return {c["name"]: DeviceClock.from_dict(c) for c in self.meta["clocks"]}

    @property
    def cameras(self) -> dict[str, PinholeCamera]:
        """Every imaging camera by device name (D415 left IR/depth, DAVIS)."""
        rig = self.meta["rig"]
        out = {d["name"]: _camera_from_dict(d["ir_left"]) for d in rig["d415"]}
        out[rig["davis"]["name"]] = _camera_from_dict(rig["davis"]["camera"])
        return out


def _camera_from_dict(d: Mapping[str, Any]) -> PinholeCamera:
    return PinholeCamera(
        str(d["name"]),
        int(d["width"]),
        int(d["height"]),
        np.asarray(d["K"], dtype=np.float64),
        np.asarray(d["distortion"], dtype=np.float64),
        np.asarray(d["T_world_cam"], dtype=np.float64),
    )


def scenario_description(scenario: Scenario, *, rate_hz: float | None = None) -> dict[str, Any]:
    """Everything that defines the scenario, JSON-ready (the content of ``scenario.json``)."""
    from mocaprig.process.body.skeleton import JOINTS

    markers = scenario.markers
    marker_dict: dict[str, Any] = {
        "names": list(markers.names),
        "joint_index": np.asarray(markers.joint_index).tolist(),
        "offsets_m": np.asarray(markers.offsets_m).tolist(),
        "normals": np.asarray(markers.normals).tolist(),
        "marker_radius_m": float(markers.marker_radius_m),
        "frame": "offsets and normals in the frame of the marker's joint (joint_index)",
    }
    out: dict[str, Any] = {
        "format_version": TRUTH_FORMAT_VERSION,
        "software": f"mocaprig {__version__}",
        "scenario": scenario.name,
        "seed": scenario.seed,
        "duration_ns": scenario.duration_ns,
        "seconds": scenario.seconds,
        "static_start_s": scenario.static_start_s,
        "units": {
            "length": "m (C3D/CSV: mm)",
            "time": "int ns of the session clock (0 = session start)",
            "angles": "rad",
            "pixels": "px, (0, 0) = centre of the top-left pixel",
        },
        "frames": {
            "world": "right-handed, Z up, metres; the actor faces +Y at zero root rotation",
            "camera": "OpenCV: +Z forward, +X right, +Y down; X_world = T_world_cam @ X_cam",
            "clock": "device_ns = offset_ns + t_ns * (1 + drift_ppm * 1e-6) (+ jitter)",
        },
        "motion": {
            "name": scenario.motion.name,
            "source": scenario.motion_source,
            "rate_hz": scenario.motion.rate_hz,
            "num_frames": scenario.motion.num_frames,
            "session_t0_ns": 0,
        },
        "body_shape": {k: float(v) for k, v in asdict(scenario.shape).items()},
        "joint_names": list(JOINTS),
        "markers": marker_dict,
        "rig": scenario.rig.to_dict(),
        "clocks": [c.to_dict() for c in scenario.clocks.values()],
        "clapperboard": scenario.clapperboard.to_dict(),
        "noise": scenario.noise.to_dict(),
        "world": scenario.world_params.to_dict(),
        "vicon_capture": {
            "start_ns": scenario.vicon_start_ns,
            "end_ns": scenario.vicon_end_ns,
            "clock": "vicon",
            "frame_time": "Vicon device time of C3D frame i = (ACTUAL_START_FIELD - 1 + i) / RATE",
        },
    }
    if rate_hz is not None:
        out["truth"] = {"file": TRUTH_NPZ, "rate_hz": rate_hz}
    return out


def _check_empty(folder: Path, *, overwrite: bool) -> None:
    if folder.exists() and not folder.is_dir():
        msg = f"output {folder} exists and is not a folder; choose another path"
        raise RecordingError(msg)
    if folder.is_dir() and any(folder.iterdir()) and not overwrite:
        msg = f"output folder {folder} is not empty; choose another one or pass overwrite=True"
        raise RecordingError(msg)


def write_truth(
    scenario: Scenario,
    out_dir: str | Path,
    *,
    rate_hz: float = 1000.0,
    overwrite: bool = False,
    progress: Progress | None = None,
) -> Path:
    """Sample the scenario on a regular grid and write ``<out_dir>/truth/``.

    Args:
        scenario: The world.
        out_dir: The session folder; the truth goes to its ``truth`` sub-folder.
        rate_hz: Sampling rate (Hz) of ``truth.npz``; samples at ``round(i·1e9/rate_hz)`` ns
            from 0 up to the session length.
        overwrite: Replace an existing non-empty ``truth`` folder.
        progress: Optional ``(done, total)`` callback over samples.

    Returns:
        The ``truth`` folder.

    Raises:
        RecordingError: the folder is not empty (without ``overwrite``) or cannot be written.
        ValidationError: a non-positive rate.
    """
    from mocaprig.process.body.skeleton import JOINTS

    if not (np.isfinite(rate_hz) and rate_hz > 0):
        msg = f"rate_hz must be > 0, got {rate_hz!r}"
        raise ValidationError(msg)
    folder = Path(out_dir) / TRUTH_DIR
    _check_empty(folder, overwrite=overwrite)
    count = int(np.floor(scenario.seconds * rate_hz + 1e-9)) + 1
    t_ns = np.round(np.arange(count, dtype=np.float64) * (1e9 / rate_hz)).astype(np.int64)
    num_markers = len(scenario.marker_names)
    pose = np.empty((count, 33))
    joints = np.empty((count, len(JOINTS), 3))
    markers = np.empty((count, num_markers, 3))
    clapper = np.empty((count, 2, 3))
    for a in range(0, count, _BLOCK):
        b = min(a + _BLOCK, count)
        s = scenario.sample(t_ns[a:b])
        pose[a:b], joints[a:b], markers[a:b], clapper[a:b] = (
            s.pose,
            s.joints_m,
            s.markers_m,
            s.clapper_m,
        )
        if progress is not None:
            progress(b, count)
    meta = scenario_description(scenario, rate_hz=rate_hz)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        for stale in (TRUTH_NPZ, SCENARIO_JSON, VICON_TRUTH_NPZ):
            (folder / stale).unlink(missing_ok=True)
        np.savez(
            folder / TRUTH_NPZ,
            t_ns=t_ns,
            pose=pose,
            joints_m=joints,
            markers_m=markers,
            clapper_m=clapper,
            clapper_angle_rad=scenario.clapperboard.angle_rad(t_ns),
            joint_names=np.array(JOINTS),
            marker_names=np.array(scenario.marker_names),
            clapper_marker_names=np.array(scenario.clapperboard.marker_names),
        )
        (folder / SCENARIO_JSON).write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
    except OSError as err:
        msg = f"cannot write the ground truth into {folder}: {err.strerror or err}"
        raise RecordingError(msg) from err
    _log.info("wrote ground truth: %d samples at %g Hz into %s", count, rate_hz, folder)
    return folder


def write_vicon_truth(capture: ViconCapture, out_dir: str | Path) -> Path:
    """Write ``<out_dir>/truth/vicon_truth.npz``: true frame times and clean positions.

    Raises:
        RecordingError: the file cannot be written.
    """
    path = Path(out_dir) / TRUTH_DIR / VICON_TRUTH_NPZ
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(
            path,
            frame_t_ns=capture.frame_t_ns,
            clean_m=capture.clean_m,
            labels=np.array(capture.labels),
            start_field=np.int64(capture.start_field),
        )
    except OSError as err:
        msg = f"cannot write the Vicon truth {path}: {err.strerror or err}"
        raise RecordingError(msg) from err
    return path


def read_truth(path: str | Path) -> Truth:
    """Read the ground truth written by :func:`write_truth`.

    Args:
        path: The session folder or its ``truth`` sub-folder.

    Raises:
        RecordingError: files are missing, unreadable or of another format version.
    """
    folder = Path(path)
    if not (folder / TRUTH_NPZ).is_file() and (folder / TRUTH_DIR / TRUTH_NPZ).is_file():
        folder = folder / TRUTH_DIR
    npz_path, json_path = folder / TRUTH_NPZ, folder / SCENARIO_JSON
    try:
        meta = json.loads(json_path.read_text(encoding="utf-8"))
        with np.load(npz_path) as z:
            arrays = {k: np.array(z[k]) for k in z.files}
        vicon: ViconTruth | None = None
        if (folder / VICON_TRUTH_NPZ).is_file():
            with np.load(folder / VICON_TRUTH_NPZ) as z:
                vicon = ViconTruth(
                    np.array(z["frame_t_ns"], dtype=np.int64),
                    np.array(z["clean_m"], dtype=np.float64),
                    tuple(str(s) for s in z["labels"]),
                    int(z["start_field"]),
                )
    except (OSError, ValueError, KeyError) as err:
        msg = (
            f"cannot read the ground truth in {folder} ({err}); it needs {TRUTH_NPZ} and "
            f"{SCENARIO_JSON} as written by `mocaprig simulate`"
        )
        raise RecordingError(msg) from err
    version = meta.get("format_version")
    if version != TRUTH_FORMAT_VERSION:
        msg = (
            f"ground truth in {folder} has format_version {version!r}; this mocaprig reads "
            f"{TRUTH_FORMAT_VERSION}; regenerate it with `mocaprig simulate`"
        )
        raise RecordingError(msg)
    try:
        return Truth(
            t_ns=arrays["t_ns"].astype(np.int64),
            pose=arrays["pose"],
            joints_m=arrays["joints_m"],
            markers_m=arrays["markers_m"],
            clapper_m=arrays["clapper_m"],
            clapper_angle_rad=arrays["clapper_angle_rad"],
            joint_names=tuple(str(s) for s in arrays["joint_names"]),
            marker_names=tuple(str(s) for s in arrays["marker_names"]),
            clapper_marker_names=tuple(str(s) for s in arrays["clapper_marker_names"]),
            meta=meta,
            vicon=vicon,
        )
    except KeyError as err:
        msg = f"ground truth {npz_path} lacks the array {err}; regenerate it"
        raise RecordingError(msg) from err


def democap_truth_at(
    truth: Truth, t_ns: npt.ArrayLike, *, clock: str | None = "vicon"
) -> tuple[F64, F64]:
    """The true DeMoCap markers and joints at given instants, for scoring a replay.

    Args:
        truth: The session's truth.
        t_ns: Times (int ns) on ``clock``'s time base (a calibration's reference clock:
            ``"vicon"``), or session times when ``clock`` is None.
        clock: The device clock ``t_ns`` is on; mapped to session time with its affine part
            (``DeviceClock.session_ns``, no jitter).

    Returns:
        ``(markers_m (N, 53, 3), joints_m (N, 19, 3))``, world, metres, in
        ``process.body.MARKER_NAMES`` / ``DEMOCAP_JOINTS`` order, linearly interpolated on the
        truth grid (1 kHz by default; times outside it take the end values).

    Raises:
        ValidationError: an unknown clock, or a marker of the DeMoCap set missing in the truth.
    """
    from mocaprig.process.body import DEMOCAP_JOINT_INDEX, MARKER_NAMES

    t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
    if clock is not None:
        clocks = truth.clocks
        if clock not in clocks:
            msg = f"no clock {clock!r} in the truth; it has {sorted(clocks)}"
            raise ValidationError(msg)
        t = clocks[clock].session_ns(t, unit_ns=1)
    missing = [m for m in MARKER_NAMES if m not in truth.marker_names]
    if missing:
        msg = f"the truth lacks the DeMoCap markers {missing}"
        raise ValidationError(msg)
    m_idx = [truth.marker_names.index(m) for m in MARKER_NAMES]
    grid = truth.t_ns.astype(np.float64)
    tq = t.astype(np.float64)

    def interp(a: F64) -> F64:
        flat = a.reshape(a.shape[0], -1)
        out = np.stack([np.interp(tq, grid, flat[:, k]) for k in range(flat.shape[1])], axis=1)
        return out.reshape(t.size, *a.shape[1:])

    return interp(truth.markers_m[:, m_idx]), interp(truth.joints_m[:, list(DEMOCAP_JOINT_INDEX)])
