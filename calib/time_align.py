"""Time alignment of the rig's device clocks onto the reference (Vicon) clock.

The recipe (calibration-vicon.md §3.1, §0 items 11–12):

1. **Claps** give a coarse offset per device. The clapperboard's two markers sit at their
   contact distance most of the time; a clap opens them (hundreds of mm), holds, and closes them
   back to contact. The clap instant is the contact instant.

   * Vicon (:func:`find_claps_vicon`, 100–120 Hz): the distance of the two labelled clapper
     markers; the contact time is where a quadratic fitted to the last pre-contact samples of
     the closing reaches the contact distance (sub-frame; ≈ 0.2 ms).
   * D415 (:func:`find_claps_d415`, 30 Hz, unlabelled markers): the clapper is found as the
     pair of *static* blobs a contact distance apart of which one leaves and comes back; the
     signal is the image distance (px) of the moving marker from the fixed one (the image is
     far more precise than D415 depth). A 30 Hz camera sees only 1–4 samples of a 60–120 ms
     closing, so the closing *trajectory* is fitted: constant angular acceleration from rest
     (``θ = θmax·(1 − u²)``, ``u`` from 0 to 1 over the closing), the signal taken as linear in
     ``θ``, evaluated as a posterior over (contact time, closing duration) on a grid with a weak
     prior on the duration; the estimate is the posterior mean and ``sigma_ns`` its spread.
   * DAVIS (:func:`find_claps_davis`): the clapper's arm sweeps a burst of events that stops
     dead at contact; the contact is the sharpest fall of the event rate of the busiest image
     cell, located to the event-rate bin.

2. **Clock from claps** (:func:`clock_from_claps`): offset from one clap, offset and drift from
   two or more (a weighted line through the clap pairs).

3. **Refinement.** The D415 claps are only good to a few ms and two claps cannot give a drift
   to ppm, so the mapping is refined over the whole session:

   * :func:`refine_by_reprojection` (accurate; needs the camera's registered pose): the Vicon
     markers interpolated at each frame's mapped time are projected onto the frame's blobs and
     the offset and drift corrections fitted to the image residuals (≈ 0.2 ms on the simulated
     sessions; see docs/calibration.md for the drift);
   * :func:`refine_by_speed` (no extrinsics): a normalised cross-correlation of marker-speed
     signals over a grid of offsets (the prior), then the correlation maximised over a
     continuous offset and drift. Speeds are rotation-invariant: :func:`speed_from_trajectories`
     (Vicon, labelled markers) and :func:`speed_from_frames` (one D415's
     :class:`~calib.markers.MarkerFrame` list, nearest-neighbour matching in the image, lateral
     speed from the image motion and depth). The two signals differ in shape, which biases the
     peak by milliseconds on the simulated sessions: a coarse prior only.

4. **Pulses** (:func:`clock_from_pulses`): the D415 master's frame pulses reach the DAVIS's
   external input, so DAVIS ↔ D415 is a line fitted through paired pulses and frames (µs-level),
   composed with the D415's mapping to reach the reference.

5. **Sync channel** (:func:`find_sync_edges`, :func:`clock_from_sync_edges`): the sync box's
   toggle output (one edge per D415 master pulse, docs/wiring.md §7) recorded on a Vicon analog
   input, i.e. sampled on the Vicon clock. Edges: mid-level crossings interpolated linearly
   between samples; a filtered (RC) edge crosses mid-level a delay after it switched, which is
   measured from the samples after each crossing (the decay towards the final level gives the
   time constant τ; each edge's switching instant is then exact for a first-order edge).
   Edges are paired with the master's frames through a prior mapping good to a quarter period
   (the video clock), and a line device → Vicon is fitted: µs-level offset and sub-ppm drift.

Clock mappings are :class:`mocaprig.calib.calibration.ClockMapping`:
``t_ref = t_dev + offset_ns + drift_ppm·1e-6·(t_dev − anchor_ns)``.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Final

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares, minimize
from scipy.spatial import cKDTree

from mocaprig.acquire.events import check_events
from mocaprig.calib.calibration import ClockMapping
from mocaprig.calib.camera_model import project_points
from mocaprig.calib.markers import MarkerFrame
from mocaprig.calib.vicon import AnalogChannels, MarkerTrajectories
from mocaprig.errors import CalibrationError, ValidationError

__all__ = [
    "VICON_CLAPPER_LABELS",
    "ClapDetection",
    "SyncEdges",
    "analog_times_ns",
    "clock_from_claps",
    "clock_from_pulses",
    "clock_from_sync_edges",
    "find_claps_d415",
    "find_claps_davis",
    "find_claps_vicon",
    "find_sync_edges",
    "refine_by_reprojection",
    "refine_by_speed",
    "speed_from_frames",
    "speed_from_trajectories",
    "vicon_times_ns",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: Labels the simulated Vicon (and a typical clapper subject) gives the clapperboard markers:
#: the moving arm's marker first.
VICON_CLAPPER_LABELS: Final = ("clapper:TOP", "clapper:BOTTOM")

#: A clap must open the markers at least this far beyond their contact distance (m).
_OPEN_MIN_M: Final = 0.05
#: Plausible marker-centre distances of a closed clapper (m).
_CONTACT_RANGE_M: Final = (0.005, 0.15)
#: Vicon markers nearer to a camera than this (m) are not projected into it (reprojection).
_MIN_DEPTH_M: Final = 0.05


@dataclass(frozen=True, slots=True, eq=False)
class ClapDetection:
    """One clap seen by one device.

    Attributes:
        device: Device label (``"vicon"``, ``"d415/<serial>"``, ``"davis/<serial>"``).
        t_ns: Contact instant in the device's own clock (integer ns, sub-frame).
        sigma_ns: 1σ uncertainty of ``t_ns`` (ns).
        quality: 0..1, how clean the detection is (1: closing well sampled and fitted).
        curve_t_ns: ``(K,)`` device times of the signal that was fitted (for the report).
        curve: ``(K,)`` that signal (Vicon: marker distance in m; D415: image distance in px;
            DAVIS: event rate of the clapper's image cell in events/s).
    """

    device: str
    t_ns: int
    sigma_ns: float
    quality: float
    curve_t_ns: I64 = field(repr=False)
    curve: F64 = field(repr=False)

    def __post_init__(self) -> None:
        t = np.array(self.curve_t_ns, dtype=np.int64)
        c = np.array(self.curve, dtype=np.float64)
        if t.shape != c.shape or t.ndim != 1:
            msg = f"clap of {self.device}: curve_t_ns and curve must be 1-D of one length"
            raise ValidationError(msg)
        t.setflags(write=False)
        c.setflags(write=False)
        object.__setattr__(self, "curve_t_ns", t)
        object.__setattr__(self, "curve", c)
        object.__setattr__(self, "t_ns", int(self.t_ns))
        object.__setattr__(self, "sigma_ns", float(self.sigma_ns))
        object.__setattr__(self, "quality", float(min(1.0, max(0.0, self.quality))))


# --------------------------------------------------------------------------- helpers


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


@dataclass(frozen=True, slots=True)
class _Episode:
    i_open: int  # last sample clearly open before the closing
    i_closed: int  # first sample back at contact level


def _episodes(
    d: F64,
    closed_level: float,
    closed_tol: float,
    open_min: float,
    min_closed: int,
    *,
    closed_mask: npt.NDArray[np.bool_] | None = None,
    min_open: int = 1,
) -> list[_Episode]:
    """Open → closed transitions of a distance signal (NaN = unknown).

    An episode needs ``min_open`` open samples since the last closed one, and ``min_closed``
    closed samples (80 % of those seen) from its first closed sample on.
    """
    ok = np.isfinite(d)
    is_open = ok & (d >= closed_level + open_min)
    is_closed = ok & (d <= closed_level + closed_tol)
    if closed_mask is not None:
        is_closed &= closed_mask
    out: list[_Episode] = []
    last_open = -1
    n_open = 0
    n = d.size
    i = 0
    while i < n:
        if is_open[i]:
            last_open = i
            n_open += 1
        elif is_closed[i] and n_open < min_open:
            last_open, n_open = -1, 0
        elif is_closed[i] and last_open >= 0:
            j_end = min(n, i + 3 * min_closed)
            seen = np.flatnonzero(ok[i:j_end])[: 2 * min_closed]
            if seen.size >= min_closed and np.count_nonzero(is_closed[i:j_end][seen]) >= max(
                min_closed, int(0.8 * seen.size)
            ):
                out.append(_Episode(last_open, i))
                last_open, n_open = -1, 0
        i += 1
    return out


def _describe_min(t_s: F64, d: F64, unit: str, scale: float) -> str:
    if not np.isfinite(d).any():
        return "no sample where both markers were seen"
    i = int(np.nanargmin(d))
    j = int(np.nanargmax(d))
    return (
        f"distance {np.nanmin(d) * scale:.0f}–{np.nanmax(d) * scale:.0f} {unit} "
        f"(closest at {t_s[i]:.2f} s, widest at {t_s[j]:.2f} s)"
    )


# ----------------------------------------------------------------------------- Vicon


def find_claps_vicon(
    traj: MarkerTrajectories,
    *,
    labels: tuple[str, str] = VICON_CLAPPER_LABELS,
    open_min_m: float = _OPEN_MIN_M,
    fit_samples: int = 5,
) -> list[ClapDetection]:
    """Claps in Vicon trajectories, from the distance of the two clapper markers.

    The contact distance is the low (5th percentile) level of the distance; a clap is an
    opening by more than ``open_min_m`` followed by a return to contact held for ≥ 50 ms. The
    contact instant is where a quadratic through the last ``fit_samples`` pre-contact samples
    of the closing reaches the contact distance (a line with fewer than 4 samples).

    Args:
        traj: Trajectories (metres), e.g. from :func:`mocaprig.calib.vicon.read_trajectories`.
        labels: The moving and the fixed clapper marker (exact or without subject prefix).
        open_min_m: Least opening beyond contact that counts as a clap (m).
        fit_samples: Pre-contact samples fitted.

    Returns:
        Claps in time order, ``t_ns`` in the Vicon clock (:func:`vicon_times_ns`).

    Raises:
        CalibrationError: a clapper marker is missing, the contact distance is implausible
            (wrong units?), or no clap is found; the message says what was seen.
    """
    where = traj.source or "the Vicon trajectories"
    try:
        top = traj.marker(labels[0])
        bottom = traj.marker(labels[1])
    except ValidationError as err:
        msg = (
            f"no clap in {where}: clapper markers {labels[0]}/{labels[1]} not found ({err}); "
            "pass labels=(moving, fixed) naming the clapperboard's markers"
        )
        raise CalibrationError(msg) from err
    t_ns = vicon_times_ns(traj)
    t_s = (t_ns - t_ns[0]) * 1e-9 if t_ns.size else np.zeros(0)
    d = np.linalg.norm(top - bottom, axis=1)
    names = f"{labels[0]}/{labels[1]}"
    if np.count_nonzero(np.isfinite(d)) < 10:
        msg = (
            f"no clap in {where}: clapper markers {names} are both present in "
            f"{np.count_nonzero(np.isfinite(d))} frames; need the clapper visible around claps"
        )
        raise CalibrationError(msg)
    level = float(np.nanpercentile(d, 5.0))
    if not _CONTACT_RANGE_M[0] <= level <= _CONTACT_RANGE_M[1]:
        msg = (
            f"no clap in {where}: clapper markers {names} are {level * 1000:.1f} mm apart when "
            f"closest (5th percentile), outside the plausible contact distance "
            f"{_CONTACT_RANGE_M[0] * 1000:.0f}–{_CONTACT_RANGE_M[1] * 1000:.0f} mm; wrong units "
            "(the trajectories must be in metres) or wrong markers?"
        )
        raise CalibrationError(msg)
    closed = np.isfinite(d) & (d <= level + 0.005)
    noise = float(np.std(d[closed])) if np.count_nonzero(closed) > 5 else 0.001
    noise = max(noise, 2e-4)
    tol = max(0.005, 5.0 * noise)
    min_closed = max(3, round(0.05 * traj.rate_hz))
    eps = _episodes(d, level, tol, open_min_m, min_closed)
    if not eps:
        msg = (
            f"no clap in {where}: clapper markers {names}: {_describe_min(t_s, d, 'mm', 1000)}, "
            f"contact level {level * 1000:.0f} mm; need an opening of > {open_min_m * 1000:.0f} "
            f"mm beyond contact followed by a return to within {tol * 1000:.0f} mm of it"
        )
        raise CalibrationError(msg)
    period_ns = 1e9 / traj.rate_hz
    out = []
    for ep in eps:
        # Contact level right after this clap (median of the closed samples that follow).
        after = d[ep.i_closed : ep.i_closed + max(2 * min_closed, 12)]
        after = after[np.isfinite(after) & (after <= level + tol)]
        dc = float(np.median(after))
        dc_sigma = noise / math.sqrt(max(after.size, 1))
        # Pre-contact samples: clearly above contact, falling, before the first closed sample.
        # Pre-contact samples: back from the first closed sample while the distance keeps
        # growing (the closing), clearly above contact.
        pre: list[int] = []
        for i in range(ep.i_closed - 1, max(-1, ep.i_closed - 4 * fit_samples), -1):
            if len(pre) >= fit_samples:
                break
            if not np.isfinite(d[i]):
                continue
            if pre and d[i] < d[pre[-1]] - 2.0 * noise:
                break
            if d[i] > dc + 4.0 * noise:
                pre.append(i)
        pre.reverse()
        lo = max(0, ep.i_open - round(0.3 * traj.rate_hz))
        hi = min(d.size, ep.i_closed + round(0.2 * traj.rate_hz))
        curve_t, curve = t_ns[lo:hi], d[lo:hi]
        if len(pre) < 2:
            t_c = float(t_ns[ep.i_closed]) - 0.5 * period_ns
            sigma = period_ns / math.sqrt(12.0)
            quality = 0.2
        else:
            t_c, sigma = _fit_contact_poly(
                t_ns[pre].astype(np.float64), d[pre], dc, noise, dc_sigma, period_ns
            )
            quality = min(1.0, len(pre) / fit_samples) * (1.0 if sigma < 0.25 * period_ns else 0.5)
        out.append(ClapDetection("vicon", round(t_c), sigma, quality, curve_t, curve))
    _log.info(
        "vicon claps at %s s (contact %.1f mm)",
        ", ".join(f"{(c.t_ns - t_ns[0]) * 1e-9:.3f}" for c in out),
        level * 1000,
    )
    return out


def _fit_contact_poly(
    t: F64, d: F64, dc: float, noise: float, dc_sigma: float, period_ns: float
) -> tuple[float, float]:
    """Where a polynomial through the closing samples reaches ``dc``; (t_ns, sigma_ns)."""
    t0 = t[-1]
    x = (t - t0) / period_ns  # frames, ≤ 0
    deg = 2 if t.size >= 4 else 1
    coef = np.polyfit(x, d, deg)
    poly = np.poly1d(coef)
    roots = (poly - dc).roots
    real = [float(r.real) for r in np.atleast_1d(roots) if abs(r.imag) < 1e-9 and 0 <= r.real < 3]
    if not real:
        coef = np.polyfit(x[-3:], d[-3:], 1)
        poly = np.poly1d(coef)
        deg = 1
        real = [float((dc - coef[1]) / coef[0])] if coef[0] < 0 else [0.5]
    xc = min(real)
    slope = float(poly.deriv()(xc))
    # Prediction variance at xc from the least-squares covariance.
    a = np.vander(x if deg == 2 else x[-3:] if x.size >= 3 else x, deg + 1)
    cov = noise**2 * np.linalg.pinv(a.T @ a)
    v = np.vander(np.array([xc]), deg + 1)[0]
    var = float(v @ cov @ v) + dc_sigma**2
    sigma_frames = math.sqrt(var) / max(abs(slope), 1e-9)
    return t0 + xc * period_ns, min(sigma_frames * period_ns, period_ns)


# ------------------------------------------------------------------------------ D415


def _static_points(
    frames: Sequence[MarkerFrame], min_presence: float, radius_px: float
) -> list[tuple[F64, float]]:
    """Image positions seen (within ``radius_px``) in at least ``min_presence`` of frames."""
    step = max(1, len(frames) // 400)
    sub = list(frames[::step])
    uv = np.concatenate([f.uv_px for f in sub]) if sub else np.zeros((0, 2))
    if uv.shape[0] == 0:
        return []
    tree = cKDTree(uv)
    counts = np.asarray(tree.query_ball_point(uv, radius_px, return_length=True))
    need = min_presence * len(sub)
    order = np.argsort(-counts, kind="stable")
    out: list[tuple[F64, float]] = []
    for i in order:
        if counts[i] < need:
            break
        if any(np.hypot(*(uv[i] - c)) < 2.0 * radius_px for c, _ in out):
            continue
        near = uv[tree.query_ball_point(uv[i], radius_px)]
        out.append((np.median(near, axis=0), float(counts[i]) / len(sub)))
    return out


def _track_moving(
    frames: Sequence[MarkerFrame], fixed: F64, start: F64, reach_px: float, step_px: float
) -> tuple[F64, npt.NDArray[np.bool_]]:
    """Per frame, image distance (px) of the marker that starts at ``start`` from ``fixed``.

    The moving marker is followed frame to frame: the blob nearest to its constant-acceleration
    prediction, within ``step_px`` of its last position and ``reach_px`` of the fixed one, in
    the direction it left its closed position, and not a blob at rest while it was moving;
    back at its closed position it is taken at once. NaN where it is not found. Also returns
    where it sits at ``start`` (its closed position).
    """
    out = np.full(len(frames), np.nan)
    at_home = np.zeros(len(frames), dtype=bool)
    last = start.copy()
    velocity = np.zeros(2)
    velocity_before = np.zeros(2)
    out_ok = False
    prev: F64 | None = None
    for k, f in enumerate(frames):
        uv = f.uv_px
        if uv.shape[0] == 0:
            prev, out_ok = None, False
            continue
        from_fixed = np.hypot(uv[:, 0] - fixed[0], uv[:, 1] - fixed[1])
        cand = (from_fixed > 1.5) & (from_fixed <= reach_px)
        if not cand.any():
            prev, out_ok = uv, False
            continue
        home = np.hypot(uv[:, 0] - start[0], uv[:, 1] - start[1])
        toward_home = float(velocity @ (start - last)) > 0 and float(np.hypot(*velocity)) > 2.0
        near_home = float(np.hypot(*(last - start))) <= 4.0
        if np.any(cand & (home <= 1.5)) and (near_home or toward_home or not out_ok):
            # Back at its closed position (it was there, was swinging back, or was lost): that
            # is the moving marker whatever else is near. A blob passing its closed position
            # while it holds open is not.
            j = int(np.argmin(np.where(cand, home, np.inf)))
            at_home[k] = True
        else:
            dist = np.hypot(uv[:, 0] - last[0], uv[:, 1] - last[1])
            pred = last + 2.0 * velocity - velocity_before  # constant acceleration
            dist_pred = np.hypot(uv[:, 0] - pred[0], uv[:, 1] - pred[1])
            lv = last - start
            reach = float(np.hypot(*lv))
            if reach > 4.0:
                # The moving arm swings on an arc: seen from its closed position the marker
                # keeps (nearly) one direction, so a blob off that direction is something else.
                cv_ = uv - start
                norm = np.hypot(cv_[:, 0], cv_[:, 1]) * reach
                cos = (cv_ @ lv) / np.maximum(norm, 1e-9)
                cand &= cos > math.cos(math.radians(30.0))
            still = (
                cKDTree(prev).query(uv)[0] < 1.0
                if prev is not None and prev.shape[0]
                else np.zeros(uv.shape[0], dtype=bool)
            )
            dist_pred[~cand] = np.inf
            j = int(np.argmin(dist_pred))
            speed = float(np.hypot(*velocity))
            if not dist_pred[j] <= max(2.5, 0.5 * speed):
                # Not where smooth motion puts it. The closing (a fast swing back home)
                # retraces the arc: look between its last position and home, among blobs that
                # moved since the previous frame (a marker at rest there is something else).
                j_smooth, j = j, -1
                if reach > 4.0:
                    seg = (uv - start) @ lv / (reach * reach)
                    perp = np.abs((uv - start) @ np.array([-lv[1], lv[0]])) / reach
                    band = (
                        cand
                        & ~still
                        & (seg > -0.05)
                        & (seg < 0.97)
                        & (perp < 0.12 * reach + 2.0)
                        & (dist >= max(2.0, 0.5 * speed))
                    )
                    if band.any():
                        # The closing accelerates all the way to contact: take the blob
                        # furthest along towards home.
                        j = int(np.argmin(np.where(band, seg, np.inf)))
                if j < 0 and dist[j_smooth] <= max(6.0, 1.5 * speed):
                    j = j_smooth  # a modest change of pace (leaving home, slowing down)
                if j < 0 or dist[j] > step_px:
                    prev, out_ok = uv, False
                    continue
        velocity_before = velocity if out_ok else np.zeros(2)
        velocity = uv[j] - last if out_ok else np.zeros(2)
        out_ok = True
        last = uv[j].copy()
        out[k] = from_fixed[j]
        prev = uv
    return out, at_home


def find_claps_d415(
    frames: Sequence[MarkerFrame],
    *,
    device: str | None = None,
    open_min_m: float = _OPEN_MIN_M,
    contact_range_m: tuple[float, float] = (0.015, 0.08),
    reach_m: float = 0.45,
    closing_prior_s: tuple[float, float] = (0.09, 0.05),
    model_sigma: float = 0.08,
) -> list[ClapDetection]:
    """Claps in one D415's marker frames (unlabelled markers; no extrinsics needed).

    The clapper is the pair of static blobs (present at one image position in ≥ 30 % of the
    frames) whose 3-D distance is a contact distance (``contact_range_m``) and of which one
    leaves by more than ``open_min_m`` and comes back. The signal is the image distance (px) of
    the moving marker from the fixed one; each closing is fitted as in the module doc.

    Args:
        frames: One camera's :class:`~calib.markers.MarkerFrame` list (any order), covering the
            claps (with ≥ 0.3 s before each closing and ≥ 0.15 s after).
        device: Label for the result (default: the frames' ``camera``).
        open_min_m: Least opening beyond contact that counts as a clap (m).
        contact_range_m: Plausible closed marker-centre distances (m).
        reach_m: Largest distance of the moving marker from the fixed one (m).
        closing_prior_s: Prior (mean, sd) of the closing duration (s).
        model_sigma: Model error of the normalised closing signal, added to the measured
            noise: the image distance is not linear in the angle (seen obliquely and close up,
            by up to 0.15 of the opening on the simulated rig).

    Returns:
        Claps in time order, ``t_ns`` in the camera's device clock.

    Raises:
        CalibrationError: too few frames, no clapper-like pair, or no clap; says what it saw.
    """
    fr = sorted(frames, key=lambda f: f.t_dev_ns)
    name = device or (fr[0].camera if fr and fr[0].camera else "d415")
    if len(fr) < 10:
        msg = f"no clap in {name}: only {len(fr)} marker frames; need the frames around a clap"
        raise CalibrationError(msg)
    t_ns = np.array([f.t_dev_ns for f in fr], dtype=np.int64)
    t_s = (t_ns - t_ns[0]) * 1e-9
    period_ns = float(np.median(np.diff(t_ns)))
    if not period_ns > 0:
        msg = f"no clap in {name}: frame times do not increase (median step {period_ns} ns)"
        raise CalibrationError(msg)
    statics = _static_points(fr, 0.3, 1.5)
    if len(statics) < 2:
        msg = (
            f"no clap in {name}: looked for the clapperboard as two markers that stay at one "
            f"image position in ≥ 30 % of {len(fr)} frames ({t_s[-1]:.1f} s) and found "
            f"{len(statics)}; is the clapper in view and closed between claps?"
        )
        raise CalibrationError(msg)
    xyz_static = [_median_xyz(fr, c) for c, _ in statics]
    focal = _focal_px(fr)
    best: tuple[float, float, list[_Episode], F64, F64, float] | None = None
    seen: list[tuple[float, str]] = []
    min_open = max(2, math.ceil(0.2e9 / period_ns))
    for a in range(len(statics)):
        for b in range(len(statics)):
            if a == b:
                continue
            pa, pb = xyz_static[a], xyz_static[b]
            if not (np.isfinite(pa).all() and np.isfinite(pb).all()):
                continue
            dist_m = float(np.linalg.norm(pa - pb))
            if not contact_range_m[0] <= dist_m <= contact_range_m[1]:
                continue
            z = float(pb[2])
            px_per_m = focal / z
            if statics[b][1] < 0.8:  # the fixed arm's marker is there all the time
                continue
            sig, home = _track_moving(
                fr, statics[b][0], statics[a][0], reach_m * px_per_m, 0.3 * px_per_m
            )
            level = float(np.hypot(*(statics[a][0] - statics[b][0])))
            eps = _episodes(
                sig, level, 2.0, open_min_m * px_per_m, 3, closed_mask=home, min_open=min_open
            )
            widest = (np.nanmax(sig) - level) / px_per_m if np.isfinite(sig).any() else 0.0
            seen.append(
                (
                    widest,
                    (
                        f"{dist_m * 1000:.0f} mm apart at {z:.2f} m: opened "
                        f"{widest * 1000:.0f} mm, {len(eps)} claps"
                    ),
                )
            )
            score = len(eps) + statics[b][1]
            if eps and (best is None or score > best[0]):
                best = (score, level, eps, sig, statics[b][0], px_per_m)
    if best is None:
        msg = (
            f"no clap in {name}: looked at {len(statics)} static blobs over {t_s[-1]:.1f} s for "
            f"a pair {contact_range_m[0] * 1000:.0f}–{contact_range_m[1] * 1000:.0f} mm apart "
            f"that opens by > {open_min_m * 1000:.0f} mm and closes again; saw "
            f"{_top_pairs(seen)}"
        )
        raise CalibrationError(msg)
    _, level, eps, sig, _, px_per_m = best
    out = []
    for ep in eps:
        out.append(
            _fit_closing(
                name, t_ns, sig, ep, level, period_ns, closing_prior_s, model_sigma, px_per_m
            )
        )
    _log.info(
        "%s claps at %s s (device clock from the first frame)",
        name,
        ", ".join(f"{(c.t_ns - t_ns[0]) * 1e-9:.3f}" for c in out),
    )
    return out


def _top_pairs(seen: list[tuple[float, str]]) -> str:
    if not seen:
        return "no such pair"
    ranked = sorted(seen, key=lambda x: -x[0])
    more = f" (and {len(ranked) - 3} more)" if len(ranked) > 3 else ""
    return "; ".join(x[1] for x in ranked[:3]) + more


def _median_xyz(frames: Sequence[MarkerFrame], uv: F64) -> F64:
    pts = []
    for f in frames[:: max(1, len(frames) // 200)]:
        if f.n_markers == 0:
            continue
        d = np.hypot(f.uv_px[:, 0] - uv[0], f.uv_px[:, 1] - uv[1])
        j = int(np.argmin(d))
        if d[j] < 1.5 and np.isfinite(f.xyz_cam_m[j]).all():
            pts.append(f.xyz_cam_m[j])
    if not pts:
        return np.full(3, np.nan)
    out: F64 = np.median(np.array(pts), axis=0)
    return out


def _focal_px(frames: Sequence[MarkerFrame]) -> float:
    """Focal length (px) recovered from the frames' deprojection (u − cx)·z/f = x."""
    num, den = [], []
    for f in frames[:: max(1, len(frames) // 50)]:
        ok = f.has_depth & (np.abs(f.xyz_cam_m[:, 0]) > 0.05)
        if np.count_nonzero(ok) >= 2:
            p = f.xyz_cam_m[ok]
            uv = f.uv_px[ok]
            # u = fx·x/z + cx for two points: fx = Δu / Δ(x/z).
            a = p[:, 0] / p[:, 2]
            i, j = int(np.argmin(a)), int(np.argmax(a))
            if a[j] - a[i] > 0.05:
                num.append(uv[j, 0] - uv[i, 0])
                den.append(a[j] - a[i])
    if not num:
        msg = "cannot recover the focal length from the marker frames (no markers with depth)"
        raise CalibrationError(msg)
    return float(np.median(np.array(num) / np.array(den)))


def _fit_closing(
    name: str,
    t_ns: I64,
    sig: F64,
    ep: _Episode,
    level: float,
    period_ns: float,
    prior: tuple[float, float],
    model_sigma: float,
    px_per_m: float,
) -> ClapDetection:
    """Fit the closing trajectory θ = θmax(1 − u²) around one episode (grid posterior)."""
    t_closed = float(t_ns[ep.i_closed])
    lo_t = t_closed - 0.45e9
    hi_t = t_closed + 0.2e9
    win = (t_ns >= lo_t) & (t_ns <= hi_t) & np.isfinite(sig)
    tw = t_ns[win].astype(np.float64)
    sw = sig[win]
    # Hold level: the top of the signal in the 0.4 s before the closing.
    before = sw[tw < t_closed]
    hold = float(np.percentile(before, 90)) if before.size else float(np.nanmax(sw))
    span = hold - level
    y = (sw - level) / span
    after = y[tw >= t_closed]
    noise = float(np.std(after)) if after.size >= 3 else 0.01
    sigma_y = math.hypot(max(noise, 0.003), model_sigma)
    # Bracket the contact: after the last clearly-open sample, before the first closed one
    # (plus a period, in case that sample itself was still closing).
    open_idx = np.flatnonzero((tw < t_closed) & (y > 3.0 * sigma_y))
    t_a = float(tw[open_idx[-1]]) if open_idx.size else t_closed - period_ns
    t_b = t_closed + 0.5 * period_ns
    tc_grid = np.arange(t_a, t_b, 2.5e5)  # 0.25 ms
    dur_grid = np.arange(0.02, 0.3, 0.002) * 1e9
    tc = tc_grid[:, None, None]
    dur = dur_grid[None, :, None]
    u = np.clip((tw[None, None, :] - (tc - dur)) / dur, 0.0, 1.0)
    model = 1.0 - u * u
    chi2 = np.sum(((y[None, None, :] - model) / sigma_y) ** 2, axis=2)
    chi2 = chi2 + ((dur_grid[None, :] * 1e-9 - prior[0]) / prior[1]) ** 2
    w = np.exp(-0.5 * (chi2 - chi2.min()))
    w /= w.sum()
    p_tc = w.sum(axis=1)
    mean = float(np.sum(p_tc * tc_grid))
    sd = float(math.sqrt(max(np.sum(p_tc * (tc_grid - mean) ** 2), 0.0) + (2.5e5**2) / 12.0))
    n_closing = int(np.count_nonzero((y > 3.0 * sigma_y) & (y < 1.0 - 3.0 * sigma_y)))
    quality = min(1.0, n_closing / 3.0) * (1.0 if sd < 0.1 * period_ns else 0.5)
    _log.debug(
        "%s clap: %d closing samples, opening %.0f mm, sd %.2f ms",
        name,
        n_closing,
        span / px_per_m * 1000,
        sd * 1e-6,
    )
    lo = max(0, ep.i_open - 12)
    hi = min(sig.size, ep.i_closed + 6)
    return ClapDetection(name, round(mean), sd, quality, t_ns[lo:hi], sig[lo:hi])


# ------------------------------------------------------------------------------ DAVIS


def find_claps_davis(
    events: npt.ArrayLike,
    *,
    device: str = "davis",
    bin_us: int = 1000,
    cell_px: int = 30,
    window_us: int = 30_000,
    max_claps: int = 2,
    min_separation_s: float = 1.0,
    min_events: int = 200,
) -> list[ClapDetection]:
    """Claps in DAVIS events: the sharpest stop of an event burst in one image cell.

    The closing arm sweeps events over its cell at a rising rate, and the stream stops dead at
    contact. Per cell (``cell_px`` square) the event rate is binned (``bin_us``); the score of a
    bin edge is the count in the ``window_us`` before minus twice the count in the window
    after, and the best-scoring edges at least ``min_separation_s`` apart are the claps, at the
    last event before the fall. Accuracy is about one bin; use the pulses
    (:func:`clock_from_pulses`) for the DAVIS clock, this is a cross-check.

    Args:
        events: Canonical :data:`mocaprig.acquire.events.EVENT_DTYPE` events (device µs), sorted.
        device: Label for the result.
        bin_us, cell_px, window_us: Rate binning.
        max_claps: How many claps to return at most.
        min_separation_s: Least time between two claps.
        min_events: Least events in the window before a stop for it to count.

    Raises:
        CalibrationError: too few events, or no burst that stops.
    """
    ev = check_events(events)
    if ev.size < min_events:
        msg = f"no clap in {device}: only {ev.size} events; need the events around a clap"
        raise CalibrationError(msg)
    t = ev["t"].astype(np.int64)
    t0 = int(t[0])
    nb = int((t[-1] - t0) // bin_us) + 1
    nx = int(ev["x"].max()) // cell_px + 1
    ny = int(ev["y"].max()) // cell_px + 1
    cell = (ev["y"].astype(np.int64) // cell_px) * nx + ev["x"].astype(np.int64) // cell_px
    b = (t - t0) // bin_us
    counts = np.zeros((nx * ny, nb), dtype=np.float64)
    np.add.at(counts, (cell, b), 1.0)
    wb = max(1, window_us // bin_us)
    c = np.concatenate([np.zeros((counts.shape[0], 1)), np.cumsum(counts, axis=1)], axis=1)
    edges = np.arange(wb, nb - wb + 1)
    if edges.size == 0:
        msg = (
            f"no clap in {device}: the events span {(t[-1] - t0) / 1e3:.0f} ms, shorter than "
            f"two {window_us / 1e3:.0f} ms windows"
        )
        raise CalibrationError(msg)
    before = c[:, edges] - c[:, edges - wb]
    after = c[:, edges + wb] - c[:, edges]
    score = before - 2.0 * after
    best_cell = score.max(axis=0)
    which = score.argmax(axis=0)
    out: list[ClapDetection] = []
    taken: list[int] = []
    order = np.argsort(-best_cell, kind="stable")
    for k in order:
        if len(out) >= max_claps:
            break
        if best_cell[k] < min_events:
            break
        edge_t = t0 + int(edges[k]) * bin_us
        if any(abs(edge_t - x) < min_separation_s * 1e6 for x in taken):
            continue
        taken.append(edge_t)
        cid = int(which[k])
        mask = (cell == cid) & (t < edge_t + bin_us) & (t >= edge_t - window_us)
        t_last = int(t[mask].max()) if mask.any() else edge_t
        lo, hi = max(0, int(edges[k]) - 4 * wb), min(nb, int(edges[k]) + 2 * wb)
        curve_t = (t0 + np.arange(lo, hi) * bin_us) * 1000
        curve = counts[cid, lo:hi] * (1e6 / bin_us)
        quality = float(min(1.0, best_cell[k] / (4.0 * min_events)))
        out.append(
            ClapDetection(
                device, t_last * 1000, bin_us * 1000 / math.sqrt(12.0), quality, curve_t, curve
            )
        )
    if not out:
        msg = (
            f"no clap in {device}: looked for an event burst in one {cell_px}-px cell that stops "
            f"within {bin_us} µs; the best stop had {best_cell.max():.0f} events before it "
            f"(need {min_events})"
        )
        raise CalibrationError(msg)
    out.sort(key=lambda x: x.t_ns)
    return out


# --------------------------------------------------------------------- clocks from claps


def _pair_claps(
    dev: Sequence[ClapDetection], ref: Sequence[ClapDetection], tol_ns: float
) -> list[tuple[ClapDetection, ClapDetection]]:
    """Pair device and reference claps under the offset that pairs the most."""
    best: list[tuple[ClapDetection, ClapDetection]] = []
    best_spread = math.inf
    for d0 in dev:
        for r0 in ref:
            off = r0.t_ns - d0.t_ns
            pairs = []
            for d in dev:
                diffs = [abs(r.t_ns - (d.t_ns + off)) for r in ref]
                j = int(np.argmin(diffs))
                if diffs[j] <= tol_ns:
                    pairs.append((d, ref[j]))
            spread = float(np.std([r.t_ns - d.t_ns for d, r in pairs])) if pairs else math.inf
            if len(pairs) > len(best) or (len(pairs) == len(best) and spread < best_spread):
                best, best_spread = pairs, spread
    return best


def clock_from_claps(
    device: str,
    dev_claps: Sequence[ClapDetection],
    ref_claps: Sequence[ClapDetection],
    *,
    reference: str = "vicon",
    pair_tol_ns: int = 50_000_000,
    max_drift_ppm: float = 200.0,
) -> ClockMapping:
    """A device's clock mapping from its claps and the reference's.

    Claps are paired under the common offset that pairs the most (within ``pair_tol_ns``,
    covering drift and detection error). Two or more pairs give offset and drift (a weighted
    line); one pair gives the offset only (drift 0, logged as a warning), and so does a drift
    beyond ``max_drift_ppm`` (crystals drift tens of ppm: such a line means a clap was detected
    poorly; the best clap's offset is kept).

    Raises:
        CalibrationError: no claps on a side, or an implausible drift (> 1000 ppm: the claps
            were paired wrongly or the times are not in ns).
    """
    if not dev_claps or not ref_claps:
        msg = (
            f"cannot map {device} onto {reference}: {len(dev_claps)} device claps and "
            f"{len(ref_claps)} reference claps; need at least one of each"
        )
        raise CalibrationError(msg)
    pairs = _pair_claps(dev_claps, ref_claps, pair_tol_ns)
    if len(dev_claps) >= 2 and len(ref_claps) >= 2 and len(pairs) < 2:
        _log.warning(
            "%s: only %d of %d claps pair with %s's within %.0f ms",
            device,
            len(pairs),
            len(dev_claps),
            reference,
            pair_tol_ns / 1e6,
        )
    td = np.array([d.t_ns for d, _ in pairs], dtype=np.int64)
    tr = np.array([r.t_ns for _, r in pairs], dtype=np.int64)
    sig = np.array([math.hypot(d.sigma_ns, r.sigma_ns) for d, r in pairs])
    sig = np.maximum(sig, 1.0)
    anchor = int(np.round(np.mean(td)))
    y = (tr - td).astype(np.float64)  # reference minus device
    if len(pairs) == 1:
        _log.warning(
            "%s: one clap pairs with %s; offset only (drift unknown, set to 0)", device, reference
        )
        return ClockMapping(
            device, reference, int(y[0]), 0.0, anchor, float(sig[0]), math.nan, "clap"
        )
    x = (td - anchor).astype(np.float64)
    w = 1.0 / sig**2
    a = np.column_stack([np.ones_like(x), x])
    cov = np.linalg.inv(a.T @ (a * w[:, None]))
    coef = cov @ (a.T @ (w * y))
    drift_ppm = float(coef[1] * 1e6)
    if max_drift_ppm < abs(drift_ppm) <= 1000:
        best = int(np.argmin(sig))
        _log.warning(
            "%s: the claps give a drift of %.0f ppm, beyond %.0f ppm (a clap detected poorly?); "
            "using the offset of the best clap only",
            device,
            drift_ppm,
            max_drift_ppm,
        )
        return ClockMapping(
            device, reference, int(y[best]), 0.0, int(td[best]), float(sig[best]), math.nan, "clap"
        )
    if abs(drift_ppm) > 1000:
        msg = (
            f"cannot map {device} onto {reference}: the claps give a drift of "
            f"{drift_ppm:.0f} ppm (clap pairs {td.tolist()} ↔ {tr.tolist()} ns); paired wrongly, "
            "or times not in ns"
        )
        raise CalibrationError(msg)
    return ClockMapping(
        device,
        reference,
        round(float(coef[0])),
        drift_ppm,
        anchor,
        float(math.sqrt(cov[0, 0])),
        float(math.sqrt(cov[1, 1]) * 1e6),
        "clap",
    )


# ----------------------------------------------------------------------------- speeds


def speed_from_trajectories(
    traj: MarkerTrajectories, *, labels: Sequence[str] | None = None
) -> tuple[I64, F64]:
    """Mean marker speed (m/s) of Vicon trajectories at every frame (Vicon clock ns).

    Central differences per marker (NaN across gaps), then the mean over the markers present;
    NaN where none is.
    """
    tr = traj if labels is None else traj.select(labels)
    t = vicon_times_ns(tr)
    p = tr.positions_m
    if tr.n_frames < 3:
        msg = f"{tr.source or 'trajectories'}: {tr.n_frames} frames, too few for speeds"
        raise CalibrationError(msg)
    v = np.full(p.shape[:2], np.nan)
    v[1:-1] = np.linalg.norm(p[2:] - p[:-2], axis=2) * (tr.rate_hz / 2.0)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(v)
        n = ok.sum(axis=1)
        s = np.where(ok, v, 0.0).sum(axis=1)
        speed = np.where(n > 0, s / np.maximum(n, 1), np.nan)
    return t, speed


def speed_from_frames(
    frames: Sequence[MarkerFrame], *, max_step_px: float = 20.0, min_matches: int = 3
) -> tuple[I64, F64]:
    """Mean lateral marker speed (m/s) between consecutive frames of one D415.

    Blobs of consecutive frames (frame counters one apart) are matched as mutual nearest
    neighbours in the image within ``max_step_px``; each match's speed is its image motion
    times its depth over the focal length (the lateral part of the 3-D motion: image positions
    are far more precise than D415 depth), over the frame interval. The value is the mean over
    the matches, stamped at the midpoint of the two frames; NaN with fewer than
    ``min_matches`` matches. Rotation-invariant: no extrinsics needed.

    Returns:
        ``(t_dev_ns (M,), speed (M,))`` in the camera's device clock.
    """
    fr = sorted(frames, key=lambda f: f.t_dev_ns)
    if len(fr) < 3:
        msg = f"{len(fr)} marker frames are too few for a speed signal"
        raise CalibrationError(msg)
    focal = _focal_px(fr)
    t_out, s_out = [], []
    for a, b in itertools.pairwise(fr):
        if b.frame_counter - a.frame_counter != 1 or a.n_markers == 0 or b.n_markers == 0:
            continue
        dt = (b.t_dev_ns - a.t_dev_ns) * 1e-9
        if not dt > 0:
            continue
        ta = cKDTree(a.uv_px)
        d_ab, j_ab = ta.query(b.uv_px, distance_upper_bound=max_step_px)
        tb = cKDTree(b.uv_px)
        _, j_ba = tb.query(a.uv_px, distance_upper_bound=max_step_px)
        ib = np.flatnonzero(np.isfinite(d_ab))
        ja = j_ab[ib]
        mutual = j_ba[ja] == ib
        ib, ja = ib[mutual], ja[mutual]
        z = np.fmax(a.xyz_cam_m[ja, 2], b.xyz_cam_m[ib, 2])
        ok = np.isfinite(z)
        if np.count_nonzero(ok) < min_matches:
            t_out.append((a.t_dev_ns + b.t_dev_ns) // 2)
            s_out.append(math.nan)
            continue
        px = np.hypot(*(b.uv_px[ib[ok]] - a.uv_px[ja[ok]]).T)
        t_out.append((a.t_dev_ns + b.t_dev_ns) // 2)
        s_out.append(float(np.mean(px * z[ok] / focal)) / dt)
    return np.array(t_out, dtype=np.int64), np.array(s_out, dtype=np.float64)


# ------------------------------------------------------------------------- refinement


def _box_filtered(t_ns: F64, v: F64, width_ns: float) -> tuple[F64, F64]:
    """Cumulative integral of ``v`` (NaN as 0) for box averages over ``width_ns``."""
    vv = np.where(np.isfinite(v), v, 0.0)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (vv[1:] + vv[:-1]) * np.diff(t_ns))])
    return t_ns, cum


def _box_eval(tt: F64, cum: F64, x: F64, width_ns: float) -> F64:
    hi = np.interp(x + 0.5 * width_ns, tt, cum)
    lo = np.interp(x - 0.5 * width_ns, tt, cum)
    out: F64 = (hi - lo) / width_ns
    return out


def refine_by_speed(
    mapping: ClockMapping,
    dev_t_ns: npt.ArrayLike,
    dev_speed: npt.ArrayLike,
    ref_t_ns: npt.ArrayLike,
    ref_speed: npt.ArrayLike,
    *,
    search_ns: int = 100_000_000,
    average_ns: int | None = None,
    fit_drift: bool = True,
    min_samples: int = 60,
) -> ClockMapping:
    """Refine a clock mapping by matching the device's speed signal to the reference's.

    The reference speed is box-averaged over ``average_ns`` (default: the device's sample
    period, which is what a displacement between consecutive frames measures) and evaluated at
    the device samples' mapped times. First a normalised cross-correlation over offsets within
    ``±search_ns`` (1 ms grid, the prior), then the correlation maximised (Nelder–Mead) over a
    continuous offset correction and drift correction (``fit_drift``; a Gaussian prior with the
    mapping's drift sigma, else 50 ppm). Correlation is blind to gain and bias, so lateral and
    3-D speeds can be compared; their different shapes still bias the peak (module doc).

    Args:
        mapping: The current device → reference mapping (from claps).
        dev_t_ns, dev_speed: Device speed samples (device clock ns; NaN = unknown).
        ref_t_ns, ref_speed: Reference speed samples (reference clock ns; NaN = unknown).
        search_ns: Half-width of the offset search around ``mapping`` (ns).
        average_ns: Box average applied to the reference speed (ns).
        fit_drift: Also refine the drift (needs motion spread over the session).
        min_samples: Fewest overlapping device samples.

    Returns:
        The refined mapping (``method`` + ``"+xcorr"``), anchored at the middle of the device
        samples, with 1σ uncertainties from the fit.

    Raises:
        CalibrationError: too little overlap or motion, or no correlation peak inside the search.
    """
    td = np.asarray(dev_t_ns, dtype=np.int64)
    vd = np.asarray(dev_speed, dtype=np.float64)
    tr = np.asarray(ref_t_ns, dtype=np.int64)
    vr = np.asarray(ref_speed, dtype=np.float64)
    if td.ndim != 1 or td.shape != vd.shape or tr.ndim != 1 or tr.shape != vr.shape:
        msg = "refine_by_speed: times and speeds must be 1-D arrays of equal length per side"
        raise ValidationError(msg)
    if np.any(np.diff(td) <= 0) or np.any(np.diff(tr) <= 0):
        msg = "refine_by_speed: sample times must be strictly increasing (ns)"
        raise ValidationError(msg)
    if td.size < 3 or tr.size < 3:
        msg = f"cannot refine {mapping.device}: {td.size} device and {tr.size} reference samples"
        raise CalibrationError(msg)
    width = float(average_ns if average_ns is not None else np.median(np.diff(td)))
    ttf = tr.astype(np.float64)
    _, cum = _box_filtered(ttf, vr, width)
    valid_ref = np.isfinite(vr).astype(np.float64)
    _, cum_valid = _box_filtered(ttf, valid_ref, width)
    anchor = int((int(td[0]) + int(td[-1])) // 2)
    mapped = mapping.to_reference_ns(td).astype(np.float64)
    rel = (td - anchor).astype(np.float64)
    ok_dev = np.isfinite(vd)

    def ref_at(x: F64) -> tuple[F64, F64]:
        val = _box_eval(ttf, cum, x, width)
        cover = _box_eval(ttf, cum_valid, x, width)
        inside = (x - 0.5 * width >= ttf[0]) & (x + 0.5 * width <= ttf[-1]) & (cover > 0.9)
        return val / np.maximum(cover, 1e-9), inside

    lags = np.arange(-float(search_ns), float(search_ns) + 1.0, 1e6)
    corr = np.full(lags.size, np.nan)
    for k, lag in enumerate(lags):
        r, inside = ref_at(mapped + lag)
        m = ok_dev & inside
        if np.count_nonzero(m) < min_samples:
            continue
        a, b = vd[m], r[m]
        sa, sb = a.std(), b.std()
        if sa > 0 and sb > 0:
            corr[k] = float(np.mean((a - a.mean()) * (b - b.mean())) / (sa * sb))
    if not np.isfinite(corr).any():
        msg = (
            f"cannot refine {mapping.device} by speed: fewer than {min_samples} device samples "
            f"overlap the reference within ±{search_ns / 1e6:.0f} ms of the clap mapping"
        )
        raise CalibrationError(msg)
    k = int(np.nanargmax(corr))
    if k == 0 or k == lags.size - 1:
        msg = (
            f"cannot refine {mapping.device} by speed: the correlation peaks at the edge of the "
            f"±{search_ns / 1e6:.0f} ms search (r = {corr[k]:.2f}); the clap mapping is off by "
            "more than that, or the signals do not match"
        )
        raise CalibrationError(msg)
    if corr[k] < 0.3:
        msg = (
            f"cannot refine {mapping.device} by speed: best correlation {corr[k]:.2f} "
            f"(at {lags[k] / 1e6:+.0f} ms) is too weak; the session needs more motion"
        )
        raise CalibrationError(msg)
    lag0 = float(lags[k])
    # The drift correction has a Gaussian prior (the clap drift's sigma, else 50 ppm): a short
    # or dull session cannot then run it away.
    drift_prior = mapping.drift_sigma_ppm
    if not (math.isfinite(drift_prior) and drift_prior > 0):
        drift_prior = 50.0

    def corr_at(delta_ns: float, eps_ppm: float) -> tuple[float, int]:
        r, inside = ref_at(mapped + delta_ns + eps_ppm * 1e-6 * rel)
        m = ok_dev & inside
        n = int(np.count_nonzero(m))
        if n < min_samples:
            return -1.0, n
        a, b = vd[m], r[m]
        sa, sb = a.std(), b.std()
        if not (sa > 0 and sb > 0):
            return -1.0, n
        return float(np.mean((a - a.mean()) * (b - b.mean())) / (sa * sb)), n

    def objective(p: F64) -> float:
        c, n = corr_at(float(p[0]) * 1e6, float(p[1]) if fit_drift else 0.0)
        # Maximise the correlation; the prior counts like one sample's worth of evidence.
        return -c + 0.5 * (float(p[1]) / drift_prior) ** 2 / max(n, 1)

    sol = minimize(
        objective,
        np.array([lag0 / 1e6, 0.0]),
        method="Nelder-Mead",
        options={
            "initial_simplex": np.array(
                [
                    [lag0 / 1e6, 0.0],
                    [lag0 / 1e6 + 1.0, 0.0],
                    [lag0 / 1e6, 10.0 if fit_drift else 0.0],
                ]
            ),
            "xatol": 1e-3,
            "fatol": 1e-7,
            "maxiter": 400,
        },
    )
    x = sol.x if fit_drift else np.array([sol.x[0], 0.0])
    if abs(x[0] * 1e6) > search_ns:
        x = np.array([lag0 / 1e6, 0.0])
    r_best, n_used = corr_at(float(x[0]) * 1e6, float(x[1]))
    # 1σ from the curvature of the correlation, (1 − r²)/n being its sampling variance.
    h_ms, h_ppm = 0.5, 5.0
    c0 = r_best
    cp = corr_at((x[0] + h_ms) * 1e6, float(x[1]))[0]
    cm = corr_at((x[0] - h_ms) * 1e6, float(x[1]))[0]
    curv = -(cp - 2.0 * c0 + cm) / h_ms**2
    var_r = max(1.0 - c0 * c0, 1e-6) / max(n_used, 1)
    off_sig = math.sqrt(var_r / curv) * 1e6 if curv > 0 else math.nan
    if fit_drift:
        dp = corr_at(x[0] * 1e6, float(x[1]) + h_ppm)[0]
        dm = corr_at(x[0] * 1e6, float(x[1]) - h_ppm)[0]
        curv_d = -(dp - 2.0 * c0 + dm) / h_ppm**2
        drift_sig = math.sqrt(var_r / curv_d) if curv_d > 0 else math.nan
    else:
        drift_sig = mapping.drift_sigma_ppm
    delta_ns = float(x[0]) * 1e6
    eps_ppm = float(x[1]) if fit_drift else 0.0
    # Old mapping re-anchored at the new anchor, plus the corrections.
    offset = mapping.offset_ns + mapping.drift_ppm * 1e-6 * (anchor - mapping.anchor_ns) + delta_ns
    _log.info(
        "%s refined by speed: %+.3f ms, %+.2f ppm (r = %.2f, %d samples)",
        mapping.device,
        delta_ns / 1e6,
        eps_ppm,
        r_best,
        n_used,
    )
    return ClockMapping(
        mapping.device,
        mapping.reference,
        round(offset),
        mapping.drift_ppm + eps_ppm,
        anchor,
        off_sig,
        drift_sig,
        (mapping.method or "clap") + "+xcorr",
    )


# ------------------------------------------------------------------------ reprojection


def _interp_positions(t_ref: F64, tv: F64, pos: F64) -> F64:
    """Vicon positions ``(F, N, 3)`` at times ``t_ref`` ``(M,)``: linear, NaN outside or in gaps."""
    idx = np.searchsorted(tv, t_ref) - 1
    inside = (idx >= 0) & (idx < tv.size - 1)
    i0 = np.clip(idx, 0, tv.size - 2)
    w = ((t_ref - tv[i0]) / (tv[i0 + 1] - tv[i0]))[:, None, None]
    out: F64 = pos[i0] * (1.0 - w) + pos[i0 + 1] * w
    out[~inside] = np.nan
    return out


def _project(p_world: F64, k: F64, t_world_cam: F64) -> F64:
    """Pinhole projection (no distortion: rectified D415) of world points ``(..., 3)``; NaN
    closer than :data:`_MIN_DEPTH_M` or behind the camera."""
    uv, _ = project_points(p_world, t_world_cam, k, None, min_depth_m=_MIN_DEPTH_M)
    return uv


def _pair_residuals(
    p: F64, mapped: F64, rel: F64, pos: F64, marker: I64, blob: F64, tv: F64, k: F64, tw: F64
) -> F64:
    """Image residuals ``(P, 2)`` (px) of marker–blob pairs under clock corrections ``p``
    (offset ms, drift ppm); ``pos`` ``(F, N, 3)`` the Vicon tracks, ``marker`` each pair's."""
    t = mapped + p[0] * 1e6 + p[1] * 1e-6 * rel
    idx = np.clip(np.searchsorted(tv, t) - 1, 0, tv.size - 2)
    w = ((t - tv[idx]) / (tv[idx + 1] - tv[idx]))[:, None]
    pw = pos[idx, marker] * (1.0 - w) + pos[idx + 1, marker] * w
    out: F64 = _project(pw, k, tw) - blob
    return out


def refine_by_reprojection(
    mapping: ClockMapping,
    frames: Sequence[MarkerFrame],
    traj: MarkerTrajectories,
    K: npt.ArrayLike,
    T_world_cam: npt.ArrayLike,
    *,
    labels: Sequence[str] | None = None,
    search_ns: int = 20_000_000,
    gate_px: float = 4.0,
    fit_drift: bool = True,
) -> ClockMapping:
    """Refine a D415's clock mapping by reprojecting the Vicon markers into its frames.

    With the camera registered (``K``, ``T_world_cam`` in the Vicon frame), the Vicon markers
    interpolated at a frame's mapped time must fall on the frame's blobs; a moving marker
    misses by its image velocity times the clock error. The blob centres are the D415's most
    precise measurement (≈ 0.1–0.3 px), so this pins the offset to a small fraction of a
    millisecond and, over a session, the drift to a few ppm — far better than the speed
    correlation, at the price of needing the extrinsics.

    Steps: a scan of offsets within ``±search_ns`` (1 ms grid) for the most projected markers
    landing within ``gate_px`` of a blob; marker ↔ blob pairs at the best offset (mutual nearest
    within ``gate_px``); a robust (soft-L1, 0.5 px) least-squares fit of the offset and drift
    corrections to the image residuals; pairs re-made at the solution and the fit repeated.

    Args:
        mapping: The camera's current mapping onto the Vicon clock (claps).
        frames: The camera's marker frames (device clock), e.g. every few frames of a session.
        traj: The Vicon trajectories (metres, Vicon clock via :func:`vicon_times_ns`).
        K: ``(3, 3)`` intrinsics (rectified D415: no distortion).
        T_world_cam: ``(4, 4)`` camera-to-world transform in the Vicon frame (registration).
        labels: Vicon markers to use (default: all).
        search_ns: Half-width of the offset scan around ``mapping`` (ns).
        gate_px: Pairing gate (px).
        fit_drift: Also refine the drift (needs a session of tens of seconds).

    Returns:
        The refined mapping (``method`` + ``"+reproj"``), anchored mid-way through the frames,
        with 1σ uncertainties from the fit.

    Raises:
        CalibrationError: too few frames or pairs (wrong extrinsics, no overlap in time), or
            too few moving markers to tell time.
    """
    k = np.asarray(K, dtype=np.float64)
    tw = np.asarray(T_world_cam, dtype=np.float64)
    if k.shape != (3, 3) or tw.shape != (4, 4):
        msg = (
            f"refine_by_reprojection: K must be 3×3 and T_world_cam 4×4, got {k.shape}, {tw.shape}"
        )
        raise ValidationError(msg)
    fr = [f for f in sorted(frames, key=lambda f: f.t_dev_ns) if f.n_markers]
    if len(fr) < 10:
        msg = f"cannot refine {mapping.device} by reprojection: {len(fr)} frames with markers"
        raise CalibrationError(msg)
    tr = traj if labels is None else traj.select(labels)
    tv_ns = vicon_times_ns(tr)
    base = int(tv_ns[0])  # keeps the float times small enough for sub-ns steps
    tv = (tv_ns - base).astype(np.float64)
    pos = np.asarray(tr.positions_m)
    td = np.array([f.t_dev_ns for f in fr], dtype=np.int64)
    anchor = int((int(td[0]) + int(td[-1])) // 2)
    mapped = (mapping.to_reference_ns(td) - base).astype(np.float64)
    rel = (td - anchor).astype(np.float64)
    trees = [cKDTree(f.uv_px) for f in fr]
    isolated = []
    for f, tree in zip(fr, trees, strict=True):
        if f.n_markers > 1:
            d2, _ = tree.query(f.uv_px, k=2)
            isolated.append(d2[:, 1] > 3.0 * gate_px)
        else:
            isolated.append(np.ones(f.n_markers, dtype=bool))
    n_mark = pos.shape[1]

    def projected(delta_ns: float, eps_ppm: float) -> F64:
        t = mapped + delta_ns + eps_ppm * 1e-6 * rel
        return _project(_interp_positions(t, tv, pos), k, tw)  # (M, N, 2)

    def hits(uv: F64) -> int:
        n = 0
        for i, tree in enumerate(trees):
            ok = np.isfinite(uv[i, :, 0])
            if ok.any():
                d, _ = tree.query(uv[i, ok], distance_upper_bound=gate_px)
                n += int(np.count_nonzero(np.isfinite(d)))
        return n

    # Offset scan per quarter of the frames (hits within half the gate on a 1 ms grid), so a
    # poor clap drift is corrected before pairing: a line through the quarters' best offsets.
    lags = np.arange(-float(search_ns), float(search_ns) + 1.0, 1e6)
    centres, offsets, weights = [], [], []
    best_hits = 0
    for part in np.array_split(np.arange(len(fr)), 4):
        if part.size == 0:
            continue
        part = part[:: max(1, part.size // 40)]
        scores = np.zeros(lags.size)
        for li, lag in enumerate(lags):
            uv = _project(_interp_positions(mapped[part] + lag, tv, pos), k, tw)
            n = 0
            for row, i in enumerate(part):
                ok = np.isfinite(uv[row, :, 0])
                if ok.any():
                    d, _ = trees[i].query(uv[row, ok], distance_upper_bound=0.5 * gate_px)
                    n += int(np.count_nonzero(np.isfinite(d)))
            scores[li] = n
        j = int(np.argmax(scores))
        best_hits = max(best_hits, int(scores[j]))
        # Hits are flat for still markers; only a clear peak says something.
        med = float(np.median(scores))
        if scores[j] >= 10 and scores[j] >= med + max(5.0, 2.0 * math.sqrt(med)):
            centres.append(float(np.mean(rel[part])))
            offsets.append(float(lags[j]))
            weights.append(float(scores[j]))
    if not offsets:
        msg = (
            f"cannot refine {mapping.device} by reprojection: at best {best_hits} Vicon markers "
            f"project within {0.5 * gate_px:.1f} px of a blob over ±{search_ns / 1e6:.0f} ms; "
            "wrong extrinsics, intrinsics or clock prior?"
        )
        raise CalibrationError(msg)
    if fit_drift and len(offsets) >= 3 and np.ptp(centres) > 5e9:
        slope, icpt = np.polyfit(np.array(centres), np.array(offsets), 1, w=np.sqrt(weights))
        start = np.array([icpt / 1e6, float(np.clip(slope * 1e6, -400.0, 400.0))])
    else:
        start = np.array([float(np.average(offsets, weights=weights)) / 1e6, 0.0])

    def pairs(delta_ns: float, eps_ppm: float) -> tuple[I64, I64, F64]:
        uv = projected(delta_ns, eps_ppm)
        fi, mi, blob, area = [], [], [], []
        for i, (f, tree) in enumerate(zip(fr, trees, strict=True)):
            ok = np.flatnonzero(np.isfinite(uv[i, :, 0]))
            if ok.size == 0:
                continue
            d, j = tree.query(uv[i, ok], distance_upper_bound=gate_px)
            hit = np.isfinite(d)
            if not hit.any():
                continue
            m_ok, b_ok = ok[hit], j[hit]
            # Mutual: each blob keeps its nearest projected marker only; and only isolated
            # blobs (two markers' blobs touching, or a marker half behind another, shift the
            # centroid).
            back = cKDTree(uv[i, m_ok]).query(f.uv_px[b_ok])[1]
            mutual = (back == np.arange(b_ok.size)) & isolated[i][b_ok]
            fi.append(np.full(int(mutual.sum()), i))
            mi.append(m_ok[mutual])
            blob.append(f.uv_px[b_ok[mutual]])
            area.append(f.area_px[b_ok[mutual]])
        if not fi:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2))
        fi_a, mi_a, blob_a = np.concatenate(fi), np.concatenate(mi), np.concatenate(blob)
        # A marker partly hidden (behind a limb, the board) has a small blob whose centroid is
        # off its centre: area × depth² is constant for whole markers, so keep those ≥ 0.85 ×
        # the median (depth from the Vicon marker at the pair's time).
        t = mapped[fi_a] + delta_ns + eps_ppm * 1e-6 * rel[fi_a]
        pw = _interp_positions(t, tv, pos)[np.arange(t.size), mi_a]
        z = (pw - tw[:3, 3]) @ tw[:3, 2]
        a_z2 = np.concatenate(area) * z * z
        whole = a_z2 >= 0.85 * float(np.nanmedian(a_z2))
        return fi_a[whole], mi_a[whole], blob_a[whole]

    drift_prior = mapping.drift_sigma_ppm
    if not (math.isfinite(drift_prior) and drift_prior > 0):
        drift_prior = 50.0
    x = start
    fi = mi = np.zeros(0, np.int64)
    blob = np.zeros((0, 2))
    sol = None
    for stage in range(3):
        fi, mi, blob = pairs(x[0] * 1e6, x[1])
        if stage == 2 and sol is not None:
            # 3σ rejection (robust σ of the image residuals at the solution), then an L2 refit.
            r_now = _pair_residuals(x, mapped[fi], rel[fi], pos, mi, blob, tv, k, tw)
            norm = np.hypot(r_now[:, 0], r_now[:, 1])
            sigma = max(1.4826 * float(np.median(norm)) / 1.1774, 0.05)
            keep = norm < 3.0 * sigma
            fi, mi, blob = fi[keep], mi[keep], blob[keep]
        if fi.size < 50:
            msg = (
                f"cannot refine {mapping.device} by reprojection: only {fi.size} marker–blob "
                f"pairs within {gate_px} px"
            )
            raise CalibrationError(msg)
        t_pair_rel = rel[fi]
        mapped_pair = mapped[fi]

        def residuals(
            p: F64,
            mapped_pair: F64 = mapped_pair,
            t_pair_rel: F64 = t_pair_rel,
            mi: I64 = mi,
            blob: F64 = blob,
        ) -> F64:
            res = _pair_residuals(p, mapped_pair, t_pair_rel, pos, mi, blob, tv, k, tw)
            return np.concatenate([np.nan_to_num(res).ravel(), [0.5 * p[1] / drift_prior]])

        lb = [-search_ns / 1e6 - 5.0, -500.0 if fit_drift else -1e-9]
        ub = [search_ns / 1e6 + 5.0, 500.0 if fit_drift else 1e-9]
        sol = least_squares(
            residuals,
            x,
            loss="soft_l1" if stage < 2 else "linear",
            f_scale=0.3,
            bounds=(lb, ub),
            x_scale=[0.1, 1.0],
            diff_step=[1e-4, 1e-2],
        )
        x = sol.x
    assert sol is not None
    res = sol.fun[:-1]
    s2 = float(np.sum(res**2) / max(res.size - 2, 1))
    jac = sol.jac
    cov = np.linalg.pinv(jac.T @ jac) * s2
    if not math.sqrt(max(cov[0, 0], 0.0)) < 2.0:  # ms
        msg = (
            f"cannot refine {mapping.device} by reprojection: the paired markers barely move "
            f"(offset σ {math.sqrt(max(cov[0, 0], 0.0)):.1f} ms), so their positions do not tell "
            "time; use frames with motion"
        )
        raise CalibrationError(msg)
    delta_ns = float(x[0]) * 1e6
    eps_ppm = float(x[1]) if fit_drift else 0.0
    offset = mapping.offset_ns + mapping.drift_ppm * 1e-6 * (anchor - mapping.anchor_ns) + delta_ns
    _log.info(
        "%s refined by reprojection: %+.3f ms, %+.2f ppm (%d pairs in %d frames, %d markers)",
        mapping.device,
        delta_ns / 1e6,
        eps_ppm,
        fi.size,
        len(fr),
        n_mark,
    )
    return ClockMapping(
        mapping.device,
        mapping.reference,
        round(offset),
        mapping.drift_ppm + eps_ppm,
        anchor,
        float(math.sqrt(max(cov[0, 0], 0.0)) * 1e6),
        float(math.sqrt(max(cov[1, 1], 0.0))) if fit_drift else mapping.drift_sigma_ppm,
        (mapping.method or "clap") + "+reproj",
    )


# ----------------------------------------------------------------------------- pulses


def clock_from_pulses(
    device: str,
    trigger_t_ns: npt.ArrayLike,
    frame_t_ns: npt.ArrayLike,
    *,
    d415_mapping: ClockMapping,
    frame_delay_ns: int = 0,
    prior_offset_ns: int | None = None,
) -> ClockMapping:
    """The DAVIS clock mapped onto the reference through the D415 master's frame pulses.

    Each rising edge of the DAVIS's external input (DAVIS clock) is the start of a D415 master
    exposure; the master stamps that frame ``frame_delay_ns`` later (its sensor timestamp is
    mid-exposure: pass ``exposure_us·500``). Edges and frames are paired (drops on either
    side are tolerated: a pair must agree within a quarter period), a line DAVIS → D415 is
    fitted with 3σ rejection, and composed with ``d415_mapping`` (D415 → reference).

    Args:
        device: The DAVIS label, e.g. ``"davis/02460013"``.
        trigger_t_ns: Rising-edge times (DAVIS clock, ns), increasing.
        frame_t_ns: The master's frame times (its clock, ns), increasing.
        d415_mapping: The master's mapping onto the reference.
        frame_delay_ns: Frame stamp minus its pulse (D415 clock ns).
        prior_offset_ns: Rough D415 minus DAVIS clock reading (ns) at a pulse, known to better
            than a quarter period (from claps or log times). Required: a periodic train pairs
            equally well at every whole-period shift; None is refused with that explanation.

    Raises:
        CalibrationError: too few pulses or frames, ambiguous pairing, or a poor line.
    """
    tt = np.asarray(trigger_t_ns, dtype=np.int64)
    ft = np.asarray(frame_t_ns, dtype=np.int64) - int(frame_delay_ns)
    if tt.ndim != 1 or ft.ndim != 1 or np.any(np.diff(tt) <= 0) or np.any(np.diff(ft) <= 0):
        msg = "clock_from_pulses: trigger and frame times must be 1-D and increasing (ns)"
        raise ValidationError(msg)
    if tt.size < 10 or ft.size < 10:
        msg = (
            f"cannot map {device} by pulses: {tt.size} trigger edges and {ft.size} frames; "
            "need at least 10 of each (is the D415 master's sync output wired to the DAVIS?)"
        )
        raise CalibrationError(msg)
    period = float(np.median(np.diff(ft)))
    p_trig = float(np.median(np.diff(tt)))
    if abs(p_trig / period - 1.0) > 0.01:
        msg = (
            f"cannot map {device} by pulses: trigger edges come every {p_trig / 1e6:.3f} ms but "
            f"frames every {period / 1e6:.3f} ms; the trigger is not the frame pulse (or edges "
            "are mixed: use rising edges only)"
        )
        raise CalibrationError(msg)
    tree = cKDTree(ft.astype(np.float64)[:, None])

    def pair(offset: float) -> tuple[I64, I64]:
        d, j = tree.query((tt + offset).astype(np.float64)[:, None])
        ok = d < 0.25 * period
        return np.flatnonzero(ok), j[ok]

    if prior_offset_ns is None:
        # A pulse train is periodic: shifting the pairing by whole periods pairs as many edges
        # (drops do not tell the shifts apart either), so the right one needs a prior.
        msg = (
            f"cannot map {device} by pulses: pairing {tt.size} edges with {ft.size} frames is "
            f"ambiguous by whole periods ({period / 1e6:.2f} ms); pass prior_offset_ns (D415 "
            "minus DAVIS clock, to better than a quarter period), e.g. from the DAVIS and D415 "
            "claps or the recording's log times"
        )
        raise CalibrationError(msg)
    offset0 = float(prior_offset_ns)
    i, j = pair(offset0)
    if i.size < 10:
        msg = (
            f"cannot map {device} by pulses: only {i.size} of {tt.size} edges pair with a frame "
            f"within ±{0.25 * period / 1e6:.1f} ms of the prior offset"
        )
        raise CalibrationError(msg)
    x_anchor = int(tt[i[i.size // 2]])
    x = (tt[i] - x_anchor).astype(np.float64)
    y = (ft[j] - tt[i]).astype(np.float64)  # D415 minus DAVIS
    keep = np.ones(x.size, dtype=bool)
    coef = np.zeros(2)
    for _ in range(3):
        coef = np.polyfit(x[keep], y[keep], 1)
        res = y - np.polyval(coef, x)
        sd = float(np.std(res[keep])) or 1.0
        new = np.abs(res) <= max(3.0 * sd, 2000.0)
        if np.array_equal(new, keep):
            break
        keep = new
    n = int(np.count_nonzero(keep))
    res = (y - np.polyval(coef, x))[keep]
    rms = float(np.sqrt(np.mean(res**2)))
    if rms > 0.05 * period:
        msg = (
            f"cannot map {device} by pulses: the DAVIS ↔ D415 line leaves {rms / 1e3:.0f} µs "
            "rms; pulses and frames are not the same train"
        )
        raise CalibrationError(msg)
    slope_ppm = float(coef[0]) * 1e6  # D415 = DAVIS·(1 + slope) + c
    off_dd = float(coef[1])  # D415 − DAVIS at the anchor
    sx = float(np.std(x[keep])) or 1.0
    sig_off_dd = rms / math.sqrt(n)
    sig_slope_ppm = rms / (sx * math.sqrt(n)) * 1e6
    # Compose: t_ref = M(t_davis + off_dd + slope·(t_davis − anchor)).
    t_d415_anchor = x_anchor + round(off_dd)
    t_ref_anchor = int(d415_mapping.to_reference_ns(np.array([t_d415_anchor]))[0])
    drift = ((1.0 + slope_ppm * 1e-6) * (1.0 + d415_mapping.drift_ppm * 1e-6) - 1.0) * 1e6
    off_sig = math.hypot(sig_off_dd, d415_mapping.offset_sigma_ns)
    drift_sig = math.hypot(sig_slope_ppm, d415_mapping.drift_sigma_ppm)
    _log.info(
        "%s by pulses: %d pairs of %d edges, %.1f µs rms, %+.2f ppm vs the D415",
        device,
        n,
        tt.size,
        rms / 1e3,
        slope_ppm,
    )
    return ClockMapping(
        device,
        d415_mapping.reference,
        t_ref_anchor - x_anchor,
        drift,
        x_anchor,
        off_sig,
        drift_sig,
        "pulses",
    )


# ----------------------------------------------------------------------------- sync channel

#: Hysteresis of the edge detector, as a fraction of the step between the two levels.
_SYNC_HYSTERESIS: Final = 0.25
#: Samples after a crossing whose distance to the final level (fraction of the step) lies in
#: this range measure the edge's time constant and switching instant.
_SYNC_RC_RANGE: Final = (0.03, 0.6)


@dataclass(frozen=True, slots=True, eq=False)
class SyncEdges:
    """Edges of a sync channel (a two-level signal; each edge one event), on the Vicon clock.

    Attributes:
        channel: The channel's label (for messages).
        t_ns: ``(E,)`` switching instants (ns, float): the mid-level crossings moved back by the
            edge's measured delay (first-order model), or the crossings themselves (``edge_model
            = "none"``, or an edge too steep for the sampling to resolve).
        crossing_ns: ``(E,)`` mid-level crossings, linearly interpolated between samples (ns).
        rising: ``(E,)`` True for low → high edges.
        low: The low level (median of the low plateau samples), channel units.
        high: The high level, channel units.
        noise: Robust noise of the samples (channel units).
        tau_ns: The edges' first-order time constant (ns), NaN when not measured.
    """

    channel: str
    t_ns: F64 = field(repr=False)
    crossing_ns: F64 = field(repr=False)
    rising: npt.NDArray[np.bool_] = field(repr=False)
    low: float
    high: float
    noise: float
    tau_ns: float

    @property
    def count(self) -> int:
        """Number of edges."""
        return int(self.t_ns.shape[0])


def find_sync_edges(
    t_ns: npt.ArrayLike,
    values: npt.ArrayLike,
    *,
    channel: str = "sync",
    edge_model: str = "rc",
) -> SyncEdges:
    """The edges of a two-level sync signal sampled at ``t_ns``.

    The levels are the medians of the samples beyond ±25 % of the step about the mid-level
    (hysteresis, so noise near mid-level makes no extra edges). Each edge's mid-level crossing is
    interpolated linearly between the two samples around it. With ``edge_model="rc"`` the edge is
    taken as first-order (an RC low-pass at the input, docs/wiring.md §7): the samples after the
    crossing approach the final level as ``d = exp(−(t − t0)/τ)`` (``d`` = distance to the final
    level over the step); τ is the median over all edges of ``Δt / ln(d_k/d_k+1)`` of successive
    samples, and each edge's switching instant ``t0`` the weighted mean (weights ``d²``) of
    ``t_k + τ·ln d_k`` over its samples with ``d`` in [0.03, 0.6]. That is exact for a first-order
    edge whatever the sampling phase, whereas the crossing lags the switch by ``τ·ln 2`` plus a
    phase-dependent interpolation error. An edge with no sample in that range (τ much shorter
    than the sampling period) keeps its crossing.

    Args:
        t_ns: ``(S,)`` sample times (ns, increasing), e.g. Vicon-clock times of analog samples.
        values: ``(S,)`` samples (any unit).
        channel: The channel's label, for messages.
        edge_model: ``"rc"`` (default) or ``"none"`` (switching instant = crossing).

    Raises:
        ValidationError: bad shapes, non-increasing times or an unknown edge model.
        CalibrationError: no edges (a flat or noise-only channel), naming the channel and what
            its samples span.
    """
    t = np.asarray(t_ns, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    if t.ndim != 1 or v.shape != t.shape or t.size < 3:
        msg = f"find_sync_edges: t_ns and values must be 1-D of equal length ≥ 3, got {t.shape}"
        raise ValidationError(msg)
    if edge_model not in ("rc", "none"):
        msg = f"edge_model must be 'rc' or 'none', got {edge_model!r}"
        raise ValidationError(msg)
    if np.any(np.diff(t) <= 0) or not np.all(np.isfinite(t)):
        msg = "find_sync_edges: sample times must be finite and increasing"
        raise ValidationError(msg)
    finite = np.isfinite(v)
    if not finite.all():
        v = np.interp(t, t[finite], v[finite]) if finite.any() else np.zeros_like(v)
    noise = 1.4826 * float(np.median(np.abs(np.diff(v)))) / math.sqrt(2.0)
    lo_p, hi_p = (float(x) for x in np.percentile(v, [5.0, 95.0]))
    span_s = (t[-1] - t[0]) * 1e-9
    if not hi_p - lo_p > max(20.0 * noise, 1e-12):
        msg = (
            f"sync channel {channel!r}: no edges: its {v.size} samples over {span_s:.1f} s stay "
            f"within {hi_p - lo_p:.3g} (5–95 %: {lo_p:.3g} to {hi_p:.3g}; noise {noise:.2g}); is "
            "the sync box's toggle output wired to this input, and the rig streaming?"
        )
        raise CalibrationError(msg)
    mid = 0.5 * (lo_p + hi_p)
    h = _SYNC_HYSTERESIS * (hi_p - lo_p)
    state = np.where(v > mid + h, 1, np.where(v < mid - h, -1, 0))
    known = np.flatnonzero(state != 0)
    filled = state[known[np.maximum(np.searchsorted(known, np.arange(v.size), "right") - 1, 0)]]
    low = float(np.median(v[state == -1])) if (state == -1).any() else lo_p
    high = float(np.median(v[state == 1])) if (state == 1).any() else hi_p
    mid = 0.5 * (low + high)
    step = high - low
    change = np.flatnonzero(np.diff(filled) != 0) + 1
    change = change[change > known[0]] if known.size else change[:0]
    crossings: list[float] = []
    rising: list[bool] = []
    after: list[tuple[F64, F64]] = []  # (times, d) of the samples after each crossing
    for j in change:
        up = bool(filled[j] > 0)
        k = j - 1
        while k > 0 and (v[k] >= mid if up else v[k] <= mid):
            k -= 1
        if (v[k] >= mid) if up else (v[k] <= mid):
            continue  # no sample on the old side (signal starts mid-edge)
        frac = (mid - v[k]) / (v[k + 1] - v[k])
        crossings.append(float(t[k] + frac * (t[k + 1] - t[k])))
        rising.append(up)
        m = np.arange(k + 1, min(k + 12, v.size))
        d = ((high - v[m]) if up else (v[m] - low)) / step
        after.append((t[m], d))
    if not crossings:
        msg = (
            f"sync channel {channel!r}: no edges: the signal spans {lo_p:.3g} to {hi_p:.3g} but "
            "never crosses its mid-level from one plateau to the other"
        )
        raise CalibrationError(msg)
    cross = np.array(crossings)
    times = cross.copy()
    tau = math.nan
    if edge_model == "rc":
        lo_d, hi_d = _SYNC_RC_RANGE
        taus = []
        for tm, d in after:
            for a in range(len(d) - 1):
                if hi_d >= d[a] > d[a + 1] >= lo_d:
                    taus.append((tm[a + 1] - tm[a]) / math.log(d[a] / d[a + 1]))
        if len(taus) >= 3:
            tau = float(np.median(taus))
            for e, (tm, d) in enumerate(after):
                ok = (d >= lo_d) & (d <= hi_d)
                if ok.any():
                    w = d[ok] ** 2
                    times[e] = float(np.sum(w * (tm[ok] + tau * np.log(d[ok]))) / np.sum(w))
    _log.info(
        "sync channel %s: %d edges, levels %.3g / %.3g, noise %.2g, τ %s",
        channel,
        cross.size,
        low,
        high,
        noise,
        "n/a" if math.isnan(tau) else f"{tau / 1e3:.0f} µs",
    )
    return SyncEdges(
        channel=channel,
        t_ns=times,
        crossing_ns=cross,
        rising=np.array(rising, dtype=bool),
        low=low,
        high=high,
        noise=noise,
        tau_ns=tau,
    )


def clock_from_sync_edges(
    device: str,
    edges: SyncEdges,
    frame_t_ns: npt.ArrayLike,
    *,
    prior: ClockMapping,
    frame_delay_ns: int = 0,
    edge_delay_ns: int = 0,
    min_pairs: int = 20,
) -> ClockMapping:
    """A device → Vicon clock line through sync-channel edges paired with the device's frames.

    Each edge marks one frame's pulse: the frame's stamp minus ``frame_delay_ns`` (a D415 master
    stamps mid-exposure and pulses at the exposure start: ``exposure_us·500``) is the pulse on
    the device clock, the edge minus ``edge_delay_ns`` (the wiring's fixed latency, e.g. the sync
    box's interrupt) the pulse on the Vicon clock. Frames are paired with the edge nearest to
    their ``prior`` mapping (within a quarter period, so the prior must be good to a few ms:
    the video clock is; no assumption on which edge is the first frame), then a line is fitted
    with 3σ rejection and the pairing redone through it. Frames dropped by the recorder and edges
    outside the recording are simply unpaired.

    Args:
        device: The device label, e.g. ``"d415/819612070593"``.
        edges: :func:`find_sync_edges` of the channel (Vicon clock).
        frame_t_ns: The device's frame stamps (its clock, ns).
        prior: A mapping device → Vicon good to better than a quarter frame period.
        frame_delay_ns: Frame stamp minus its pulse (device ns).
        edge_delay_ns: Edge minus its pulse (Vicon ns).
        min_pairs: Fewest edge–frame pairs accepted.

    Returns:
        The mapping (``method = "sync channel <label>"``), σ from the line's residuals.

    Raises:
        CalibrationError: too few edges or frames, an edge period that is not the frame
            period, too few pairs, or a line with large residuals; the message names the
            channel and what was seen.
    """
    ch = edges.channel
    ft = np.unique(np.asarray(frame_t_ns, dtype=np.int64)) - int(frame_delay_ns)
    et = np.sort(np.asarray(edges.t_ns, dtype=np.float64)) - float(edge_delay_ns)
    if et.size < min_pairs or ft.size < min_pairs:
        msg = (
            f"sync channel {ch!r}: {et.size} edges and {ft.size} {device} frames; need "
            f"{min_pairs} of each to fit its clock"
        )
        raise CalibrationError(msg)
    period = float(np.median(np.diff(ft)))
    p_edge = float(np.median(np.diff(et)))
    if abs(p_edge / period - 1.0) > 0.02:
        msg = (
            f"sync channel {ch!r}: edges come every {p_edge / 1e6:.3f} ms (median) but {device} "
            f"frames every {period / 1e6:.3f} ms; the channel does not carry one edge per frame "
            "pulse (a stretched pulse gives two edges per frame: use the toggle output, "
            "docs/wiring.md §7)"
        )
        raise CalibrationError(msg)

    def pair(mapping: ClockMapping) -> tuple[I64, I64]:
        q = mapping.to_reference_ns(ft).astype(np.float64)
        k = np.clip(np.searchsorted(et, q), 1, et.size - 1)
        k = np.where(np.abs(et[k - 1] - q) < np.abs(et[k] - q), k - 1, k)
        ok = np.abs(et[k] - q) < 0.25 * period
        i, j = np.flatnonzero(ok), k[ok]
        _, first = np.unique(j, return_index=True)  # an edge pairs with one frame at most
        return i[first], j[first]

    mapping = prior
    rms = math.nan
    n_fit = 0
    sd_x = 1.0
    for _ in range(3):  # pair through the prior, then twice through the fitted line
        i, j = pair(mapping)
        if i.size < min_pairs:
            through = f"prior clock ({prior.method or 'prior'})"
            if mapping is not prior:
                through = "fitted line"
            msg = (
                f"sync channel {ch!r}: only {i.size} of {ft.size} {device} frames pair with "
                f"one of its {et.size} edges within ±{0.25 * period / 1e6:.1f} ms of the "
                f"{through}; need {min_pairs} (is the prior good to a few ms, and is this the "
                "master's pulse train?)"
            )
            raise CalibrationError(msg)
        anchor = int(ft[i[i.size // 2]])
        x = (ft[i] - anchor).astype(np.float64) * 1e-9  # s
        y_full = et[j] - ft[i].astype(np.float64)  # Vicon minus device (ns)
        y0 = float(np.median(y_full))
        y = y_full - y0
        keep = np.ones(x.size, dtype=bool)
        coef = np.zeros(2)
        for _ in range(5):
            coef = np.polyfit(x[keep], y[keep], 1)
            res = y - np.polyval(coef, x)
            sd = float(np.std(res[keep]))
            new = np.abs(res) <= max(3.0 * sd, 1000.0)
            if np.array_equal(new, keep) or int(new.sum()) < min_pairs:
                break
            keep = new
        res = (y - np.polyval(coef, x))[keep]
        rms = float(np.sqrt(np.mean(res**2)))
        n_fit = int(keep.sum())
        sd_x = float(np.std(x[keep])) or 1.0
        mapping = ClockMapping(
            device,
            prior.reference,
            round(y0 + float(coef[1])),
            float(coef[0]) * 1e-3,  # ns per s → ppm
            anchor,
            rms / math.sqrt(n_fit),
            rms / (sd_x * math.sqrt(n_fit)) * 1e-3,
            f"sync channel {ch}",
        )
    if rms > 0.05 * period:
        msg = (
            f"sync channel {ch!r}: the {device} ↔ Vicon line through {n_fit} edge–frame pairs "
            f"leaves {rms / 1e3:.0f} µs RMS (> 5 % of the {period / 1e6:.1f} ms period); the "
            "edges are not this device's frame pulses"
        )
        raise CalibrationError(msg)
    _log.info(
        "%s by sync channel %s: %d pairs (%d edges, %d frames), %.2f µs RMS, drift %+.3f ± %.3f "
        "ppm",
        device,
        ch,
        n_fit,
        et.size,
        ft.size,
        rms / 1e3,
        mapping.drift_ppm,
        mapping.drift_sigma_ppm,
    )
    return mapping
