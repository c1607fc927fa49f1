"""Each D415's own clock from its video: Vicon markers reprojected onto its blobs.

The Vicon markers are interpolated at a frame's mapped time (:class:`ViconInterp`) and projected
into the registered camera; the device → Vicon offset is what puts them on the frame's blobs. A
coarse offset comes from a grid over the truncated reprojection cost (:func:`grid_offset`,
:func:`reprojection_cost`), then each 0.5 s stretch of frames gets its own offset by least
squares (:func:`stretch_offsets`), and :func:`line_clock` fits a robust weighted line (offset,
drift) through a camera's stretches. The pooled clock of hardware-synchronised cameras is in
:mod:`mocaprig.calib.vicon_calibration_pooled_clock`.

With ``clock_method="claps+speed"`` that line is the prior of :func:`claps_speed_clock` (the D415's
claps paired with the Vicon's, then the marker-speed correlation: :mod:`mocaprig.calib.time_align`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Final

import numpy as np
import numpy.typing as npt

from mocaprig.calib.calibration import ClockMapping
from mocaprig.calib.clap_detection import ClapDetection
from mocaprig.calib.markers import MarkerFrame
from mocaprig.calib.registration import project_points
from mocaprig.calib.vicon import MarkerTrajectories
from mocaprig.calib.vicon_calibration_frames import CalibCamera
from mocaprig.errors import CalibrationError

__all__ = [
    "STRETCH_BIAS_PX",
    "STRETCH_REJECT_SIGMA",
    "STRETCH_SIGMA_FLOOR_NS",
    "ViconInterp",
    "claps_speed_clock",
    "grid_offset",
    "line_clock",
    "reprojection_cost",
    "stretch_offsets",
    "stretch_weights",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: Length of the stretches of frames that each give one clock offset (ns).
_CHUNK_NS: Final = 500_000_000
#: Half the interval over which a stretch's image speed is measured (ns).
_SPEED_STEP_NS: Final = 5_000_000
#: Systematic image bias (px) of a camera's blobs against its projected Vicon markers, common
#: to a stretch's frames: it limits a stretch's offset to ± bias / image speed. Measured on
#: the random worlds (world 1004: stretch errors × image speed 0.1–0.2 px, up to 4 ms on
#: stretches of standing still, whose own fit claimed 0.4–0.9 ms).
STRETCH_BIAS_PX: Final = 0.2


class ViconInterp:
    """Vicon marker positions at Vicon-clock times: cubic (Catmull–Rom) between frames, linear
    next to a gap, NaN inside gaps and outside the trial."""

    def __init__(self, t_ns: I64, positions_m: F64) -> None:
        self.t = t_ns.astype(np.float64)
        self.p = positions_m

    def at(self, t_ns: npt.ArrayLike) -> F64:
        t = np.asarray(t_ns, dtype=np.float64)
        n = len(self.t)
        i = np.clip(np.searchsorted(self.t, t) - 1, 0, n - 2)
        u = ((t - self.t[i]) / (self.t[i + 1] - self.t[i]))[:, None, None]
        p0 = self.p[np.maximum(i - 1, 0)]
        p1 = self.p[i]
        p2 = self.p[i + 1]
        p3 = self.p[np.minimum(i + 2, n - 1)]
        linear = (1.0 - u) * p1 + u * p2
        cubic = 0.5 * (
            2.0 * p1
            + (p2 - p0) * u
            + (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3) * u**2
            + (3.0 * p1 - p0 - 3.0 * p2 + p3) * u**3
        )
        out: F64 = np.where(np.isfinite(cubic), cubic, linear)
        outside = (t < self.t[0]) | (t > self.t[-1])
        out[outside] = np.nan
        return out


def _project_frames(frames: Sequence[MarkerFrame], ref: F64, T: F64, cam: CalibCamera) -> F64:
    uv, _ = project_points(ref.reshape(-1, 3), T, cam.K, cam.dist)
    out: F64 = uv.reshape(len(frames), -1, 2)
    return out


def reprojection_cost(
    frames: Sequence[MarkerFrame],
    T: F64,
    cam: CalibCamera,
    vicon: ViconInterp,
    t_vicon_ns: npt.ArrayLike,
    *,
    gate_px: float,
) -> float:
    """Truncated reprojection cost (px²) of the frames' blobs against the Vicon markers
    interpolated at the frames' Vicon times: each blob's distance to the nearest projected
    marker, capped at ``gate_px``."""
    from scipy.spatial import cKDTree

    uv = _project_frames(frames, vicon.at(np.asarray(t_vicon_ns, dtype=np.int64)), T, cam)
    total = 0.0
    for i, f in enumerate(frames):
        ok = np.isfinite(uv[i]).all(axis=1)
        if ok.any():
            d, _ = cKDTree(uv[i][ok]).query(f.uv_px, distance_upper_bound=gate_px)
            total += float((np.minimum(d, gate_px) ** 2).sum())
        else:
            total += gate_px**2 * f.n_markers
    return total


def grid_offset(
    frames: Sequence[MarkerFrame],
    T: F64,
    cam: CalibCamera,
    vicon: ViconInterp,
    prior_ns: int,
    *,
    half_width_ns: int,
    step_ns: int,
    gate_px: float = 3.0,
) -> int:
    """The device → Vicon offset (ns) minimising the truncated reprojection cost: a coarse grid
    (5 × ``step_ns``, gate 2 × ``gate_px``) over ±``half_width_ns``, then ``step_ns`` around
    the coarse minimum."""

    t_dev = np.array([f.t_dev_ns for f in frames], dtype=np.int64)
    used = [k for k, f in enumerate(frames) if f.n_markers > 0]
    sub = [frames[k] for k in used]

    def cost(delta: int, gate: float) -> float:
        return reprojection_cost(sub, T, cam, vicon, t_dev[used] + delta, gate_px=gate)

    if not used:
        return prior_ns
    coarse = 5 * step_ns
    grid = range(prior_ns - half_width_ns, prior_ns + half_width_ns + 1, coarse)
    best = min(grid, key=lambda d: cost(d, 2.0 * gate_px))
    fine = range(best - coarse, best + coarse + 1, step_ns)
    return min(fine, key=lambda d: cost(d, gate_px))


def _fit_offset(
    frames: Sequence[MarkerFrame],
    T: F64,
    cam: CalibCamera,
    vicon: ViconInterp,
    delta0_ns: int,
    *,
    gate_px: float = 3.0,
) -> tuple[float, float, int]:
    """Continuous device → Vicon offset over frames: matched blobs, soft-L1 least squares over
    the offset (ms). Returns (offset ns, 1σ ns, pairs); σ combines the fit's own with
    :data:`STRETCH_BIAS_PX` over the markers' image speed, and is inf without motion."""
    from scipy.optimize import least_squares

    from mocaprig.calib.registration import match_markers

    t_dev = np.array([f.t_dev_ns for f in frames], dtype=np.float64)
    delta = float(delta0_ns)
    sigma, n_pairs = math.inf, 0
    for _ in range(2):
        uv = _project_frames(frames, vicon.at(t_dev + delta), T, cam)
        rows: list[tuple[int, int, int]] = []
        for k, f in enumerate(frames):
            i, j = match_markers(f.uv_px, uv[k], gate_m=gate_px)
            rows.extend((k, int(a), int(b)) for a, b in zip(i, j, strict=True))
        if len(rows) < 6:
            return delta, math.inf, len(rows)
        fk = np.array([r[0] for r in rows])
        bi = np.array([r[1] for r in rows])
        mj = np.array([r[2] for r in rows])
        # A marker with a Vicon gap within the fit's reach would jump to a penalty as the
        # offset moves (a step the finite differences read as a huge slope): left out.
        ends = [
            vicon.at(t_dev[fk] + delta + s * _SPEED_STEP_NS)[np.arange(len(fk)), mj]
            for s in (-1.0, 1.0)
        ]
        whole = np.isfinite(ends[0]).all(axis=1) & np.isfinite(ends[1]).all(axis=1)
        if int(whole.sum()) < 6:
            return delta, math.inf, int(whole.sum())
        fk, bi, mj = fk[whole], bi[whole], mj[whole]
        obs = np.stack([frames[k].uv_px[b] for k, b in zip(fk, bi, strict=True)])
        # The markers' image speed (px/ms, RMS per coordinate) over the fit's reach.
        uv_a, _ = project_points(ends[0][whole], T, cam.K, cam.dist)
        uv_b, _ = project_points(ends[1][whole], T, cam.K, cam.dist)
        speed = float(np.sqrt(np.mean((uv_b - uv_a) ** 2))) / (2e-6 * _SPEED_STEP_NS)

        base = delta

        def residuals(x: F64, fk: npt.NDArray[np.int_] = fk, mj: npt.NDArray[np.int_] = mj,
                      obs: F64 = obs, base: float = base) -> F64:  # fmt: skip
            # x: correction to ``base`` in ms (a small number: finite differences stay sane).
            ref = vicon.at(t_dev[fk] + base + x[0] * 1e6)
            pts = ref[np.arange(len(fk)), mj]
            uvp, _ = project_points(pts, T, cam.K, cam.dist)
            r: F64 = np.nan_to_num(uvp - obs, nan=50.0).ravel()
            return r

        sol = least_squares(residuals, [0.0], loss="soft_l1", f_scale=1.0, diff_step=1e-2)
        delta = base + float(sol.x[0] * 1e6)
        n_pairs = len(rows)
        jtj = float(sol.jac[:, 0] @ sol.jac[:, 0])
        s2 = float(np.mean(sol.fun**2))
        stat = math.sqrt(s2 / jtj) * 1e6 if jtj > 0 else math.inf
        # A bias of the blobs against the projected markers (the pose's error, a marker half
        # hidden) is the same in every frame of the stretch: it does not average down, and
        # it reads as a time offset of bias / image speed.
        bias = STRETCH_BIAS_PX / speed * 1e6 if speed > 0 else math.inf
        sigma = math.hypot(stat, bias)
    return delta, sigma, n_pairs


