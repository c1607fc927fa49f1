"""C3D files of every processor type and storage format read the same (issue 17, item 1).

The six variants (Intel / DEC / SGI-MIPS × float / integer storage) are made without our reader's
code: py-c3d's ``c3d.Writer`` writes the Intel originals (it writes Intel only, float or integer
storage), and :func:`_convert` below, a byte-level converter written from the c3d.org layout,
rewrites an Intel file for another processor type and storage format (VAX F-floats for DEC,
big-endian words for SGI, 16-bit integers × POINT:SCALE and requantised analogs for integer
storage). Each variant is also read by a second reader (py-c3d) as a check on the converter.
"""

from __future__ import annotations

import functools
import json
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt
import pytest

from mocaprig.calib.vicon import (
    AnalogChannels,
    MarkerTrajectories,
    ViconFileError,
    read_c3d,
    read_c3d_analogs,
    validate_c3d,
    write_c3d,
)

Proc = Literal["intel", "dec", "sgi"]
Storage = Literal["float", "int"]
FloatArray = npt.NDArray[np.float64]

_PROC_BYTE = {"intel": 84, "dec": 85, "sgi": 86}
_PROCS: tuple[Proc, ...] = ("intel", "dec", "sgi")
_STORAGES: tuple[Storage, ...] = ("float", "int")
_VARIANTS = [(p, s) for p in _PROCS for s in _STORAGES]
_NEXUS = "vicon/nexus24_markers_analogs.c3d"


# --------------------------------------------------------------------------------------------
# the converter: an Intel C3D (float or integer) to any processor type and storage format
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Rec:
    """One record of the parameter section (group when ``gid`` < 0)."""

    n_chars: int  # signed: < 0 marks a locked record
    gid: int
    name: str
    type_code: int
    dims: tuple[int, ...]
    data: bytes  # Intel byte order
    desc: bytes


def _parse_records(buf: bytes) -> list[_Rec]:
    start = (buf[0] - 1) * 512
    assert buf[start + 3] == 84, "the converter reads Intel files only"
    end = start + buf[start + 2] * 512
    pos, out = start + 4, []
    while pos + 2 <= end:
        n_chars, gid = struct.unpack_from("bb", buf, pos)
        if n_chars == 0 or gid == 0:
            break
        name_end = pos + 2 + abs(n_chars)
        name = buf[pos + 2 : name_end].decode("ascii")
        (offset,) = struct.unpack_from("<H", buf, name_end)
        body = name_end + 2
        dims: tuple[int, ...] = ()
        if gid < 0:
            type_code, data, d = 0, b"", body
        else:
            type_code, n_dims = struct.unpack_from("bB", buf, body)
            dims = tuple(buf[body + 2 : body + 2 + n_dims])
            count = int(np.prod(dims)) if dims else 1
            d = body + 2 + n_dims + count * abs(type_code)
            data = buf[body + 2 + n_dims : d]
        desc = buf[d + 1 : d + 1 + buf[d]]
        out.append(_Rec(n_chars, gid, name, type_code, dims, data, desc))
        if offset == 0:
            break
        pos = name_end + offset
    return out


def _floats_to(values: npt.ArrayLike, proc: Proc) -> bytes:
    """IEEE values as 32-bit floats of ``proc`` (DEC: VAX F = IEEE x 4, 16-bit halves swapped)."""
    v = np.asarray(values, dtype=np.float32).ravel()
    if proc == "sgi":
        return v.astype(">f4").tobytes()
    if proc == "dec":
        b = (v * np.float32(4.0)).astype("<f4").view(np.uint8).reshape(-1, 4)
        return b[:, [2, 3, 0, 1]].tobytes()
    return v.astype("<f4").tobytes()


def _ints_to(values: npt.ArrayLike, proc: Proc, *, unsigned: bool = False) -> bytes:
    kind = "u2" if unsigned else "i2"
    return np.asarray(values).astype((">" if proc == "sgi" else "<") + kind).tobytes()


def _record_bytes(r: _Rec, proc: Proc) -> bytes:
    if r.gid < 0:
        rest = bytes([len(r.desc)]) + r.desc
    else:
        if r.type_code == 2:
            data = _ints_to(np.frombuffer(r.data, "<i2"), proc)
        elif r.type_code == 4:
            data = _floats_to(np.frombuffer(r.data, "<f4"), proc)
        else:
            data = r.data
        rest = (
            struct.pack("bB", r.type_code, len(r.dims))
            + bytes(r.dims)
            + data
            + bytes([len(r.desc)])
            + r.desc
        )
    e = ">" if proc == "sgi" else "<"
    return (
        struct.pack("bb", r.n_chars, r.gid)
        + r.name.encode()
        + struct.pack(e + "H", 2 + len(rest))
        + rest
    )


