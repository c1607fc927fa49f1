"""Tests of process.eventcap.detections: keypoint tables, importers, our JSON, synthetic noise."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mocaprig.errors import ProcessingError, RecordingError, ValidationError
from mocaprig.process.body.kinematics import EVENTCAP_KEYPOINTS
from mocaprig.process.eventcap.detections import (
    KEYPOINT_SET_SIZES,
    CocoKeypointDetections,
    Detection,
    Detector,
    JsonDetections,
    OpenPoseJsonDetections,
    SyntheticDetections,
    SyntheticNoise,
    convert_keypoints,
    write_detections_json,
)

SLOT = {name: i for i, name in enumerate(EVENTCAP_KEYPOINTS)}

# Source keypoint names of each set, in the set's order (OpenPose doc/output.md, COCO, BlazePose).
BODY25_NAMES = [
    "nose", "neck", "right_shoulder", "right_elbow", "right_wrist", "left_shoulder",
    "left_elbow", "left_wrist", "mid_hip", "right_hip", "right_knee", "right_ankle", "left_hip",
    "left_knee", "left_ankle", "right_eye", "left_eye", "right_ear", "left_ear", "left_big_toe",
    "left_small_toe", "left_heel", "right_big_toe", "right_small_toe", "right_heel",
]  # fmt: skip
COCO18_NAMES = [
    "nose", "neck", "right_shoulder", "right_elbow", "right_wrist", "left_shoulder",
    "left_elbow", "left_wrist", "right_hip", "right_knee", "right_ankle", "left_hip",
    "left_knee", "left_ankle", "right_eye", "left_eye", "right_ear", "left_ear",
]  # fmt: skip
COCO17_NAMES = [
    "nose", "left_eye", "right_eye", "left_ear", "right_ear", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hip", "right_hip",
    "left_knee", "right_knee", "left_ankle", "right_ankle",
]  # fmt: skip
BLAZEPOSE_NAMES = [
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye",
    "right_eye_outer", "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_pinky",
    "right_pinky", "left_index", "right_index", "left_thumb", "right_thumb", "left_hip",
    "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle", "left_heel",
    "right_heel", "left_foot_index", "right_foot_index",
]  # fmt: skip


def _pose(names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """A pose whose keypoint k sits at (10k + 1, 1000 + 7k) with confidence 0.5 + k/100."""
    k = np.arange(len(names), dtype=np.float64)
    return np.column_stack([10 * k + 1, 1000 + 7 * k]), 0.5 + k / 100


def _expect_named(
    names: list[str], xy: np.ndarray, conf: np.ndarray, out_xy: np.ndarray, out_c: np.ndarray
) -> None:
    for ours in EVENTCAP_KEYPOINTS:
        if ours in names:
            src = names.index(ours)
            np.testing.assert_allclose(out_xy[SLOT[ours]], xy[src], err_msg=ours)
            assert out_c[SLOT[ours]] == pytest.approx(conf[src]), ours


@pytest.mark.parametrize(
    ("kset", "names"),
    [
        ("body25", BODY25_NAMES),
        ("coco18", COCO18_NAMES),
        ("coco17", COCO17_NAMES),
        ("blazepose33", BLAZEPOSE_NAMES),
    ],
)
def test_every_named_joint_lands_in_its_own_slot(kset: str, names: list[str]) -> None:
    assert len(names) == KEYPOINT_SET_SIZES[kset]  # type: ignore[index]
    xy, conf = _pose(names)
    out_xy, out_c, _ = convert_keypoints(xy, conf, kset)  # type: ignore[arg-type]
    _expect_named(names, xy, conf, out_xy, out_c)


def test_body25_pelvis_is_mid_hip_and_head_is_the_mean_of_the_ears() -> None:
    xy, conf = _pose(BODY25_NAMES)
    out_xy, out_c, _ = convert_keypoints(xy, conf, "body25")
    np.testing.assert_allclose(out_xy[SLOT["pelvis"]], xy[BODY25_NAMES.index("mid_hip")])
    ears = [BODY25_NAMES.index("right_ear"), BODY25_NAMES.index("left_ear")]
    np.testing.assert_allclose(out_xy[SLOT["head"]], xy[ears].mean(axis=0))
    assert out_c[SLOT["head"]] == pytest.approx(conf[ears].min())


def test_coco17_neck_and_pelvis_are_means_with_the_lower_confidence() -> None:
    xy, conf = _pose(COCO17_NAMES)
    out_xy, out_c, _ = convert_keypoints(xy, conf, "coco17")
    sh = [COCO17_NAMES.index("left_shoulder"), COCO17_NAMES.index("right_shoulder")]
    hips = [COCO17_NAMES.index("left_hip"), COCO17_NAMES.index("right_hip")]
    np.testing.assert_allclose(out_xy[SLOT["neck"]], xy[sh].mean(axis=0))
    np.testing.assert_allclose(out_xy[SLOT["pelvis"]], xy[hips].mean(axis=0))
    assert out_c[SLOT["neck"]] == pytest.approx(conf[sh].min())
    assert out_c[SLOT["pelvis"]] == pytest.approx(conf[hips].min())


def test_a_missing_source_joint_gives_confidence_zero_and_zero_coordinates() -> None:
    xy, conf = _pose(COCO18_NAMES)
    conf[COCO18_NAMES.index("left_hip")] = 0.0
    out_xy, out_c, _ = convert_keypoints(xy, conf, "coco18")
    for ours in ("left_hip", "pelvis"):  # pelvis needs both hips
        assert out_c[SLOT[ours]] == 0.0
        np.testing.assert_array_equal(out_xy[SLOT[ours]], [0.0, 0.0])
    assert out_c[SLOT["right_hip"]] > 0


def test_converted_3d_is_recentred_on_the_pelvis() -> None:
    rng = np.random.default_rng(5)
    p3 = rng.normal(scale=300.0, size=(17, 3))
    xy, conf = _pose(COCO17_NAMES)
    _, _, out3 = convert_keypoints(xy, conf, "coco17", joints3d=p3)
    assert out3 is not None
    np.testing.assert_allclose(out3[SLOT["pelvis"]], 0.0, atol=1e-12)
    pelvis = p3[[11, 12]].mean(axis=0)
    np.testing.assert_allclose(out3[SLOT["left_knee"]], p3[13] - pelvis)


# --- Detection record ------------------------------------------------------------------------


def test_detection_keeps_read_only_copies() -> None:
    xy = np.ones((19, 2))
    det = Detection(5, xy, np.full(19, 0.5), source="unit")
    xy[0, 0] = 99.0
    assert det.joints2d_px[0, 0] == 1.0
    with pytest.raises(ValueError, match="read-only"):
        det.confidence[0] = 1.0


def test_detection_rejects_confidence_above_one() -> None:
    with pytest.raises(ValidationError, match=r"confidences must lie in \[0, 1\]"):
        Detection(0, np.zeros((19, 2)), np.full(19, 1.5), source="unit")


def test_detection_rejects_3d_not_centred_on_the_pelvis() -> None:
    with pytest.raises(ValidationError, match="pelvis at the origin"):
        Detection(
            0, np.zeros((19, 2)), np.ones(19), source="u", joints3d_root_rel_mm=np.ones((19, 3))
        )


def test_detection_needs_a_source_label() -> None:
    with pytest.raises(ValidationError, match="no source label"):
        Detection(0, np.zeros((19, 2)), np.ones(19), source="")


# --- OpenPose --------------------------------------------------------------------------------


def _openpose_file(folder: Path, frame: int, people: list[list[float]]) -> Path:
    path = folder / f"take_{frame:012d}_keypoints.json"
    doc = {"version": 1.3, "people": [{"person_id": [-1], "pose_keypoints_2d": p} for p in people]}
    path.write_text(json.dumps(doc))
    return path


def _flat(xy: np.ndarray, conf: np.ndarray) -> list[float]:
    return [float(v) for v in np.column_stack([xy, conf]).ravel()]


def test_openpose_body25_folder_maps_frames_to_the_given_times(tmp_path: Path) -> None:
    xy, conf = _pose(BODY25_NAMES)
    _openpose_file(tmp_path, 0, [_flat(xy, conf)])
    _openpose_file(tmp_path, 1, [_flat(xy + 5.0, conf)])
    dets = OpenPoseJsonDetections(tmp_path, [40_000, 80_000])
    assert dets.source == "openpose-body25"
    assert dets.times_us.tolist() == [40_000, 80_000]
    d1 = dets.detect(80_000)
    assert d1.source == "openpose-body25"
    assert d1.t_us == 80_000
    np.testing.assert_allclose(d1.joints2d_px[SLOT["neck"]], xy[1] + 5.0)


def test_openpose_coco18_is_recognised_by_its_keypoint_count(tmp_path: Path) -> None:
    xy, conf = _pose(COCO18_NAMES)
    _openpose_file(tmp_path, 0, [_flat(xy, conf)])
    det = OpenPoseJsonDetections(tmp_path, [1000]).detect(1000)
    assert det.source == "openpose-coco18"
    np.testing.assert_allclose(det.joints2d_px[SLOT["pelvis"]], xy[[8, 11]].mean(axis=0))


def test_openpose_picks_the_person_with_the_highest_mean_confidence(tmp_path: Path) -> None:
    xy, conf = _pose(BODY25_NAMES)
    _openpose_file(
        tmp_path, 0, [_flat(xy, conf * 0.5), _flat(xy + 100.0, conf), _flat(xy, conf * 0)]
    )
    det = OpenPoseJsonDetections(tmp_path, [0]).detect(0)
    np.testing.assert_allclose(det.joints2d_px[SLOT["right_wrist"]], xy[4] + 100.0)


def test_openpose_frame_without_people_has_zero_confidence(tmp_path: Path) -> None:
    xy, conf = _pose(BODY25_NAMES)
    _openpose_file(tmp_path, 0, [_flat(xy, conf)])
    _openpose_file(tmp_path, 1, [])
    det = OpenPoseJsonDetections(tmp_path, [0, 40_000]).detect(40_000)
    assert det.source == "openpose-body25"
    assert not det.confidence.any()


def test_openpose_malformed_json_names_the_file(tmp_path: Path) -> None:
    (tmp_path / "take_000000000000_keypoints.json").write_text("{ not json")
    with pytest.raises(
        RecordingError, match=r"take_000000000000_keypoints\.json is not valid JSON"
    ):
        OpenPoseJsonDetections(tmp_path, [0])


def test_openpose_unexpected_keypoint_count_is_refused(tmp_path: Path) -> None:
    _openpose_file(tmp_path, 0, [[1.0, 2.0, 0.5] * 20])
    with pytest.raises(RecordingError, match="has 20 keypoints"):
        OpenPoseJsonDetections(tmp_path, [0])


def test_openpose_frame_index_beyond_the_given_times_is_refused(tmp_path: Path) -> None:
    xy, conf = _pose(BODY25_NAMES)
    _openpose_file(tmp_path, 3, [_flat(xy, conf)])
    with pytest.raises(RecordingError, match="frame index 3 has no time"):
        OpenPoseJsonDetections(tmp_path, [0, 1, 2])


def test_openpose_empty_folder_says_how_to_make_files(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="--write_json"):
        OpenPoseJsonDetections(tmp_path, [0])


def test_detect_at_a_time_without_a_frame_is_a_processing_error(tmp_path: Path) -> None:
    xy, conf = _pose(BODY25_NAMES)
    _openpose_file(tmp_path, 0, [_flat(xy, conf)])
    dets = OpenPoseJsonDetections(tmp_path, [40_000], tolerance_us=100)
    assert dets.detect(40_050).t_us == 40_000
    with pytest.raises(ProcessingError, match="no detection at t_us=41000"):
        dets.detect(41_000)


# --- COCO ------------------------------------------------------------------------------------


def test_coco_results_keep_the_best_scored_person_per_image(tmp_path: Path) -> None:
    xy, conf = _pose(COCO17_NAMES)
    results = [
        {"image_id": 7, "category_id": 1, "keypoints": _flat(xy, conf), "score": 0.4},
        {"image_id": 7, "category_id": 1, "keypoints": _flat(xy + 3.0, conf), "score": 0.9},
        {"image_id": 8, "category_id": 1, "keypoints": _flat(xy, conf), "score": 0.8},
    ]
    path = tmp_path / "results.json"
    path.write_text(json.dumps(results))
    dets = CocoKeypointDetections(path, {7: 1000, 8: 2000, 9: 3000})
    d7 = dets.detect(1000)
    assert d7.source == "coco17"
    np.testing.assert_allclose(d7.joints2d_px[SLOT["left_wrist"]], xy[9] + 3.0)
    _expect_named(
        COCO17_NAMES, xy, conf, dets.detect(2000).joints2d_px, dets.detect(2000).confidence
    )
    assert not dets.detect(3000).confidence.any()  # image 9 has no person


def test_coco_annotations_turn_visibility_into_confidence(tmp_path: Path) -> None:
    xy, _ = _pose(COCO17_NAMES)
    vis = np.full(17, 2.0)
    vis[COCO17_NAMES.index("right_knee")] = 0.0
    vis[COCO17_NAMES.index("left_knee")] = 1.0
    doc = {"images": [{"id": 1}], "annotations": [{"image_id": 1, "keypoints": _flat(xy, vis)}]}
    path = tmp_path / "person_keypoints.json"
    path.write_text(json.dumps(doc))
    det = CocoKeypointDetections(path, {1: 500}).detect(500)
    assert det.confidence[SLOT["right_knee"]] == 0.0
    assert det.confidence[SLOT["left_knee"]] == 1.0
    assert det.confidence[SLOT["right_ankle"]] == 1.0


def test_coco_image_without_a_time_is_refused(tmp_path: Path) -> None:
    xy, conf = _pose(COCO17_NAMES)
    path = tmp_path / "results.json"
    path.write_text(json.dumps([{"image_id": 4, "keypoints": _flat(xy, conf), "score": 1.0}]))
    with pytest.raises(RecordingError, match=r"image ids \[4\] have no time"):
        CocoKeypointDetections(path, {5: 0})


def test_coco_short_keypoint_list_names_the_entry(tmp_path: Path) -> None:
    path = tmp_path / "results.json"
    path.write_text(json.dumps([{"image_id": 1, "keypoints": [1.0, 2.0, 1.0]}]))
    with pytest.raises(RecordingError, match=r"results.json entry 0: expected 51 numbers"):
        CocoKeypointDetections(path, {1: 0})


# --- our JSON --------------------------------------------------------------------------------


def _synthetic(seed: int = 0, frames: int = 4) -> SyntheticDetections:
    rng = np.random.default_rng(100 + seed)
    t = np.arange(frames, dtype=np.int64) * 40_000
    j2 = rng.uniform(0, 240, size=(frames, 19, 2))
    j3 = rng.normal(scale=400.0, size=(frames, 19, 3))
    return SyntheticDetections(t, j2, joints3d_root_rel_mm=j3, seed=seed)


def test_json_round_trip_keeps_times_values_and_the_source(tmp_path: Path) -> None:
    syn = _synthetic()
    dets = [syn.detect(int(t)) for t in syn.times_us]
    path = tmp_path / "detections.json"
    write_detections_json(path, dets)
    back = JsonDetections(path)
    assert back.source == "synthetic"
    assert json.loads(path.read_text())["source"] == "synthetic"
    for d in dets:
        r = back.detect(d.t_us)
        assert r.source == "synthetic"
        np.testing.assert_allclose(r.joints2d_px, d.joints2d_px)
        np.testing.assert_allclose(r.confidence, d.confidence)
        assert r.joints3d_root_rel_mm is not None
        assert d.joints3d_root_rel_mm is not None
        np.testing.assert_allclose(r.joints3d_root_rel_mm, d.joints3d_root_rel_mm, atol=1e-9)


def test_json_writer_refuses_to_overwrite(tmp_path: Path) -> None:
    path = tmp_path / "detections.json"
    path.write_text("keep me")
    syn = _synthetic()
    with pytest.raises(RecordingError, match="exists already, not overwriting"):
        write_detections_json(path, [syn.detect(0)])
    assert path.read_text() == "keep me"


def test_json_writer_refuses_mixed_sources(tmp_path: Path) -> None:
    other = Detection(1, np.zeros((19, 2)), np.zeros(19), source="coco17")
    with pytest.raises(ValidationError, match="mix sources"):
        write_detections_json(tmp_path / "d.json", [_synthetic().detect(0), other])


def test_json_reads_a_blazepose_file_written_elsewhere(tmp_path: Path) -> None:
    xy, conf = _pose(BLAZEPOSE_NAMES)
    doc = {
        "format": "mocaprig.eventcap.detections",
        "format_version": 1,
        "source": "mediapipe-0.10.14",
        "keypoint_set": "blazepose33",
        "frames": [{"t_us": 10, "joints2d": np.column_stack([xy, conf]).tolist()}],
    }
    path = tmp_path / "bp.json"
    path.write_text(json.dumps(doc))
    det = JsonDetections(path).detect(10)
    assert det.source == "mediapipe-0.10.14"
    assert det.joints3d_root_rel_mm is None
    _expect_named(BLAZEPOSE_NAMES, xy, conf, det.joints2d_px, det.confidence)


@pytest.mark.parametrize(
    ("doc", "match"),
    [
        ({"format": "other"}, "not a detections file"),
        (
            {
                "format": "mocaprig.eventcap.detections",
                "format_version": 99,
                "source": "s",
                "frames": [],
            },
            "format_version 99 is not supported",
        ),
        (
            {
                "format": "mocaprig.eventcap.detections",
                "format_version": 1,
                "source": "s",
                "frames": [{"t_us": 0, "joints2d": [[1, 2, 0.5]] * 18}],
            },
            r"frame 0: 'joints2d' has shape \(18, 3\), expected \(19, 3\)",
        ),
        (
            {
                "format": "mocaprig.eventcap.detections",
                "format_version": 1,
                "source": "s",
                "frames": [{"t_us": 1.5, "joints2d": [[1, 2, 0.5]] * 19}],
            },
            "needs an integer 't_us'",
        ),
    ],
)
def test_json_malformed_files_are_refused_with_the_file_named(
    tmp_path: Path, doc: dict[str, object], match: str
) -> None:
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(RecordingError, match=match) as info:
        JsonDetections(path)
    assert "bad.json" in str(info.value)


# --- synthetic detector ----------------------------------------------------------------------


def _separated_truth(frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Truth where every right joint is far left of its left partner (swaps are visible)."""
    rng = np.random.default_rng(11)
    t = np.arange(frames, dtype=np.int64) * 1000 + 17
    j2 = np.empty((frames, 19, 2))
    for name, i in SLOT.items():
        base = 60.0 if name.startswith("right_") else 180.0 if name.startswith("left_") else 120.0
        j2[:, i, 0] = base + rng.uniform(-5, 5, frames)
        j2[:, i, 1] = 20.0 + 8.0 * i
    j3 = np.zeros((frames, 19, 3))
    j3[:, :, 0] = (j2[:, :, 0] - 120.0) * 5.0
    j3[:, :, 1] = (j2[:, :, 1] - 20.0) * 5.0
    return t, j2, j3


