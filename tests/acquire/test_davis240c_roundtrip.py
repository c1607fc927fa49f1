"""Decoder vs engineer B's independent word encoder (both written from the note, not each other):
a hypothesis round trip on random activity, and an acceptance test through
``mocaprig davis decode``."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mocaprig.acquire.commands import load_decoded
from mocaprig.acquire.davis240c_decode import ApsFrame, DavisDecoder, SpecialType
from mocaprig.acquire.events import make_events
from mocaprig.cli import main
from mocaprig.drivers_mock.davis240c_encoder import DavisWordEncoder, EncoderConfig
from mocaprig.drivers_mock.davis_activity import (
    EXT_INPUT_DTYPE,
    IMU_DTYPE,
    ApsExposure,
    DavisActivity,
    ExtInputEdge,
)

CONFIG = EncoderConfig(detect_rising_edges=True, detect_falling_edges=True, detect_pulses=True)
_RISING, _FALLING, _PULSE = (
    SpecialType.EXTERNAL_INPUT_RISING_EDGE,
    SpecialType.EXTERNAL_INPUT_FALLING_EDGE,
    SpecialType.EXTERNAL_INPUT_PULSE,
)


def sort_events(ev: npt.NDArray[np.void]) -> npt.NDArray[np.void]:
    return ev[np.lexsort((ev["p"], ev["x"], ev["y"], ev["t"]))]


def expected_ext(edges: npt.NDArray[np.void]) -> list[tuple[int, int]]:
    """Specials the note's detector (§11.2) reports for these edges (active-high, >= 10 µs)."""
    out: list[tuple[int, int]] = []
    high_since: int | None = None
    for t, kind in zip(edges["t"].tolist(), edges["edge"].tolist(), strict=True):
        if kind == ExtInputEdge.PULSE:
            out.append((t, _PULSE))
        elif kind == ExtInputEdge.RISING:
            out.append((t, _RISING))
            high_since = t
        else:
            out.append((t, _FALLING))
            if high_since is not None and t - high_since >= 10:
                out.append((t, _PULSE))
            high_since = None
    return out


def ext_specials(specials: npt.NDArray[np.void]) -> list[tuple[int, int]]:
    keep = np.isin(specials["type"], [_RISING, _FALLING, _PULSE])
    return [(int(s["t"]), int(s["type"])) for s in specials[keep]]


def reported_at(got_us: int, due_us: int, *, wrap_race: bool) -> bool:
    """Whether a word due at ``due_us`` may be reported at ``got_us``: exactly, or, with the
    wrap race (note §7.1), 1 µs early when it falls on a rollover (latched, stamped 0xFFFF)."""
    early = wrap_race and due_us > 0 and due_us % 32768 == 0 and got_us == due_us - 1
    return got_us == due_us or early


def race_canonical(t_us: npt.ArrayLike, *, wrap_race: bool) -> npt.NDArray[np.int64]:
    """Times with the wrap race's one allowed error folded away (note §7.1): a word due on a
    rollover (t % 32768 == 0, t > 0) may arrive 1 µs early, so both are mapped to t - 1."""
    t = np.asarray(t_us, dtype=np.int64).copy()
    if wrap_race:
        t[(t > 0) & (t % 32768 == 0)] -= 1
    return t


def check_frame(frame: ApsFrame, exposure: ApsExposure, *, wrap_race: bool = False) -> None:
    assert reported_at(frame.t_start_exposure_us, exposure.start_us, wrap_race=wrap_race)
    assert reported_at(frame.t_end_exposure_us, exposure.end_us, wrap_race=wrap_race)
    assert frame.exposure_cycles == (exposure.end_us - exposure.start_us) * 30
    assert frame.pixels.shape == (180, 240)
    # reset - signal is sent as two 10-bit reads and doubled by the host: ±1 count of rounding.
    assert np.abs(frame.pixels.astype(np.int64) - exposure.cds).max() <= 1


