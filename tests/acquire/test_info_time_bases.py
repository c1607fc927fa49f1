"""One time base per recording (issue 17, item 3): ``info`` never mixes clocks, names the streams
of a file that does, and the pipelines' results files keep every message on one clock."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from mocaprig.acquire.events import make_events
from mocaprig.acquire.recorder import Recorder
from mocaprig.acquire.recording import UNIX_EPOCH_MIN_NS, info
from mocaprig.acquire.recording_format import EventPacket
from mocaprig.cli import main


def _all_times_ns(path: Path) -> dict[str, list[int]]:
    """Every time stamped in an MCAP: message log/publish times per topic, attachments, and the
    recorder's summary time, read with the mcap package (not our reader)."""
    out: dict[str, list[int]] = {}
    with path.open("rb") as fh:
        reader = make_reader(fh)
        for _, channel, msg in reader.iter_messages(log_time_order=False):
            out.setdefault(channel.topic, []).extend([msg.log_time, msg.publish_time])
        for att in reader.iter_attachments():
            out.setdefault("attachment", []).extend([att.log_time, att.create_time])
        for meta in reader.iter_metadata():
            if "ended_ns" in meta.metadata:
                out.setdefault("ended_ns", []).append(int(meta.metadata["ended_ns"]))
    return out


