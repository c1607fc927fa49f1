"""The simulated Vicon capture and its exports (C3D written directly with ezc3d, Nexus CSV).

This module is deliberately independent of the project's own Vicon reader/writer
(``calib``): a test reading these files with ``calib`` then catches reader/writer disagreements.

Timing
======

The Vicon frame clock is a :class:`~drivers_mock.clock.DeviceClock` in ns: Vicon frame ``n``
(counted since the Vicon system started) happens at device time ``n / rate_hz``. A capture starts
at Vicon frame ``n0`` (the first frame at or after the capture's session start), so::

    C3D frame i  <->  Vicon device time (n0 + i) / rate_hz  <->  session time clock.session_ns(...)
    TRIAL:ACTUAL_START_FIELD = n0 + 1   (1-based field number, two int16 words: low, high;
                                         the low word is stored signed, decode it as & 0xFFFF)

Measurement model
=================

* every marker sample gets independent Gaussian noise, σ = ``ViconSpec.noise_sigma_m`` ×
  ``NoiseSettings.vicon_noise_scale`` per axis;
* occlusion gaps: each (marker, frame) starts a gap with a hazard chosen so that about
  ``vicon_gap_fraction`` of the samples are lost; lengths are log-uniform in
  ``[1, vicon_gap_max_frames]`` (the real Nexus sample: 1–71 frames, 1.0 %). *Visibility
  heuristic*: from a body marker's outward skin normal (the marker set's normal, posed), the
  fraction ``s`` of Vicon cameras within 80° of that normal says
  how well it is seen, and its hazard is weighted by ``1 + vicon_facing_weight · (1 − s)²``
  (weights normalised so the overall fraction stays on target). Markers outside the calibrated
  volume are gaps too;
* residuals (mm): Gamma-distributed with the spec's mean and spread, quantised to the C3D's
  0.1 mm step (|POINT:SCALE|); −1 for gaps.

Sync channel
============

With D415s in the session, :func:`simulate_sync_channel` gives the trial an analog channel
``D415_SYNC`` (docs/wiring.md §7): the sync box's toggle output, which flips at every pulse of
the D415 master (after the box's interrupt latency), through an RC low-pass into a Vicon analog
input, sampled on the Vicon clock at ``SyncWiring.rate_hz`` (an integer number of samples per
Vicon frame; C3D analog sample ``s`` of the trial is at Vicon device time
``((start_field − 1)·spf + s) / rate``), with Gaussian noise and 16-bit quantisation over ±10 V.
The pulse instants are the ones the mock D415 master really emitted in the recorded session
(``SessionRecording.sync_pulses_ns``), so the analog edges and the recorded frames are the same
events.
"""

from __future__ import annotations

import csv
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from mocaprig import __version__
from mocaprig.drivers_mock.clock import DeviceClock
from mocaprig.drivers_mock.noise import NoiseSettings
from mocaprig.drivers_mock.rig import ViconSpec
from mocaprig.errors import RecordingError, ValidationError

if TYPE_CHECKING:
    from mocaprig.drivers_mock.scenario import Scenario
    from mocaprig.drivers_mock.world import WorldParams

