"""Simulate a session: the ground truth, the simulated Vicon exports and the rig's recording.

``simulate_session`` is the typed function behind ``mocaprig simulate`` (and the ``demo``)::

    <out>/truth/truth.npz, scenario.json, vicon_truth.npz    (drivers_mock.truth)
    <out>/truth/d415_captures.npz                            every mock D415 capture (truth)
    <out>/truth/vicon_sync.npz                               the sync channel's switch instants
    <out>/vicon/session.c3d                                  float C3D, mm, 120 Hz (+ D415_SYNC)
    <out>/vicon/session.csv                                  Nexus Trajectories CSV, same values
    <out>/session.mcap                                       the rig's recording (MCAP)

``session.mcap`` is recorded by :func:`record_session` through the real drivers
(:class:`mocaprig.acquire.davis240c.Davis240C` over the mock USB backend,
``acquire.camera_backends.open_cameras("mock")``, :class:`acquire.syncbox.SyncBox` on the mock's
pseudo-terminal) and the recorder of ``mocaprig record``, from the mock devices of the same
world. The mocks are paced "asap" (simulated time, deterministic): the recording takes as long as
the simulation needs, the sources use the recorder's back-pressure (``put_wait``) and nothing is
dropped. The mock D415 master's pulse train is the one the DAVIS sees on its trigger input and
the sync box counts (``MockD415.pulse_at_or_after``), and, with D415s recorded, the one whose
edges the Vicon samples on its analog channel ``D415_SYNC`` (the C3D is then written after the
recording, when the master's pulses are known; ``drivers_mock.vicon.simulate_sync_channel``).

Cost on the 2-core machine (``docs/simulated-world.md``): ~50 ms CPU per D415 frameset at
848×480 (4 cameras: ~6 s per simulated second), ~2 s per simulated second for the DAVIS with its
DVS off (APS frames, IMU, trigger input), ~20 s per simulated second with the DVS on.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, Literal, get_args

import numpy as np

from mocaprig.drivers_mock.noise import NoiseSettings
from mocaprig.drivers_mock.rig import D415Timing, PulseAt
from mocaprig.drivers_mock.scenario import Scenario, build_scenario
from mocaprig.drivers_mock.truth import write_truth, write_vicon_truth
from mocaprig.drivers_mock.vicon import (
    AnalogCapture,
    SyncWiring,
    simulate_sync_channel,
    simulate_vicon,
    write_c3d,
    write_nexus_csv,
)
from mocaprig.drivers_mock.world import WorldKind, WorldParams
from mocaprig.errors import RecordingError, ValidationError

__all__ = [
    "DEVICES",
    "Device",
    "SessionRecording",
    "SimulationResult",
    "record_session",
    "simulate_session",
]

_log = logging.getLogger(__name__)

Progress = Callable[[int, int], None]

#: A recorded device kind of the simulated rig.
Device = Literal["davis", "d415", "syncbox"]
#: Every device kind, the default of ``simulate --devices``.
DEVICES: Final[tuple[Device, ...]] = get_args(Device)


@dataclass(frozen=True, slots=True)
class SessionRecording:
    """What :func:`record_session` recorded.

    Attributes:
        path: The recording (``<out>/session.mcap``).
        devices: The recorded device kinds.
        cameras: D415 count (0 without ``d415``).
        davis_dvs: Whether the DAVIS DVS module ran.
        streams: ``(topic, messages, drops)`` per stream.
        drops_total: Messages dropped, all streams (0: back-pressure, nothing is dropped).
        davis_driver_drops: Packets the DAVIS driver dropped (0 expected).
        bytes: File size (bytes).
        elapsed_s: Wall time the recording took (s).
        sync_pulses_ns: Every sync pulse the D415 master emitted while it streamed (session
            ns), the train the slaves, the DAVIS, the sync box and the Vicon's sync channel
            see; empty without D415s.
    """

    path: Path
    devices: tuple[Device, ...]
    cameras: int
    davis_dvs: bool
    streams: tuple[tuple[str, int, int], ...] = field(repr=False)
    drops_total: int
    davis_driver_drops: int
    bytes: int
    elapsed_s: float
    sync_pulses_ns: tuple[int, ...] = field(default=(), repr=False)

    def to_dict(self) -> dict[str, object]:
        """JSON-ready summary."""
        return {
            "path": str(self.path),
            "devices": list(self.devices),
            "cameras": self.cameras,
            "davis_dvs": self.davis_dvs,
            "streams": [{"topic": t, "messages": m, "drops": d} for t, m, d in self.streams],
            "drops_total": self.drops_total,
            "davis_driver_drops": self.davis_driver_drops,
            "bytes": self.bytes,
            "elapsed_s": self.elapsed_s,
        }


@dataclass(frozen=True, slots=True)
class SimulationResult:
    """What :func:`simulate_session` wrote.

    Attributes:
        out_dir: The session folder.
        truth_dir: ``<out>/truth``.
        c3d_path: The simulated Vicon C3D.
        csv_path: The same capture as a Nexus CSV.
        scenario: The simulated world.
        seed: Its seed.
        seconds: Session length (s).
        num_body_markers: Body markers in the C3D.
        num_clapper_markers: Clapperboard markers in the C3D.
        vicon_rate_hz: Vicon frame rate (Hz).
        vicon_frames: Frames in the C3D.
        vicon_gap_fraction: Fraction of C3D samples that are gaps.
        truth_rate_hz: Sampling rate of ``truth.npz`` (Hz).
        clap_times_ns: Clapperboard contact instants (session ns).
        elapsed_s: Wall time the simulation took (s).
        recording: The session recording (``None`` with ``devices=()``).
    """

    out_dir: Path
    truth_dir: Path
    c3d_path: Path
    csv_path: Path
    scenario: Scenario
    seed: int
    seconds: float
    num_body_markers: int
    num_clapper_markers: int
    vicon_rate_hz: float
    vicon_frames: int
    vicon_gap_fraction: float
    truth_rate_hz: float
    clap_times_ns: tuple[int, ...]
    elapsed_s: float
    recording: SessionRecording | None = None

    def to_dict(self) -> dict[str, object]:
        """A JSON-ready summary (what ``simulate --json`` prints)."""
        return {
            "recording": None if self.recording is None else self.recording.to_dict(),
            "out_dir": str(self.out_dir),
            "truth_dir": str(self.truth_dir),
            "c3d": str(self.c3d_path),
            "csv": str(self.csv_path),
            "scenario": self.scenario.name,
            "motion": self.scenario.motion_source,
            "seed": self.seed,
            "seconds": self.seconds,
            "body_markers": self.num_body_markers,
            "clapper_markers": self.num_clapper_markers,
            "vicon_rate_hz": self.vicon_rate_hz,
            "vicon_frames": self.vicon_frames,
            "vicon_gap_fraction": self.vicon_gap_fraction,
            "truth_rate_hz": self.truth_rate_hz,
            "clap_times_ns": list(self.clap_times_ns),
            "elapsed_s": self.elapsed_s,
        }


def simulate_session(
    out_dir: str | Path,
    *,
    scenario: str = "default",
    seed: int = 0,
    seconds: float = 10.0,
    motion_path: str | Path | None = None,
    joint_map: Mapping[str, str] | None = None,
    noise: NoiseSettings | None = None,
    truth_rate_hz: float = 1000.0,
    overwrite: bool = False,
    progress: Callable[[str], Progress | None] | None = None,
    devices: Sequence[Device] = (),
    cameras: int | None = None,
    davis_dvs: bool = False,
    d415_timing: D415Timing | PulseAt | None = None,
    world: WorldKind | WorldParams = "nominal",
) -> SimulationResult:
    """Build a scenario and write its ground truth and simulated Vicon capture.

    Args:
        out_dir: The session folder (created; must be empty unless ``overwrite``).
        scenario: A key of :data:`mocaprig.drivers_mock.scenario.SCENARIOS`.
        seed: The seed.
        seconds: Session length (s), at least 3.
        motion_path: A BVH file to retarget onto the actor instead of the scenario's motion.
        joint_map: Our joint name -> the BVH's joint name, for a skeleton the exporter tables
            of :mod:`mocaprig.process.body.bvh_names` do not cover.
        noise: Noise settings (default :class:`NoiseSettings`).
        truth_rate_hz: Sampling rate of the truth (Hz).
        overwrite: Write into a non-empty folder, replacing what this function writes.
        progress: Optional factory ``label -> (done, total) callback`` for each stage
            (``"retarget"`` with a BVH, ``"truth"``, ``"vicon"``, ``"record"``), e.g.
            ``mocaprig.cli.ProgressBar``.
        devices: Devices recorded into ``session.mcap`` (:func:`record_session`); ``()``
            (the default here; ``mocaprig simulate`` records every device by default) writes
            no recording.
        cameras: D415 count (default: every rig D415, 4).
        davis_dvs: Run the DAVIS DVS module (~10x the DAVIS simulation cost).
        d415_timing: The D415s' undocumented sync timing (``Rig.d415_timing``): a
            :class:`~mocaprig.drivers_mock.rig.D415Timing` or a preset's name,
            ``"exposure-start"`` (the default) or ``"readout-start"`` (Intel's answers for the
            D4xx family: pulse at the master's readout start, slaves 0.77 ms after it); see
            :func:`~mocaprig.drivers_mock.scenario.build_scenario`. The mock D415s, the DAVIS
            trigger input, the sync box and the Vicon sync channel all follow it, and
            ``truth/scenario.json`` records it under ``rig.d415_timing``; the clocks of the
            truth are the same under either timing.
        world: The hidden world parameters (:mod:`~mocaprig.drivers_mock.world`):
            ``"nominal"`` (the default, the same sessions as before), ``"random"`` (drawn from
            the seed) or a :class:`~mocaprig.drivers_mock.world.WorldParams`; recorded in
            ``truth/scenario.json`` under ``world``, never in the recording or the C3D.

    Raises:
        RecordingError: the folder is not empty (without ``overwrite``) or cannot be written.
        ValidationError: bad scenario name, seed, length or D415 timing.
        ProcessingError: the BVH motion cannot be read or retargeted.
    """
    t0 = time.monotonic()
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        msg = f"output {out} exists and is not a folder; choose another --out"
        raise RecordingError(msg)
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        msg = f"output folder {out} is not empty; choose another --out or pass --overwrite"
        raise RecordingError(msg)

    def stage(label: str) -> Progress | None:
        return None if progress is None else progress(label)

    scene = build_scenario(
        scenario,
        seed=seed,
        seconds=seconds,
        motion_path=motion_path,
        joint_map=joint_map,
        noise=noise,
        progress=stage("retarget") if motion_path is not None else None,
        d415_timing=d415_timing,
        world=world,
    )
    truth_dir = write_truth(
        scene, out, rate_hz=truth_rate_hz, overwrite=True, progress=stage("truth")
    )
    capture = simulate_vicon(scene, progress=stage("vicon"))
    write_vicon_truth(capture, out)
    c3d_path = out / "vicon" / "session.c3d"
    if "d415" not in devices:
        # With D415s the C3D gets their sync channel: written once their pulses are known.
        write_c3d(capture, c3d_path, subject=scene.rig.vicon.subject)
    csv_path = write_nexus_csv(capture, out / "vicon" / "session.csv")
    recording = None
    if devices:
        session_mcap = out / "session.mcap"
        if session_mcap.exists():
            if not overwrite:  # pragma: no cover - the folder check above refuses first
                msg = f"{session_mcap} exists; pass --overwrite"
                raise RecordingError(msg)
            session_mcap.unlink()
        recording = record_session(
            scene,
            session_mcap,
            devices=devices,
            cameras=cameras,
            davis_dvs=davis_dvs,
            truth_dir=truth_dir,
            progress=stage("record"),
        )
        if recording.sync_pulses_ns:
            sync = simulate_sync_channel(
                capture,
                scene.clocks["vicon"],
                np.asarray(recording.sync_pulses_ns, dtype=np.int64),
                rng=scene.rng("vicon-sync"),
                wiring=SyncWiring.for_world(scene.world_params),
            )
            _write_sync_truth(truth_dir / "vicon_sync.npz", sync, recording.sync_pulses_ns)
            write_c3d(capture, c3d_path, subject=scene.rig.vicon.subject, analogs=sync)
        elif "d415" in devices:  # pragma: no cover - a recorded master always pulses
            write_c3d(capture, c3d_path, subject=scene.rig.vicon.subject)
    elapsed = time.monotonic() - t0
    _log.info("simulated %.2f s session (seed %d) into %s in %.1f s", seconds, seed, out, elapsed)
    return SimulationResult(
        out_dir=out,
        truth_dir=truth_dir,
        c3d_path=c3d_path,
        csv_path=csv_path,
        scenario=scene,
        seed=scene.seed,
        seconds=scene.seconds,
        num_body_markers=len(scene.marker_names),
        num_clapper_markers=len(scene.clapperboard.marker_names),
        vicon_rate_hz=capture.rate_hz,
        vicon_frames=capture.num_frames,
        vicon_gap_fraction=capture.gap_fraction,
        truth_rate_hz=truth_rate_hz,
        clap_times_ns=scene.clap_times_ns,
        elapsed_s=elapsed,
        recording=recording,
    )


def record_session(
    world: Scenario,
    path: Path,
    *,
    devices: Sequence[Device] = DEVICES,
    cameras: int | None = None,
    davis_dvs: bool = False,
    truth_dir: Path | None = None,
    compression: Literal["zstd", "lz4", "none"] = "lz4",
    progress: Progress | None = None,
) -> SessionRecording:
    """Record the whole simulated session of ``world`` into ``path`` (module doc).

    Devices: ``davis`` (APS frames, IMU, trigger input, and DVS events with ``davis_dvs``),
    ``d415`` (the first ``cameras`` rig D415, master first, IR + depth, 848×480@30), ``syncbox``
    (listening to the D415 master's pulses; needs ``d415``). With ``truth_dir``, every mock
    D415 capture (delivered or not) goes to ``truth_dir/d415_captures.npz``, and the DAVIS's
    recorded time base (its last timestamp reset) to ``truth_dir/davis_clock.json``.

    Raises:
        ValidationError: an unknown device, a bad camera count, ``syncbox`` without ``d415``.
        RecordingError: ``path`` exists, a device failed or something was dropped.
    """
    from mocaprig.acquire.camera_backends import open_cameras
    from mocaprig.acquire.davis240c import Davis240C
    from mocaprig.acquire.depth_camera import SensorOptions, StreamConfig, SyncMode
    from mocaprig.acquire.record_session import record_to_file
    from mocaprig.acquire.record_sources import DavisSource, DepthCameraSource, SyncBoxSource
    from mocaprig.acquire.recorder import StreamSource
    from mocaprig.acquire.syncbox import SyncBox
    from mocaprig.drivers_mock.davis240c_sim import DavisSimulator
    from mocaprig.drivers_mock.davis240c_usb import mock_backend
    from mocaprig.drivers_mock.syncbox import MockSyncBox

    chosen = tuple(dict.fromkeys(devices))
    unknown = [d for d in chosen if d not in DEVICES]
    if unknown or not chosen:
        msg = f"devices must be a non-empty subset of {list(DEVICES)}, got {list(devices)}"
        raise ValidationError(msg)
    n_rig = len(world.rig.d415)
    n_cams = (n_rig if cameras is None else int(cameras)) if "d415" in chosen else 0
    if "d415" in chosen and not (1 <= n_cams <= n_rig):
        msg = f"cameras must lie in 1..{n_rig} (the rig's D415 count), got {cameras}"
        raise ValidationError(msg)
    if "syncbox" in chosen and "d415" not in chosen:
        msg = "the sync box listens to the D415 master's pulses: add d415 to the devices"
        raise ValidationError(msg)
    if path.exists():
        msg = f"{path} exists already; not overwriting a recording"
        raise RecordingError(msg)

    t_start = time.monotonic()
    closers: list[Any] = []
    sources: list[StreamSource] = []
    followers: list[StreamSource] = []
    d415s: list[Any] = []
    cam: Any = None
    davis_sim: Any = None
    try:
        master_pulses: Callable[[int], int | None] | None = None
        if n_cams:
            d415s = list[Any](open_cameras("mock", scenario=world, count=n_cams, pacing="asap"))
            closers.extend(reversed(d415s))
            mode, opts = StreamConfig(), SensorOptions()
            for i, d in enumerate(d415s):
                d.configure(
                    stream=mode,
                    options=opts,
                    sync_mode=SyncMode.MASTER if i == 0 else SyncMode.SLAVE,
                )
            # Every camera starts at simulated time 0 (deterministic), master first.
            for d in d415s:
                d.start()
            master_pulses = d415s[0].pulse_at_or_after
            sources.extend(
                DepthCameraSource(
                    d, stream=mode, options=opts, manage_streaming=False, offline=True
                )
                for d in d415s
            )
        if "davis" in chosen:
            sim = DavisSimulator(world, sync_source=master_pulses)
            davis_sim = sim
            backend = mock_backend(
                source=sim, scenario=world, seed=world.seed, serial=world.rig.davis.serial
            )
            big = 1 << 40  # offline: the driver's queues must never drop (memory follows the sim)
            cam = Davis240C.open(
                backend=backend,
                queue_packets=1 << 30,
                queue_bytes=big,
                raw_queue_bytes=big,
                settle_delays_s=(0.0, 0.0, 0.0),
            )
            closers.append(cam)
            # Held device time: the timestamp reset lands at session time 0 (deterministic).
            backend.hold()
            cam.start()
            if not davis_dvs:
                from mocaprig.acquire.davis240c_config import DvsParam, Module

                cam.config_set(Module.DVS, DvsParam.RUN, 0)
            end_t_us = math.floor(float(sim.device_us(world.duration_ns)))
            sources.append(
                DavisSource(
                    cam, manage_streaming=False, dvs=davis_dvs, offline=True, end_t_us=end_t_us
                )
            )
            backend.release()
        if "syncbox" in chosen:
            rig = d415s[0].rig
            mock_box = MockSyncBox(
                seed=world.seed, pulse_source=master_pulses, session_clock_ns=rig.now_ns
            )
            closers.append(mock_box)
            box = SyncBox(mock_box.port)
            box.open()
            closers.append(box)
            followers.append(SyncBoxSource(box, report_interval_ms=100))
        metadata = {
            "session": {
                "mock": "true",
                "simulated": "true",
                "scenario": world.name,
                "seed": str(world.seed),
                "seconds": repr(world.seconds),
                "motion": str(world.motion_source),
                "devices": ",".join(chosen),
                "d415_count": str(n_cams),
                "davis_dvs": str(davis_dvs).lower(),
            }
        }
        watcher = _Progress(progress, world.duration_ns, d415s)
        summary = record_to_file(
            path,
            sources,
            seconds=None,
            followers=followers,
            metadata=metadata,
            compression=compression,
            min_free_mb=64.0,
            status_line=False,
        )
        watcher.done()
    finally:
        for d in d415s:
            if d.is_streaming:
                d.stop()
        for dev in reversed(closers):
            try:
                dev.close()
            except Exception as err:  # closing must not hide the outcome
                _log.warning("closing %s failed: %s", dev, err)
    pulses: list[int] = []
    if d415s:
        master = d415s[0]
        t = master.pulse_at_or_after(0)
        while t is not None and t <= world.duration_ns:
            pulses.append(int(t))
            t = master.pulse_at_or_after(t + 1)
    driver_drops = 0
    if cam is not None:
        st = cam.stats()
        driver_drops = int(st.packets_dropped) + int(st.raw_bytes_dropped)
    if truth_dir is not None and d415s:
        _write_captures(truth_dir / "d415_captures.npz", d415s)
    if truth_dir is not None and davis_sim is not None:
        _write_davis_clock(truth_dir / "davis_clock.json", world, davis_sim)
    if summary.drops_total or driver_drops:
        msg = (
            f"recording {path}: {summary.drops_total} messages and {driver_drops} DAVIS driver "
            "packets/bytes dropped although the simulated devices wait for the recorder; "
            "this is a bug, report it"
        )
        raise RecordingError(msg)
    streams = tuple((s.topic, s.written, s.dropped) for s in summary.streams)
    return SessionRecording(
        path=path,
        devices=chosen,
        cameras=n_cams,
        davis_dvs=davis_dvs,
        streams=streams,
        drops_total=summary.drops_total,
        davis_driver_drops=driver_drops,
        bytes=summary.bytes,
        elapsed_s=time.monotonic() - t_start,
        sync_pulses_ns=tuple(pulses),
    )


class _Progress:
    """Reports the D415 rig's simulated time as progress (a background thread)."""

    def __init__(self, progress: Progress | None, total_ns: int, d415s: Sequence[Any]) -> None:
        import threading

        self._cb = progress
        self._total_ms = max(total_ns // 1_000_000, 1)
        self._rig = d415s[0].rig if d415s else None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if progress is not None and self._rig is not None:
            self._thread = threading.Thread(target=self._run, name="simulate-progress", daemon=True)
            self._thread.start()

    def _run(self) -> None:
        cb, rig = self._cb, self._rig
        if cb is None or rig is None:
            return
        while not self._stop.wait(0.5):
            cb(min(int(rig.now_ns()) // 1_000_000, self._total_ms), self._total_ms)

    def done(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self._cb is not None:
            self._cb(self._total_ms, self._total_ms)


def _write_captures(path: Path, d415s: Sequence[Any]) -> None:
    """Every capture of every mock D415 (session ns; -1 = none) as ground truth."""
    arrays: dict[str, np.ndarray[Any, Any]] = {}
    for d in d415s:
        caps = d.captures
        key = f"{d.spec.name}__{d.info.serial}"
        arrays[f"{key}__frame_counter"] = np.array([c.frame_counter for c in caps], np.int64)
        arrays[f"{key}__exposure_start_ns"] = np.array(
            [c.exposure_start_ns for c in caps], np.int64
        )
        arrays[f"{key}__exposure_ns"] = np.array([c.exposure_ns for c in caps], np.int64)
        arrays[f"{key}__arrival_ns"] = np.array([c.arrival_ns for c in caps], np.int64)
        arrays[f"{key}__pulse_ns"] = np.array(
            [-1 if c.pulse_ns is None else c.pulse_ns for c in caps], np.int64
        )
        arrays[f"{key}__delivered"] = np.array(
            [c.outcome in ("delivered", "incomplete") for c in caps], bool
        )
        arrays[f"{key}__is_master"] = np.array(d.sync_mode.name == "MASTER")
    with path.open("wb") as f:  # truth/ is rewritten as a whole by simulate_session
        np.savez(f, **arrays)  # type: ignore[arg-type]


def _write_sync_truth(path: Path, sync: AnalogCapture, pulses_ns: Sequence[int]) -> None:
    """The sync channel's truth: the master's pulses and the switch instants of the signal
    (session ns; switch = pulse + the box's latency), its polarity and RC time constant."""
    with path.open("wb") as f:
        np.savez(
            f,
            pulse_ns=np.asarray(pulses_ns, dtype=np.int64),
            switch_ns=np.asarray(sync.edges_ns, dtype=np.int64),
            rising=np.asarray(sync.edge_rising, dtype=bool),
            tau_ns=np.array(sync.tau_ns),
            rate_hz=np.array(sync.rate_hz),
            channel=np.array(sync.labels[0]),
        )


def _write_davis_clock(path: Path, world: Scenario, sim: Any) -> None:
    """The recorded DAVIS time base as ground truth: the session instant of its last timestamp
    reset and the formula from session time to the recorded device time."""
    import json

    clock = world.clocks["davis"]
    data = {
        "format_version": 1,
        "device": f"davis/{world.rig.davis.serial}",
        "clock": "davis",
        "reset_session_ns": int(np.asarray(sim.session_ns(0)).item()),
        "drift_ppm": float(clock.drift_ppm),
        "formula": "recorded_device_ns = (t_ns - reset_session_ns) * (1 + drift_ppm * 1e-6), "
        "stamped in whole us (floored)",
    }
    path.write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
