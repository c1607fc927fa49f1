"""What the calibration estimates on a rig the simulator does not mirror (issue 16): the sync
edge's shape from the edges, the D415 pulse phase from the video, the DAVIS pulse pairing from
the motion; and a refusal naming what the data cannot tell."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest

from mocaprig.calib.calibration import ClockMapping
from mocaprig.calib.sync_edges import find_sync_edges
from mocaprig.calib.vicon_calibration import _pool_by_cost, _refuse_unobservable_phase
from mocaprig.calib.vicon_calibration_davis import DavisMotion, motion_period_shift
from mocaprig.calib.vicon_calibration_options import CalibrationOptions, D415PulseTiming
from mocaprig.calib.vicon_calibration_sync import SyncInputs, sync_clocks
from mocaprig.errors import CalibrationError
from tests.calib.test_sync_channel import _errors, _prior, _rig

F64 = npt.NDArray[np.float64]
RATE_HZ = 2400.0
PERIOD_NS = 1e9 / 30.0


def _filtered_toggle(
    seed: int, *, tau_us: float, antialias_hz: float | None, seconds: float = 6.0
) -> tuple[F64, F64, F64]:
    """Sample times, volts and true switches (ns) of a toggle through an RC and, optionally, a
    2-pole Butterworth anti-alias filter (its step response from scipy's ``lti``, apart from
    the simulator's own)."""
    from scipy import signal

    rng = np.random.default_rng(seed)
    switches = 0.1e9 + rng.uniform(0, PERIOD_NS) + np.arange(int(seconds * 30) - 6) * PERIOD_NS
    num, den = [1.0], [tau_us * 1e-6, 1.0]
    if antialias_hz is not None:
        wc = 2 * math.pi * antialias_hz
        num, den = [wc * wc], list(np.polymul(den, [1.0, math.sqrt(2) * wc, wc * wc]))
    grid_s = np.arange(0.0, 0.02, 1e-6)  # settled long before the next switch (33 ms)
    _, h = signal.lti(num, den).step(T=grid_s)
    t = np.arange(0.0, seconds * 1e9, 1e9 / RATE_HZ) + rng.uniform(0.0, 1e9 / RATE_HZ)
    k = np.searchsorted(switches, t, side="right") - 1
    since_s = (t - switches[np.maximum(k, 0)]) * 1e-9
    before = (np.maximum(k, 0) % 2 == 1).astype(float)  # the level before the last switch
    step = np.where(before > 0, -1.0, 1.0) * np.interp(since_s, grid_s, h, right=1.0)
    level = np.where(k >= 0, before + step, 0.0)
    volts = 4.8 * level + rng.normal(0.0, 0.002, t.size)
    quantised: F64 = np.round(volts / (20 / 4096)) * (20 / 4096)
    return t, quantised, switches.astype(np.float64)


def _switch_errors_us(edges_t: F64, switches: F64) -> F64:
    j = np.clip(np.searchsorted(switches, edges_t - 5e6), 0, switches.size - 1)
    return (edges_t - switches[j]) / 1e3


def test_the_fitted_edge_model_finds_the_switches_behind_an_anti_alias_filter() -> None:
    t, v, switches = _filtered_toggle(3, tau_us=470.0, antialias_hz=1500.0, seconds=3.0)
    rc = find_sync_edges(t, v, channel="D415_SYNC")
    fit = find_sync_edges(t, v, channel="D415_SYNC", edge_model="fit")
    # The first-order model reads the filter's group delay (√2/(2π·1.5 kHz) = 150 µs) as a
    # later switch; the fitted shape finds it.
    assert np.median(_switch_errors_us(rc.t_ns, switches)) > 100.0
    assert np.abs(_switch_errors_us(fit.t_ns, switches)).max() < 5.0
    assert fit.lowpass_ns == pytest.approx(1e9 / (2 * math.pi * 1500.0), rel=0.1)
    assert fit.tau_ns == pytest.approx(470e3, rel=0.05)


def test_the_fitted_edge_model_keeps_a_first_order_edge_first_order() -> None:
    t, v, switches = _filtered_toggle(4, tau_us=470.0, antialias_hz=None, seconds=3.0)
    fit = find_sync_edges(t, v, channel="D415_SYNC", edge_model="fit")
    assert fit.lowpass_ns < 5e3
    assert np.abs(_switch_errors_us(fit.t_ns, switches)).max() < 5.0


@pytest.mark.parametrize("assumed", ["exposure-start", "readout-start"])
def test_the_video_clock_tells_the_pulse_phase_when_the_assumption_is_wrong(assumed: str) -> None:
    """The synthetic rig pulses at the exposure start (stamp = pulse + 4.25 ms). Assuming the
    readout start would put the master's clock one exposure (8.5 ms) out; the video clock (here
    1 ms off) picks the convention whose sync clock agrees with it."""
    rig = _rig(2, seconds=20.0)
    edges = find_sync_edges(rig.t_ns, rig.volts, channel="D415_SYNC")
    opt = CalibrationOptions(d415_pulse_at=assumed)  # type: ignore[arg-type]
    delay = opt.pulse_timing.master_frame_delay_ns(8.5e6)
    sync = SyncInputs(edges, "m", rig.frames_dev_ns, delay, master_exposure_ns=8.5e6)
    prior = _prior(rig, offset_err_ns=-1e6, drift_err_ppm=3.0)
    used: list[D415PulseTiming] = []
    out, notes = sync_clocks(sync, {"m": prior}, {}, opt, timing_out=used)
    offset_ns, _ = _errors(out["m"], rig)
    assert abs(offset_ns) < 5_000.0
    assert used[-1].pulse_at == "exposure-start"
    if assumed == "readout-start":
        assert any("pulse phase measured" in n for n in notes)
        told = CalibrationOptions(d415_pulse_at="readout-start", measure_pulse_phase=False)
        blind, _ = sync_clocks(sync, {"m": prior}, {}, told)
        assert abs(_errors(blind["m"], rig)[0]) == pytest.approx(8.5e6, abs=10_000.0)


def _halfway_rig() -> tuple[SyncInputs, ClockMapping, Callable[[ClockMapping], float]]:
    """The master's sync inputs, a video clock 4.25 ms off (halfway between the two
    conventions' sync clocks) and the mapping's true offset error (ns)."""
    rig = _rig(5, seconds=20.0)
    edges = find_sync_edges(rig.t_ns, rig.volts, channel="D415_SYNC")
    sync = SyncInputs(
        edges, "m", rig.frames_dev_ns,
        CalibrationOptions().pulse_timing.master_frame_delay_ns(8.5e6), master_exposure_ns=8.5e6,
    )  # fmt: skip
    return sync, _prior(rig, offset_err_ns=-4.25e6, drift_err_ppm=0.0), lambda m: _errors(m, rig)[0]


def test_a_pulse_phase_nothing_tells_refuses_the_calibration_naming_it() -> None:
    sync, prior, _ = _halfway_rig()
    with pytest.raises(CalibrationError, match="pulse phase") as err:
        sync_clocks(sync, {"m": prior}, {}, CalibrationOptions())
    assert "--d415-pulse-at" in str(err.value)
    assert "not observable" in str(err.value)
    # Told (a measured rig), or forced: the convention given stays, the forced one with a note.
    told = CalibrationOptions(d415_pulse_at="exposure-start", measure_pulse_phase=False)
    sync_clocks(sync, {"m": prior}, {}, told)
    used: list[D415PulseTiming] = []
    _, notes = sync_clocks(sync, {"m": prior}, {}, CalibrationOptions(force=True), timing_out=used)
    assert used[-1].pulse_at == "exposure-start"
    assert any("pulse phase NOT observable" in n for n in notes)


@pytest.mark.parametrize("assumed", ["exposure-start", "readout-start"])
def test_the_masters_own_video_clock_tells_the_phase_the_pooled_one_cannot(assumed: str) -> None:
    """The pooled clock is pulled halfway by the slaves' convention-dependent delays; the
    master's clock from its own frames (0.5 ms off) is not."""
    sync, pooled, error_ns = _halfway_rig()
    own = dataclasses.replace(pooled, offset_ns=pooled.offset_ns + round(3.75e6))
    opt = CalibrationOptions(d415_pulse_at=assumed)  # type: ignore[arg-type]
    used: list[D415PulseTiming] = []
    out, notes = sync_clocks(sync, {"m": pooled}, {}, opt, timing_out=used, own={"m": own})
    assert used[-1].pulse_at == "exposure-start"
    assert abs(error_ns(out["m"])) < 5_000.0
    assert any("pulse phase measured" in n and "own video clock" in n for n in notes)


def test_the_reprojection_cost_tells_the_phase_when_the_video_clock_cannot() -> None:
    sync, prior, error_ns = _halfway_rig()
    used: list[D415PulseTiming] = []

    def cost(_name: str, m: ClockMapping) -> float:
        # A moving marker set reprojects worse the further the clock is out.
        return 1.0 + abs(error_ns(m)) / 1e6

    opt = CalibrationOptions(d415_pulse_at="readout-start")
    out, notes = sync_clocks(sync, {"m": prior}, {}, opt, cost, used)
    assert used[-1].pulse_at == "exposure-start"
    assert abs(error_ns(out["m"])) < 5_000.0
    assert any("by the reprojection cost" in n for n in notes)


def test_the_reprojection_cost_does_not_tell_the_phase_through_video_clocks_ms_off() -> None:
    # World 1013 (seed of calibrate_worlds): video clocks 7.3 / 6.3 ms off under the two
    # conventions, an 8.5 ms exposure, costs 17,370 vs 22,370 for the wrong convention.
    costs, far, near, exposure = [1.737e4, 2.237e4], [7.25e6, 6.283e6], [0.6e6, 2.8e6], 8.5e6
    assert _pool_by_cost(costs, far, exposure, final=True) is None
    assert _pool_by_cost(costs, far, exposure, final=False) == 0  # the first pass seeds poses
    assert _pool_by_cost(costs, near, exposure, final=True) == 0
    assert _pool_by_cost([1.00e4, 1.02e4], near, exposure, final=True) is None  # within 3 %


# ------------------------------------------------------------------- DAVIS pairing by motion


def _motion_world(seed: int) -> tuple[DavisMotion, Callable[[npt.ArrayLike], F64]]:
    """A DAVIS whose clock is the Vicon's (identity mapping) watching markers that move in
    bursts; its image motion a saturating, noisy function of their displacement."""
    rng = np.random.default_rng(seed)
    t_v = np.arange(0, 30e9, 1e9 / 120)
    speed = np.zeros(t_v.size)
    for start in rng.uniform(1e9, 28e9, 25):
        burst = (t_v > start) & (t_v < start + rng.uniform(0.2e9, 0.8e9))
        speed[burst] += rng.uniform(0.3, 2.0)
    pos = np.cumsum(speed) / 120.0
    markers = np.stack([pos, np.zeros_like(pos), np.zeros_like(pos)], axis=-1)[:, None, :]

    def vicon_at(t: npt.ArrayLike) -> F64:
        tt = np.asarray(t, dtype=float)
        x = np.interp(tt, t_v, markers[:, 0, 0], left=np.nan, right=np.nan)
        return np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=-1)[:, None, :]

    t0 = np.arange(20e6, 29.5e9, 40e6)
    t1 = t0 + 40e6
    disp = np.abs(vicon_at(t1) - vicon_at(t0))[:, 0, 0]
    image = 3.0 + 40.0 * np.tanh(disp / 0.03) + rng.normal(0.0, 0.3, t0.size)
    return DavisMotion(t0.astype(np.int64), t1.astype(np.int64), image), vicon_at


