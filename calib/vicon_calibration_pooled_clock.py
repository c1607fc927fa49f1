"""One Vicon clock for the hardware-synchronised D415s.

Slaves capture on the master's pulses, so a slave's frame and the pivot camera's frame of the
same counter (up to a fixed shift) are the same instant: :func:`tie_by_counters` fits the line
between their device times (a :class:`Tie`), :func:`through_tie` maps a camera through its tie
and the pivot's mapping, and :func:`pooled_clocks` fits one robust line through every tied
camera's stretch offsets, plus a constant per camera (a slave's trigger delay).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Final

import numpy as np
import numpy.typing as npt

from mocaprig.calib.calibration import ClockMapping
from mocaprig.calib.vicon_calibration_video_clock import (
    STRETCH_REJECT_SIGMA,
    line_clock,
    stretch_weights,
)

__all__ = ["Tie", "pooled_clocks", "through_tie", "tie_by_counters"]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]


#: Largest RMS (ns) of a camera's frame times about a line through the pivot camera's frame
#: times for the two to count as hardware-synchronised (the D415's sync jitter is µs-level;
#: a free-running slave slides through a whole frame period).
_SYNC_RMS_NS: Final = 100_000


@dataclass(frozen=True, slots=True)
class Tie:
    """Camera c's device time on the pivot's: ``t_p = t_c + a_ns + s·(t_c − centre_ns)``."""

    a_ns: float
    s: float
    centre_ns: float
    pairs: int
    rms_ns: float
    counter_shift: int


def tie_by_counters(t_c: I64, n_c: I64, t_p: I64, n_p: I64, shift: int) -> Tie | None:
    """The line through the frames with ``counter_c − counter_p == shift`` (ns), or None
    without 10 such pairs over ≥ 5 s or with an RMS above :data:`_SYNC_RMS_NS`."""
    idx = {int(n): k for k, n in enumerate(n_p)}
    kc, kp = [], []
    for k, n in enumerate(n_c):
        m = idx.get(int(n) - shift)
        if m is not None:
            kc.append(k)
            kp.append(m)
    if len(kc) < 10:
        return None
    x = t_c[kc].astype(np.float64)
    if np.ptp(x) < 5e9:
        return None
    centre = float(np.mean(x))
    y = (t_p[kp] - t_c[kc]).astype(np.float64)
    A = np.stack([np.ones_like(x), (x - centre) * 1e-9], axis=1)
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    rms = float(np.sqrt(np.mean((y - A @ coef) ** 2)))
    if rms > _SYNC_RMS_NS:
        return None
    return Tie(float(coef[0]), float(coef[1]) * 1e-9, centre, len(kc), rms, shift)


def through_tie(
    name: str, tie: Tie, pivot_map: ClockMapping, *, delay_ns: float = 0.0, method: str
) -> ClockMapping:
    """Camera ``name``'s mapping: its time → the pivot's (``tie``) → Vicon (``pivot_map``),
    plus ``delay_ns`` (the camera's own constant, e.g. a slave's trigger delay)."""
    a, s, centre = tie.a_ns, tie.s, tie.centre_ns
    dp = pivot_map.drift_ppm * 1e-6
    # Anchored where the camera's time maps onto the pivot map's anchor.
    anchor = round((pivot_map.anchor_ns - a + s * centre) / (1.0 + s))
    t_pa = anchor + a + s * (anchor - centre)
    offset = t_pa - anchor + pivot_map.offset_ns + delay_ns + dp * (t_pa - pivot_map.anchor_ns)
    return ClockMapping(
        device=name,
        reference=pivot_map.reference,
        offset_ns=round(offset),
        drift_ppm=(s + dp * (1.0 + s)) * 1e6,
        anchor_ns=anchor,
        offset_sigma_ns=pivot_map.offset_sigma_ns,
        drift_sigma_ppm=pivot_map.drift_sigma_ppm,
        method=method,
    )


def pooled_clocks(
    frames: Mapping[str, tuple[I64, I64]],
    fits: Mapping[str, tuple[F64, F64, F64]],
    own: Mapping[str, ClockMapping],
    score: Callable[[str, ClockMapping], float] | None = None,
    sync_modes: Mapping[str, int | None] | None = None,
    ties_out: dict[str, Tie] | None = None,
    expected_delays_ns: Mapping[str, float] | None = None,
) -> tuple[dict[str, ClockMapping], list[str]]:
    """One Vicon clock line through the stretch offsets of every hardware-synchronised camera.

    Slaves capture on the master's pulses, so frame k of a slave and frame k + shift of the
    pivot camera (the one whose own line is best determined) are the same instant: a line
    through their device times ties each camera's clock to the pivot's to well under a µs and
    0.1 ppm (frame counters pair the frames: host arrival times cannot be relied on, and a
    camera's own Vicon line can be off by more than a frame period). The counter shift is
    ambiguous by whole periods: the one whose mapping (the pivot's own line through the tie)
    gives the lowest ``score`` (the reprojection cost of the camera's frames) is kept, or
    without ``score`` the one that puts the camera's stretch offsets closest to the pivot's
    line. Every camera's stretch offsets are then moved onto the pivot's clock and one robust
    weighted line (:func:`_shared_line_fit`) is fitted through all of them (N cameras' worth
    of data; a camera whose own stretches are poor is outvoted instead of getting a poor
    clock), plus a constant per camera from its inlier stretches (a slave exposes a fixed
    trigger delay after the pulse; their weighted mean, shrunk towards the convention's). A
    camera whose frames do not pair (free-running, counters restarted, too little data) keeps
    its own line, and a note says so.

    Args:
        frames: Per camera the frames' ``(device times ns, frame counters)``.
        fits: Per camera ``(t_dev, offset, σ)`` of its stretches (ns).
        own: Per camera the line through its own stretches alone.
        score: ``(camera, candidate mapping) -> cost``, lower is better.
        sync_modes: Per camera its recorded ``inter_cam_sync_mode`` (None: unknown). Only
            masters (1), slaves (2) and unknowns are pooled: a camera in mode 0 free-runs on
            its own crystal, and a free-running camera at the same frame rate can pair with
            the master's frames on a line (its phase slides linearly), so the frame times
            alone cannot always tell it.
        ties_out: Filled with each pooled camera's tie to the pivot (the pivot's own is the
            identity), for the sync-channel clocks (:func:`sync_clocks`).
        expected_delays_ns: Per camera its frame stamp minus the master's of the same pulse
            that the D415 pulse convention predicts (ns; missing: 0): for a slave the trigger
            delay, half the exposure difference and, when the pulse comes at the master's
            readout start, the master's exposure
            (:meth:`~mocaprig.calib.vicon_calibration_options.D415PulseTiming.slave_delay_ns`).
            Each camera's constant is bounded and shrunk about it (relative to the pivot's)
            instead of about 0.

    Returns:
        ``(mapping per camera, notes)``.
    """
    out = dict(own)
    modes = sync_modes or {}
    notes: list[str] = []
    names = []
    for n in own:
        if modes.get(n) not in (None, 1, 2):
            notes.append(
                f"{n}: clock fitted on its own: recorded with inter_cam_sync_mode "
                f"{modes.get(n)} (not a master or slave)"
            )
        else:
            names.append(n)
    if len(names) < 2:
        return out, notes
    pivot = min(
        names,
        key=lambda n: own[n].drift_sigma_ppm if math.isfinite(own[n].drift_sigma_ppm) else 1e9,
    )
    t_p, n_p = frames[pivot]
    line_p = own[pivot]
    rel: dict[str, Tie] = {pivot: Tie(0.0, 0.0, 0.0, len(t_p), 0.0, 0)}
    for n in names:
        if n == pivot:
            continue
        t_c, n_c = frames[n]
        # First guess of the counter shift: nearest pivot frame through the own lines.
        r_c = own[n].to_reference_ns(t_c)
        r_p = line_p.to_reference_ns(t_p)
        order = np.argsort(r_p)
        k = np.clip(np.searchsorted(r_p[order], r_c), 0, len(r_p) - 1)
        shifts, counts = np.unique(n_c - n_p[order][k], return_counts=True)
        guess = int(shifts[np.argmax(counts)]) if len(shifts) else 0

        def on_pivot_line(tie: Tie, n: str = n) -> float:
            if score is not None:
                return score(n, through_tie(n, tie, line_p, method="candidate"))
            t_w, d_w, _ = fits[n]
            tp_w = (t_w + tie.a_ns + tie.s * (t_w - tie.centre_ns)).round()
            on_pivot = (t_w + d_w - tp_w) - (line_p.to_reference_ns(tp_w) - tp_w)
            return float(np.median(np.abs(on_pivot)))

        best = _best_tie(guess, (t_c, n_c), (t_p, n_p), on_pivot_line)
        if best is None:
            notes.append(
                f"{n}: clock fitted on its own: its frames do not pair with {pivot}'s (no frame "
                f"counter shift gives a line within {_SYNC_RMS_NS / 1e3:.0f} µs RMS over ≥ 5 s); "
                "is it hardware-synchronised?"
            )
            _log.warning("%s", notes[-1])
            continue
        tie = best
        _log.info(
            "%s: synchronised with %s (counter shift %d, %d frame pairs, %.1f µs RMS, relative "
            "rate %+.3f ppm)",
            n, pivot, tie.counter_shift, tie.pairs, tie.rms_ns / 1e3, tie.s * 1e6,
        )  # fmt: skip
        rel[n] = tie
    if len(rel) < 2:
        return out, notes
    expected = expected_delays_ns or {}
    centres = [float(expected.get(n, 0.0)) - float(expected.get(pivot, 0.0)) for n in rel]

    def fit_pool() -> tuple[ClockMapping, list[float], list[float]]:
        t_all, d_all, s_all, cam_all = [], [], [], []
        for c, (n, tie) in enumerate(rel.items()):
            t_w, d_w, s_w = fits[n]
            tp_w = t_w + tie.a_ns + tie.s * (t_w - tie.centre_ns)
            t_all.append(tp_w)
            d_all.append(t_w + d_w - tp_w - centres[c])
            s_all.append(s_w)
            cam_all.append(np.full(len(t_w), c))
        line, delays, sig = _shared_line_fit(
            pivot,
            np.concatenate(t_all),
            np.concatenate(d_all),
            np.concatenate(s_all),
            np.concatenate(cam_all),
            len(rel),
        )
        return line, [d + e for d, e in zip(delays, centres, strict=True)], sig

    pooled, delays, delay_sig = fit_pool()
    if score is not None:
        # The shifts were scored through the pivot's own line, which can be frames off (world
        # 1016 without the sync channel: two slaves tied 1 and 2 periods out). The pooled line
        # outvotes a poor pivot: each shift is scored again through it, and the pool refitted
        # when one moves.
        moved = []
        for c, (n, tie) in enumerate(list(rel.items())):
            if n == pivot:
                continue

            def on_pooled_line(cand: Tie, n: str = n, c: int = c) -> float:
                m = through_tie(n, cand, pooled, delay_ns=delays[c], method="candidate")
                return score(n, m)

            best_tie = _best_tie(tie.counter_shift, frames[n], (t_p, n_p), on_pooled_line, keep=tie)
            if best_tie is not tie and best_tie is not None:
                moved.append(f"{n} {best_tie.counter_shift - tie.counter_shift:+d}")
                rel[n] = best_tie
        if moved:
            _log.info("counter shifts moved through the pooled clock: %s", ", ".join(moved))
            notes.append(
                "clock: frame tie shifts corrected through the pooled clock (periods): "
                + ", ".join(moved)
            )
            pooled, delays, delay_sig = fit_pool()
    if ties_out is not None:
        ties_out.update(rel)
    method = f"reprojection, pooled over {len(rel)} synchronised cameras"
    for c, (n, tie) in enumerate(rel.items()):
        m = through_tie(n, tie, pooled, delay_ns=delays[c], method=method)
        out[n] = dataclasses.replace(
            m, offset_sigma_ns=math.hypot(pooled.offset_sigma_ns, delay_sig[c])
        )
    notes.append(
        f"clock: one line fitted through the stretch offsets of {len(rel)} hardware-"
        f"synchronised cameras (pivot {pivot}), each camera's clock tied to the pivot's by its "
        "frame times, plus its own constant delay"
    )
    return out, notes


def _best_tie(
    centre: int,
    camera: tuple[I64, I64],
    pivot: tuple[I64, I64],
    cost: Callable[[Tie], float],
    *,
    keep: Tie | None = None,
) -> Tie | None:
    """The lowest-cost tie (:func:`tie_by_counters`) of a camera's ``(frame time, counter)`` to
    the pivot's over the counter shifts ``centre - 2 … centre + 2``. ``keep``, the tie in hand
    at its own shift, stays unless another costs less; without it the first tie stands until
    one costs less. None when no shift gives a tie."""
    best, best_cost = keep, math.inf
    for shift in range(centre - 2, centre + 3):
        cand = (
            keep
            if keep is not None and shift == keep.counter_shift
            else tie_by_counters(*camera, *pivot, shift)
        )
        if cand is None:
            continue
        c = cost(cand)
        if best is None or c < best_cost:
            best, best_cost = cand, c
    return best


#: Fewest inlier stretches for a camera's own constant delay in the pooled clock; with fewer
#: it gets none (0 ± the pooled line's σ).
_MIN_DELAY_STRETCHES: Final = 3
#: Largest per-camera constant (trigger delay) of the pooled clock, and the prior it is shrunk
#: with (ns), about the delay the pulse convention predicts beyond the trigger delay
#: (``expected_delays_ns`` of :func:`pooled_clocks`). A D415 slave exposes a fixed delay after
#: the pulse (0.1 ms or 0.77 ms in the published conventions, each within ±0.1 ms:
#: docs/d415-timing.md), so the data move a camera's constant away from the convention's only
#: as far as they are sure.
_MAX_DELAY_NS: Final = 1_000_000.0
_DELAY_PRIOR_NS: Final = 100_000.0


def _shared_line_fit(
    pivot: str, t_ns: F64, delta_ns: F64, sigma_ns: F64, cam: npt.NDArray[np.int_], n_cams: int
) -> tuple[ClockMapping, list[float], list[float]]:
    """Robust weighted line ``delta = offset + drift·(t − anchor)`` (ns; ``t`` on the pivot's
    clock) through every camera's stretches, with the weighting and rejection of
    :func:`line_clock`, then per camera the weighted mean of its inlier residuals shrunk
    towards 0 with :data:`_DELAY_PRIOR_NS` (its constant delay, with ≥
    :data:`_MIN_DELAY_STRETCHES` inliers).

    Returns ``(the pivot's mapping, delay ns per camera, delay σ ns per camera)``.
    """
    ok = np.isfinite(sigma_ns) & np.isfinite(delta_ns) & np.isfinite(t_ns)
    t_ns, delta_ns, sigma_ns, cam = t_ns[ok], delta_ns[ok], sigma_ns[ok], cam[ok]
    w = stretch_weights(sigma_ns)
    pooled = line_clock(pivot, t_ns, delta_ns, sigma_ns)
    res = delta_ns - (pooled.to_reference_ns(t_ns.round()) - t_ns.round())
    z = res * np.sqrt(w)
    scale = max(1.4826 * float(np.median(np.abs(z))), 1.0)
    # A per-camera constant is a trigger delay: physically ≤ _MAX_DELAY_NS. Only stretches that
    # close to the line say anything about it (wider ones are fits on a neighbouring frame or a
    # bad stretch), and a weak estimate is shrunk towards 0 (Gaussian prior _DELAY_PRIOR_NS).
    inlier = (np.abs(z) <= STRETCH_REJECT_SIGMA * scale) & (np.abs(res) <= _MAX_DELAY_NS)
    delays, sig = [], []
    for c in range(n_cams):
        sel = inlier & (cam == c)
        r, wc = res[sel], w[sel]
        if len(r) >= _MIN_DELAY_STRETCHES:
            # Weighted as in the line: a stretch's σ is honest about its markers' speed.
            mean = float((wc * r).sum() / wc.sum())
            chi2 = float((wc * (r - mean) ** 2).sum()) / (len(r) - 1)
            se = math.sqrt(max(chi2, 1.0) / float(wc.sum()))
            k = _DELAY_PRIOR_NS**2 / (_DELAY_PRIOR_NS**2 + se**2)
            delays.append(k * mean)
            sig.append(math.sqrt(k) * se)
        else:
            delays.append(0.0)
            sig.append(0.0)
    _log.info(
        "%s clock (pooled): %d of %d stretches inliers; delays %s µs",
        pivot, int(inlier.sum()), len(inlier), [round(d / 1e3, 1) for d in delays],
    )  # fmt: skip
    return pooled, delays, sig