__all__ = [
    "C3D_POINT_SCALE",
    "SYNC_CHANNEL",
    "AnalogCapture",
    "SyncWiring",
    "ViconCapture",
    "capture_markers",
    "simulate_sync_channel",
    "simulate_vicon",
    "vicon_frame_times_ns",
    "write_c3d",
    "write_nexus_csv",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
Progress = Callable[[int, int], None]

#: POINT:SCALE of the written C3D: negative = float storage; |scale| is the residual step (mm).
C3D_POINT_SCALE = -0.1

#: A camera sees a marker when the marker's normal is within this angle of the camera (deg).
_FACING_LIMIT_DEG = 80.0

#: How many frames are sampled per block (bounds memory and drives the progress callback).
_BLOCK_FRAMES = 600

#: Label of the simulated sync channel (the sync box's toggle output, docs/wiring.md §7).
SYNC_CHANNEL = "D415_SYNC"


@dataclass(frozen=True, slots=True, eq=False)
class ViconCapture:
    """One simulated Vicon trial.

    Attributes:
        labels: Point labels ``"<subject>:<MARKER>"`` and ``"clapper:TOP"``/``"clapper:BOTTOM"``.
        rate_hz: Frame rate (Hz).
        start_field: ``TRIAL:ACTUAL_START_FIELD``: the 1-based Vicon frame number of frame 0.
        frame_t_ns: True session time of every frame (int64 ns), shape ``(F,)``.
        points_m: Measured positions (m), NaN in gaps, shape ``(F, N, 3)``.
        residuals_mm: Residuals (mm), −1 in gaps, shape ``(F, N)``.
        clean_m: Noise-free positions at the frame times (m), shape ``(F, N, 3)``.
    """

    labels: tuple[str, ...]
    rate_hz: float
    start_field: int
    frame_t_ns: I64 = field(repr=False)
    points_m: F64 = field(repr=False)
    residuals_mm: F64 = field(repr=False)
    clean_m: F64 = field(repr=False)

    @property
    def num_frames(self) -> int:
        """Number of frames ``F``."""
        return int(self.frame_t_ns.shape[0])

    @property
    def gap_fraction(self) -> float:
        """Fraction of samples that are gaps."""
        return float(np.mean(self.residuals_mm < 0)) if self.residuals_mm.size else 0.0


@dataclass(frozen=True, slots=True)
class SyncWiring:
    """The sync box's toggle output on a Vicon analog input (docs/wiring.md §7).

    Attributes:
        rate_hz: Analog sampling rate (Hz); an integer multiple of the Vicon frame rate.
        low_v: Output level low (V).
        high_v: Output level high (V) as seen by the input (5 V into ≥ 100 kΩ through 4.7 kΩ).
        tau_us: Nominal time constant of the RC low-pass at the input (µs; 4.7 kΩ × 100 nF).
        tau_tolerance: Per-session relative deviation of the time constant, uniform in
            ±``tau_tolerance`` (component tolerances): the calibration must measure τ.
        latency_us: The box's interrupt latency from the master's pulse to the toggle (µs).
        latency_jitter_us: Uniform jitter of that latency, ± (µs).
        noise_v: Gaussian noise of the input (V RMS).
        lsb_v: Quantisation step (V): 16 bits over ±10 V.
        offset_v: The input's offset (V).
        antialias_hz: Cut-off of a 2-pole Butterworth anti-alias filter after the RC (Hz);
            None: none, the edge is a pure first-order RC.
        range_v: The input's full scale, ± (V): samples beyond it clip.
    """

    rate_hz: float = 2400.0
    low_v: float = 0.0
    high_v: float = 4.8
    tau_us: float = 470.0
    tau_tolerance: float = 0.05
    latency_us: float = 2.0
    latency_jitter_us: float = 1.0
    noise_v: float = 0.002
    lsb_v: float = 20.0 / 65536.0
    offset_v: float = 0.0
    antialias_hz: float | None = None
    range_v: float = 10.0

    @classmethod
    def for_world(cls, params: WorldParams) -> SyncWiring:
        """The wiring of a world's hidden parameters (:mod:`drivers_mock.world`)."""
        return cls(
            tau_us=params.sync_tau_us,
            latency_us=params.sync_latency_us,
            latency_jitter_us=params.sync_latency_jitter_us,
            noise_v=params.sync_noise_v,
            lsb_v=2.0 * params.adc_range_v / 2.0**params.adc_bits,
            offset_v=params.adc_offset_v,
            antialias_hz=params.antialias_hz,
            range_v=params.adc_range_v,
        )


def _step_response(tau_ns: float, antialias_hz: float) -> Callable[[F64], F64]:
    """The unit step response of the RC (τ) followed by a 2-pole Butterworth at
    ``antialias_hz``, a function of the time since the step (ns; 0 before it)."""
    from scipy.signal import residue

    # µs keep the polynomial coefficients well-scaled for the partial fractions.
    tau_us = tau_ns * 1e-3
    wc = 2.0 * np.pi * antialias_hz * 1e-6  # rad per µs
    den = np.polymul(np.polymul([tau_us, 1.0], [1.0, np.sqrt(2.0) * wc, wc * wc]), [1.0, 0.0])
    # H(s)/s = Σ r_k / (s − p_k), so h(t) = Σ r_k exp(p_k t).
    r, p, _ = residue([wc * wc], den)

    def h(t: F64) -> F64:
        tt = np.maximum(t, 0.0) * 1e-3
        out = np.real(np.exp(np.multiply.outer(tt, p)) @ r)
        return np.where(t > 0, out, 0.0)

    return h


@dataclass(frozen=True, slots=True, eq=False)
class AnalogCapture:
    """Analog channels of a simulated Vicon trial, in physical units.

    Attributes:
        labels: Channel labels (C).
        units: Channel units (C).
        descriptions: Channel descriptions (C).
        rate_hz: Sampling rate (Hz), an integer multiple of the trial's frame rate.
        values: ``(S, C)`` samples, ``S`` = frames × samples per frame.
        edges_ns: True session times (int64 ns) at which the signal switched (truth).
        edge_rising: ``(E,)`` True where the switch went low → high.
        tau_ns: The true RC time constant (ns).
    """

    labels: tuple[str, ...]
    units: tuple[str, ...]
    descriptions: tuple[str, ...]
    rate_hz: float
    values: F64 = field(repr=False)
    edges_ns: I64 = field(repr=False)
    edge_rising: npt.NDArray[np.bool_] = field(repr=False)
    tau_ns: float


def simulate_sync_channel(
    capture: ViconCapture,
    clock: DeviceClock,
    pulses_ns: npt.ArrayLike,
    *,
    rng: np.random.Generator,
    wiring: SyncWiring | None = None,
) -> AnalogCapture:
    """The ``D415_SYNC`` analog channel of a trial: the sync box's toggle output (module doc).

    Args:
        capture: The Vicon trial (its first frame and frame count fix the samples).
        clock: The Vicon frame clock (analog samples are on it).
        pulses_ns: The D415 master's sync pulses (session ns, increasing); each flips the level.
        rng: Seeded generator (time constant, latency jitter, noise).
        wiring: The wiring model (default :class:`SyncWiring`).

    Returns:
        One channel in volts; the switch instants as truth.

    Raises:
        ValidationError: the analog rate is not an integer multiple of the frame rate.
    """
    w = wiring or SyncWiring()
    spf = w.rate_hz / capture.rate_hz
    if abs(spf - round(spf)) > 1e-9 or round(spf) < 1:
        msg = (
            f"the analog rate {w.rate_hz:g} Hz must be an integer multiple of the Vicon frame "
            f"rate {capture.rate_hz:g} Hz"
        )
        raise ValidationError(msg)
    spf_i = round(spf)
    pulses = np.sort(np.asarray(pulses_ns, dtype=np.int64))
    tau = w.tau_us * 1e3 * (1.0 + rng.uniform(-w.tau_tolerance, w.tau_tolerance))
    latency = w.latency_us * 1e3 + rng.uniform(-1.0, 1.0, size=pulses.shape) * (
        w.latency_jitter_us * 1e3
    )
    edges = pulses.astype(np.float64) + latency
    target = ((np.arange(edges.size) + 1) % 2).astype(np.float64)  # first pulse: low → high
    n_samples = capture.num_frames * spf_i
    n = (capture.start_field - 1) * spf_i + np.arange(n_samples, dtype=np.int64)
    device = np.round(n.astype(np.float64) * (1e9 / w.rate_hz)).astype(np.int64)
    t = clock.session_ns(device, unit_ns=1).astype(np.float64)
    k = np.searchsorted(edges, t, side="right") - 1
    if not edges.size:
        level = np.zeros(n_samples)
    elif w.antialias_hz is None:
        # A first-order RC: each sample relaxes from the level at its last switch.
        y_before = np.zeros(edges.size)
        y = 0.0  # settled low before the first pulse
        for j in range(1, edges.size):
            y = target[j - 1] + (y - target[j - 1]) * np.exp(-(edges[j] - edges[j - 1]) / tau)
            y_before[j] = y
        kk = np.clip(k, 0, edges.size - 1)
        level = target[kk] + (y_before[kk] - target[kk]) * np.exp(-(t - edges[kk]) / tau)
        level = np.where(k >= 0, level, 0.0)
    else:
        # A filtered edge is no first-order curve: sum the chain's step responses of the
        # last few switches (earlier ones have settled within 33 ms ≫ τ).
        h = _step_response(tau, w.antialias_hz)
        level = np.zeros(n_samples)
        for back in range(3):
            ok = k - back >= 0
            jj = np.clip(k - back, 0, edges.size - 1)
            prev = np.where(jj > 0, target[np.maximum(jj - 1, 0)], 0.0)
            step = (target[jj] - prev) * h(t - edges[jj])
            level += np.where(ok, step, 0.0)
        settled = np.where(k - 3 >= 0, target[np.clip(k - 3, 0, max(edges.size - 1, 0))], 0.0)
        level += settled
    volts = w.low_v + (w.high_v - w.low_v) * level + rng.normal(0.0, w.noise_v, n_samples)
    volts = np.clip(volts + w.offset_v, -w.range_v, w.range_v)
    volts = np.round(volts / w.lsb_v) * w.lsb_v
    values = volts[:, None]
    edges_ns = np.round(edges).astype(np.int64)
    rising = target.astype(bool)
    for arr in (values, edges_ns, rising):
        arr.setflags(write=False)
    return AnalogCapture(
        labels=(SYNC_CHANNEL,),
        units=("V",),
        descriptions=("sync box toggle output: each edge is a D415 master frame pulse",),
        rate_hz=float(w.rate_hz),
        values=values,
        edges_ns=edges_ns,
        edge_rising=rising,
        tau_ns=float(tau),
    )


def vicon_frame_times_ns(
    clock: DeviceClock, *, rate_hz: float, start_ns: int, end_ns: int
) -> tuple[int, I64]:
    """The Vicon frames that fall inside a session interval.

    Args:
        clock: The Vicon frame clock (device ns).
        rate_hz: Vicon frame rate (Hz).
        start_ns: Session time (ns) the capture starts (first frame at or after it).
        end_ns: Session time (ns) the capture stops (last frame at or before it).

    Returns:
        ``(n0, t_ns)``: the Vicon frame number of the first frame (0-based, since the system
        started) and the session times (int64 ns) of the frames.

    Raises:
        ValidationError: the interval holds no frame.
    """
    d0, d1 = (int(v) for v in clock.device_ns(np.array([start_ns, end_ns], dtype=np.int64)))
    n0 = int(np.ceil(d0 * rate_hz / 1e9 - 1e-9))
    n1 = int(np.floor(d1 * rate_hz / 1e9 + 1e-9))
    if n1 < n0:
        msg = f"the Vicon capture [{start_ns}, {end_ns}] ns holds no {rate_hz:g} Hz frame"
        raise ValidationError(msg)
    n = np.arange(n0, n1 + 1, dtype=np.int64)
    device = np.round(n.astype(np.float64) * (1e9 / rate_hz)).astype(np.int64)
    return n0, clock.session_ns(device, unit_ns=1)


def _facing_fraction(points_m: F64, normals: F64 | None, cameras_m: F64) -> F64:
    """Fraction of cameras within the facing limit of each sample's normal, shape ``(T, N)``."""
    if normals is None:
        return np.ones(points_m.shape[:-1])
    to_cam = cameras_m[None, None, :, :] - points_m[:, :, None, :]
    to_cam /= np.linalg.norm(to_cam, axis=-1, keepdims=True)
    nrm = normals / np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)
    cos = np.einsum("tnk,tnck->tnc", nrm, to_cam)
    seen: F64 = np.mean(cos > np.cos(np.radians(_FACING_LIMIT_DEG)), axis=-1)
    return seen


