"""The DAVIS clock of the Vicon calibration: the D415 master's sync pulses on its trigger input.

When the recording has ``/davis/<serial>/trigger``, :func:`davis_pulse_inputs` gives the
DAVIS's external-input edges and the D415 master they come from (:class:`DavisPulses`), and
:func:`davis_clock` pairs them with the master's frames (``calib.clock_fit.clock_from_pulses``)
and composes the result with the master's Vicon mapping. The DAVIS's extrinsics come from
``mocaprig calibrate board``.

A pulse train pairs equally well at every whole-period shift, and which edge is which frame is
not in the timing (a master that loses its first frames still pulses for them). So the shift is
chosen by the data: :func:`davis_motion` (the image motion of the DAVIS's APS frames) is compared
with the Vicon markers' motion over the same intervals (:func:`motion_period_shift`) for each
whole-period shift, and a shift the motion does not single out is refused, naming it.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.device_streams import RecordedDavis, davis_devices
from mocaprig.acquire.recording import Recording
from mocaprig.calib.calibration import ClockMapping
from mocaprig.calib.vicon_calibration_frames import CalibCamera
from mocaprig.calib.vicon_calibration_options import D415PulseTiming
from mocaprig.errors import CalibrationError

__all__ = [
    "DavisMotion",
    "DavisPulses",
    "davis_clock",
    "davis_motion",
    "davis_pulse_inputs",
    "motion_period_shift",
]

I64 = npt.NDArray[np.int64]
F64 = npt.NDArray[np.float64]

#: Whole periods tried either side of the first-edge pairing.
_MAX_PERIOD_SHIFT = 8
#: Fewest APS frame pairs for a motion score.
_MIN_MOTION_FRAMES = 50
#: Added to the markers' mean displacement before its log (m): about the Vicon's noise.
_DISP_FLOOR_M = 1e-4


@dataclass(frozen=True, slots=True, eq=False)
class DavisMotion:
    """Image motion of a DAVIS's APS frames: mean absolute difference of consecutive frames.

    Attributes:
        t0_ns: Exposure midpoint of the first frame of each pair (DAVIS ns since its reset).
        t1_ns: Exposure midpoint of the second.
        motion: Mean |difference| (counts) of the pair.
    """

    t0_ns: I64
    t1_ns: I64
    motion: F64


def davis_motion(rec: Recording, device: str) -> DavisMotion | None:
    """The :class:`DavisMotion` of a recorded DAVIS (None without APS frames and their info)."""
    davis = RecordedDavis(rec, device)
    mids: list[int] = []
    diffs: list[float] = []
    prev: F64 | None = None
    prev_mid = 0
    t0: list[int] = []
    for fr in davis.frames():
        if fr.info is None:
            continue
        img = np.asarray(fr.image, dtype=np.float64)
        mid = 500 * (int(fr.info.t_start_exposure_us) + int(fr.info.t_end_exposure_us))
        if prev is not None and prev.shape == img.shape:
            t0.append(prev_mid)
            mids.append(mid)
            diffs.append(float(np.mean(np.abs(img - prev))))
        prev, prev_mid = img, mid
    if len(diffs) < _MIN_MOTION_FRAMES:
        return None
    return DavisMotion(
        np.asarray(t0, dtype=np.int64), np.asarray(mids, dtype=np.int64), np.asarray(diffs)
    )


def motion_period_shift(
    device: str,
    motion: DavisMotion,
    mapping: ClockMapping,
    vicon_at: Callable[[npt.ArrayLike], F64],
    period_ns: float,
) -> tuple[int, str]:
    """The whole-period shift of a DAVIS → Vicon ``mapping`` that the motion singles out.

    For each offset on a 1 ms grid over ±(:data:`_MAX_PERIOD_SHIFT` + ½) periods, the change
    of the log of the Vicon markers' mean displacement over each APS frame pair's interval
    (``vicon_at``: positions ``(T, M, 3)`` at Vicon ns) is correlated with that of the frame
    pairs' image motion; the peak, refined by a parabola, is rounded to whole periods.

    Returns:
        The shift ``k`` (the mapping is ``k`` periods late: add ``k·period``) and a note.

    Raises:
        CalibrationError: the motion does not single out a shift (no correlation, or a peak
            within a quarter period of the midpoint between two shifts), naming the DAVIS and
            what was measured.
    """
    t0 = mapping.to_reference_ns(motion.t0_ns).astype(np.float64)
    t1 = mapping.to_reference_ns(motion.t1_ns).astype(np.float64)
    # Changes of the log of both: the image motion is far from proportional to the markers'
    # displacement (it saturates, and depends on the texture), and its slow envelope peaks
    # broadly (10 ms biased on the simulated rig); its changes from one pair to the next time
    # the onsets and stops (within 1–3 ms there).
    m = np.diff(np.log(np.maximum(motion.motion, 1e-9)))
    half = (_MAX_PERIOD_SHIFT + 0.5) * period_ns
    grid = np.arange(-half, half + 1e6, 1e6)
    scores = np.full(grid.size, np.nan)
    for i, d in enumerate(grid):
        p0, p1 = vicon_at(t0 + d), vicon_at(t1 + d)
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # pairs outside the trial: NaN
            disp = np.nanmean(np.linalg.norm(p1 - p0, axis=-1), axis=-1)
        b_all = np.diff(np.log(disp + _DISP_FLOOR_M))
        ok = np.isfinite(b_all)
        if ok.sum() < _MIN_MOTION_FRAMES:
            continue
        a, b = m[ok] - float(np.mean(m[ok])), b_all[ok] - float(np.mean(b_all[ok]))
        den = float(np.sqrt(np.sum(a * a) * np.sum(b * b)))
        scores[i] = float(np.sum(a * b)) / den if den > 0 else np.nan
    if not np.isfinite(scores).any():
        msg = (
            f"cannot pair {device}'s pulses with the D415 master's frames: the Vicon trial does "
            "not cover its APS frames, so the whole-period shift is unobservable"
        )
        raise CalibrationError(msg)
    i = int(np.nanargmax(scores))
    peak = float(scores[i])
    delta = float(grid[i])
    if 0 < i < grid.size - 1 and np.isfinite(scores[i - 1 : i + 2]).all():
        y0, y1, y2 = scores[i - 1], scores[i], scores[i + 1]
        den = y0 - 2.0 * y1 + y2
        if den < 0:
            delta += 0.5 * float(y0 - y2) / float(den) * 1e6
    k = round(delta / period_ns)
    residual = delta - k * period_ns
    note = (
        f"{device}: pulse pairing by the motion: the APS frames' image motion correlates best "
        f"({peak:.2f}) with the Vicon markers' {delta / 1e6:+.1f} ms from the first-edge pairing, "
        f"i.e. {k:+d} periods ({residual / 1e6:+.1f} ms off a whole period)"
    )
    if peak < 0.3 or abs(residual) > 0.25 * period_ns:
        msg = (
            f"cannot pair {device}'s pulses with the D415 master's frames: the whole-period "
            f"shift is unobservable here (the APS motion correlates {peak:.2f} with the Vicon's "
            f"at {delta / 1e6:+.1f} ms, {residual / 1e6:+.1f} ms off a whole period of "
            f"{period_ns / 1e6:.1f} ms; needs ≥ 0.3 and within a quarter period): record more "
            "motion in the DAVIS's view, or start it before the D415s and lose no master frame"
        )
        raise CalibrationError(msg)
    return k, note


@dataclass(frozen=True, slots=True)
class DavisPulses:
    """A DAVIS's external-input edges and the D415 master they come from."""

    device: str
    edges_ns: I64
    master: str | None
    frame_delay_ns: int
    note: str = ""


