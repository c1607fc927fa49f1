"""The per-stretch video clock offsets of calib.vicon_calibration_video_clock on a synthetic
camera with truth: a stretch's σ covers a blob bias that does not average down (bias / image
speed), and the clock's windows go where the Vicon markers move."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.device_streams import D415Settings
from mocaprig.calib.markers import MarkerFrame
from mocaprig.calib.registration import project_points
from mocaprig.calib.vicon_calibration import _busiest_windows
from mocaprig.calib.vicon_calibration_frames import CalibCamera
from mocaprig.calib.vicon_calibration_video_clock import (
    STRETCH_BIAS_PX,
    ViconInterp,
    stretch_offsets,
)

F64 = npt.NDArray[np.float64]
OFFSET_NS = 7_000_000_000  # device → Vicon, the truth
PERIOD_NS = 33_333_333


def _camera() -> tuple[CalibCamera, F64]:
    K = np.array([[640.0, 0.0, 424.0], [0.0, 640.0, 240.0], [0.0, 0.0, 1.0]])
    cam = CalibCamera(
        name="d415/1",
        serial="1",
        width=848,
        height=480,
        K=K,
        dist=np.zeros(5),
        settings=D415Settings(serial="1"),
    )
    # Camera 3 m in front of the markers, looking along +y of the world.
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # cam → world
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [0.0, -3.0, 1.0]
    return cam, T


def _vicon(speed_m_s: float, seconds: float = 2.0) -> tuple[npt.NDArray[np.int64], F64]:
    """Eight markers on a circle of 0.3 m about (0, 0, 1) m, turning at ``speed_m_s``
    (Vicon 100 Hz, Vicon clock ns)."""
    t = np.arange(0, round(seconds * 100) + 1) * 10_000_000 + 1_000_000_000
    w = speed_m_s / 0.3
    ang = w * (t - t[0]) * 1e-9
    phase = np.arange(8) * 2 * np.pi / 8
    a = ang[:, None] + phase[None, :]
    p = np.stack([0.3 * np.cos(a), 0.3 * np.sin(a) * 0.2, 1.0 + 0.3 * np.sin(a)], axis=2)
    return t, p


def _frames(
    cam: CalibCamera, T: F64, interp: ViconInterp, rng: np.random.Generator, bias_px: F64
) -> list[MarkerFrame]:
    t_dev = np.arange(1_100_000_000, 2_800_000_000, PERIOD_NS) - OFFSET_NS
    out = []
    for k, td in enumerate(t_dev):
        p = interp.at(np.array([td + OFFSET_NS]))[0]
        uv, _ = project_points(p, T, cam.K, cam.dist)
        uv = uv + bias_px + rng.normal(0.0, 0.1, uv.shape)
        uv = uv[np.isfinite(uv).all(axis=1)]  # no truth to draw its blob from
        out.append(
            MarkerFrame(
                camera=cam.name,
                t_dev_ns=int(td),
                frame_counter=k,
                uv_px=uv,
                xyz_cam_m=np.full((len(uv), 3), np.nan),
                area_px=np.full(len(uv), 20.0),
            )
        )
    return out


def _stretches(speed_m_s: float, seed: int) -> tuple[F64, F64]:
    """(offset error ns, σ ns) per stretch for markers at ``speed_m_s`` whose blobs carry a
    fixed per-marker bias of 0.3 px."""
    rng = np.random.default_rng(seed)
    cam, T = _camera()
    t, p = _vicon(speed_m_s)
    interp = ViconInterp(t, p)
    bias = rng.normal(0.0, 0.3, (8, 2))
    frames = _frames(cam, T, interp, rng, bias)
    _, d, s = stretch_offsets(cam, frames, T, interp, OFFSET_NS + 2_000_000, None)
    return d - OFFSET_NS, s


def test_a_stretch_sigma_covers_a_blob_bias_that_does_not_average_down() -> None:
    for seed in range(3):
        slow_err, slow_sig = _stretches(0.05, seed)
        fast_err, fast_sig = _stretches(1.0, seed)
        # The error a fixed bias makes scales as 1 / speed, and σ follows it.
        assert np.all(np.abs(slow_err) <= 3.0 * slow_sig), (slow_err, slow_sig)
        assert np.all(np.abs(fast_err) <= 3.0 * fast_sig), (fast_err, fast_sig)
        assert np.median(slow_sig) > 10.0 * np.median(fast_sig)
        # 0.2 px over 0.05 m/s at 3 m with f = 640 px (≈ 0.011 px/ms): ≥ 10 ms.
        assert np.all(slow_sig > 0.5 * STRETCH_BIAS_PX / (0.05 * 640 / 3.0) * 1e9)


def test_a_stretch_beside_a_vicon_gap_gets_a_finite_nonzero_sigma() -> None:
    rng = np.random.default_rng(4)
    cam, T = _camera()
    t, p = _vicon(0.5)
    p = p.copy()
    p[60:64, 2] = np.nan  # marker 2 in a gap for 40 ms
    interp = ViconInterp(t, p)
    frames = _frames(cam, T, interp, rng, np.zeros((8, 2)))
    _, d, s = stretch_offsets(cam, frames, T, interp, OFFSET_NS + 1_000_000, None)
    assert np.all(np.isfinite(s)), s
    assert np.all(s > 10_000.0), s
    assert np.all(np.abs(d - OFFSET_NS) <= 3.0 * s)


def test_the_clock_window_moves_to_where_the_markers_move_within_its_reach() -> None:
    t = np.arange(3001, dtype=np.int64) * 10_000_000  # 30 s at 100 Hz
    p = np.zeros((len(t), 4, 3))
    # Still, except a burst of motion at 11–12 s and a faster one at 20 s (out of reach).
    burst = (t >= 11_000_000_000) & (t < 12_000_000_000)
    p[burst, :, 0] = np.sin(np.arange(burst.sum()) * 0.3)[:, None] * 0.1
    far = (t >= 20_000_000_000) & (t < 20_500_000_000)
    p[far, :, 0] = np.sin(np.arange(far.sum()) * 0.9)[:, None] * 0.3
    # Nothing moves within reach of the second centre: its window stays inside the reach,
    # never past the trial's ends.
    mid, edge = _busiest_windows(
        t, p, [10_000_000_000, 29_900_000_000], reach_ns=1_500_000_000, half_ns=300_000_000
    )
    assert 11_000_000_000 <= mid <= 12_000_000_000
    assert edge + 300_000_000 <= t[-1]
    still = np.zeros_like(p)
    (quiet,) = _busiest_windows(t, still, [5_000_000_000], reach_ns=10**9, half_ns=3 * 10**8)
    assert abs(quiet - 5e9) <= 1e9
