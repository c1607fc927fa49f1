"""Registration core: coarse alignment, ICP, gated matching, bundle adjustment, one camera.

Synthetic observations follow the mock D415's noise model (docs/simulated-world.md "The mock
D415"): blob centroids with 0.15 px noise; per-frame depth invalid on 60 % of marker blobs, an
outlier (σ 5 cm) on 15 %, else σZ = Z²·0.08 px/(f·B); markers facing away (> 75° from the
camera) are unseen, 10 % more are occluded, 3 % missed per frame, and 5 % ghost blobs. The marker
cloud is the simulated actor's T-pose (53 markers + 2 clapperboard markers).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import pytest
from scipy.spatial.transform import Rotation

from mocaprig.calib.registration import (
    BundleProblem,
    bundle_adjust,
    bundle_adjust_camera,
    coarse_align,
    kabsch,
    match_markers,
    project_points,
    register_camera,
    rotation_error_deg,
    transform_points,
    trimmed_icp,
)
from mocaprig.drivers_mock import build_scenario, look_at
from mocaprig.errors import CalibrationError

F64 = npt.NDArray[np.float64]

#: Acceptance (issue 6): < 0.1° and < 2 mm per camera, ≥ 95 % of 20 seeds.
ROT_OK_DEG = 0.1
TRANS_OK_MM = 2.0


#: Distinct simulated actors (bodies, marker placements); rig poses vary with every seed.
N_ACTORS = 4
N_FRAMES = 20


@functools.cache
def _actor(body_seed: int) -> tuple[F64, F64]:
    """(markers (F, 55, 3), outward normals (F, 55, 3)) of a T-pose over N_FRAMES at 30 Hz."""
    sc = build_scenario("tpose", seed=body_seed, seconds=3.0)
    ws = sc.sample((np.arange(N_FRAMES) * (1e9 / 30) + 1e8).astype(np.int64))
    ref = np.concatenate([ws.markers_m, ws.clapper_m], axis=1)
    normals = np.concatenate([ws.marker_normals, np.zeros((N_FRAMES, 2, 3))], axis=1)
    return ref, normals


def _tpose_cloud(seed: int) -> F64:
    cloud: F64 = _actor(seed % N_ACTORS)[0][0]
    return cloud


def _random_pose(rng: np.random.Generator, cloud: F64) -> F64:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.uniform(-2, 2, 3)
    return T


@dataclass
class _Views:
    uv: list[F64]
    xyz: list[F64]
    refs: list[F64]
    K: F64
    T: F64


def _synth_camera(seed: int, *, ghost_fraction: float = 0.05) -> _Views:
    rng = np.random.default_rng(1000 + seed)
    ref, normals = _actor(seed % N_ACTORS)
    n_frames = N_FRAMES
    az = rng.uniform(0, 2 * np.pi)
    rad = rng.uniform(2.0, 3.2)
    eye = np.array([rad * np.cos(az), rad * np.sin(az), rng.uniform(0.8, 2.0)])
    T = look_at(eye, np.array([0.0, 0.0, 0.9]) + rng.normal(0, 0.1, 3))
    roll = np.radians(rng.uniform(-3, 3))
    T[:3, :3] = T[:3, :3] @ Rotation.from_rotvec([0, 0, roll]).as_matrix()
    f = 623.0 * rng.uniform(0.995, 1.005)
    K = np.array([[f, 0, 424 + rng.uniform(-2, 2)], [0, f, 240 + rng.uniform(-2, 2)], [0, 0, 1.0]])
    to_cam = eye - ref[0]
    to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
    facing = np.einsum("ij,ij->i", normals[0], to_cam) > math.cos(math.radians(75))
    facing[53:] = True
    visible = facing & (rng.random(len(facing)) >= 0.10)
    n_ghost = max(1, round(ghost_fraction * visible.sum()))
    ghost_uv = np.c_[rng.uniform(0, 848, n_ghost), rng.uniform(0, 480, n_ghost)]
    ghost_z = rng.uniform(1.0, 4.0, n_ghost)
    uvs, xyzs, refs = [], [], []
    for k in range(n_frames):
        uv, z = project_points(ref[k], T, K, np.zeros(5))
        inside = visible & np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] < 848)
        inside &= (uv[:, 1] >= 0) & (uv[:, 1] < 480)
        u = uv[inside] + rng.normal(0, 0.15, (inside.sum(), 2))
        zz = z[inside]
        zm = zz + rng.normal(0, 1, len(zz)) * zz**2 * 0.08 / (f * 0.055)
        r = rng.random(len(zz))
        zm = np.where(r < 0.6, np.nan, np.where(r < 0.75, zz + rng.normal(0, 0.05, len(zz)), zm))
        u = np.vstack([u, ghost_uv + rng.normal(0, 0.15, ghost_uv.shape)])
        zm = np.r_[zm, ghost_z]
        keep = rng.random(len(u)) > 0.03
        u, zm = u[keep], zm[keep]
        xyz = np.c_[(u[:, 0] - K[0, 2]) / f * zm, (u[:, 1] - K[1, 2]) / f * zm, zm]
        order = rng.permutation(len(u))
        uvs.append(u[order])
        xyzs.append(xyz[order])
        refs.append(ref[k] + rng.normal(0, 0.0005, ref[k].shape))
    return _Views(uvs, xyzs, refs, K, T)


# ------------------------------------------------------------------------------ kabsch, ICP


def test_kabsch_recovers_a_rigid_transform_without_reflection() -> None:
    rng = np.random.default_rng(0)
    src = rng.normal(size=(10, 3))
    T = _random_pose(rng, src)
    got = kabsch(src, transform_points(T, src))
    assert np.allclose(got, T, atol=1e-9)
    assert np.linalg.det(got[:3, :3]) == pytest.approx(1.0)


def test_match_markers_respects_the_gate_and_is_one_to_one() -> None:
    dst = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    src = np.array([[0.01, 0, 0], [0.02, 0, 0], [1.5, 0, 0], [2.03, 0, 0]])
    i, j = match_markers(src, dst, gate_m=0.05)
    pairs = set(zip(i.tolist(), j.tolist(), strict=True))
    assert pairs == {(0, 0), (3, 2)}  # one of two near 0 wins; 1.5 is beyond every gate


def test_match_markers_honours_forbidden_pairs_and_nan_rows() -> None:
    dst = np.array([[0.0, 0], [10.0, 0]])
    src = np.array([[0.1, 0], [np.nan, 0]])
    forbid = np.array([[True, False], [False, False]])
    i, _ = match_markers(src, dst, gate_m=1.0, forbid=forbid)
    assert len(i) == 0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_trimmed_icp_converges_from_a_small_error(seed: int) -> None:
    rng = np.random.default_rng(seed)
    dst = _tpose_cloud(seed)
    T = _random_pose(rng, dst)
    src = transform_points(np.linalg.inv(T), dst[rng.permutation(len(dst))[:40]])
    src += rng.normal(0, 0.002, src.shape)
    small = np.eye(4)
    small[:3, :3] = Rotation.from_rotvec(np.radians(3) * rng.normal(size=3) / 1.7).as_matrix()
    small[:3, 3] = rng.normal(0, 0.02, 3)
    res = trimmed_icp(src, dst, T_init=small @ T, keep_fraction=0.8)
    assert rotation_error_deg(res.T, T) < 0.5
    assert np.linalg.norm(res.T[:3, 3] - T[:3, 3]) < 0.01


# ------------------------------------------------------------------------------ coarse


@pytest.mark.parametrize("seed", range(6))
def test_coarse_align_needs_no_initial_pose_with_ghosts_and_misses(seed: int) -> None:
    rng = np.random.default_rng(seed)
    dst = _tpose_cloud(seed)
    T = _random_pose(rng, dst)
    seen = rng.permutation(len(dst))[: rng.integers(18, 35)]
    src = transform_points(np.linalg.inv(T), dst[seen]) + rng.normal(0, 0.008, (len(seen), 3))
    ghosts = rng.uniform(-1.5, 1.5, (3, 3)) + src.mean(axis=0)
    src = np.vstack([src, ghosts, [[np.nan, np.nan, np.nan]]])
    res = coarse_align(src, dst, seed=seed)
    assert rotation_error_deg(res.T, T) < 2.0
    assert np.linalg.norm(res.T[:3, 3] - T[:3, 3]) < 0.05
    correct = np.mean(res.dst_index == seen[np.minimum(res.src_index, len(seen) - 1)])
    assert correct > 0.8


def test_coarse_align_refuses_too_few_markers() -> None:
    dst = _tpose_cloud(0)
    with pytest.raises(CalibrationError, match="at least 6 markers"):
        coarse_align(dst[:3], dst)


def test_coarse_align_says_wrong_units_when_no_distances_match() -> None:
    dst = _tpose_cloud(0)
    with pytest.raises(CalibrationError, match="wrong units"):
        coarse_align(dst * 1000.0, dst)


# ------------------------------------------------------------------------------ bundle


def test_bundle_adjustment_rejects_outliers_and_reports_uncertainty() -> None:
    rng = np.random.default_rng(3)
    pts = rng.uniform([-1, -1, 0], [1, 1, 2], (300, 3))
    T = look_at([2.5, 0.3, 1.2], [0, 0, 1.0])
    K = np.array([[620.0, 0, 424], [0, 620, 240], [0, 0, 1]])
    uv, _ = project_points(pts, T, K, np.zeros(5))
    uv += rng.normal(0, 0.2, uv.shape)
    bad = rng.random(len(uv)) < 0.05
    uv[bad] += rng.normal(0, 20, (bad.sum(), 2))
    start = np.eye(4)
    start[:3, :3] = Rotation.from_rotvec(np.radians([2.0, -1.0, 1.5])).as_matrix()
    start[:3, 3] = [0.05, -0.03, 0.04]
    res = bundle_adjust_camera(pts, uv, K=K, distortion=np.zeros(5), T_world_cam_init=T @ start)
    assert rotation_error_deg(res.T_world_cam, T) < 0.02
    assert np.linalg.norm(res.T_world_cam[:3, 3] - T[:3, 3]) < 0.002
    assert not res.inliers[
        bad & (np.linalg.norm(uv - project_points(pts, T, K, np.zeros(5))[0], axis=1) > 5)
    ].any()
    assert 0.2 < res.reprojection_rms_px < 0.35
    assert 0 < res.rotation_sigma_deg < 0.02
    assert 0 < res.translation_sigma_mm < 2.0


def test_bundle_adjust_solves_several_cameras_at_once() -> None:
    rng = np.random.default_rng(4)
    pts = rng.uniform([-1, -1, 0], [1, 1, 2], (200, 3))
    K = np.array([[620.0, 0, 424], [0, 620, 240], [0, 0, 1]])
    probs, truths = [], []
    for az in (0.3, 2.0):
        T = look_at([2.5 * math.cos(az), 2.5 * math.sin(az), 1.3], [0, 0, 1.0])
        uv, _ = project_points(pts, T, K, np.zeros(5))
        start = T.copy()
        start[:3, 3] += [0.02, 0.02, -0.02]
        probs.append(BundleProblem(pts, uv + rng.normal(0, 0.2, uv.shape), K, np.zeros(5), start))
        truths.append(T)
    for res, T in zip(bundle_adjust(probs), truths, strict=True):
        assert rotation_error_deg(res.T_world_cam, T) < 0.02


def test_bundle_adjustment_refuses_too_few_observations() -> None:
    K = np.array([[620.0, 0, 424], [0, 620, 240], [0, 0, 1]])
    with pytest.raises(CalibrationError, match="needs ≥ 6 matched markers"):
        bundle_adjust_camera(
            np.zeros((3, 3)), np.zeros((3, 2)), K=K, distortion=np.zeros(5),
            T_world_cam_init=np.eye(4), name="d415/1",
        )  # fmt: skip


# ------------------------------------------------------------------------------ one camera


@pytest.mark.slow
def test_register_camera_meets_the_acceptance_over_20_random_rig_poses() -> None:
    """Issue 6: < 0.1° and < 2 mm in ≥ 95 % of 20 seeds, random poses, no initial guess,
    5 % ghosts and occlusions."""
    ok, report = 0, []
    for seed in range(20):
        v = _synth_camera(seed)
        try:
            reg = register_camera(v.uv, v.xyz, v.refs, K=v.K, distortion=np.zeros(5), seed=seed)
        except CalibrationError as err:
            report.append(f"seed {seed}: {err}")
            continue
        rot = rotation_error_deg(reg.T_world_cam, v.T)
        trans = 1e3 * float(np.linalg.norm(reg.T_world_cam[:3, 3] - v.T[:3, 3]))
        ok += rot < ROT_OK_DEG and trans < TRANS_OK_MM
        report.append(f"seed {seed}: {rot:.4f} deg, {trans:.2f} mm")
    assert ok >= 19, "\n".join(report)


def test_register_camera_reports_residual_statistics() -> None:
    v = _synth_camera(7)
    reg = register_camera(v.uv, v.xyz, v.refs, K=v.K, distortion=np.zeros(5), name="d415/7")
    stats = reg.residual_statistics()
    assert 0.15 < stats["reprojection_rms_px"] < 0.5
    assert stats["inliers"] >= 100
    assert stats["frames"] == 20
    assert stats["rotation_sigma_deg"] < 0.05
    assert stats["translation_sigma_mm"] < 2.0
    assert rotation_error_deg(reg.T_world_cam_coarse, v.T) < 3.0


def test_register_camera_names_the_camera_when_too_few_markers_are_seen() -> None:
    v = _synth_camera(8)
    few = [u[:4] for u in v.uv]
    with pytest.raises(CalibrationError, match=r"d415/8.*too few markers"):
        register_camera(few, [x[:4] for x in v.xyz], v.refs, K=v.K, distortion=np.zeros(5),
                        name="d415/8")  # fmt: skip
