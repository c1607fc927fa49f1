"""Opening D415 cameras by backend: ``"realsense"`` (pyrealsense2) or ``"mock"`` (simulated).

The protocol and its records live in :mod:`acquire.depth_camera`, the pyrealsense2 adapter in
:mod:`acquire.realsense`; this module sits above both, so neither imports the other.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from mocaprig.acquire.depth_camera import DepthCamera
from mocaprig.acquire.mocks import load_mock_factory
from mocaprig.errors import ValidationError

__all__ = ["CAMERA_BACKENDS", "CameraFactory", "open_cameras", "register_camera_backend"]

CameraFactory = Callable[..., list[DepthCamera]]
"""Enumerates cameras: ``factory(**kwargs) -> list[DepthCamera]`` (keyword options only)."""


def _realsense_cameras(**kwargs: Any) -> list[DepthCamera]:
    from mocaprig.acquire.realsense import enumerate_cameras  # lazy: pyrealsense2 is optional

    return list(enumerate_cameras(**kwargs))


def _mock_cameras(**kwargs: Any) -> list[DepthCamera]:
    cams = load_mock_factory("d415")(**kwargs)
    return list(cams)


_BACKENDS: dict[str, CameraFactory] = {"realsense": _realsense_cameras, "mock": _mock_cameras}
CAMERA_BACKENDS: Mapping[str, CameraFactory] = _BACKENDS
"""Backend name → factory: ``"realsense"`` (pyrealsense2) and ``"mock"`` (entry point)."""


def register_camera_backend(name: str, factory: CameraFactory) -> None:
    """Add (or replace) a backend in :data:`CAMERA_BACKENDS` (tests plug fakes in here)."""
    _BACKENDS[name] = factory


def open_cameras(backend: str = "realsense", **kwargs: Any) -> list[DepthCamera]:
    """Enumerate the cameras of ``backend`` (keyword options go to its factory).

    Raises:
        ValidationError: unknown backend name.
        DeviceError: the backend cannot be used (pyrealsense2 missing, mock not installed).
    """
    if backend not in CAMERA_BACKENDS:
        msg = f"unknown camera backend {backend!r}; choose one of {sorted(CAMERA_BACKENDS)}"
        raise ValidationError(msg)
    return CAMERA_BACKENDS[backend](**kwargs)
