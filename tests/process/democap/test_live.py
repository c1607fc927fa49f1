"""Live DeMoCap pipeline (process/democap/live.py): same results as the stages by hand, the
two-stage stream, validation at the boundary, shutdown and error propagation.

The frames are small synthetic D415 images (240×180): bright discs drawn with OpenCV at the
projections of a seeded marker cloud, the markers' depth filled around them; the network is a
tiny random one (conftest's ``tiny_config``), so each module runs in a few seconds.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator, Sequence
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import pytest
import torch

from mocaprig.calib.calibration import Calibration, CameraCalibration
from mocaprig.calib.markers import crop_volume, measure_frame, merge_views, to_world
from mocaprig.errors import CalibrationError, ProcessingError, ValidationError
from mocaprig.process.democap.checkpoint import Checkpoint
from mocaprig.process.democap.config import DemocapConfig
from mocaprig.process.democap.infer import DemocapPredictor, Prediction
from mocaprig.process.democap.live import (
    LIVE_ROTATIONS,
    LiveCamera,
    LivePipeline,
    LiveResult,
    cameras_from_calibration,
    live_predictor,
)
from mocaprig.process.democap.model import DemocapNet
from mocaprig.process.democap.simdata import CAPTURE_BOX_M, in_frustum

F64 = npt.NDArray[np.float64]
W, H = 240, 180
K = np.array([[170.0, 0.0, 119.5], [0.0, 170.0, 89.5], [0.0, 0.0, 1.0]])
Pair = tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint16]]


def _look_at(centre: F64, target: F64) -> F64:
    """``T_world_cam`` of a camera at ``centre`` looking at ``target`` (OpenCV axes, z up)."""
    z = (target - centre) / np.linalg.norm(target - centre)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    t = np.eye(4)
    t[:3, :3] = np.column_stack([x, y, z])
    t[:3, 3] = centre
    return t


def _cameras(n: int = 3) -> list[LiveCamera]:
    target = np.array([0.0, 0.0, 1.0])
    out = []
    for i in range(n):
        a = 2 * np.pi * i / n
        centre = np.array([2.5 * np.cos(a), 2.5 * np.sin(a), 1.4])
        out.append(LiveCamera(f"d415/{100 + i}", K, _look_at(centre, target), width=W, height=H))
    return out


def _markers(seed: int) -> F64:
    """12 markers around (0, 0, 1) m, at least 0.25 m apart."""
    rng = np.random.default_rng(seed)
    pts: list[F64] = []
    while len(pts) < 12:
        p = np.array([0.0, 0.0, 1.0]) + rng.uniform(-0.7, 0.7, 3)
        if all(np.linalg.norm(p - q) > 0.25 for q in pts):
            pts.append(p)
    return np.array(pts)


def _render(cam: LiveCamera, points: F64) -> Pair:
    """IR discs (r = 2 px, soft edge) and their depth (mm) around them; 0 elsewhere."""
    t_cw = np.linalg.inv(cam.T_world_cam)
    p = points @ t_cw[:3, :3].T + t_cw[:3, 3]
    rng = np.random.default_rng(0)
    ir = rng.integers(10, 40, (H, W)).astype(np.uint8)
    depth = np.zeros((H, W), np.uint16)
    for x, y, z in p[np.argsort(-p[:, 2])]:  # far first: the near marker wins
        u, v = K[0, 0] * x / z + K[0, 2], K[1, 1] * y / z + K[1, 2]
        c = (round(u * 16), round(v * 16))
        cv2.circle(depth, c, 6 * 16, round(z * 1000), -1, cv2.LINE_8, 4)
        cv2.circle(ir, c, 3 * 16, 120, -1, cv2.LINE_AA, 4)
        cv2.circle(ir, c, 2 * 16, 255, -1, cv2.LINE_AA, 4)
    return ir, depth


def _frame_set(cams: Sequence[LiveCamera], seed: int) -> list[Pair]:
    pts = _markers(seed)
    return [_render(c, pts) for c in cams]


@pytest.fixture
def predictor(tiny_config: DemocapConfig) -> DemocapPredictor:
    torch.manual_seed(0)
    # the live setting: the network alone (its test, not the solve's)
    return DemocapPredictor(Checkpoint(tiny_config, DemocapNet(tiny_config).eval()), solve=False)


def _by_hand(
    predictor: DemocapPredictor, cams: Sequence[LiveCamera], frames: Sequence[Pair]
) -> tuple[F64, Prediction]:
    """The replay's stages, one call after the other."""
    box = np.asarray(CAPTURE_BOX_M)
    views = []
    for cam, (ir, depth) in zip(cams, frames, strict=True):
        mf = measure_frame(ir, depth, cam.K, depth_scale_m=0.001, distortion=np.zeros(5))
        views.append(crop_volume(to_world(mf.xyz_cam_m, cam.T_world_cam), box[:, 0], box[:, 1]))
    cloud = merge_views(views, radius_m=0.010)
    return cloud, predictor.predict_many([cloud])[0]


