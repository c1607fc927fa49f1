"""Shared helpers for the body-model tests: seeded random poses within the joint limits."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from process.body.skeleton import DOF_LIMITS_RAD, POSE_DIM, ROOT_DIM


def random_poses(rng: np.random.Generator, n: int) -> npt.NDArray[np.float64]:
    """``n`` pose vectors: random root rotation and translation, angles uniform in limits."""
    q = np.zeros((n, POSE_DIM))
    q[:, 0:3] = rng.normal(scale=1.5, size=(n, 3))
    q[:, 3:6] = rng.normal(scale=2.0, size=(n, 3))
    lo, hi = DOF_LIMITS_RAD[:, 0], DOF_LIMITS_RAD[:, 1]
    q[:, ROOT_DIM:] = rng.uniform(lo, hi, size=(n, lo.size))
    return q