def _gap_mask(
    weights: F64, *, fraction: float, max_frames: int, rng: np.random.Generator
) -> npt.NDArray[np.bool_]:
    """Occlusion gaps (True = lost), shape of ``weights`` ``(F, N)``."""
    mask = np.zeros(weights.shape, dtype=bool)
    if fraction <= 0 or weights.size == 0:
        return mask
    lengths_support = np.arange(1, max_frames + 1, dtype=np.float64)
    # Log-uniform lengths: P(L = k) ∝ log((k + 1) / k), k = 1..max.
    p_len = np.log1p(1.0 / lengths_support)
    p_len /= p_len.sum()
    mean_len = float(np.sum(lengths_support * p_len))
    hazard = fraction / mean_len * weights / max(float(np.mean(weights)), 1e-12)
    starts = np.argwhere(rng.random(weights.shape) < np.clip(hazard, 0.0, 1.0))
    lengths = rng.choice(lengths_support.astype(np.int64), size=len(starts), p=p_len)
    for (f, n), length in zip(starts, lengths, strict=True):
        mask[f : f + int(length), n] = True
    return mask


def capture_markers(
    sample: Callable[[I64], tuple[F64, F64 | None]],
    labels: Sequence[str],
    *,
    spec: ViconSpec,
    clock: DeviceClock,
    start_ns: int,
    end_ns: int,
    noise: NoiseSettings,
    rng: np.random.Generator,
    progress: Progress | None = None,
) -> ViconCapture:
    """Simulate a Vicon capture of any set of marker trajectories.

    Args:
        sample: ``t_ns (T,) -> (positions (T, N, 3) m, normals (T, N, 3) or None)``; a normal
            row of zeros means "always visible" (e.g. a clapperboard marker).
        labels: The ``N`` point labels.
        spec: The Vicon system (rate, volume, noise σ, residual figures, camera positions).
        clock: The Vicon frame clock.
        start_ns: Session time the capture starts.
        end_ns: Session time the capture stops.
        noise: Scenario noise settings (noise scale, gap fraction and lengths, facing weight).
        rng: The seeded generator (consumed).
        progress: Optional ``(done, total)`` callback over frames.

    Returns:
        The capture (measured and clean positions, residuals, frame times).
    """
    n0, t_ns = vicon_frame_times_ns(clock, rate_hz=spec.rate_hz, start_ns=start_ns, end_ns=end_ns)
    num_frames = int(t_ns.shape[0])
    num_markers = len(labels)
    clean = np.empty((num_frames, num_markers, 3))
    seen = np.empty((num_frames, num_markers))
    for a in range(0, num_frames, _BLOCK_FRAMES):
        b = min(a + _BLOCK_FRAMES, num_frames)
        pos, normals = sample(t_ns[a:b])
        if pos.shape != (b - a, num_markers, 3):
            msg = f"marker sampler returned shape {pos.shape}, expected {(b - a, num_markers, 3)}"
            raise ValidationError(msg)
        clean[a:b] = pos
        frac = _facing_fraction(pos, normals, spec.camera_positions_m)
        if normals is not None:
            frac = np.where(np.linalg.norm(normals, axis=-1) > 0, frac, 1.0)
        seen[a:b] = frac
        if progress is not None:
            progress(b, num_frames)
    weights = 1.0 + noise.vicon_facing_weight * (1.0 - seen) ** 2
    gaps = _gap_mask(
        weights,
        fraction=noise.vicon_gap_fraction,
        max_frames=noise.vicon_gap_max_frames,
        rng=rng,
    )
    outside = np.any((clean < spec.volume_min_m) | (clean > spec.volume_max_m), axis=-1)
    gaps |= outside
    sigma = spec.noise_sigma_m * noise.vicon_noise_scale
    measured = clean + rng.normal(0.0, 1.0, size=clean.shape) * sigma
    measured[gaps] = np.nan
    k = spec.residual_mean_mm / max(spec.residual_sd_mm, 1e-9)
    shape_k = k * k
    scale = spec.residual_mean_mm / shape_k
    step = abs(C3D_POINT_SCALE)
    raw = rng.gamma(shape_k, scale, size=gaps.shape)
    residuals = np.clip(np.round(raw / step), 1, 255) * step
    residuals[gaps] = -1.0
    _log.info(
        "simulated Vicon: %d frames × %d markers at %g Hz, %.2f %% gaps",
        num_frames,
        num_markers,
        spec.rate_hz,
        100.0 * float(np.mean(gaps)) if gaps.size else 0.0,
    )
    for arr in (t_ns, measured, residuals, clean):
        arr.setflags(write=False)
    return ViconCapture(tuple(labels), spec.rate_hz, n0 + 1, t_ns, measured, residuals, clean)


