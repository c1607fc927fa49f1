"""What every sync box must do through this driver: the mock, or a real one with --hardware.

Run against the rig's box with ``pytest --hardware tests/acquire/test_syncbox_contract.py``
(the first USB-serial port that answers ``HELLO``; nothing else may hold the port).
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest

from mocaprig.acquire.syncbox import (
    PROTOCOL_VERSION,
    SyncBox,
    SyncBoxMode,
    find_syncboxes,
    open_mock_syncbox,
)
from mocaprig.errors import DeviceError


def _real_box() -> SyncBox:
    for port in find_syncboxes():
        box = SyncBox(port, boot_timeout_s=2.5, max_reopen=0)
        try:
            box.open()
        except DeviceError:
            continue  # another USB-serial device
        return box
    pytest.skip("no sync box answered HELLO on this machine's serial ports")


@pytest.fixture(params=["mock", "hardware"])
def box(request: pytest.FixtureRequest) -> Iterator[SyncBox]:
    if request.param == "hardware":
        if not request.config.getoption("--hardware"):
            pytest.skip("real sync box not requested (run pytest with --hardware)")
        real = _real_box()
        with real:
            yield real
        return
    with open_mock_syncbox() as mock, SyncBox(mock.port) as opened:
        yield opened


class TestSyncBoxContract:
    def test_it_speaks_this_protocol(self, box: SyncBox) -> None:
        ident = box.identity
        assert ident is not None
        assert ident.version == PROTOCOL_VERSION
        assert ident.board

    def test_it_generates_the_rate_it_is_asked_for(self, box: SyncBox) -> None:
        box.set_report_interval(100)
        box.start(hz=50, width_us=200)
        assert box.status().mode is SyncBoxMode.GENERATE
        t0 = time.monotonic()
        time.sleep(1.0)
        count = box.stop()
        elapsed = time.monotonic() - t0
        # 50 Hz on the box's crystal (±100 ppm): the count matches the host's second within
        # the command round trips.
        assert abs(count - 50 * elapsed) <= 3

    def test_a_second_start_is_refused_until_stop(self, box: SyncBox) -> None:
        box.start(hz=30, width_us=100)
        with pytest.raises(DeviceError):
            box.start(hz=30, width_us=100)
        box.stop()
        box.start(hz=30, width_us=100)
        box.stop()
