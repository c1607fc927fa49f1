"""Cheap stand-ins for the batch run's worker functions (``runner.TASKS``), importable by the
pool's and Dask's worker processes. What they do is steered by files in the session folder, so
that a second try in another process sees what the first did."""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from mocaprig.acquire.device_id import DeviceId
from mocaprig.acquire.device_streams import D415FrameIndex
from mocaprig.process.batch.segments import EventcapPlan, Segment, SegmentResult, plan_segments
from mocaprig.process.batch.sessions import SessionInputs
from mocaprig.process.batch.tasks import ProcessSettings
from mocaprig.process.democap.instants import Instant
from mocaprig.process.democap.replay import ReplayPlan, ReplaySpan

if TYPE_CHECKING:
    from mocaprig.calib.calibration import Calibration

SERIAL = "02460013"
#: Instants per fake batch (40 ms at 1 kHz).
STEP = 40
#: Batches of the fake take.
BATCHES = 3
#: Rig instants of the fake recording, and their period (ns).
INSTANTS = 12
PERIOD_NS = 33_333_333


def calibration() -> Calibration:
    """A DAVIS calibration with its clock on the Vicon clock (5 s offset)."""
    # Imported here: the worker processes load this module and should start quickly.
    from mocaprig.calib.calibration import Calibration, CameraCalibration, ClockMapping

    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]
    T[:3, 3] = (0.0, -3.0, 1.0)
    cam = CameraCalibration(
        name=f"davis/{SERIAL}",
        kind="davis",
        serial=SERIAL,
        width=240,
        height=180,
        K=np.array([[200.0, 0, 120], [0, 200, 90], [0, 0, 1]]),
        distortion=np.zeros(5),
        T_world_cam=T,
    )
    clock = ClockMapping(f"davis/{SERIAL}", "vicon", offset_ns=5_000_000_000)
    return Calibration(cameras=(cam,), clocks=(clock,))


def _first_try(session: SessionInputs, what: str) -> bool:
    marker = Path(session.folder) / f"tried-{what}"
    if marker.exists():
        return False
    marker.touch()
    return True


def instants(session: SessionInputs, settings: ProcessSettings) -> ReplayPlan:
    """A recording of :data:`INSTANTS` rig instants of one camera, every ``democap_every``-th
    selected."""
    t_dev = np.arange(INSTANTS, dtype=np.int64) * PERIOD_NS
    index = D415FrameIndex(DeviceId("d415", "123"), t_dev, np.arange(INSTANTS), t_dev, t_dev)
    every = settings.democap_every
    selected = tuple(Instant(int(5e9 + t), {"d415/123": int(t)}) for t in t_dev[::every])
    return ReplayPlan(
        Path(session.recording),
        ("d415/123",),
        {"d415/123": index},
        {},
        selected,
        instants_total=INSTANTS,
        every=every,
        period_ns=PERIOD_NS,
    )


def span(session: SessionInputs, plan: ReplayPlan) -> ReplaySpan:
    """Markers and joints at x = the instant's time in s; fails as ``session.folder``'s
    ``mode`` file says (the first span only)."""
    mode_file = Path(session.folder) / "mode"
    mode = mode_file.read_text().strip() if mode_file.exists() else "ok"
    if plan.offset == 0:
        if mode == "always":
            msg = f"{session.name} cannot be replayed"
            raise RuntimeError(msg)
        if mode == "raise-once" and _first_try(session, "span"):
            msg = "boom"
            raise RuntimeError(msg)
        if mode == "die-once" and _first_try(session, "span"):
            os.kill(os.getpid(), signal.SIGKILL)  # the worker dies mid-task
    t = np.array([i.t_ref_ns for i in plan.instants], dtype=np.int64)
    n = t.size
    x = np.zeros((n, 1, 3))
    x[:, 0, 0] = t * 1e-9
    return ReplaySpan(
        plan.offset,
        plan.offset + n,
        t,
        np.ones(n, dtype=np.int64),
        np.repeat(x, 53, axis=1),
        np.repeat(x, 19, axis=1),
        tuple(x[i] for i in range(n)),
        checkpoint="fake (1 epochs)",
    )


def csv_rows(path: Path) -> np.ndarray:
    """The rows of a replay CSV (``time_s`` then mm), ``(N, 1 + 3·72)``."""
    return np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


def plan(session: SessionInputs, settings: ProcessSettings) -> EventcapPlan:
    """A take of :data:`BATCHES` batches."""
    n, overlap = settings.segment_batches, settings.overlap
    return EventcapPlan(BATCHES, plan_segments(BATCHES, segment_batches=n, overlap=overlap))


def segment(session: SessionInputs, settings: ProcessSettings, seg: Segment) -> SegmentResult:
    """The kept instants of ``seg`` (batch ``b`` covers ``b·STEP .. (b+1)·STEP`` ms): a neutral
    body moving 1 mm per ms along x; raises once for segment 1 when ``mode`` says so."""
    from mocaprig.process.body.kinematics import (
        eventcap_keypoints,
        forward_kinematics,
        neutral_pose,
    )
    from mocaprig.process.body.shape import BodyShape

    shape = BodyShape.from_height(1.75)
    mode_file = Path(session.folder) / "mode"
    once = mode_file.exists() and mode_file.read_text().strip() == "segment-once"
    if once and seg.index == 1 and _first_try(session, "segment"):
        msg = "segment boom"
        raise RuntimeError(msg)
    n = (seg.end - seg.keep) * STEP + (1 if seg.last else 0)
    k = np.arange(seg.keep * STEP, seg.keep * STEP + n)
    pose = np.repeat(neutral_pose()[None], n, axis=0)
    pose[:, 3] = k * 1e-3
    kp = eventcap_keypoints(forward_kinematics(pose, shape), shape)
    return SegmentResult(
        seg, 1_000_000 + 1000 * k.astype(np.int64), pose, kp, f"davis/{SERIAL}", "synthetic", 0.0
    )