def davis_pulse_inputs(
    rec: Recording,
    cams: Sequence[CalibCamera],
    sync_pulse_us: float,
    *,
    pulse_timing: D415PulseTiming | None = None,
) -> list[DavisPulses]:
    """The rising edges of every DAVIS's external input (DAVIS ns since its last timestamp
    reset) and the D415 sync master (``sync_mode`` 1 in its device metadata) whose pulses they
    are, with that master's frame delay (stamp minus pulse: a D415 stamps frames mid-exposure,
    so +half its exposure when the pulse marks the exposure start, −half when it marks the
    readout start, as ``pulse_timing`` says; default :class:`D415PulseTiming`, the exposure
    start). Rising-edge events (type 2) are used as they are; whole pulses (type 4, stamped at
    the trailing edge) are moved back by ``sync_pulse_us``."""
    timing = D415PulseTiming() if pulse_timing is None else pulse_timing

    master, delay, why = None, 0, ""
    for cam in cams:
        if cam.sync_mode == 1:
            master = cam.name
            if cam.exposure_us is None:
                master, why = None, f"{cam.name}'s metadata has no options.exposure_us"
            else:
                delay = timing.master_frame_delay_ns(float(cam.exposure_us) * 1e3)
            break
    else:
        why = "no calibrated D415 is the sync master (device metadata sync_mode = 1)"
    out = []
    for dev in davis_devices(rec):
        davis = RecordedDavis(rec, dev)
        if not davis.has("trigger"):
            continue
        edges, none_why = davis.external_edges_ns(pulse_us=sync_pulse_us)
        note = why
        if not edges.size and not note:
            note = none_why
        out.append(DavisPulses(dev.label, edges, master, delay, note))
    return out