@pytest.mark.parametrize("true_shift", [0, -3, 2])
def test_the_motion_finds_the_whole_period_shift_of_the_pulse_pairing(true_shift: int) -> None:
    motion, vicon_at = _motion_world(1)
    # The first-edge pairing is ``true_shift`` periods late.
    mapping = ClockMapping("davis/x", "vicon", round(-true_shift * PERIOD_NS), 0.0, 0)
    shift, note = motion_period_shift("davis/x", motion, mapping, vicon_at, PERIOD_NS)
    assert shift == true_shift
    assert "pulse pairing by the motion" in note


def test_motion_that_cannot_tell_the_periods_apart_is_refused_naming_the_pairing() -> None:
    motion, vicon_at = _motion_world(2)
    flat = DavisMotion(
        motion.t0_ns, motion.t1_ns, np.random.default_rng(0).normal(10.0, 0.3, motion.t0_ns.size)
    )
    mapping = ClockMapping("davis/x", "vicon", 0, 0.0, 0)
    with pytest.raises(CalibrationError, match="whole-period shift is unobservable"):
        motion_period_shift("davis/x", flat, mapping, vicon_at, PERIOD_NS)


# ------------------------------------------------------- pulse phase without the sync channel


def _cams(*modes: int) -> list[Any]:
    """Stand-ins for ``CalibCamera``: the helper reads name, sync mode and exposure only."""
    return [
        SimpleNamespace(name=f"d415/{k}", sync_mode=m, exposure_us=8500)
        for k, m in enumerate(modes)
    ]


def test_without_the_sync_channel_an_untold_phase_refuses_when_a_slave_depends_on_it() -> None:
    untold = ["clock: the video does not tell the pulse phase (...)"]
    with pytest.raises(CalibrationError, match="not observable") as err:
        _refuse_unobservable_phase(_cams(1, 2), [], CalibrationOptions(), list(untold))
    assert "--d415-pulse-at" in str(err.value)
    assert "d415/1" in str(err.value)
    notes = list(untold)
    _refuse_unobservable_phase(_cams(1, 2), [], CalibrationOptions(force=True), notes)
    assert any("NOT observable" in n for n in notes)
    # Nothing depends on it: a master alone, or cameras not on hardware sync.
    _refuse_unobservable_phase(_cams(1), [], CalibrationOptions(), list(untold))
    _refuse_unobservable_phase(_cams(0, 0), [], CalibrationOptions(), list(untold))
