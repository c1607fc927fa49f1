"""Live DeMoCap on the (mock) D415 rig: the driver's frame sets -> instants -> joints -> MCAP.

The mock cameras of the shared calibrated session's seed see the same world, so the session's
calibration serves them, their joints can be scored against its truth, and a live run must give
what the replay of the session's recording gives: live and replay are one path.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from mocaprig.acquire.camera_backends import open_cameras
from mocaprig.acquire.recording import Recording, info
from mocaprig.cli import main
from mocaprig.drivers_mock.truth import democap_truth_at
from mocaprig.process.body import MARKER_NAMES
from mocaprig.process.democap.infer import DemocapPredictor
from mocaprig.process.democap.live import LiveResult
from mocaprig.process.democap.live_capture import LiveInstant, run_live
from mocaprig.process.democap.replay import JOINTS_TOPIC, MARKERS_TOPIC, run_replay
from mocaprig.process.democap.solve import SHAPE_DIM, SubjectCalibration
from mocaprig.process.democap.subject import save_subject
from tests.conftest import CalibratedSession


@pytest.fixture
def one_thread() -> Iterator[None]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


@pytest.mark.slow
@pytest.mark.usefixtures("one_thread")
def test_live_run_on_the_mock_rig_records_joints_near_the_truth(
    calibrated_session: CalibratedSession, tmp_path: Path
) -> None:
    cs = calibrated_session
    cams = open_cameras("mock", seed=cs.seed, seconds=cs.seconds)
    got: list[tuple[LiveResult, LiveInstant]] = []
    out = tmp_path / "live.mcap"
    # the live setting: 2 turns in one batched pass, the network alone (no skeleton solve)
    predictor = DemocapPredictor(rotations=2, solve=False)
    try:
        summary = run_live(
            cams,
            cs.calibration,
            seconds=1.0,
            out=out,
            predictor=predictor,
            on_result=lambda r, i: got.append((r, i)),
        )
    finally:
        for cam in cams:
            cam.close()
    # 30 Hz for 1 s of camera time: every instant seen by all four hardware-synced cameras.
    assert summary.instants == len(got) >= 28
    assert all(r.cameras_used == 4 for r, _ in got)
    assert summary.predicted == summary.instants
    t = np.array([i.t_ref_ns for _, i in got])
    assert np.all(np.diff(t) > 30_000_000)  # one instant per frame period, in order
    _, true_j = democap_truth_at(cs.truth, t, clock="vicon")
    pred_j = np.stack([r.prediction.joints_m for r, _ in got if r.prediction is not None])
    mpjpe_mm = float(np.mean(np.linalg.norm(pred_j - true_j, axis=-1)) * 1e3)
    assert mpjpe_mm < 60.0  # 2-turn live ensemble, 19 joints: 37 mm measured on this seed
    # Written through the recorder: nothing dropped, one scene per instant and topic.
    s = info(out)
    assert s.drops_total == 0
    counts = {st.topic: st.messages for st in s.streams}
    assert counts[MARKERS_TOPIC] == counts[JOINTS_TOPIC] == summary.predicted
    with Recording(out) as rec:
        assert "calibration.toml" in [a.name for a in rec.attachments()]
        assert rec.metadata()["democap_live"]["cameras"].count("d415/") == 4
        # this predictor runs uncompiled, and the run and its file say so
        assert rec.metadata()["democap_live"]["compiled"] == "False"
    assert summary.compiled is False
    # One path: the replay of the recording of the same world gives the same instants and joints.
    replay = run_replay(cs.session, cs.calib, out=tmp_path / "replay.mcap", predictor=predictor)
    k = np.searchsorted(replay.t_ref_ns, t)
    np.testing.assert_array_equal(replay.t_ref_ns[k], t)
    np.testing.assert_allclose(replay.joints_m[k], pred_j, atol=1e-9)
    np.testing.assert_array_equal(replay.points_per_instant[k], [r.points for r, _ in got])


@pytest.mark.slow
@pytest.mark.usefixtures("one_thread")
def test_democap_live_command_reports_json(
    calibrated_session: CalibratedSession, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(
        ["democap", "live", "--mock", "--seed", str(calibrated_session.seed), "--calib",
         str(calibrated_session.calib), "--seconds", "0.3", "--world-seconds",
         str(calibrated_session.seconds), "--rotations", "1", "--json"]
    )  # fmt: skip
    assert code == 0
    out: dict[str, Any] = json.loads(capsys.readouterr().out)
    assert out["instants"] >= 8
    assert out["predicted"] == out["instants"]
    assert sorted(out["frame_sets"]) == sorted(out["cameras"])
    assert out["out"] is None
    # compiled by default, before the cameras started; the network kept up
    assert isinstance(out["compiled"], bool)
    assert out["warm_up_s"] > 0.0
    assert out["skipped"] == 0
    assert out["subject_height_m"] is None  # every instant on its own


@pytest.mark.slow
@pytest.mark.usefixtures("one_thread")
def test_democap_live_with_the_solve_solves_as_a_subject_file(
    calibrated_session: CalibratedSession, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    subject = SubjectCalibration(
        shape_z=np.r_[0.92, 1.0, np.zeros(SHAPE_DIM - 2)],
        marker_offsets_m=np.zeros((len(MARKER_NAMES), 3)),
        frames=3,
    )
    actor = save_subject(subject, tmp_path / "actor.json")
    out = tmp_path / "live.mcap"
    code = main(
        ["democap", "live", "--mock", "--seed", str(calibrated_session.seed), "--calib",
         str(calibrated_session.calib), "--seconds", "0.2", "--world-seconds",
         str(calibrated_session.seconds), "--rotations", "1", "--no-compile", "--solve",
         "--subject", str(actor), "--out", str(out), "--json"]
    )  # fmt: skip
    assert code == 0
    summary: dict[str, Any] = json.loads(capsys.readouterr().out)
    assert summary["predicted"] >= 1
    assert summary["subject_height_m"] == pytest.approx(subject.standing_height_m)
    with Recording(out) as rec:
        written = float(rec.metadata()["democap_live"]["subject_height_m"])
    assert written == pytest.approx(subject.standing_height_m, abs=1e-4)


class _SlowNetwork:
    """The live network slowed far below the camera rate (as with ``--solve``)."""

    def __init__(self, inner: DemocapPredictor) -> None:
        self.inner = inner

    def predict_many(self, clouds: Any, **kw: Any) -> Any:
        time.sleep(0.4)
        return self.inner.predict_many(clouds, **kw)


@pytest.mark.slow
@pytest.mark.usefixtures("one_thread")
def test_a_network_behind_the_cameras_skips_instants_and_writes_each_skip_down(
    calibrated_session: CalibratedSession, tmp_path: Path
) -> None:
    cs = calibrated_session
    cams = open_cameras("mock", seed=cs.seed, seconds=cs.seconds)
    out = tmp_path / "live.mcap"
    slow = _SlowNetwork(DemocapPredictor(rotations=1, solve=False))
    try:
        summary = run_live(cams, cs.calibration, seconds=0.5, out=out, predictor=slow)
    finally:
        for cam in cams:
            cam.close()
    assert summary.skipped >= 1
    assert summary.predicted + summary.skipped == summary.instants
    assert summary.compiled is None  # this predictor does not say
    with Recording(out) as rec:
        logs = [m.decode().message for m in rec.messages("/log")]
        counts = {st.topic: st.messages for st in info(out).streams}
    assert sum("skipped: the network was behind" in m for m in logs) == summary.skipped
    assert counts[JOINTS_TOPIC] == summary.predicted


def test_democap_live_help_has_examples(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["democap", "live", "--help"])
    assert exc.value.code == 0
    assert "examples:" in capsys.readouterr().out


def test_democap_live_takes_a_subject_only_with_the_solve(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # refused before a calibration is read or a camera opened
    argv = ["democap", "live", "--calib", str(tmp_path / "calib.toml"), "--mock"]
    assert main([*argv, "--subject", str(tmp_path / "actor.json")]) == 1
    assert "--subject is used by the skeleton solve" in capsys.readouterr().err
    assert main([*argv, "--solve", "--subject", str(tmp_path / "actor.json")]) == 1
    assert "democap subject" in capsys.readouterr().err  # no such file: how to make one
