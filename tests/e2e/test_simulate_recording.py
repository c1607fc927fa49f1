"""`mocaprig simulate` records session.mcap through the real drivers talking to the mocks."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from mocaprig.acquire.davis240c_decode import SpecialType
from mocaprig.acquire.recording import RecordedMessage, Recording, info
from mocaprig.cli import main
from mocaprig.drivers_mock.scenario import build_scenario
from mocaprig.drivers_mock.session import record_session
from mocaprig.drivers_mock.truth import read_truth
from mocaprig.errors import ValidationError

PULSE_WIDTH_US = 50  # the D415 master's sync pulse (DavisSimulator.sync_pulse_us)


SECONDS = 6.0  # the shared rig session's length (tests/conftest.py rig_session)


@pytest.fixture(scope="module")
def simulated(rig_session: Path) -> Path:
    report = json.loads((rig_session.parent / "simulate.json").read_text(encoding="utf-8"))
    rec = report["recording"]
    assert rec["devices"] == ["davis", "d415", "syncbox"]
    assert rec["drops_total"] == 0
    assert rec["davis_driver_drops"] == 0
    return rig_session


def _captures(out: Path) -> dict[str, dict[str, np.ndarray]]:
    cap = np.load(out / "truth" / "d415_captures.npz")
    cams = sorted({"__".join(k.split("__")[:2]) for k in cap.files})
    return {
        c: {k.split("__")[2]: cap[k] for k in cap.files if k.startswith(c + "__")} for c in cams
    }


@pytest.mark.slow
def test_simulated_recording_has_every_d415_frame_and_no_drops(simulated) -> None:
    caps = _captures(simulated)
    assert len(caps) == 2
    inf = info(simulated / "session.mcap")
    assert inf.indexed
    assert all(s.drops == 0 for s in inf.streams)
    with Recording(simulated / "session.mcap") as rec:
        meta = rec.metadata()
        assert meta["session"]["scenario"] == "default"
        assert meta["session"]["seed"] == "5"
        assert meta["session"]["davis_dvs"] == "false"
        master = next(c for c, v in caps.items() if bool(v["is_master"]))
        master_starts = caps[master]["exposure_start_ns"]
        for cam, truth in caps.items():
            serial = cam.split("__")[1]
            n_ir = sum(1 for _ in rec.messages(f"/d415/{serial}/ir"))
            n_depth = sum(1 for _ in rec.messages(f"/d415/{serial}/depth"))
            # Every capture of the world arrived (no drop fault) and is in the recording.
            assert n_ir == n_depth == int(truth["delivered"].sum()) == truth["delivered"].size
            assert n_ir >= 30 * SECONDS - 5  # 30 fps, minus the start-up
            counters = [m.decode().frame_counter for _, m in _frame_infos(rec, serial)]
            np.testing.assert_array_equal(counters, truth["frame_counter"])
            if cam != master:
                # Every slave frame was triggered by one of the master's pulses.
                assert np.all(np.isin(truth["pulse_ns"], master_starts))


def _frame_infos(rec: Recording, serial: str) -> Iterator[tuple[int, RecordedMessage]]:
    for m in rec.messages(f"/d415/{serial}/frame_info"):
        yield m.log_time_ns, m


@pytest.mark.slow
def test_davis_trigger_pulses_are_the_master_d415_pulses(simulated) -> None:
    caps = _captures(simulated)
    master = next(v for v in caps.values() if bool(v["is_master"]))
    starts_ns = master["exposure_start_ns"]  # the master pulses at each exposure start
    truth = read_truth(simulated)
    rate = truth.clocks["davis"].rate  # DAVIS µs per session µs (its drift)
    with Recording(simulated / "session.mcap") as rec:
        topic = next(t for t in rec.topics if t.startswith("/davis/") and t.endswith("/trigger"))
        tr = rec.triggers(topic)
        resets = tr[tr["type"] == SpecialType.TIMESTAMP_RESET]
        pulses_us = tr["t"][tr["type"] == SpecialType.EXTERNAL_INPUT_PULSE]
        assert resets.size == 1
        # IMU at 1 kHz and APS frames for the whole session (DVS off: no events).
        imu_topic = topic.replace("/trigger", "/imu")
        assert rec.imu(imu_topic).size >= 1000 * SECONDS - 100
        assert rec.events(topic.replace("/trigger", "/events")).size == 0
    # The pulse detector reports at the falling edge; device time 0 = session time 0.
    rise_ns = (pulses_us - PULSE_WIDTH_US) * 1000.0 / rate
    world = build_scenario("default", seed=5, seconds=SECONDS)
    in_session = rise_ns < world.duration_ns
    assert in_session.all()
    # One DAVIS pulse per master frame, within the µs quantisation ...
    idx = np.searchsorted(rise_ns, starts_ns)
    idx = np.clip(idx, 1, rise_ns.size - 1)
    nearest = np.minimum(np.abs(rise_ns[idx] - starts_ns), np.abs(rise_ns[idx - 1] - starts_ns))
    assert nearest.max() < 2_000
    # ... and the only extra pulses are those whose frame would arrive after the session end.
    extra = rise_ns.size - starts_ns.size
    assert 0 <= extra <= 2
    assert np.all(rise_ns[starts_ns.size :] > starts_ns[-1])


def test_record_session_refuses_a_syncbox_without_cameras(tmp_path) -> None:
    world = build_scenario("tpose", seed=0, seconds=3.0)
    with pytest.raises(ValidationError, match="add d415"):
        record_session(world, tmp_path / "s.mcap", devices=("davis", "syncbox"))
    with pytest.raises(ValidationError, match="cameras must lie"):
        record_session(world, tmp_path / "s.mcap", devices=("d415",), cameras=5)


def test_simulate_rejects_an_unknown_device(tmp_path, capsys) -> None:
    code = main(["-q", "simulate", "--seconds", "3", "--devices", "kinect", "--out", str(tmp_path)])
    assert code != 0
    assert "kinect" in capsys.readouterr().err
