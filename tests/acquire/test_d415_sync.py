"""Sync verification on synthetic D415 timing streams (seeded; realsense-d415.md §2.4–§2.6)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mocaprig.acquire.camera_backends import open_cameras
from mocaprig.acquire.d415_sync import SyncCheckConfig, SyncChecker, SyncFlag, run_sync_check
from mocaprig.acquire.depth_camera import FrameTiming, SyncMode, TimestampDomain
from mocaprig.cli import main
from mocaprig.errors import ValidationError

WRAP = 1 << 32


@dataclass
class Rig:
    """Truth of a synthetic rig: per-camera clock rate (ppm), offset and counter start."""

    serials: list[str]
    ppm: list[float]
    offset_us: list[float]
    counter0: list[int]
    fps: int = 30
    trigger_delay_us: float = 20.0
    jitter_us: float = 5.0
    cut: dict[int, float] = field(default_factory=dict)
    """camera index → true time (s) its trigger is cut."""
    timeout_factor: float = 1.5
    """A slave without trigger self-triggers this many of its periods after its last frame."""
    drops: dict[int, set[int]] = field(default_factory=dict)
    """camera index → capture indices lost on USB (counter still advances)."""
    identical: bool = False
    metadata: bool = True
    reset_at: dict[int, int] = field(default_factory=dict)
    """camera index → capture index at which its counter restarts at 0 (ESD)."""
    own_period_ppm: dict[int, float] = field(default_factory=dict)
    """camera index → error of its self-timed period on its own clock (ppm; default 0)."""
    global_time: bool = False
    """``global_time_enabled``: frames switch to ``global_time`` ``global_ready_s`` after the
    camera's first frame, stamped on the host clock with a per-camera offset error."""
    global_ready_s: float = 1.5
    keeper_offset_us: float = 300.0


def make_rig(n: int = 4, *, seed: int = 0, min_ppm_apart: float = 8.0, **kw: object) -> Rig:
    """A rig whose slaves' crystals differ from the reference's by at least ``min_ppm_apart``:
    timestamps cannot verify the sync of crystals that agree (Intel's check; tested apart)."""
    rng = np.random.default_rng(seed)
    ppm = list(rng.uniform(-50, 50, n))
    for i in range(1, n):
        while abs(ppm[i] - ppm[0]) < min_ppm_apart:
            ppm[i] = float(rng.uniform(-50, 50))
    return Rig(
        serials=[f"8{i:02d}312070{seed:03d}" for i in range(n)],
        ppm=ppm,
        offset_us=list(rng.uniform(1e7, 3e9, n)),
        counter0=list(rng.integers(0, 5000, n)),
        **kw,  # type: ignore[arg-type]
    )


