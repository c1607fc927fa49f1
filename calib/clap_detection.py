"""Claps seen by the Vicon and the DAVIS: the clap instant is the clapperboard's contact instant.

The clapperboard's two markers sit at their contact distance most of the time; a clap opens them
(hundreds of mm), holds, and closes them back to contact (calibration-vicon.md §3.1).

* Vicon (:func:`find_claps_vicon`, 100–120 Hz): the distance of the two labelled clapper
  markers; the contact time is where a quadratic fitted to the last pre-contact samples of the
  closing reaches the contact distance (sub-frame; ≈ 0.2 ms).
* DAVIS (:func:`find_claps_davis`): the clapper's arm sweeps a burst of events that stops dead at
  contact; the contact is the sharpest fall of the event rate of the busiest image cell, located
  to the event-rate bin.

The D415's unlabelled markers need tracking and a fit of the closing trajectory:
:mod:`mocaprig.calib.clap_detection_d415`. Both use :class:`ClapDetection` (one clap seen by one
device) and :func:`clap_episodes` (the open → closed transitions of a distance signal).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Final

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.events import check_events
from mocaprig.calib.vicon import MarkerTrajectories
from mocaprig.calib.vicon_times import vicon_times_ns
from mocaprig.errors import CalibrationError, ValidationError

__all__ = [
    "CLAP_OPEN_MIN_M",
    "VICON_CLAPPER_LABELS",
    "ClapDetection",
    "ClapEpisode",
    "clap_episodes",
    "find_claps_davis",
    "find_claps_vicon",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: Labels the simulated Vicon (and a typical clapper subject) gives the clapperboard markers:
#: the moving arm's marker first.
VICON_CLAPPER_LABELS: Final = ("clapper:TOP", "clapper:BOTTOM")

#: A clap must open the markers at least this far beyond their contact distance (m).
CLAP_OPEN_MIN_M: Final = 0.05
#: Plausible marker-centre distances of a closed clapper (m).
_CONTACT_RANGE_M: Final = (0.005, 0.15)


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


@dataclass(frozen=True, slots=True)
class ClapEpisode:
    """One open → closed transition of a distance signal (sample indices)."""

    i_open: int  # last sample clearly open before the closing
    i_closed: int  # first sample back at contact level


def clap_episodes(
    d: F64,
    closed_level: float,
    closed_tol: float,
    open_min: float,
    min_closed: int,
    *,
    closed_mask: npt.NDArray[np.bool_] | None = None,
    min_open: int = 1,
) -> list[ClapEpisode]:
    """Open → closed transitions of a distance signal (NaN = unknown).

    An episode needs ``min_open`` open samples since the last closed one, and ``min_closed``
    closed samples (80 % of those seen) from its first closed sample on.
    """
    ok = np.isfinite(d)
    is_open = ok & (d >= closed_level + open_min)
    is_closed = ok & (d <= closed_level + closed_tol)
    if closed_mask is not None:
        is_closed &= closed_mask
    out: list[ClapEpisode] = []
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
                out.append(ClapEpisode(last_open, i))
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
    open_min_m: float = CLAP_OPEN_MIN_M,
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
    eps = clap_episodes(d, level, tol, open_min_m, min_closed)
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
