"""``process.eventcap.run``: recording access, inputs, errors and the result writers (no batch
is solved here; tests/e2e/test_eventcap_run.py runs the whole command on a simulated session)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pytest

from mocaprig.acquire.events import make_events
from mocaprig.acquire.recorder import Recorder
from mocaprig.acquire.recording import Recording
from mocaprig.acquire.recording_format import (
    DavisFrameInfo,
    EventPacket,
    ImageMsg,
    SceneUpdateMsg,
)
from mocaprig.calib.calibration import (
    Calibration,
    CameraCalibration,
    ClockMapping,
    write_calibration,
)
from mocaprig.errors import CalibrationError, ProcessingError, RecordingError, ValidationError
from mocaprig.process.body.kinematics import (
    EVENTCAP_KEYPOINTS,
    eventcap_keypoints,
    forward_kinematics,
    neutral_pose,
)
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.body.surface import capsules
from mocaprig.process.eventcap.detections import Detection, write_detections_json
from mocaprig.process.eventcap.run import (
    JOINTS_TOPIC,
    KEYPOINT_BONES,
    METADATA_NAME,
    TEMPLATE_TOPIC,
    EventcapResultsWriter,
    EventcapRunResult,
    RecordingEventSource,
    RecordingFrames,
    ResultsHeader,
    keypoint_scene,
    load_detector,
    load_shape,
    run_eventcap,
    select_davis,
)
from mocaprig.process.eventcap.take import array_source

SERIAL = "02460013"
FRAME_PERIOD_US = 40_000
EXPOSURE_US = 5_000


def _record(
    path: Path,
    *,
    frames: int = 4,
    events: bool = True,
    serials: tuple[str, ...] = (SERIAL,),
    seed: int = 0,
) -> np.ndarray:
    """A DAVIS recording: ``frames`` APS frames every 40 ms (5 ms exposure, frame info) and
    random events in 10 ms packets; returns all events (sorted)."""
    rng = np.random.default_rng(seed)
    span_us = frames * FRAME_PERIOD_US
    n = 4000
    t = np.sort(rng.integers(0, span_us, n))
    evs = make_events(t, rng.integers(0, 240, n), rng.integers(0, 180, n), rng.integers(0, 2, n))
    with Recorder(path, min_free_disk_bytes=0) as rec:
        for serial in serials:
            hf = rec.add_stream(f"/davis/{serial}/frame", ImageMsg)
            hi = rec.add_stream(f"/davis/{serial}/frame_info", DavisFrameInfo)
            he = rec.add_stream(f"/davis/{serial}/events", EventPacket) if events else None
            log = 1_000_000_000
            for k in range(frames):
                start = k * FRAME_PERIOD_US + 1000
                end = start + EXPOSURE_US
                img = np.full((180, 240), 100 + k, np.uint16)
                mid_ns = (start + end) // 2 * 1000
                log += 1_000_000
                rec.put_wait(hf, ImageMsg(img, "mono16", mid_ns), log_time_ns=log, sequence=k)
                info = DavisFrameInfo(k, start - 100, end + 100, start, end, 1)
                rec.put_wait(hi, info, log_time_ns=log, sequence=k)
            if he is not None:
                edges = np.arange(0, span_us + 10_000, 10_000)
                for j in range(edges.size - 1):
                    sel = (t >= edges[j]) & (t < edges[j + 1])
                    log += 1_000_000
                    rec.put_wait(he, EventPacket(evs[sel], seq=j), log_time_ns=log, sequence=j)
    return evs


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    p = tmp_path_factory.mktemp("run") / "session.mcap"
    return p, _record(p)


def _calibration(*, davis: bool = True, clock: bool = True) -> Calibration:
    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]  # looking along +Y
    T[:3, 3] = (0.0, -3.0, 1.0)
    cam = CameraCalibration(
        name=f"davis/{SERIAL}" if davis else "d415/1",
        kind="davis" if davis else "d415",
        serial=SERIAL if davis else "1",
        width=240,
        height=180,
        K=np.array([[200.0, 0, 120], [0, 200, 90], [0, 0, 1]]),
        distortion=np.zeros(5),
        T_world_cam=T,
    )
    clocks = (ClockMapping(f"davis/{SERIAL}", "vicon", offset_ns=5_000_000_000),) if clock else ()
    return Calibration(cameras=(cam,), clocks=clocks)


def _detections(path: Path, times_us: list[int]) -> Path:
    dets = [
        Detection(t, np.full((19, 2), 100.0), np.ones(19), source="synthetic") for t in times_us
    ]
    write_detections_json(path, dets)
    return path


def test_event_source_windows_match_the_in_memory_events(
    recording: tuple[Path, np.ndarray],
) -> None:
    path, evs = recording
    ref = array_source(evs)
    with Recording(path) as rec:
        src = RecordingEventSource(select_davis(rec))
        for t0, t1 in ((0, 5_000), (9_990, 10_010), (33_000, 118_000), (150_000, 400_000)):
            got, want = src(t0, t1), ref(t0, t1)
            np.testing.assert_array_equal(got["t"], want["t"])
            np.testing.assert_array_equal(got["x"], want["x"])
        assert src(500_000, 600_000).size == 0
        assert src.peak_window_events == ref(33_000, 118_000).size


def test_an_event_source_bounded_in_log_time_indexes_less_and_misses_no_event(
    recording: tuple[Path, np.ndarray],
) -> None:
    path, evs = recording
    ref = array_source(evs)
    with Recording(path) as rec:
        dav = select_davis(rec)
        whole = RecordingEventSource(dav).events_total_span_us
        logs = [m.log_time_ns for m in rec.messages(dav.device.topic("events"))]
        src = RecordingEventSource(
            dav, start_ns=logs[len(logs) // 3], end_ns=logs[2 * len(logs) // 3]
        )
        lo, hi = src.events_total_span_us
        assert whole[0] < lo < hi < whole[1]  # only the middle packets were decoded
        inside = (lo + 1, hi - 1)
        np.testing.assert_array_equal(src(*inside)["t"], ref(*inside)["t"])
        assert src.events_total_span_us == (lo, hi)
        # A window past what was indexed indexes the whole take: nothing is missed.
        np.testing.assert_array_equal(src(0, 5_000)["t"], ref(0, 5_000)["t"])
        assert src.events_total_span_us == whole


def test_frames_are_indexed_with_exposure_windows_and_decoded_lazily(
    recording: tuple[Path, np.ndarray],
) -> None:
    path, _ = recording
    with Recording(path) as rec:
        frames = RecordingFrames(select_davis(rec))
        assert len(frames) == 4
        assert frames[2].exposure_start_us == 2 * FRAME_PERIOD_US + 1000
        assert frames[2].exposure_end_us == frames[2].exposure_start_us + EXPOSURE_US
        assert float(frames[2].image_dn[0, 0]) == 102.0
        assert float(frames[-1].image_dn[5, 5]) == 103.0
        np.testing.assert_array_equal(frames.times_us, frames.all_times_us)
        part = RecordingFrames(select_davis(rec), start_us=40_000, end_us=125_000)
        assert [f.exposure_start_us for f in part] == [41_000, 81_000]
        assert part.all_times_us.size == 4
        assert len(RecordingFrames(select_davis(rec), limit=3)) == 3


def test_select_davis_asks_for_a_serial_when_there_are_several(tmp_path: Path) -> None:
    p = tmp_path / "two.mcap"
    _record(p, frames=2, serials=("111", "222"))
    with Recording(p) as rec:
        with pytest.raises(RecordingError, match="--davis SERIAL"):
            select_davis(rec)
        assert select_davis(rec, "222").device.serial == "222"
        with pytest.raises(RecordingError, match="no DAVIS with serial '333'"):
            select_davis(rec, "333")


def test_a_recording_without_a_davis_is_refused(tmp_path: Path) -> None:
    p = tmp_path / "none.mcap"
    with Recorder(p, min_free_disk_bytes=0) as rec:
        rec.log("INFO", "nothing")
    with Recording(p) as rec, pytest.raises(RecordingError, match="no DAVIS in the recording"):
        select_davis(rec)


def test_a_davis_without_events_is_refused(tmp_path: Path) -> None:
    p = tmp_path / "aps.mcap"
    _record(p, frames=3, events=False)
    with Recording(p) as rec, pytest.raises(RecordingError, match="no DVS events"):
        RecordingEventSource(select_davis(rec))


def test_load_detector_tells_our_json_from_coco_and_openpose(tmp_path: Path) -> None:
    times = [3_500, 43_500]
    ours = load_detector(_detections(tmp_path / "d.json", times), times)
    assert ours.source == "synthetic"
    coco = tmp_path / "coco.json"
    kp = [v for j in range(17) for v in (10.0 + j, 20.0, 0.9)]
    coco.write_text(json.dumps([{"image_id": 1, "keypoints": kp, "score": 0.9}]))
    det = load_detector(coco, times)
    assert det.source.startswith("coco")
    assert det.detect(43_500).t_us == 43_500
    op = tmp_path / "openpose"
    op.mkdir()
    body = [v for j in range(25) for v in (30.0 + j, 40.0, 0.8)]
    doc = {"people": [{"pose_keypoints_2d": body}]}
    (op / "take_000000000000_keypoints.json").write_text(json.dumps(doc))
    assert load_detector(op, times).source == "openpose-body25"
    with pytest.raises(ValidationError, match="no such file"):
        load_detector(tmp_path / "missing.json", times)


def test_load_shape_from_height_or_a_truth_file_but_not_both(tmp_path: Path) -> None:
    assert load_shape(height_m=1.8).height_m == pytest.approx(1.8)
    ref = BodyShape.from_height(1.66)
    (tmp_path / "scenario.json").write_text(json.dumps({"body_shape": asdict(ref)}))
    assert load_shape(shape_path=tmp_path / "scenario.json") == ref
    with pytest.raises(ValidationError, match="one of them"):
        load_shape(height_m=1.8, shape_path=tmp_path / "scenario.json")
    with pytest.raises(ValidationError, match="--height"):
        load_shape(height_m=17.5)


def _run(tmp_path: Path, session: Path, cal: Calibration, **kw: object) -> EventcapRunResult:
    calib = write_calibration(cal, tmp_path / "calib.toml", overwrite=True)
    det = kw.pop("detections", None) or _detections(tmp_path / "d.json", [3_500, 43_500])
    return run_eventcap(
        session,
        calib,
        out=tmp_path / "res.mcap",
        detections=det,  # type: ignore[arg-type]
        height_m=1.75,
        **kw,  # type: ignore[arg-type]
    )


def test_a_calibration_without_the_davis_says_to_calibrate_it(
    tmp_path: Path, recording: tuple[Path, np.ndarray]
) -> None:
    with pytest.raises(CalibrationError, match="mocaprig calibrate board"):
        _run(tmp_path, recording[0], _calibration(davis=False))


def test_fewer_than_two_frames_in_the_span_is_refused(
    tmp_path: Path, recording: tuple[Path, np.ndarray]
) -> None:
    with pytest.raises(ProcessingError, match=r"1 APS frame.*at least 2"):
        _run(tmp_path, recording[0], _calibration(), start_s=0.1, end_s=0.15)


def test_detections_that_miss_a_frame_are_refused_before_any_batch(
    tmp_path: Path, recording: tuple[Path, np.ndarray]
) -> None:
    det = _detections(tmp_path / "short.json", [3_500])
    with pytest.raises(ProcessingError, match="do not cover APS frame 1 at 43500"):
        _run(tmp_path, recording[0], _calibration(), detections=det, batches=1)


def test_existing_outputs_are_not_overwritten(
    tmp_path: Path, recording: tuple[Path, np.ndarray]
) -> None:
    (tmp_path / "res.bvh").write_text("keep")
    with pytest.raises(ProcessingError, match="--overwrite"):
        _run(tmp_path, recording[0], _calibration())
    assert (tmp_path / "res.bvh").read_text() == "keep"


@dataclass(frozen=True)
class _Track:
    header: ResultsHeader
    shape: BodyShape
    t_ns: np.ndarray
    poses: np.ndarray
    keypoints_m: np.ndarray


def _track(tmp_path: Path, frames: int = 5) -> _Track:
    shape = BodyShape.from_height(1.75)
    poses = np.repeat(neutral_pose(shape)[None], frames, axis=0)
    poses[:, 3] += np.linspace(0.0, 0.004, frames)  # 1 m/s along x
    kp = eventcap_keypoints(forward_kinematics(poses, shape), shape)
    t_us = 20_000 + 1000 * np.arange(frames, dtype=np.int64)
    header = ResultsHeader(
        session=tmp_path / "session.mcap",
        davis=f"davis/{SERIAL}",
        batches=1,
        frames=frames,
        time_base="vicon",
        t_first_davis_us=int(t_us[0]),
        world_frame="vicon",
        detection_source="synthetic",
    )
    return _Track(header, shape, t_us * 1000 + 7, poses, kp)


def _write(
    tr: _Track,
    blocks: list[int],
    *,
    mcap: Path | None = None,
    c3d: Path | None = None,
    bvh: Path | None = None,
) -> None:
    cal = _calibration()
    with EventcapResultsWriter(
        tr.header, tr.shape, mcap=mcap, c3d=c3d, bvh=bvh, calibration=cal
    ) as w:
        i = 0
        for n in blocks:
            w.write(tr.t_ns[i : i + n], tr.poses[i : i + n], tr.keypoints_m[i : i + n])
            i += n


def test_results_mcap_holds_one_scene_per_tracking_frame_and_topic(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import mocaprig.process.eventcap.run as run_module

    monkeypatch.setattr(run_module, "_CAPSULE_BLOCK", 2)  # capsules posed 2 frames at a time
    tr = _track(tmp_path)
    path = tmp_path / "r.mcap"
    _write(tr, [3, 2], mcap=path)
    with Recording(path) as rec:
        joints = list(rec.decoded(JOINTS_TOPIC))
        template = list(rec.decoded(TEMPLATE_TOPIC))
        assert "calibration.toml" in [a.name for a in rec.attachments()]
        assert rec.metadata()[METADATA_NAME]["frames"] == "5"
    assert [t for t, _ in joints] == tr.t_ns.tolist()
    assert len(template) == 5
    first = joints[0][1]
    assert isinstance(first, SceneUpdateMsg)
    ent = first.update.entities[0]
    assert len(ent.spheres) == 19
    assert len(ent.lines[0].points) == 2 * len(KEYPOINT_BONES)
    assert ent.spheres[0].pose.position.x == pytest.approx(tr.keypoints_m[0, 0, 0])
    assert ent.timestamp.ToNanoseconds() == tr.t_ns[0]
    for k in (2, 4):  # the first frame of a block and the last frame
        caps = template[k][1].update.entities[0]
        assert len(caps.cylinders) > 10
        assert len(caps.spheres) == 2 * len(caps.cylinders)
        want = capsules(tr.poses[k], tr.shape)
        end = caps.spheres[0].pose.position
        np.testing.assert_allclose([end.x, end.y, end.z], want.a_m[0], atol=1e-12)
    with pytest.raises(ProcessingError, match="--overwrite"):
        _write(tr, [5], mcap=path)


def test_results_written_in_blocks_equal_the_results_written_at_once(tmp_path: Path) -> None:
    tr = _track(tmp_path, frames=7)
    one = {k: tmp_path / f"one.{k}" for k in ("mcap", "c3d", "bvh")}
    many = {k: tmp_path / f"many.{k}" for k in ("mcap", "c3d", "bvh")}
    _write(tr, [7], **one)
    _write(tr, [1, 4, 0, 2], **many)
    assert one["c3d"].read_bytes() == many["c3d"].read_bytes()
    assert one["bvh"].read_text() == many["bvh"].read_text()
    with Recording(one["mcap"]) as a, Recording(many["mcap"]) as b:
        for topic in (JOINTS_TOPIC, TEMPLATE_TOPIC):
            assert [m.data for m in a.messages(topic)] == [m.data for m in b.messages(topic)]


def test_results_that_miss_announced_frames_leave_no_file(tmp_path: Path) -> None:
    tr = _track(tmp_path, frames=4)
    paths = {k: tmp_path / f"r.{k}" for k in ("mcap", "c3d", "bvh")}
    with pytest.raises(ProcessingError, match=r"3 tracking frames.*announced 4"):
        _write(tr, [3], **paths)
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_a_failure_while_writing_results_leaves_no_file(tmp_path: Path) -> None:
    tr = _track(tmp_path, frames=4)
    paths = {k: tmp_path / f"r.{k}" for k in ("mcap", "c3d", "bvh")}

    def run() -> None:
        with EventcapResultsWriter(
            tr.header, tr.shape, mcap=paths["mcap"], c3d=paths["c3d"], bvh=paths["bvh"]
        ) as w:
            w.write(tr.t_ns[:2], tr.poses[:2], tr.keypoints_m[:2])
            raise RuntimeError("batch 2 failed")

    with pytest.raises(RuntimeError, match="batch 2 failed"):
        run()
    assert list(tmp_path.iterdir()) == []


def test_results_c3d_holds_the_19_keypoints_at_1000_hz_in_mm(tmp_path: Path) -> None:
    import ezc3d

    tr = _track(tmp_path)
    path = tmp_path / "r.c3d"
    _write(tr, [2, 3], c3d=path)
    c = ezc3d.c3d(str(path))
    assert c["parameters"]["POINT"]["RATE"]["value"][0] == pytest.approx(1000.0)
    assert list(c["parameters"]["POINT"]["LABELS"]["value"]) == list(EVENTCAP_KEYPOINTS)
    pts = c["data"]["points"]  # (4, 19, F), mm
    assert pts.shape[1:] == (19, 5)
    np.testing.assert_allclose(pts[:3].transpose(2, 1, 0), tr.keypoints_m * 1e3, atol=1e-2)


def test_keypoint_scene_names_its_spheres_and_leaves_the_input_unchanged(tmp_path: Path) -> None:
    tr = _track(tmp_path, frames=1)
    kp = tr.keypoints_m[0].copy()
    scene = keypoint_scene("vicon", 5, kp)
    np.testing.assert_array_equal(kp, tr.keypoints_m[0])
    names = scene.update.entities[0].metadata[0].value.split(",")
    assert names == list(EVENTCAP_KEYPOINTS)


def test_cli_help_shows_examples_and_outputs(capsys: pytest.CaptureFixture[str]) -> None:
    from mocaprig.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["eventcap", "run", "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    assert "examples:" in text
    assert "/eventcap/joints" in text
    assert "--overwrite" in text


def test_cli_refuses_existing_outputs_without_overwrite(
    tmp_path: Path, recording: tuple[Path, np.ndarray], capsys: pytest.CaptureFixture[str]
) -> None:
    from mocaprig.cli import main

    calib = write_calibration(_calibration(), tmp_path / "calib.toml")
    det = _detections(tmp_path / "d.json", [3_500, 43_500])
    (tmp_path / "res.mcap").write_bytes(b"old")
    args = [str(recording[0]), "--calib", str(calib), "--detections", str(det)]
    code = main(["eventcap", "run", *args, "--height", "1.7", "--out", str(tmp_path / "res.mcap")])
    assert code != 0
    assert "pass --overwrite" in capsys.readouterr().err
    assert (tmp_path / "res.mcap").read_bytes() == b"old"
