"""EventCap inputs for a ``mocaprig simulate`` session, from the simulator's truth.

**For tests and the demo only.** A real session gets its DAVIS calibration from
``mocaprig calibrate board`` and its detections from a 2D/3D pose detector (OpenPose, a COCO
keypoint model); a simulated one has neither, so this module stands the simulator's ground truth
in for both:

* :func:`davis_calibration` — the DAVIS's *true* intrinsics, distortion and camera-to-world pose
  (``truth/scenario.json``) and its *true* clock mapping onto the Vicon clock
  (``truth/davis_clock.json`` and the Vicon clock of ``scenario.json``), as a
  :class:`~mocaprig.calib.calibration.Calibration` with ``source="simulator-truth"``;
* :func:`session_detections` — :class:`~mocaprig.process.eventcap.detections.SyntheticDetections`
  (truth + paper-level noise, labelled ``"synthetic"``) at the recorded APS frame times
  (exposure midpoints of ``session.mcap``'s frame info, DAVIS µs);
* :func:`write_session_inputs` writes both (``calib.toml`` and the detections JSON).

Times: the recorded DAVIS clock is ``device_ns = (t_ns - reset_session_ns) · (1 + drift)``
(``davis_clock.json``); truth keypoints at a DAVIS time are linearly interpolated between the
1 kHz truth samples (``truth.npz``), well under a millimetre for the simulator's motions.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.device_streams import RecordedDavis, davis_devices
from mocaprig.acquire.recording import Recording
from mocaprig.calib.calibration import (
    Calibration,
    CameraCalibration,
    ClockMapping,
    write_calibration,
)
from mocaprig.calib.camera_model import project_points
from mocaprig.drivers_mock.truth import Truth, read_truth
from mocaprig.errors import RecordingError
from mocaprig.process.body.kinematics import eventcap_keypoints, forward_kinematics
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.eventcap.detections import (
    SyntheticDetections,
    SyntheticNoise,
    write_detections_json,
)

__all__ = [
    "SessionTruth",
    "davis_calibration",
    "read_session_truth",
    "session_detections",
    "write_session_inputs",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

_SESSION_MCAP = "session.mcap"
_DAVIS_CLOCK_JSON = "davis_clock.json"


@dataclass(frozen=True, slots=True, eq=False)
class SessionTruth:
    """A simulated session's truth as EventCap needs it (DAVIS time axis).

    Attributes:
        folder: The ``mocaprig simulate`` output folder.
        truth: Its ground truth (:func:`~mocaprig.drivers_mock.truth.read_truth`).
        shape: The actor's true body.
        davis_serial: The DAVIS's serial.
        reset_session_ns: Session time of the DAVIS's last timestamp reset (ns).
        davis_drift_ppm: The DAVIS clock's rate error (ppm).
    """

    folder: Path
    truth: Truth = field(repr=False)
    shape: BodyShape = field(repr=False)
    davis_serial: str
    reset_session_ns: int
    davis_drift_ppm: float

    def session_ns(self, t_davis_us: npt.ArrayLike) -> I64:
        """Session times (ns) of recorded DAVIS times (µs), any shape."""
        dev = np.asarray(t_davis_us, dtype=np.float64) * 1000.0
        out: I64 = self.reset_session_ns + np.rint(
            dev / (1.0 + self.davis_drift_ppm * 1e-6)
        ).astype(np.int64)
        return out

    def keypoints_at(self, t_davis_us: npt.ArrayLike) -> F64:
        """The 19 true EventCap keypoints (T, 19, 3), world m, at DAVIS times (T,) µs.

        Raises:
            RecordingError: a time outside the truth's span.
        """
        s = self.session_ns(np.atleast_1d(np.asarray(t_davis_us)))
        grid = self.truth.t_ns
        if s.size and (s.min() < grid[0] or s.max() > grid[-1]):
            msg = (
                f"{self.folder}: DAVIS times map to session {s.min()}..{s.max()} ns, outside the "
                f"truth's {grid[0]}..{grid[-1]} ns"
            )
            raise RecordingError(msg)
        i = np.clip(np.searchsorted(grid, s, side="right") - 1, 0, grid.size - 2)
        w = ((s - grid[i]) / (grid[i + 1] - grid[i]).astype(np.float64))[:, None, None]
        kp = self._keypoints(i)
        kp1 = self._keypoints(i + 1)
        out: F64 = (1.0 - w) * kp + w * kp1
        return out

    def _keypoints(self, idx: I64) -> F64:
        kin = forward_kinematics(self.truth.pose[idx], self.shape)
        return eventcap_keypoints(kin, self.shape)


def read_session_truth(folder: str | Path) -> SessionTruth:
    """The truth of a ``mocaprig simulate --devices davis…`` folder.

    Raises:
        RecordingError: no truth, or no ``truth/davis_clock.json`` (simulate with the DAVIS).
    """
    root = Path(folder)
    truth = read_truth(root)
    clock_path = root / "truth" / _DAVIS_CLOCK_JSON
    try:
        clock = json.loads(clock_path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        msg = (
            f"{clock_path}: cannot read the DAVIS clock truth ({err}); simulate the session with "
            "the DAVIS recorded (mocaprig simulate --devices davis --davis-dvs)"
        )
        raise RecordingError(msg) from err
    meta: dict[str, Any] = dict(truth.meta)
    return SessionTruth(
        folder=root,
        truth=truth,
        shape=BodyShape(**meta["body_shape"]),
        davis_serial=str(meta["rig"]["davis"]["serial"]),
        reset_session_ns=int(clock["reset_session_ns"]),
        davis_drift_ppm=float(clock["drift_ppm"]),
    )


def davis_calibration(st: SessionTruth) -> Calibration:
    """The DAVIS's true camera and clock as a calibration (module doc): world frame = the
    simulated world (the Vicon frame), reference clock ``"vicon"``."""
    meta = st.truth.meta
    cam = meta["rig"]["davis"]["camera"]
    name = f"davis/{st.davis_serial}"
    vicon = st.truth.clocks["vicon"]
    # t_ref = vicon(session(dev)), both affine: one offset and one rate (anchor 0).
    rate_v = 1.0 + vicon.drift_ppm * 1e-6
    rate_d = 1.0 + st.davis_drift_ppm * 1e-6
    clock = ClockMapping(
        device=name,
        reference="vicon",
        offset_ns=round(vicon.offset_ns + st.reset_session_ns * rate_v),
        drift_ppm=(rate_v / rate_d - 1.0) * 1e6,
        anchor_ns=0,
        method="simulator-truth",
    )
    return Calibration(
        cameras=(
            CameraCalibration(
                name=name,
                kind="davis",
                serial=st.davis_serial,
                width=int(cam["width"]),
                height=int(cam["height"]),
                K=np.asarray(cam["K"], dtype=np.float64),
                distortion=np.asarray(cam["distortion"], dtype=np.float64),
                T_world_cam=np.asarray(cam["T_world_cam"], dtype=np.float64),
                source="simulator-truth",
            ),
        ),
        clocks=(clock,),
        reference_clock="vicon",
        world_frame="vicon",
    )


def _aps_times_us(folder: Path) -> I64:
    """Exposure midpoints (DAVIS µs) of the recorded APS frames, as EventCap times them."""
    path = folder / _SESSION_MCAP
    with Recording(path) as rec:
        devs = davis_devices(rec)
        if not devs:
            msg = f"{path}: no DAVIS in the recording; simulate with --devices davis"
            raise RecordingError(msg)
        times = [
            (int(f.info.t_start_exposure_us) + int(f.info.t_end_exposure_us)) // 2
            if f.info is not None
            else int(f.t_ns) // 1000
            for f in RecordedDavis(rec, devs[0]).frames()
        ]
    if not times:
        msg = f"{path}: the DAVIS recorded no APS frames"
        raise RecordingError(msg)
    return np.asarray(sorted(set(times)), dtype=np.int64)


def session_detections(
    st: SessionTruth, *, seed: int, noise: SyntheticNoise | None = None
) -> SyntheticDetections:
    """Synthetic detections (``"synthetic"``) at every recorded APS frame time (module doc)."""
    t_us = _aps_times_us(st.folder)
    inside = st.session_ns(t_us) <= st.truth.t_ns[-1]
    t_us = t_us[inside]
    kp = st.keypoints_at(t_us)
    cam = st.truth.meta["rig"]["davis"]["camera"]
    T = np.asarray(cam["T_world_cam"], dtype=np.float64)
    px, _ = project_points(
        kp, T, np.asarray(cam["K"], np.float64), np.asarray(cam["distortion"], np.float64)
    )
    # A keypoint behind the camera cannot be detected; the simulator's rig never puts one there.
    if not np.all(np.isfinite(px)):
        msg = f"{st.folder}: some true keypoints project behind the DAVIS; check the rig"
        raise RecordingError(msg)
    return SyntheticDetections.from_world(t_us, px, kp, T, noise=noise, seed=seed)


def write_session_inputs(
    folder: str | Path,
    *,
    detections_path: str | Path,
    calibration_path: str | Path,
    seed: int = 0,
    noise: SyntheticNoise | None = None,
    overwrite: bool = False,
) -> tuple[Path, Path]:
    """Write the synthetic detections JSON and the DAVIS calibration of a simulated session.

    Returns ``(detections_path, calibration_path)``.

    Raises:
        RecordingError: the folder is not a simulated session with a DAVIS, or a file exists
            and ``overwrite`` is False.
    """
    st = read_session_truth(folder)
    det = session_detections(st, seed=seed, noise=noise)
    dpath, cpath = Path(detections_path), Path(calibration_path)
    write_detections_json(dpath, [det.detect(int(t)) for t in det.times_us], overwrite=overwrite)
    write_calibration(davis_calibration(st), cpath, overwrite=overwrite)
    _log.info("wrote %s (%d frames) and %s", dpath, det.times_us.size, cpath)
    return dpath, cpath