def stretch_offsets(
    cam: CalibCamera,
    frames: Sequence[MarkerFrame],
    T: F64,
    interp: ViconInterp,
    delta0_ns: int,
    mapping: ClockMapping | None,
) -> tuple[F64, F64, F64]:
    """Device → Vicon offsets of stretches of ≤ ``_CHUNK_NS`` of frames.

    Returns ``(t_dev (S,), offset (S,), σ (S,))`` in ns, stretches without a finite offset left
    out. Without ``mapping`` each stretch starts from a grid search around ``delta0_ns``; with
    one (good to ~1 ms) a fit from the mapped offset suffices.

    Raises:
        CalibrationError: no stretch gives an offset (no motion seen in the windows read).
    """
    t_all = np.array([f.t_dev_ns for f in frames], dtype=np.int64)
    wins = (t_all - t_all.min()) // _CHUNK_NS if len(t_all) else t_all
    t_w, d_w, s_w = [], [], []
    for w in np.unique(wins):
        fw = [f for f, k in zip(frames, wins, strict=True) if k == w]
        if mapping is None:
            d0 = grid_offset(
                fw, T, cam, interp, delta0_ns, half_width_ns=20_000_000, step_ns=1_000_000
            )
        else:
            tm = int(np.median([f.t_dev_ns for f in fw]))
            d0 = int(mapping.to_reference_ns(tm)) - tm
        d, s, n_pairs = _fit_offset(fw, T, cam, interp, d0)
        _log.debug(
            "%s: frames at %d ns: offset %d ns ± %.0f ns (%d pairs)",
            cam.name, int(np.median([f.t_dev_ns for f in fw])), round(d), s, n_pairs,
        )  # fmt: skip
        if math.isfinite(s):
            t_w.append(float(np.median([f.t_dev_ns for f in fw])))
            d_w.append(d)
            s_w.append(s)
    if not d_w:
        msg = (
            f"{cam.name}: no time offset to the Vicon: its markers never matched the "
            "Vicon markers while moving (no motion in the windows read?)"
        )
        raise CalibrationError(msg)
    return np.array(t_w), np.array(d_w), np.array(s_w)


