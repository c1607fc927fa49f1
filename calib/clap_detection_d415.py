"""Claps seen by one D415 (30 Hz, unlabelled markers, no extrinsics needed).

The clapper is found as the pair of *static* blobs a contact distance apart of which one leaves
and comes back; the signal is the image distance (px) of the moving marker from the fixed one
(the image is far more precise than D415 depth). A 30 Hz camera sees only 1–4 samples of a
60–120 ms closing, so the closing *trajectory* is fitted: constant angular acceleration from
rest (``θ = θmax·(1 − u²)``, ``u`` from 0 to 1 over the closing), the signal taken as linear in
``θ``, evaluated as a posterior over (contact time, closing duration) on a grid with a weak prior
on the duration; the estimate is the posterior mean and ``sigma_ns`` its spread.

:func:`focal_px_from_frames` recovers a camera's focal length from its frames' deprojection
(also used by the speed signal, :mod:`mocaprig.calib.time_refine_speed`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from mocaprig.calib.clap_detection import (
    CLAP_OPEN_MIN_M,
    ClapDetection,
    ClapEpisode,
    clap_episodes,
)
from mocaprig.calib.markers import MarkerFrame
from mocaprig.errors import CalibrationError

__all__ = ["find_claps_d415", "focal_px_from_frames"]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]


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
    open_min_m: float = CLAP_OPEN_MIN_M,
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
    focal = focal_px_from_frames(fr)
    best: tuple[float, float, list[ClapEpisode], F64, F64, float] | None = None
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
            eps = clap_episodes(
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


def focal_px_from_frames(frames: Sequence[MarkerFrame]) -> float:
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
    ep: ClapEpisode,
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