# -- random activity ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Segment:
    """Windows between two timestamp resets (device time restarts at 0)."""

    windows: tuple[DavisActivity, ...]


@st.composite
def windows(draw: st.DrawFn, *, last: bool) -> Segment:
    out = []
    t0 = 0
    for _ in range(draw(st.integers(1, 3))):
        length = draw(st.sampled_from([1000, 20_000, 100_000, 300_000]))
        t1 = t0 + length
        n = draw(st.integers(0, 150))
        seed = draw(st.integers(0, 2**32 - 1))
        rng = np.random.default_rng(seed)
        ev = make_events(
            np.sort(rng.integers(t0, t1, n)),
            rng.integers(0, 240, n),
            rng.integers(0, 180, n),
            rng.integers(0, 2, n),
        )
        k = draw(st.integers(0, 4))
        imu = np.zeros(k, IMU_DTYPE)
        imu["t"] = np.sort(rng.choice(np.arange(t0, t1), k, replace=False))
        imu["accel_g"] = rng.uniform(-3.9, 3.9, (k, 3))
        imu["gyro_dps"] = rng.uniform(-450, 450, (k, 3))
        imu["temp_c"] = rng.uniform(15, 45, k)
        m = draw(st.integers(0, 4))
        ext = np.zeros(m, EXT_INPUT_DTYPE)
        ext["t"] = np.sort(rng.choice(np.arange(t0, t1), m, replace=False))
        ext["edge"] = rng.integers(1, 4, m)
        exposures: tuple[ApsExposure, ...] = ()
        # A frame's signal read ends ~20 ms after its exposure; a reset cuts it off.
        room = t1 - (0 if last else 30_000)
        if length >= 100_000 and draw(st.booleans()) and room - 5000 > t0 + 25_000:
            end = draw(st.integers(t0 + 25_000, room - 5000))
            cds = rng.integers(0, 1000, (180, 240)).astype(np.float64)
            exposures = (ApsExposure(start_us=end - 4000, end_us=end, cds=cds),)
        out.append(
            DavisActivity(
                t0_us=t0, t1_us=t1, events=ev, exposures=exposures, imu=imu, ext_input=ext
            )
        )
        t0 = t1 + draw(st.sampled_from([0, 0, 5, 40_000, 200_000]))
    return Segment(tuple(out))


@st.composite
def streams(draw: st.DrawFn) -> list[Segment]:
    n = draw(st.integers(1, 3))
    return [draw(windows(last=i == n - 1)) for i in range(n)]