#: Floor added (in quadrature) to each stretch's offset σ in the clock line. A stretch's own σ
#: (from its reprojection fit) is 70–900 µs, but stretches of the same camera scatter by
#: 0.3–1 ms about the line (blob bias that depends on the motion), and a σ near zero from a
#: degenerate stretch would otherwise take all the weight.
STRETCH_SIGMA_FLOOR_NS: Final = 250_000.0
#: Stretches farther than this many robust σ from the line are rejected, then it is refitted.
STRETCH_REJECT_SIGMA: Final = 3.0


def stretch_weights(sigma_ns: F64) -> F64:
    """Weights ``1/(σ² + floor²)`` of clock stretches with offset σ ``sigma_ns`` (ns), the floor
    :data:`STRETCH_SIGMA_FLOOR_NS`: every fit of stretch offsets weighs them this way."""
    return np.asarray(1.0 / (np.square(sigma_ns) + STRETCH_SIGMA_FLOOR_NS**2), dtype=np.float64)


#: A video clock line steeper than this (ppm) is not believed (D415 and Vicon crystals are
#: within ±50 ppm): :func:`line_clock` keeps the offset alone.
VIDEO_DRIFT_LIMIT_PPM: Final = 1000.0


def line_clock(device: str, t_dev: F64, delta_ns: F64, sigma_ns: F64) -> ClockMapping:
    """A device → Vicon mapping through per-stretch offsets (ns, at device times ns): a
    weighted line (offset + drift) when the stretches span ≥ 5 s, else the weighted mean
    offset with no drift.

    Each stretch is weighted by ``1/(σ² + floor²)`` (:data:`STRETCH_SIGMA_FLOOR_NS`); stretches
    beyond :data:`STRETCH_REJECT_SIGMA` robust σ (MAD of the weighted residuals) are rejected
    and the line refitted, until none is (at least 3 kept). The reported σ are scaled by the
    residual χ² when it exceeds 1. A slope beyond :data:`VIDEO_DRIFT_LIMIT_PPM` (a short or
    poorly timed take) is not believed: the offset alone is kept, with a warning."""
    ok = np.isfinite(sigma_ns) & np.isfinite(delta_ns) & np.isfinite(t_dev)
    t_dev, delta_ns, sigma_ns = t_dev[ok], delta_ns[ok], sigma_ns[ok]
    if len(t_dev) == 0:
        msg = f"{device}: no stretch gave a finite clock offset"
        raise CalibrationError(msg)
    w = stretch_weights(sigma_ns)
    anchor = round(float((w * t_dev).sum() / w.sum()))
    x = (t_dev - anchor) * 1e-9
    line = bool(len(t_dev) >= 2 and np.ptp(t_dev) >= 5e9)
    coef, cov = _robust_line(device, x, delta_ns, w, line=line)
    if line and abs(float(coef[1]) * 1e-3) > VIDEO_DRIFT_LIMIT_PPM:
        # No crystal drifts this much: the stretches are too few or too noisy to fix a slope.
        _log.warning(
            "%s: the video clock's drift came out %.0f ppm over %.1f s of stretches (beyond "
            "%g ppm): kept the mean offset with no drift; a longer take with moving markers "
            "times the camera better",
            device, float(coef[1]) * 1e-3, float(np.ptp(t_dev)) * 1e-9, VIDEO_DRIFT_LIMIT_PPM,
        )  # fmt: skip
        line = False
        coef, cov = _robust_line(device, x, delta_ns, w, line=False)
    return ClockMapping(
        device=device,
        reference="vicon",
        offset_ns=round(float(coef[0])),
        drift_ppm=float(coef[1]) * 1e-3 if line else 0.0,
        anchor_ns=anchor,
        offset_sigma_ns=math.sqrt(cov[0, 0]),
        drift_sigma_ppm=math.sqrt(cov[1, 1]) * 1e-3 if line else math.nan,
        method="reprojection",
    )