def _old_import_like(path: Path, *, n: int = 20, step_ns: int = 10_000_000) -> Path:
    """A file as `import-events` wrote them before one clock per file: packets on the events'
    clock (ns from 0), the recorder's /diagnostics on wall time."""
    with Recorder(path, min_free_disk_bytes=0) as rec:
        h = rec.add_stream("/davis/old/events", EventPacket)
        for i in range(n):
            t = np.array([i * step_ns // 1000])
            ev = EventPacket(make_events(t, t % 7, t % 5, t % 2), seq=i)
            assert rec.put(h, ev, log_time_ns=i * step_ns, sequence=i)
    return path


def test_a_mixed_epoch_file_is_reported_with_its_streams_named(tmp_path: Path) -> None:
    inf = info(_old_import_like(tmp_path / "old.mcap"))
    assert inf.mixed_time_bases
    by_name = {b.name: b for b in inf.time_bases}
    assert by_name["relative"].topics == ("/davis/old/events",)
    assert by_name["unix"].topics == ("/diagnostics",)
    # The duration is that of the data streams' clock, never across the two epochs.
    assert inf.time_bases[0].name == "relative"
    assert inf.duration_s == pytest.approx(0.19)


def test_info_json_and_text_flag_a_mixed_epoch_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _old_import_like(tmp_path / "old.mcap")
    assert main(["info", str(path), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["mixed_time_bases"] is True
    assert d["duration_s"] == pytest.approx(0.19)
    assert {b["time_base"]: b["topics"] for b in d["time_bases"]} == {
        "relative": ["/davis/old/events"],
        "unix": ["/diagnostics"],
    }
    assert main(["info", str(path)]) == 0
    warning = [x for x in capsys.readouterr().out.splitlines() if "WARNING" in x]
    assert len(warning) == 1
    assert "mixed time bases" in warning[0]
    assert "/davis/old/events on a relative clock (0.000 .. 0.190 s)" in warning[0]
    assert "/diagnostics on Unix time (from " in warning[0]


def test_a_file_on_one_clock_is_not_flagged(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "one.mcap"
    with Recorder(path, min_free_disk_bytes=0) as rec:
        h = rec.add_stream("/davis/a/events", EventPacket)
        t0 = time.time_ns()
        for i in range(5):
            t = np.array([i])
            rec.put(h, EventPacket(make_events(t, t, t, t), seq=i), log_time_ns=t0 + i, sequence=i)
    inf = info(path)
    assert not inf.mixed_time_bases
    assert [b.name for b in inf.time_bases] == ["unix"]
    assert set(inf.time_bases[0].topics) == {"/davis/a/events", "/diagnostics"}
    assert main(["info", str(path)]) == 0
    assert "WARNING" not in capsys.readouterr().out


# --------------------------------------------------------------------------------------------
# results files of the pipelines
# --------------------------------------------------------------------------------------------


def _assert_one_clock(path: Path, t_first_ns: int, t_last_ns: int) -> None:
    times = _all_times_ns(path)
    assert "/diagnostics" in times
    for what, values in times.items():
        assert min(values) >= t_first_ns, what
        assert max(values) <= t_last_ns, what
    assert not info(path).mixed_time_bases


def test_democap_results_keep_every_message_on_the_reference_clock(tmp_path: Path) -> None:
    from mocaprig.process.body import DEMOCAP_JOINTS, MARKER_NAMES
    from mocaprig.process.democap.replay import ReplayResult, write_scene_mcap

    rng = np.random.default_rng(0)
    n = 6
    t_ref = 5_000_000_000 + 33_333_333 * np.arange(n, dtype=np.int64)  # a relative clock
    result = ReplayResult(
        session=tmp_path / "session.mcap",
        outputs={},
        cameras=("d415/1",),
        frames_per_camera={"d415/1": n},
        t_ref_ns=t_ref,
        cameras_per_instant=np.ones(n, dtype=np.int64),
        points_per_instant=np.full(n, 40, dtype=np.int64),
        markers_m=rng.normal(size=(n, len(MARKER_NAMES), 3)),
        joints_m=rng.normal(size=(n, len(DEMOCAP_JOINTS), 3)),
    )
    path = write_scene_mcap(result, tmp_path / "democap.mcap")
    _assert_one_clock(path, int(t_ref[0]), int(t_ref[-1]))
    assert info(path).time_bases[0].name == "relative"


def test_eventcap_results_keep_every_message_on_the_output_clock(tmp_path: Path) -> None:
    from mocaprig.process.body.kinematics import (
        eventcap_keypoints,
        forward_kinematics,
        neutral_pose,
    )
    from mocaprig.process.body.shape import BodyShape
    from mocaprig.process.eventcap.run import EventcapResultsWriter, ResultsHeader

    shape = BodyShape.from_height(1.75)
    frames = 4
    poses = np.repeat(neutral_pose(shape)[None], frames, axis=0)
    t_us = 20_000 + 1000 * np.arange(frames, dtype=np.int64)
    header = ResultsHeader(
        session=tmp_path / "session.mcap",
        davis="davis/1",
        batches=1,
        frames=frames,
        time_base="vicon",
        t_first_davis_us=int(t_us[0]),
        world_frame="vicon",
        detection_source="synthetic",
    )
    path = tmp_path / "eventcap.mcap"
    t_ns = t_us * 1000 + 7
    with EventcapResultsWriter(header, shape, mcap=path) as writer:
        writer.write(t_ns, poses, eventcap_keypoints(forward_kinematics(poses, shape), shape))
    _assert_one_clock(path, int(t_ns[0]), int(t_ns[-1]))


def test_a_mock_rig_recording_keeps_every_stream_on_unix_time(tmp_path: Path) -> None:
    # D415 frames, sync pulses, the log and the recorder's status: one host clock.
    from mocaprig.acquire.commands_record import record

    out = tmp_path / "r.mcap"
    t0 = time.time_ns()
    assert record(out=out, seconds=0.3, mock=True, rig=None, cameras=1) == 0
    t1 = time.time_ns()
    _assert_one_clock(out, t0, t1)
    inf = info(out)
    assert [b.name for b in inf.time_bases] == ["unix"]
    assert {"/syncbox/pulses", "/diagnostics"} <= set(inf.time_bases[0].topics)
    assert any(t.startswith("/d415/") for t in inf.time_bases[0].topics)
    assert t0 >= UNIX_EPOCH_MIN_NS


def test_a_stream_whose_own_times_jump_between_clocks_is_named_on_both(tmp_path: Path) -> None:
    path = tmp_path / "jump.mcap"
    with Recorder(path, min_free_disk_bytes=0, clock_ns=lambda: 1_000) as rec:
        h = rec.add_stream("/davis/j/events", EventPacket)
        for i, t_ns in enumerate([1_000, 2_000, 1_468_940_293_982_000_000]):
            t = np.array([t_ns // 1000])
            rec.put(h, EventPacket(make_events(t, t % 7, t % 5, t % 2), seq=i), log_time_ns=t_ns)
    inf = info(path)
    assert inf.mixed_time_bases
    by_name = {b.name: b for b in inf.time_bases}
    assert by_name["unix"].topics == ("/davis/j/events",)
    assert set(by_name["relative"].topics) == {"/davis/j/events", "/diagnostics"}
    assert inf.duration_s == pytest.approx(1e-6)  # 1,000 .. 2,000 ns, never across the jump
