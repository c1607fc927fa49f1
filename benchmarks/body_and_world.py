"""Benchmark the body model and the simulated world (issue 2).

Measures, in one run so the figures can be compared as ratios on a noisy machine:
forward kinematics (numpy vs torch), marker positions, the capsule renderer at the D415 and
DAVIS resolutions, ground-truth sampling of a scenario, and reading a Vicon C3D in-process vs
isolated in a child process. Prints one JSON object as its last line.
"""

from __future__ import annotations

import json
import platform
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from mocaprig.calib.vicon import read_c3d
from mocaprig.drivers_mock.scenario import build_scenario
from mocaprig.drivers_mock.session import simulate_session
from mocaprig.process.body import (
    BodyShape,
    MarkerSet,
    capsules,
    forward_kinematics,
    forward_kinematics_torch,
    marker_positions,
    neutral_pose,
)
from mocaprig.process.body.skeleton import DOF_LIMITS_RAD


def best_of(fn: Callable[[], object], *, repeat: int = 7) -> float:
    """Minimum wall time of ``repeat`` calls (s): the least disturbed estimate."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    poses = np.zeros((n, 33))
    poses[:, :3] = rng.normal(scale=0.5, size=(n, 3))
    poses[:, 3:6] = rng.normal(scale=0.2, size=(n, 3)) + np.array([0.0, 0.0, 1.0])
    lo, hi = DOF_LIMITS_RAD[:, 0], DOF_LIMITS_RAD[:, 1]
    poses[:, 6:] = rng.uniform(lo, hi, size=(n, 27))
    return poses


def main() -> None:
    rng = np.random.default_rng(0)
    shape = BodyShape.from_height(1.75)
    markers = MarkerSet.for_shape(shape)
    n = 1000
    poses = random_poses(rng, n)
    poses_t = torch.from_numpy(poses)

    t_fk_np = best_of(lambda: forward_kinematics(poses, shape))
    t_fk_t64 = best_of(lambda: forward_kinematics_torch(poses_t, shape))
    t_fk_t32 = best_of(lambda: forward_kinematics_torch(poses_t.float(), shape))
    kin = forward_kinematics(poses, shape)
    t_markers = best_of(lambda: marker_positions(kin, shape, markers))

    # one standing actor 3 m in front of a camera looking along +Y (OpenCV axes)
    pose = neutral_pose(shape)
    caps = capsules(pose, shape)
    T_cam_world = np.array(
        [[1.0, 0, 0, 0], [0, 0, -1.0, 1.0], [0, 1.0, 0, 3.0], [0, 0, 0, 1.0]]
    )  # camera at (0, -3, 1) looking at +Y, image down = world -Z
    k_d415 = np.array([[623.0, 0, 424.0], [0, 623.0, 240.0], [0, 0, 1.0]])
    k_davis = np.array([[243.0, 0, 120.0], [0, 243.0, 90.0], [0, 0, 1.0]])
    from mocaprig.process.body import render_pinhole

    t_r848 = best_of(lambda: render_pinhole(caps, k_d415, T_cam_world, 848, 480))
    t_r240 = best_of(lambda: render_pinhole(caps, k_davis, T_cam_world, 240, 180))
    hit = render_pinhole(caps, k_d415, T_cam_world, 848, 480).segment >= 0

    world = build_scenario("default", seed=0, seconds=10.0)
    t_ns = np.arange(0, 10_000_000_000, 1_000_000, dtype=np.int64)  # 10 s at 1 kHz
    t_truth = best_of(lambda: world.sample(t_ns), repeat=3)

    with tempfile.TemporaryDirectory() as tmp:
        sim = simulate_session(Path(tmp) / "s", seconds=10.0, seed=0)
        t_c3d_in = best_of(lambda: read_c3d(sim.c3d_path, isolate=False))
        t_c3d_iso = best_of(lambda: read_c3d(sim.c3d_path, isolate=True), repeat=3)

    result = {
        "benchmark": "body_and_world",
        "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
        "threads_torch": torch.get_num_threads(),
        "fk_numpy_poses_per_s": n / t_fk_np,
        "fk_torch64_poses_per_s": n / t_fk_t64,
        "fk_torch32_poses_per_s": n / t_fk_t32,
        "fk_torch64_over_numpy": t_fk_np / t_fk_t64,
        "markers_poses_per_s": n / t_markers,
        "render_848x480_fps": 1.0 / t_r848,
        "render_240x180_fps": 1.0 / t_r240,
        "render_848x480_body_pixels": int(hit.sum()),
        "truth_samples_per_s": len(t_ns) / t_truth,
        "truth_realtime_factor_at_1khz": 10.0 / t_truth,
        "c3d_read_inprocess_s": t_c3d_in,
        "c3d_read_isolated_s": t_c3d_iso,
        "c3d_isolation_cost_ratio": t_c3d_iso / t_c3d_in,
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
