"""Registration of a camera's marker observations to Vicon markers.

The recipe of DeMoCap §3.4 and ``../shared/docs/calibration-vicon.md`` §3.2–§3.4:

1. :func:`coarse_align` — a rigid transform between two marker clouds with unknown
   correspondences and **no initial pose**: RANSAC over triplets whose three side lengths match
   (rigid-invariant), scored with a truncated-distance (MSAC) count, then the best hypotheses are
   refined by :func:`trimmed_icp` and Hungarian-gated ICP. Tolerant to ghosts, misses and unequal
   counts.
2. :func:`match_markers` — minimum-weight bipartite matching
   (``scipy.optimize.linear_sum_assignment``) under a strict gate.
3. :func:`bundle_adjust` / :func:`bundle_adjust_camera` — camera poses from matched
   (fixed world point, pixel) pairs, intrinsics fixed: ``least_squares`` with a sparse Jacobian
   pattern (block-diagonal over cameras), ``loss="soft_l1"``, then a 3σ rejection and a linear
   refit; reprojection RMS, inliers and the 6×6 pose covariance.
4. :func:`register_camera` — all of it for one camera over several frames of a static start:
   the camera-frame marker cloud (median depth of each blob tracked over the frames), coarse
   alignment to the Vicon markers, gated 2D matching per frame and two rounds of bundle
   adjustment with a tightening gate.

Frames and units: world = Vicon (metres, Z up); camera = OpenCV (+Z forward, +Y down);
``T_world_cam`` (4×4) maps camera to world, translation in metres; pixels per
``cv2.projectPoints`` with Brown–Conrady ``(k1, k2, p1, p2, k3)``, computed by
:mod:`calib.camera_model` (:func:`project_points` is its function, re-exported here).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from itertools import combinations
from typing import Final

import numpy as np
import numpy.typing as npt
from scipy.optimize import OptimizeResult, least_squares, linear_sum_assignment
from scipy.sparse import lil_matrix
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from mocaprig.calib.camera_model import project_camera, project_points
from mocaprig.errors import CalibrationError, ValidationError
from mocaprig.validation import check_positive, check_range, check_shape

__all__ = [
    "AlignmentResult",
    "BundleProblem",
    "BundleResult",
    "CameraRegistration",
    "IcpResult",
    "bundle_adjust",
    "bundle_adjust_camera",
    "coarse_align",
    "kabsch",
    "kabsch_batch",
    "match_markers",
    "project_points",
    "register_camera",
    "rotation_error_deg",
    "static_cloud",
    "transform_points",
    "trimmed_icp",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: A large finite cost for gated-out pairs (``linear_sum_assignment`` refuses infeasible inf).
_BIG: Final = 1e6
#: Fewest correspondences a rigid fit from a cloud accepts.
_MIN_PAIRS: Final = 4


# --------------------------------------------------------------------------------------------
# Small geometry
# --------------------------------------------------------------------------------------------


def transform_points(T: npt.ArrayLike, points: npt.ArrayLike) -> F64:
    """Apply a 4×4 rigid transform to points ``(..., 3)``."""
    t = np.asarray(T, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    out: F64 = p @ t[:3, :3].T + t[:3, 3]
    return out


def _make_T(r: F64, t: F64) -> F64:
    out = np.eye(4)
    out[:3, :3] = r
    out[:3, 3] = t
    return out


def _invert(T: F64) -> F64:
    r, t = T[:3, :3], T[:3, 3]
    return _make_T(r.T, -r.T @ t)


def rotation_error_deg(T_a: npt.ArrayLike, T_b: npt.ArrayLike) -> float:
    """Angle (degrees) of the rotation between two 4×4 transforms' rotation parts."""
    ra = np.asarray(T_a, dtype=np.float64)[:3, :3]
    rb = np.asarray(T_b, dtype=np.float64)[:3, :3]
    # The rotation vector's length is exact near zero, where acos((trace − 1)/2) is not.
    return math.degrees(float(Rotation.from_matrix(ra.T @ rb).magnitude()))


def kabsch(src: npt.ArrayLike, dst: npt.ArrayLike, weights: npt.ArrayLike | None = None) -> F64:
    """The rigid transform (4×4) minimising ``Σ w·|T·src − dst|²`` (reflection-safe).

    Args:
        src: Points ``(N, 3)``.
        dst: Corresponding points ``(N, 3)``.
        weights: Optional non-negative weights ``(N,)``.

    Raises:
        ValidationError: shapes differ or fewer than 3 points.
    """
    s = np.asarray(check_shape(src, ["n", 3], name="src"), dtype=np.float64)
    d = np.asarray(check_shape(dst, [s.shape[0], 3], name="dst"), dtype=np.float64)
    if s.shape[0] < 3:
        msg = f"kabsch() needs at least 3 point pairs, got {s.shape[0]}"
        raise ValidationError(msg)
    w = np.ones(len(s)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / max(float(w.sum()), 1e-300)
    cs = w @ s
    cd = w @ d
    h = (s - cs).T @ ((d - cd) * w[:, None])
    u, _, vt = np.linalg.svd(h)
    fix = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(vt.T @ u.T)) or 1.0)])
    r = vt.T @ fix @ u.T
    return _make_T(r, cd - r @ cs)


