"""The DAVIS clock of the Vicon calibration: the D415 master's sync pulses on its trigger input.

When the recording has ``/davis/<serial>/trigger``, :func:`davis_pulse_inputs` gives the
DAVIS's external-input edges and the D415 master they come from (:class:`DavisPulses`), and
:func:`davis_clock` pairs them with the master's frames (``calib.clock_fit.clock_from_pulses``)
and composes the result with the master's Vicon mapping. The DAVIS's extrinsics come from
``mocaprig calibrate board``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.device_streams import RecordedDavis, davis_devices
from mocaprig.acquire.recording import Recording
from mocaprig.calib.calibration import ClockMapping
from mocaprig.calib.vicon_calibration_frames import CalibCamera
from mocaprig.calib.vicon_calibration_options import D415PulseTiming
from mocaprig.errors import CalibrationError

__all__ = ["DavisPulses", "davis_clock", "davis_pulse_inputs"]

I64 = npt.NDArray[np.int64]


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
    pulses: DavisPulses, master_first_ns: int, master_frames_ns: I64, master_map: ClockMapping
) -> ClockMapping:
    """The DAVIS → Vicon mapping through the master's pulses.

    Pairing prior (a periodic train pairs equally well at every whole-period shift): the DAVIS's
    first edge after its timestamp reset is the master's first recorded frame. That holds when
    the DAVIS was reset and listening before the master's pulse train began (the recorder
    starts the DAVIS first; the simulated rig resets it at session time 0 and starts the D415s
    then) and is checked: the first edge must come ≥ 1.5 periods after the reset, else the
    train was already running and the pairing is refused.

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
    if edges[0] < 1.5 * period:
        msg = (
            f"cannot map {pulses.device} by pulses: its first edge comes {edges[0] / 1e6:.1f} ms "
            f"after its timestamp reset (< 1.5 periods of {period / 1e6:.1f} ms), so the pulse "
            "train was already running and which pulse is which frame is unknown; start the "
            "DAVIS (timestamp reset) before the D415 master streams"
        )
        raise CalibrationError(msg)
    prior = int(master_first_ns - pulses.frame_delay_ns - int(edges[0]))
    return clock_from_pulses(
        pulses.device,
        edges,
        master_frames_ns,
        d415_mapping=master_map,
        frame_delay_ns=pulses.frame_delay_ns,
        prior_offset_ns=prior,
    )