def test_synthetic_2d_noise_has_the_configured_sigma() -> None:
    t, j2, _ = _separated_truth(600)
    syn = SyntheticDetections(
        t,
        j2,
        noise=SyntheticNoise(sigma_px=3.0, swap_probability=0.0, drop_probability=0.0),
        seed=1,
    )
    res = np.stack([syn.detect(int(v)).joints2d_px for v in t]) - j2
    assert res.std() == pytest.approx(3.0, rel=0.04)  # 22 800 samples: 1 σ of the estimate ≈ 0.5 %
    assert abs(res.mean()) < 0.1


def test_synthetic_swap_and_drop_rates_match_the_configuration() -> None:
    t, j2, _ = _separated_truth(2000)
    noise = SyntheticNoise(sigma_px=1.0, swap_probability=0.05, drop_probability=0.1)
    syn = SyntheticDetections(t, j2, noise=noise, seed=2)
    dets = [syn.detect(int(v)) for v in t]
    rs = SLOT["right_shoulder"]
    conf = np.stack([d.confidence for d in dets])
    xs = np.stack([d.joints2d_px[:, 0] for d in dets])
    # a frame is swapped when its right-side joints sit on the left side's x (> 120 px)
    right = [SLOT[n] for n in EVENTCAP_KEYPOINTS if n.startswith("right_")]
    seen = conf[:, right] > 0
    swapped = (np.where(seen, xs[:, right], np.nan) > 120.0).any(axis=1)
    assert swapped.mean() == pytest.approx(0.05, abs=0.015)  # binomial σ ≈ 0.005
    assert (conf == 0).mean() == pytest.approx(0.1, abs=0.01)
    kept = conf[conf > 0]
    assert kept.min() >= 0.6
    assert np.all(xs[conf == 0] == 0.0)
    assert np.isfinite(xs[:, rs]).all()