def simulate_vicon(scenario: Scenario, *, progress: Progress | None = None) -> ViconCapture:
    """Capture the scenario's body markers and the clapperboard with the simulated Vicon.

    The capture runs from the scenario's ``vicon_start_ns`` to ``vicon_end_ns``; its generator
    is derived from the scenario seed, so the capture is reproducible.
    """
    spec = scenario.rig.vicon
    body_labels = [f"{spec.subject}:{name}" for name in scenario.marker_names]
    clap_labels = [f"clapper:{name}" for name in scenario.clapperboard.marker_names]

    def sample(t: I64) -> tuple[F64, F64 | None]:
        world = scenario.sample(t)
        zeros = np.zeros_like(world.clapper_m)
        return (
            np.concatenate([world.markers_m, world.clapper_m], axis=1),
            np.concatenate([world.marker_normals, zeros], axis=1),
        )

    return capture_markers(
        sample,
        body_labels + clap_labels,
        spec=spec,
        clock=scenario.clocks["vicon"],
        start_ns=scenario.vicon_start_ns,
        end_ns=scenario.vicon_end_ns,
        noise=scenario.noise,
        rng=scenario.rng("vicon"),
        progress=progress,
    )


def _int_parameter(c3d: object, group: str, name: str, values: Sequence[int]) -> None:
    """Add an integer (C3D type 2) parameter; ezc3d's ``add_parameter`` stores ints as floats."""
    from ezc3d import ezc3d as ezc3d_core

    param = ezc3d_core.Parameter(name, "")
    param.set(ezc3d_core.VecInt([int(v) for v in values]))
    c3d._storage["parameters"].add_parameter(group, param)  # type: ignore[attr-defined]


