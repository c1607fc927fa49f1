"""Vicon I/O, marker measurement, time alignment, registration and intrinsics.

Imports flow one way: ``process -> calib -> acquire``.
"""

from __future__ import annotations

from mocaprig.calib.vicon import (
    MarkerTrajectories,
    ViconFileError,
    read_c3d,
    read_nexus_csv,
    read_trajectories,
    validate_c3d,
    write_c3d,
)

__all__ = [
    "MarkerTrajectories",
    "ViconFileError",
    "read_c3d",
    "read_nexus_csv",
    "read_trajectories",
    "validate_c3d",
    "write_c3d",
]
