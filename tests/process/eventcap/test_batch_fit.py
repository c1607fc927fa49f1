"""Tests of the EventCap hybrid batch fit (paper Eqs. 3–8) on synthetic batches.

A synthetic batch: 41 frames at 1 kHz of the fastest 40 ms of a procedural ``karate`` take, a
240×180 camera 3.5 m away, 100 surface points picked under silhouette pixels at frame 0 and
projected at every frame (exact E_cor correspondences for frames i±1), and noisy detections
at frames 0 and 40 (2D σ 2 px, root-relative 3D σ 20 mm).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from mocaprig.calib.camera_model import project_points
from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body.kinematics import (
    EVENTCAP_KEYPOINTS,
    eventcap_keypoints,
    forward_kinematics,
    within_limits,
)
from mocaprig.process.body.procedural import make_motion
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.body.skeleton import DOF_LIMITS_RAD, DOF_NAMES, JOINT_INDEX, ROOT_DIM
from mocaprig.process.body.surface import capsules, raycast, render_pinhole
from mocaprig.process.eventcap import batch_fit
from mocaprig.process.eventcap.batch_fit import (
    BatchFitOptions,
    BatchFitResult,
    Correspondences,
    FrameDetections,
    fit_batch,
    fit_frame,
    interpolate_poses,
    linear_baseline,
    temporal_weights,
)
from mocaprig.process.eventcap.camera import EventCamera

N = 40
SHAPE = BodyShape.from_height(1.75)


@pytest.fixture(scope="module", autouse=True)
def _one_torch_thread() -> Iterator[None]:
    """The solver's tensors are small: on the shared 2-core test machine, intra-op threads
    spin against the other jobs and make it several times slower, so run on one."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _camera() -> EventCamera:
    """DAVIS240C-like: f = 243 px (4.5 mm lens), 3.5 m in front of the subject, 1 m high."""
    K = np.array([[243.0, 0.0, 119.5], [0.0, 243.0, 89.5], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]  # looks along +Y
    T[:3, 3] = [0.3, -3.5, 1.0]
    return EventCamera(
        K=K,
        T_world_cam=T,
        distortion=np.array([-0.1, 0.02, 0.0, 0.0, 0.0]),
        width=240,
        height=180,
    )


def _keypoints(poses: np.ndarray) -> np.ndarray:
    return eventcap_keypoints(forward_kinematics(poses, SHAPE), SHAPE)


def _mpjpe_mm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-frame mean error (mm) of the 15 body joints, no alignment."""
    ka, kb = _keypoints(a)[..., :15, :], _keypoints(b)[..., :15, :]
    return np.asarray(np.linalg.norm(ka - kb, axis=-1).mean(-1) * 1000.0)


def _pa_mpjpe_mm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-frame mean error (mm) of the 15 body joints after a rigid Procrustes fit (AE)."""
    out = []
    for x, y in zip(_keypoints(a)[:, :15], _keypoints(b)[:, :15], strict=True):
        xc, yc = x - x.mean(0), y - y.mean(0)
        rot, _ = Rotation.align_vectors(yc, xc)
        out.append(np.linalg.norm(rot.apply(xc) - yc, axis=1).mean() * 1000.0)
    return np.array(out)


def _detections(
    rng: np.random.Generator,
    cam: EventCamera,
    pose: np.ndarray,
    frame: int,
    *,
    s2: float,
    s3: float,
) -> FrameDetections:
    kp = _keypoints(pose)
    uv, _ = project_points(kp, cam.T_world_cam, cam.K, cam.distortion)
    p3 = (kp - kp[0]) @ cam.R_world_cam * 1000.0  # root-relative, camera axes, mm
    return FrameDetections(
        frame=frame,
        keypoints2d_px=uv + rng.normal(0.0, s2, uv.shape),
        confidence=np.ones(19),
        keypoints3d_mm=p3 + rng.normal(0.0, s3, p3.shape),
    )


def _tracks(rng: np.random.Generator, cam: EventCamera, poses: np.ndarray, count: int) -> _Tracks:
    """Surface points under random silhouette pixels at frame 0, projected at every frame."""
    kin = forward_kinematics(poses, SHAPE)
    render = render_pinhole(
        capsules(forward_kinematics(poses[0], SHAPE), SHAPE),
        cam.K,
        np.linalg.inv(cam.T_world_cam),
        240,
        180,
    )
    vs, us = np.nonzero(render.segment >= 0)
    pick = rng.choice(us.size, count, replace=False)
    u, v = us[pick], vs[pick]
    ray = np.linalg.solve(cam.K, np.stack([u, v, np.ones(count)]).astype(float)).T
    world = (ray * render.depth_m[v, u][:, None]) @ cam.R_world_cam.T + cam.T_world_cam[:3, 3]
    seg = render.segment[v, u].astype(np.int64)
    local = np.einsum("hji,hj->hi", kin.rotations[0, seg], world - kin.positions_m[0, seg])
    x = np.einsum("fhij,hj->fhi", kin.rotations[:, seg], local) + kin.positions_m[:, seg]
    pixels, _ = project_points(x, cam.T_world_cam, cam.K, cam.distortion)  # (F, H, 2)
    return _Tracks(pixels_px=pixels, segment=seg, local_m=local)


@dataclass(frozen=True)
class _Tracks:
    pixels_px: np.ndarray  # (F, H, 2)
    segment: np.ndarray  # (H,) true segment
    local_m: np.ndarray  # (H, 3) true point in the segment frame


def _rows(n: int, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(frame_i, frame_j, track) of every E_cor pair: i in 1..n-1, j = i ± 1."""
    ii = np.repeat(np.arange(1, n), 2)
    jj = ii + np.tile([-1, 1], n - 1)
    return np.repeat(ii, count), np.repeat(jj, count), np.tile(np.arange(count), ii.size)


def _exact_correspondences(tracks: _Tracks) -> Correspondences:
    """The true surface points (associated at the true poses)."""
    n, count = tracks.pixels_px.shape[0] - 1, tracks.segment.size
    fi, fj, h = _rows(n, count)
    return Correspondences(
        frame_i=fi,
        frame_j=fj,
        segment=tracks.segment[h],
        local_m=tracks.local_m[h],
        target_px=tracks.pixels_px[fj, h],
        weight=np.ones(fi.size),
    )


def _associate(cam: EventCamera, pixels: np.ndarray, poses: np.ndarray) -> Correspondences:
    """What the rasteriser does: the surface under each tracked pixel of frame i at pose S_i
    (rays that graze a capsule, |cos| < 0.5, are dropped as unreliable)."""
    n, count = pixels.shape[0] - 1, pixels.shape[1]
    centre = cam.T_world_cam[:3, 3]
    seg = np.full((n + 1, count), -1)
    local = np.zeros((n + 1, count, 3))
    for i in range(1, n):
        kin = forward_kinematics(poses[i], SHAPE)
        caps = capsules(kin, SHAPE)
        und = cv2.undistortPoints(pixels[i].reshape(-1, 1, 2), cam.K, cam.distortion)
        d = np.column_stack([und.reshape(-1, 2), np.ones(count)]) @ cam.R_world_cam.T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        depth, cid, normal = raycast(np.repeat(centre[None], count, 0), d, caps)
        ok = (cid >= 0) & (np.abs((normal * d).sum(1)) > 0.5)
        s = caps.joint[cid[ok]]
        x = centre + d[ok] * depth[ok, None]
        seg[i, ok] = s
        local[i, ok] = np.einsum("hji,hj->hi", kin.rotations[s], x - kin.positions_m[s])
    fi, fj, h = _rows(n, count)
    keep = seg[fi, h] >= 0
    fi, fj, h = fi[keep], fj[keep], h[keep]
    return Correspondences(
        frame_i=fi,
        frame_j=fj,
        segment=seg[fi, h],
        local_m=local[fi, h],
        target_px=pixels[fj, h],
        weight=np.ones(fi.size),
    )


@dataclass(frozen=True)
class _Batch:
    truth: np.ndarray
    camera: EventCamera
    correspondences: Correspondences  # exact
    detections: tuple[FrameDetections, FrameDetections]
    exact: BatchFitResult  # exact associations ("fixed" model)
    realistic: BatchFitResult  # associated at the initial poses, noisy tracks ("relative")
    linear: np.ndarray


def _curved_window(seed: int, n: int = N) -> np.ndarray:
    """The n+1 frames (1 kHz) of a karate take where the joints stray furthest from the
    straight line between the window's ends (what linear interpolation misses)."""
    rng = np.random.default_rng(seed)
    motion = make_motion("karate", seconds=3.0, rng=rng, rate_hz=1000.0, shape=SHAPE)
    kp = _keypoints(motion.poses)[:, :15]
    s = np.linspace(0.0, 1.0, n + 1)[:, None, None]
    starts = np.arange(0, kp.shape[0] - n, 5)
    dev = [
        np.linalg.norm(kp[a : a + n + 1] - (kp[a] + s * (kp[a + n] - kp[a])), axis=-1).mean()
        for a in starts
    ]
    a = int(starts[int(np.argmax(dev))])
    return np.array(motion.poses[a : a + n + 1])


@pytest.fixture(scope="module")
def batch() -> _Batch:
    rng = np.random.default_rng(11)
    truth = _curved_window(0)
    cam = _camera()
    tracks = _tracks(rng, cam, truth, 100)
    cor = _exact_correspondences(tracks)
    dets = (
        _detections(rng, cam, truth[0], 0, s2=2.0, s3=20.0),
        _detections(rng, cam, truth[N], N, s2=2.0, s3=20.0),
    )
    exact = fit_batch(
        cor, dets, cam, SHAPE, n=N, options=BatchFitOptions(correspondence_model="fixed")
    )
    linear = linear_baseline(dets[0], dets[1], cam, SHAPE, n=N)
    noisy = tracks.pixels_px + rng.normal(0.0, 0.3, tracks.pixels_px.shape)
    realistic = fit_batch(
        _associate(cam, noisy, linear), dets, cam, SHAPE, n=N, initial_poses=linear
    )
    return _Batch(truth, cam, cor, dets, exact, realistic, linear)


# --- the batch fit --------------------------------------------------------------------------


@pytest.mark.slow
def test_batch_fit_with_exact_associations_recovers_poses_far_better_than_linear(
    batch: _Batch,
) -> None:
    fit = _mpjpe_mm(batch.exact.poses, batch.truth)
    lin = _mpjpe_mm(batch.linear, batch.truth)
    ends = _mpjpe_mm(interpolate_poses(batch.truth[0], batch.truth[N], n=N), batch.truth)
    mid_fit, mid_lin = float(fit[1:-1].mean()), float(lin[1:-1].mean())
    print(
        f"MPJPE frames 1..39: exact-association fit {mid_fit:.1f} mm, linear baseline "
        f"{mid_lin:.1f} mm (linear between the true ends: {ends[1:-1].mean():.1f} mm)"
    )
    assert mid_fit < 10.0
    assert mid_fit < 0.3 * mid_lin
    assert fit.max() < 30.0
    assert batch.exact.poses.shape == (N + 1, 33)


def test_batch_fit_with_associations_at_the_initial_poses_is_no_worse_than_linear(
    batch: _Batch,
) -> None:
    # Tracks with 0.3 px noise, looked up on the body at the linear-baseline poses. The error
    # is dominated by the end detections (2 px, 20 mm), which the events cannot correct, so
    # the gain is small on this seed (PA-MPJPE x0.83-0.98 of linear over three seeds).
    fit = _mpjpe_mm(batch.realistic.poses, batch.truth)[1:-1].mean()
    lin = _mpjpe_mm(batch.linear, batch.truth)[1:-1].mean()
    fit_pa = _pa_mpjpe_mm(batch.realistic.poses, batch.truth)[1:-1].mean()
    lin_pa = _pa_mpjpe_mm(batch.linear, batch.truth)[1:-1].mean()
    print(
        f"frames 1..39, realistic fit vs linear: MPJPE {fit:.1f} vs {lin:.1f} mm, "
        f"PA-MPJPE {fit_pa:.1f} vs {lin_pa:.1f} mm"
    )
    assert fit_pa < lin_pa
    assert fit < 1.05 * lin


@pytest.mark.parametrize(("which", "drop"), [("exact", 0.2), ("realistic", 0.95)])
def test_batch_fit_energy_never_increases_and_converges(
    batch: _Batch, which: str, drop: float
) -> None:
    res: BatchFitResult = getattr(batch, which)
    history = np.array(res.energy_history)
    assert np.all(np.diff(history) <= 0.0)
    assert history[0] == pytest.approx(res.initial_energy.total)
    assert history[-1] == pytest.approx(res.final_energy.total)
    assert res.final_energy.total < drop * res.initial_energy.total
    assert res.converged
    assert 1 <= res.iterations <= BatchFitOptions().max_iterations
    assert res.seconds > 0.0


def test_batch_fit_matches_exact_tracks(batch: _Batch) -> None:
    assert batch.exact.final_energy.cor < 0.05 * batch.exact.initial_energy.cor


def test_batch_fit_angles_stay_within_limits(batch: _Batch) -> None:
    assert within_limits(batch.exact.poses).all()
    assert within_limits(batch.realistic.poses).all()
    assert within_limits(batch.linear).all()


def test_batch_fit_auxiliary_translation_places_the_root(batch: _Batch) -> None:
    # t′ (one, shared) ≈ the pelvis position at the detection frames (P3D is pelvis-centred).
    pelvis = _keypoints(batch.truth[[0, N]])[:, 0]
    assert batch.exact.translation_3d_m.shape == (1, 3)
    assert np.linalg.norm(batch.exact.translation_3d_m[0] - pelvis.mean(0)) < 0.08


def test_batch_fit_per_detection_translation_gives_one_t_per_frame(batch: _Batch) -> None:
    opt = BatchFitOptions(
        translation_3d="per_detection", max_iterations=3, correspondence_model="fixed"
    )
    res = fit_batch(
        batch.correspondences,
        batch.detections,
        batch.camera,
        SHAPE,
        n=N,
        initial_poses=batch.exact.poses,
        options=opt,
    )
    pelvis = _keypoints(batch.truth[[0, N]])[:, 0]
    assert res.translation_3d_m.shape == (2, 3)
    assert np.linalg.norm(res.translation_3d_m - pelvis, axis=1).max() < 0.08
    assert res.final_energy.total <= res.initial_energy.total


def test_batch_fit_does_not_modify_its_inputs(batch: _Batch) -> None:
    init = np.array(batch.linear)
    init[5, ROOT_DIM + 3] = 3.0  # beyond a limit: clipped in the solver's copy only
    before = init.copy()
    fit_batch(
        batch.correspondences,
        batch.detections,
        batch.camera,
        SHAPE,
        n=N,
        initial_poses=init,
        options=BatchFitOptions(max_iterations=1),
    )
    np.testing.assert_array_equal(init, before)


def test_batch_fit_reassociates_at_the_current_poses_between_rounds() -> None:
    rng = np.random.default_rng(9)
    truth = _curved_window(3, n=8)
    cam = _camera()
    pixels = _tracks(rng, cam, truth, 30).pixels_px
    dets = [
        _detections(rng, cam, truth[0], 0, s2=1.0, s3=10.0),
        _detections(rng, cam, truth[8], 8, s2=1.0, s3=10.0),
    ]
    init = interpolate_poses(truth[0], truth[8], n=8)
    seen: list[np.ndarray] = []

    def reassociate(poses: np.ndarray) -> Correspondences:
        seen.append(poses.copy())
        return _associate(cam, pixels, poses)

    res = fit_batch(
        _associate(cam, pixels, init),
        dets,
        cam,
        SHAPE,
        n=8,
        initial_poses=init,
        reassociate=reassociate,
        rounds=3,
    )
    assert len(seen) == 2
    assert seen[0].shape == (9, 33)
    assert np.abs(seen[0] - init).max() > 1e-4  # round 2 looks up at the round-1 poses
    assert np.abs(seen[1] - seen[0]).max() > 0.0
    assert res.energy_history[-1] <= res.energy_history[0]


# --- Jacobian blocks ------------------------------------------------------------------------


def _small_problem(
    robust: str, model: str, *, step: int = 10, reach: int = 1
) -> tuple[batch_fit._Problem, batch_fit._State]:
    """5 frames 10 ms apart (or more, closer), E_cor pairs ``reach`` frames apart."""
    rng = np.random.default_rng(3)
    truth = _curved_window(1)[::step]
    n = len(truth) - 1
    cam = _camera()
    cor = _exact_correspondences(_tracks(rng, cam, truth, 6))
    if reach != 1:
        fj = np.clip(cor.frame_i + reach * (cor.frame_j - cor.frame_i), 0, n)
        cor = dataclasses.replace(cor, frame_j=fj)
    dets = [
        _detections(rng, cam, truth[0], 0, s2=3.0, s3=30.0),
        _detections(rng, cam, truth[n], n, s2=3.0, s3=30.0),
    ]
    opt = BatchFitOptions(
        robust=robust,  # type: ignore[arg-type]
        correspondence_model=model,  # type: ignore[arg-type]
        translation_3d="per_detection",
        huber_2d_px=2.0,
    )
    phi = np.where(np.arange(15) % 2 == 0, 1.0, 0.3)
    start = truth + rng.normal(0.0, 0.05, truth.shape)  # residuals of every term are non-zero
    start[:, ROOT_DIM:] = np.clip(start[:, ROOT_DIM:], DOF_LIMITS_RAD[:, 0], DOF_LIMITS_RAD[:, 1])
    prob = batch_fit._Problem(
        num_frames=n + 1,
        correspondences=cor,
        detections=dets,
        camera=cam,
        shape=SHAPE,
        options=opt,
        phi=phi,
        association_poses=truth,  # anchors off the start state: E_cor is non-zero too
    )
    state = batch_fit._state_from_poses(start, rng.normal(0.0, 0.05, (2, 3)))
    return prob, state


@pytest.mark.parametrize(("robust", "model"), [("none", "relative"), ("huber", "fixed")])
def test_normal_equations_match_dense_autograd_jacobian(robust: str, model: str) -> None:
    prob, state = _small_problem(robust, model)
    h, g, terms = prob.normal_equations(state)
    # IRLS weights at the current state, held fixed, as the solver does.
    zero_q = prob.quantities(state, torch.zeros(33, dtype=torch.float64))
    raw = prob.raw_residuals(state, zero_q, torch.zeros_like(state.tprime))
    _, weights = prob.weights(raw)

    def residuals(delta: torch.Tensor, dt: torch.Tensor) -> torch.Tensor:
        q = prob.quantities(state, delta)
        r = prob.raw_residuals(state, q, dt)
        return torch.cat(
            [
                (ri * torch.sqrt(wi)[..., None]).reshape(-1)
                for ri, wi in zip(r, weights, strict=True)
            ]
        )

    delta0 = torch.zeros(5, 33, dtype=torch.float64)
    dt0 = torch.zeros(2, 3, dtype=torch.float64)
    j_frames, j_t = torch.func.jacrev(residuals, argnums=(0, 1))(delta0, dt0)
    jac = torch.cat([j_frames.reshape(j_frames.shape[0], -1), j_t.reshape(j_t.shape[0], -1)], 1)
    r0 = residuals(delta0, dt0)
    h_ref, g_ref = jac.T @ jac, jac.T @ r0
    scale = float(h_ref.abs().max())
    assert float((h - h_ref).abs().max()) < 1e-9 * scale
    assert float((g - g_ref).abs().max()) < 1e-9 * float(g_ref.abs().max())
    if robust == "none":
        assert float(r0 @ r0) == pytest.approx(terms.total, rel=1e-12)
    # The frame blocks two apart are zero: the structure is block-tridiagonal plus t′.
    assert float(h[0:33, 66:99].abs().max()) == 0.0


@pytest.mark.parametrize(("model", "reach"), [("relative", 1), ("fixed", 1), ("relative", 3)])
def test_the_banded_solve_of_a_batch_matches_the_dense_one(model: str, reach: int) -> None:
    prob, state = _small_problem("huber", model, step=2, reach=reach)  # 21 frames: a band
    assert prob.frame_reach == reach
    h, g, _ = prob.normal_equations(state)
    d = torch.diagonal(h)
    d = torch.clamp(d, min=1e-6 * float(d.max()))  # as the solver damps: unseen DoFs too
    for mu in (1e-3, 10.0):
        a = h + torch.diag(mu * d)
        dense = torch.linalg.solve(a, -g)
        banded = prob.solve(a, -g)
        assert banded is not None
        assert float((banded - dense).abs().max()) < 1e-8 * float(dense.abs().max())
    indefinite = h.clone()
    indefinite[40, 40] = -1.0
    assert prob.solve(indefinite, -g) is None  # the solver then damps more
    bad_t = h.clone()
    bad_t[-1, -1] = -1.0
    assert prob.solve(bad_t, -g) is None


# --- the per-frame fit and its helpers ------------------------------------------------------


def test_fit_frame_recovers_a_pose_from_exact_detections() -> None:
    rng = np.random.default_rng(5)
    truth = _curved_window(2)[20]
    cam = _camera()
    det = _detections(rng, cam, truth, 0, s2=0.0, s3=0.0)
    res = fit_frame(det, cam, SHAPE)
    err = float(_mpjpe_mm(res.pose, truth))
    print(f"per-frame fit on exact detections: MPJPE {err:.2f} mm in {res.seconds:.2f} s")
    assert err < 5.0
    assert res.translation_3d_m is not None
    assert res.energy.d2 < 1.0


@pytest.mark.parametrize("with_3d", [True, False])
def test_independent_frames_solved_at_once_match_one_solve_each(with_3d: bool) -> None:
    # fit_frame's root stage solves its candidates as the frames of one problem; each must
    # come out as its own single-frame solve would (same damping path, stop and state).
    rng = np.random.default_rng(11)
    cam = _camera()
    poses = _curved_window(3)[[0, 13, 26, 39]].copy()
    det = _detections(rng, cam, poses[1], 0, s2=1.5, s3=15.0)
    if not with_3d:
        det = FrameDetections(frame=0, keypoints2d_px=det.keypoints2d_px, confidence=det.confidence)
    starts = poses + rng.normal(0.0, 0.15, poses.shape) * (np.arange(33) < 6)
    starts[:, 3:6] += rng.normal(0.0, 0.3, (len(starts), 3))
    opts = BatchFitOptions(translation_3d="per_detection")
    lm: dict[str, Any] = {"max_iterations": 40, "rtol": 1e-8, "mu_init": 1e-3}

    def problem(count: int) -> batch_fit._Problem:
        prob = batch_fit._Problem(
            num_frames=count,
            correspondences=Correspondences.empty(),
            detections=[dataclasses.replace(det, frame=k) for k in range(count)],
            camera=cam,
            shape=SHAPE,
            options=opts,
            phi=np.zeros(15),
            association_poses=np.zeros((count, 33)),
        )
        free = torch.zeros(count, 33, dtype=torch.bool)
        free[:, :6] = True
        prob.free = torch.cat([free.reshape(-1), torch.ones(3 * prob.T, dtype=torch.bool)])
        return prob

    many = problem(len(starts))
    state = batch_fit._state_from_poses(starts, batch_fit._closed_form_tprime(many, starts))
    together = batch_fit._levenberg_marquardt_frames(many, state, **lm)
    one = problem(1)
    for k, out in enumerate(together):
        s = starts[k : k + 1]
        alone = batch_fit._levenberg_marquardt(
            one, batch_fit._state_from_poses(s, batch_fit._closed_form_tprime(one, s)), **lm
        )
        assert out.iterations == alone.iterations
        assert out.converged == alone.converged
        assert len(out.history) == len(alone.history)
        np.testing.assert_allclose(out.history, alone.history, rtol=1e-9)
        np.testing.assert_allclose(out.state.poses(), alone.state.poses(), atol=1e-9)
        np.testing.assert_allclose(out.state.tprime, alone.state.tprime, atol=1e-9)
        assert out.final.total == pytest.approx(alone.final.total, rel=1e-9)
    assert len({o.iterations for o in together}) > 1  # the frames stopped at their own times


def test_solving_frames_at_once_refuses_coupled_frames() -> None:
    cam = _camera()
    det = _detections(np.random.default_rng(1), cam, _curved_window(2)[0], 0, s2=0.0, s3=0.0)
    prob = batch_fit._Problem(
        num_frames=2,
        correspondences=Correspondences.empty(),
        detections=[dataclasses.replace(det, frame=k) for k in range(2)],
        camera=cam,
        shape=SHAPE,
        options=BatchFitOptions(),  # one t′ shared by both frames
        phi=np.zeros(15),
        association_poses=np.zeros((2, 33)),
    )
    poses = np.zeros((2, 33))
    state = batch_fit._state_from_poses(poses, np.zeros((1, 3)))
    with pytest.raises(ValidationError, match="independent"):
        batch_fit._levenberg_marquardt_frames(
            prob, state, max_iterations=5, rtol=1e-8, mu_init=1e-3
        )


def test_fit_frame_without_3d_fits_the_2d_keypoints() -> None:
    # Monocular 2D alone leaves depth and limb flips ambiguous (EventCap always has 3D), so
    # only the image fit is checked, not the pose.
    rng = np.random.default_rng(6)
    truth = _curved_window(2)[0]
    cam = _camera()
    det = _detections(rng, cam, truth, 0, s2=0.0, s3=0.0)
    det2 = FrameDetections(frame=0, keypoints2d_px=det.keypoints2d_px, confidence=det.confidence)
    res = fit_frame(det2, cam, SHAPE)
    assert res.translation_3d_m is None
    assert res.energy.d3 == 0.0
    uv, _ = project_points(_keypoints(res.pose), cam.T_world_cam, cam.K, cam.distortion)
    assert np.median(np.linalg.norm(uv - det.keypoints2d_px, axis=1)) < 1.0


def test_fit_frame_respects_joint_limits_when_detections_exceed_them() -> None:
    rng = np.random.default_rng(7)
    pose = _curved_window(2)[0]
    knee = ROOT_DIM + DOF_NAMES.index("right_knee_flexion")
    pose[knee] = -0.6  # hyperextended: 34° past the limit
    cam = _camera()
    res = fit_frame(_detections(rng, cam, pose, 0, s2=0.0, s3=0.0), cam, SHAPE)
    assert within_limits(res.pose).all()
    assert res.pose[knee] == pytest.approx(DOF_LIMITS_RAD[DOF_NAMES.index("right_knee_flexion")][0])


def test_linear_baseline_interpolates_the_two_frame_fits(batch: _Batch) -> None:
    a = fit_frame(batch.detections[0], batch.camera, SHAPE)
    b = fit_frame(batch.detections[1], batch.camera, SHAPE)
    np.testing.assert_allclose(batch.linear[0], a.pose, atol=1e-12)
    np.testing.assert_allclose(batch.linear[-1], b.pose, atol=1e-12)
    np.testing.assert_allclose(batch.linear[20, 3:], 0.5 * (a.pose[3:] + b.pose[3:]), atol=1e-12)


def test_interpolate_poses_slerps_the_root_and_keeps_the_ends() -> None:
    a = np.zeros(33)
    b = np.zeros(33)
    a[:3] = [0.0, 0.0, 2.5]
    b[:3] = [0.0, 0.0, -2.5]  # the short way round is through π, not through 0
    b[3:6] = [1.0, 2.0, 3.0]
    b[ROOT_DIM + 21] = 1.0
    out = interpolate_poses(a, b, n=4)
    assert out.shape == (5, 33)
    np.testing.assert_array_equal(out[0], a)
    np.testing.assert_array_equal(out[-1], b)
    mid = Rotation.from_rotvec(out[2, :3])
    assert mid.magnitude() == pytest.approx(np.pi, abs=1e-9)
    np.testing.assert_allclose(out[1, 3:6], [0.25, 0.5, 0.75], atol=1e-12)
    np.testing.assert_allclose(out[:, ROOT_DIM + 21], np.linspace(0.0, 1.0, 5), atol=1e-12)


def test_temporal_weights_free_only_the_joints_next_to_observed_bones() -> None:
    forearm = JOINT_INDEX["RightForeArm"]
    cor = Correspondences(
        frame_i=np.array([1, 1, 2]),
        frame_j=np.array([0, 2, 1]),
        segment=np.array([forearm, forearm, JOINT_INDEX["LeftUpLeg"]]),
        local_m=np.zeros((3, 3)),
        target_px=np.zeros((3, 2)),
        weight=np.array([1.0, 1.0, 0.0]),  # the thigh row has τ = 0: it observes nothing
    )
    phi = temporal_weights(cor)
    moving = {EVENTCAP_KEYPOINTS[i] for i in np.flatnonzero(phi == 0.0)}
    assert moving == {"right_elbow", "right_wrist"}
    assert phi.shape == (15,)
    assert temporal_weights(cor, min_points=3).min() == 1.0


# --- validation -----------------------------------------------------------------------------


def test_fit_batch_rejects_frames_outside_the_batch(batch: _Batch) -> None:
    with pytest.raises(ValidationError, match="outside the batch"):
        fit_batch(batch.correspondences, batch.detections, batch.camera, SHAPE, n=20)


def test_fit_batch_needs_end_detections_without_initial_poses(batch: _Batch) -> None:
    with pytest.raises(ValidationError, match="frames 0 and 40"):
        fit_batch(Correspondences.empty(), batch.detections[:1], batch.camera, SHAPE, n=N)


def test_fit_batch_reports_points_in_the_camera_centre_plane(batch: _Batch) -> None:
    T = np.array(batch.camera.T_world_cam)
    T[:3, 3] = 0.0  # the camera sits at the Hips of the all-zero poses below
    cam = EventCamera(
        K=batch.camera.K, T_world_cam=T, distortion=np.zeros(5), width=240, height=180
    )
    with pytest.raises(ProcessingError, match="camera's centre plane"):
        fit_batch(
            Correspondences.empty(),
            batch.detections,
            cam,
            SHAPE,
            n=N,
            initial_poses=np.zeros((N + 1, 33)),
        )


def test_records_reject_bad_values() -> None:
    with pytest.raises(ValidationError, match="negative"):
        Correspondences(
            frame_i=np.array([1]),
            frame_j=np.array([0]),
            segment=np.array([3]),
            local_m=np.zeros((1, 3)),
            target_px=np.zeros((1, 2)),
            weight=np.array([-1.0]),
        )
    with pytest.raises(ValidationError, match="frame_i == frame_j"):
        Correspondences(
            frame_i=np.array([1]),
            frame_j=np.array([1]),
            segment=np.array([3]),
            local_m=np.zeros((1, 3)),
            target_px=np.zeros((1, 2)),
            weight=np.array([1.0]),
        )
    with pytest.raises(ValidationError, match="keypoints2d_px"):
        FrameDetections(frame=0, keypoints2d_px=np.zeros((15, 2)), confidence=np.ones(19))
    with pytest.raises(ValidationError, match="T_world_cam"):
        EventCamera(
            K=np.eye(3), T_world_cam=np.eye(3), distortion=np.zeros(5), width=240, height=180
        )
    with pytest.raises(ValidationError, match="robust"):
        BatchFitOptions(robust="cauchy")  # type: ignore[arg-type]
    with pytest.raises(ValidationError, match="at least 4"):
        fit_frame(
            FrameDetections(frame=0, keypoints2d_px=np.zeros((19, 2)), confidence=np.zeros(19)),
            _camera(),
            SHAPE,
        )
