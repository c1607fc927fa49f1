"""Event-based silhouette refinement of EventCap (stage C, paper Eqs. 9–13).

Per tracking frame ``f``, starting from the batch result ``Ŝ_f``, a few ICP rounds of:

1. rasterise the current pose (:func:`process.eventcap.raster.rasterize`): boundary pixels
   ``s_b``, outward normals ``n_b`` and the surface point ``v_b`` under each (joint-local);
2. find the closest event ``u_b`` of each ``s_b`` (:func:`process.eventcap.event_index.
   closest_events`: 8×8 patch, time window ``[t_f − T_b/2, t_f + T_b/2]``, Eq. 12); boundary
   pixels without one are dropped;
3. minimise ``E_refine = λ_sil·Σ_b (n_bᵀ(π(v_b(S)) − u_b))² + λ_stab·Σ_l ‖J_l(S) − J_l(Ŝ_f)‖²``
   over the 33 pose parameters with ``scipy.optimize.least_squares`` (``"trf"``; the 27 joint
   angles boxed by ``DOF_LIMITS_RAD``, the root free). ``J_l`` are the 19 EventCap keypoints.

Data-term guard. Events alone can degrade a good pose (noise, texture edges, a static body
that fires no silhouette events), so the refined pose replaces ``Ŝ_f`` only when it lowers the
*data term* (:func:`data_terms_px`) by more than ``min_gain_px``: half the mean capped distance
from the rendered boundary pixels to their closest events plus half the mean capped distance
from the window's events near either boundary to the rendered boundary, in pixels. It is
evaluated on *check* events (:func:`split_events` puts every other event of the stream there
and the ICP fits only the others), so an improvement must carry over to events the fit has not
seen: fitting noise lowers the distances to the noise it fitted, not to fresh noise.

Units: pixels for 2D residuals; the stabilisation residuals in ``stab_unit`` (``"cm"`` by
default, not the batch fit's mm: :class:`RefineOptions` says why).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares

from mocaprig.acquire.events import check_events
from mocaprig.calib.camera_model import project_points
from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body.kinematics import (
    clamp_to_limits,
    eventcap_keypoints,
    forward_kinematics,
)
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.body.skeleton import DOF_LIMITS_RAD, POSE_DIM, ROOT_DIM
from mocaprig.process.eventcap.camera import EventCamera
from mocaprig.process.eventcap.event_index import (
    LAMBDA_DIST,
    EventIndex,
    closest_events,
)
from mocaprig.process.eventcap.raster import Raster, rasterize
from mocaprig.validation import check_finite, check_positive, check_shape

__all__ = [
    "FrameWindow",
    "RefineOptions",
    "RefineResult",
    "data_terms_px",
    "refine_frame",
    "refine_frames",
    "split_events",
]

_log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

_UNIT_SCALE: dict[str, float] = {"m": 1.0, "cm": 100.0, "mm": 1000.0}


@dataclass(frozen=True, slots=True)
class RefineOptions:
    """Weights and limits of the refinement (paper values where the paper gives them).

    Attributes:
        lambda_sil: weight of the point-to-line silhouette term (paper 1), px⁻².
        lambda_stab: weight of the keypoint stabilisation term (paper 5).
        stab_unit: unit of the stabilisation residuals; the paper gives none. With ``"mm"`` a
            1 mm shift of all 19 keypoints costs 5·19 = 95 while it moves a silhouette 3 m away
            (f = 200 px) by ~0.07 px, so events cannot correct anything (a 2 cm / 5-6° error
            went from 24.6 to 24.4 mm mean keypoint error); with ``"m"`` the directions a
            single view cannot see (a leg swinging towards the camera) are free and the ICP
            ran off (24.6 -> 153 mm). ``"cm"`` (default) gave 24.6 -> 15.4 mm.
        lambda_dist: weight of the time term of the closest-event distance (paper 4).
        icp_rounds: ICP rounds (paper: typically 4).
        patch_size: side of the closest-event patch, px (paper 8: offsets −4..+3).
        max_nfev: residual evaluations per ICP round's least-squares solve.
        min_matches: fewest matched boundary pixels a round needs; fewer ends the ICP.
        min_gain_px: the refined pose is accepted only if it lowers the data term by more
            than this (px). Refining a true pose against pure noise changed the held-out data
            term by -0.005..+0.035 px (4 seeds), while correcting a 2 cm / 5-6° error from
            boundary events lowered it by about 0.4 px.
        normal_smoothing_px: Gaussian sigma of the signed distance field for the normals, px.
    """

    lambda_sil: float = 1.0
    lambda_stab: float = 5.0
    stab_unit: Literal["m", "cm", "mm"] = "cm"
    lambda_dist: float = LAMBDA_DIST
    icp_rounds: int = 4
    patch_size: int = 8
    max_nfev: int = 30
    min_matches: int = 20
    min_gain_px: float = 0.05
    normal_smoothing_px: float = 1.0

    def __post_init__(self) -> None:
        for name in ("lambda_sil", "lambda_stab", "lambda_dist", "min_gain_px"):
            value = float(getattr(self, name))
            if not (np.isfinite(value) and value >= 0):
                msg = f"RefineOptions.{name} must be a finite number >= 0, got {value!r}"
                raise ValidationError(msg)
        if self.stab_unit not in _UNIT_SCALE:
            msg = f"RefineOptions.stab_unit must be 'm', 'cm' or 'mm', got {self.stab_unit!r}"
            raise ValidationError(msg)
        for name in ("icp_rounds", "patch_size", "max_nfev", "min_matches"):
            if int(getattr(self, name)) < 1:
                msg = f"RefineOptions.{name} must be >= 1, got {getattr(self, name)!r}"
                raise ValidationError(msg)


@dataclass(frozen=True, slots=True)
class FrameWindow:
    """Timing of one tracking frame inside its batch (all µs).

    Attributes:
        t_us: the tracking frame's time ``t_f``.
        batch_t0_us, batch_t1_us: the batch's first and last frame times ``t_0``, ``t_N``; the
            event window is ``t_f ± (t_N − t_0)/2``.
    """

    t_us: int
    batch_t0_us: int
    batch_t1_us: int

    def __post_init__(self) -> None:
        if not int(self.batch_t1_us) > int(self.batch_t0_us):
            msg = (
                f"FrameWindow: batch_t1_us ({self.batch_t1_us}) must be after batch_t0_us "
                f"({self.batch_t0_us})"
            )
            raise ValidationError(msg)

    @property
    def duration_us(self) -> int:
        """Batch duration ``t_N − t_0``, µs."""
        return int(self.batch_t1_us) - int(self.batch_t0_us)


@dataclass(frozen=True, slots=True, eq=False)
class RefineResult:
    """Outcome of refining one frame.

    Attributes:
        pose: the pose to use (33,): the refined pose if accepted, else ``Ŝ_f`` unchanged.
        refined_pose: the ICP result (33,), accepted or not.
        accepted: whether the data-term guard accepted the refined pose.
        data_before_px, data_after_px: data term of ``Ŝ_f`` and of the refined pose, px.
        rounds: ICP rounds run.
        matched: matched boundary pixels in each round.
        seconds: wall time of the refinement, s.
    """

    pose: FloatArray = field(repr=False)
    refined_pose: FloatArray = field(repr=False)
    accepted: bool
    data_before_px: float
    data_after_px: float
    rounds: int
    matched: tuple[int, ...]
    seconds: float


def split_events(events: npt.ArrayLike) -> tuple[npt.NDArray[np.void], npt.NDArray[np.void]]:
    """Split a stream into ``(fit, check)`` events: the even and odd rows of its time order.

    Interleaving keeps both halves spread like the stream (same edges, half the density);
    the refinement fits the first and judges its result on the second.

    Raises:
        ValidationError: not an array of the canonical event dtype.
    """
    ev = check_events(events)
    order = np.argsort(ev["t"], kind="stable")
    return ev[order[0::2]], ev[order[1::2]]


def _check_pose(pose: npt.ArrayLike, name: str) -> FloatArray:
    return np.array(check_finite(check_shape(pose, [POSE_DIM], name=name), name=name), np.float64)


def _match(
    raster: Raster, index: EventIndex, window: FrameWindow, opts: RefineOptions
) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.int64], FloatArray]:
    """Closest events of the boundary pixels: ``(found (B,), uv (B, 2), distance px (B,))``."""
    ce = closest_events(
        index,
        raster.boundary_uv,
        t_ref_us=window.t_us,
        half_window_us=window.duration_us // 2,
        batch_duration_us=window.duration_us,
        lambda_dist=opts.lambda_dist,
        patch_size=opts.patch_size,
    )
    d = np.linalg.norm((ce.uv - raster.boundary_uv).astype(np.float64), axis=-1)
    return ce.found, ce.uv, np.where(ce.found, d, np.inf)


def _window_event_pixels(index: EventIndex, window: FrameWindow) -> npt.NDArray[np.int64]:
    """Pixels ``(E, 2)`` as ``(x, y)`` of the events in the frame's time window."""
    half = window.duration_us // 2
    sel = (index.t_us >= window.t_us - half) & (index.t_us <= window.t_us + half)
    pix = index.key[sel] // index.span_us
    return np.stack([pix % index.width, pix // index.width], axis=-1)


def data_terms_px(
    poses: npt.ArrayLike,
    shape: BodyShape,
    camera: EventCamera,
    index: EventIndex,
    window: FrameWindow,
    *,
    options: RefineOptions | None = None,
) -> FloatArray:
    """The guard's data term of each of P poses (P, 33), px; lower is better.

    ``E_data(S) = ½·(mean_b min(‖u_b − s_b‖, c) + mean_e min(dist(e, ∂S), c))``: the first
    mean runs over S's boundary pixels ``s_b`` and their closest events ``u_b`` (Eq. 12–13;
    ``c`` where the patch holds none), the second over the window's events lying within ``c``
    of the boundary of *any* of the poses (the same events for every pose), with
    ``dist(e, ∂S)`` the distance from the event's pixel to S's nearest boundary pixel. ``c``
    is half the patch size. Both directions are needed: a pose can shorten its boundary (a
    limb folded out of sight) and keep only well-matched boundary pixels, but then the events
    of the hidden edge count against it. With no event near any boundary the second mean is
    ``c``; a pose with no boundary pixel in the image gets NaN.

    Raises:
        ValidationError: bad poses.
    """
    opts = options or RefineOptions()
    q = np.asarray(check_finite(check_shape(poses, ["P", POSE_DIM], name="poses")), np.float64)
    cap = 0.5 * opts.patch_size
    h, w = camera.height, camera.width
    rasters = [rasterize(p, shape, camera, normal_smoothing_px=opts.normal_smoothing_px) for p in q]
    near_any = np.zeros((h, w), dtype=bool)
    dist_maps = []
    for r in rasters:
        edge = np.ones((h, w), dtype=np.uint8)
        edge[r.boundary_uv[:, 1], r.boundary_uv[:, 0]] = 0
        dmap = cv2.distanceTransform(edge, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        dist_maps.append(dmap)
        if r.boundary_uv.shape[0]:
            near_any |= dmap <= cap
    ev = _window_event_pixels(index, window)
    ev = ev[near_any[ev[:, 1], ev[:, 0]]]
    out = np.full(q.shape[0], np.nan)
    for i, (r, dmap) in enumerate(zip(rasters, dist_maps, strict=True)):
        if r.boundary_uv.shape[0] == 0:
            continue
        _, _, d = _match(r, index, window, opts)
        to_events = float(np.mean(np.minimum(d, cap)))
        to_model = float(np.mean(np.minimum(dmap[ev[:, 1], ev[:, 0]], cap))) if ev.size else cap
        out[i] = 0.5 * (to_events + to_model)
    return out


class _Problem:
    """Residuals of E_refine for fixed correspondences (one ICP round)."""

    def __init__(
        self,
        shape: BodyShape,
        camera: EventCamera,
        segment: npt.NDArray[np.int64],
        local_m: FloatArray,
        normals: FloatArray,
        target_uv: FloatArray,
        keypoints_ref: FloatArray,
        opts: RefineOptions,
    ) -> None:
        self.shape = shape
        self.camera = camera
        self.segment = segment
        self.local_m = local_m
        self.normals = normals
        self.target = target_uv
        self.kp_ref = keypoints_ref
        self.w_sil = float(np.sqrt(opts.lambda_sil))
        self.w_stab = float(np.sqrt(opts.lambda_stab)) * _UNIT_SCALE[opts.stab_unit]

    def residuals_batch(self, q: FloatArray) -> FloatArray:
        """Residuals (P, R) of poses (P, 33)."""
        kin = forward_kinematics(q, self.shape)
        rot = kin.rotations[:, self.segment]
        v = kin.positions_m[:, self.segment] + (rot @ self.local_m[:, :, None])[..., 0]
        c = self.camera
        # No depth test: the solver needs finite residuals everywhere.
        uv, _ = project_points(v, c.T_world_cam, c.K, c.distortion, min_depth_m=None)
        r_sil = self.w_sil * np.sum(self.normals * (uv - self.target), axis=-1)
        kp = eventcap_keypoints(kin, self.shape) - self.kp_ref
        r_stab = self.w_stab * kp.reshape(q.shape[0], -1)
        return np.concatenate([r_sil, r_stab], axis=-1)

    def residuals(self, q: FloatArray) -> FloatArray:
        out: FloatArray = self.residuals_batch(q[None])[0]
        return out

    def jacobian(self, q: FloatArray) -> FloatArray:
        """Forward differences, all 33 columns from one batched evaluation."""
        h = _FD_STEP * np.maximum(1.0, np.abs(q))
        # Step inwards at an upper bound so every probe stays inside the box.
        h = np.where(q + h > _UPPER, -h, h)
        probes = np.vstack([q, q + np.diag(h)])
        r = self.residuals_batch(probes)
        out: FloatArray = ((r[1:] - r[0]) / h[:, None]).T
        return out


_FD_STEP = 1e-7
_LOWER = np.concatenate([np.full(ROOT_DIM, -np.inf), DOF_LIMITS_RAD[:, 0]])
_UPPER = np.concatenate([np.full(ROOT_DIM, np.inf), DOF_LIMITS_RAD[:, 1]])


def refine_frame(
    pose: npt.ArrayLike,
    shape: BodyShape,
    camera: EventCamera,
    fit_index: EventIndex,
    window: FrameWindow,
    *,
    check_index: EventIndex | None = None,
    options: RefineOptions | None = None,
) -> RefineResult:
    """Refine one tracking frame's pose against the events (module docstring).

    Args:
        pose: the batch result ``Ŝ_f`` (33,).
        shape: body shape.
        camera: the event camera (sensor size included).
        fit_index: index of the events the ICP fits (the batch window's, or the ``fit`` half
            of :func:`split_events`).
        window: the frame's time and its batch.
        check_index: index of the held-out events the data-term guard is evaluated on;
            ``None`` evaluates it on ``fit_index`` (in-sample: fitted noise then looks like
            an improvement).
        options: weights and limits; defaults to the paper's.

    Returns:
        :class:`RefineResult`.

    Raises:
        ValidationError: bad pose or an index whose sensor size differs from the camera's.
        ProcessingError: the least-squares solve failed.
    """
    started = time.perf_counter()
    opts = options or RefineOptions()
    q_hat = clamp_to_limits(_check_pose(pose, "pose"))
    for name, idx in (("fit_index", fit_index), ("check_index", check_index)):
        if idx is not None and (idx.width, idx.height) != (camera.width, camera.height):
            msg = (
                f"{name} is for a {idx.width}x{idx.height} sensor but the camera is "
                f"{camera.width}x{camera.height}; build the index with the camera's size"
            )
            raise ValidationError(msg)
    check = check_index if check_index is not None else fit_index
    kp_ref = eventcap_keypoints(forward_kinematics(q_hat, shape), shape)
    q = q_hat.copy()
    matched: list[int] = []
    for _ in range(opts.icp_rounds):
        raster = rasterize(q, shape, camera, normal_smoothing_px=opts.normal_smoothing_px)
        found, uv, _ = _match(raster, fit_index, window, opts)
        n = int(np.count_nonzero(found))
        matched.append(n)
        if n < opts.min_matches:
            _log.debug("ICP stops: %d matched boundary pixels < %d", n, opts.min_matches)
            break
        problem = _Problem(
            shape,
            camera,
            raster.boundary_segment[found],
            raster.boundary_local_m[found],
            raster.boundary_normals[found],
            uv[found].astype(np.float64),
            kp_ref,
            opts,
        )
        try:
            sol = least_squares(
                problem.residuals,
                np.clip(q, _LOWER, _UPPER),
                bounds=(_LOWER, _UPPER),
                jac=problem.jacobian,
                method="trf",
                # The exact (SVD) subproblem: 2x faster than LSMR's Python loop here. Its
                # BLAS must run on one thread on a busy machine (run_batch scopes it).
                tr_solver="exact",
                max_nfev=opts.max_nfev,
            )
        except (ValueError, np.linalg.LinAlgError) as err:
            msg = f"refinement at t = {window.t_us} µs: least-squares solve failed ({err})"
            raise ProcessingError(msg) from err
        q = np.asarray(sol.x, dtype=np.float64)
    before, after = (
        float(x)
        for x in data_terms_px(np.stack([q_hat, q]), shape, camera, check, window, options=opts)
    )
    accepted = bool(
        np.isfinite(after) and np.isfinite(before) and after < before - opts.min_gain_px
    )
    _log.debug(
        "frame t = %d µs: data term %.3f -> %.3f px, %s",
        window.t_us,
        before,
        after,
        "accepted" if accepted else "rejected",
    )
    return RefineResult(
        pose=q if accepted else q_hat,
        refined_pose=q,
        accepted=accepted,
        data_before_px=before,
        data_after_px=after,
        rounds=len(matched),
        matched=tuple(matched),
        seconds=time.perf_counter() - started,
    )


def _refine_one(
    args: tuple[
        FloatArray,
        BodyShape,
        EventCamera,
        EventIndex,
        FrameWindow,
        EventIndex | None,
        RefineOptions,
    ],
) -> RefineResult:
    pose, shape, camera, fit, window, check, opts = args
    return refine_frame(pose, shape, camera, fit, window, check_index=check, options=opts)


def refine_frames(
    poses: npt.ArrayLike,
    shape: BodyShape,
    camera: EventCamera,
    fit_index: EventIndex,
    windows: Sequence[FrameWindow],
    *,
    check_index: EventIndex | None = None,
    options: RefineOptions | None = None,
    workers: int = 1,
) -> tuple[RefineResult, ...]:
    """:func:`refine_frame` for each of F frames (independent; ``workers > 1``: a process pool).

    Args:
        poses: batch results (F, 33).
        windows: one :class:`FrameWindow` per frame (F).
        workers: processes; 1 runs in this process.

    Returns:
        F :class:`RefineResult`, in frame order.

    Raises:
        ValidationError: ``poses`` and ``windows`` differ in length, or ``workers < 1``.
    """
    q = np.asarray(check_finite(check_shape(poses, ["F", POSE_DIM], name="poses")), np.float64)
    if len(windows) != q.shape[0]:
        msg = f"poses has {q.shape[0]} frames but windows has {len(windows)}; give one each"
        raise ValidationError(msg)
    check_positive(float(workers), name="workers")
    opts = options or RefineOptions()
    jobs = [(q[i], shape, camera, fit_index, windows[i], check_index, opts) for i in range(len(q))]
    if workers == 1 or len(jobs) <= 1:
        return tuple(_refine_one(j) for j in jobs)
    with ProcessPoolExecutor(max_workers=int(workers)) as pool:
        return tuple(pool.map(_refine_one, jobs))
