"""Tests of process.eventcap.metrics: AE vs MPJPE, frame selection, baseline, Size.sec."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocaprig.acquire.events import EVENT_DTYPE, make_events
from mocaprig.acquire.rpg_text import read_events_txt
from mocaprig.errors import ValidationError
from mocaprig.process.eventcap.metrics import (
    DAVIS240C_FRAME_BYTES,
    MB,
    data_rate,
    davis_usb_event_bytes,
    evaluate_tracking,
    upsample_linear,
)
from mocaprig.process.metrics import procrustes_align


def _truth(frames: int, seed: int = 0) -> np.ndarray:
    """(F, 15, 3) mm: a random body-sized point set drifting smoothly."""
    rng = np.random.default_rng(seed)
    base = rng.normal(scale=300.0, size=(15, 3))
    drift = np.linspace(0.0, 500.0, frames)[:, None, None] * np.array([1.0, 0.3, 0.0])
    return np.asarray(base[None] + drift, np.float64)


def _rigidly_moved(points: np.ndarray, seed: int) -> np.ndarray:
    rot = Rotation.random(points.shape[0], rng=np.random.default_rng(seed)).as_matrix()
    moved = np.einsum("fij,fkj->fki", rot, points) + np.array([100.0, -50.0, 2000.0])
    return np.asarray(moved, np.float64)


def test_ae_is_zero_for_a_rigidly_moved_truth_while_mpjpe_is_not() -> None:
    true = _truth(100)
    pred = _rigidly_moved(true, 1)
    err = evaluate_tracking(pred, true)
    assert err.ae_mean_mm < 1e-6
    assert err.mpjpe_mean_mm > 1000.0


def test_alignment_never_increases_the_rms_error_and_ae_stays_below_mpjpe() -> None:
    rng = np.random.default_rng(2)
    true = _truth(200, seed=3)
    pred = true + rng.normal(scale=40.0, size=true.shape) + np.array([30.0, 0.0, -20.0])
    rigid = procrustes_align(pred[::10], true[::10])
    scaled = procrustes_align(pred[::10], true[::10], with_scale=True)

    def rms(a: np.ndarray) -> np.ndarray:
        return np.asarray(np.sqrt(np.mean(np.sum((a - true[::10]) ** 2, axis=-1), axis=1)))

    # Procrustes minimises the squared error; identity (and rigid, for the scaled fit) is feasible
    assert np.all(rms(rigid.aligned) <= rms(pred[::10]) + 1e-9)
    assert np.all(rms(scaled.aligned) <= rms(rigid.aligned) + 1e-9)
    err = evaluate_tracking(pred, true)
    assert err.ae_mean_mm < err.mpjpe_mean_mm
    np.testing.assert_allclose(
        err.ae_mm, np.linalg.norm(rigid.aligned - true[::10], axis=-1).mean(axis=1)
    )


def test_every_tenth_frame_is_evaluated_and_other_rows_may_be_nan() -> None:
    true = _truth(95)
    pred = true + 10.0
    true_sparse = np.full_like(true, np.nan)
    true_sparse[::10] = true[::10]
    err = evaluate_tracking(pred, true_sparse)
    assert err.frame_indices.tolist() == list(range(0, 95, 10))
    np.testing.assert_allclose(err.mpjpe_mm, np.sqrt(300.0))


def test_nan_in_an_evaluated_frame_is_refused() -> None:
    true = _truth(30)
    true[20, 3, 0] = np.nan
    with pytest.raises(ValidationError, match="true_mm \\(evaluated frames\\)"):
        evaluate_tracking(_truth(30), true)


def test_per_batch_means_and_raw_vs_latent_frames() -> None:
    true = _truth(120)
    pred = true.copy()
    # absolute error 5 mm everywhere, plus 20 mm more in batch 1 (frames 40..79)
    pred[..., 0] += 5.0
    pred[40:80, :, 2] += 20.0
    err = evaluate_tracking(pred, true, step=10, batch_frames=40)
    assert err.batch_indices.tolist() == [0, 1, 2]
    np.testing.assert_allclose(err.batch_mpjpe_mm, [5.0, np.hypot(5.0, 20.0), 5.0])
    assert err.ae_raw_mean_mm is not None
    assert err.ae_nonraw_mean_mm is not None
    assert err.ae_raw_mean_mm == pytest.approx(err.ae_mm[err.frame_indices % 40 == 0].mean())
    assert err.ae_nonraw_mean_mm == pytest.approx(err.ae_mm[err.frame_indices % 40 != 0].mean())


def test_mean_and_std_are_over_evaluated_frames() -> None:
    true = _truth(50)
    pred = true.copy()
    offsets = np.arange(50, dtype=np.float64)
    pred[..., 0] += offsets[:, None]
    err = evaluate_tracking(pred, true, step=10)
    np.testing.assert_allclose(err.mpjpe_mm, [0, 10, 20, 30, 40])
    assert err.mpjpe_mean_mm == pytest.approx(20.0)
    assert err.mpjpe_std_mm == pytest.approx(np.std([0, 10, 20, 30, 40]))


def test_summary_says_which_alignment_was_used() -> None:
    true = _truth(20)
    assert "rigid (R, t)" in evaluate_tracking(true + 1.0, true).summary()
    assert "similarity" in evaluate_tracking(true + 1.0, true, with_scale=True).summary()


def test_bad_step_is_refused() -> None:
    with pytest.raises(ValidationError, match="step >= 1"):
        evaluate_tracking(_truth(5), _truth(5), step=0)


def test_upsample_linear_hits_the_keys_and_interpolates_between_them() -> None:
    keys = np.array([[[0.0, 0.0, 0.0]], [[40.0, -8.0, 4.0]], [[40.0, 0.0, 0.0]]])
    out = upsample_linear([0, 40_000, 80_000], keys, np.array([0, 10_000, 40_000, 60_000]))
    np.testing.assert_allclose(out[:, 0], [[0, 0, 0], [10, -2, 1], [40, -8, 4], [40, -4, 2]])


def test_upsample_linear_does_not_extrapolate() -> None:
    with pytest.raises(ValidationError, match="does not extrapolate"):
        upsample_linear([0, 1000], np.zeros((2, 1, 3)), np.array([1001]))


# --- Size.sec --------------------------------------------------------------------------------


def test_paper_units_are_binary_megabytes() -> None:
    # the paper: one minute of VGA RGB at 1000 fps "yields 51.5GB"
    assert pytest.approx(51.5, abs=0.05) == 640 * 480 * 3 * 1000 * 60 / 2**30
    assert MB == 2**20


def test_canonical_size_is_13_bytes_per_event_plus_frames() -> None:
    n = 1000
    ev = make_events(np.arange(n) * 100, np.zeros(n), np.zeros(n), np.ones(n))
    dr = data_rate(ev, t_start_us=0, t_end_us=100_000, n_aps_frames=3)
    assert EVENT_DTYPE.itemsize == 13
    assert dr.event_bytes == 13_000
    assert dr.aps_bytes == 3 * 43_200
    assert dr.ours_bytes_per_s == pytest.approx((13_000 + 129_600) / 0.1)
    assert dr.reference_bytes_per_s == 1000 * DAVIS240C_FRAME_BYTES
    assert dr.reference_bytes_per_s / MB == pytest.approx(41.199, abs=1e-3)
    assert dr.ratio == pytest.approx(1_426_000 / 43_200_000)


def test_only_events_inside_the_interval_are_counted() -> None:
    ev = make_events([5, 10, 20, 30], [0, 0, 0, 0], [0, 0, 0, 0], [1, 1, 1, 1])
    dr = data_rate(ev, t_start_us=10, t_end_us=30, n_aps_frames=0)
    assert dr.n_events == 2
    assert dr.duration_us == 20


def test_davis_usb_words_for_a_hand_built_stream() -> None:
    # t=1: rows 3 (2 events) and 4 -> 1 timestamp + 2 Y + 3 X words;
    # t=2: row 3 -> 1 timestamp + 1 Y + 1 X; t=32768: row 0 -> a wrap, 1 Y + 1 X, no timestamp
    ev = make_events([1, 1, 1, 2, 32768], [5, 6, 7, 5, 0], [3, 3, 4, 3, 0], [1, 0, 1, 1, 0])
    words = (1 + 2 + 3) + (1 + 1 + 1) + (1 + 1 + 1)
    assert davis_usb_event_bytes(ev) == 2 * words


def test_davis_usb_size_matches_the_mock_device_encoder() -> None:
    from mocaprig.drivers_mock.davis240c_encoder import DavisWordEncoder
    from mocaprig.drivers_mock.davis_activity import DavisActivity

    rng = np.random.default_rng(4)
    n, span = 4000, 150_000
    t = np.sort(rng.integers(1, span, n))
    ev = make_events(t, rng.integers(0, 240, n), rng.integers(0, 180, n), rng.integers(0, 2, n))
    enc = DavisWordEncoder(latency_us=0)
    stream = enc.encode(DavisActivity(0, span, ev)) + enc.flush()
    assert davis_usb_event_bytes(ev) == len(stream)


def test_unsorted_events_are_refused() -> None:
    ev = make_events([5, 1], [0, 0], [0, 0], [1, 1])
    with pytest.raises(ValidationError, match="not sorted"):
        data_rate(ev, t_start_us=0, t_end_us=10, n_aps_frames=0)


def test_size_sec_of_the_real_davis240c_chunk(shared_data: Path) -> None:
    folder = shared_data / "events" / "ecd_shapes_rotation_0to500ms"
    ev = read_events_txt(folder / "events.txt").events
    frame_t_s = [float(line.split()[0]) for line in (folder / "images.txt").read_text().split("\n")
                 if line.strip()]  # fmt: skip
    t0, t1 = 0, 500_000
    n_frames = sum(1 for t in frame_t_s if t0 <= t * 1e6 < t1)
    canon = data_rate(ev, t_start_us=t0, t_end_us=t1, n_aps_frames=n_frames)
    usb = data_rate(
        ev, t_start_us=t0, t_end_us=t1, n_aps_frames=n_frames, event_encoding="davis_usb"
    )
    assert canon.n_events == 9058
    assert n_frames == 11
    # sparse jitter events: nearly every event has its own µs, so about 3 words (6 B) each
    assert 4.0 < usb.bytes_per_event < 8.0
    assert usb.ours_bytes_per_s < canon.ours_bytes_per_s
    assert canon.ratio < 0.05  # a few % of 1000 fps frames, as in the paper
