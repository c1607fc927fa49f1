"""The 3D scene of ``record --live --calib``: a recording's D415 messages, offered as the
recorder's tap offers them, become the replay's markers, joints and cloud, on the truth."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

from mocaprig.acquire.commands_record import record
from mocaprig.acquire.recording import Recording
from mocaprig.drivers_mock.truth import democap_truth_at
from mocaprig.errors import CalibrationError, ValidationError
from mocaprig.process.body import DEMOCAP_JOINTS, MARKER_NAMES
from mocaprig.process.democap.live_scene import DemocapLiveScene, live_scene
from mocaprig.process.democap.replay import CLOUD_TOPIC, JOINTS_TOPIC, MARKERS_TOPIC
from tests.conftest import CalibratedSession


def _spheres(msg: object) -> np.ndarray:
    (ent,) = SceneUpdate.FromString(msg.encode()).entities  # type: ignore[attr-defined]
    return np.array(
        [[s.pose.position.x, s.pose.position.y, s.pose.position.z] for s in ent.spheres]
    )


def _stamp_ns(msg: object) -> int:
    (ent,) = SceneUpdate.FromString(msg.encode()).entities  # type: ignore[attr-defined]
    return int(ent.timestamp.ToNanoseconds())


@pytest.mark.slow  # runs the network on ~30 instants (~10 s)
def test_recorded_frames_offered_live_become_markers_and_joints_on_the_truth(
    calibrated_session: CalibratedSession,
) -> None:
    out: list[tuple[str, object, int]] = []
    with Recording(calibrated_session.session) as r:
        msgs = [m for m in r.messages() if m.topic.startswith("/d415/")]
    with live_scene(calibrated_session.calib, max_hz=100.0) as scene:
        last_log = None
        for m in msgs:
            if m.log_time_ns != last_log and last_log is not None:
                time.sleep(0.008)  # the recorder's pace, roughly: the worker takes the newest
            last_log = m.log_time_ns
            scene.offer(m.topic, m.decode(), m.log_time_ns)
            out.extend(scene.take())
        deadline = time.monotonic() + 10.0
        while scene.stats.run + scene.stats.failed < 5 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)
        out.extend(scene.take())
        stats = scene.stats
    assert stats.failed == 0
    assert stats.run >= 5
    # The worker always takes the newest instant: what it skipped is counted, none is run twice.
    assert stats.run + stats.skipped <= stats.grouped
    by_topic: dict[str, list[object]] = {}
    for topic, msg, _ in out:
        by_topic.setdefault(topic, []).append(msg)
    assert set(by_topic) == {CLOUD_TOPIC, MARKERS_TOPIC, JOINTS_TOPIC}
    assert len(_spheres(by_topic[MARKERS_TOPIC][0])) == len(MARKER_NAMES)
    assert len(_spheres(by_topic[JOINTS_TOPIC][0])) == len(DEMOCAP_JOINTS)
    # The fused clouds, stamped on the Vicon clock, sit on the true markers (as the replay's).
    clouds = by_topic[CLOUD_TOPIC]
    t = np.array([_stamp_ns(c) for c in clouds])
    assert np.all(np.diff(t) > 0)
    true_m, _ = democap_truth_at(calibrated_session.truth, t)
    d = np.concatenate(
        [
            np.linalg.norm(_spheres(c)[:, None] - true_m[k][None], axis=-1).min(axis=1)
            for k, c in enumerate(clouds)
        ]
    )
    assert np.median(d) * 1e3 < 25.0


def test_a_calibration_without_a_d415_or_a_live_flag_is_refused(
    tmp_path: Path, calibrated_session: CalibratedSession
) -> None:
    with pytest.raises(CalibrationError):
        live_scene(tmp_path / "missing.toml")
    with pytest.raises(ValidationError, match="needs --live"):
        record(
            out=tmp_path / "s.mcap",
            seconds=1.0,
            mock=True,
            rig=None,
            live_calibration=calibrated_session.calib,
        )
    with pytest.raises(ValidationError, match="max_hz"):
        DemocapLiveScene(calibrated_session.calibration, max_hz=0.0)


@pytest.mark.slow  # the mock rig for 4 s with the network behind the live view
def test_record_live_with_a_calibration_serves_the_3d_scene_without_a_recorder_drop(
    tmp_path: Path, calibrated_session: CalibratedSession
) -> None:
    """``mocaprig record --mock --cameras 4 --live --calib`` (a child process, as a user runs
    it): a WebSocket client sees the cloud, markers and joints channels (the mock cameras of the
    session's seed see its world), and the recording drops nothing and holds none of them."""
    import json
    import socket
    import subprocess
    import sys

    from mocaprig.acquire.live_view import LiveClient

    pytest.importorskip("foxglove")
    with socket.socket() as s:  # a free port for the client to know before recording starts
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "live.mcap"
    cmd = [
        sys.executable, "-m", "mocaprig.cli", "record", "--mock", "--seed",
        str(calibrated_session.seed), "--cameras", "4", "--no-syncbox", "--seconds", "4",
        "--live", "--port", str(port), "--calib", str(calibrated_session.calib),
        "--out", str(out), "--json",
    ]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    client = None
    try:
        deadline = time.monotonic() + 120.0
        while client is None and time.monotonic() < deadline and proc.poll() is None:
            try:
                client = LiveClient("127.0.0.1", port)
                client.connect()
            except Exception:
                client = None
                time.sleep(0.2)
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        if client is not None:
            client.close()
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stderr[-2000:]
    summary = json.loads(stdout)
    assert summary["drops_total"] == 0
    assert client is not None
    assert {CLOUD_TOPIC, MARKERS_TOPIC, JOINTS_TOPIC} <= set(client.channels), client.channels
    assert client.counts().get(CLOUD_TOPIC, 0) >= 1, client.counts()
    with Recording(out) as r:
        assert not any(t.startswith("/democap/") for t in r.topics)  # shown, never recorded
