"""A simulated EventCap take: one DAVIS240C watching the actor, with 1 kHz ground truth.

The world is a :class:`~mocaprig.drivers_mock.scenario.Scenario` (procedural motion or a BVH
clip retargeted onto a sampled body); :class:`~mocaprig.drivers_mock.davis240c_sim.DavisSimulator`
renders it into DVS events and blurred APS exposures. The truth is sampled on the DAVIS's own
µs timeline (device time, what the recorded events carry) every ``truth_step_us``: pose vectors,
the 19 EventCap keypoints in the world and their projections through the DAVIS's true camera.

The take is what an EventCap evaluation needs and nothing the estimator may see is mixed in:
the estimator gets ``events``, ``exposures`` and the camera (which a real user has from
calibration); everything under ``truth_*`` is for scoring and for the synthetic detector.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from mocaprig.calib.camera_model import project_points
from mocaprig.drivers_mock.davis240c_sim import DavisSimulator
from mocaprig.drivers_mock.davis_activity import ApsExposure
from mocaprig.drivers_mock.rig import PinholeCamera
from mocaprig.drivers_mock.scenario import Scenario, build_scenario
from mocaprig.errors import ValidationError
from mocaprig.process.body.kinematics import eventcap_keypoints, forward_kinematics
from mocaprig.process.eventcap.camera import EventCamera
from mocaprig.process.eventcap.evaluate import TakeWithTruth
from mocaprig.process.eventcap.pipeline import ApsFrame
from mocaprig.validation import check_positive

__all__ = ["EventcapTake", "simulate_eventcap_take", "simulated_take_with_truth"]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: Events are simulated in windows of this length (µs) so memory follows the window.
_WINDOW_US = 100_000


@dataclass(frozen=True, slots=True, eq=False)
class EventcapTake:
    """A simulated DAVIS take with its ground truth (module doc).

    Attributes:
        scenario: The world it was rendered from.
        simulator: The DAVIS that rendered it (its clock maps device µs to session time;
            :meth:`reference_image` renders through it).
        camera: The DAVIS's true camera (intrinsics, distortion, camera-to-world pose).
        events: DVS events (:data:`mocaprig.acquire.events.EVENT_DTYPE`), device µs, sorted.
        exposures: APS exposures (device µs, 10-bit CDS counts), in time order.
        t0_us: First device µs of the simulated events (``start_s``).
        t1_us: End of the simulated events (exclusive), device µs: ``end_s``, else the
            take's end.
        truth_t_us: Truth sample times (T,), device µs, over the whole take.
        truth_pose: Pose vectors (T, 33) (``process.body.skeleton`` layout).
        truth_keypoints_m: The 19 EventCap keypoints (T, 19, 3), world frame, metres.
        truth_keypoints_px: Their projections (T, 19, 2) through ``camera``, px.
        truth_depth_m: Their depth along the optical axis (T, 19), metres.
    """

    scenario: Scenario = field(repr=False)
    simulator: DavisSimulator = field(repr=False)
    camera: PinholeCamera = field(repr=False)
    events: npt.NDArray[np.void] = field(repr=False)
    exposures: tuple[ApsExposure, ...] = field(repr=False)
    t0_us: int
    t1_us: int
    truth_t_us: I64 = field(repr=False)
    truth_pose: F64 = field(repr=False)
    truth_keypoints_m: F64 = field(repr=False)
    truth_keypoints_px: F64 = field(repr=False)
    truth_depth_m: F64 = field(repr=False)

    def truth_at(self, t_us: npt.ArrayLike) -> tuple[F64, F64]:
        """Pose (…, 33) and keypoints (…, 19, 3) m at any device times (int µs), exact."""
        return _truth(self.scenario, self.simulator.session_ns(t_us))

    def reference_image(self, t_us: int) -> F64:
        """The sharp linear irradiance (180, 240) at device µs ``t_us`` (the ``*_all`` input)."""
        return self.simulator.render_intensity(int(self.simulator.session_ns(int(t_us))))


def _truth(scenario: Scenario, session_ns: I64) -> tuple[F64, F64]:
    pose = scenario.pose(session_ns)
    kin = forward_kinematics(pose, scenario.shape)
    return pose, eventcap_keypoints(kin, scenario.shape)


def simulate_eventcap_take(
    *,
    seed: int,
    seconds: float,
    motion_path: str | Path | None = None,
    joint_map: Mapping[str, str] | None = None,
    scenario: str = "default",
    start_s: float = 0.0,
    end_s: float | None = None,
    max_frames: int | None = None,
    truth_step_us: int = 1000,
    progress: Callable[[int, int], None] | None = None,
    **davis_options: Any,
) -> EventcapTake:
    """Simulate a DAVIS take of ``seconds`` from device time 0 with 1 kHz truth (the events
    and frames of ``[start_s, end_s)`` only, when given).

    Args:
        seed: World seed (body, texture, thresholds, noise).
        seconds: Take length (s; ≥ 3, the scenario's minimum).
        motion_path: A BVH clip for the actor (default: the scenario's procedural motion).
        joint_map: Our joint name -> the BVH's joint name (``--joint-map``), when needed.
        scenario: Scenario name (see :data:`~mocaprig.drivers_mock.scenario.SCENARIOS`).
        start_s: Simulate the DAVIS only from this instant of the world (s): a short, cheap
            excerpt of a longer motion (the truth still covers the whole take).
        end_s: Simulate the DAVIS only until this instant of the world (s; default: the end of
            the take). The events and frames before it are those of the whole take.
        max_frames: Stop simulating (at the end of a 100 ms window) once this many APS frames
            from ``start_s`` are complete: what an evaluation of ``max_frames - 1`` batches uses.
        truth_step_us: Truth sampling period (µs; 1000 = the 1 kHz tracking rate).
        progress: Optional ``(done_us, total_us)`` callback while events are simulated.
        **davis_options: Keyword options of :class:`DavisSimulator` (exposure, contrast …).

    Raises:
        ValidationError: a bad option; ProcessingError: the BVH cannot be read.
    """
    check_positive(float(truth_step_us), name="truth_step_us")
    world = build_scenario(
        scenario, seed=seed, seconds=seconds, motion_path=motion_path, joint_map=joint_map
    )
    sim = DavisSimulator(world, **davis_options)
    camera = world.rig.davis.camera
    t_end_us = int(np.floor(float(sim.device_us(world.duration_ns))))
    t0_us = int(np.ceil(float(sim.device_us(round(start_s * 1e9)))))
    if not 0 <= t0_us < t_end_us:
        msg = f"start_s={start_s} s must lie in [0, {seconds}) s, the take"
        raise ValidationError(msg)
    t1_us = t_end_us
    if end_s is not None:
        t1_us = min(t_end_us, int(np.floor(float(sim.device_us(round(end_s * 1e9))))))
        if t1_us <= t0_us:
            msg = f"end_s={end_s} s must lie after start_s={start_s} s"
            raise ValidationError(msg)
    if max_frames is not None and max_frames < 1:
        msg = f"max_frames must be >= 1, got {max_frames}"
        raise ValidationError(msg)
    events: list[npt.NDArray[np.void]] = []
    exposures: list[ApsExposure] = []
    for w0 in range(t0_us, t1_us, _WINDOW_US):
        w1 = min(w0 + _WINDOW_US, t1_us)
        act = sim.activity(w0, w1)
        events.append(act.events)
        exposures.extend(act.exposures)
        if progress is not None:
            progress(w1 - t0_us, t1_us - t0_us)
        if max_frames is not None and sum(e.start_us >= t0_us for e in exposures) >= max_frames:
            t1_us = w1
            break
    all_events = np.concatenate(events) if events else sim.activity(0, 0).events
    # The truth covers the whole take whatever the excerpt: what is drawn from it (synthetic
    # detections) is then the same for every excerpt.
    t_us = np.arange(0, t_end_us, int(truth_step_us), dtype=np.int64)
    pose, kp = _truth(world, np.asarray(sim.session_ns(t_us), dtype=np.int64))
    uv, depth = project_points(
        kp.reshape(-1, 3), camera.T_world_cam, camera.K, camera.distortion, min_depth_m=None
    )
    _log.info(
        "simulated EventCap take: %.1f s, %d events, %d APS frames",
        t1_us * 1e-6,
        all_events.size,
        len(exposures),
    )
    return EventcapTake(
        scenario=world,
        simulator=sim,
        camera=camera,
        events=all_events,
        exposures=tuple(e for e in exposures if e.start_us >= t0_us),
        t0_us=t0_us,
        t1_us=t1_us,
        truth_t_us=t_us,
        truth_pose=pose,
        truth_keypoints_m=kp,
        truth_keypoints_px=uv.reshape(*kp.shape[:-1], 2),
        truth_depth_m=depth.reshape(kp.shape[:-1]),
    )


def simulated_take_with_truth(
    *,
    seed: int,
    seconds: float,
    motion_path: str | Path | None = None,
    joint_map: Mapping[str, str] | None = None,
    scenario: str = "default",
    start_s: float = 0.0,
    end_s: float | None = None,
    max_frames: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    **davis_options: Any,
) -> TakeWithTruth:
    """:func:`simulate_eventcap_take` as the product's evaluation takes it (the ``eventcap-take``
    mock of the ``mocaprig.mocks`` entry points): events, APS frames, the DAVIS's true
    calibration, the actor's body as the template, and the 1 kHz keypoint truth."""
    take = simulate_eventcap_take(
        seed=seed,
        seconds=seconds,
        motion_path=motion_path,
        joint_map=joint_map,
        scenario=scenario,
        start_s=start_s,
        end_s=end_s,
        max_frames=max_frames,
        progress=progress,
        **davis_options,
    )
    cam = take.camera
    # The world second at which the simulated events end (the take's end unless cut short).
    sim_end_s = round(float(take.simulator.session_ns(take.t1_us)) * 1e-9, 3)
    motion = Path(motion_path).stem if motion_path is not None else f"procedural:{scenario}"
    return TakeWithTruth(
        label=f"{motion} seed {seed} ({start_s:g}–{sim_end_s:g} s)",
        events=take.events,
        frames=tuple(ApsFrame(e.start_us, e.end_us, e.cds) for e in take.exposures),
        camera=EventCamera(
            K=cam.K,
            distortion=cam.distortion,
            T_world_cam=cam.T_world_cam,
            width=cam.width,
            height=cam.height,
        ),
        shape=take.scenario.shape,
        truth_t_us=take.truth_t_us,
        truth_keypoints_m=take.truth_keypoints_m,
        truth_keypoints_px=take.truth_keypoints_px,
    )