def _set(
    recs: list[_Rec], group: str, name: str, type_code: int, dims: tuple[int, ...], data: bytes
) -> list[_Rec]:
    """``recs`` with GROUP:NAME replaced (or added) holding ``data`` (Intel order)."""
    gid = next(-r.gid for r in recs if r.gid < 0 and r.name == group)
    new = _Rec(len(name), gid, name, type_code, dims, data, b"")
    out = [new if (r.gid == gid and r.name == name) else r for r in recs]
    return out if new in out else [*out, new]


def _param(recs: list[_Rec], group: str, name: str) -> _Rec:
    gid = next(-r.gid for r in recs if r.gid < 0 and r.name == group)
    return next(r for r in recs if r.gid == gid and r.name == name)


def _convert(
    buf: bytes,
    proc: Proc,
    storage: Storage,
    *,
    point_scale: float | None = None,
    analog_offset: int = 0,
    unsigned: bool = False,
) -> bytes:
    """Rewrite the Intel C3D ``buf`` for ``proc`` with ``storage``.

    Float → integer storage quantises the points to ``point_scale`` (file units; default: the
    coordinates' range over 30,000) and the analogs to new ANALOG:SCALE values (their range over
    30,000 counts) around ``analog_offset`` counts, stored as unsigned words (ANALOG:FORMAT
    ``UNSIGNED``) when ``unsigned``. Integer → integer keeps the stored words.
    """
    hdr = buf[:512]
    n_points, n_analog, first, last, gap = struct.unpack_from("<5H", hdr, 2)
    (h_scale,) = struct.unpack_from("<f", hdr, 12)
    spf = struct.unpack_from("<H", hdr, 18)[0]
    (rate,) = struct.unpack_from("<f", hdr, 20)
    recs = _parse_records(buf)
    (data_start,) = np.frombuffer(_param(recs, "POINT", "DATA_START").data, "<u2")
    src_float = h_scale < 0
    word = 4 if src_float else 2
    frame_words = 4 * n_points + n_analog
    n_frames = (len(buf) - (int(data_start) - 1) * 512) // (frame_words * word)
    n_frames = min(n_frames, last - first + 1)
    raw = buf[(int(data_start) - 1) * 512 :][: n_frames * frame_words * word]
    words = np.frombuffer(raw, "<f4" if src_float else "<i2").reshape(n_frames, frame_words)
    pts = words[:, : 4 * n_points].reshape(n_frames, n_points, 4).astype(np.float64)
    ana = words[:, 4 * n_points :].astype(np.float64)
    scale = float(np.frombuffer(_param(recs, "POINT", "SCALE").data, "<f4")[0])
    if storage == "float":
        assert src_float, "integer → float is not needed by these tests"
        gap_rows = pts[..., 3] < 0
        pts[gap_rows, :3] = 0.0  # VAX floats have no NaN; a gap is its negative fourth word
        body = _floats_to(np.concatenate([pts.reshape(n_frames, -1), ana], axis=1), proc)
    elif not src_float:
        body = _ints_to(np.concatenate([pts.reshape(n_frames, -1), ana], axis=1), proc)
    else:
        valid = pts[..., 3] >= 0
        if point_scale is None:
            point_scale = max(float(np.abs(pts[..., :3][valid]).max(initial=1.0)) / 30_000, 1e-4)
        q = np.where(valid[..., None], np.rint(pts[..., :3] / point_scale), 0.0)
        q = np.concatenate([q, np.where(valid, pts[..., 3], -1.0)[..., None]], axis=2)
        n_ch = n_analog // spf if spf else 0
        a_scale = np.frombuffer(_param(recs, "ANALOG", "SCALE").data, "<f4")[:n_ch].astype(float)
        a_off = np.frombuffer(_param(recs, "ANALOG", "OFFSET").data, "<i2")[:n_ch].astype(float)
        gen = float(np.frombuffer(_param(recs, "ANALOG", "GEN_SCALE").data, "<f4")[0])
        samples = ana.reshape(n_frames * spf, n_ch) if n_ch else np.zeros((0, 0))
        phys = (samples - a_off) * a_scale * gen
        span = np.abs(phys).max(axis=0, initial=0.0)
        new_scale = np.where(span > 0, span / 30_000, 1.0) / gen  # silent channels: scale 1
        new_scale = new_scale.astype(np.float32).astype(np.float64)  # as the file stores it
        counts = np.rint(phys / (new_scale * gen)) + analog_offset
        e = ">" if proc == "sgi" else "<"
        point_words = q.reshape(n_frames, -1).astype(e + "i2")
        analog_words = counts.reshape(n_frames, -1).astype(e + ("u2" if unsigned else "i2"))
        body = b"".join(
            point_words[f].tobytes() + analog_words[f].tobytes() for f in range(n_frames)
        )
        scale = point_scale
        if n_ch:
            recs = _set(recs, "ANALOG", "SCALE", 4, (n_ch,), new_scale.astype("<f4").tobytes())
            off_bits = np.full(n_ch, analog_offset).astype("<u2" if unsigned else "<i2")
            recs = _set(recs, "ANALOG", "OFFSET", 2, (n_ch,), off_bits.tobytes())
            fmt = b"UNSIGNED" if unsigned else b"SIGNED  "
            recs = _set(recs, "ANALOG", "FORMAT", -1, (len(fmt),), fmt)
    new_scale_value = -abs(scale) if storage == "float" else abs(scale)
    recs = _set(recs, "POINT", "SCALE", 4, (), struct.pack("<f", new_scale_value))
    # The parameter section is re-laid out, so DATA_START follows its new length.
    for _ in range(2):
        section = b"".join(_record_bytes(r, proc) for r in recs) + b"\x00\x00"
        n_blocks = -(-(4 + len(section)) // 512)
        data_block = 2 + n_blocks
        recs = _set(recs, "POINT", "DATA_START", 2, (), struct.pack("<H", data_block))
    section = b"".join(_record_bytes(r, proc) for r in recs) + b"\x00\x00"
    params = (bytes([1, 0x50, n_blocks, _PROC_BYTE[proc]]) + section).ljust(n_blocks * 512, b"\0")
    e = ">" if proc == "sgi" else "<"
    new_hdr = bytearray(hdr)
    new_hdr[0] = 2
    new_hdr[2:12] = struct.pack(e + "5H", n_points, n_analog, first, last, gap)
    new_hdr[12:16] = _floats_to([new_scale_value], proc)
    new_hdr[16:20] = struct.pack(e + "2H", data_block, spf)
    new_hdr[20:24] = _floats_to([rate], proc)
    for off in (294, 296, 298, 300, 302):  # label/range and event keys and counts
        new_hdr[off : off + 2] = struct.pack(e + "H", struct.unpack_from("<H", hdr, off)[0])
    new_hdr[304:376] = _floats_to(np.frombuffer(hdr[304:376], "<f4"), proc)  # event times
    out = bytes(new_hdr) + params + body
    return out.ljust(-(-len(out) // 512) * 512, b"\x00")


# --------------------------------------------------------------------------------------------
# Intel originals from py-c3d's writer, with known truth
# --------------------------------------------------------------------------------------------

_LABELS = ("S:LASI", "S:RASI", "S:LKNE", "S:RKNE")
_ANALOG_LABELS = ("Fz", "EMG1", "Sync")
_SPF = 4  # analog samples per point frame
_FIRST_FRAME = 4001


@dataclass(frozen=True, slots=True)
class _Truth:
    xyz_mm: FloatArray  # (F, N, 3), NaN gaps
    residual_mm: FloatArray  # (F, N), NaN gaps
    analogs: FloatArray  # (S, C) physical
    analog_scale: FloatArray  # ANALOG:SCALE x GEN_SCALE: the quantum of integer analogs


def _truth(seed: int = 3) -> _Truth:
    rng = np.random.default_rng(seed)
    f, n = 9, len(_LABELS)
    xyz = rng.uniform(-1500.0, 1500.0, (f, n, 3))
    res = (
        rng.integers(0, 30, (f, n)).astype(np.float64) * 0.1
    )  # a multiple of the 0.1 mm residual quantum
    xyz[2, 1] = xyz[5:7, 3] = np.nan
    res[np.isnan(xyz[..., 0])] = np.nan
    scale = np.array([0.5, 0.002, 0.01]) * 2.0  # x GEN_SCALE 2
    counts = rng.integers(-3000, 3000, (f * _SPF, len(_ANALOG_LABELS)))
    return _Truth(xyz, res, (counts * scale).astype(np.float64), scale)


def _pyc3d_intel(path: Path, truth: _Truth, storage: Storage) -> Path:
    """An Intel C3D of ``truth`` written by py-c3d (not our writer)."""
    import c3d

    w = c3d.Writer(
        point_rate=100.0,
        analog_rate=100.0 * _SPF,
        point_scale=-0.1 if storage == "float" else 0.1,
        point_units="mm  ",
        gen_scale=2.0,
    )
    w.set_point_labels(list(_LABELS))
    w.set_analog_labels(list(_ANALOG_LABELS))
    w.set_analog_scales(truth.analog_scale / 2.0)
    w.set_analog_offsets([0, 0, 0])
    w.set_start_frame(_FIRST_FRAME)
    n_ch = len(_ANALOG_LABELS)
    for i in range(truth.xyz_mm.shape[0]):
        pts = np.zeros((len(_LABELS), 5))
        gap = np.isnan(truth.xyz_mm[i, :, 0])
        pts[:, :3] = np.where(gap[:, None], 0.0, truth.xyz_mm[i])
        pts[:, 3] = np.where(gap, -1.0, truth.residual_mm[i])
        pts[:, 4] = np.where(gap, 0, 0b0101)  # camera mask: cameras 1 and 3
        block = truth.analogs[i * _SPF : (i + 1) * _SPF].T.reshape(n_ch, _SPF)
        w.add_frames([(pts, block)])
    with path.open("wb") as fh:
        w.write(fh)
    return path


def _variant(tmp_path: Path, src: Path, proc: Proc, storage: Storage, **kw: float) -> Path:
    out = tmp_path / f"{src.stem}_{proc}_{storage}.c3d"
    out.write_bytes(_convert(src.read_bytes(), proc, storage, **kw))  # type: ignore[arg-type]
    return out


def _pyc3d_read(path: Path) -> tuple[FloatArray, FloatArray]:
    """Points (F, N, 5) and analogs (S, C) as py-c3d, the second reader, reads them."""
    import c3d

    pts, ana = [], []
    with path.open("rb") as fh:
        r = c3d.Reader(fh)
        for _, p, a in r.read_frames(copy=True, check_nan=False):
            pts.append(np.asarray(p, dtype=np.float64))
            ana.append(np.asarray(a, dtype=np.float64).T)
    return np.stack(pts), np.concatenate(ana)


@pytest.fixture(scope="module")
def originals(tmp_path_factory: pytest.TempPathFactory) -> dict[Storage, Path]:
    folder = tmp_path_factory.mktemp("pyc3d")
    truth = _truth()
    return {s: _pyc3d_intel(folder / f"pyc3d_{s}.c3d", truth, s) for s in ("float", "int")}


@pytest.mark.parametrize(("proc", "storage"), _VARIANTS)
def test_converted_variants_read_the_same_as_their_intel_original_by_py_c3d(
    tmp_path: Path, originals: dict[Storage, Path], proc: Proc, storage: Storage
) -> None:
    # The converter is checked by a reader that is not ours.
    path = _variant(tmp_path, originals[storage], proc, storage)
    pts, ana = _pyc3d_read(path)
    ref_pts, ref_ana = _pyc3d_read(originals[storage])
    gap = ref_pts[..., 3] < 0
    np.testing.assert_array_equal(pts[..., 3] < 0, gap)
    # py-c3d's writer leaves stale coordinates in gaps; only the gap flag counts there.
    np.testing.assert_array_equal(pts[~gap], ref_pts[~gap])
    np.testing.assert_allclose(ana, ref_ana, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize(("proc", "storage"), _VARIANTS)
def test_every_processor_and_storage_reads_points_residuals_analogs_and_metadata(
    tmp_path: Path, originals: dict[Storage, Path], proc: Proc, storage: Storage
) -> None:
    truth = _truth()
    path = _variant(tmp_path, originals[storage], proc, storage)
    traj = read_c3d(path, isolate=False)
    assert traj.metadata["processor"] == proc
    assert traj.metadata["storage"] == storage
    assert float(traj.metadata["point_scale"]) == pytest.approx(0.1, rel=1e-6)
    assert traj.labels == _LABELS
    assert traj.source_unit == "mm"
    assert traj.rate_hz == 100.0
    assert traj.first_frame == _FIRST_FRAME
    # Float storage keeps float32; integer storage keeps POINT:SCALE steps (0.1 mm; py-c3d's
    # writer truncates rather than rounds, so up to one step).
    atol = 1e-4 if storage == "float" else 0.1 + 1e-4
    np.testing.assert_allclose(traj.positions_m * 1e3, truth.xyz_mm, atol=atol, equal_nan=True)
    np.testing.assert_allclose(traj.residuals_m * 1e3, truth.residual_mm, atol=1e-6, equal_nan=True)
    ana = read_c3d_analogs(path, isolate=False)
    assert ana.labels == _ANALOG_LABELS
    assert ana.rate_hz == 100.0 * _SPF
    assert ana.first_frame == _FIRST_FRAME
    assert ana.metadata["processor"] == proc
    assert ana.metadata["storage"] == storage
    # Integer storage: within one count (ANALOG:SCALE x GEN_SCALE; py-c3d truncates).
    if storage == "int":
        tol = np.broadcast_to(truth.analog_scale * 1.0001, truth.analogs.shape)
    else:
        tol = 1e-6 * np.abs(truth.analogs) + 1e-12
    assert np.all(np.abs(ana.values - truth.analogs) <= tol)


def test_the_six_variants_give_identical_points_to_their_storage_precision(
    tmp_path: Path, originals: dict[Storage, Path]
) -> None:
    reads = {
        (p, s): read_c3d(_variant(tmp_path, originals[s], p, s), isolate=False)
        for p, s in _VARIANTS
    }
    for p, s in _VARIANTS:
        # Same storage: bit for bit whatever the processor.
        np.testing.assert_array_equal(reads[p, s].positions_m, reads["intel", s].positions_m)
        np.testing.assert_array_equal(reads[p, s].residuals_m, reads["intel", s].residuals_m)
    diff = reads["sgi", "int"].positions_m - reads["dec", "float"].positions_m
    assert np.nanmax(np.abs(diff)) <= 0.1e-3 + 1e-7  # one POINT:SCALE step, in m


def test_an_sgi_file_reads_through_the_isolated_child_reader(
    tmp_path: Path, originals: dict[Storage, Path]
) -> None:
    path = _variant(tmp_path, originals["int"], "sgi", "int")
    assert (
        read_c3d(path).positions_m.tobytes() == read_c3d(path, isolate=False).positions_m.tobytes()
    )


# --------------------------------------------------------------------------------------------
# the real Vicon Nexus file in all six variants
# --------------------------------------------------------------------------------------------


@functools.cache
def _read_original(path: Path) -> tuple[Path, MarkerTrajectories, AnalogChannels]:
    return path, read_c3d(path, isolate=False), read_c3d_analogs(path, isolate=False)


@pytest.fixture
def nexus(shared_data: Path) -> tuple[Path, MarkerTrajectories, AnalogChannels]:
    return _read_original(shared_data / _NEXUS)


_ANALOG_FORMS = {
    "float": {},
    "int": {"analog_offset": -1500},  # signed words with a negative ANALOG:OFFSET
    "uint": {"analog_offset": 32768, "unsigned": True},  # ANALOG:FORMAT UNSIGNED
}


@pytest.mark.parametrize("form", ["float", "int", "uint"])
@pytest.mark.parametrize("proc", ["intel", "dec", "sgi"])
def test_the_real_nexus_file_reads_the_same_in_every_variant(
    tmp_path: Path,
    nexus: tuple[Path, MarkerTrajectories, AnalogChannels],
    proc: Proc,
    form: str,
) -> None:
    src, ref, ref_ana = nexus
    storage: Storage = "float" if form == "float" else "int"
    point_scale = 0.05  # mm: the file's coordinates reach 1,085 mm, inside ±32767 steps
    kw: dict[str, float] = dict(_ANALOG_FORMS[form])
    if storage == "int":
        kw["point_scale"] = point_scale
    path = _variant(tmp_path, src, proc, storage, **kw)
    traj = read_c3d(path, isolate=False)
    assert (traj.metadata["processor"], traj.metadata["storage"]) == (proc, storage)
    assert traj.labels == ref.labels
    assert traj.source_unit == ref.source_unit == "mm"
    assert (traj.rate_hz, traj.first_frame, traj.n_frames) == (ref.rate_hz, 1, 580)
    np.testing.assert_array_equal(traj.valid, ref.valid)
    if storage == "float":
        np.testing.assert_array_equal(traj.positions_m, ref.positions_m)
    else:
        err = np.nanmax(np.abs(traj.positions_m - ref.positions_m))
        # Half a step, plus the float32 rounding of POINT:SCALE itself (< 0.1 µm here).
        assert err <= point_scale / 2 * 1e-3 + 1e-7
    np.testing.assert_array_equal(traj.residuals_m, ref.residuals_m)
    ana = read_c3d_analogs(path, isolate=False)
    assert ana.labels == ref_ana.labels
    assert ana.units == ref_ana.units
    assert (ana.rate_hz, ana.first_frame) == (ref_ana.rate_hz, ref_ana.first_frame)
    assert ana.metadata["format"] == ("unsigned" if form == "uint" else "signed")
    if storage == "float":
        np.testing.assert_array_equal(ana.values, ref_ana.values)
    else:
        # Half a count: the converter rounds to the new ANALOG:SCALE (range / 30,000).
        count = np.abs(ref_ana.values).max(axis=0) / 30_000
        assert np.all(np.abs(ana.values - ref_ana.values) <= count / 2 * (1 + 1e-4) + 1e-12)
    # The second reader agrees on the points of the converted file.
    pts, _ = _pyc3d_read(path)
    ok = pts[..., 3] >= 0
    np.testing.assert_array_equal(ok, ref.valid)
    np.testing.assert_allclose(pts[..., :3][ok] * 1e-3, traj.positions_m[ok], rtol=1e-6)


# --------------------------------------------------------------------------------------------
# writing stays Intel; vicon info; errors
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("proc", "storage"), [("dec", "float"), ("sgi", "int")])
def test_a_file_read_from_any_variant_is_written_back_as_intel_float(
    tmp_path: Path, originals: dict[Storage, Path], proc: Proc, storage: Storage
) -> None:
    traj = read_c3d(_variant(tmp_path, originals[storage], proc, storage), isolate=False)
    out = write_c3d(tmp_path / "written.c3d", traj)
    layout = validate_c3d(out)
    assert (layout.processor, layout.is_float) == ("intel", True)
    back = read_c3d(out, isolate=False)
    np.testing.assert_allclose(back.positions_m, traj.positions_m, atol=1e-7, equal_nan=True)
    assert back.first_frame == traj.first_frame == _FIRST_FRAME


def test_vicon_info_names_the_processor_type_and_storage(
    tmp_path: Path, originals: dict[Storage, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    from mocaprig.cli import main

    path = _variant(tmp_path, originals["int"], "sgi", "int")
    assert main(["vicon", "info", str(path), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert (summary["processor"], summary["storage"]) == ("sgi", "int")
    assert summary["point_scale"] == pytest.approx(0.1)
    assert main(["vicon", "info", str(_variant(tmp_path, originals["float"], "dec", "float"))]) == 0
    text = capsys.readouterr().out
    assert "storage:   DEC VAX (little-endian, VAX floats), 32-bit floats" in text


def test_an_sgi_file_without_its_fallback_reader_names_the_file_and_the_fix(
    tmp_path: Path, originals: dict[Storage, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    import sys

    path = _variant(tmp_path, originals["float"], "sgi", "float")
    monkeypatch.setitem(sys.modules, "c3d", None)  # `import c3d` now fails
    with pytest.raises(ViconFileError, match=r"SGI/MIPS.*pip install c3d") as err:
        read_c3d(path, isolate=False)
    assert str(path) in str(err.value)


def test_sgi_points_that_py_c3d_and_numpy_read_differently_are_refused(
    tmp_path: Path, originals: dict[Storage, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    from mocaprig.calib import c3d_decode, c3d_read

    path = _variant(tmp_path, originals["float"], "sgi", "float")
    real = c3d_decode.read_points_native

    def off_by_a_millimetre(proc: Proc, p: str) -> tuple[FloatArray, FloatArray, str]:
        xyz, res, reader = real(proc, p)
        return xyz + 1.0, res, reader

    monkeypatch.setattr(c3d_read, "read_points_native", off_by_a_millimetre)
    with pytest.raises(ViconFileError, match=r"read frame 1, point 1 as .*inconsistent") as err:
        read_c3d(path, isolate=False)
    assert str(path) in str(err.value)
