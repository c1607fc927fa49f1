"""``process.batch.runner``: resumable, atomic outputs, one retry, failures reported by stage.

The worker functions are the cheap stand-ins of ``fake_tasks`` (``runner.TASKS`` patched);
the real pipelines run in tests/e2e/test_process_batch.py.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path
from unittest.mock import patch

import numpy as np
import pytest

from mocaprig.calib.c3d_read import read_c3d
from mocaprig.calib.calibration import write_calibration
from mocaprig.process.batch import runner
from mocaprig.process.batch.engines import Engine, InProcessEngine, ProcessPoolEngine
from mocaprig.process.batch.runner import MANIFEST_NAME, process_sessions
from mocaprig.process.batch.sessions import SessionInputs, find_sessions
from mocaprig.process.batch.tasks import ProcessSettings
from tests.process.batch import fake_tasks

DEMOCAP = ProcessSettings(methods=("democap",), democap_every=3)


@pytest.fixture(autouse=True)
def fake_workers() -> Iterator[None]:
    fakes = {
        "instants": fake_tasks.instants,
        "span": fake_tasks.span,
        "plan": fake_tasks.plan,
        "segment": fake_tasks.segment,
    }
    with patch.dict(runner.TASKS, fakes):
        yield


def _sessions(root: Path, modes: dict[str, str]) -> tuple[SessionInputs, ...]:
    """Session folders with an (unread) recording, a calibration and a ``mode`` each."""
    cal = write_calibration(fake_tasks.calibration(), root / "calib.toml")
    folders = []
    for name, mode in modes.items():
        d = root / name
        d.mkdir()
        (d / "session.mcap").write_bytes(b"")
        (d / "eventcap_detections.json").write_text("{}")
        (d / "mode").write_text(mode)
        folders.append(d)
    return find_sessions(folders, calib=cal)


def _parts(out: Path) -> list[Path]:
    return sorted(out.glob("*/.*.part-*"))


def test_every_session_gets_its_outputs_and_manifest(tmp_path: Path) -> None:
    sessions = _sessions(tmp_path, {"a": "ok", "b": "ok"})
    report = process_sessions(
        sessions, out=tmp_path / "out", settings=DEMOCAP, engine=InProcessEngine()
    )
    assert report.ok
    assert [(j.session, j.status) for j in report.jobs] == [("a", "done"), ("b", "done")]
    job = report.jobs[1]
    assert [p.name for p in job.outputs] == [
        "democap.c3d",
        "democap.csv",
        "democap.mcap",
        MANIFEST_NAME,
    ]
    rows = fake_tasks.csv_rows(tmp_path / "out/b/democap/democap.csv")
    # Every 3rd of the 12 instants, 33.3 ms apart, in one span.
    np.testing.assert_allclose(rows[:, 0], [5.0, 5.1, 5.2, 5.3], atol=1e-8)
    assert job.details["spans"] == 1
    assert "outputs" not in job.details  # the staging paths are not reported
    assert _parts(tmp_path / "out") == []


def test_democap_spans_are_joined_into_the_files_of_one_span(tmp_path: Path) -> None:
    sessions = _sessions(tmp_path, {"a": "ok"})
    one = process_sessions(
        sessions, out=tmp_path / "one", settings=DEMOCAP, engine=InProcessEngine()
    )
    split = ProcessSettings(methods=("democap",), democap_every=3, democap_span=3)
    two = process_sessions(sessions, out=tmp_path / "two", settings=split, engine=InProcessEngine())
    assert (one.jobs[0].details["spans"], two.jobs[0].details["spans"]) == (1, 2)
    assert two.jobs[0].details["instants"] == 4
    for name in ("democap.csv", "democap.c3d"):
        a = (tmp_path / "one/a/democap" / name).read_bytes()
        assert a == (tmp_path / "two/a/democap" / name).read_bytes()


def test_finished_outputs_are_kept_and_skipped(tmp_path: Path) -> None:
    sessions = _sessions(tmp_path, {"a": "ok"})
    out = tmp_path / "out"
    process_sessions(sessions, out=out, settings=DEMOCAP, engine=InProcessEngine())
    mcap = out / "a/democap/democap.mcap"
    before = mcap.stat().st_mtime_ns
    (Path(sessions[0].folder) / "mode").write_text("always")
    report = process_sessions(sessions, out=out, settings=DEMOCAP, engine=InProcessEngine())
    assert report.ok
    assert report.jobs[0].status == "skipped"
    assert report.jobs[0].details == {}  # same settings
    assert report.jobs[0].seconds == 0.0
    assert mcap.stat().st_mtime_ns == before


def test_a_kept_output_made_with_other_settings_is_flagged(tmp_path: Path) -> None:
    sessions = _sessions(tmp_path, {"a": "ok"})
    out = tmp_path / "out"
    process_sessions(sessions, out=out, settings=DEMOCAP, engine=InProcessEngine())
    every_5 = ProcessSettings(methods=("democap",), democap_every=5)
    report = process_sessions(sessions, out=out, settings=every_5, engine=InProcessEngine())
    assert report.jobs[0].status == "skipped"
    assert report.jobs[0].details == {"other_settings": {"democap_every": 3, "subject": None}}


def test_a_kept_output_made_without_the_session_s_subject_file_is_flagged(tmp_path: Path) -> None:
    sessions = _sessions(tmp_path, {"a": "ok"})
    out = tmp_path / "out"
    process_sessions(sessions, out=out, settings=DEMOCAP, engine=InProcessEngine())
    as_actor = [dataclasses.replace(s, subject=f"{s.folder}/actor.json") for s in sessions]
    report = process_sessions(as_actor, out=out, settings=DEMOCAP, engine=InProcessEngine())
    assert report.jobs[0].status == "skipped"
    assert report.jobs[0].details == {"other_settings": {"democap_every": 3, "subject": None}}


def test_a_task_that_raises_is_retried_once(tmp_path: Path) -> None:
    sessions = _sessions(tmp_path, {"a": "raise-once"})
    report = process_sessions(
        sessions, out=tmp_path / "out", settings=DEMOCAP, engine=InProcessEngine()
    )
    job = report.jobs[0]
    assert job.status == "done"
    assert job.retried == ("span 0: RuntimeError: boom",)
    assert _parts(tmp_path / "out") == []


def test_a_failing_session_is_reported_by_stage_and_the_others_finish(tmp_path: Path) -> None:
    sessions = _sessions(tmp_path, {"bad": "always", "good": "ok"})
    report = process_sessions(
        sessions, out=tmp_path / "out", settings=DEMOCAP, engine=InProcessEngine()
    )
    bad, good = report.jobs
    assert not report.ok
    assert (bad.status, bad.stage) == ("failed", "span 0")
    assert bad.error == "RuntimeError: bad cannot be replayed"
    assert len(bad.retried) == 1
    assert good.status == "done"
    # No partial output: neither the method folder nor an attempt's staging folder.
    assert not (tmp_path / "out/bad/democap").exists()
    assert _parts(tmp_path / "out") == []


def test_a_folder_not_written_by_the_run_is_not_taken_as_finished(tmp_path: Path) -> None:
    sessions = _sessions(tmp_path, {"a": "ok"})
    (tmp_path / "out/a/democap").mkdir(parents=True)
    report = process_sessions(
        sessions, out=tmp_path / "out", settings=DEMOCAP, engine=InProcessEngine()
    )
    assert (report.jobs[0].status, report.jobs[0].stage) == ("failed", "outputs")
    assert "no done.json" in str(report.jobs[0].error)


def test_staging_left_by_a_killed_run_is_removed(tmp_path: Path) -> None:
    sessions = _sessions(tmp_path, {"a": "ok"})
    stale = tmp_path / "out/a/.democap.part-0123456789ab"
    stale.mkdir(parents=True)
    (stale / "democap.mcap").write_text("half")
    process_sessions(sessions, out=tmp_path / "out", settings=DEMOCAP, engine=InProcessEngine())
    assert not stale.exists()
    assert (tmp_path / "out/a/democap/done.json").is_file()


def _eventcap(tmp_path: Path, engine: Engine, mode: str = "ok") -> tuple[Path, runner.BatchReport]:
    sessions = _sessions(tmp_path, {"take": mode})
    settings = ProcessSettings(
        methods=("eventcap",), height_m=1.75, segment_batches=2, overlap=1, template=False
    )
    out = tmp_path / "out"
    return out, process_sessions(sessions, out=out, settings=settings, engine=engine)


def test_eventcap_segments_are_stitched_into_one_take(tmp_path: Path) -> None:
    out, report = _eventcap(tmp_path, InProcessEngine())
    job = report.jobs[0]
    assert job.status == "done", job.error
    assert job.details["segments"] == 2
    assert job.details["tracking_frames"] == fake_tasks.BATCHES * fake_tasks.STEP + 1
    c3d = read_c3d(out / "take/eventcap/eventcap.c3d")
    x_mm = np.nanmean(np.asarray(c3d.positions_m)[:, :, 0], axis=1) * 1e3
    # Every instant once, in order: the fake body moves 1 mm per instant.
    np.testing.assert_allclose(np.diff(x_mm), 1.0, atol=1e-3)
    assert {p.name for p in job.outputs} == {
        "eventcap.mcap",
        "eventcap.c3d",
        "eventcap.bvh",
        MANIFEST_NAME,
    }


def test_a_failed_segment_is_retried_alone(tmp_path: Path) -> None:
    _, report = _eventcap(tmp_path, InProcessEngine(), mode="segment-once")
    job = report.jobs[0]
    assert job.status == "done"
    assert job.retried == ("segment 1: RuntimeError: segment boom",)


@pytest.mark.slow
def test_a_dead_pool_process_is_retried(tmp_path: Path) -> None:
    sessions = _sessions(tmp_path, {"a": "die-once"})
    with ProcessPoolEngine(1) as engine:
        report = process_sessions(sessions, out=tmp_path / "out", settings=DEMOCAP, engine=engine)
    job = report.jobs[0]
    assert job.status == "done", job.error
    assert len(job.retried) == 1
    assert job.retried[0].startswith("span 0: BrokenProcessPool")
    assert _parts(tmp_path / "out") == []