def stream(rig: Rig, seconds: float, *, seed: int = 1) -> Iterator[tuple[str, FrameTiming]]:
    """Timing records of every camera, interleaved by host arrival time."""
    rng = np.random.default_rng(seed)
    period = 1.0 / rig.fps
    events: list[tuple[int, str, FrameTiming]] = []
    # master: camera 0 triggers on its own timer (its clock), so true period = T/(1+ppm0)
    n_frames = int(seconds * rig.fps)
    own0 = 1 + rig.own_period_ppm.get(0, 0.0) * 1e-6
    trig = np.arange(n_frames) * period * own0 / (1 + rig.ppm[0] * 1e-6) + 0.013
    keeper = rng.normal(0, rig.keeper_offset_us, len(rig.serials))
    for i, serial in enumerate(rig.serials):
        ppm = rig.ppm[i] * 1e-6
        capture: list[float] = []
        cut = rig.cut.get(i)
        if i == 0:
            capture = list(trig)
        else:
            for k, t in enumerate(trig):
                if cut is None or t < cut:
                    capture.append(t + rig.trigger_delay_us * 1e-6 + rng.normal(0, 1e-6))
                else:
                    # free-run: first self-trigger after the timeout, then its own period
                    own = period * (1 + rig.own_period_ppm.get(i, 0.0) * 1e-6) / (1 + ppm)
                    first = k == 0 or trig[k - 1] < cut
                    step = rig.timeout_factor * own if first else own
                    capture.append(capture[-1] + step if capture else t)
        for k, t in enumerate(capture):
            if t > seconds:
                break
            if k in rig.drops.get(i, set()):
                continue
            base = 0 if (i in rig.reset_at and k >= rig.reset_at[i]) else rig.counter0[i]
            kk = k - rig.reset_at[i] if (i in rig.reset_at and k >= rig.reset_at[i]) else k
            dev = rig.offset_us[i] + t * 1e6 * (1 + ppm) + rng.normal(0, rig.jitter_us)
            if rig.identical:
                dev = rig.offset_us[0] + trig[k] * 1e6  # every camera stamps the same value
            sensor = round(dev) % WRAP
            host_ns = int((t + 0.004 + abs(rng.normal(0, 0.001))) * 1e9)
            if rig.metadata:
                frame_ts = (sensor + int(0.4e6 / rig.fps)) % WRAP
                domain, stamp_ms = TimestampDomain.HARDWARE_CLOCK, frame_ts / 1e3
                if rig.global_time and t - capture[0] >= rig.global_ready_s:
                    domain = TimestampDomain.GLOBAL_TIME
                    stamp_ms = (t + 0.4 / rig.fps) * 1e3 + (keeper[i] + rng.normal(0, 5)) / 1e3
                timing = FrameTiming(
                    frame_counter=base + kk,
                    sensor_timestamp_us=sensor,
                    frame_timestamp_us=frame_ts,
                    time_of_arrival_ms=host_ns // 1_000_000,
                    timestamp_domain=domain,
                    host_time_ns=host_ns,
                    timestamp_ms=stamp_ms,
                )
            else:
                timing = FrameTiming(
                    frame_counter=kk,
                    sensor_timestamp_us=None,
                    frame_timestamp_us=None,
                    time_of_arrival_ms=host_ns // 1_000_000,
                    timestamp_domain=TimestampDomain.SYSTEM_TIME,
                    host_time_ns=host_ns,
                    timestamp_ms=host_ns / 1e6,
                )
            events.append((host_ns, serial, timing))
    events.sort(key=lambda e: e[0])
    for _h, serial, timing in events:
        yield serial, timing


def run(rig: Rig, seconds: float = 10.0, *, seed: int = 1) -> SyncChecker:
    roles = {s: (SyncMode.MASTER if i == 0 else SyncMode.SLAVE) for i, s in enumerate(rig.serials)}
    checker = SyncChecker(roles, SyncCheckConfig(fps=rig.fps))
    for serial, timing in stream(rig, seconds, seed=seed):
        checker.feed(serial, timing)
    return checker


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_clean_four_camera_run_is_ok(seed: int) -> None:
    rig = make_rig(seed=seed)
    report = run(rig, seed=seed).report()
    assert report.ok, report.to_dict()
    assert report.master == rig.serials[0]
    for i, serial in enumerate(rig.serials):
        cam = report.cameras[serial]
        assert cam.flags == ()
        assert cam.drops == 0
        assert cam.frames == 300
        if i:
            truth = ((1 + rig.ppm[i] * 1e-6) / (1 + rig.ppm[0] * 1e-6) - 1) * 1e6
            assert cam.drift_ppm == pytest.approx(truth, abs=0.5)
            assert cam.free_running_since_s is None
            assert cam.max_phase_error_us is not None
            assert cam.max_phase_error_us < 60


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4])
def test_slave_trigger_cut_is_flagged_by_serial_within_one_second(seed: int) -> None:
    t_cut = 4.0
    rig = make_rig(seed=seed, cut={2: t_cut})
    report = run(rig, seed=seed).report()
    assert not report.ok
    cut_serial = rig.serials[2]
    flagged = [s for s, c in report.cameras.items() if SyncFlag.FREE_RUNNING in c.flags]
    assert flagged == [cut_serial]
    cam = report.cameras[cut_serial]
    assert cam.free_running_detected_s is not None
    assert cam.free_running_since_s is not None
    # master clock seconds since its first frame (first trigger at 0.013 s true time)
    t_cut_master = t_cut - 0.013
    assert cam.free_running_detected_s - t_cut_master <= 1.0
    assert cam.free_running_since_s >= t_cut_master - 0.1


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_free_run_without_phase_jump_is_caught_by_its_rate(seed: int) -> None:
    """Timeout = one period: no jump, only the 60 ppm rate difference makes the phase walk."""
    t_cut = 3.0
    rig = make_rig(seed=seed, cut={1: t_cut}, timeout_factor=1.0)
    rig.ppm[0], rig.ppm[1] = 30.0, -30.0
    report = run(rig, seed=seed).report()
    cam = report.cameras[rig.serials[1]]
    assert SyncFlag.FREE_RUNNING in cam.flags
    assert cam.free_running_detected_s is not None
    assert cam.free_running_detected_s - (t_cut - 0.013) <= 1.0
    assert all(SyncFlag.FREE_RUNNING not in report.cameras[s].flags for s in rig.serials[2:])


