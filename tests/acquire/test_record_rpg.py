"""Real DAVIS240C events in the RPG text format (an excerpt of the RPG Event-Camera Dataset,
tests/acquire/data/) through `mocaprig import-events` -> `mocaprig export --format txt`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from acquire.cli import main
from acquire.commands_record import read_events_txt
from acquire.recording import Recording

_DATA = Path(__file__).parent / "data" / "rpg_shapes_rotation_events_head.txt"
_TOPIC = "/davis/imported/events"


def _rows(path: Path) -> list[list[str]]:
    lines = path.read_text().splitlines()
    return [ln.split() for ln in lines if ln and not ln.startswith("#") and len(ln.split()) == 4]


def test_real_rpg_events_round_trip_through_import_and_export(tmp_path: Path) -> None:
    src = _rows(_DATA)
    assert len(src) == 9
    rec = tmp_path / "e.mcap"
    assert main(["import-events", str(_DATA), "--out", str(rec), "--width", "240",
                 "--height", "180"]) == 0  # fmt: skip
    txt = tmp_path / "e.txt"
    assert main(["export", str(rec), "--topic", _TOPIC, "--format", "txt", "--out", str(txt)]) == 0
    assert txt.read_text().splitlines()[0] == "240 180"
    out = _rows(txt)
    # Every event comes back, in order, with x, y and polarity unchanged ...
    assert [r[1:] for r in out] == [r[1:] for r in src]
    # ... and its time to the µs (the DAVIS clock's resolution): the canonical event dtype
    # holds µs, so the sub-µs digits of the RPG text (ROS-time conversion residue, here 1 ns
    # on 5 of 9 lines) are rounded away: the text is unchanged up to those digits.
    for a, b in zip(src, out, strict=True):
        assert b[0] == f"{round(float(a[0]) * 1e6) / 1e6:.6f}"
        assert abs(float(a[0]) - float(b[0])) < 0.5e-6
    assert sum(a[0][-3:] != "000" for a in src) == 5
    # The exported text is a fixed point: import -> export again gives the same bytes.
    rec2 = tmp_path / "e2.mcap"
    assert main(["import-events", str(txt), "--out", str(rec2)]) == 0
    txt2 = tmp_path / "e2.txt"
    assert (
        main(["export", str(rec2), "--topic", _TOPIC, "--format", "txt", "--out", str(txt2)]) == 0
    )
    assert txt2.read_bytes() == txt.read_bytes()
    with Recording(rec) as r:
        ev = r.events(_TOPIC)
    parsed, _, _ = read_events_txt(_DATA)
    np.testing.assert_array_equal(ev, parsed)
    assert ev["t"].tolist() == [0, 11, 50, 55, 80, 123, 130, 139, 148]
