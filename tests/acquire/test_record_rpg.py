"""Real DAVIS240C events in the RPG text format (an excerpt of the RPG Event-Camera Dataset,
tests/acquire/data/) through `mocaprig import-events` -> `mocaprig export --format txt`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mocaprig.acquire.recording import Recording
from mocaprig.acquire.rpg_text import read_events_txt
from mocaprig.cli import main

_DATA = Path(__file__).parent / "data" / "rpg_shapes_rotation_events_head.txt"
_TOPIC = "/davis/imported/events"


def _event_lines(path: Path) -> bytes:
    """The file's event lines (comments excluded), as bytes with their newlines."""
    lines = path.read_bytes().splitlines(keepends=True)
    return b"".join(ln for ln in lines if ln.strip() and not ln.startswith(b"#"))


def _export(rec: Path, out: Path, *extra: str) -> None:
    args = ["export", str(rec), "--topic", _TOPIC, "--format", "txt", "--out", str(out), *extra]
    assert main(args) == 0


def test_real_rpg_events_round_trip_unchanged_through_import_and_export(tmp_path: Path) -> None:
    src = _event_lines(_DATA)
    assert src.count(b"\n") == 9
    # 5 of the 9 times have sub-µs digits (ROS-time conversion residue): they must survive.
    assert sum(not ln.split()[0].endswith(b"000") for ln in src.splitlines()) == 5
    rec = tmp_path / "e.mcap"
    assert main(["import-events", str(_DATA), "--out", str(rec), "--width", "240",
                 "--height", "180"]) == 0  # fmt: skip
    txt = tmp_path / "e.txt"
    _export(rec, txt)
    # The exported text is the source's event lines, byte for byte (no header line by default).
    assert txt.read_bytes() == src
    # A second round trip is a fixed point.
    rec2 = tmp_path / "e2.mcap"
    assert main(["import-events", str(txt), "--out", str(rec2)]) == 0
    txt2 = tmp_path / "e2.txt"
    _export(rec2, txt2)
    assert txt2.read_bytes() == src
    # The canonical events hold µs = floor(ns / 1000); the ns are kept beside them.
    parsed = read_events_txt(_DATA)
    assert parsed.t_ns.tolist() == [0, 11001, 50000, 55000, 80001, 123000, 130001, 139001, 148001]
    with Recording(rec) as r:
        ev = r.events(_TOPIC)
        ev_ns, t_ns = r.events_ns(_TOPIC)
    np.testing.assert_array_equal(t_ns, parsed.t_ns)
    np.testing.assert_array_equal(ev["t"], t_ns // 1000)
    assert ev["t"].tolist() == [0, 11, 50, 55, 80, 123, 130, 139, 148]
    np.testing.assert_array_equal(ev, parsed.events)
    np.testing.assert_array_equal(ev_ns, ev)


def test_txt_header_option_writes_width_height_first_and_imports_back(tmp_path: Path) -> None:
    rec = tmp_path / "e.mcap"
    assert main(["import-events", str(_DATA), "--out", str(rec), "--width", "346",
                 "--height", "260"]) == 0  # fmt: skip
    txt = tmp_path / "e2vid.txt"
    _export(rec, txt, "--txt-header")
    assert txt.read_bytes() == b"346 260\n" + _event_lines(_DATA)
    rec2 = tmp_path / "e2.mcap"
    assert main(["import-events", str(txt), "--out", str(rec2)]) == 0  # size from the header
    with Recording(rec2) as r:
        (p0, *_) = [m.decode() for m in r.messages(_TOPIC)]
        _, t_ns = r.events_ns(_TOPIC)
    assert (p0.width, p0.height) == (346, 260)
    np.testing.assert_array_equal(t_ns, read_events_txt(_DATA).t_ns)