def _robust_line(device: str, x: F64, delta_ns: F64, w: F64, *, line: bool) -> tuple[F64, F64]:
    """Weighted fit of ``delta_ns`` against ``x`` (s from the anchor): offset and slope
    (ns/s) with ``line``, else the offset alone; outliers rejected one by one (see
    :func:`line_clock`). Returns the coefficients and their covariance (scaled by χ²)."""
    keep = np.ones(len(x), dtype=bool)
    A = np.stack([np.ones_like(x), x], axis=1) if line else np.ones((len(x), 1))
    for _ in range(len(x)):
        wk = w * keep
        cov = np.linalg.inv(A.T @ (A * wk[:, None]))
        coef = cov @ (A.T @ (wk * delta_ns))
        z = (delta_ns - A @ coef) * np.sqrt(w)
        scale = max(1.4826 * float(np.median(np.abs(z[keep]))), 1.0)
        worse = keep & (np.abs(z) > STRETCH_REJECT_SIGMA * scale)
        if not worse.any() or keep.sum() - 1 < max(3, A.shape[1] + 1):
            break
        keep[np.argmax(np.where(worse, np.abs(z), -np.inf))] = False
    n_rej = int((~keep).sum())
    if n_rej:
        _log.info("%s: clock line: %d of %d stretches rejected", device, n_rej, len(keep))
    chi2 = float((z[keep] ** 2).sum()) / max(int(keep.sum()) - A.shape[1], 1)
    scaled = np.asarray(cov * max(chi2, 1.0), dtype=np.float64)
    return coef, scaled


