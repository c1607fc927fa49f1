"""The Vicon sync channel: its edges, and a device's clock through them.

The sync box's toggle output (one edge per D415 master pulse, docs/wiring.md §7) is recorded on
a Vicon analog input, i.e. sampled on the Vicon clock. Edges (:func:`find_sync_edges`):
mid-level crossings interpolated linearly between samples; a filtered (RC) edge crosses
mid-level a delay after it switched, which is measured from the samples after each crossing (the
decay towards the final level gives the time constant τ; each edge's switching instant is then
exact for a first-order edge). Edges are paired with the master's frames through a prior mapping
good to a quarter period (the video clock), and a line device → Vicon is fitted
(:func:`clock_from_sync_edges`): µs-level offset and sub-ppm drift.

A real input need not be a pure RC: an anti-alias filter after it delays the edge by its group
delay (≈ 45–450 µs for a 2-pole filter at 5–0.5 kHz) and rounds its start, which a first-order
fit reads as a later switch. ``edge_model="fit"`` (what the calibration uses) takes the shape from
the edges themselves: the RC followed by a 2-pole Butterworth low-pass, its two time constants
fitted to every edge at once (the edges fall at all sampling phases, so together they sample
the curve densely), the low-pass dropped when it does not lower the residuals; then each edge's
switch is fitted with that shape. A pure delay (the sync box's latency) has no shape: no model
can see it.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final

import numpy as np
import numpy.typing as npt

from mocaprig.calib.calibration import ClockMapping
from mocaprig.errors import CalibrationError, ValidationError

__all__ = ["SyncEdges", "clock_from_sync_edges", "find_sync_edges"]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

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
        lowpass_ns: Time constant ``1/(2π f_c)`` of the 2-pole low-pass fitted after the RC
            (ns); 0 when the edges are first-order (or with ``edge_model`` ``"rc"``/``"none"``).
    """

    channel: str
    t_ns: F64 = field(repr=False)
    crossing_ns: F64 = field(repr=False)
    rising: npt.NDArray[np.bool_] = field(repr=False)
    low: float
    high: float
    noise: float
    tau_ns: float
    lowpass_ns: float = 0.0

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
        edge_model: ``"rc"`` (default: first-order), ``"fit"`` (an RC and a 2-pole low-pass,
            shape fitted to the edges, module doc) or ``"none"`` (switching instant =
            crossing).

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
    if edge_model not in ("rc", "fit", "none"):
        msg = f"edge_model must be 'rc', 'fit' or 'none', got {edge_model!r}"
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
    shape: list[tuple[F64, F64]] = []  # (times, progress 0 → 1) around each crossing
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
        w = np.arange(max(k - 4, 0), min(k + 14, v.size))
        shape.append((t[w], ((v[w] - low) if up else (high - v[w])) / step))
    if not crossings:
        msg = (
            f"sync channel {channel!r}: no edges: the signal spans {lo_p:.3g} to {hi_p:.3g} but "
            "never crosses its mid-level from one plateau to the other"
        )
        raise CalibrationError(msg)
    cross = np.array(crossings)
    times = cross.copy()
    tau = math.nan
    lowpass = 0.0
    if edge_model in ("rc", "fit"):
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
    if edge_model == "fit" and len(shape) >= 10:
        times, tau, lowpass = _fit_edge_shape(shape, times, tau, noise / step)
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
        lowpass_ns=lowpass,
    )


def _step_response(tau_us: float, u_us: float) -> Callable[[F64], tuple[F64, F64]]:
    """Unit step response of an RC (τ) followed by a 2-pole Butterworth of time constant ``u``
    (``u`` = 0: none), and its derivative, as a function of the time since the step (µs; 0
    before it)."""
    if u_us <= 0:

        def rc(t: F64) -> tuple[F64, F64]:
            pos = t > 0
            e = np.exp(-np.where(pos, t, 0.0) / tau_us)
            return np.where(pos, 1.0 - e, 0.0), np.where(pos, e / tau_us, 0.0)

        return rc
    from scipy.signal import residue

    wc = 1.0 / u_us
    den = np.polymul(np.polymul([tau_us, 1.0], [1.0, math.sqrt(2.0) * wc, wc * wc]), [1.0, 0.0])
    r, p, _ = residue([wc * wc], den)  # H(s)/s = Σ r_k / (s − p_k): h(t) = Σ r_k exp(p_k t)

    def filtered(t: F64) -> tuple[F64, F64]:
        pos = t > 0
        ex = np.exp(np.multiply.outer(np.where(pos, t, 0.0), p))
        return np.where(pos, np.real(ex @ r), 0.0), np.where(pos, np.real(ex @ (r * p)), 0.0)

    return filtered


