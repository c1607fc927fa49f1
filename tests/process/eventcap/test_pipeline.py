"""run_batch end to end on one simulated 40 ms batch (realistic DAVIS simulator, karate)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import pytest
import torch
from scipy.spatial.transform import Rotation
from threadpoolctl import threadpool_info

from mocaprig.calib.camera_model import project_points
from mocaprig.drivers_mock.davis240c_sim import DavisSimulator
from mocaprig.drivers_mock.scenario import build_scenario
from mocaprig.errors import ValidationError
from mocaprig.process.body.kinematics import eventcap_keypoints, forward_kinematics
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.eventcap.camera import EventCamera
from mocaprig.process.eventcap.detections import Detection, SyntheticDetections
from mocaprig.process.eventcap.pipeline import (
    ApsFrame,
    BatchResult,
    EventcapOptions,
    _associate_trajectories,
    _body_shift_mm,
    _mirrored,
    _pose_prior,
    _unswap,
    _unswap_first,
    frame_detections,
    run_batch,
)
from mocaprig.process.eventcap.raster import rasterize
from mocaprig.process.eventcap.tracking import CorrespondencePairs

#: A kick is under way 1.7 s into the karate clip of seed 3 (device time 0 there).
_RESET_NS = 1_700_000_000


@dataclass(frozen=True, slots=True, eq=False)
class _Batch:
    events: npt.NDArray[np.void]
    frame_a: ApsFrame
    frame_b: ApsFrame
    detection_a: Detection
    detection_b: Detection
    camera: EventCamera
    shape: BodyShape
    sim: DavisSimulator

    def truth_pose(self, t_us: npt.NDArray[np.int64]) -> npt.NDArray[np.float64]:
        pose: npt.NDArray[np.float64] = self.sim.scenario.pose(
            np.asarray(self.sim.session_ns(t_us), dtype=np.int64)
        )
        return pose

    def truth_keypoints_m(self, t_us: npt.NDArray[np.int64]) -> npt.NDArray[np.float64]:
        shape = self.sim.scenario.shape
        kp: npt.NDArray[np.float64] = eventcap_keypoints(
            forward_kinematics(self.truth_pose(t_us), shape), shape
        )
        return kp


@pytest.fixture(scope="module")
def batch() -> _Batch:
    scenario = build_scenario("karate", seed=3, seconds=3.0)
    sim = DavisSimulator(scenario, reset_session_ns=_RESET_NS)
    act = sim.activity(0, 64_000)  # two exposures (18–22 ms and 58–62 ms by default)
    a, b = act.exposures[:2]
    frames = [ApsFrame(e.start_us, e.end_us, e.cds) for e in (a, b)]
    cam = scenario.rig.davis.camera
    camera = EventCamera(
        K=cam.K, distortion=cam.distortion, T_world_cam=cam.T_world_cam, width=240, height=180
    )
    times = np.array([f.t_us for f in frames], dtype=np.int64)
    pose = scenario.pose(np.asarray(sim.session_ns(times), dtype=np.int64))
    kp = eventcap_keypoints(forward_kinematics(pose, scenario.shape), scenario.shape)
    uv, _ = project_points(kp.reshape(-1, 3), cam.T_world_cam, cam.K, cam.distortion)
    det = SyntheticDetections.from_world(times, uv.reshape(-1, 19, 2), kp, cam.T_world_cam, seed=3)
    t = act.events["t"]
    events = act.events[(t >= a.start_us) & (t <= b.end_us)]
    return _Batch(
        events=events,
        frame_a=frames[0],
        frame_b=frames[1],
        detection_a=det.detect(int(times[0])),
        detection_b=det.detect(int(times[1])),
        camera=camera,
        shape=scenario.shape,
        sim=sim,
    )


def _run(
    batch: _Batch,
    start_pose: npt.NDArray[np.float64] | None = None,
    options: EventcapOptions | None = None,
) -> BatchResult:
    return run_batch(
        batch.events,
        batch.frame_a,
        batch.frame_b,
        batch.detection_a,
        batch.detection_b,
        batch.camera,
        batch.shape,
        start_pose=start_pose,
        options=options,
    )


@pytest.fixture(scope="module")
def result(batch: _Batch) -> BatchResult:
    return _run(batch)


@pytest.fixture(scope="module")
def start_pose(batch: _Batch) -> npt.NDArray[np.float64]:
    """What the previous batch would hand on at frame a: here the true pose."""
    return np.asarray(batch.truth_pose(np.array([batch.frame_a.t_us]))[0], dtype=np.float64)


@pytest.fixture(scope="module")
def chained(batch: _Batch, start_pose: npt.NDArray[np.float64]) -> BatchResult:
    return _run(batch, start_pose)


@pytest.mark.slow
def test_batch_covers_every_millisecond_between_the_frames(
    batch: _Batch, result: BatchResult
) -> None:
    n = (batch.frame_b.t_us - batch.frame_a.t_us) // 1000
    assert n == 40
    assert result.t_us.tolist() == [batch.frame_a.t_us + 1000 * k for k in range(n + 1)]
    assert result.poses.shape == (n + 1, 33)
    assert result.keypoints_m.shape == (n + 1, 19, 3)
    assert np.isfinite(result.poses).all()
    assert result.detection_source == "synthetic"


def test_batch_keypoints_stay_near_the_truth(batch: _Batch, result: BatchResult) -> None:
    truth = batch.truth_keypoints_m(result.t_us)
    err_mm = 1000 * np.linalg.norm(result.keypoints_m[:, :15] - truth[:, :15], axis=-1)
    # Detections carry 3 px / 40 mm noise; a sane fit stays within a few centimetres on
    # average and never runs off (a lost actor is metres away).
    assert err_mm.mean() < 120.0
    assert err_mm.max() < 400.0


def test_batch_uses_events_and_reports_stage_times(result: BatchResult) -> None:
    assert result.trajectories > 10
    assert result.correspondences > 100
    assert 0.05 < result.contrast[0] < 1.0
    stages = {"edi", "init", "tracking", "batch_fit", "association", "refine"}
    assert stages <= set(result.stage_seconds)
    assert all(v >= 0.0 for v in result.stage_seconds.values())


@pytest.mark.slow
def test_start_pose_ties_the_first_frame_to_the_previous_batch(
    batch: _Batch, result: BatchResult, chained: BatchResult
) -> None:
    truth = batch.truth_keypoints_m(result.t_us[:1])[0, :15]

    def err_mm(res: BatchResult) -> float:
        return float(1000 * np.linalg.norm(res.keypoints_m[0, :15] - truth, axis=-1).mean())

    # Alone, frame 0 fits one noisy detection; tied to a (here exact) previous pose it moves
    # toward it (measured 50 -> 31 mm; the prior weighs as much as detection a), and
    # refinement leaves the shared frame alone.
    assert err_mm(chained) < 0.75 * err_mm(result)
    assert chained.refined == result.refined - 1


@pytest.mark.slow
def test_batch_is_deterministic_and_leaves_threads_alone(
    batch: _Batch, start_pose: npt.NDArray[np.float64]
) -> None:
    cheap = EventcapOptions(refine_every=0, association_rounds=1)
    first = _run(batch, start_pose, cheap)
    before = torch.get_num_threads()
    blas_before = [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]
    torch.set_num_threads(2)
    try:
        again = _run(batch, start_pose, cheap)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"] == blas_before
    np.testing.assert_array_equal(again.poses, first.poses)


def test_trajectory_association_gives_one_surface_point_per_trajectory(
    batch: _Batch, result: BatchResult
) -> None:
    poses = batch.truth_pose(result.t_us)
    mask = rasterize(poses[1], batch.shape, batch.camera).mask
    ys, xs = np.nonzero(mask)
    inner = int(np.argmin((xs - xs.mean()) ** 2 + (ys - ys.mean()) ** 2))
    on_body = np.array([xs[inner], ys[inner]], dtype=np.float64)
    off_body = np.array([2.0, 2.0])  # a corner of the sensor, far from the actor
    assert not mask[2, 2]
    # Trajectory 0 on the body at frames 1..3 (drifting), trajectory 1 off it.
    rows = [(0, 1, 0), (0, 1, 2), (0, 2, 1), (0, 2, 3), (0, 3, 2), (1, 1, 0), (1, 1, 2)]
    tid = np.array([r[0] for r in rows])
    fi = np.array([r[1] for r in rows])
    fj = np.array([r[2] for r in rows])
    p_i = np.where(tid[:, None] == 0, on_body + 0.5 * (fi[:, None] - 1), off_body)
    pairs = CorrespondencePairs(fi, fj, p_i, p_i + 1.0, tid)
    cor = _associate_trajectories(pairs, poses, batch.shape, batch.camera, 1)
    assert cor.count == 5  # trajectory 1 dropped
    assert np.unique(cor.segment).size == 1
    np.testing.assert_array_equal(cor.local_m, np.repeat(cor.local_m[:1], 5, axis=0))
    np.testing.assert_array_equal(cor.target_px, p_i[:5] + 1.0)


def test_body_shift_flags_a_turned_body_but_not_a_moved_one(start_pose: np.ndarray) -> None:
    shape = BodyShape.from_height(1.75)
    moved = start_pose.copy()
    moved[3:6] += [0.3, -0.2, 0.1]  # the whole body carried 0.37 m: no shape change
    turned = start_pose.copy()
    turned[:3] = (
        Rotation.from_euler("z", np.pi) * Rotation.from_rotvec(start_pose[:3])
    ).as_rotvec()
    assert _body_shift_mm(start_pose, moved, shape) < 1e-6
    assert _body_shift_mm(start_pose, turned, shape) > 150.0


@pytest.mark.slow
def test_unswap_undoes_one_left_right_swap_and_keeps_true_detections(
    batch: _Batch, start_pose: npt.NDArray[np.float64]
) -> None:
    n = (batch.frame_b.t_us - batch.frame_a.t_us) // 1000
    true = [frame_detections(batch.detection_a, 0), frame_detections(batch.detection_b, n)]
    prior = _pose_prior(start_pose, batch.shape, batch.camera, 1.0)
    swapped = [_mirrored(d) for d in true]
    assert not np.allclose(swapped[1].keypoints2d_px, true[1].keypoints2d_px)
    opt = EventcapOptions().batch
    for given in ([prior, *true], [prior, true[0], swapped[1]], [prior, swapped[0], true[1]]):
        out = _unswap(given, start_pose, batch.shape, batch.camera, opt)
        assert out[0] is prior
        for got, want in zip(out[1:], true, strict=True):
            np.testing.assert_allclose(got.keypoints2d_px, want.keypoints2d_px)
            assert got.keypoints3d_mm is not None
            assert want.keypoints3d_mm is not None
            np.testing.assert_allclose(got.keypoints3d_mm, want.keypoints3d_mm)
            np.testing.assert_allclose(got.confidence, want.confidence)
    assert given[1] is swapped[0]  # the input list is not modified


def test_unswap_trusts_two_detections_that_both_disagree_with_the_handed_on_pose(
    batch: _Batch, start_pose: npt.NDArray[np.float64]
) -> None:
    # Both detections mirrored against the handed-on pose is what a mirrored hand-on looks
    # like (two swaps in a row are rare): the detections stand.
    n = (batch.frame_b.t_us - batch.frame_a.t_us) // 1000
    true = [frame_detections(batch.detection_a, 0), frame_detections(batch.detection_b, n)]
    given = [_pose_prior(start_pose, batch.shape, batch.camera, 1.0)]
    given += [_mirrored(d) for d in true]
    out = _unswap(given, start_pose, batch.shape, batch.camera, EventcapOptions().batch)
    assert all(got is want for got, want in zip(out, given, strict=True))


@pytest.mark.slow
def test_first_batch_vote_undoes_a_swap_of_either_detection(batch: _Batch) -> None:
    # No pose handed on: detections a, b and the next frame's vote. Here the next frame's
    # detection is b's again (it agrees with the true a and b).
    n = (batch.frame_b.t_us - batch.frame_a.t_us) // 1000
    true = [frame_detections(batch.detection_a, 0), frame_detections(batch.detection_b, n)]
    look = frame_detections(batch.detection_b, 2 * n)
    swapped = [_mirrored(d) for d in true]
    opt = EventcapOptions().batch
    for given in (list(true), [swapped[0], true[1]], [true[0], swapped[1]]):
        out = _unswap_first(given, look, batch.shape, batch.camera, opt)
        for got, want in zip(out, true, strict=True):
            np.testing.assert_allclose(got.keypoints2d_px, want.keypoints2d_px)
            np.testing.assert_allclose(got.confidence, want.confidence)
    assert given[1] is swapped[1]  # the input list is not modified


def test_batch_rejects_frames_not_whole_steps_apart(batch: _Batch) -> None:
    late = ApsFrame(
        batch.frame_b.exposure_start_us + 500,
        batch.frame_b.exposure_end_us + 500,
        batch.frame_b.image_dn,
    )
    with pytest.raises(ValidationError, match="whole number"):
        run_batch(
            batch.events,
            batch.frame_a,
            late,
            batch.detection_a,
            batch.detection_b,
            batch.camera,
            batch.shape,
        )


def test_frame_detections_carries_the_detection_at_its_frame(batch: _Batch) -> None:
    fd = frame_detections(batch.detection_a, 7)
    assert fd.frame == 7
    np.testing.assert_array_equal(fd.keypoints2d_px, batch.detection_a.joints2d_px)
