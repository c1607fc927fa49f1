"""The reader, info, recover and the recording commands (CLI)."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mocaprig.acquire.events import make_events
from mocaprig.acquire.recorder import Attachment, Recorder, StreamSource
from mocaprig.acquire.recording import Recording, info, recover
from mocaprig.acquire.recording_format import (
    IMU_DTYPE,
    EventPacket,
    ImageMsg,
    ImuPacket,
    topic,
)
from mocaprig.cli import main
from mocaprig.errors import RecordingError


def _write_sample(path: Path) -> dict[str, object]:
    rng = np.random.default_rng(1)
    ev_topic = topic("davis", "00000042", "events")
    t = np.sort(rng.integers(0, 3_000_000, 5000)).astype(np.int64)
    ev = make_events(t, rng.integers(0, 240, t.size), rng.integers(0, 180, t.size), t % 2)
    imu = np.zeros(50, IMU_DTYPE)
    imu["t"] = np.arange(50) * 1000
    frames = [rng.integers(0, 1024, (180, 240)).astype(np.uint16) for _ in range(4)]
    meta = {"rig": {"name": "lab-a"}, "device/davis/00000042": {"firmware": "18"}}
    att = [Attachment("calibration/davis.json", "application/json", b'{"k": 1}')]
    with Recorder(path, metadata=meta, attachments=att, chunk_size_bytes=16_384) as rec:
        he = rec.add_stream(ev_topic, EventPacket, metadata={"serial": "00000042"})
        hi = rec.add_stream(topic("davis", "00000042", "imu"), ImuPacket)
        hf = rec.add_stream(topic("davis", "00000042", "frame"), ImageMsg)
        for i, lo in enumerate(range(0, 5000, 500)):
            ok = rec.put(
                he, EventPacket(ev[lo : lo + 500], seq=i), log_time_ns=(i + 1) * 10**8, sequence=i
            )
            assert ok
        rec.put(hi, ImuPacket(imu[:25], 0), log_time_ns=10**8, sequence=0)
        rec.put(hi, ImuPacket(imu[25:], 2), log_time_ns=2 * 10**8, sequence=2)
        for i, f in enumerate(frames):
            rec.put(hf, ImageMsg(f, "mono16", i * 1000), log_time_ns=(i + 1) * 10**8, sequence=i)
    return {"events": ev, "imu": imu, "frames": frames, "ev_topic": ev_topic}


@pytest.fixture(scope="module")
def sample(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, object]]:
    p = tmp_path_factory.mktemp("rec") / "session.mcap"
    return p, _write_sample(p)


def test_reader_decodes_every_stream(sample: tuple[Path, dict[str, object]]) -> None:
    path, truth = sample
    with Recording(path) as r:
        assert r.indexed
        np.testing.assert_array_equal(r.events(str(truth["ev_topic"])), truth["events"])
        np.testing.assert_array_equal(r.imu("/davis/00000042/imu"), truth["imu"])
        imgs = [m.image for _, m in r.images("/davis/00000042/frame")]
        for a, b in zip(imgs, truth["frames"], strict=True):  # type: ignore[call-overload]
            np.testing.assert_array_equal(a, b)
        assert r.metadata()["rig"] == {"name": "lab-a"}
        assert r.metadata()["mocaprig"]["format_version"] == "1.0"
        (att,) = r.attachments()
        assert (att.name, att.data) == ("calibration/davis.json", b'{"k": 1}')
        assert r.channels[str(truth["ev_topic"])].metadata["serial"] == "00000042"


def test_reader_time_range_is_half_open(sample: tuple[Path, dict[str, object]]) -> None:
    path, truth = sample
    with Recording(path) as r:
        ev = r.events(str(truth["ev_topic"]), start_ns=2 * 10**8, end_ns=4 * 10**8)
    np.testing.assert_array_equal(ev, truth["events"][500:1500])  # type: ignore[index]


def test_reader_rejects_unknown_topic_and_wrong_kind(
    sample: tuple[Path, dict[str, object]],
) -> None:
    path, _ = sample
    with Recording(path) as r:
        with pytest.raises(RecordingError, match="no topic"):
            list(r.messages("/nope"))
        with pytest.raises(RecordingError, match=r"not mocaprig\.EventPacket"):
            r.events("/davis/00000042/imu")


def test_reader_rejects_non_mcap(tmp_path: Path) -> None:
    p = tmp_path / "x.mcap"
    p.write_bytes(b"hello world, not mcap")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        Recording(p)


def test_unfinished_file_reads_the_same_as_finished(
    sample: tuple[Path, dict[str, object]], tmp_path: Path
) -> None:
    path, truth = sample
    from mcap.reader import make_reader

    with path.open("rb") as f:
        summary_start = make_reader(f).get_summary()
    assert summary_start is not None
    data = path.read_bytes()
    # Drop DataEnd + summary + footer: what a crash right after the last chunk leaves.
    import struct

    footer_summary_start = struct.unpack_from("<Q", data, len(data) - 8 - 20)[0]
    cut = tmp_path / "nosummary.mcap"
    cut.write_bytes(data[: footer_summary_start - 13])  # DataEnd record is 13 bytes
    with Recording(cut) as r:
        assert not r.indexed
        assert not r.scan.truncated
        np.testing.assert_array_equal(r.events(str(truth["ev_topic"])), truth["events"])
        assert r.metadata()["rig"] == {"name": "lab-a"}


def test_info_reports_counts_gaps_and_devices(sample: tuple[Path, dict[str, object]]) -> None:
    path, _ = sample
    inf = info(path)
    streams = {s.topic: s for s in inf.streams}
    assert streams["/davis/00000042/events"].messages == 10
    assert streams["/davis/00000042/events"].drops == 0
    assert streams["/davis/00000042/imu"].counter_gaps == 1
    assert streams["/davis/00000042/events"].rate_hz == pytest.approx(10.0)
    assert "device/davis/00000042" in inf.devices
    assert inf.attachments == ("calibration/davis.json",)
    assert inf.scan.complete_chunks > 1
    assert not inf.recovered


def test_cli_info_json(
    sample: tuple[Path, dict[str, object]], capsys: pytest.CaptureFixture[str]
) -> None:
    path, _ = sample
    assert main(["info", str(path), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    s = {x["topic"]: x for x in d["streams"]}
    assert s["/davis/00000042/events"]["messages"] == 10
    assert s["/davis/00000042/events"]["drops"] == 0
    assert d["complete_chunks"] > 1
    assert d["truncated"] is False
    assert "duration_s" in d
    assert "devices" in d
    assert "counter_gaps_total" in d


def test_cli_recover_exit_codes(
    sample: tuple[Path, dict[str, object]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, truth = sample
    assert main(["recover", str(path), str(tmp_path / "ok.mcap")]) == 0
    cut = tmp_path / "cut.mcap"
    data = path.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    assert main(["recover", str(cut), str(tmp_path / "fixed.mcap"), "--json"]) == 3
    capsys.readouterr()
    assert main(["recover", str(cut), str(tmp_path / "fixed.mcap")]) == 1  # never overwrites
    assert "not overwriting" in capsys.readouterr().err
    with Recording(tmp_path / "fixed.mcap") as r:
        assert r.indexed
        assert r.metadata()["mocaprig.recovery"]["truncated"] == "true"
        got = r.events(str(truth["ev_topic"]))
    np.testing.assert_array_equal(got, truth["events"][: got.size])  # type: ignore[index]


def test_recover_keeps_everything_of_a_finished_file(
    sample: tuple[Path, dict[str, object]], tmp_path: Path
) -> None:
    path, _ = sample
    rep = recover(path, tmp_path / "copy.mcap")
    assert rep.lossless
    assert rep.attachments == 1
    a, b = info(path), info(tmp_path / "copy.mcap")
    assert [(s.topic, s.messages) for s in a.streams] == [(s.topic, s.messages) for s in b.streams]


def test_events_ns_of_a_recorded_topic_are_the_us_times_times_1000(
    sample: tuple[Path, dict[str, object]],
) -> None:
    path, truth = sample
    with Recording(path) as r:
        ev, t_ns = r.events_ns(str(truth["ev_topic"]), start_ns=2 * 10**8)
        ev_all = r.events(str(truth["ev_topic"]), start_ns=2 * 10**8)
        none_ev, none_t = r.events_ns(str(truth["ev_topic"]), start_ns=10**15)
    assert ev.size > 0
    np.testing.assert_array_equal(ev, ev_all)
    np.testing.assert_array_equal(t_ns, ev["t"] * 1000)
    assert (none_ev.size, none_t.size, str(none_t.dtype)) == (0, 0, "int64")


def test_export_txt_and_import_round_trip(
    sample: tuple[Path, dict[str, object]], tmp_path: Path
) -> None:
    path, truth = sample
    txt = tmp_path / "ev.txt"
    assert main(["export", str(path), "--topic", str(truth["ev_topic"]), "--format", "txt",
                 "--out", str(txt)]) == 0  # fmt: skip
    lines = txt.read_text().splitlines()
    ev0 = truth["events"][0]  # type: ignore[index]
    # No header line (the RPG events.txt has none); µs times written with 9 decimals.
    assert len(lines) == truth["events"].size  # type: ignore[attr-defined]
    t0 = int(ev0["t"])
    assert lines[0] == f"{t0 // 10**6}.{t0 % 10**6:06d}000 {ev0['x']} {ev0['y']} {ev0['p']}"
    back = tmp_path / "back.mcap"
    assert main(["import-events", str(txt), "--out", str(back)]) == 0
    with Recording(back) as r:
        np.testing.assert_array_equal(r.events("/davis/imported/events"), truth["events"])
    txt2 = tmp_path / "ev2.txt"
    assert main(["export", str(back), "--topic", "/davis/imported/events", "--format", "txt",
                 "--out", str(txt2)]) == 0  # fmt: skip
    assert txt2.read_text() == txt.read_text()


def test_import_reads_rpg_text_with_ns_digits(tmp_path: Path) -> None:
    txt = tmp_path / "e.txt"
    txt.write_text("0.003811000 96 133 0\n0.003820001 5 6 1\n1468940293.982000 1 2 1\n")
    out = tmp_path / "e.mcap"
    assert main(["import-events", str(txt), "--out", str(out), "--width", "346",
                 "--height", "260"]) == 0  # fmt: skip
    with Recording(out) as r:
        ev = r.events("/davis/imported/events")
        ev_ns, t_ns = r.events_ns("/davis/imported/events")
        (p0, *_) = [m.decode() for m in r.messages("/davis/imported/events")]
    assert ev["t"].tolist() == [3811, 3820, 1468940293982000]
    assert t_ns.tolist() == [3_811_000, 3_820_001, 1_468_940_293_982_000_000]
    np.testing.assert_array_equal(ev_ns, ev)
    assert (p0.width, p0.height) == (346, 260)


def test_import_rejects_malformed_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    txt = tmp_path / "e.txt"
    txt.write_text("0.1 1 2 1\n0.2 1 2\n")
    assert main(["import-events", str(txt), "--out", str(tmp_path / "e.mcap")]) == 1
    assert "e.txt:2" in capsys.readouterr().err


def test_export_npz_png_mp4(sample: tuple[Path, dict[str, object]], tmp_path: Path) -> None:
    path, truth = sample
    npz = tmp_path / "imu.npz"
    assert main(["export", str(path), "--topic", "/davis/00000042/imu", "--format", "npz",
                 "--out", str(npz)]) == 0  # fmt: skip
    with np.load(npz) as z:
        np.testing.assert_array_equal(z["t"], truth["imu"]["t"])  # type: ignore[index]
    fr = "/davis/00000042/frame"
    assert main(["export", str(path), "--topic", fr, "--format", "png",
                 "--out", str(tmp_path / "png")]) == 0  # fmt: skip
    import cv2

    pngs = sorted((tmp_path / "png").glob("*.png"))
    assert len(pngs) == 4
    img = cv2.imread(str(pngs[0]), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(img, truth["frames"][0])  # type: ignore[index]
    mp4 = tmp_path / "f.mp4"
    assert main(["export", str(path), "--topic", fr, "--format", "mp4", "--out", str(mp4)]) == 0
    assert mp4.stat().st_size > 0


def test_export_refuses_wrong_kind(
    sample: tuple[Path, dict[str, object]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, _ = sample
    assert main(["export", str(path), "--topic", "/davis/00000042/imu", "--format", "txt",
                 "--out", str(tmp_path / "x.txt")]) == 1  # fmt: skip
    assert "event topics" in capsys.readouterr().err


@pytest.mark.parametrize("cmd", ["record", "info", "recover", "export", "import-events"])
def test_commands_have_help_with_examples(cmd: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main([cmd, "--help"])
    assert exc.value.code == 0
    assert "examples:" in capsys.readouterr().out


class _TinySource:
    name = "tiny"

    def __init__(self) -> None:
        self.metadata = {"device/tiny": {"serial": "1"}}

    def declare(self, recorder: Recorder) -> None:
        self.h = recorder.add_stream(topic("davis", "tiny", "events"), EventPacket)

    def run(self, recorder: Recorder, stop: threading.Event) -> None:
        i = 0
        while not stop.wait(0.01):
            t = np.arange(10) + i * 10
            recorder.put(self.h, EventPacket(make_events(t, t, t, t % 2), seq=i), sequence=i)
            i += 1


def test_record_command_over_a_source(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from mocaprig.acquire.commands_record import record

    out = tmp_path / "r.mcap"
    sources: list[StreamSource] = [_TinySource()]
    code = record(out=out, seconds=0.5, mock=False, rig=None, sources=sources, as_json=True)
    assert code == 0
    d = json.loads(capsys.readouterr().out)
    assert d["files"] == [str(out)]
    inf = info(out)
    assert {s.topic: s.messages for s in inf.streams}["/davis/tiny/events"] > 10
    assert "device/tiny" in inf.devices


def test_record_requires_a_source(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["record", "--seconds", "1", "--out", str(tmp_path / "a.mcap")])
    assert exc.value.code == 2
    assert "--rig --mock is required" in capsys.readouterr().err


def test_record_rig_without_format_version_is_refused_clearly(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = tmp_path / "rig.toml"
    rig.write_text("[davis]\n")
    assert (
        main(["record", "--rig", str(rig), "--seconds", "1", "--out", str(tmp_path / "a.mcap")])
        == 1
    )
    assert "'format_version' is missing" in capsys.readouterr().err


def test_reader_refuses_a_newer_major_format(tmp_path: Path) -> None:
    from mcap.writer import Writer

    p = tmp_path / "future.mcap"
    with p.open("wb") as f:
        w = Writer(f)
        w.start()
        w.add_metadata("mocaprig", {"format_version": "2.0"})
        w.finish()  # type: ignore[no-untyped-call]
    with pytest.raises(RecordingError, match="upgrade mocaprig"):
        Recording(p)


@settings(max_examples=25, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.integers(-(10**16), 10**16),  # ns, both signs, up to ~116 days
            st.integers(0, 239),
            st.integers(0, 179),
            st.booleans(),
        ),
        min_size=1,
        max_size=50,
    ),
    st.booleans(),
)
def test_rpg_text_round_trips_exactly_to_the_ns(
    rows: list[tuple[int, int, int, bool]], header: bool
) -> None:
    import io
    import tempfile

    from mocaprig.acquire.rpg_text import (
        _read_events_txt_lines,
        export_events_txt,
        read_events_txt,
    )

    arr = np.asarray(rows, dtype=np.int64).reshape(-1, 4)
    t_ns = np.sort(arr[:, 0])
    ev = make_events(t_ns // 1000, arr[:, 1], arr[:, 2], arr[:, 3])
    buf = io.StringIO()
    export_events_txt(ev, buf, t_ns=t_ns, header=(240, 180) if header else None)
    assert buf.getvalue().count("\n") == ev.size + header
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "e.txt"
        p.write_text(buf.getvalue())
        back = read_events_txt(p)
        slow = _read_events_txt_lines(p)  # the line-by-line reader agrees with the fast path
    assert (back.width, back.height) == ((240, 180) if header else (None, None))
    np.testing.assert_array_equal(back.t_ns, t_ns)
    np.testing.assert_array_equal(back.events, ev)
    np.testing.assert_array_equal(slow.t_ns, t_ns)
    np.testing.assert_array_equal(slow.events, ev)


@pytest.mark.parametrize(
    ("text", "t_ns"),
    [
        ("0.000011001", 11001),
        ("12", 12_000_000_000),
        ("12.", 12_000_000_000),
        (".5", 500_000_000),
        ("0.003811", 3_811_000),
        ("0.0000110010000", 11001),  # zeros beyond the 9th decimal are exact
        ("1.5e-3", 1_500_000),
        ("-0.000000001", -1),
        ("1468940293.982000", 1_468_940_293_982_000_000),
    ],
)
def test_rpg_text_times_parse_exactly(tmp_path: Path, text: str, t_ns: int) -> None:
    from mocaprig.acquire.rpg_text import read_events_txt

    p = tmp_path / "e.txt"
    p.write_text(f"{text} 1 2 1\n")
    got = read_events_txt(p)
    assert got.t_ns.tolist() == [t_ns]
    assert got.events["t"].tolist() == [t_ns // 1000]  # floor, also below zero


@pytest.mark.parametrize("text", ["0.0000000011", "1e-10", "0x10", "1_0", "nan"])
def test_rpg_text_refuses_times_finer_than_ns_or_not_decimal(tmp_path: Path, text: str) -> None:
    from mocaprig.acquire.rpg_text import read_events_txt

    p = tmp_path / "e.txt"
    p.write_text(f"0.1 1 2 1\n{text} 1 2 1\n")
    with pytest.raises(RecordingError, match=r"e\.txt:2: .*t in s with at most 9 decimals"):
        read_events_txt(p)


def test_put_from_many_threads_counts_every_message(tmp_path: Path) -> None:
    p = tmp_path / "mt.mcap"
    n_threads, n_each = 4, 200
    with Recorder(p) as rec:
        hs = [rec.add_stream(f"/davis/t{i}/events", EventPacket) for i in range(n_threads)]

        def produce(i: int) -> None:
            for k in range(n_each):
                t = np.arange(5) + k * 5
                rec.put(hs[i], EventPacket(make_events(t, t, t, t % 2), seq=k), sequence=k)

        threads = [threading.Thread(target=produce, args=(i,)) for i in range(n_threads)]
        for th in threads:
            th.start()
        for th in threads:
            th.join()
    inf = info(p)
    for s in inf.streams:
        if s.topic.startswith("/davis/"):
            assert s.drops == 0  # 200 messages fit the default 4096-message queue
            assert s.messages == n_each
            assert s.counter_gaps == 0


@pytest.mark.parametrize(
    ("text", "fast"),
    [
        ("240 180\r\n0.003811 1 2 1\r\n0.000011001 3 4 0\r\n7 5 6 1\r\n", True),
        ("# c\n\n0.003811 1 2 1\n0.000011001 3 4 0\n7 5 6 1\n", True),
        ("240 180\n0.003811\t1 2 1\n0.000011001  3 4 0\n+7 5 6 1 \n", False),
        ("240 180\n0.003811 1 2 1\n1.1e-5 3 4 0\n7 5 6 1\n", False),
    ],
)
def test_fast_and_line_readers_agree_on_layout_variants(
    tmp_path: Path, text: str, fast: bool
) -> None:
    from mocaprig.acquire.rpg_text import (
        _read_events_txt_fast,
        _read_events_txt_lines,
        read_events_txt,
    )

    p = tmp_path / "e.txt"
    p.write_bytes(text.encode())
    got = read_events_txt(p)
    ref = _read_events_txt_lines(p)
    expected_ns = [3_811_000, 11_000 if "1.1e-5" in text else 11_001, 7_000_000_000]
    assert got.t_ns.tolist() == ref.t_ns.tolist() == expected_ns
    np.testing.assert_array_equal(got.events, ref.events)
    assert (got.width, got.height) == (ref.width, ref.height)
    assert (_read_events_txt_fast(p.read_bytes()) is not None) == fast
