"""`mocaprig import-events` puts every message of the file on the file's clock, shifted by a
stated epoch (issue 17, item 3)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from mcap.reader import make_reader

from mocaprig.acquire.recording import info
from mocaprig.acquire.rpg_text import import_events_txt, read_events_txt
from mocaprig.cli import main
from mocaprig.errors import RecordingError, ValidationError

_ECD = "events/ecd_shapes_rotation_0to500ms/events.txt"


def _times_by_topic(path: Path) -> dict[str, list[int]]:
    out: dict[str, list[int]] = {}
    with path.open("rb") as fh:
        for _, channel, msg in make_reader(fh).iter_messages(log_time_order=False):
            out.setdefault(channel.topic, []).extend([msg.log_time, msg.publish_time])
    return out


@pytest.mark.parametrize("epoch_ns", [0, 1_589_163_147_355_806_000])
def test_an_imported_real_file_has_one_clock_and_the_duration_of_its_events(
    shared_data: Path, tmp_path: Path, epoch_ns: int
) -> None:
    src = shared_data / _ECD
    t_ns = read_events_txt(src).t_ns
    out = tmp_path / "imported.mcap"
    import_events_txt(src, out, width=None, height=None, epoch_ns=epoch_ns)
    lo, hi = epoch_ns + int(t_ns.min()), epoch_ns + int(t_ns.max())
    for topic, times in _times_by_topic(out).items():
        assert min(times) >= lo, topic  # /diagnostics included
        assert max(times) <= hi, topic
    inf = info(out)
    assert not inf.mixed_time_bases
    assert [b.name for b in inf.time_bases] == ["relative" if epoch_ns == 0 else "unix"]
    # Packets are stamped with their first event: the duration lies within the events' span
    # (0.49997 s) and loses at most one 10 ms packet.
    span_s = (hi - lo) / 1e9
    assert span_s - 0.010 <= inf.duration_s <= span_s
    assert inf.metadata["import"]["epoch_ns"] == str(epoch_ns)


def test_import_then_info_reports_the_events_duration_from_the_cli(
    shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "imported.mcap"
    assert main(["import-events", str(shared_data / _ECD), "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["info", str(out), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert 0.48 <= d["duration_s"] <= 0.5  # was 1.8e9 s when /diagnostics was on wall time
    assert d["mixed_time_bases"] is False


def test_an_epoch_that_overflows_the_clock_is_refused(tmp_path: Path) -> None:
    txt = tmp_path / "e.txt"
    txt.write_text("0.5 1 2 1\n1.0 3 4 0\n")
    with pytest.raises(RecordingError, match=r"e\.txt: .*overflows .*--epoch-ns"):
        import_events_txt(
            txt, tmp_path / "a.mcap", width=None, height=None, epoch_ns=(1 << 63) - 10
        )
    with pytest.raises(ValidationError, match="epoch_ns"):
        import_events_txt(txt, tmp_path / "b.mcap", width=None, height=None, epoch_ns=-1)