def _int16_words(value: int) -> list[int]:
    """A 32-bit count as two signed int16 words (low, high), as C3D stores FIELD parameters."""
    low, high = value & 0xFFFF, (value >> 16) & 0xFFFF
    return [low - 0x10000 if low >= 0x8000 else low, high]


def write_c3d(
    capture: ViconCapture,
    path: str | Path,
    *,
    subject: str = "actor",
    analogs: AnalogCapture | None = None,
) -> Path:
    """Write the capture as a Vicon-like float C3D (mm), with ezc3d directly.

    Parameters written: POINT (RATE, UNITS ``mm``, SCALE −0.1 → float data, LABELS,
    DESCRIPTIONS, X_SCREEN ``+X``, Y_SCREEN ``+Z``), TRIAL (ACTUAL_START_FIELD,
    ACTUAL_END_FIELD, CAMERA_RATE), SUBJECTS (NAMES, LABEL_PREFIXES, USES_PREFIXES) and
    MANUFACTURER (COMPANY ``mocaprig``, SOFTWARE ``simulated Vicon``, VERSION_LABEL). Gaps are
    NaN with residual −1. With ``analogs``: ANALOG (RATE, LABELS, UNITS, DESCRIPTIONS, SCALE 1,
    OFFSET 0, GEN_SCALE 1, as Nexus writes float files) and the samples.

    Raises:
        RecordingError: the file cannot be written.
    """
    import ezc3d

    out = Path(path)
    c3d = ezc3d.c3d()
    params = c3d["parameters"]
    params["POINT"]["RATE"]["value"] = np.array([capture.rate_hz])
    params["POINT"]["LABELS"]["value"] = list(capture.labels)
    params["POINT"]["DESCRIPTIONS"]["value"] = [
        "clapperboard marker" if lab.startswith("clapper:") else "body marker"
        for lab in capture.labels
    ]
    params["POINT"]["UNITS"]["value"] = ["mm"]
    params["POINT"]["SCALE"]["value"] = np.array([C3D_POINT_SCALE])
    num_frames, num_markers = capture.num_frames, len(capture.labels)
    pts = np.ones((4, num_markers, num_frames))
    pts[:3] = np.transpose(capture.points_m, (2, 1, 0)) * 1000.0
    c3d["data"]["points"] = pts
    # ezc3d truncates residual / |scale| to an integer: write mid-step values.
    res = capture.residuals_mm.T[None].copy()
    step = abs(C3D_POINT_SCALE)
    res[res >= 0] += 0.5 * step
    c3d["data"]["meta_points"]["residuals"] = res
    if analogs is not None:
        spf = round(analogs.rate_hz / capture.rate_hz)
        n_ch = len(analogs.labels)
        if analogs.values.shape != (num_frames * spf, n_ch):
            msg = (
                f"analog samples have shape {analogs.values.shape}, expected "
                f"{(num_frames * spf, n_ch)} ({spf} per frame)"
            )
            raise ValidationError(msg)
        aparams = params["ANALOG"]
        aparams["RATE"]["value"] = np.array([analogs.rate_hz])
        aparams["LABELS"]["value"] = list(analogs.labels)
        aparams["DESCRIPTIONS"]["value"] = list(analogs.descriptions)
        aparams["UNITS"]["value"] = list(analogs.units)
        aparams["SCALE"]["value"] = np.ones(n_ch)
        aparams["GEN_SCALE"]["value"] = np.array([1.0])
        c3d["data"]["analogs"] = analogs.values.T[None].astype(np.float64)
    c3d.add_parameter("POINT", "X_SCREEN", ["+X"])
    c3d.add_parameter("POINT", "Y_SCREEN", ["+Z"])
    _int_parameter(c3d, "TRIAL", "ACTUAL_START_FIELD", _int16_words(capture.start_field))
    end_field = capture.start_field + num_frames - 1
    _int_parameter(c3d, "TRIAL", "ACTUAL_END_FIELD", _int16_words(end_field))
    c3d.add_parameter("TRIAL", "CAMERA_RATE", [float(capture.rate_hz)])
    c3d.add_parameter("SUBJECTS", "NAMES", [subject, "clapper"])
    c3d.add_parameter("SUBJECTS", "LABEL_PREFIXES", [f"{subject}:", "clapper:"])
    _int_parameter(c3d, "SUBJECTS", "USES_PREFIXES", [1])
    c3d.add_parameter("MANUFACTURER", "COMPANY", ["mocaprig"])
    c3d.add_parameter("MANUFACTURER", "SOFTWARE", ["simulated Vicon"])
    c3d.add_parameter("MANUFACTURER", "VERSION_LABEL", [__version__])
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        c3d.write(str(out))
    except (OSError, RuntimeError) as err:
        msg = f"cannot write the simulated Vicon C3D {out}: {err}; check the folder is writable"
        raise RecordingError(msg) from err
    return out