def _same(a: LiveResult, b: LiveResult) -> None:
    assert a.prediction is not None
    assert b.prediction is not None
    np.testing.assert_array_equal(a.cloud_m, b.cloud_m)
    np.testing.assert_array_equal(a.prediction.joints_m, b.prediction.joints_m)
    np.testing.assert_array_equal(a.prediction.markers_m, b.prediction.markers_m)


def _drain(results: Iterator[LiveResult], into: list[int]) -> None:
    for r in results:
        into.append(r.index)


def _live_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith("democap-live")]


# ------------------------------------------------------------------------------ results


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_process_equals_the_replay_stages_by_hand(
    predictor: DemocapPredictor, workers: int
) -> None:
    cams = _cameras()
    frames = _frame_set(cams, seed=1)
    threads = torch.get_num_threads()
    cloud, pred = _by_hand(predictor, cams, frames)
    with LivePipeline(predictor, cams, workers=workers) as pipe:
        res = pipe.process(frames)
    assert torch.get_num_threads() == threads
    # The synthetic scene is not vacuous: every true marker is near a fused point.
    truth = _markers(1)
    near = np.linalg.norm(truth[:, None] - cloud[None], axis=-1).min(axis=1)
    assert cloud.shape[0] >= 10
    assert np.mean(near < 0.01) >= 0.75
    assert res.index == 0
    assert res.cameras_used == 3
    assert res.points == cloud.shape[0]
    assert res.prediction is not None
    np.testing.assert_array_equal(res.cloud_m, cloud)
    np.testing.assert_array_equal(res.prediction.joints_m, pred.joints_m)
    np.testing.assert_array_equal(res.prediction.markers_m, pred.markers_m)
    for cam, mf in zip(cams, res.markers, strict=True):
        assert mf is not None
        assert mf.camera == cam.name
        assert mf.n_markers >= 8
    t = res.timings_ms
    expected = {"measure_ms", "merge_ms", "predict_ms", "total_ms", "latency_ms", "network_ms"}
    expected |= {f"measure_{c.name}_ms" for c in cams}
    assert expected <= set(t)
    assert all(v >= 0.0 for v in t.values())
    assert t["total_ms"] == pytest.approx(t["measure_ms"] + t["merge_ms"] + t["predict_ms"])


def test_cameras_by_name_missing_frame_and_empty_cloud(predictor: DemocapPredictor) -> None:
    cams = _cameras()
    frames = _frame_set(cams, seed=2)
    with LivePipeline(predictor, cams, workers=2) as pipe:
        full = pipe.process(frames)
        by_name = pipe.process({c.name: f for c, f in zip(cams, frames, strict=True)})
        _same(full, by_name)
        dropped = pipe.process([frames[0], None, frames[2]])
        assert dropped.cameras_used == 2
        assert dropped.markers[1] is None
        assert "measure_d415/101_ms" not in dropped.timings_ms
        cloud, pred = _by_hand(predictor, [cams[0], cams[2]], [frames[0], frames[2]])
        np.testing.assert_array_equal(dropped.cloud_m, cloud)
        assert dropped.prediction is not None
        np.testing.assert_array_equal(dropped.prediction.joints_m, pred.joints_m)
        dark = [(np.zeros((H, W), np.uint8), np.zeros((H, W), np.uint16))] * 3
        empty = pipe.process(dark)
        assert empty.prediction is None
        assert empty.points == 0
        assert empty.cameras_used == 3
        nothing = pipe.process([None, None, None])
        assert nothing.prediction is None
        assert nothing.cameras_used == 0