@settings(
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(segments=streams(), wrap_race=st.booleans(), chunk=st.sampled_from([511, 4096, 65536]))
def test_decoder_inverts_the_independent_encoder(
    segments: list[Segment], wrap_race: bool, chunk: int
) -> None:
    enc = DavisWordEncoder(CONFIG, wrap_race=wrap_race, seed=1)
    parts = []
    for i, seg in enumerate(segments):
        parts += [enc.encode(w) for w in seg.windows]
        if i < len(segments) - 1:
            parts.append(enc.reset_timestamps())
    parts.append(enc.flush())
    data = b"".join(parts)
    dec = DavisDecoder()
    pkts = [dec.decode(data[i : i + chunk]) for i in range(0, len(data), chunk)]
    pkts.append(dec.decode(b""))
    s = dec.stats
    assert s.skipped_words == 0
    assert s.timestamp_resets == len(segments) - 1
    assert s.frames_dropped == 0
    assert s.imu_samples_dropped == 0
    events = np.concatenate([p.events for p in pkts])
    specials = np.concatenate([p.specials for p in pkts])
    imu = np.concatenate([p.imu for p in pkts])
    frames = [f for p in pkts for f in p.frames]
    want_events = [np.concatenate([w.events for w in seg.windows]) for seg in segments]
    assert events.size == sum(w.size for w in want_events)
    # Stream order is segment order (time restarts at 0 after each reset).
    bounds = np.cumsum([w.size for w in want_events])[:-1]
    for got_seg, want_seg in zip(np.split(events, bounds), want_events, strict=True):
        got_seg, want_seg = got_seg.copy(), want_seg.copy()
        got_seg["t"] = race_canonical(got_seg["t"], wrap_race=wrap_race)
        want_seg["t"] = race_canonical(want_seg["t"], wrap_race=wrap_race)
        np.testing.assert_array_equal(sort_events(got_seg), sort_events(want_seg))
    want_ext = [
        expected_ext(np.concatenate([w.ext_input for w in seg.windows])) for seg in segments
    ]
    got_ext = ext_specials(specials)
    want_flat = [x for seg in want_ext for x in seg]
    assert [(int(race_canonical([t], wrap_race=wrap_race)[0]), k) for t, k in got_ext] == [
        (int(race_canonical([t], wrap_race=wrap_race)[0]), k) for t, k in want_flat
    ]
    want_imu = np.concatenate([w.imu for seg in segments for w in seg.windows])
    assert imu.size == want_imu.size
    np.testing.assert_array_equal(
        race_canonical(imu["t"], wrap_race=wrap_race),
        race_canonical(want_imu["t"], wrap_race=wrap_race),
    )
    np.testing.assert_allclose(imu["accel_g"], want_imu["accel_g"], atol=0.5 / 8192)
    np.testing.assert_allclose(imu["gyro_dps"], want_imu["gyro_dps"], atol=0.5 / 65.536)
    np.testing.assert_allclose(imu["temp_c"], want_imu["temp_c"], atol=0.5 / 340)
    want_frames = [e for seg in segments for w in seg.windows for e in w.exposures]
    assert len(frames) == len(want_frames)
    for f, e in zip(frames, want_frames, strict=True):
        check_frame(f, e, wrap_race=wrap_race)


# -- acceptance: a raw stream through `mocaprig davis decode` -------------------------------------


def _window(t0: int, t1: int, *, seed: int, n: int, **extra: object) -> DavisActivity:
    rng = np.random.default_rng(seed)
    ev = make_events(
        np.sort(rng.integers(t0, t1, n)),
        rng.integers(0, 240, n),
        rng.integers(0, 180, n),
        rng.integers(0, 2, n),
    )
    return DavisActivity(t0_us=t0, t1_us=t1, events=ev, **extra)  # type: ignore[arg-type]


@pytest.mark.parametrize("wrap_race", [False, True])
def test_exposure_ending_on_a_rollover_is_latched_one_microsecond_early_by_the_race(
    wrap_race: bool,
) -> None:
    """Note §7.1: a word due exactly at a rollover, latched before the WRAP, is stamped 0xFFFF:
    the exposure that ends at 32768 µs is reported at 32767 µs."""
    cds = np.random.default_rng(3).integers(0, 1000, (180, 240)).astype(np.float64)
    exposure = ApsExposure(start_us=28_768, end_us=32_768, cds=cds)
    enc = DavisWordEncoder(CONFIG, wrap_race=wrap_race, seed=1)
    empty = {"imu": np.zeros(0, IMU_DTYPE), "ext_input": np.zeros(0, EXT_INPUT_DTYPE)}
    data = enc.encode(_window(0, 100_000, seed=0, n=0, exposures=(exposure,), **empty))
    data += enc.encode(_window(100_000, 101_000, seed=0, n=0, **empty)) + enc.flush()
    dec = DavisDecoder()
    frames = [*dec.decode(data).frames, *dec.decode(b"").frames]
    assert len(frames) == 1
    assert frames[0].t_start_exposure_us == 28_768
    assert frames[0].t_end_exposure_us == (32_767 if wrap_race else 32_768)
    check_frame(frames[0], exposure, wrap_race=wrap_race)


def test_acceptance_independent_encoder_stream_decodes_exactly_through_the_cli(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    big = 1 << 31
    rng = np.random.default_rng(7)
    cds = rng.integers(0, 1000, (180, 240)).astype(np.float64)
    exposure = ApsExposure(start_us=50_000, end_us=54_000, cds=cds)
    imu = np.zeros(50, IMU_DTYPE)
    imu["t"] = np.arange(1, 51) * 1000
    imu["accel_g"] = [0.0, -1.0, 0.0]
    imu["gyro_dps"] = [10.0, -20.0, 30.0]
    imu["temp_c"] = 31.0
    ext = np.zeros(3, EXT_INPUT_DTYPE)
    ext["t"] = [10_000, 10_060, 30_000]
    ext["edge"] = [ExtInputEdge.RISING, ExtInputEdge.FALLING, ExtInputEdge.PULSE]
    seg1 = [
        _window(0, 100_000, seed=1, n=5000, exposures=(exposure,), imu=imu, ext_input=ext),
        _window(100_000, 200_000, seed=2, n=3000),
        _window(200_000, big - 1000, seed=3, n=200),  # 35.8 min: wraps up to the big wrap
        _window(big - 1000, big + 100_000, seed=4, n=2000),
    ]
    seg2 = [_window(0, 70_000, seed=5, n=4000, imu=imu[:5])]
    enc = DavisWordEncoder(CONFIG, seed=2)
    data = b"".join(
        [
            *(enc.encode(w) for w in seg1),
            enc.reset_timestamps(),
            *(enc.encode(w) for w in seg2),
            enc.flush(),
        ]
    )
    raw = tmp_path / "capture.bin"
    raw.write_bytes(data)
    out = tmp_path / "decoded.npz"

    assert main(["davis", "decode", str(raw), "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    got = load_decoded(out)

    want1 = np.concatenate([w.events for w in seg1])
    want2 = seg2[0].events
    events = got["events"]
    n1 = want1.size
    np.testing.assert_array_equal(sort_events(events[:n1]), sort_events(want1))
    np.testing.assert_array_equal(sort_events(events[n1:]), sort_events(want2))
    assert events["t"][:n1].max() > big  # 64-bit time across the big wrap
    assert summary["events"] == n1 + want2.size
    assert summary["skipped_words"] == 0
    assert summary["bytes"] == len(data)
    assert summary["frames"] == 1
    assert summary["imu_samples"] == 55
    assert summary["specials"]["TIMESTAMP_RESET"] == 1
    assert summary["specials"]["TIMESTAMP_WRAP"] == 1

    sp = got["specials"]
    assert [(int(s["t"]), int(s["type"])) for s in sp if s["type"] in (0, 1)] == [
        (big - 1, SpecialType.TIMESTAMP_WRAP),
        (0, SpecialType.TIMESTAMP_RESET),
    ]
    assert ext_specials(sp) == [
        (10000, _RISING),
        (10060, _FALLING),
        (10060, _PULSE),
        (30000, _PULSE),
    ]
    exp_marks = [(int(s["t"]), int(s["type"])) for s in sp if s["type"] in (16, 17)]
    assert exp_marks == [
        (50_000, SpecialType.APS_EXPOSURE_START),
        (54_000, SpecialType.APS_EXPOSURE_END),
    ]
    (frame,) = got["frames"]
    check_frame(frame, exposure)

    im = got["imu"]
    np.testing.assert_array_equal(im["t"], np.concatenate([imu["t"], imu["t"][:5]]))
    np.testing.assert_allclose(im["accel_g"], np.tile([0.0, -1.0, 0.0], (55, 1)))
    np.testing.assert_allclose(im["gyro_dps"], np.tile([10.0, -20.0, 30.0], (55, 1)), atol=0.01)
    np.testing.assert_allclose(im["temp_c"], 31.0, atol=0.5 / 340)
    assert json.dumps(summary)  # plain JSON