def test_synthetic_3d_noise_sigma_and_scale() -> None:
    t, j2, j3 = _separated_truth(400)
    noise = SyntheticNoise(sigma_3d_mm=40.0, swap_probability=0.0, scale_sigma=0.03)
    syn = SyntheticDetections(t, j2, joints3d_root_rel_mm=j3, noise=noise, seed=3)
    got3 = [syn.detect(int(v)).joints3d_root_rel_mm for v in t]
    got = np.stack([g for g in got3 if g is not None])
    assert got.shape == j3.shape
    assert np.all(got[:, SLOT["pelvis"]] == 0.0)
    truth = syn.scale * (j3 - j3[:, SLOT["pelvis"] : SLOT["pelvis"] + 1])
    res = got - truth
    # pelvis noise is subtracted from all joints: per-coordinate σ of the rest is 40·√2
    others = [i for i in range(19) if i != SLOT["pelvis"]]
    assert res[:, others].std() == pytest.approx(40.0 * np.sqrt(2.0), rel=0.05)
    assert syn.scale != 1.0
    assert abs(syn.scale - 1.0) < 0.15


def test_synthetic_is_deterministic_per_seed_and_independent_of_call_order() -> None:
    t, j2, j3 = _separated_truth(30)
    a = SyntheticDetections(t, j2, joints3d_root_rel_mm=j3, seed=7)
    b = SyntheticDetections(t, j2, joints3d_root_rel_mm=j3, seed=7)
    forward = [a.detect(int(v)) for v in t]
    backward = {int(v): b.detect(int(v)) for v in t[::-1]}
    for d in forward:
        np.testing.assert_array_equal(d.joints2d_px, backward[d.t_us].joints2d_px)
        np.testing.assert_array_equal(d.confidence, backward[d.t_us].confidence)
    np.testing.assert_array_equal(a.detect(int(t[3])).joints2d_px, forward[3].joints2d_px)
    c = SyntheticDetections(t, j2, seed=8)
    assert not np.allclose(c.detect(int(t[0])).joints2d_px, forward[0].joints2d_px)