def test_a_live_cameras_view_is_what_its_image_shows() -> None:
    cam = _cameras(1)[0]
    view = cam.view()
    np.testing.assert_allclose(view.centre_m, cam.T_world_cam[:3, 3])
    pts = np.random.default_rng(3).uniform([-3.0, -3.0, -1.0], [3.0, 3.0, 3.0], (500, 3))
    t_cw = np.linalg.inv(cam.T_world_cam)
    p = pts @ t_cw[:3, :3].T + t_cw[:3, 3]
    z = np.where(p[:, 2] > 0, p[:, 2], 1.0)
    u, v = K[0, 0] * p[:, 0] / z + K[0, 2], K[1, 1] * p[:, 1] / z + K[1, 2]
    # the image with the view test's 2 px margin, 0.3-6 m
    near = np.linalg.norm(p, axis=1) < 6.0
    want = near & (p[:, 2] > 0.3) & (u > 2) & (u < W - 2) & (v > 2) & (v < H - 2)
    assert 0.05 < want.mean() < 0.95  # the test has both
    np.testing.assert_array_equal(in_frustum(pts, [view])[0], want)


def test_the_predictor_is_told_which_cameras_made_the_cloud_and_its_crop(
    predictor: DemocapPredictor,
) -> None:
    cams = _cameras()
    frames = _frame_set(cams, seed=2)
    told: list[object] = []
    crops: list[object] = []

    class Spy:
        def predict_many(
            self,
            clouds: Sequence[npt.ArrayLike],
            *,
            views: object = None,
            crop_box_m: object = None,
        ) -> list[Prediction]:
            told.append(views)
            crops.append(crop_box_m)
            return predictor.predict_many(clouds)

    with LivePipeline(Spy(), cams) as pipe:
        pipe.process(frames)
        pipe.process([frames[0], None, frames[2]])
    box = ((-1.0, 1.0), (-1.0, 1.0), (0.0, 2.0))
    with LivePipeline(Spy(), cams, crop_box_m=box) as pipe:
        pipe.process(frames)
    with LivePipeline(Spy(), cams, crop_box_m=None) as pipe:
        pipe.process(frames)
    assert crops == [CAPTURE_BOX_M, CAPTURE_BOX_M, box, None]
    full, dropped = told[:2]

    def centres(views: object) -> list[list[float]]:
        assert isinstance(views, list)
        assert len(views) == 1  # one cloud
        return [v.centre_m.tolist() for v in views[0]]

    assert centres(full) == [c.T_world_cam[:3, 3].tolist() for c in cams]
    assert centres(dropped) == [c.T_world_cam[:3, 3].tolist() for c in (cams[0], cams[2])]


def test_stream_keeps_order_and_equals_process(predictor: DemocapPredictor) -> None:
    cams = _cameras()
    sets = [_frame_set(cams, seed=s) for s in range(6)]
    with LivePipeline(predictor, cams, workers=2, queue_size=1) as pipe:
        one_by_one = [pipe.process(s) for s in sets]
        streamed = list(pipe.stream(iter(sets)))
        assert [r.index for r in streamed] == list(range(6))
        assert not any(r.skipped for r in streamed)  # a replay's stream waits, skips nothing
        for a, b in zip(one_by_one, streamed, strict=True):
            _same(a, b)
            assert b.timings_ms["latency_ms"] >= b.timings_ms["predict_ms"]
        assert list(pipe.stream([])) == []
    assert _live_threads() == []


class _SlowPredictor:
    """A predictor far slower than the measurement (a network behind the cameras)."""

    def __init__(self, inner: DemocapPredictor, delay_s: float) -> None:
        self.inner, self.delay_s = inner, delay_s

    def predict_many(self, clouds: Any, **kw: Any) -> list[Prediction]:
        time.sleep(self.delay_s)
        return self.inner.predict_many(clouds, **kw)


