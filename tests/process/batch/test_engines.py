"""``process.batch.engines``: in-process, process pool and Dask behind one interface; a worker
killed mid-run under Dask (the runner's one retry)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from unittest.mock import patch

import pytest

from mocaprig.calib.calibration import write_calibration
from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.batch import runner
from mocaprig.process.batch.engines import (
    DaskEngine,
    InProcessEngine,
    ProcessPoolEngine,
    open_engine,
)
from mocaprig.process.batch.runner import process_sessions
from mocaprig.process.batch.sessions import find_sessions
from mocaprig.process.batch.tasks import ProcessSettings
from tests.process.batch import fake_tasks

NO_DASK = "Dask is not installed (pip install 'dask[distributed]')"


def _fail(text: str) -> None:
    raise RuntimeError(text)


def test_in_process_engine_runs_tasks_in_order_when_waited_on() -> None:
    calls: list[int] = []
    engine = InProcessEngine()
    futures = [engine.submit(calls.append, i) for i in range(3)]
    assert calls == []  # nothing runs at submission
    done = engine.wait(futures)
    assert calls == [0]
    assert done == {futures[0]}
    engine.wait(futures[2:])
    assert calls == [0, 1, 2]


def test_in_process_engine_hands_back_a_task_exception() -> None:
    engine = InProcessEngine()
    fut = engine.submit(_fail, "broken input")
    engine.wait([fut])
    with pytest.raises(RuntimeError, match="broken input"):
        fut.result()


def test_auto_is_in_process_without_a_scheduler_or_workers(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DASK_SCHEDULER_ADDRESS", raising=False)
    with open_engine("auto") as engine:
        assert isinstance(engine, InProcessEngine)
        assert engine.describe() == "in-process (1 worker)"


def test_auto_with_workers_is_a_local_pool(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DASK_SCHEDULER_ADDRESS", raising=False)
    with open_engine("auto", workers=2) as engine:
        assert isinstance(engine, ProcessPoolEngine)
        assert engine.describe() == "local (2 workers)"


def test_workers_below_one_are_refused() -> None:
    with pytest.raises(ValidationError, match="--workers must be >= 1"):
        open_engine("local", workers=0)


def test_a_cluster_that_is_no_address_is_refused() -> None:
    with pytest.raises(ValidationError, match="tcp://host:8786"):
        open_engine("locl")


def test_an_address_without_a_scheduler_says_how_to_start_one() -> None:
    pytest.importorskip("distributed", reason=NO_DASK)
    with pytest.raises(ProcessingError, match="dask scheduler"):
        DaskEngine.connect("tcp://127.0.0.1:1", timeout_s=1.0)


@pytest.fixture
def fake_replay() -> Iterator[None]:
    with patch.dict(runner.TASKS, {"instants": fake_tasks.instants, "span": fake_tasks.span}):
        yield


@pytest.mark.usefixtures("fake_replay")
@pytest.mark.slow
def test_a_killed_dask_worker_mid_run_is_retried_and_the_run_completes(tmp_path: Path) -> None:
    pytest.importorskip("distributed", reason=NO_DASK)
    cal = write_calibration(fake_tasks.calibration(), tmp_path / "calib.toml")
    for name, mode in (("a", "die-once"), ("b", "ok")):
        (tmp_path / name).mkdir()
        (tmp_path / name / "session.mcap").write_bytes(b"")
        (tmp_path / name / "mode").write_text(mode)
    sessions = find_sessions([tmp_path / "a", tmp_path / "b"], calib=cal)
    settings = ProcessSettings(methods=("democap",), democap_every=3)
    # Session a's first try SIGKILLs its worker process in the middle of writing its files.
    with DaskEngine.local(2) as engine:
        report = process_sessions(sessions, out=tmp_path / "out", settings=settings, engine=engine)
    a, b = report.jobs
    assert (a.status, b.status) == ("done", "done")
    assert len(a.retried) == 1
    assert a.retried[0].startswith("span 0: KilledWorker")
    assert (
        len(fake_tasks.csv_rows(tmp_path / "out/a/democap/democap.csv")) == fake_tasks.INSTANTS // 3
    )
    assert sorted((tmp_path / "out").glob("*/.*.part-*")) == []
