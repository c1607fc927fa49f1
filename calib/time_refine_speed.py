"""Clock refinement without extrinsics: marker-speed signals cross-correlated.

The D415 claps are only good to a few ms and two claps cannot give a drift to ppm, so a mapping
is refined over the whole session. Speeds are rotation-invariant, so no camera pose is needed:
:func:`speed_from_trajectories` (Vicon, labelled markers) and :func:`speed_from_frames` (one
D415's :class:`~calib.markers.MarkerFrame` list, nearest-neighbour matching in the image,
lateral speed from the image motion and depth). :func:`refine_by_speed` takes a normalised
cross-correlation of the two over a grid of offsets (the prior), then maximises the correlation
over a continuous offset and drift. The two signals differ in shape, which biases the peak by
milliseconds on the simulated sessions: a coarse prior only (the accurate refinement is
:func:`mocaprig.calib.time_refine_reprojection.refine_by_reprojection`).
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
from scipy.optimize import minimize
from scipy.spatial import cKDTree

from mocaprig.calib.calibration import ClockMapping
from mocaprig.calib.clap_detection_d415 import focal_px_from_frames
from mocaprig.calib.markers import MarkerFrame
from mocaprig.calib.vicon import MarkerTrajectories
from mocaprig.calib.vicon_times import vicon_times_ns
from mocaprig.errors import CalibrationError, ValidationError

__all__ = ["refine_by_speed", "speed_from_frames", "speed_from_trajectories"]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]


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
    focal = focal_px_from_frames(fr)
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