def test_identical_timestamps_are_flagged() -> None:
    rig = make_rig(seed=5, identical=True)
    report = run(rig, seconds=3.0).report()
    assert not report.ok
    for serial in rig.serials[1:]:
        assert SyncFlag.IDENTICAL_TIMESTAMPS in report.cameras[serial].flags


def test_counter_gaps_are_counted_as_drops() -> None:
    rig = make_rig(seed=6, drops={0: {50}, 3: {100, 101}})
    checker = run(rig)
    report = checker.report()
    assert report.cameras[rig.serials[0]].drops == 1
    assert report.cameras[rig.serials[3]].drops == 2
    assert report.cameras[rig.serials[1]].drops == 0
    assert SyncFlag.FRAME_DROPS in report.cameras[rig.serials[3]].flags
    assert report.ok  # 2 of 300 is below the 1 % budget; sync itself is fine
    assert checker.health().cameras[rig.serials[3]].drops == 2


def test_many_drops_fail_the_check() -> None:
    rig = make_rig(seed=7, drops={1: set(range(100, 120))})
    report = run(rig).report()
    assert SyncFlag.TOO_MANY_DROPS in report.cameras[rig.serials[1]].flags
    assert not report.ok


def test_missing_metadata_fails_with_no_hardware_timestamps() -> None:
    rig = make_rig(seed=8, metadata=False)
    report = run(rig, seconds=2.0).report()
    assert not report.ok
    for cam in report.cameras.values():
        assert SyncFlag.NO_HARDWARE_TIMESTAMPS in cam.flags


def test_counter_reset_is_reported_and_pairing_recovers() -> None:
    rig = make_rig(seed=9, reset_at={2: 150})
    report = run(rig).report()
    cam = report.cameras[rig.serials[2]]
    assert cam.counter_resets == 1
    assert SyncFlag.COUNTER_RESET in cam.flags
    assert SyncFlag.FREE_RUNNING not in cam.flags
    assert report.ok


def test_u32_clock_wrap_is_not_a_fault() -> None:
    rig = make_rig(seed=10)
    rig.offset_us = [WRAP - 2e6, WRAP - 5e6, 1e6, WRAP - 1]
    report = run(rig).report()
    assert report.ok, report.to_dict()


def test_no_master_fails() -> None:
    rig = make_rig(2, seed=11)
    checker = SyncChecker(dict.fromkeys(rig.serials, SyncMode.SLAVE))
    for serial, timing in stream(rig, 1.0):
        checker.feed(serial, timing)
    report = checker.report()
    assert not report.ok
    assert report.master is None
    assert all(SyncFlag.NO_MASTER in c.flags for c in report.cameras.values())