def davis_clock(
    pulses: DavisPulses,
    master_first_ns: int,
    master_frames_ns: I64,
    master_map: ClockMapping,
    *,
    period_shift: int = 0,
    check_first_edge: bool = True,
) -> ClockMapping:
    """The DAVIS → Vicon mapping through the master's pulses.

    Pairing prior (a periodic train pairs equally well at every whole-period shift): the DAVIS's
    first edge after its timestamp reset is the master's first recorded frame, moved by
    ``period_shift`` whole periods (:func:`motion_period_shift` says how many: a master that
    lost its first frames is that many periods on). With ``check_first_edge`` (no motion
    check), the first edge must come ≥ 1.5 periods after the reset, else the train was already
    running and the pairing is refused.

    Raises:
        CalibrationError: too few edges or frames, the train already running at the reset, or
            a failed pulse fit (from ``clock_from_pulses``).
    """
    from mocaprig.calib.clock_fit import clock_from_pulses

    edges = pulses.edges_ns
    if edges.size < 10 or master_frames_ns.size < 10:
        msg = (
            f"cannot map {pulses.device} by pulses: {edges.size} external-input edges and "
            f"{master_frames_ns.size} master frames; need 10 of each (is the D415 master's sync "
            "output wired to the DAVIS trigger input, with edge or pulse detection on?)"
        )
        raise CalibrationError(msg)
    period = float(np.median(np.diff(edges)))
    if check_first_edge and edges[0] < 1.5 * period:
        msg = (
            f"cannot map {pulses.device} by pulses: its first edge comes {edges[0] / 1e6:.1f} ms "
            f"after its timestamp reset (< 1.5 periods of {period / 1e6:.1f} ms), so the pulse "
            "train was already running and which pulse is which frame is unknown; start the "
            "DAVIS (timestamp reset) before the D415 master streams"
        )
        raise CalibrationError(msg)
    prior = int(master_first_ns - pulses.frame_delay_ns - int(edges[0])) + round(
        period_shift * period
    )
    return clock_from_pulses(
        pulses.device,
        edges,
        master_frames_ns,
        d415_mapping=master_map,
        frame_delay_ns=pulses.frame_delay_ns,
        prior_offset_ns=prior,
    )