def test_keep_up_skips_the_sets_a_slow_network_cannot_reach_and_says_so(
    predictor: DemocapPredictor,
) -> None:
    cams = _cameras()
    sets = [_frame_set(cams, seed=s) for s in range(12)]
    with LivePipeline(predictor, cams) as pipe:
        want = [pipe.process(s) for s in sets]
    with LivePipeline(_SlowPredictor(predictor, 0.2), cams, queue_size=1) as pipe:
        got = list(pipe.stream(iter(sets), keep_up=True))
    # every set comes out once, in order: predicted, or skipped in its place
    assert [r.index for r in got] == list(range(12))
    skipped = [r for r in got if r.skipped]
    assert skipped  # the network took 0.2 s a set; the sets came at once
    for r in skipped:
        assert r.prediction is None
        assert r.cloud_m.shape == (0, 3)
        assert r.cameras_used == 0
        assert r.timings_ms == {}
    assert not got[-1].skipped  # the newest set always reaches the network
    for r in got:
        if not r.skipped:
            _same(want[r.index], r)
    assert _live_threads() == []


def test_from_calibration_sorts_by_name_and_checks_kind() -> None:
    cams = _cameras()

    def entry(cam: LiveCamera, kind: Any = "d415") -> CameraCalibration:
        serial = cam.name.split("/")[1]
        return CameraCalibration(
            f"{kind}/{serial}", kind, serial, W, H, cam.K, np.zeros(5), cam.T_world_cam
        )

    cal = Calibration(cameras=(entry(cams[2]), entry(cams[0]), entry(cams[1], "davis")))
    got = cameras_from_calibration(cal, depth_scale_m=0.0001)
    assert [c.name for c in got] == ["d415/100", "d415/102"]
    assert got[0].depth_scale_m == 0.0001
    assert (got[0].width, got[0].height) == (W, H)
    np.testing.assert_array_equal(got[1].T_world_cam, cams[2].T_world_cam)
    with pytest.raises(CalibrationError, match="davis"):
        LiveCamera.from_calibration(cal, "davis/101")
    with pytest.raises(CalibrationError, match="no D415"):
        cameras_from_calibration(Calibration(cameras=(entry(cams[1], "davis"),)))


# ------------------------------------------------------------------------------ validation


def test_bad_frame_sets_raise_validation_errors_naming_the_camera(
    predictor: DemocapPredictor,
) -> None:
    cams = _cameras()
    frames = _frame_set(cams, seed=3)
    ir, depth = frames[1]
    with LivePipeline(predictor, cams, workers=2) as pipe:
        with pytest.raises(ValidationError, match=r"2 \(IR, depth\) pair\(s\) for the 3 cameras"):
            pipe.process(frames[:2])
        bad: list[tuple[Any, str]] = [
            ((ir.astype(np.uint16), depth), "IR image must be 2-D uint8"),
            ((ir, depth.astype(np.float32)), "depth image must be uint16"),
            ((ir, depth[:, :-1]), "depth image must be uint16"),
            ((ir[:, :-2], depth[:, :-2]), "calibrated at 240×180"),
            ((ir,), r"expected an \(IR, depth\) pair"),
        ]
        for pair, what in bad:
            with pytest.raises(ValidationError, match=f"camera 'd415/101'.*{what}"):
                pipe.process([frames[0], pair, frames[2]])
        with pytest.raises(ValidationError, match=r"missing \['d415/102'\].*unknown \['d415/9'\]"):
            pipe.process({"d415/100": frames[0], "d415/101": frames[1], "d415/9": frames[2]})
        with pytest.raises(ValidationError, match="sequence of"):
            pipe.process(frames[0][0])  # type: ignore[arg-type]
        # In a stream, the results before the bad set come out first.
        sets = [frames, frames, [frames[0], None]]
        got: list[int] = []
        with pytest.raises(ValidationError, match="2 \\(IR, depth\\) pair"):
            _drain(pipe.stream(sets), got)  # type: ignore[arg-type]
        assert got == [0, 1]
    assert _live_threads() == []


def test_bad_cameras_and_options_are_rejected(predictor: DemocapPredictor) -> None:
    cams = _cameras()
    with pytest.raises(ValidationError, match="K needs positive focal"):
        LiveCamera("d415/1", np.diag([-1.0, 1.0, 1.0]), np.eye(4))
    with pytest.raises(ValidationError, match="T_world_cam"):
        LiveCamera("d415/1", K, np.eye(3))
    with pytest.raises(ValidationError, match="depth_scale_m"):
        LiveCamera("d415/1", K, np.eye(4), depth_scale_m=1.0)
    with pytest.raises(ValidationError, match="unique"):
        LivePipeline(predictor, [cams[0], cams[0]])
    with pytest.raises(ValidationError, match="workers"):
        LivePipeline(predictor, cams, workers=0)
    with pytest.raises(ValidationError, match="crop_box_m"):
        LivePipeline(predictor, cams, crop_box_m=((0.0, 1.0), (0.0, 1.0)))  # type: ignore[arg-type]