def kabsch_batch(src: npt.ArrayLike, dst: npt.ArrayLike) -> F64:
    """:func:`kabsch` for a batch of point sets ``(H, k, 3)`` → ``(H, 4, 4)`` (equal weights;
    no checks: ``k`` >= 3 non-collinear points per set is the caller's)."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    cs = src.mean(axis=1)
    cd = dst.mean(axis=1)
    h = np.einsum("hki,hkj->hij", src - cs[:, None], dst - cd[:, None])
    u, _, vt = np.linalg.svd(h)
    det = np.linalg.det(np.einsum("hji,hkj->hik", vt, u))
    fix = np.zeros((len(src), 3, 3))
    fix[:, 0, 0] = 1.0
    fix[:, 1, 1] = 1.0
    fix[:, 2, 2] = np.where(det < 0, -1.0, 1.0)
    r = np.einsum("hji,hjk,hlk->hil", vt, fix, u)
    out = np.zeros((len(src), 4, 4))
    out[:, :3, :3] = r
    out[:, :3, 3] = cd - np.einsum("hij,hj->hi", r, cs)
    out[:, 3, 3] = 1.0
    return out


# --------------------------------------------------------------------------------------------
# Matching and ICP
# --------------------------------------------------------------------------------------------


def match_markers(
    src: npt.ArrayLike,
    dst: npt.ArrayLike,
    *,
    gate_m: float,
    forbid: npt.NDArray[np.bool_] | None = None,
) -> tuple[I64, I64]:
    """Minimum-weight bipartite matching of two point sets under a strict distance gate.

    Works for any dimension (3D markers in metres, or 2D pixels with the gate in pixels).
    Pairs farther apart than ``gate_m`` are never matched; NaN rows never match.

    Args:
        src: Points ``(N, D)``.
        dst: Points ``(M, D)``.
        gate_m: Largest accepted distance (same unit as the points).
        forbid: Optional ``(N, M)`` mask of pairs that must not match (e.g. depth disagrees).

    Returns:
        ``(i, j)``: int64 index arrays of the matched pairs, ``src[i[k]] ↔ dst[j[k]]``,
        sorted by ``i``.
    """
    check_positive(gate_m, name="gate_m")
    s = np.asarray(src, dtype=np.float64)
    d = np.asarray(dst, dtype=np.float64)
    if s.ndim != 2 or d.ndim != 2 or s.shape[1] != d.shape[1]:
        msg = f"match_markers(): src {s.shape} and dst {d.shape} must be (N, D) and (M, D)"
        raise ValidationError(msg)
    empty = np.zeros(0, dtype=np.int64)
    if len(s) == 0 or len(d) == 0:
        return empty, empty
    cost = np.sqrt(((s[:, None, :] - d[None, :, :]) ** 2).sum(axis=-1))
    bad = ~np.isfinite(cost) | (cost > gate_m)
    if forbid is not None:
        bad |= np.asarray(forbid, dtype=bool)
    cost = np.where(bad, _BIG, cost)
    rows = np.flatnonzero((~bad).any(axis=1))
    cols = np.flatnonzero((~bad).any(axis=0))
    if len(rows) == 0:
        return empty, empty
    sub = cost[np.ix_(rows, cols)]
    ri, ci = linear_sum_assignment(sub)
    keep = sub[ri, ci] < _BIG
    return rows[ri[keep]].astype(np.int64), cols[ci[keep]].astype(np.int64)


@dataclass(frozen=True, slots=True)
class IcpResult:
    """Outcome of an ICP run (``T`` maps source to destination).

    Attributes:
        T: ``(4, 4)`` source → destination.
        rms_m: RMS distance of the pairs kept in the last iteration (m).
        n_pairs: Pairs kept in the last iteration.
        iterations: Iterations run.
        converged: The update fell below the tolerance before ``max_iterations``.
    """

    T: F64 = field(repr=False)
    rms_m: float
    n_pairs: int
    iterations: int
    converged: bool


def trimmed_icp(
    src: npt.ArrayLike,
    dst: npt.ArrayLike,
    *,
    T_init: npt.ArrayLike | None = None,
    keep_fraction: float = 0.7,
    max_iterations: int = 50,
    tolerance_m: float = 1e-5,
) -> IcpResult:
    """Trimmed nearest-neighbour ICP: each iteration keeps the closest ``keep_fraction`` pairs.

    Local only (calibration-vicon.md §3.2): give it a start within ~10° / 10 cm.

    Raises:
        CalibrationError: fewer than 4 usable points on either side.
    """
    check_range(keep_fraction, 0.1, 1.0, name="keep_fraction")
    s = _finite_rows(np.asarray(check_shape(src, ["n", 3], name="src"), dtype=np.float64))
    d = _finite_rows(np.asarray(check_shape(dst, ["m", 3], name="dst"), dtype=np.float64))
    if len(s) < _MIN_PAIRS or len(d) < _MIN_PAIRS:
        msg = f"trimmed_icp(): needs ≥ {_MIN_PAIRS} points each side, got {len(s)} and {len(d)}"
        raise CalibrationError(msg)
    T = np.eye(4) if T_init is None else np.array(T_init, dtype=np.float64)
    tree = cKDTree(d)
    n_keep = max(3, round(keep_fraction * len(s)))
    rms = math.inf
    converged = False
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007 - reported below
        moved = transform_points(T, s)
        dist, j = tree.query(moved)
        order = np.argsort(dist)[:n_keep]
        step = kabsch(moved[order], d[j[order]])
        T = step @ T
        rms = float(np.sqrt(np.mean(dist[order] ** 2)))
        if np.linalg.norm(step[:3, 3]) < tolerance_m and rotation_error_deg(step, np.eye(4)) < 1e-4:
            converged = True
            break
    return IcpResult(T=T, rms_m=rms, n_pairs=n_keep, iterations=it, converged=converged)


def _finite_rows(a: F64) -> F64:
    out: F64 = a[np.isfinite(a).all(axis=1)]
    return out


def _gated_icp(s: F64, d: F64, T: F64, gates: Sequence[float]) -> tuple[F64, I64, I64]:
    """Hungarian-gated ICP with an annealed gate; returns T and the last pairs."""
    i = j = np.zeros(0, dtype=np.int64)
    for gate in gates:
        for _ in range(3):
            i, j = match_markers(transform_points(T, s), d, gate_m=gate)
            if len(i) < 3:
                return T, i, j
            T_new = kabsch(s[i], d[j])
            done = rotation_error_deg(T_new, T) < 1e-4 and bool(
                np.linalg.norm(T_new[:3, 3] - T[:3, 3]) < 1e-6
            )
            T = T_new
            if done:
                break
    i, j = match_markers(transform_points(T, s), d, gate_m=gates[-1])
    return T, i, j


# --------------------------------------------------------------------------------------------
# Coarse alignment
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class AlignmentResult:
    """A coarse alignment of a source cloud onto a destination cloud.

    Attributes:
        T: ``(4, 4)`` source → destination (for camera → world: ``T_world_cam``).
        src_index: Matched source indices (into the array given, NaN rows included).
        dst_index: Matched destination indices, pairwise with ``src_index``.
        rms_m: RMS distance of the matched pairs (m).
        n_inliers: Number of matched pairs under ``gate_m``.
        n_hypotheses: Triplet hypotheses scored.
    """

    T: F64 = field(repr=False)
    src_index: I64 = field(repr=False)
    dst_index: I64 = field(repr=False)
    rms_m: float
    n_inliers: int
    n_hypotheses: int


def _triplet_table(d: F64, min_side_m: float) -> tuple[I64, F64]:
    """All ordered triplets of ``d`` with every side ≥ ``min_side_m``: (K, 3) idx, (K, 3) sides."""
    combos = np.array(list(combinations(range(len(d)), 3)), dtype=np.int64)
    if len(combos) == 0:
        return np.zeros((0, 3), np.int64), np.zeros((0, 3))
    perms = np.array([[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]])
    idx = combos[:, perms].reshape(-1, 3)
    sides = _sides(d[idx])
    ok = (sides >= min_side_m).all(axis=1)
    return idx[ok], sides[ok]


def _sides(tri: F64) -> F64:
    """Side lengths (|ab|, |bc|, |ca|) of triangles ``(..., 3, 3)``."""
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    return np.stack(
        [
            np.linalg.norm(a - b, axis=-1),
            np.linalg.norm(b - c, axis=-1),
            np.linalg.norm(c - a, axis=-1),
        ],
        axis=-1,
    )


def coarse_align(
    src_m: npt.ArrayLike,
    dst_m: npt.ArrayLike,
    *,
    gate_m: float = 0.04,
    triplet_tolerance_m: float = 0.04,
    min_side_m: float = 0.15,
    n_triplets: int = 400,
    max_hypotheses: int = 10000,
    n_refine: int = 12,
    min_inliers: int = 6,
    seed: int = 0,
) -> AlignmentResult:
    """Rigidly align ``src_m`` onto ``dst_m`` with unknown correspondences and no initial pose.

    RANSAC over distance-invariant triplets: random well-spread source triplets are looked up by
    their three side lengths among all destination triplets (a KD-tree over side-length
    signatures, every vertex order), each match gives a Kabsch hypothesis, hypotheses are scored
    by the truncated squared distance of every source point to its nearest destination point
    (MSAC with ``gate_m``), and the best ``n_refine`` are refined by :func:`trimmed_icp` and
    Hungarian-gated ICP (gates 3, 2, 1 × ``gate_m``). The winner has the most inliers, then the
    lowest RMS.

    Args:
        src_m: Source points ``(N, 3)`` (m), e.g. a camera's markers in its frame; NaN rows are
            ignored. Ghosts and misses are expected.
        dst_m: Destination points ``(M, 3)`` (m), e.g. Vicon markers; NaN rows are ignored.
        gate_m: Inlier distance after alignment (m); ~3σ of the source's 3D noise.
        triplet_tolerance_m: Radius of the side-length signature match (m).
        min_side_m: Shortest triangle side used (m); short sides are ill-conditioned.
        n_triplets: Source triplets sampled.
        max_hypotheses: Cap on scored hypotheses (randomly subsampled beyond it).
        n_refine: Best hypotheses refined by ICP.
        min_inliers: Fewest matched pairs accepted.
        seed: Seed of the sampling (results are deterministic for a seed).

    Raises:
        CalibrationError: too few markers on either side, or no hypothesis with
            ``min_inliers`` inliers (the message says how many it found).
    """
    check_positive(gate_m, name="gate_m")
    check_positive(triplet_tolerance_m, name="triplet_tolerance_m")
    src_all = np.asarray(check_shape(src_m, ["n", 3], name="src_m"), dtype=np.float64)
    dst_all = np.asarray(check_shape(dst_m, ["m", 3], name="dst_m"), dtype=np.float64)
    s_idx = np.flatnonzero(np.isfinite(src_all).all(axis=1))
    d_idx = np.flatnonzero(np.isfinite(dst_all).all(axis=1))
    s, d = src_all[s_idx], dst_all[d_idx]
    need = max(min_inliers, _MIN_PAIRS)
    if len(s) < need or len(d) < need:
        msg = (
            f"coarse alignment needs at least {need} markers on each side; got {len(s)} "
            f"measured and {len(d)} reference markers (too few markers visible?)"
        )
        raise CalibrationError(msg)
    rng = np.random.default_rng(seed)
    d_tri, d_sides = _triplet_table(d, min_side_m)
    if len(d_tri) == 0:
        msg = (
            f"the {len(d)} reference markers span less than {min_side_m} m; cannot align "
            "(wrong units?)"
        )
        raise CalibrationError(msg)
    sig_tree = cKDTree(d_sides)

    # Source triplets: spread out, not collinear.
    tri_src: list[npt.NDArray[np.int64]] = []
    tries = 0
    while len(tri_src) < n_triplets and tries < 50 * n_triplets:
        tries += 1
        abc = rng.choice(len(s), size=3, replace=False)
        p = s[abc]
        sides = _sides(p[None])[0]
        if sides.min() < min_side_m:
            continue
        area2 = np.linalg.norm(np.cross(p[1] - p[0], p[2] - p[0]))
        if area2 < 0.2 * sides.max() ** 2:
            continue
        tri_src.append(abc)
    if not tri_src:
        msg = (
            f"the {len(s)} measured markers have no well-spread triplet (sides ≥ {min_side_m} m); "
            "too few markers visible, or wrong units?"
        )
        raise CalibrationError(msg)
    src_tris = np.array(tri_src, dtype=np.int64)
    hits = sig_tree.query_ball_point(_sides(s[src_tris]), r=triplet_tolerance_m)
    pairs_s = [np.repeat(src_tris[k][None], len(h), axis=0) for k, h in enumerate(hits) if h]
    pairs_d = [d_tri[np.asarray(h, dtype=np.int64)] for h in hits if h]
    if not pairs_s:
        msg = (
            "no triplet of measured markers matches the reference markers' distances within "
            f"{1000 * triplet_tolerance_m:.0f} mm (different marker sets, or wrong units?)"
        )
        raise CalibrationError(msg)
    hyp_s = np.concatenate(pairs_s)
    hyp_d = np.concatenate(pairs_d)
    if len(hyp_s) > max_hypotheses:
        pick = rng.choice(len(hyp_s), size=max_hypotheses, replace=False)
        hyp_s, hyp_d = hyp_s[pick], hyp_d[pick]
    Ts = kabsch_batch(s[hyp_s], d[hyp_d])
    d_tree = cKDTree(d)
    scores = np.empty(len(Ts))
    chunk = max(1, 200_000 // len(s))
    for a in range(0, len(Ts), chunk):
        T = Ts[a : a + chunk]
        moved = np.einsum("hij,nj->hni", T[:, :3, :3], s) + T[:, None, :3, 3]
        dist, _ = d_tree.query(moved.reshape(-1, 3), distance_upper_bound=gate_m)
        dist = np.minimum(dist, gate_m).reshape(len(T), len(s))
        scores[a : a + chunk] = (dist**2).sum(axis=1)
    best_first = np.argsort(scores, kind="stable")
    best: tuple[int, float, F64, I64, I64] | None = None
    seen: list[F64] = []
    for h in best_first:
        if len(seen) >= n_refine:
            break
        T0 = Ts[h]
        if any(
            rotation_error_deg(T0, q) < 2.0 and np.linalg.norm(T0[:3, 3] - q[:3, 3]) < 0.05
            for q in seen
        ):
            continue
        seen.append(T0)
        T1 = trimmed_icp(s, d, T_init=T0, keep_fraction=0.6, max_iterations=20).T
        T2, i, j = _gated_icp(s, d, T1, (3 * gate_m, 2 * gate_m, gate_m))
        if len(i) < 3:
            continue
        rms = float(np.sqrt(np.mean(np.sum((transform_points(T2, s[i]) - d[j]) ** 2, axis=1))))
        if best is None or (len(i), -rms) > (best[0], -best[1]):
            best = (len(i), rms, T2, i, j)
    if best is None or best[0] < need:
        found = 0 if best is None else best[0]
        msg = (
            f"coarse alignment found no pose with {need} markers within {1000 * gate_m:.0f} mm "
            f"(best: {found} of {len(s)} measured); markers too few, too noisy, or not the same "
            "scene"
        )
        raise CalibrationError(msg)
    n, rms, T, i, j = best
    _log.debug("coarse_align: %d hypotheses, %d inliers, rms %.1f mm", len(Ts), n, 1e3 * rms)
    return AlignmentResult(
        T=T,
        src_index=s_idx[i].astype(np.int64),
        dst_index=d_idx[j].astype(np.int64),
        rms_m=rms,
        n_inliers=n,
        n_hypotheses=len(Ts),
    )


# --------------------------------------------------------------------------------------------
# Bundle adjustment (poses only; world points and intrinsics fixed)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class BundleProblem:
    """One camera's matched observations for :func:`bundle_adjust`.

    Attributes:
        points_world_m: Fixed world points ``(N, 3)`` (m), one per observation.
        uv_px: Observed pixels ``(N, 2)``.
        K: ``(3, 3)`` intrinsics (fixed).
        distortion: ``(5,)`` Brown–Conrady coefficients (fixed).
        T_world_cam_init: ``(4, 4)`` starting pose.
        name: Camera label for messages.
    """

    points_world_m: F64 = field(repr=False)
    uv_px: F64 = field(repr=False)
    K: F64 = field(repr=False)
    distortion: F64 = field(repr=False)
    T_world_cam_init: F64 = field(repr=False)
    name: str = "camera"

    def __post_init__(self) -> None:
        p = check_shape(self.points_world_m, ["n", 3], name=f"{self.name} points_world_m")
        check_shape(self.uv_px, [p.shape[0], 2], name=f"{self.name} uv_px")
        check_shape(self.K, [3, 3], name=f"{self.name} K")
        check_shape(self.distortion, [5], name=f"{self.name} distortion")
        check_shape(self.T_world_cam_init, [4, 4], name=f"{self.name} T_world_cam_init")
        for name in ("points_world_m", "uv_px", "K", "distortion", "T_world_cam_init"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64))


@dataclass(frozen=True, slots=True)
class BundleResult:
    """One camera's refined pose and how well it is known.

    Attributes:
        name: Camera label.
        T_world_cam: ``(4, 4)`` refined camera → world (m).
        reprojection_rms_px: RMS reprojection error of the inliers (px).
        inliers: Boolean mask ``(N,)`` of the observations kept by the 3σ rejection.
        residuals_px: Reprojection error norm of every observation at the solution ``(N,)``.
        covariance: ``(6, 6)`` covariance of (rotation vector in rad about the world axes,
            camera centre in m) from the final linear fit.
        rotation_sigma_deg: 1σ of the rotation (largest axis), degrees.
        translation_sigma_mm: 1σ of the camera centre (largest axis), mm.
        sigma_px: Robust scale of the pixel residuals used for the 3σ rejection.
    """

    name: str
    T_world_cam: F64 = field(repr=False)
    reprojection_rms_px: float
    inliers: npt.NDArray[np.bool_] = field(repr=False)
    residuals_px: F64 = field(repr=False)
    covariance: F64 = field(repr=False)
    rotation_sigma_deg: float
    translation_sigma_mm: float
    sigma_px: float

    @property
    def n_inliers(self) -> int:
        """Observations kept."""
        return int(np.count_nonzero(self.inliers))


def _pose_from_params(x: F64, r0: F64) -> tuple[F64, F64]:
    """(R_world_cam, centre) from 6 parameters: a rotation vector about the world axes applied
    to the start rotation ``r0``, and the camera centre (m)."""
    r = Rotation.from_rotvec(x[:3]).as_matrix() @ r0
    return r, x[3:6]


def _solve(
    problems: Sequence[BundleProblem],
    masks: Sequence[npt.NDArray[np.bool_]],
    x0: F64,
    r0s: Sequence[F64],
    *,
    loss: str,
    f_scale: float,
) -> OptimizeResult:
    sizes = [int(np.count_nonzero(m)) for m in masks]
    pts = [p.points_world_m[m] for p, m in zip(problems, masks, strict=True)]
    uvs = [p.uv_px[m] for p, m in zip(problems, masks, strict=True)]

    def fun(x: F64) -> F64:
        out = []
        for c, prob in enumerate(problems):
            r, centre = _pose_from_params(x[6 * c : 6 * c + 6], r0s[c])
            pc = (pts[c] - centre) @ r
            uv = project_camera(pc, prob.K, prob.distortion)
            res = uv - uvs[c]
            out.append(np.nan_to_num(res, nan=1e3).ravel())
        return np.concatenate(out) if out else np.zeros(0)

    n_res = 2 * sum(sizes)
    sparsity = lil_matrix((n_res, 6 * len(problems)), dtype=np.int8)
    row = 0
    for c, n in enumerate(sizes):
        sparsity[row : row + 2 * n, 6 * c : 6 * c + 6] = 1
        row += 2 * n
    return least_squares(
        fun,
        x0,
        jac_sparsity=sparsity,
        loss=loss,
        f_scale=f_scale,
        x_scale="jac",
        method="trf",
        xtol=1e-10,
        ftol=1e-10,
        max_nfev=200,
    )


def bundle_adjust(
    problems: Sequence[BundleProblem],
    *,
    f_scale_px: float = 1.0,
    reject_sigma: float = 3.0,
    min_observations: int = 6,
) -> list[BundleResult]:
    """Refine camera poses with fixed world points and intrinsics (all cameras in one solve).

    ``least_squares`` (TRF) over 6 parameters per camera with a block-diagonal ``jac_sparsity``
    (a camera's residuals depend on its pose only), ``loss="soft_l1"`` with ``f_scale_px``, then
    observations beyond ``reject_sigma`` × the robust residual scale (1.4826·MAD of the residual
    norms, floored at 0.05 px) are rejected and the inliers refitted with a linear loss. The
    covariance is ``σ²·(JᵀJ)⁻¹`` of that refit (σ² = residual sum of squares / dof).

    Raises:
        CalibrationError: a camera has fewer than ``min_observations`` observations (before
            or after rejection); the message names it.
    """
    check_positive(f_scale_px, name="f_scale_px")
    for p in problems:
        if len(p.uv_px) < min_observations:
            msg = (
                f"{p.name}: bundle adjustment needs ≥ {min_observations} matched markers, got "
                f"{len(p.uv_px)} (too few markers visible or matched)"
            )
            raise CalibrationError(msg)
    r0s = [p.T_world_cam_init[:3, :3] for p in problems]
    x0 = np.concatenate([np.r_[np.zeros(3), p.T_world_cam_init[:3, 3]] for p in problems])
    all_in = [np.ones(len(p.uv_px), dtype=bool) for p in problems]
    first = _solve(problems, all_in, x0, r0s, loss="soft_l1", f_scale=f_scale_px)
    masks: list[npt.NDArray[np.bool_]] = []
    scales: list[float] = []
    for c, p in enumerate(problems):
        err = _reprojection_norms(p, first.x[6 * c : 6 * c + 6], r0s[c])
        med = float(np.median(err))
        sigma = max(1.4826 * float(np.median(np.abs(err - med))) + 0.0, 0.05)
        # MAD of a norm is not its σ; use the RMS of the bulk as the scale instead when larger.
        bulk = err[err <= np.percentile(err, 80)]
        sigma = max(sigma, float(np.sqrt(np.mean(bulk**2))) if len(bulk) else sigma)
        keep = err <= reject_sigma * sigma
        if np.count_nonzero(keep) < min_observations:
            msg = (
                f"{p.name}: only {np.count_nonzero(keep)} of {len(err)} observations within "
                f"{reject_sigma}σ = {reject_sigma * sigma:.2f} px; the matches are unreliable"
            )
            raise CalibrationError(msg)
        masks.append(keep)
        scales.append(sigma)
    final = _solve(problems, masks, first.x, r0s, loss="linear", f_scale=1.0)
    jac = final.jac.toarray() if hasattr(final.jac, "toarray") else np.asarray(final.jac)
    results = []
    row = 0
    for c, p in enumerate(problems):
        n = int(np.count_nonzero(masks[c]))
        x = final.x[6 * c : 6 * c + 6]
        r, centre = _pose_from_params(x, r0s[c])
        err = _reprojection_norms(p, x, r0s[c])
        rms = float(np.sqrt(np.mean(err[masks[c]] ** 2)))
        j = jac[row : row + 2 * n, 6 * c : 6 * c + 6]
        res = final.fun[row : row + 2 * n]
        row += 2 * n
        dof = max(2 * n - 6, 1)
        s2 = float(res @ res) / dof
        try:
            cov = s2 * np.linalg.inv(j.T @ j)
        except np.linalg.LinAlgError:
            cov = np.full((6, 6), np.nan)
        rot_sigma = math.degrees(
            math.sqrt(max(float(np.max(np.linalg.eigvalsh(cov[:3, :3]))), 0.0))
        )
        tr_sigma = 1e3 * math.sqrt(max(float(np.max(np.linalg.eigvalsh(cov[3:, 3:]))), 0.0))
        results.append(
            BundleResult(
                name=p.name,
                T_world_cam=_make_T(r, centre),
                reprojection_rms_px=rms,
                inliers=masks[c],
                residuals_px=err,
                covariance=cov,
                rotation_sigma_deg=rot_sigma,
                translation_sigma_mm=tr_sigma,
                sigma_px=scales[c],
            )
        )
    return results


def _reprojection_norms(p: BundleProblem, x: F64, r0: F64) -> F64:
    r, centre = _pose_from_params(x, r0)
    uv = project_camera((p.points_world_m - centre) @ r, p.K, p.distortion)
    err: F64 = np.nan_to_num(np.linalg.norm(uv - p.uv_px, axis=1), nan=1e3)
    return err


def bundle_adjust_camera(
    points_world_m: npt.ArrayLike,
    uv_px: npt.ArrayLike,
    *,
    K: npt.ArrayLike,
    distortion: npt.ArrayLike,
    T_world_cam_init: npt.ArrayLike,
    name: str = "camera",
    f_scale_px: float = 1.0,
    reject_sigma: float = 3.0,
) -> BundleResult:
    """One camera's pose from matched (world point, pixel) pairs; see :func:`bundle_adjust`."""
    prob = BundleProblem(
        points_world_m=np.asarray(points_world_m, dtype=np.float64),
        uv_px=np.asarray(uv_px, dtype=np.float64),
        K=np.asarray(K, dtype=np.float64),
        distortion=np.asarray(distortion, dtype=np.float64),
        T_world_cam_init=np.asarray(T_world_cam_init, dtype=np.float64),
        name=name,
    )
    return bundle_adjust([prob], f_scale_px=f_scale_px, reject_sigma=reject_sigma)[0]


# --------------------------------------------------------------------------------------------
# One camera, end to end
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class CameraRegistration:
    """One camera registered to the reference markers.

    Attributes:
        name: Camera label.
        T_world_cam: ``(4, 4)`` camera → world after bundle adjustment.
        T_world_cam_coarse: ``(4, 4)`` after coarse alignment only (before/after figures).
        coarse_inliers: 3D marker pairs of the coarse alignment.
        coarse_rms_m: Their RMS distance (m).
        bundle: The final bundle adjustment.
        cloud_cam_m: The camera-frame marker cloud that was aligned ``(C, 3)``.
        obs_frame: Frame index of every bundle observation ``(N,)``.
        obs_marker: Reference marker index of every observation ``(N,)``.
        obs_uv_px: Observed pixels ``(N, 2)``.
        n_frames: Frames used.
    """

    name: str
    T_world_cam: F64 = field(repr=False)
    T_world_cam_coarse: F64 = field(repr=False)
    coarse_inliers: int
    coarse_rms_m: float
    bundle: BundleResult = field(repr=False)
    cloud_cam_m: F64 = field(repr=False)
    obs_frame: I64 = field(repr=False)
    obs_marker: I64 = field(repr=False)
    obs_uv_px: F64 = field(repr=False)
    n_frames: int

    def residual_statistics(self) -> dict[str, float]:
        """Plain figures for the calibration file's ``residuals`` table."""
        b = self.bundle
        return {
            "reprojection_rms_px": b.reprojection_rms_px,
            "inliers": float(b.n_inliers),
            "observations": float(len(b.inliers)),
            "markers": float(len(np.unique(self.obs_marker[b.inliers]))),
            "frames": float(self.n_frames),
            "rotation_sigma_deg": b.rotation_sigma_deg,
            "translation_sigma_mm": b.translation_sigma_mm,
            "coarse_inliers": float(self.coarse_inliers),
            "coarse_rms_mm": 1e3 * self.coarse_rms_m,
        }


def static_cloud(
    uv_px_frames: Sequence[npt.ArrayLike],
    xyz_cam_m_frames: Sequence[npt.ArrayLike],
    *,
    track_gate_px: float = 2.0,
    min_depth_samples: int = 2,
) -> F64:
    """Camera-frame marker cloud of a static stretch: blobs tracked by pixel across frames,
    each with the median of its valid depth-derived points; ``(C, 3)`` (m)."""
    if not uv_px_frames:
        return np.zeros((0, 3))
    ref_k = int(np.argmax([len(np.asarray(u)) for u in uv_px_frames]))
    ref = np.asarray(uv_px_frames[ref_k], dtype=np.float64).reshape(-1, 2)
    samples: list[list[F64]] = [[] for _ in range(len(ref))]
    if len(ref) == 0:
        return np.zeros((0, 3))
    tree = cKDTree(ref)
    for uv, xyz in zip(uv_px_frames, xyz_cam_m_frames, strict=True):
        u = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        x = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        if len(u) == 0:
            continue
        dist, j = tree.query(u, distance_upper_bound=track_gate_px)
        for k in np.flatnonzero(np.isfinite(dist)):
            if np.isfinite(x[k]).all():
                samples[int(j[k])].append(x[k])
    out = [np.median(np.array(s), axis=0) for s in samples if len(s) >= min_depth_samples]
    return np.array(out, dtype=np.float64).reshape(-1, 3)


def _match_frame(
    uv: F64, xyz: F64, ref_m: F64, T: F64, K: F64, dist: F64, *, gate_px: float, depth_gate_m: float
) -> tuple[I64, I64]:
    proj, z = project_points(ref_m, T, K, dist)
    ok = np.asarray(np.isfinite(proj).all(axis=1), dtype=np.bool_)
    forbid = None
    if len(xyz):
        zb = xyz[:, 2]
        diff = np.abs(zb[:, None] - z[None, :])
        forbid = np.isfinite(zb)[:, None] & (diff > depth_gate_m)
    proj = np.where(ok[:, None], proj, np.nan)
    return match_markers(uv, proj, gate_m=gate_px, forbid=forbid)


def register_camera(
    uv_px_frames: Sequence[npt.ArrayLike],
    xyz_cam_m_frames: Sequence[npt.ArrayLike],
    reference_m_frames: Sequence[npt.ArrayLike],
    *,
    K: npt.ArrayLike,
    distortion: npt.ArrayLike,
    name: str = "camera",
    static_reference_m: npt.ArrayLike | None = None,
    T_world_cam_init: npt.ArrayLike | None = None,
    coarse_gate_m: float = 0.05,
    gates_px: Sequence[float] = (12.0, 4.0, 2.5),
    depth_gate_m: float = 0.12,
    f_scale_px: float = 1.0,
    areas_px_frames: Sequence[npt.ArrayLike] | None = None,
    min_area_ratio: float = 0.7,
    seed: int = 0,
) -> CameraRegistration:
    """Register one camera to reference (Vicon) markers from several frames.

    Args:
        uv_px_frames: Per frame, the blob centroids ``(N_f, 2)`` (px).
        xyz_cam_m_frames: Per frame, the blobs' camera-frame points ``(N_f, 3)`` (m), NaN where
            the blob had no valid depth.
        reference_m_frames: Per frame, the reference markers at that frame's instant ``(M, 3)``
            (m, world), NaN in gaps; same marker order in every frame.
        K: ``(3, 3)`` intrinsics (fixed).
        distortion: ``(5,)`` distortion (fixed).
        name: Camera label for messages.
        static_reference_m: ``(M, 3)`` reference cloud for the coarse alignment (default: the
            NaN-mean over the frames); the frames should be a static stretch unless
            ``T_world_cam_init`` is given.
        T_world_cam_init: Skip the coarse alignment and start from this pose.
        coarse_gate_m: Inlier gate of the coarse 3D alignment (m).
        gates_px: Matching gates of successive bundle rounds (px), loosest first.
        depth_gate_m: A blob with valid depth never matches a marker whose camera depth differs
            by more than this (m); keeps front and back markers apart.
        f_scale_px: ``soft_l1`` scale of the bundle adjustment (px).
        areas_px_frames: Per frame, the blobs' areas ``(N_f,)`` (px); when given, blobs whose
            area × depth² is below ``min_area_ratio`` × the median (partly occluded markers,
            whose centroids are biased) are left out of the bundle adjustment.
        min_area_ratio: See ``areas_px_frames``.
        seed: Seed of the coarse alignment.

    Raises:
        CalibrationError: too few markers, no alignment, or too few matches (names ``name``).
    """
    n = len(uv_px_frames)
    if n == 0 or len(xyz_cam_m_frames) != n or len(reference_m_frames) != n:
        msg = f"{name}: needs the same, non-zero number of blob and reference frames"
        raise ValidationError(msg)
    Km = np.asarray(check_shape(K, [3, 3], name="K"), dtype=np.float64)
    dist = np.asarray(check_shape(distortion, [5], name="distortion"), dtype=np.float64)
    uvs = [np.asarray(u, dtype=np.float64).reshape(-1, 2) for u in uv_px_frames]
    xyzs = [np.asarray(x, dtype=np.float64).reshape(-1, 3) for x in xyz_cam_m_frames]
    refs = [np.asarray(r, dtype=np.float64) for r in reference_m_frames]
    areas = (
        None
        if areas_px_frames is None
        else [np.asarray(a, dtype=np.float64).reshape(-1) for a in areas_px_frames]
    )
    m = refs[0].shape[0]
    if any(r.shape != (m, 3) for r in refs):
        msg = f"{name}: every reference frame must be (M, 3) with the same M"
        raise ValidationError(msg)
    cloud = static_cloud(uvs, xyzs)
    if T_world_cam_init is None:
        if static_reference_m is None:
            with np.errstate(invalid="ignore"):
                stack = np.stack(refs)
                valid = np.asarray(np.isfinite(stack).all(axis=2), dtype=np.bool_)
                cnt = valid.sum(axis=0)
                static_ref = (
                    np.where(valid[..., None], stack, 0.0).sum(axis=0) / np.maximum(cnt, 1)[:, None]
                )
                static_ref[cnt == 0] = np.nan
        else:
            static_ref = np.asarray(
                check_shape(static_reference_m, [m, 3], name="static_reference_m"), dtype=np.float64
            )
        try:
            coarse = coarse_align(cloud, static_ref, gate_m=coarse_gate_m, seed=seed)
        except CalibrationError as err:
            msg = f"{name}: {err}"
            raise CalibrationError(msg) from err
        T = coarse.T
        coarse_n, coarse_rms = coarse.n_inliers, coarse.rms_m
    else:
        T = np.array(
            check_shape(T_world_cam_init, [4, 4], name="T_world_cam_init"), dtype=np.float64
        )
        coarse_n, coarse_rms = 0, math.nan
    T_coarse = T.copy()
    bundle: BundleResult | None = None
    fr = mk = np.zeros(0, dtype=np.int64)
    uv_obs = np.zeros((0, 2))
    for gate in gates_px:
        fl, ml, ul, al = [], [], [], []
        for f in range(n):
            i, j = _match_frame(
                uvs[f], xyzs[f], refs[f], T, Km, dist, gate_px=gate, depth_gate_m=depth_gate_m
            )
            fl.append(np.full(len(i), f, dtype=np.int64))
            ml.append(j)
            ul.append(uvs[f][i])
            al.append(areas[f][i] if areas is not None else np.full(len(i), np.nan))
        fr = np.concatenate(fl)
        mk = np.concatenate(ml)
        uv_obs = np.concatenate(ul) if ul else np.zeros((0, 2))
        pts = (
            np.stack([refs[f][k] for f, k in zip(fr, mk, strict=True)])
            if len(fr)
            else np.zeros((0, 3))
        )
        if areas is not None and len(fr):
            # A blob partly hidden behind the body is small for its distance and its centroid
            # is biased: keep blobs whose area·Z² is at least min_area_ratio × the median.
            z = (pts - T[:3, 3]) @ T[:3, 2]
            q = np.concatenate(al) * z**2
            keep = ~(q < min_area_ratio * np.nanmedian(q))
            fr, mk, uv_obs, pts = fr[keep], mk[keep], uv_obs[keep], pts[keep]
        prob = BundleProblem(
            points_world_m=pts, uv_px=uv_obs, K=Km, distortion=dist, T_world_cam_init=T, name=name
        )
        bundle = bundle_adjust([prob], f_scale_px=f_scale_px)[0]
        T = bundle.T_world_cam
    if bundle is None:
        msg = f"{name}: gates_px is empty; give at least one matching gate"
        raise ValidationError(msg)
    return CameraRegistration(
        name=name,
        T_world_cam=T,
        T_world_cam_coarse=T_coarse,
        coarse_inliers=coarse_n,
        coarse_rms_m=coarse_rms,
        bundle=bundle,
        cloud_cam_m=cloud,
        obs_frame=fr,
        obs_marker=mk,
        obs_uv_px=uv_obs,
        n_frames=n,
    )
