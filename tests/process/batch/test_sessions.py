"""``process.batch.sessions``: sessions and their side files by convention, local or fsspec."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import fsspec  # type: ignore[import-untyped]
import pytest

from mocaprig.errors import ValidationError
from mocaprig.process.batch.sessions import find_sessions, local_path


def _session(folder: Path, *side: str, recording: str = "session.mcap") -> Path:
    folder.mkdir(parents=True)
    (folder / recording).write_bytes(b"mcap")
    for name in side:
        (folder / name).write_text("x")
    return folder


def test_side_files_are_found_in_the_session_folder(tmp_path: Path) -> None:
    d = _session(tmp_path / "take1", "eventcap_detections.json", "eventcap_shape.json")
    (s,) = find_sessions([d], calib=_session(tmp_path / "c", "calib.toml") / "calib.toml")
    assert s.name == "take1"
    assert s.recording == str(d / "session.mcap")
    assert s.calibration == str(tmp_path / "c/calib.toml")
    assert s.eventcap_calibration == s.calibration
    assert s.detections == str(d / "eventcap_detections.json")
    assert s.shape == str(d / "eventcap_shape.json")
    assert s.subject is None


def test_a_subject_file_in_the_session_folder_is_democap_s(tmp_path: Path) -> None:
    d = _session(tmp_path / "take1", "calib.toml", "democap_subject.json")
    (s,) = find_sessions([d])
    assert s.subject == str(d / "democap_subject.json")


def test_a_session_calibration_beats_calib_and_eventcap_has_its_own(tmp_path: Path) -> None:
    d = _session(tmp_path / "take1", "calib.toml", "eventcap_calib.toml")
    (s,) = find_sessions([d], calib=_session(tmp_path / "c", "calib.toml") / "calib.toml")
    assert s.calibration == str(d / "calib.toml")
    assert s.eventcap_calibration == str(d / "eventcap_calib.toml")
    assert s.detections is None
    assert s.shape is None


def test_demo_folders_and_openpose_folders_are_sessions(tmp_path: Path) -> None:
    demo = tmp_path / "demo-out"
    _session(demo / "session")
    (demo / "eventcap_detections").mkdir()
    (s,) = find_sessions([demo])
    assert s.name == "demo-out"
    assert s.recording == str(demo / "session/session.mcap")
    assert s.detections == str(demo / "eventcap_detections")


def test_a_recording_is_named_by_its_stem(tmp_path: Path) -> None:
    d = _session(tmp_path / "day", recording="kick.mcap")
    (s,) = find_sessions([d / "kick.mcap"])
    assert (s.name, s.folder) == ("kick", str(d))


def test_sessions_with_one_name_are_refused(tmp_path: Path) -> None:
    a = _session(tmp_path / "x/take")
    b = _session(tmp_path / "y/take")
    with pytest.raises(ValidationError, match="same name 'take'"):
        find_sessions([a, b])


def test_a_folder_without_a_recording_is_refused(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValidationError, match=r"no session\.mcap"):
        find_sessions([tmp_path / "empty"])


def test_a_missing_calib_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValidationError, match="--calib"):
        find_sessions([_session(tmp_path / "t")], calib=tmp_path / "nope.toml")


@pytest.fixture
def memory_session() -> Iterator[str]:
    fs = fsspec.filesystem("memory")
    fs.pipe("/lab/take7/session.mcap", b"recording bytes")
    fs.pipe("/lab/take7/eventcap_detections.json", b"{}")
    yield "memory://lab/take7"
    fs.rm("/lab", recursive=True)


def test_urls_are_resolved_without_reading_and_fetched_by_the_reader(memory_session: str) -> None:
    (s,) = find_sessions([memory_session])
    assert s.recording == "memory://lab/take7/session.mcap"
    assert s.detections == "memory://lab/take7/eventcap_detections.json"
    assert s.shape is None
    local = local_path(s.recording)
    assert local.read_bytes() == b"recording bytes"


def test_local_paths_are_read_in_place(tmp_path: Path) -> None:
    assert local_path(f"file://{tmp_path}/a.mcap") == tmp_path / "a.mcap"
    assert local_path(tmp_path / "a.mcap") == tmp_path / "a.mcap"