def _fit_edge_shape(
    shape: list[tuple[F64, F64]], times: F64, tau_ns: float, noise: float
) -> tuple[F64, float, float]:
    """The edge shape fitted to the edges (module doc): ``(switch times ns, τ ns, low-pass ns)``.

    For a shape (τ, low-pass u) each edge's switch is found by Gauss–Newton; the shape's cost
    is the sum of squared residuals of up to 80 edges spread over the channel with their best
    switches (a profile over the switches). τ alone is fitted first (first-order), then τ and u
    (Nelder–Mead on their logs, from short and long starts); u is kept only when it lowers the
    cost clearly beyond the noise. Then every edge's switch is fitted with the shape. ``times``
    are the first-order switches, or the crossings when ``tau_ns`` is NaN (edges too fast for
    the first-order estimate)."""
    from scipy.optimize import minimize, minimize_scalar

    # Padded (edges, samples) arrays in µs relative to each edge's starting estimate.
    width = max(len(tm) for tm, _ in shape)
    tt = np.zeros((len(shape), width))
    gg = np.zeros((len(shape), width))
    ok = np.zeros((len(shape), width), dtype=bool)
    for e, ((tm, g), t0) in enumerate(zip(shape, times, strict=True)):
        tt[e, : len(tm)] = (tm - t0) * 1e-3
        gg[e, : len(g)] = g
        ok[e, : len(g)] = True
    pick = np.unique(np.linspace(0, len(shape) - 1, min(80, len(shape))).round().astype(int))
    sigma = max(noise, 1e-4)
    first_order = math.isfinite(tau_ns)
    tau0_us = tau_ns * 1e-3 if first_order else 300.0
    # A first-order edge crosses mid-level τ·ln 2 after its switch.
    start = 0.0 if first_order else -tau0_us * math.log(2.0)

    def switches(tau_us: float, u_us: float, rows: npt.NDArray[np.intp]) -> tuple[F64, float]:
        """Each edge's best switch (µs, relative) under the shape, and the shape's cost."""
        h = _step_response(tau_us, u_us)
        t, g, m = tt[rows], gg[rows], ok[rows]
        shifts = np.full(rows.size, start - math.sqrt(2.0) * u_us)
        for _ in range(30):
            model, slope = h(t - shifts[:, None])
            slope = np.where(m, slope, 0.0)
            num = np.sum(slope * np.where(m, g - model, 0.0), axis=1)
            den = np.sum(slope * slope, axis=1)
            step = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
            shifts -= np.clip(step, -0.5 * tau_us, 0.5 * tau_us)
            if float(np.max(np.abs(step))) < 1e-3:
                break
        model, _ = h(t - shifts[:, None])
        cost = float(np.sum(np.where(m, (g - model) / sigma, 0.0) ** 2))
        return shifts, cost

    def cost(x: F64) -> float:
        return switches(math.exp(x[0]), math.exp(x[1]) if x.size > 1 else 0.0, pick)[1]

    lo, hi = math.log(0.2 * tau0_us), math.log(5.0 * tau0_us)
    rc = minimize_scalar(
        lambda x: cost(np.array([x])), bounds=(lo, hi), method="bounded",
        options={"xatol": 1e-4},
    )  # fmt: skip
    best_cost, tau_us, u_us = float(rc.fun), math.exp(float(rc.x)), 0.0
    for u0 in (0.05, 0.3, 1.5):  # short to long low-pass starts, as fractions of τ
        x0 = np.array([math.log(tau_us), math.log(max(u0 * tau_us, 1.0))])
        lp = minimize(
            cost, x0, method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 0.1, "maxfev": 150}
        )
        # Keep the low-pass only when it explains clearly more than the noise.
        if float(lp.fun) < best_cost - 10.0 and math.exp(float(lp.x[1])) >= 0.5:
            best_cost, tau_us, u_us = float(lp.fun), math.exp(lp.x[0]), math.exp(lp.x[1])
    shifts, _ = switches(tau_us, u_us, np.arange(len(shape)))
    return times + shifts * 1e3, tau_us * 1e3, u_us * 1e3


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