def test_health_reports_lock_while_streaming() -> None:
    rig = make_rig(seed=12, cut={3: 2.0})
    roles = {s: (SyncMode.MASTER if i == 0 else SyncMode.SLAVE) for i, s in enumerate(rig.serials)}
    checker = SyncChecker(roles)
    states = []
    for serial, timing in stream(rig, 4.0):
        checker.feed(serial, timing)
        if serial == rig.serials[0] and timing.frame_counter % 30 == 0:
            states.append(checker.health().cameras[rig.serials[3]].locked)
    assert True in states
    assert states[-1] is False
    assert not checker.health().ok


def test_unknown_serial_is_rejected() -> None:
    checker = SyncChecker({"A": SyncMode.MASTER})
    timing = FrameTiming(1, 1, 2, 0, TimestampDomain.HARDWARE_CLOCK, 0)
    with pytest.raises(ValidationError, match="not part of this sync check"):
        checker.feed("B", timing)


# -- end to end through engineer E's mock cameras (entry point mocaprig.mocks: d415) -----------


def _mock_run(fault: str | None, *, seed: int = 3, seconds: float = 10.0) -> tuple[Any, list[Any]]:
    cams: list[Any] = open_cameras(
        "mock", seed=seed, seconds=seconds + 1, fault=fault, images=False
    )
    return run_sync_check(cams, seconds=seconds), cams


def _delivered_span_drops(cam: Any, fed: int) -> int:
    """Captures the mock lost between the first and last of the ``fed`` delivered frames."""
    delivered = [r.frame_counter for r in cam.captures if r.outcome == "delivered"][:fed]
    lo, hi = delivered[0], delivered[-1]
    return sum(1 for r in cam.captures if r.outcome != "delivered" and lo < r.frame_counter < hi)


def test_mock_rig_ten_seconds_is_ok_with_no_unexplained_drops() -> None:
    report, cams = _mock_run(None)
    assert report.ok, report.to_dict()
    master = cams[0]
    for cam in cams:
        found = report.cameras[cam.info.serial]
        assert found.drops == _delivered_span_drops(cam, found.frames) == 0
        assert found.frames >= 299
        if cam is not master:
            truth = (
                (1 + cam.clock.drift_ppm * 1e-6) / (1 + master.clock.drift_ppm * 1e-6) - 1
            ) * 1e6
            assert found.drift_ppm == pytest.approx(truth, abs=1.0)


def test_mock_slave_trigger_cut_is_flagged_by_serial_within_one_second() -> None:
    report, cams = _mock_run("slave-trigger-cut")
    master, victim = cams[0], cams[1]  # the fault's default target: the first slave
    flagged = [s for s, c in report.cameras.items() if SyncFlag.FREE_RUNNING in c.flags]
    assert flagged == [victim.info.serial]
    assert not report.ok
    # truth: the first capture the slave triggered itself, on the master's clock
    first_master = master.captures[0].mid_exposure_ns
    first_free = next(r for r in victim.captures if not r.triggered)
    cut_s = 1.0 - first_master / 1e9  # the fault's default at_s, as seconds since master frame 0
    found = report.cameras[victim.info.serial]
    assert found.free_running_detected_s is not None
    assert found.free_running_detected_s - cut_s <= 1.0
    assert found.free_running_detected_s >= (first_free.mid_exposure_ns - first_master) / 1e9 - 0.05


def test_mock_drops_are_counted_exactly() -> None:
    report, cams = _mock_run("drops:rate=0.03", seconds=5.0)
    for cam in cams:
        found = report.cameras[cam.info.serial]
        assert found.drops == _delivered_span_drops(cam, found.frames)
    assert sum(report.cameras[c.info.serial].drops for c in cams) > 0


