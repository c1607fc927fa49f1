"""Simulate a session: the ground truth plus the simulated Vicon exports, in one folder.

``simulate_session`` is the typed function behind ``mocaprig simulate`` (and the ``demo``)::

    <out>/truth/truth.npz, scenario.json, vicon_truth.npz    (drivers_mock.truth)
    <out>/vicon/session.c3d                                  float C3D, mm, 120 Hz
    <out>/vicon/session.csv                                  Nexus Trajectories CSV, same values
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from acquire.errors import RecordingError
from drivers_mock.noise import NoiseSettings
from drivers_mock.scenario import Scenario, build_scenario
from drivers_mock.truth import write_truth, write_vicon_truth
from drivers_mock.vicon import simulate_vicon, write_c3d, write_nexus_csv

__all__ = ["SimulationResult", "simulate_session"]

_log = logging.getLogger(__name__)

Progress = Callable[[int, int], None]


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

    def to_dict(self) -> dict[str, object]:
        """A JSON-ready summary (what ``simulate --json`` prints)."""
        return {
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
    noise: NoiseSettings | None = None,
    truth_rate_hz: float = 1000.0,
    overwrite: bool = False,
    progress: Callable[[str], Progress | None] | None = None,
) -> SimulationResult:
    """Build a scenario and write its ground truth and simulated Vicon capture.

    Args:
        out_dir: The session folder (created; must be empty unless ``overwrite``).
        scenario: A key of :data:`drivers_mock.scenario.SCENARIOS`.
        seed: The seed.
        seconds: Session length (s), at least 3.
        motion_path: A BVH file to retarget onto the actor instead of the scenario's motion.
        noise: Noise settings (default :class:`NoiseSettings`).
        truth_rate_hz: Sampling rate of the truth (Hz).
        overwrite: Write into a non-empty folder, replacing what this function writes.
        progress: Optional factory ``label -> (done, total) callback`` for each stage
            (``"retarget"`` with a BVH, ``"truth"``, ``"vicon"``), e.g. ``acquire.cli.ProgressBar``.

    Raises:
        RecordingError: the folder is not empty (without ``overwrite``) or cannot be written.
        ValidationError: bad scenario name, seed or length.
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

    world = build_scenario(
        scenario,
        seed=seed,
        seconds=seconds,
        motion_path=motion_path,
        noise=noise,
        progress=stage("retarget") if motion_path is not None else None,
    )
    truth_dir = write_truth(
        world, out, rate_hz=truth_rate_hz, overwrite=True, progress=stage("truth")
    )
    capture = simulate_vicon(world, progress=stage("vicon"))
    write_vicon_truth(capture, out)
    c3d_path = write_c3d(capture, out / "vicon" / "session.c3d", subject=world.rig.vicon.subject)
    csv_path = write_nexus_csv(capture, out / "vicon" / "session.csv")
    elapsed = time.monotonic() - t0
    _log.info("simulated %.2f s session (seed %d) into %s in %.1f s", seconds, seed, out, elapsed)
    return SimulationResult(
        out_dir=out,
        truth_dir=truth_dir,
        c3d_path=c3d_path,
        csv_path=csv_path,
        scenario=world,
        seed=world.seed,
        seconds=world.seconds,
        num_body_markers=len(world.marker_names),
        num_clapper_markers=len(world.clapperboard.marker_names),
        vicon_rate_hz=capture.rate_hz,
        vicon_frames=capture.num_frames,
        vicon_gap_fraction=capture.gap_fraction,
        truth_rate_hz=truth_rate_hz,
        clap_times_ns=world.clap_times_ns,
        elapsed_s=elapsed,
    )
