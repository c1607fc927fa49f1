"""Calibrate a recorded D415 rig against a Vicon trial; score a calibration against truth.

:func:`calibrate_vicon` (``mocaprig calibrate vicon``):

1. **Vicon**: the trial's trajectories (metres), frame times on the Vicon clock
   ``(first_frame − 1 + i)/rate``; a unit check on the marker cloud's extent; the **static
   start** (markers within ``static_tolerance_m`` of the first frames) and its median cloud; the
   claps (``mocaprig.calib.time_align.find_claps_vicon``; none is an error).
2. **Reading**: the recording is measured (``calib.markers.measure_frame``) only in device-time
   windows — the first ``head_window_s``, around each Vicon clap, and ``extra_windows`` (each
   with its neighbour where the Vicon markers move fastest) — found by bisection over the host
   log time, all cameras in one pass per window.
3. **Registration** per camera on its static start (blobs still within
   ``static_tolerance_px``): :func:`calib.registration.register_camera` (coarse alignment without
   an initial pose, gated matching, bundle adjustment).
4. **Clock** (``clock_method``): reprojection offsets of 0.5 s stretches of frames per camera;
   the cameras whose frames pair with one another's (hardware sync, checked, not assumed) share
   one line through all their stretches (offset, drift) composed with each camera's tie to the
   pivot camera (:func:`~mocaprig.calib.vicon_calibration_pooled_clock.pooled_clocks`);
   optionally refined by ``mocaprig.calib.time_align``.
   With a **sync channel** in the Vicon trial (``CalibrationOptions.sync_channel``, default
   ``D415_SYNC``: the sync box's toggle output on a Vicon analog input, docs/wiring.md §7),
   the master's clock is instead the line through the channel's edges paired with its frames
   (``calib.time_align.clock_from_sync_edges``, the video clock as the pairing prior), and every
   camera tied to it by frame counters in the pool gets it through its tie plus its trigger
   delay (:func:`~mocaprig.calib.vicon_calibration_sync.sync_clocks`); without the channel, or
   when it is unusable, the video clocks stay and a note says why.
5. **Final bundle adjustment** over all frames read, the Vicon markers interpolated at each
   frame's mapped time (fast markers and partly occluded blobs left out); clock and pose are
   iterated twice.
6. **Refusal**: a camera whose reprojection RMS exceeds ``max_rms_px`` (default
   :data:`MAX_RMS_PX` = 1.5 px) or with fewer than ``min_inliers`` (default 30) inlier
   observations makes the calibration fail with the figures, unless ``force`` is set.

7. **DAVIS clock** (when the recording has ``/davis/<serial>/trigger``): the D415 master's sync
   pulses on the DAVIS's external input, paired with the master's frames
   (``calib.time_align.clock_from_pulses``) and composed with the master's Vicon mapping; see
   :func:`~mocaprig.calib.vicon_calibration_davis.davis_clock` for the pairing prior. The
   DAVIS's extrinsics come from ``mocaprig calibrate board``.

:func:`evaluate_calibration` (``mocaprig calibrate evaluate``) compares a calibration with a
simulated session's truth (``SIMDIR/truth/scenario.json``, read directly: calib/ never imports
the simulator).

The steps live in modules of their own; this one runs them and re-exports the public names
that callers import from it:

- :mod:`~mocaprig.calib.vicon_calibration_options`: :class:`CalibrationOptions`;
- :mod:`~mocaprig.calib.vicon_calibration_frames`: the D415 cameras and the frames read (2);
- :mod:`~mocaprig.calib.vicon_calibration_static`: the static starts and the registration (1, 3);
- :mod:`~mocaprig.calib.vicon_calibration_video_clock`: each camera's clock from its video (4);
- :mod:`~mocaprig.calib.vicon_calibration_pooled_clock`: one clock for the synchronised D415s;
- :mod:`~mocaprig.calib.vicon_calibration_sync`: the clocks from the Vicon sync channel;
- :mod:`~mocaprig.calib.vicon_calibration_davis`: the DAVIS clock through the pulses (7);
- :mod:`~mocaprig.calib.calibration_attachment`: :func:`attach_calibration`;
- :mod:`~mocaprig.calib.calibration_eval`: :func:`evaluate_calibration`.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import logging
import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from mocaprig import __version__
from mocaprig.acquire.recording import Recording
from mocaprig.calib.calibration import Calibration, CameraCalibration, ClockMapping
from mocaprig.calib.calibration_attachment import ATTACHMENT_NAME, attach_calibration
from mocaprig.calib.calibration_eval import DeviceEvaluation, Evaluation, evaluate_calibration
from mocaprig.calib.clap_detection import ClapDetection
from mocaprig.calib.markers import MarkerFrame
from mocaprig.calib.registration import CameraRegistration, register_camera
from mocaprig.calib.vicon_calibration_davis import (
    DavisPulses,
    davis_clock,
    davis_motion,
    davis_pulse_inputs,
    motion_period_shift,
)
from mocaprig.calib.vicon_calibration_frames import (
    CalibCamera,
    calib_cameras,
    first_frames,
    read_device_window,
)
from mocaprig.calib.vicon_calibration_options import (
    MAX_RMS_PX,
    CalibrationOptions,
    D415PulseTiming,
)
from mocaprig.calib.vicon_calibration_pooled_clock import Tie, pooled_clocks, tie_by_counters
from mocaprig.calib.vicon_calibration_static import (
    ViconStatic,
    register_static_start,
    vicon_static_start,
)
from mocaprig.calib.vicon_calibration_sync import (
    SyncInputs,
    sync_channel_edges,
    sync_channel_inputs,
    sync_clocks,
)
from mocaprig.calib.vicon_calibration_video_clock import (
    ViconInterp,
    claps_speed_clock,
    grid_offset,
    line_clock,
    reprojection_cost,
    stretch_offsets,
    stretch_weights,
)
from mocaprig.calib.vicon_records import MarkerTrajectories
from mocaprig.errors import CalibrationError, RecordingError

__all__ = [
    "ATTACHMENT_NAME",
    "MAX_RMS_PX",
    "CalibrationOptions",
    "DeviceEvaluation",
    "Evaluation",
    "ViconCalibrationResult",
    "ViconStatic",
    "attach_calibration",
    "calibrate_vicon",
    "evaluate_calibration",
    "vicon_static_start",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

# The steps' former private names in this module, which the tests still reach.
_line_clock = line_clock
_pooled_clocks = pooled_clocks
_tie_by_counters = tie_by_counters
_Tie = Tie
_sync_clocks = sync_clocks
_SyncInputs = SyncInputs
_sync_channel_edges = sync_channel_edges
_davis_clock = davis_clock
_DavisPulses = DavisPulses


@dataclass(frozen=True, slots=True)
class ViconCalibrationResult:
    """What :func:`calibrate_vicon` found, with diagnostics for the report.

    Attributes:
        calibration: The calibration (cameras with residual statistics, clock mappings).
        registrations: Per camera label, the registration (coarse and final pose, observations).
        static_frames: Per camera label, the number of still D415 frames used.
        vicon: The Vicon static start.
        refused: Cameras above the thresholds (written anyway because ``force`` was set).
        notes: Human-readable remarks (what was not done and why).
        vicon_claps: The claps found in the Vicon trial (for the report).
        clock_fits: Per camera, the reprojection clock's stretches: device times (ns), offsets
            (ns) and their 1σ (ns) (for the report).
        trajectories: The Vicon trial as read (the report draws the volume its markers span);
            None in a result built without it.
    """

    calibration: Calibration
    registrations: Mapping[str, CameraRegistration] = field(repr=False)
    static_frames: Mapping[str, int]
    vicon: ViconStatic = field(repr=False)
    refused: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()
    vicon_claps: tuple[ClapDetection, ...] = field(default=(), repr=False)
    clock_fits: Mapping[str, tuple[F64, F64, F64]] = field(default_factory=dict, repr=False)
    trajectories: MarkerTrajectories | None = field(default=None, repr=False, compare=False)

    def summary(self) -> dict[str, Any]:
        """Plain JSON-able figures (``--json``)."""
        cams = []
        for c in self.calibration.cameras:
            cams.append(
                {
                    "name": c.name,
                    "serial": c.serial,
                    "static_frames": self.static_frames.get(c.name, 0),
                    **dict(c.residuals),
                    "camera_centre_m": c.T_world_cam[:3, 3].tolist(),
                }
            )
        clocks = [
            {
                "device": k.device,
                "offset_ns": k.offset_ns,
                "drift_ppm": k.drift_ppm,
                "offset_sigma_ns": k.offset_sigma_ns,
                "method": k.method,
            }
            for k in self.calibration.clocks
        ]
        return {
            "cameras": cams,
            "clocks": clocks,
            "vicon_static_frames": self.vicon.n_frames,
            "refused": list(self.refused),
            "notes": list(self.notes),
            "statistics": dict(self.calibration.statistics),
        }


#: How far (fraction of the session) an extra clock window may move from its nominal place
#: to where the Vicon markers move fastest.
_WINDOW_REACH: Final = 0.05


def _busiest_windows(
    t_ns: I64, positions_m: F64, centres_ns: Sequence[int], *, reach_ns: int, half_ns: int
) -> list[int]:
    """Per centre in ``centres_ns`` (Vicon ns), the centre of the window of ±``half_ns`` within
    ``reach_ns`` of it where the Vicon markers (positions ``(F, M, 3)`` m at ``t_ns``) move
    fastest on average (the centre itself when no window fits).

    A stretch's clock offset is only as good as its markers' image speed (a blob bias of a
    fraction of a pixel reads as bias / speed), so the clock's windows go where the actor
    moves, close enough to their nominal place to keep the spread the drift needs."""
    if len(t_ns) < 3:
        return list(centres_ns)
    dt = np.diff(t_ns).astype(np.float64) * 1e-9
    step = np.linalg.norm(np.diff(positions_m, axis=0), axis=2) / dt[:, None]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # frames with every marker in a gap
        speed = np.nan_to_num(np.nanmean(step, axis=1), nan=0.0)
    cum = np.concatenate([[0.0], np.cumsum(speed)])
    mids = t_ns[1:].astype(np.float64)
    lo = np.searchsorted(mids, mids - half_ns)
    hi = np.searchsorted(mids, mids + half_ns)
    mean = (cum[hi] - cum[lo]) / np.maximum(hi - lo, 1)
    inside = (mids - half_ns >= mids[0]) & (mids + half_ns <= mids[-1])
    out = []
    for centre_ns in centres_ns:
        ok = inside & (np.abs(mids - centre_ns) <= reach_ns)
        out.append(int(mids[np.flatnonzero(ok)[np.argmax(mean[ok])]]) if ok.any() else centre_ns)
    return out


def _merge_windows(windows: Sequence[tuple[int, int]]) -> list[tuple[int, int]]:
    out: list[tuple[int, int]] = []
    for lo, hi in sorted(windows):
        if out and lo <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], hi))
        else:
            out.append((lo, hi))
    return out


def _with_pulse_timing(opt: CalibrationOptions, timing: D415PulseTiming) -> CalibrationOptions:
    """``opt`` with ``timing`` as its pulse convention (``opt`` itself when it already is)."""
    if timing == opt.pulse_timing:
        return opt
    return dataclasses.replace(
        opt, d415_pulse_at=timing.pulse_at, slave_trigger_delay_us=timing.slave_trigger_delay_us
    )


def _pool_misfit_ns(
    mappings: Mapping[str, ClockMapping], fits: Mapping[str, tuple[F64, F64, F64]]
) -> float:
    """Median |stretch offset − mapping| over every camera's stretches (ns), each stretch
    weighted as in the clock line (a stretch of slow markers says little about the phase)."""
    res, wts = [], []
    for name, (t_w, d_w, s_w) in fits.items():
        if name in mappings and len(t_w):
            t = np.round(t_w).astype(np.int64)
            res.append(np.abs(t_w + d_w - mappings[name].to_reference_ns(t)))
            wts.append(stretch_weights(s_w))
    if not res:
        return math.nan
    r, w = np.concatenate(res), np.concatenate(wts)
    ok = np.isfinite(r) & np.isfinite(w)
    if not ok.any():
        return math.nan
    order = np.argsort(r[ok])
    cum = np.cumsum(w[ok][order])
    return float(r[ok][order][np.searchsorted(cum, 0.5 * cum[-1])])


def _choose_pool(
    pools: Sequence[
        tuple[D415PulseTiming, dict[str, ClockMapping], list[str], dict[str, Tie], float]
    ],
    opt: CalibrationOptions,
) -> tuple[D415PulseTiming, dict[str, ClockMapping], list[str], dict[str, Tie], list[str], bool]:
    """The pooled video clock whose convention the stretches fit best, when clearly so (the
    other's misfit exceeds it by 0.5 ms and by itself); else the assumed one. Also notes, and
    whether the video told the convention (True too when there was nothing to choose)."""
    first = pools[0]
    if len(pools) < 2:
        return (*first[:4], [], True)
    if not (math.isfinite(pools[0][4]) and math.isfinite(pools[1][4])):
        return (*first[:4], [], False)
    best, worst = sorted(pools, key=lambda p: p[4])
    if worst[4] - best[4] > max(500_000.0, best[4]):
        note = (
            f"clock: pulse phase from the video: {best[0].describe()} (the cameras' stretch "
            f"offsets fit the pooled clock within {best[4] / 1e3:.0f} µs median, "
            f"{worst[4] / 1e3:.0f} µs under the other convention)"
        )
        return (*best[:4], [note] if best[0] != opt.pulse_timing else [], True)
    note = (
        "clock: the video does not tell the pulse phase (the stretch offsets fit both "
        f"conventions' pooled clocks, {pools[0][4] / 1e3:.0f} / {pools[1][4] / 1e3:.0f} µs "
        f"median): {opt.pulse_timing.describe()} assumed"
    )
    return (*first[:4], [note], False)


#: A pooled clock's reprojection cost must be below this fraction of the other convention's
#: to tell the pulse phase when the stretch offsets do not.
_POOL_COST_RATIO = 0.97
#: ... and, in the final pass, the better pool's stretch misfit below this fraction of the
#: master's exposure (the shift the phase makes): with video clocks several ms off, the cost
#: prefers whichever pool their error happens to favour (world 1013: 6.3 ms misfits, an
#: 8.5 ms exposure, the wrong phase at a cost ratio of 0.78).
_POOL_COST_MAX_MISFIT = 0.25


def _with_timing(
    dp: DavisPulses, cams: Sequence[CalibCamera], timing: D415PulseTiming
) -> DavisPulses:
    """A DAVIS's pulse inputs with the master's frame delay of ``timing`` (the measured pulse
    phase instead of the assumed one)."""
    master = next((c for c in cams if c.name == dp.master), None)
    if master is None or master.exposure_us is None:
        return dp
    delay = timing.master_frame_delay_ns(float(master.exposure_us) * 1e3)
    return dataclasses.replace(dp, frame_delay_ns=delay)


def _assumption_notes(
    opt: CalibrationOptions, timing: D415PulseTiming, *, sync_used: bool
) -> list[str]:
    """What the recording cannot tell, the value taken and what a wrong one does."""
    out = [
        (
            f"assumption: a D415 slave exposes {timing.slave_trigger_delay_us:g} µs after the "
            "pulse (not observable: the video clocks are good to ≈ 0.1–0.5 ms); a slave whose "
            "true delay differs by d has its clock d off (published: 0–0.2 ms with the pulse "
            "at the exposure start, 0.7–0.9 ms at the readout start); measure it, "
            "docs/d415-timing.md §4"
        )
    ]
    if sync_used:
        out.append(
            f"assumption: the sync box toggles {opt.sync_latency_us:g} µs after the master's "
            "pulse (a pure delay, not observable from the recording: every D415 clock is "
            "off by the true latency minus this, e.g. up to 48 µs for a box with 50 µs); "
            "measure pulse in vs toggle out with a scope (CalibrationOptions.sync_latency_us)"
        )
        out.append(
            "assumption: analog sample 0 of a Vicon frame is taken at the frame's time (a "
            "skew between the analog and the frame clocks shifts every sync clock by it)"
        )
    else:
        out.append(
            "without the sync channel the pulse phase comes from the pooled video clock alone "
            f"({timing.describe()}); where the video cannot tell it, a wrong assumption moves "
            "the DAVIS ↔ D415 relation by one exposure"
        )
    return out


def _pool_by_cost(
    costs: Sequence[float], misfits_ns: Sequence[float], exposure_ns: float, *, final: bool
) -> int | None:
    """The pool (of two) whose reprojection cost tells the pulse phase: below
    :data:`_POOL_COST_RATIO` × the other's and, in the ``final`` pass, with pooled clocks whose
    better stretch misfit is below :data:`_POOL_COST_MAX_MISFIT` × the master's exposure;
    None when the cost does not tell."""
    if final and not min(misfits_ns) < _POOL_COST_MAX_MISFIT * exposure_ns:
        return None
    lo = int(np.argmin(costs))
    if math.isfinite(costs[lo]) and costs[lo] < _POOL_COST_RATIO * costs[1 - lo]:
        return lo
    return None


def _master(cams: Sequence[CalibCamera]) -> CalibCamera | None:
    """The D415 master (``sync_mode`` 1) among ``cams``, if any."""
    return next((c for c in cams if c.sync_mode == 1), None)


def _master_exposure_ns(cams: Sequence[CalibCamera]) -> float:
    """The D415 master's exposure (ns); 8.5 ms when it is unknown."""
    master = _master(cams)
    if master is None or master.exposure_us is None:
        return 8.5e6
    return float(master.exposure_us) * 1e3


def _expected_slave_delays(
    cams: Sequence[CalibCamera], timing: D415PulseTiming
) -> dict[str, float]:
    """Per slave (``sync_mode`` 2) its frame stamp minus the master's of the same pulse under
    ``timing`` (ns, :meth:`D415PulseTiming.slave_delay_ns`: the trigger delay, half their
    exposure difference and, with the pulse at the master's readout start, the master's
    exposure); the trigger delay alone when the master's exposure is unknown; none without a
    master. The stretch offsets then move a slave's constant away from this only as far as
    they are sure (its published spread is ±0.1 ms, about a tenth of what they resolve)."""
    master = _master(cams)
    if master is None:
        return {}
    if master.exposure_us is None:
        return {c.name: timing.slave_trigger_delay_us * 1e3 for c in cams if c.sync_mode == 2}
    m_exp = float(master.exposure_us) * 1e3
    return {
        c.name: timing.slave_delay_ns(
            m_exp, m_exp if c.exposure_us is None else float(c.exposure_us) * 1e3
        )
        for c in cams
        if c.sync_mode == 2
    }


def _refuse_unobservable_phase(
    cams: Sequence[CalibCamera],
    davis_inputs: Sequence[DavisPulses],
    opt: CalibrationOptions,
    phase_notes: list[str],
) -> None:
    """Without the sync channel, raise when the video could not tell the D415 pulse phase and
    it matters (a master with an exposure, and a slave or a DAVIS on its pulses); with
    ``opt.force`` the assumed convention stays and ``phase_notes`` says so.

    Raises:
        CalibrationError: the phase is needed, not observable, and ``opt.force`` is off."""
    master = _master(cams)
    slaves = [c.name for c in cams if c.sync_mode == 2]
    if master is None or master.exposure_us is None or not (slaves or davis_inputs):
        return
    why = phase_notes[0].removeprefix("clock: ") if phase_notes else "no pooled clock fitted"
    users = ", ".join([*slaves, *(dp.device for dp in davis_inputs)])
    if opt.force:
        phase_notes.append(
            f"clock: pulse phase NOT observable without the sync channel ({why}); the assumed "
            f"convention (--force) moves {users} by up to one master exposure "
            f"({float(master.exposure_us):.0f} µs) if wrong"
        )
        return
    msg = (
        f"{master.name}: the D415 pulse phase (where the master's sync pulse falls in its "
        f"exposure) is not observable in this recording without the Vicon sync channel: {why}. "
        f"It sets the clocks of {users} to within one master exposure "
        f"({float(master.exposure_us):.0f} µs), so the calibration is refused. Measure it once "
        "for the rig (docs/d415-timing.md §4) and pass --d415-pulse-at "
        "exposure-start|readout-start with --no-measure-pulse-phase, or record the sync box's "
        "toggle on a Vicon analog input (--sync-channel), or pass --force to keep the assumed "
        "convention"
    )
    raise CalibrationError(msg)


def calibrate_vicon(
    session_mcap: str | Path,
    vicon_c3d: str | Path,
    *,
    options: CalibrationOptions | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ViconCalibrationResult:
    """Calibrate the D415s of a recording against a Vicon trial of the same session.

    Args:
        session_mcap: The recording (``mocaprig record``).
        vicon_c3d: The Vicon trial (C3D or Nexus CSV).
        options: :class:`CalibrationOptions`.
        progress: Optional ``(done, total)`` callback.

    Returns:
        The calibration and its diagnostics.

    Raises:
        CalibrationError: unreadable inputs, wrong units, no static start, no clap, too few
            markers, no alignment, or (without ``force``) a camera above the residual
            thresholds; the message names the camera and the cause.
    """
    from mocaprig.calib.clap_detection import find_claps_vicon
    from mocaprig.calib.vicon import read_trajectories
    from mocaprig.calib.vicon_times import vicon_times_ns

    opt = options or CalibrationOptions()
    steps = 7
    done = 0

    def tick() -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, steps)

    traj = read_trajectories(vicon_c3d, unit=opt.unit)
    t_vicon = vicon_times_ns(traj)
    vicon = vicon_static_start(
        traj.positions_m,
        traj.labels,
        t_vicon,
        tolerance_m=opt.static_tolerance_m,
        source=str(vicon_c3d),
    )
    vicon_claps = find_claps_vicon(traj)
    interp = ViconInterp(t_vicon, traj.positions_m)
    tick()
    _log.info(
        "Vicon: %d still frames, %d markers, claps at %s s (Vicon clock)",
        vicon.n_frames,
        len(vicon.labels),
        [round(c.t_ns * 1e-9, 3) for c in vicon_claps],
    )
    try:
        rec = Recording(Path(session_mcap))
    except RecordingError as err:
        msg = f"cannot read the recording {session_mcap}: {err}"
        raise CalibrationError(msg) from err
    registrations: dict[str, CameraRegistration] = {}
    static_frames: dict[str, int] = {}
    clock_fits: dict[str, tuple[F64, F64, F64]] = {}
    clocks: list[ClockMapping] = []
    notes: list[str] = []
    with rec:
        cams = calib_cameras(rec, opt.cameras, str(session_mcap))
        end_log, firsts = first_frames(rec, cams, str(session_mcap))
        head_ns = round(opt.head_window_s * 1e9)
        head_windows = {c: (p.dev_ns, p.dev_ns + head_ns) for c, p in firsts.items()}
        head = read_device_window(rec, cams, head_windows, firsts, end_log)
        tick()
        poses: dict[str, F64] = {}
        deltas: dict[str, int] = {}
        t_onset_v = int(t_vicon[min(vicon.n_frames, len(t_vicon) - 1)])
        for cam in cams:
            frames = head[cam.name]
            reg, k0, n_still = register_static_start(cam, frames, vicon, opt)
            static_frames[cam.name] = n_still
            registrations[cam.name] = reg
            poses[cam.name] = reg.T_world_cam
            # Coarse clock: the motion onsets of both, then the reprojection cost on a grid.
            onset_d = frames[min(k0 + n_still, len(frames) - 1)].t_dev_ns
            prior = t_onset_v - onset_d
            deltas[cam.name] = grid_offset(
                frames, reg.T_world_cam, cam, interp, prior,
                half_width_ns=200_000_000, step_ns=2_000_000,
            )  # fmt: skip
        tick()
        # Windows with motion across the session, in Vicon time, then per camera device time.
        v_first = t_vicon[0]
        span_ns = int(t_vicon[-1] - v_first)  # ≈ the session
        windows_v = [(c.t_ns - 800_000_000, c.t_ns + 400_000_000) for c in vicon_claps]
        # The nominal windows (their slow markers serve the poses) and, near each, where the
        # markers move fastest (the clock's stretches are only as good as their speed).
        nominal = [int(v_first) + round(frac * span_ns) for frac in opt.extra_windows]
        busiest = _busiest_windows(
            t_vicon, traj.positions_m, nominal,
            reach_ns=round(_WINDOW_REACH * span_ns), half_ns=300_000_000,
        )  # fmt: skip
        for pair in zip(nominal, busiest, strict=True):
            for mid in set(pair):
                windows_v.append((mid - 300_000_000, mid + 300_000_000))
        frames_all: dict[str, list[MarkerFrame]] = {c.name: list(head[c.name]) for c in cams}
        for lo_v, hi_v in _merge_windows(windows_v):
            dev_windows = {}
            for c in cams:
                lo = max(lo_v - deltas[c.name], head_windows[c.name][1])
                dev_windows[c.name] = (lo, max(lo, hi_v - deltas[c.name]))
            if all(lo >= hi for lo, hi in dev_windows.values()):
                continue
            got = read_device_window(rec, cams, dev_windows, firsts, end_log)
            for c in cams:
                frames_all[c.name].extend(got[c.name])
        davis_inputs = davis_pulse_inputs(
            rec, cams, opt.sync_pulse_us, pulse_timing=opt.pulse_timing
        )
        davis_motions = {dp.device: davis_motion(rec, dp.device) for dp in davis_inputs}
        sync = sync_channel_inputs(
            Path(vicon_c3d),
            rec,
            cams,
            {c: np.array([f.t_dev_ns for f in fr], dtype=np.int64) for c, fr in frames_all.items()},
            opt,
        )
        tick()
    # Clocks and final poses, iterated twice: per-camera stretch offsets, then one pooled clock
    # line for the hardware-synchronised cameras, then each camera's bundle adjustment.
    mappings: dict[str, ClockMapping] = {}
    by_name = {c.name: c for c in cams}

    def shift_cost(name: str, m: ClockMapping) -> float:
        # Reprojection cost of every third frame read, at the Vicon times m gives them.
        fr = frames_all[name][::3]
        t_ref = m.to_reference_ns(np.array([f.t_dev_ns for f in fr], dtype=np.int64))
        return reprojection_cost(fr, poses[name], by_name[name], interp, t_ref, gate_px=3.0)

    # The frames read do not change between the two passes.
    stamps = {
        c.name: np.array([f.t_dev_ns for f in frames_all[c.name]], dtype=np.int64) for c in cams
    }
    counters = {
        c.name: np.array([f.frame_counter for f in frames_all[c.name]], dtype=np.int64)
        for c in cams
    }
    ties: dict[str, Tie] = {}
    timings_used: list[D415PulseTiming] = []
    phase_notes: list[str] = []
    for pass_ in range(2):
        own: dict[str, ClockMapping] = {}
        for cam in cams:
            t_w, d_w, s_w = stretch_offsets(
                cam, frames_all[cam.name], poses[cam.name], interp, deltas[cam.name],
                mappings.get(cam.name),
            )  # fmt: skip
            clock_fits[cam.name] = (t_w, d_w, s_w)
            own[cam.name] = line_clock(cam.name, t_w, d_w, s_w)
        # Where the master's pulse falls sets how much later than the master's a slave
        # exposes (0.1 ms or an exposure + 0.77 ms): pool under each convention and keep the
        # one the stretches fit (a wrong one splits the difference between the cameras).
        pools = []
        for timing in opt.pulse_timings():
            t_ties: dict[str, Tie] = {}
            pooled, p_notes = pooled_clocks(
                {c.name: (stamps[c.name], counters[c.name]) for c in cams},
                clock_fits,
                own,
                shift_cost,
                {c.name: c.sync_mode for c in cams},
                ties_out=t_ties,
                expected_delays_ns=_expected_slave_delays(cams, timing),
            )
            pools.append((timing, pooled, p_notes, t_ties, _pool_misfit_ns(pooled, clock_fits)))
        pool_timing, mappings, pool_notes, pool_ties, phase_notes, pool_told = _choose_pool(
            pools, opt
        )
        if not pool_told and len(pools) == 2:
            # The stretches do not tell: the reprojection of every camera's frames may, when
            # the pooled clocks are good enough to resolve the phase's shift (the first pass
            # only seeds the poses of the final one).
            costs = [sum(shift_cost(c.name, pl[1][c.name]) for c in cams) for pl in pools]
            by_cost = _pool_by_cost(
                costs, [pl[4] for pl in pools], _master_exposure_ns(cams), final=pass_ > 0
            )
            if by_cost is not None:
                lo = by_cost
                pool_timing, mappings, pool_notes, pool_ties = pools[lo][:4]
                pool_told = True
                phase_notes = [
                    (
                        "clock: pulse phase from the video by the reprojection cost of every "
                        f"camera's frames: {pool_timing.describe()} ({costs[lo]:.4g} vs "
                        f"{costs[1 - lo]:.4g}; the stretch offsets did not tell: "
                        f"{pools[0][4] / 1e3:.0f} / {pools[1][4] / 1e3:.0f} µs median)"
                    )
                ]
        ties.clear()
        ties.update(pool_ties)
        video = mappings
        opt_used = _with_pulse_timing(opt, pool_timing)
        # The first pass's poses are coarse: only the final pass may refuse an unobservable
        # pulse phase.
        opt_sync = opt_used if pass_ else dataclasses.replace(opt_used, force=True)
        mappings, sync_notes = sync_clocks(
            sync, video, ties, opt_sync, shift_cost, timings_used, own=own
        )
        for cam in cams:
            if opt.clock_method == "claps+speed" and mappings[cam.name] is video[cam.name]:
                mappings[cam.name] = claps_speed_clock(
                    cam.name, frames_all[cam.name], vicon_claps, traj, mappings[cam.name]
                )
            frames = frames_all[cam.name]
            t_ref = mappings[cam.name].to_reference_ns(stamps[cam.name])
            refs = interp.at(t_ref)
            # Fast markers carry the clock's error into the pose (1 ms at 1 m/s = 1 mm): the
            # final bundle adjustment uses the markers slower than opt.max_marker_speed_m_s.
            step = 5_000_000
            speed = np.linalg.norm(interp.at(t_ref + step) - interp.at(t_ref - step), axis=2)
            refs[speed / (2 * step * 1e-9) > opt.max_marker_speed_m_s] = np.nan
            reg = register_camera(
                [f.uv_px for f in frames],
                [f.xyz_cam_m for f in frames],
                list(refs),
                K=cam.K,
                distortion=cam.dist,
                name=cam.name,
                T_world_cam_init=poses[cam.name],
                gates_px=(4.0, 2.5),
                areas_px_frames=[f.area_px for f in frames] if opt.min_area_ratio > 0 else None,
                min_area_ratio=opt.min_area_ratio,
            )
            poses[cam.name] = reg.T_world_cam
            registrations[cam.name] = dataclasses.replace(
                reg, T_world_cam_coarse=registrations[cam.name].T_world_cam_coarse,
                coarse_inliers=registrations[cam.name].coarse_inliers,
                coarse_rms_m=registrations[cam.name].coarse_rms_m,
            )  # fmt: skip
    if not pool_told and not timings_used:
        _refuse_unobservable_phase(cams, davis_inputs, opt, phase_notes)
    notes.extend(pool_notes)
    notes.extend(phase_notes)
    notes.extend([sync.note] if sync.note else sync_notes)
    timing = timings_used[-1] if timings_used else pool_timing
    how = "measured" if timing != opt.pulse_timing else "assumed"
    notes.append(
        f"clock: D415 sync timing {how}: {timing.describe()} (--d415-pulse-at "
        f"{timing.pulse_at}; undocumented for the D415: measure it, docs/d415-timing.md §4); it "
        "sets how frames relate to the sync channel's edges, the DAVIS trigger pulses and the "
        "slaves' delays"
    )
    notes.extend(_assumption_notes(opt, timing, sync_used=sync.edges is not None))
    if timing != opt.pulse_timing:
        davis_inputs = [_with_timing(dp, cams, timing) for dp in davis_inputs]
    clocks.extend(mappings[c.name] for c in cams)
    tick()
    refused = tuple(
        name
        for name, r in registrations.items()
        if r.bundle.reprojection_rms_px > opt.max_rms_px or r.bundle.n_inliers < opt.min_inliers
    )
    if refused and not opt.force:
        figures = "; ".join(
            f"{n}: {registrations[n].bundle.reprojection_rms_px:.2f} px RMS, "
            f"{registrations[n].bundle.n_inliers} inliers"
            for n in refused
        )
        msg = (
            f"refusing the calibration: {figures} (thresholds: RMS ≤ {opt.max_rms_px} px, "
            f"≥ {opt.min_inliers} inliers); check the markers and the Vicon file, or pass "
            "--force to write it anyway"
        )
        raise CalibrationError(msg)
    cameras = []
    for cam in cams:
        reg = registrations[cam.name]
        stats = reg.residual_statistics()
        k = next(c for c in clocks if c.device == cam.name)
        stats["clock_offset_sigma_ns"] = k.offset_sigma_ns
        stats = {key: v for key, v in stats.items() if math.isfinite(v)}
        cameras.append(
            CameraCalibration(
                name=cam.name,
                kind="d415",
                serial=cam.serial,
                width=cam.width,
                height=cam.height,
                K=cam.K,
                distortion=cam.dist,
                T_world_cam=reg.T_world_cam,
                residuals=stats,
                source="vicon",
            )
        )
    for dp in davis_inputs:
        master_map = next((k for k in clocks if k.device == dp.master), None)
        if dp.master is None or master_map is None or dp.note:
            notes.append(f"{dp.device}: no clock mapping: {dp.note}")
            continue
        master_frames = np.unique(
            np.array([f.t_dev_ns for f in frames_all[dp.master]], dtype=np.int64)
        )
        motion = davis_motions.get(dp.device)
        try:
            dmap = davis_clock(
                dp,
                firsts[dp.master].dev_ns,
                master_frames,
                master_map,
                check_first_edge=motion is None,
            )
            if motion is not None:
                # Which edge is which frame is not in the timing: the motion decides.
                period = float(np.median(np.diff(dp.edges_ns)))
                shift, shift_note = motion_period_shift(dp.device, motion, dmap, interp.at, period)
                notes.append(shift_note)
                if shift:
                    dmap = davis_clock(
                        dp,
                        firsts[dp.master].dev_ns,
                        master_frames,
                        master_map,
                        period_shift=shift,
                        check_first_edge=False,
                    )
        except CalibrationError as err:
            notes.append(f"{dp.device}: no clock mapping: {err}")
            _log.warning("%s", err)
            continue
        dmap = dataclasses.replace(dmap, method=f"pulses via {dp.master}")
        clocks.append(dmap)
        notes.append(
            f"{dp.device}: clock from the {dp.master} sync pulses on its trigger input "
            f"(DAVIS ns since its last timestamp reset → Vicon), ±{dmap.offset_sigma_ns / 1e3:.1f}"
            " µs; extrinsics come from `mocaprig calibrate board`"
        )
    if not davis_inputs:
        notes.append(
            "DAVIS: not in the recording (no /davis/<serial>/trigger): no DAVIS clock mapping"
        )
    rms = [r.bundle.reprojection_rms_px for r in registrations.values()]
    cal = Calibration(
        cameras=tuple(cameras),
        clocks=tuple(clocks),
        reference_clock="vicon",
        world_frame="vicon",
        statistics={
            "cameras": float(len(cameras)),
            "max_reprojection_rms_px": float(max(rms)),
            "vicon_static_frames": float(vicon.n_frames),
            "vicon_claps": float(len(vicon_claps)),
            "max_rms_threshold_px": float(opt.max_rms_px),
            "forced": float(bool(refused)),
            # The D415 sync-timing convention assumed (the statistics hold numbers only).
            "d415_pulse_at_readout_start": float(timing.pulse_at == "readout-start"),
            "d415_slave_trigger_delay_us": float(timing.slave_trigger_delay_us),
        },
        software_version=__version__,
        created_utc=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
    )
    tick()
    return ViconCalibrationResult(
        calibration=cal,
        registrations=registrations,
        static_frames=static_frames,
        vicon=vicon,
        refused=refused,
        notes=tuple(notes),
        vicon_claps=tuple(vicon_claps),
        clock_fits=clock_fits,
        trajectories=traj,
    )