def test_synthetic_detections_are_always_labelled_synthetic(tmp_path: Path) -> None:
    syn = _synthetic(frames=2)
    assert syn.source == "synthetic"
    path = tmp_path / "d.json"
    write_detections_json(path, [syn.detect(int(v)) for v in syn.times_us])
    assert json.loads(path.read_text())["source"] == "synthetic"


def test_synthetic_rejects_float_times() -> None:
    with pytest.raises(ValidationError, match="integer µs"):
        SyntheticDetections(np.array([0.0, 1.0]), np.zeros((2, 19, 2)), seed=0)


def test_every_implementation_satisfies_the_detector_protocol(tmp_path: Path) -> None:
    xy, conf = _pose(BODY25_NAMES)
    _openpose_file(tmp_path, 0, [_flat(xy, conf)])
    coco = tmp_path / "coco.json"
    coco.write_text("[]")
    ours = tmp_path / "ours.json"
    write_detections_json(ours, [_synthetic().detect(0)])
    for det in (
        OpenPoseJsonDetections(tmp_path, [0]),
        CocoKeypointDetections(coco, {1: 0}),
        JsonDetections(ours),
        _synthetic(),
    ):
        assert isinstance(det, Detector)
        assert isinstance(det.detect(0), Detection)


def test_synthetic_from_world_gives_root_relative_camera_axes_in_mm() -> None:
    rng = np.random.default_rng(12)
    world = rng.normal(scale=0.4, size=(3, 19, 3)) + np.array([0.0, 3.0, 1.0])
    pose = np.eye(4)
    # camera x = world x, camera y (down) = world −z, camera z (forward) = world y
    pose[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    pose[:3, 3] = [0.0, -2.0, 1.2]
    exact = SyntheticNoise(
        sigma_px=0.0,
        swap_probability=0.0,
        drop_probability=0.0,
        confidence_low=1.0,
        sigma_3d_mm=0.0,
        scale_sigma=0.0,
    )
    px = rng.uniform(0, 200, size=(3, 19, 2))
    t = np.array([0, 40_000, 80_000])
    syn = SyntheticDetections.from_world(t, px, world, pose, noise=exact, seed=0)
    det = syn.detect(40_000)
    d = (world[1] - world[1, SLOT["pelvis"]]) * 1000.0
    expected = np.column_stack([d[:, 0], -d[:, 2], d[:, 1]])
    assert det.joints3d_root_rel_mm is not None
    np.testing.assert_allclose(det.joints3d_root_rel_mm, expected, atol=1e-9)
    np.testing.assert_allclose(det.joints2d_px, px[1])
    np.testing.assert_array_equal(det.confidence, np.ones(19))
