"""What every D415 rig must do through this driver: the mock rig, or the real one with --hardware.

Run against the cameras plugged in with ``pytest --hardware tests/acquire/test_d415_contract.py``
(pyrealsense2 and libusb-1.0 installed; two or more D415s wired for hardware sync,
docs/wiring.md). It proves what the recorder and the calibration rely on.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from mocaprig.acquire.camera_backends import open_cameras
from mocaprig.acquire.d415_sync import configure_rig, iter_framesets, run_sync_check, start_rig
from mocaprig.acquire.depth_camera import DepthCamera, StreamConfig, SyncMode
from mocaprig.acquire.realsense import MIN_SYNC_FIRMWARE
from mocaprig.errors import DeviceError


@pytest.fixture(params=["mock", "hardware"])
def rig(request: pytest.FixtureRequest) -> Iterator[list[DepthCamera]]:
    if request.param == "hardware":
        if not request.config.getoption("--hardware"):
            pytest.skip("real D415s not requested (run pytest with --hardware)")
        try:
            cams = open_cameras("realsense")
        except DeviceError as err:
            pytest.skip(f"the RealSense backend cannot be used here: {err}")
        if not cams:
            pytest.skip("no D415 connected")
    else:
        cams = open_cameras("mock", seed=3, seconds=4.0, images=False)  # timing only: fast
    try:
        yield cams
    finally:
        for cam in cams:
            cam.close()


class TestD415RigContract:
    def test_every_camera_can_be_hardware_synced(self, rig: list[DepthCamera]) -> None:
        for cam in rig:
            fw = tuple(int(p) for p in cam.info.firmware.split("."))
            assert fw >= MIN_SYNC_FIRMWARE, f"{cam.info.serial}: firmware {cam.info.firmware}"
            assert cam.info.usb_type.startswith("3"), f"{cam.info.serial}: USB {cam.info.usb_type}"

    def test_frame_sets_pair_ir_and_depth_of_one_capture_with_metadata(
        self, rig: list[DepthCamera]
    ) -> None:
        mode = StreamConfig()
        roles = configure_rig(rig, stream=mode)
        assert sum(r is SyncMode.MASTER for r in roles.values()) == (1 if len(rig) > 1 else 0)
        start_rig(rig)
        try:
            sets = list(iter_framesets(rig, seconds=1.0))
        finally:
            for cam in rig:
                cam.stop()
        assert {fs.serial for fs in sets} == {c.info.serial for c in rig}
        for fs in sets:
            assert fs.infrared.image.shape == fs.depth.image.shape == (mode.height, mode.width)
            assert fs.infrared.image.dtype == np.uint8
            assert fs.depth.image.dtype == np.uint16
            assert fs.timing.has_hardware_timestamps, f"{fs.serial}: no per-frame metadata"
        for cam in rig:
            counters = [fs.timing.frame_counter for fs in sets if fs.serial == cam.info.serial]
            assert counters == sorted(counters)
            assert len(counters) >= 0.9 * mode.fps  # one second at the mode's rate
            k = cam.intrinsics()
            assert (k.width, k.height) == (mode.width, mode.height)
            assert k.fx > 0 and k.fy > 0  # noqa: PT018

    def test_the_slaves_follow_the_master(self, rig: list[DepthCamera]) -> None:
        if len(rig) < 2:
            pytest.skip("one camera: nothing to synchronise")
        report = run_sync_check(rig, seconds=3.0)
        assert report.ok, report.to_dict()
