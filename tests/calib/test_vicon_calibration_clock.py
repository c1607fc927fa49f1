"""The pooled D415 → Vicon clock of calib.vicon_calibration on synthetic stretches with truth."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
import numpy.typing as npt
import pytest

from mocaprig.calib.calibration import ClockMapping
from mocaprig.calib.vicon_calibration import _line_clock, _pooled_clocks, _tie_by_counters

PERIOD_NS = 33_333_333
VICON_DRIFT = 4.9e-6
VICON_OFFSET_NS = 5_000_000_000_000


Frames = dict[str, tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]]
Fits = dict[str, tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]]
ToVicon = Callable[[npt.ArrayLike], npt.NDArray[np.float64]]


def _rig(
    seed: int,
    *,
    garbage_cam: int | None = None,
    free_cam: int | None = None,
    slave_delay_ns: int = 100_000,
) -> tuple[Frames, Fits, dict[str, ToVicon]]:
    """Four cameras on one pulse train (30 s), d415/0 the master; returns frames, stretch
    fits, truth maps."""
    rng = np.random.default_rng(seed)
    n = 900
    t = np.arange(n) * PERIOD_NS + 12_345_678  # session ns of the master's exposures
    frames: Frames = {}
    fits: Fits = {}
    truth: dict[str, ToVicon] = {}
    for c in range(4):
        name = f"d415/{c}"
        drift = rng.uniform(-40e-6, 40e-6)
        offset = int(rng.integers(10**11, 4 * 10**12))
        delay = 0 if c == 0 else slave_delay_ns  # a slave exposes after the master
        tc = t + delay
        if c == free_cam:  # its trigger is cut after 10 s: it free-runs on its own period
            cut = 300
            own_period = PERIOD_NS / (1 + drift)  # 1/30 s of its own crystal
            tc = tc.astype(np.float64)
            tc[cut:] = tc[cut - 1] + 50e6 + np.arange(n - cut) * own_period
        dev = np.round(offset + tc * (1 + drift)).astype(np.int64)
        dev += rng.normal(0, 5_000, n).astype(np.int64)  # µs stamps, 5 µs jitter
        counters = np.arange(n, dtype=np.int64) + int(rng.integers(0, 100_000))
        keep = rng.random(n) > 0.02  # 2 % dropped frames
        frames[name] = (dev[keep], counters[keep])

        def to_vicon(
            d: npt.ArrayLike, offset: int = offset, drift: float = drift
        ) -> npt.NDArray[np.float64]:
            s = (np.asarray(d, dtype=np.float64) - offset) / (1 + drift)
            return VICON_OFFSET_NS + s * (1 + VICON_DRIFT)

        truth[name] = to_vicon
        # Stretches: 0.5 s of frames every ~2 s, offset error 0.3 ms (σ claimed 0.2 ms).
        t_w = dev[::60].astype(np.float64)
        d_w = to_vicon(t_w) - t_w + rng.normal(0, 300_000, len(t_w))
        if c == garbage_cam:  # most stretches converged on a wrong frame
            bad = rng.random(len(t_w)) < 0.6
            d_w[bad] += rng.uniform(-35e6, -10e6, bad.sum())
        fits[name] = (t_w, d_w, np.full(len(t_w), 200_000.0))
    return frames, fits, truth


def _own(fits: Fits) -> dict[str, ClockMapping]:
    return {n: _line_clock(n, *f) for n, f in fits.items()}


def _score(truth: dict[str, ToVicon]) -> Callable[[str, ClockMapping], float]:
    # What the reprojection cost measures: how far a mapping is from the truth (ns).
    def score(name: str, m: ClockMapping) -> float:
        d = np.linspace(0, 30e9, 50) + float(m.anchor_ns)
        return float(np.abs(m.to_reference_ns(d.round()) - truth[name](d)).mean())

    return score


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pooled_clock_ties_synchronised_cameras_and_outvotes_a_poor_one(seed: int) -> None:
    frames, fits, truth = _rig(seed, garbage_cam=2)
    maps, notes = _pooled_clocks(frames, fits, _own(fits), _score(truth))
    assert "4 hardware-synchronised cameras" in notes[-1]
    for name, m in maps.items():
        d = frames[name][0].astype(np.float64)
        err = m.to_reference_ns(d.round().astype(np.int64)) - truth[name](d)
        assert np.abs(err).max() < 400_000, name  # < 0.4 ms over the whole session
        assert m.method.startswith("reprojection, pooled")
    # The pooled drift is as good as the best camera's own line, not dragged by the poor one.
    own = _own(fits)
    d = frames["d415/2"][0].astype(np.float64)
    own_err = own["d415/2"].to_reference_ns(d.round().astype(np.int64)) - truth["d415/2"](d)
    assert np.abs(own_err).max() > 1_000_000  # its own line is off by more than a ms


def test_pooled_clock_drift_beats_the_single_camera_lines() -> None:
    def drift_err_ppm(m: ClockMapping, to_vicon: ToVicon) -> float:
        a = np.array([m.anchor_ns, m.anchor_ns + 20e9])
        mapped = m.to_reference_ns(a.round().astype(np.int64)).astype(np.float64)
        true = to_vicon(a)
        return abs(float((mapped[1] - mapped[0]) - (true[1] - true[0]))) / 20e9 * 1e6

    pooled, single = [], []
    for seed in range(6):
        frames, fits, truth = _rig(seed)
        maps, _ = _pooled_clocks(frames, fits, _own(fits), _score(truth))
        own = _own(fits)
        pooled += [drift_err_ppm(maps[n], truth[n]) for n in maps]
        single += [drift_err_ppm(own[n], truth[n]) for n in maps]
    # Four cameras' stretches with independent errors: about half the single-camera error.
    assert np.mean(pooled) < 0.7 * np.mean(single)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_slaves_keep_the_conventions_delay_that_their_stretches_cannot_resolve(seed: int) -> None:
    # Pulse at the master's readout start: a slave's stamp comes an exposure (8.5 ms) and its
    # trigger delay (here 820 µs, the convention's 770 µs + 50 µs) after the master's.
    frames, fits, truth = _rig(seed, slave_delay_ns=8_500_000 + 820_000)

    def worst_us(expected: dict[str, float]) -> float:
        maps, _ = _pooled_clocks(
            frames, fits, _own(fits), _score(truth), expected_delays_ns=expected
        )
        errs = []
        for name, m in maps.items():
            d = frames[name][0]
            errs.append(float(np.abs(m.to_reference_ns(d) - truth[name](d)).max()) / 1e3)
        return max(errs)

    slaves = [f"d415/{c}" for c in (1, 2, 3)]
    convention = worst_us(dict.fromkeys(slaves, 8_500_000.0 + 770_000.0))
    assert convention < 300.0
    # Expecting the exposure alone leaves the 0.77 ms trigger delay to the stretches, whose
    # 0.3 ms errors cannot place it as well.
    assert worst_us(dict.fromkeys(slaves, 8_500_000.0)) > 1.5 * convention


def test_a_slave_whose_trigger_is_cut_keeps_its_own_clock_and_is_named() -> None:
    frames, fits, truth = _rig(3, free_cam=1)
    maps, notes = _pooled_clocks(frames, fits, _own(fits), _score(truth))
    assert maps["d415/1"].method == "reprojection"
    assert any(n.startswith("d415/1: clock fitted on its own") for n in notes)
    assert "pooled over 3" in maps["d415/0"].method


def test_a_camera_recorded_in_sync_mode_0_is_not_pooled() -> None:
    frames, fits, truth = _rig(5)
    modes = {"d415/0": 1, "d415/1": 2, "d415/2": 0, "d415/3": None}
    maps, notes = _pooled_clocks(frames, fits, _own(fits), _score(truth), modes)
    assert maps["d415/2"].method == "reprojection"
    assert any("inter_cam_sync_mode 0" in n for n in notes)
    assert "pooled over 3" in maps["d415/3"].method


def test_tie_by_counters_recovers_the_relative_rate_for_any_period_shift() -> None:
    frames, _, truth = _rig(4)
    t_c, n_c = frames["d415/1"]
    t_p, n_p = frames["d415/0"]
    # Same instants share the counter offset of the two cameras' first frames (no drop there).
    shift = int(n_c[0] - n_p[0])
    ties = [_tie_by_counters(t_c, n_c, t_p, n_p, k) for k in range(shift - 2, shift + 3)]
    assert all(t is not None and t.rms_ns < 20_000 for t in ties)
    rates = np.array([t.s for t in ties if t is not None])
    # A whole-period shift moves the line, never its slope (< 0.05 ppm apart) ...
    assert np.ptp(rates) < 5e-8
    # ... which is the clocks' true relative rate d t_p / d t_c − 1.
    span = np.array([0.0, 1e10])
    dv_dc = np.diff(truth["d415/1"](span + float(t_c[0])))[0] / 1e10
    dv_dp = np.diff(truth["d415/0"](span + float(t_p[0])))[0] / 1e10
    assert abs(rates.mean() - (dv_dc / dv_dp - 1.0)) < 1e-7  # 0.1 ppm


@pytest.mark.parametrize("seed", [0, 3])
def test_a_tie_scored_through_a_poor_pivot_line_is_corrected_through_the_pooled_clock(
    seed: int,
) -> None:
    frames, fits, truth = _rig(seed)
    # The pivot camera has the most stretches (every 15th frame) but its own line is 40 ms
    # (1.2 frame periods) off, as when its line's fit converged on neighbouring frames:
    # through it, the other cameras' counter shifts come out a period wrong.
    own = _own(fits)
    pivot = min(own, key=lambda n: own[n].drift_sigma_ppm)
    t_w = frames[pivot][0][::15].astype(np.float64)
    noise = np.random.default_rng(seed).normal(0, 300_000, len(t_w))
    fits[pivot] = (t_w, truth[pivot](t_w) - t_w + noise, np.full(len(t_w), 200_000.0))
    own = _own(fits)
    pivot = min(own, key=lambda n: own[n].drift_sigma_ppm)
    own[pivot] = dataclasses.replace(own[pivot], offset_ns=own[pivot].offset_ns + 40_000_000)
    maps, notes = _pooled_clocks(frames, fits, own, _score(truth))
    assert any("frame tie shifts corrected through the pooled clock" in n for n in notes)
    for name, m in maps.items():
        d = frames[name][0]
        assert np.abs(m.to_reference_ns(d) - truth[name](d)).max() < 400_000, name