def claps_speed_clock(
    device: str,
    frames: Sequence[MarkerFrame],
    vicon_claps: Sequence[ClapDetection],
    traj: MarkerTrajectories,
    prior: ClockMapping,
) -> ClockMapping:
    """The clock from :mod:`mocaprig.calib.time_align`: the camera's claps paired with the Vicon's
    (offset, and drift from two claps), then refined by the marker-speed correlation over the
    frames read. Falls back to ``prior`` (the reprojection clock) for a step that fails, and
    says so in the log."""
    from mocaprig.calib.clap_detection_d415 import find_claps_d415
    from mocaprig.calib.clock_fit import clock_from_claps
    from mocaprig.calib.time_refine_speed import (
        refine_by_speed,
        speed_from_frames,
        speed_from_trajectories,
    )

    mapping = prior
    try:
        claps = find_claps_d415(frames, device=device)
        mapping = clock_from_claps(device, claps, vicon_claps)
    except CalibrationError as err:
        _log.warning("%s: clap clock unavailable (%s); keeping the reprojection clock", device, err)
    a = prior.anchor_ns
    if abs(int(mapping.to_reference_ns(a)) - int(prior.to_reference_ns(a))) > 50_000_000:
        _log.warning("%s: the clap clock disagrees with the reprojection clock by > 50 ms", device)
        mapping = prior
    try:
        td, vd = speed_from_frames(frames)
        tr, vr = speed_from_trajectories(traj)
        mapping = refine_by_speed(mapping, td, vd, tr, vr, search_ns=20_000_000)
    except CalibrationError as err:
        _log.warning("%s: speed refinement failed (%s)", device, err)
    return mapping