def write_nexus_csv(capture: ViconCapture, path: str | Path) -> Path:
    """Write the capture as a Vicon Nexus ``Trajectories`` CSV (mm, gaps as empty cells).

    Layout (calibration-vicon.md §1.3): ``Trajectories`` / rate / names at every third column
    from column 3 / ``Frame,Sub Frame,X,Y,Z,...`` / units ``mm`` / data rows from frame 1
    (sub frame 0) / a blank line.

    Raises:
        RecordingError: the file cannot be written.
    """
    out = Path(path)
    n = len(capture.labels)
    rows: list[list[str]] = [
        ["Trajectories"],
        [f"{capture.rate_hz:g}"],
        ["", ""] + [cell for lab in capture.labels for cell in (lab, "", "")],
        ["Frame", "Sub Frame"] + ["X", "Y", "Z"] * n,
        ["", ""] + ["mm"] * (3 * n),
    ]
    flat = capture.points_m.reshape(capture.num_frames, 3 * n) * 1000.0
    text = np.char.mod("%.5f", flat)
    text[np.isnan(flat)] = ""
    for i in range(capture.num_frames):
        rows.append([str(i + 1), "0", *text[i].tolist()])
    rows.append([])
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with out.open("w", newline="", encoding="utf-8") as fh:
            csv.writer(fh, lineterminator="\n").writerows(rows)
    except OSError as err:
        msg = f"cannot write the simulated Nexus CSV {out}: {err.strerror or err}"
        raise RecordingError(msg) from err
    return out
