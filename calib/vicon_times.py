"""Vicon-clock times of a trial's frames and analog samples.

The Vicon clock is the rig's reference clock (calibration-vicon.md §3.1): frame ``n`` of a trial
(0-based since the system started) is at ``n / rate``, and an analog sample likewise at the
analog rate, the first sample of a frame falling on the frame's time. Clap detection, the
refinements and the sync channel all stamp Vicon data with these.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from mocaprig.calib.vicon import AnalogChannels, MarkerTrajectories

__all__ = ["analog_times_ns", "vicon_times_ns"]

I64 = npt.NDArray[np.int64]


def vicon_times_ns(traj: MarkerTrajectories) -> I64:
    """Vicon-clock time (integer ns) of every frame: frame ``n`` (0-based since the system
    started, ``first_frame − 1 + row``) is at ``n / rate``."""
    n = traj.first_frame - 1 + np.arange(traj.n_frames, dtype=np.int64)
    out: I64 = np.round(n.astype(np.float64) * (1e9 / traj.rate_hz)).astype(np.int64)
    return out


def analog_times_ns(analogs: AnalogChannels) -> I64:
    """Vicon-clock time (integer ns) of every analog sample: sample ``s`` is
    ``((first_frame − 1)·samples_per_frame + s) / rate`` (its first sample of a frame falls on
    the frame's :func:`vicon_times_ns`)."""
    n = (analogs.first_frame - 1) * analogs.samples_per_frame + np.arange(
        analogs.n_samples, dtype=np.int64
    )
    out: I64 = np.round(n.astype(np.float64) * (1e9 / analogs.rate_hz)).astype(np.int64)
    return out
