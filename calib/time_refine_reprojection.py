"""Clock refinement by reprojection (accurate; needs the camera's registered pose).

The Vicon markers interpolated at each frame's mapped time are projected onto the frame's blobs
and the offset and drift corrections fitted to the image residuals (≈ 0.2 ms on the simulated
sessions; see docs/calibration.md for the drift): :func:`refine_by_reprojection`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Final

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from mocaprig.calib.calibration import ClockMapping
from mocaprig.calib.camera_model import project_points
from mocaprig.calib.markers import MarkerFrame
from mocaprig.calib.vicon import MarkerTrajectories
from mocaprig.calib.vicon_times import vicon_times_ns
from mocaprig.errors import CalibrationError, ValidationError

__all__ = ["refine_by_reprojection"]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: Vicon markers nearer to a camera than this (m) are not projected into it (reprojection).
_MIN_DEPTH_M: Final = 0.05


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