def test_cli_check_sync_mock_json(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["d415", "check-sync", "--mock", "--seconds", "10", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["ok"] is True
    assert len(out["cameras"]) >= 2
    assert all(c["drops"] == 0 and c["flags"] == [] for c in out["cameras"].values())


def test_cli_check_sync_mock_fault_flags_the_slave(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["d415", "check-sync", "--mock", "--mock-fault", "slave-trigger-cut"]
    assert main([*argv, "--seconds", "10", "--json"]) == 1
    out = json.loads(capsys.readouterr().out)
    assert out["ok"] is False
    bad = {s: c for s, c in out["cameras"].items() if "free-running" in c["flags"]}
    assert len(bad) == 1
    ((_serial, cam),) = bad.items()
    assert cam["role"] == "slave"
    assert cam["free_running_detected_s"] <= 2.0  # cut at 1 s (session) + at most 1 s


def test_cli_stream_and_list_mock(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["d415", "stream", "--mock", "--seconds", "2", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for cam in out["cameras"].values():
        assert cam["drops"] == 0
        assert cam["fps"] == pytest.approx(30, abs=0.5)
    assert main(["d415", "list", "--mock", "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)["cameras"]
    assert {c["serial"] for c in listed} == set(out["cameras"])


def test_cli_mock_fault_needs_mock(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["d415", "check-sync", "--mock-fault", "drops", "--seconds", "1"]) == 1
    assert "--mock-fault needs --mock" in capsys.readouterr().err


def test_external_trigger_uses_a_slave_as_reference() -> None:
    rig = make_rig(3, seed=13)
    checker = SyncChecker(dict.fromkeys(rig.serials, SyncMode.SLAVE), external_trigger=True)
    for serial, timing in stream(rig, 3.0):
        checker.feed(serial, timing)
    report = checker.report()
    assert report.ok, report.to_dict()
    assert report.master == rig.serials[0]


# -- Intel's rate check: synced timestamps drift apart, unsynced ones keep their difference ----
# (realsense-ros #2323, #1889; librealsense #14131). These replace the old "zero-drift" warning
# tests, which let a never-triggered slave pass.


@pytest.mark.parametrize("global_time", [False, True])
def test_slave_never_triggered_is_free_running(global_time: bool) -> None:
    """Free-running from the start: its own period equals the master's in their own clocks, so
    the hardware timestamps keep a constant difference (no phase jump ever happens)."""
    rig = make_rig(seed=14, cut={1: 0.0}, timeout_factor=1.0, global_time=global_time)
    report = run(rig).report()
    assert not report.ok
    cam = report.cameras[rig.serials[1]]
    assert SyncFlag.FREE_RUNNING in cam.flags
    assert cam.drift_ppm is not None
    assert abs(cam.drift_ppm) < 1.0
    assert cam.free_running_since_s is not None
    assert cam.free_running_since_s < 0.1
    assert cam.rate_reference == ("global-time" if global_time else "host-arrival")
    if global_time:  # its exposures walk against the master's at the crystals' difference
        truth = ((1 + rig.ppm[0] * 1e-6) / (1 + rig.ppm[1] * 1e-6) - 1) * 1e6
        assert cam.walk_ppm == pytest.approx(truth, abs=1.0)
    for serial in rig.serials[2:]:
        assert report.cameras[serial].flags == ()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_synced_rig_passes_across_the_switch_to_global_time(seed: int) -> None:
    """Real D415s switch from hardware_clock to global_time ~1.5 s into the stream."""
    rig = make_rig(seed=seed, global_time=True)
    report = run(rig, seed=seed).report()
    assert report.ok, report.to_dict()
    for i, serial in enumerate(rig.serials[1:], start=1):
        cam = report.cameras[serial]
        assert cam.flags == ()
        assert cam.timestamp_domain is TimestampDomain.GLOBAL_TIME
        assert cam.rate_reference == "global-time"
        truth = ((1 + rig.ppm[i] * 1e-6) / (1 + rig.ppm[0] * 1e-6) - 1) * 1e6
        assert cam.drift_ppm == pytest.approx(truth, abs=0.5)
        assert cam.crystal_ppm == pytest.approx(truth, abs=1.0)
        assert cam.walk_ppm == pytest.approx(0.0, abs=1.0)


def test_synced_rig_without_global_time_is_read_against_host_arrival() -> None:
    rig = make_rig(seed=21)
    report = run(rig, seconds=20.0).report()
    assert report.ok, report.to_dict()
    for serial in rig.serials[1:]:
        cam = report.cameras[serial]
        assert cam.rate_reference == "host-arrival"
        assert cam.walk_ppm is not None
        assert abs(cam.walk_ppm) < 10.0


@pytest.mark.parametrize("own_ppm", [-25.0, 20.0])
def test_free_running_slave_with_a_period_of_its_own_is_caught_by_its_walk(
    own_ppm: float,
) -> None:
    """If a unit's self-timed period is not exactly nominal on its own clock, a never-triggered
    slave's hardware timestamps drift like a synced one's; its walk in host time still shows."""
    rig = make_rig(seed=15, cut={2: 0.0}, timeout_factor=1.0, global_time=True)
    rig.own_period_ppm = {2: own_ppm}
    report = run(rig).report()
    cam = report.cameras[rig.serials[2]]
    assert cam.drift_ppm is not None
    assert abs(cam.drift_ppm) > 10.0  # the naive "timestamps drift apart" rule would pass it
    assert SyncFlag.FREE_RUNNING in cam.flags
    assert not report.ok


def test_crystals_that_agree_cannot_be_verified() -> None:
    """Equal crystals: a locked slave's timestamps keep a constant difference too."""
    rig = make_rig(2, seed=16, global_time=True)
    rig.ppm[1] = rig.ppm[0] + 0.2
    report = run(rig).report()
    cam = report.cameras[rig.serials[1]]
    assert cam.flags == (SyncFlag.SYNC_UNVERIFIED,)
    assert not report.ok


def test_a_run_too_short_to_resolve_the_drift_is_only_warned() -> None:
    rig = make_rig(2, seed=17)
    rig.ppm[1] = rig.ppm[0] + 3.0
    report = run(rig, seconds=1.5).report()
    assert report.cameras[rig.serials[1]].flags == (SyncFlag.TOO_SHORT,)
    assert report.ok  # inconclusive, not failed: 10 s runs resolve it
    assert run(rig, seconds=10.0).report().cameras[rig.serials[1]].flags == ()


def test_intermittent_trigger_is_flagged_at_the_first_missed_pulse() -> None:
    """A slave that misses one pulse self-triggers after its timeout: a phase jump."""
    rig = make_rig(3, seed=18, cut={1: 5.0}, timeout_factor=1.5)
    events = list(stream(rig, 10.0))
    # the trigger comes back after 0.2 s: keep the free-run frames only until then
    roles = {s: (SyncMode.MASTER if i == 0 else SyncMode.SLAVE) for i, s in enumerate(rig.serials)}
    back = make_rig(3, seed=18)
    relocked = {
        (s, t.frame_counter): t
        for s, t in stream(back, 10.0)
        if s == rig.serials[1] and t.host_time_ns > 5.2e9
    }
    checker = SyncChecker(roles, SyncCheckConfig(fps=30))
    for serial, timing in events:
        if serial == rig.serials[1] and timing.host_time_ns > 5.2e9:
            timing = relocked.get((serial, timing.frame_counter), timing)
        checker.feed(serial, timing)
    cam = checker.report().cameras[rig.serials[1]]
    assert SyncFlag.FREE_RUNNING in cam.flags
    assert cam.free_running_since_s is not None
    assert 4.9 <= cam.free_running_since_s + 0.013 <= 5.3


def test_mock_slave_never_triggered_fails_in_both_domains() -> None:
    for global_time in (False, True):
        cams: list[Any] = open_cameras(
            "mock",
            seed=3,
            seconds=11.0,
            fault="slave-trigger-cut:at_s=0",
            images=False,
            global_time_enabled=global_time,
        )
        report = run_sync_check(cams, seconds=10.0)
        victim = report.cameras[cams[1].info.serial]
        assert SyncFlag.FREE_RUNNING in victim.flags, (global_time, victim)
        assert not report.ok
        assert all(report.cameras[c.info.serial].ok for c in cams[2:])
        want = TimestampDomain.GLOBAL_TIME if global_time else TimestampDomain.HARDWARE_CLOCK
        assert victim.timestamp_domain is want


@pytest.mark.parametrize("global_time", [False, True])
def test_mock_synced_rig_passes_in_both_domains(global_time: bool) -> None:
    cams: list[Any] = open_cameras(
        "mock", seed=4, seconds=11.0, images=False, global_time_enabled=global_time
    )
    report = run_sync_check(cams, seconds=10.0)
    assert report.ok, report.to_dict()
    for cam in cams[1:]:
        found = report.cameras[cam.info.serial]
        assert found.rate_reference == ("global-time" if global_time else "host-arrival")
        assert found.walk_ppm is not None


def test_mock_intermittent_trigger_is_flagged() -> None:
    report, cams = _mock_run("trigger-dropout:rate=0.02,camera=d415-2")
    victim = report.cameras[cams[2].info.serial]
    assert SyncFlag.FREE_RUNNING in victim.flags
    missed = [r for r in cams[2].captures if not r.triggered and r.exposure_start_ns > 0.5e9]
    assert missed  # the truth: it did trigger itself
    assert all(report.cameras[c.info.serial].ok for c in cams if c is not cams[2])


def test_mock_readout_convention_passes_the_check() -> None:
    """The check does not depend on where the pulse falls (D415Timing is the world's secret)."""
    from mocaprig.drivers_mock.rig import D415Timing

    cams: list[Any] = open_cameras(
        "mock", seed=5, seconds=8.0, images=False, timing=D415Timing.readout_start()
    )
    report = run_sync_check(cams, seconds=7.0)
    assert report.ok, report.to_dict()


def test_mock_without_metadata_fails_the_check() -> None:
    report, cams = _mock_run("no-metadata", seconds=3.0)
    assert not report.ok
    for cam in cams:
        assert SyncFlag.NO_HARDWARE_TIMESTAMPS in report.cameras[cam.info.serial].flags


@settings(max_examples=20, deadline=None, derandomize=True)
@given(
    seed=st.integers(0, 2**31),
    fps=st.sampled_from([30, 90]),
    jitter_us=st.floats(1.0, 12.0),
    delay_us=st.floats(0.0, 500.0),
)
def test_any_clean_rig_passes(seed: int, fps: int, jitter_us: float, delay_us: float) -> None:
    rig = make_rig(3, seed=seed % 100_000, fps=fps, jitter_us=jitter_us, trigger_delay_us=delay_us)
    report = run(rig, seconds=4.0, seed=seed).report()
    assert report.ok, report.to_dict()


def test_cli_stream_without_metadata_needs_the_flag(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["d415", "stream", "--mock", "--mock-fault", "no-metadata", "--seconds", "1"]
    assert main([*argv, "--json"]) == 1
    assert "allow-no-metadata" in capsys.readouterr().err
    assert main([*argv, "--allow-no-metadata", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert all(c["frames"] > 20 for c in out["cameras"].values())


def test_cli_check_sync_reports_a_never_triggered_slave(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["d415", "check-sync", "--mock", "--mock-fault", "slave-trigger-cut:at_s=0"]
    assert main([*argv, "--seconds", "6"]) == 1
    out = capsys.readouterr().out
    assert "sync FAILED" in out
    assert "free-running" in out
