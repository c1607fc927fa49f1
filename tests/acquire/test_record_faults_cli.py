"""`mocaprig record --mock --mock-faults ...`: the mock rig with its DAVIS unplugged, a D415
disconnected and the sync box's cable pulled, each plugged back, in one recording."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from mocaprig.acquire import commands_record
from mocaprig.acquire.mocks import load_mock_factory
from mocaprig.acquire.recording import Recording, info
from mocaprig.cli import main
from mocaprig.drivers_mock.faults import fault_schedule
from mocaprig.errors import DeviceError


@pytest.mark.slow  # builds the simulated world (~5-15 s on a busy machine) and records 7.5 s
def test_record_mock_rig_survives_three_devices_lost_and_back(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:

    def factory(name: str) -> Any:
        # The ``faults`` entry point of pyproject.toml, resolved here in case the installed
        # metadata predates it.
        return fault_schedule if name == "faults" else load_mock_factory(name)

    monkeypatch.setattr(commands_record, "load_mock_factory", factory, raising=True)
    out = tmp_path / "s.mcap"
    # The faults are spread out so that, even when a loaded machine notices a loss late, the
    # DAVIS is found lost and back well before the D415 goes (the D415 is checked below to
    # have recorded while the DAVIS was away).
    spec = "davis-unplug@1+1,d415-disconnect@3.5+1.2,syncbox-unplug@5.5+0.6"
    argv = ["record", "--mock", "--cameras", "1", "--seconds", "7.5", "--out", str(out)]
    try:
        code = main([*argv, "--mock-faults", spec, "--json"])
    except DeviceError as err:  # the mocks are entry points of the installed package
        pytest.skip(f"mock devices not available: {err}")
    summary = json.loads(capsys.readouterr().out)
    assert code == 3, summary["outcome"]
    assert summary["exit_code"] == 3
    inf = info(out)
    assert inf.indexed
    assert inf.stop_reason == "requested"
    lost = {f.device for f in inf.faults if f.kind == "disconnected"}
    back = {f.device for f in inf.faults if f.kind == "reconnected"}
    devices = {d.split("/")[0] for d in lost}
    assert devices == {"davis", "d415", "syncbox"}, inf.faults
    assert back == lost
    assert all(g.back for g in inf.gaps)
    for device in lost:
        assert f"{device} lost and back" in summary["outcome"]
    # The other streams went on while the DAVIS delivered nothing: from its last message before
    # it was found lost (if any: a slow machine may still be configuring it) to its first once
    # back (the gap itself runs from noticing the loss to re-opening, which may be short).
    davis_gap = next(g for g in inf.gaps if g.device.startswith("davis/"))
    with Recording(out) as r:
        davis_ns = [m.log_time_ns for m in r.messages() if m.topic.startswith("/davis/")]
        before = max((t for t in davis_ns if t < davis_gap.start_ns), default=davis_gap.start_ns)
        after = min(t for t in davis_ns if t > davis_gap.end_ns)
        others = {
            m.topic
            for m in r.messages(start_ns=before + 1, end_ns=after)
            if m.topic.startswith(("/d415/", "/syncbox/"))
        }
    assert others, f"no D415 or sync box message while the DAVIS was away: {inf.gaps}"