# ------------------------------------------------------------------------------ lifetime


def test_context_manager_and_early_stop_shut_the_threads_down(
    predictor: DemocapPredictor,
) -> None:
    cams = _cameras()
    frames = _frame_set(cams, seed=4)
    pulled = 0

    def source() -> Iterator[list[Pair]]:
        nonlocal pulled
        for _ in range(1000):
            pulled += 1
            yield frames

    with LivePipeline(predictor, cams, workers=3, queue_size=2) as pipe:
        pipe.process(frames)
        assert 1 <= len(_live_threads()) <= 2  # pool threads (made on demand), none more
        it = pipe.stream(source())
        for r in it:
            if r.index == 2:
                break
        it.close()  # type: ignore[attr-defined]
        assert "democap-live-measure" not in _live_threads()
        assert pulled <= 3 + 2 + 2  # results + queue + one in hand each side
    assert pipe.closed
    assert _live_threads() == []
    with pytest.raises(ProcessingError, match="closed"):
        pipe.process(frames)
    with pytest.raises(ProcessingError, match="closed"):
        pipe.stream([frames])
    pipe.close()  # idempotent


def test_closing_the_pipeline_stops_a_running_stream(predictor: DemocapPredictor) -> None:
    cams = _cameras()
    frames = _frame_set(cams, seed=5)
    pipe = LivePipeline(predictor, cams, workers=1)
    it = pipe.stream(frames for _ in range(1000))
    next(it)
    pipe.close()
    with pytest.raises(ProcessingError, match="closed while streaming"):
        list(it)
    assert _live_threads() == []


class _Boom(RuntimeError):
    pass


def test_errors_of_every_stage_propagate(
    predictor: DemocapPredictor, monkeypatch: pytest.MonkeyPatch
) -> None:
    cams = _cameras()
    sets = [_frame_set(cams, seed=s) for s in range(4)]

    class Failing:
        calls = 0

        def predict_many(
            self,
            clouds: Sequence[npt.ArrayLike],
            *,
            views: object = None,
            crop_box_m: object = None,
        ) -> list[Prediction]:
            Failing.calls += 1
            if Failing.calls == 3:
                raise _Boom("network failed")
            return predictor.predict_many(clouds)

    with LivePipeline(Failing(), cams, workers=2) as pipe:
        got: list[int] = []
        with pytest.raises(_Boom, match="network failed"):
            _drain(pipe.stream(sets), got)
        assert got == [0, 1]

    def bad_source() -> Iterator[list[Pair]]:
        yield sets[0]
        raise _Boom("camera unplugged")

    with LivePipeline(predictor, cams, workers=2) as pipe:
        got.clear()
        with pytest.raises(_Boom, match="camera unplugged"):
            _drain(pipe.stream(bad_source()), got)
        assert got == [0]

        real = measure_frame

        def flaky(*args: Any, **kwargs: Any) -> Any:
            if kwargs.get("camera") == "d415/101":  # measured on the pool's thread
                raise _Boom("measurement failed")
            return real(*args, **kwargs)

        monkeypatch.setattr("mocaprig.process.democap.live.measure_frame", flaky)
        with pytest.raises(_Boom, match="measurement failed"):
            pipe.process(sets[0])
        with pytest.raises(_Boom, match="measurement failed"):
            list(pipe.stream(sets))
    assert _live_threads() == []


def test_live_predictor_runs_its_two_turns_in_one_compiled_pass(
    tiny_config: DemocapConfig,
) -> None:
    ck = Checkpoint(tiny_config, DemocapNet(tiny_config).eval())
    pred = live_predictor(ck)
    assert pred.rotations == LIVE_ROTATIONS == 2
    assert pred.workers == 1
    assert pred.compiled  # asked for; compiling waits for the first pass
    assert not pred.solves
    single = live_predictor(ck, rotations=1, compile=False)
    assert (single.rotations, single.workers, single.compiled) == (1, 1, False)
    with pytest.raises(ValidationError, match="rotations"):
        live_predictor(ck, rotations=0)
