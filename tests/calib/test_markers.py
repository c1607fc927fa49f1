"""Marker measurement (calib/markers.py) against synthetic images and the simulated D415."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from scipy.spatial import cKDTree

from mocaprig.acquire.recorder import Recorder
from mocaprig.acquire.recording import Recording
from mocaprig.acquire.recording_format import CameraCalibrationMsg, D415FrameInfo, ImageMsg, topic
from mocaprig.calib.markers import (
    MarkerFrame,
    crop_volume,
    detect_blobs,
    frame_times,
    measure_frame,
    measure_recording,
    merge_views,
    to_world,
)
from mocaprig.drivers_mock.d415_render import IrSettings, RenderedFrame, SceneRenderer
from mocaprig.drivers_mock.scenario import Scenario, build_scenario
from mocaprig.errors import CalibrationError, ValidationError

K = np.array([[623.0, 0.0, 424.0], [0.0, 623.0, 240.0], [0.0, 0.0, 1.0]])


def _disc_image(
    centres: npt.NDArray[np.float64], radius_px: float, shape: tuple[int, int] = (480, 848)
) -> npt.NDArray[np.uint8]:
    """Saturated discs with a 1-px soft edge at sub-pixel centres over a dim noisy background."""
    rng = np.random.default_rng(3)
    img = rng.normal(30.0, 5.0, shape)
    vv, uu = np.mgrid[0 : shape[0], 0 : shape[1]]
    for cu, cv in centres:
        r = np.hypot(uu - cu, vv - cv)
        img = np.maximum(img, 255.0 * np.clip(radius_px + 0.5 - r, 0.0, 1.0))
    out: npt.NDArray[np.uint8] = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return out


def render_frames(
    scenario: Scenario,
    camera_index: int,
    t0_ns: int,
    t1_ns: int,
    *,
    phase_ns: int = 0,
    seed: int = 0,
    width: int = 848,
    height: int = 480,
) -> tuple[list[MarkerFrame], SceneRenderer]:
    """Render one D415 at its 30 Hz frame times in [t0, t1) and measure the markers.

    The device time of a frame is its mid-exposure in the camera's clock (µs, with the clock's
    jitter), as the mock D415 stamps ``sensor_timestamp``.
    """
    spec = scenario.rig.d415[camera_index]
    renderer = SceneRenderer(scenario, spec, width=width, height=height)
    settings = IrSettings()
    clock = scenario.clocks[spec.name]
    period = round(1e9 / 30 / clock.rate)
    rng = np.random.default_rng(seed)
    frames = []
    k = (t0_ns - phase_ns) // period
    while (t_start := phase_ns + k * period) < t1_ns:
        if t_start >= t0_ns:
            frame = renderer.render(int(t_start), settings, rng)
            mid = t_start + settings.exposure_us * 500
            t_dev = int(clock.device_ticks(np.array([mid]))[0]) * 1000
            frames.append(
                measure_frame(
                    frame.ir_y8,
                    frame.depth_z16,
                    renderer.K,
                    camera=f"d415/{spec.serial}",
                    t_dev_ns=t_dev,
                    frame_counter=int(k),
                )
            )
        k += 1
    return frames, renderer


def _matched(
    frame: RenderedFrame, uv: npt.NDArray[np.float64]
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.intp]]:
    truth = frame.marker_uv[frame.marker_visible]
    d, i = cKDTree(truth).query(uv)
    return d, np.flatnonzero(frame.marker_visible)[i]


def test_detect_blobs_recovers_subpixel_centres_of_synthetic_discs() -> None:
    rng = np.random.default_rng(0)
    centres = np.column_stack([rng.uniform(20, 828, 30), rng.uniform(20, 460, 30)])
    # Keep them apart so no two discs touch.
    keep = [0]
    for i in range(1, len(centres)):
        if np.min(np.hypot(*(centres[keep] - centres[i]).T)) > 12:
            keep.append(i)
    centres = centres[keep]
    uv, area = detect_blobs(_disc_image(centres, 2.5))
    assert uv.shape == (len(centres), 2)
    d, _ = cKDTree(centres).query(uv)
    assert d.max() < 0.05
    assert np.all((area > 12) & (area < 30))


def test_detect_blobs_applies_area_limits_and_threshold() -> None:
    img = _disc_image(np.array([[100.0, 100.0], [300.0, 200.0]]), 2.0)
    big = _disc_image(np.array([[500.0, 300.0]]), 30.0)
    both = np.maximum(img, big)
    uv, _ = detect_blobs(both, max_area_px=500)
    assert uv.shape[0] == 2  # the 30-px disc is too large for a marker
    uv, _ = detect_blobs(both, min_area_px=100, max_area_px=5000)
    assert uv.shape[0] == 1  # only the large one
    assert detect_blobs(np.zeros((10, 10), np.uint8))[0].shape == (0, 2)


@pytest.mark.parametrize(
    ("image", "kwargs", "fragment"),
    [
        (np.zeros((4, 4), np.uint16), {}, "uint8"),
        (np.zeros((4, 4, 3), np.uint8), {}, "2-D"),
        (np.zeros((4, 4), np.uint8), {"threshold": 0}, "threshold"),
        (np.zeros((4, 4), np.uint8), {"min_area_px": 5, "max_area_px": 2}, "area"),
    ],
)
def test_detect_blobs_rejects_bad_input(
    image: npt.NDArray[np.generic], kwargs: dict[str, int], fragment: str
) -> None:
    with pytest.raises(ValidationError, match=fragment):
        detect_blobs(image, **kwargs)


def test_measure_frame_reads_depth_from_the_ring_when_the_blob_has_none() -> None:
    centres = np.array([[200.3, 150.7], [600.8, 320.2]])
    ir = _disc_image(centres, 3.0)
    depth = np.full(ir.shape, 2000, np.uint16)  # a wall at 2 m
    depth[ir > 128] = 0  # saturated blobs: no depth
    frame = measure_frame(ir, depth, K, camera="d415/x", t_dev_ns=5, frame_counter=7)
    assert frame.n_markers == 2
    assert np.allclose(frame.xyz_cam_m[:, 2], 2.0)
    expect_x = (frame.uv_px[:, 0] - K[0, 2]) / K[0, 0] * 2.0
    assert np.allclose(frame.xyz_cam_m[:, 0], expect_x)
    assert (frame.camera, frame.t_dev_ns, frame.frame_counter) == ("d415/x", 5, 7)
    # No depth anywhere: the rows are NaN, the blobs stay.
    none = measure_frame(ir, np.zeros_like(depth), K)
    assert none.n_markers == 2
    assert not none.has_depth.any()


def test_measure_frame_ignores_background_beyond_a_limb_edge() -> None:
    ir = _disc_image(np.array([[400.0, 240.0]]), 3.0)
    depth = np.full(ir.shape, 4000, np.uint16)  # far wall
    depth[:, :402] = 1500  # the limb the marker sits on ends 2 px right of the centre
    depth[ir > 128] = 0
    frame = measure_frame(ir, depth, K)
    assert frame.xyz_cam_m[0, 2] == pytest.approx(1.5)


def test_measure_frame_rejects_wrong_units_and_shapes() -> None:
    ir = np.zeros((8, 8), np.uint8)
    with pytest.raises(ValidationError, match="depth_scale_m"):
        measure_frame(ir, np.zeros((8, 8), np.uint16), K, depth_scale_m=1.0)
    with pytest.raises(ValidationError, match="uint16"):
        measure_frame(ir, np.zeros((8, 8), np.float32), K)
    with pytest.raises(ValidationError, match="K"):
        measure_frame(ir, np.zeros((8, 8), np.uint16), np.eye(2))


@pytest.mark.parametrize("seed", [0, 1])
def test_measure_frame_on_the_simulated_d415_matches_the_truth(seed: int) -> None:
    sc = build_scenario("default", seed=seed, seconds=3)
    renderer = SceneRenderer(sc, sc.rig.d415[seed % 4])
    frame = renderer.render(2_000_000_000, IrSettings(), np.random.default_rng(seed))
    mf = measure_frame(frame.ir_y8, frame.depth_z16, renderer.K)
    d, idx = _matched(frame, mf.uv_px)
    # Recall: most visible markers are found; no blob is far from a marker.
    assert mf.n_markers >= 0.8 * np.count_nonzero(frame.marker_visible)
    # Partially hidden markers (behind a limb) pull their centroids off; the rest are exact.
    assert np.median(d) < 0.3
    assert np.mean(d < 1.0) > 0.75
    good = d < 0.5
    dz = mf.xyz_cam_m[good, 2] - frame.marker_z_m[idx[good]]
    dz = dz[np.isfinite(dz)]
    assert dz.size > 10
    assert abs(np.median(dz)) < 0.02
    assert np.mean(np.abs(dz) < 0.05) > 0.8


def test_to_world_crop_and_merge_views() -> None:
    t = np.eye(4)
    t[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    t[:3, 3] = [1.0, 2.0, 3.0]
    p = np.array([[1.0, 0.0, 0.0], [np.nan, np.nan, np.nan]])
    w = to_world(p, t)
    assert np.allclose(w[0], [1.0, 3.0, 3.0])
    assert np.isnan(w[1]).all()
    pts = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [np.nan, 0.0, 0.0], [1.0, 1.0, 1.0]])
    assert crop_volume(pts, [-1, -1, -1], [2, 2, 2]).tolist() == [[0, 0, 0], [1, 1, 1]]
    with pytest.raises(ValidationError, match="empty"):
        crop_volume(pts, [1, 1, 1], [0, 0, 0])
    a = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    b = np.array([[0.004, 0.0, 0.0], [1.0, 0.5, 0.0], [np.nan, 0.0, 0.0]])
    c = np.array([[-0.004, 0.002, 0.0]])
    merged = merge_views([a, b, c], radius_m=0.010)
    assert merged.shape == (3, 3)
    assert np.allclose(merged[0], [0.0, 0.002 / 3, 0.0])
    assert merge_views([]).shape == (0, 3)


def _write_recording(path: Path, frames: list[RenderedFrame], k: npt.NDArray[np.float64]) -> None:
    serial = "123456789012"
    stamps_us = [(1 << 32) - 50_000 + i * 33_333 for i in range(len(frames))]  # wraps mid-way
    with Recorder(path, min_free_disk_bytes=0) as rec:
        h = {
            s: rec.add_stream(topic("d415", serial, s), cls)
            for s, cls in (
                ("ir", ImageMsg),
                ("depth", ImageMsg),
                ("frame_info", D415FrameInfo),
                ("camera_info", CameraCalibrationMsg),
            )
        }
        fid = f"d415_{serial}"
        rec.put(
            h["camera_info"],
            CameraCalibrationMsg(848, 480, tuple(float(x) for x in k.ravel()), (0.0,) * 5),
            log_time_ns=1,
        )
        for i, f in enumerate(frames):
            t = 1000 + i * 33_000_000
            stamp = stamps_us[i] % (1 << 32)
            rec.put(
                h["ir"],
                ImageMsg(f.ir_y8, "mono8", stamp * 1000, fid),
                log_time_ns=t,
                sequence=50 + i,
            )
            rec.put(
                h["depth"],
                ImageMsg(f.depth_z16, "16UC1", stamp * 1000, fid),
                log_time_ns=t,
                sequence=50 + i,
            )
            info = D415FrameInfo(
                50 + i, stamp, stamp, None, "HARDWARE_CLOCK", stamp / 1000, t, 0.001, fid
            )
            rec.put(h["frame_info"], info, log_time_ns=t, sequence=50 + i)


def test_measure_recording_reads_d415_streams_with_windows_and_decimation(tmp_path: Path) -> None:
    sc = build_scenario("default", seed=2, seconds=4)
    renderer = SceneRenderer(sc, sc.rig.d415[0])
    rng = np.random.default_rng(2)
    rendered = [
        renderer.render(2_000_000_000 + i * 33_333_333, IrSettings(), rng) for i in range(4)
    ]
    path = tmp_path / "s.mcap"
    _write_recording(path, rendered, renderer.K)
    with Recording(path) as rec:
        out = measure_recording(rec)
        assert list(out) == ["d415/123456789012"]
        frames = out["d415/123456789012"]
        assert [f.frame_counter for f in frames] == [50, 51, 52, 53]
        t = np.array([f.t_dev_ns for f in frames])
        assert np.all(np.diff(t) == 33_333_000)  # the u32 µs wrap is undone
        direct = measure_frame(rendered[1].ir_y8, rendered[1].depth_z16, renderer.K)
        assert np.allclose(frames[1].uv_px, direct.uv_px)
        sub = measure_recording(rec, t_range_ns=(int(t[1]), int(t[3]) + 1), every=2)
        assert [f.frame_counter for f in sub["d415/123456789012"]] == [51, 53]
        with pytest.raises(CalibrationError, match="no D415 stream"):
            measure_recording(rec, cameras=["999"])
        with pytest.raises(ValidationError, match="every"):
            measure_recording(rec, every=0)


def test_frame_times_lists_frames_and_measure_recording_takes_them_by_time(
    tmp_path: Path,
) -> None:
    sc = build_scenario("default", seed=2, seconds=4)
    renderer = SceneRenderer(sc, sc.rig.d415[0])
    rng = np.random.default_rng(3)
    rendered = [
        renderer.render(2_000_000_000 + i * 33_333_333, IrSettings(), rng) for i in range(3)
    ]
    path = tmp_path / "s.mcap"
    _write_recording(path, rendered, renderer.K)
    with Recording(path) as rec:
        times = frame_times(rec)
        assert list(times) == ["d415/123456789012"]
        t = times["d415/123456789012"]
        assert t.dtype == np.int64
        assert np.all(np.diff(t) == 33_333_000)  # the u32 µs wrap is undone, as when measured
        sub = measure_recording(rec, frames_t_dev_ns={"123456789012": [int(t[0]), int(t[2])]})
        assert [f.t_dev_ns for f in sub["d415/123456789012"]] == [t[0], t[2]]
        assert [f.frame_counter for f in sub["d415/123456789012"]] == [50, 52]
        with pytest.raises(CalibrationError, match="no D415 stream"):
            frame_times(rec, cameras=["999"])
