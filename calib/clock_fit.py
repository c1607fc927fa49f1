"""Clock mappings fitted through paired events: claps, and the D415 master's frame pulses.

* :func:`clock_from_claps`: a device's claps paired with the reference's (Vicon) give the offset
  from one clap, offset and drift from two or more (a weighted line through the clap pairs).
* :func:`clock_from_pulses`: the D415 master's frame pulses reach the DAVIS's external input, so
  DAVIS ↔ D415 is a line fitted through paired pulses and frames (µs-level), composed with the
  D415's mapping to reach the reference.

Clock mappings are :class:`mocaprig.calib.calibration.ClockMapping`:
``t_ref = t_dev + offset_ns + drift_ppm·1e-6·(t_dev − anchor_ns)``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from mocaprig.calib.calibration import ClockMapping
from mocaprig.calib.clap_detection import ClapDetection
from mocaprig.errors import CalibrationError, ValidationError

__all__ = ["clock_from_claps", "clock_from_pulses"]

_log = logging.getLogger(__name__)

I64 = npt.NDArray[np.int64]


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
