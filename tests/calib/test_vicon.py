"""Tests of calib.vicon: C3D/CSV readers, the writer, structural validation and isolation."""

from __future__ import annotations

import struct
import time
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mocaprig.calib import c3d_decode, vicon
from mocaprig.calib.vicon import (
    MarkerTrajectories,
    ViconFileError,
    parse_length_unit,
    read_c3d,
    read_nexus_csv,
    read_trajectories,
    validate_c3d,
    write_c3d,
)
from mocaprig.errors import CalibrationError, ValidationError

Proc = Literal["intel", "dec", "sgi"]


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def _trajectories(
    seed: int = 0, n_frames: int = 12, labels: tuple[str, ...] = ("S:a", "S:b", "S:c")
) -> MarkerTrajectories:
    """Random trajectories (m) about 1 m from the origin with two gaps and mixed residuals."""
    rng = np.random.default_rng(seed)
    n = len(labels)
    pos = rng.uniform(-1.0, 1.0, (n_frames, n, 3))
    pos[3, 1] = np.nan
    pos[7:9, 0] = np.nan
    res = rng.choice([0.0, 0.0005, 0.0012], size=(n_frames, n))
    return MarkerTrajectories(labels=labels, rate_hz=120.0, positions_m=pos, residuals_m=res)


def _ezc3d_file(
    path: Path,
    labels: list[str],
    points: npt.NDArray[np.float64],
    *,
    units: str = "mm",
    extra: dict[str, list[str]] | None = None,
) -> Path:
    """Write ``points`` (F, N, 3, file units, NaN gaps) with ezc3d directly, not write_c3d."""
    import ezc3d

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [100.0]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(labels)
    c["parameters"]["POINT"]["UNITS"]["value"] = [units]
    data = np.ones((4, len(labels), points.shape[0]))
    data[:3] = np.transpose(points, (2, 1, 0))
    c["data"]["points"] = data
    for name, values in (extra or {}).items():
        c.add_parameter("POINT", name, values)
    c.write(str(path))
    return path


def _find_param(buf: bytes, name: bytes) -> int:
    """Byte offset of a parameter record's name inside the parameter section."""
    i = buf.find(name, 512)
    assert i > 0, name
    return i


# An independent, minimal byte-level C3D writer (straight from the c3d.org layout, sharing no code
# with calib.vicon): header block, one parameter block (POINT only), float or integer data, in
# Intel, DEC (VAX floats) or SGI/MIPS (big-endian) order.

_PROC_BYTE = {"intel": 84, "dec": 85, "sgi": 86}


def _end(proc: Proc) -> str:
    return ">" if proc == "sgi" else "<"


def _f32(x: float, proc: Proc) -> bytes:
    if proc == "dec":
        b = struct.pack("<f", x * 4.0)  # VAX F-float = IEEE x 4 with the 16-bit halves swapped
        return b[2:4] + b[0:2]
    return struct.pack(_end(proc) + "f", x)


def _prm(name: str, type_code: int, dims: list[int], data: bytes, proc: Proc) -> bytes:
    body = struct.pack("b", type_code) + bytes([len(dims), *dims]) + data + b"\x00"
    return (
        struct.pack("bb", len(name), 1)
        + name.encode()
        + struct.pack(_end(proc) + "H", 2 + len(body))
        + body
    )


def build_c3d(
    labels: list[str],
    xyz: npt.NDArray[np.float64],
    residual: npt.NDArray[np.float64],
    *,
    proc: Proc,
    is_float: bool,
    units: str = "mm",
    scale: float = 0.1,
    rate: float = 100.0,
) -> bytes:
    """C3D bytes for ``xyz`` (F, N, 3) and ``residual`` (F, N) in file units; residual < 0 = gap."""
    n_frames, n_points = xyz.shape[:2]
    e = _end(proc)
    sscale = -scale if is_float else scale
    width = max(len(x) for x in labels)
    section = b"".join(
        [
            struct.pack("bb", 5, -1) + b"POINT" + struct.pack(e + "H", 3) + b"\x00",
            _prm("USED", 2, [], struct.pack(e + "H", n_points), proc),
            _prm("FRAMES", 2, [], struct.pack(e + "H", n_frames), proc),
            _prm("DATA_START", 2, [], struct.pack(e + "H", 3), proc),
            _prm("SCALE", 4, [], _f32(sscale, proc), proc),
            _prm("RATE", 4, [], _f32(rate, proc), proc),
            _prm(
                "LABELS",
                -1,
                [width, n_points],
                "".join(x.ljust(width) for x in labels).encode(),
                proc,
            ),
            _prm("UNITS", -1, [len(units)], units.encode(), proc),
            b"\x00\x00",
        ]
    )
    params = (bytes([1, 0x50, 1, _PROC_BYTE[proc]]) + section).ljust(512, b"\x00")
    header = bytearray(512)
    header[0], header[1] = 2, 0x50
    struct.pack_into(e + "HHHHH", header, 2, n_points, 0, 1, n_frames, 10)
    header[12:16] = _f32(sscale, proc)
    struct.pack_into(e + "HH", header, 16, 3, 0)
    header[20:24] = _f32(rate, proc)
    data = bytearray()
    for f in range(n_frames):
        for i in range(n_points):
            gap = residual[f, i] < 0
            word = -1 if gap else round(residual[f, i] / scale)  # camera byte 0, residual byte
            if is_float:
                for v in xyz[f, i]:
                    data += _f32(0.0 if gap else float(v), proc)
                data += _f32(float(word), proc)
            else:
                ints = [0, 0, 0] if gap else [round(float(v) / scale) for v in xyz[f, i]]
                data += struct.pack(e + "4h", *ints, word)
    body = bytes(header) + params + bytes(data)
    return body.ljust(-(-len(body) // 512) * 512, b"\x00")


@pytest.fixture
def small_c3d(tmp_path: Path) -> Path:
    return write_c3d(tmp_path / "small.c3d", _trajectories())


# --------------------------------------------------------------------------------------------
# the record
# --------------------------------------------------------------------------------------------


def test_record_is_read_only_and_copies_its_inputs() -> None:
    pos = np.zeros((2, 1, 3)) + 1.0
    traj = MarkerTrajectories(
        labels=("a",), rate_hz=50.0, positions_m=pos, residuals_m=np.zeros((2, 1))
    )
    pos[0, 0, 0] = 99.0
    assert traj.positions_m[0, 0, 0] == 1.0
    assert not traj.positions_m.flags.writeable
    with pytest.raises(AttributeError):
        traj.rate_hz = 1.0  # type: ignore[misc]
    with pytest.raises(TypeError):
        traj.metadata["x"] = "y"  # type: ignore[index]


def test_record_helpers_report_times_gaps_and_extent() -> None:
    pos = np.array([[[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0]], [[1.0, 2.0, 2.0], [0.5, 0.5, 0.5]]])
    traj = MarkerTrajectories(
        labels=("a", "b"),
        rate_hz=100.0,
        positions_m=pos,
        residuals_m=np.zeros((2, 2)),
        first_frame=11,
    )
    np.testing.assert_allclose(traj.times_s, [0.10, 0.11])
    assert traj.duration_s == pytest.approx(0.02)
    assert traj.gap_fraction == pytest.approx(0.25)
    assert np.isnan(traj.residuals_m[0, 1])
    assert traj.extent_m == pytest.approx(3.0)


def test_record_rejects_bad_shapes_and_duplicate_labels() -> None:
    with pytest.raises(ValidationError, match=r"expected: \(F, 2, 3\)"):
        MarkerTrajectories(
            labels=("a", "b"),
            rate_hz=1.0,
            positions_m=np.zeros((3, 1, 3)),
            residuals_m=np.zeros((3, 1)),
        )
    with pytest.raises(ValidationError, match="unique"):
        MarkerTrajectories(
            labels=("a", "a"),
            rate_hz=1.0,
            positions_m=np.zeros((1, 2, 3)),
            residuals_m=np.zeros((1, 2)),
        )
    with pytest.raises(ValidationError, match="rate_hz"):
        MarkerTrajectories(
            labels=("a",),
            rate_hz=0.0,
            positions_m=np.zeros((1, 1, 3)),
            residuals_m=np.zeros((1, 1)),
        )


def test_select_matches_labels_with_or_without_subject_prefix() -> None:
    traj = _trajectories()
    sub = traj.select(["c", "S:a"])
    assert sub.labels == ("S:c", "S:a")
    np.testing.assert_array_equal(sub.marker("a"), traj.marker("S:a"))
    with pytest.raises(ValidationError, match="not in"):
        traj.select(["nope"])


def test_strip_subject_prefixes_refuses_to_merge_two_subjects() -> None:
    traj = _trajectories(labels=("A:x", "B:x", "A:y"))
    with pytest.raises(ValidationError, match=r"\['x'\] occur for more than one subject"):
        traj.strip_subject_prefixes()
    assert traj.select(["A:x", "A:y"]).strip_subject_prefixes().labels == ("x", "y")


# --------------------------------------------------------------------------------------------
# write -> read
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("unit", ["mm", "m"])
def test_write_read_round_trip_keeps_positions_gaps_and_residuals(
    tmp_path: Path, unit: Literal["mm", "m"]
) -> None:
    traj = _trajectories()
    path = write_c3d(tmp_path / "rt.c3d", traj, unit=unit)
    back = read_c3d(path, isolate=False)
    assert back.labels == traj.labels
    assert back.rate_hz == traj.rate_hz
    assert back.source_unit == unit
    assert back.first_frame == 1
    np.testing.assert_array_equal(back.valid, traj.valid)
    # float32 storage: relative 6e-8 of ~1 m coordinates
    np.testing.assert_allclose(back.positions_m, traj.positions_m, atol=2e-7, equal_nan=True)
    # residual resolution: 0.01 mm (POINT:SCALE)
    np.testing.assert_allclose(back.residuals_m, traj.residuals_m, atol=5e-6, equal_nan=True)
    assert back.metadata["software"] == "mocaprig"


def test_round_trip_through_the_isolated_reader_matches_in_process(small_c3d: Path) -> None:
    a = read_c3d(small_c3d, isolate=False)
    b = read_c3d(small_c3d, isolate=True)
    np.testing.assert_array_equal(a.positions_m, b.positions_m)
    np.testing.assert_array_equal(a.residuals_m, b.residuals_m)


def test_written_file_keeps_first_frame(tmp_path: Path) -> None:
    t = _trajectories()
    t = MarkerTrajectories(
        labels=t.labels,
        rate_hz=t.rate_hz,
        positions_m=t.positions_m,
        residuals_m=t.residuals_m,
        first_frame=70_001,
    )
    back = read_c3d(write_c3d(tmp_path / "ff.c3d", t), isolate=False)
    assert back.first_frame == 70_001


def test_write_refuses_to_overwrite_unless_asked(small_c3d: Path) -> None:
    with pytest.raises(ViconFileError, match="exists; pass overwrite=True"):
        write_c3d(small_c3d, _trajectories(seed=1))
    write_c3d(small_c3d, _trajectories(seed=1), overwrite=True)
    np.testing.assert_allclose(
        read_c3d(small_c3d, isolate=False).positions_m,
        _trajectories(seed=1).positions_m,
        atol=2e-7,
        equal_nan=True,
    )
    assert sorted(p.name for p in small_c3d.parent.iterdir()) == ["small.c3d"]


# --------------------------------------------------------------------------------------------
# units, gaps and label rules
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "unit"),
    [
        ("mm", "mm"),
        (" MM ", "mm"),
        ("millimeters", "mm"),
        ("millimetre", "mm"),
        ("m", "m"),
        ("mete", "m"),
        ("Metres", "m"),
        ("cm", "cm"),
        ("centim", "cm"),
        ("in", None),
        ("", None),
        ("deg", None),
    ],
)
def test_parse_length_unit_accepts_truncated_spellings(text: str, unit: str | None) -> None:
    assert parse_length_unit(text) == unit


@pytest.mark.parametrize(
    ("units", "factor"), [("mm", 1e-3), ("mete", 1.0), ("millimeters", 1e-3), ("cm", 1e-2)]
)
def test_c3d_units_are_converted_to_metres(tmp_path: Path, units: str, factor: float) -> None:
    pts = np.array([[[100.0, 200.0, 300.0]]])
    path = _ezc3d_file(tmp_path / "u.c3d", ["a"], pts, units=units)
    traj = read_c3d(path, isolate=False)
    np.testing.assert_allclose(traj.positions_m[0, 0], pts[0, 0] * factor, rtol=1e-7)


def _file_without_units(tmp_path: Path) -> Path:
    path = _ezc3d_file(tmp_path / "nounits.c3d", ["a"], np.array([[[100.0, 200.0, 300.0]]]))
    buf = bytearray(path.read_bytes())
    i = _find_param(bytes(buf), b"UNITS")
    buf[i : i + 5] = b"UNITX"  # the parameter now has another name: POINT:UNITS is absent
    path.write_bytes(bytes(buf))
    return path


def test_missing_units_raise_a_clear_error(tmp_path: Path) -> None:
    path = _file_without_units(tmp_path)
    with pytest.raises(
        ViconFileError, match=r"nounits\.c3d: POINT:UNITS is missing.*pass unit='mm'"
    ):
        read_c3d(path, isolate=False)


def test_missing_units_can_be_supplied_by_the_caller(tmp_path: Path) -> None:
    traj = read_c3d(_file_without_units(tmp_path), unit="cm", isolate=False)
    assert traj.source_unit == "cm"
    np.testing.assert_allclose(traj.positions_m[0, 0], [1.0, 2.0, 3.0], rtol=1e-7)


def test_unknown_units_raise_unless_overridden(tmp_path: Path) -> None:
    path = _ezc3d_file(tmp_path / "inch.c3d", ["a"], np.array([[[1.0, 2.0, 3.0]]]), units="in")
    with pytest.raises(
        ViconFileError, match="POINT:UNITS is 'in', which is not a known length unit"
    ):
        read_c3d(path, isolate=False)
    assert read_c3d(path, unit="mm", isolate=False).positions_m[0, 0, 0] == pytest.approx(1e-3)
    with pytest.raises(ValidationError, match="not a length unit"):
        read_c3d(path, unit="furlong", isolate=False)


def test_exact_zero_coordinates_are_a_gap(tmp_path: Path) -> None:
    pts = np.array(
        [[[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]], [[0.0, 5.0, 0.0], [np.nan, np.nan, np.nan]]]
    )
    traj = read_c3d(_ezc3d_file(tmp_path / "z.c3d", ["a", "b"], pts), isolate=False)
    np.testing.assert_array_equal(traj.valid, [[False, True], [True, False]])


def _nexus_like(tmp_path: Path) -> Path:
    labels = ["Sub:LASI", "Sub:PELO", "Sub:LHipAngles", "*115", "CentreOfMass", "Sub:RFEA"]
    pts = np.arange(len(labels) * 3, dtype=np.float64).reshape(1, len(labels), 3) + 1.0
    return _ezc3d_file(tmp_path / "pig.c3d", labels, pts, extra={"ANGLES": ["Sub:LHipAngles"]})


def test_model_outputs_virtual_and_unlabeled_points_are_dropped_by_default(tmp_path: Path) -> None:
    assert read_c3d(_nexus_like(tmp_path), isolate=False).labels == ("Sub:LASI",)


def test_keep_options_keep_virtual_and_unlabeled_points(tmp_path: Path) -> None:
    path = _nexus_like(tmp_path)
    assert read_c3d(path, keep_unlabeled=True, isolate=False).labels == ("Sub:LASI", "*115")
    assert read_c3d(path, keep_virtual=True, isolate=False).labels == (
        "Sub:LASI",
        "Sub:PELO",
        "Sub:LHipAngles",
        "CentreOfMass",
        "Sub:RFEA",
    )


def test_subject_prefixes_are_stripped_on_request(tmp_path: Path) -> None:
    traj = read_c3d(
        _nexus_like(tmp_path), strip_subject_prefix=True, keep_virtual=True, isolate=False
    )
    assert traj.labels[:2] == ("LASI", "PELO")


# --------------------------------------------------------------------------------------------
# frame-count quirk
# --------------------------------------------------------------------------------------------


def test_more_than_65535_frames_are_all_read(tmp_path: Path) -> None:
    """ezc3d writes 0xFFFF into the header and POINT:FRAMES and reads back only 65,535 frames."""
    n = 70_000
    pts = np.ones((n, 1, 3))
    pts[:, 0, 0] = np.arange(n) + 1.0
    path = _ezc3d_file(tmp_path / "long.c3d", ["a"], pts)
    layout = validate_c3d(path)
    assert (layout.n_frames, layout.frames_source) == (n, "data section length")
    traj = read_c3d(path, isolate=False)
    assert traj.n_frames == n
    np.testing.assert_allclose(traj.positions_m[:, 0, 0], pts[:, 0, 0] * 1e-3, rtol=1e-7)
    assert "numpy" in traj.metadata["reader"]


def test_more_than_65535_frames_use_the_trial_fields_when_present(tmp_path: Path) -> None:
    n = 66_000
    pos = np.zeros((n, 1, 3)) + 0.5
    traj = MarkerTrajectories(
        labels=("a",), rate_hz=1000.0, positions_m=pos, residuals_m=np.zeros((n, 1))
    )
    path = write_c3d(tmp_path / "trial.c3d", traj)
    assert validate_c3d(path).frames_source == "TRIAL:ACTUAL_END_FIELD"
    assert read_c3d(path, isolate=False).n_frames == n


# --------------------------------------------------------------------------------------------
# processors: Intel, DEC and big-endian SGI/MIPS from an independent writer
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("is_float", [True, False], ids=["float", "int"])
@pytest.mark.parametrize("proc", ["intel", "dec", "sgi"])
def test_files_from_an_independent_writer_read_in_every_byte_order(
    tmp_path: Path, proc: Proc, is_float: bool
) -> None:
    rng = np.random.default_rng(7)
    xyz = rng.uniform(-1000.0, 1000.0, (6, 3, 3)).round(1)
    res = np.full((6, 3), 0.5)
    res[2, 1] = -1.0
    path = tmp_path / f"{proc}.c3d"
    path.write_bytes(build_c3d(["a", "b", "c"], xyz, res, proc=proc, is_float=is_float))
    traj = read_c3d(path, isolate=False)
    assert traj.metadata["processor"] == proc
    assert traj.metadata["reader"].startswith("py-c3d" if proc == "sgi" else "ezc3d")
    expected = xyz * 1e-3
    expected[2, 1] = np.nan
    np.testing.assert_allclose(traj.positions_m, expected, atol=1e-7, equal_nan=True)
    exp_res = np.where(res < 0, np.nan, res * 1e-3)
    np.testing.assert_allclose(traj.residuals_m, exp_res, atol=1e-9, equal_nan=True)


# --------------------------------------------------------------------------------------------
# malformed and hostile files
# --------------------------------------------------------------------------------------------


def test_truncated_file_is_rejected(small_c3d: Path, tmp_path: Path) -> None:
    cut = tmp_path / "cut.c3d"
    cut.write_bytes(small_c3d.read_bytes()[:700])
    with pytest.raises(ViconFileError, match=r"cut\.c3d: .*700 bytes.*truncated"):
        read_c3d(cut)


def test_truncated_data_section_is_rejected(tmp_path: Path) -> None:
    big = write_c3d(tmp_path / "big.c3d", _trajectories(n_frames=200))
    cut = tmp_path / "cutdata.c3d"
    cut.write_bytes(big.read_bytes()[:-1024])
    with pytest.raises(ViconFileError, match=r"200 frames of .* the file is truncated"):
        read_c3d(cut)


def test_garbage_is_rejected(tmp_path: Path) -> None:
    junk = tmp_path / "junk.c3d"
    junk.write_bytes(np.random.default_rng(3).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    with pytest.raises(ViconFileError, match=r"junk\.c3d: not a readable C3D file"):
        read_c3d(junk)


def test_bad_parameter_section_pointer_is_rejected(small_c3d: Path) -> None:
    buf = bytearray(small_c3d.read_bytes())
    buf[0] = 200
    small_c3d.write_bytes(bytes(buf))
    with pytest.raises(ViconFileError, match="parameter section to block 200"):
        read_c3d(small_c3d)


def test_bad_processor_type_is_rejected(small_c3d: Path) -> None:
    buf = bytearray(small_c3d.read_bytes())
    buf[512 + 3] = 99
    small_c3d.write_bytes(bytes(buf))
    with pytest.raises(ViconFileError, match="unknown processor type 99"):
        validate_c3d(small_c3d)


def _set_point_used(path: Path, value: int, *, header: bool) -> None:
    buf = bytearray(path.read_bytes())
    i = _find_param(bytes(buf), b"USED")  # POINT:USED is ezc3d's first USED parameter
    data = i + 4 + 2 + 2  # name, offset, type, ndims (scalar)
    struct.pack_into("<H", buf, data, value)
    if header:
        struct.pack_into("<H", buf, 2, value)
    path.write_bytes(bytes(buf))


def test_absurd_point_used_is_rejected(small_c3d: Path) -> None:
    _set_point_used(small_c3d, 30_000, header=False)
    with pytest.raises(ViconFileError, match="header says 3 points but POINT:USED says 30000"):
        read_c3d(small_c3d)
    _set_point_used(small_c3d, 30_000, header=True)
    with pytest.raises(
        ViconFileError, match="POINT:USED says 30000 points but POINT:LABELS holds 3"
    ):
        read_c3d(small_c3d)


def test_broken_parameter_link_is_rejected(small_c3d: Path) -> None:
    buf = bytearray(small_c3d.read_bytes())
    i = _find_param(bytes(buf), b"USED")
    struct.pack_into("<H", buf, i + 4, 0xFFF0)  # offset to the next record: far past the section
    small_c3d.write_bytes(bytes(buf))
    with pytest.raises(ViconFileError, match="points to the next record at byte"):
        read_c3d(small_c3d)


def test_vicon_file_error_is_a_calibration_error_naming_the_file(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError) as info:
        read_c3d(tmp_path / "absent.c3d")
    assert isinstance(info.value, ViconFileError)
    assert info.value.path == str(tmp_path / "absent.c3d")
    assert "check the path" in str(info.value)


def test_a_crash_in_the_isolated_reader_becomes_vicon_file_error(
    small_c3d: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(
        c3d_decode, "_CHILD_CODE", "import os, signal; os.kill(os.getpid(), signal.SIGSEGV)"
    )
    with pytest.raises(ViconFileError, match=r"crashed on this file \(killed by signal 11"):
        read_c3d(small_c3d, isolate=True)


def test_an_error_in_the_isolated_reader_becomes_vicon_file_error(
    small_c3d: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(
        c3d_decode,
        "_CHILD_CODE",
        "import sys; sys.stderr.write('mocaprig-c3d-error: RuntimeError: boom'); sys.exit(3)",
    )
    with pytest.raises(ViconFileError, match="rejected the file: RuntimeError: boom"):
        read_c3d(small_c3d, isolate=True)


@settings(
    max_examples=20,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    edits=st.lists(
        st.tuples(
            st.integers(min_value=0, max_value=1700), st.integers(min_value=0, max_value=255)
        ),
        min_size=1,
        max_size=6,
    )
)
@pytest.mark.slow
def test_mutated_files_either_read_or_raise_vicon_file_error(
    small_c3d: Path, edits: list[tuple[int, int]]
) -> None:
    """Byte edits in the header, parameter section and first frames never escape as anything else.

    The reader runs isolated, so even a segfault inside ezc3d only fails the child process.
    """
    buf = bytearray(small_c3d.read_bytes())
    for pos, value in edits:
        if pos < len(buf):
            buf[pos] = value
    mutated = small_c3d.with_name("mutated.c3d")
    mutated.write_bytes(bytes(buf))
    try:
        traj = read_c3d(mutated, unit="mm", isolate=True)
    except ViconFileError as err:
        message = str(err)
    else:
        assert traj.positions_m.shape[1:] == (traj.n_markers, 3)
        return
    assert "mutated.c3d" in message


# --------------------------------------------------------------------------------------------
# Nexus CSV
# --------------------------------------------------------------------------------------------

_NEXUS_CSV = """\
Trajectories,,,,,,,,
100,,,,,,,,
,,Sub:LASI,,,Sub:RASI,,,
Frame,Sub Frame,X,Y,Z,X,Y,Z
,,mm,mm,mm,mm,mm,mm
1,0,1.5,2.5,3.5,10,20,30
2,0,1.6,2.6,3.6,,,
3,0,1.7,2.7,3.7,11,21,31

Model Outputs,,,,,,,,
100,,,,,,,,
,,Sub:LHipAngles,,,
Frame,Sub Frame,X,Y,Z
,,deg,deg,deg
1,0,5,6,7
"""

_WORKSTATION_CSV = """\
Title,,,,,,,
Date:,,,,,,,
Notes:,,,,,,,
,,,,,,,
TRAJECTORIES,,,,,,,
100,Hz,,,,,,
,LFHD,,,LHipAngles,,,
Field #,X,Y,Z,X,Y,Z
1,174.5,324.5,1728.9,-3.0,-4.5,-1.7
2,174.6,324.6,1729.0,-3.1,-4.6,-1.8
"""


def test_nexus_csv_is_parsed_by_section(tmp_path: Path) -> None:
    path = tmp_path / "nexus.csv"
    path.write_text(_NEXUS_CSV)
    traj = read_nexus_csv(path)
    assert traj.labels == ("Sub:LASI", "Sub:RASI")
    assert (traj.rate_hz, traj.n_frames, traj.first_frame, traj.source_unit) == (100.0, 3, 1, "mm")
    np.testing.assert_array_equal(traj.valid, [[True, True], [True, False], [True, True]])
    np.testing.assert_allclose(traj.positions_m[2, 1], [0.011, 0.021, 0.031])
    assert np.isnan(traj.residuals_m).all()
    assert traj.metadata["format"] == "nexus-csv"


def test_nexus_csv_with_crlf_and_bom_reads_the_same(tmp_path: Path) -> None:
    path = tmp_path / "crlf.csv"
    path.write_bytes(b"\xef\xbb\xbf" + _NEXUS_CSV.replace("\n", "\r\n").encode())
    assert read_trajectories(path).labels == ("Sub:LASI", "Sub:RASI")


def test_workstation_csv_requires_a_unit(tmp_path: Path) -> None:
    path = tmp_path / "ws.csv"
    path.write_text(_WORKSTATION_CSV)
    with pytest.raises(ViconFileError, match=r"the units row is missing.*pass unit='mm'"):
        read_nexus_csv(path)
    traj = read_nexus_csv(path, unit="mm")
    assert traj.labels == ("LFHD",)  # LHipAngles is a model output
    assert traj.metadata["format"] == "workstation-csv"
    np.testing.assert_allclose(traj.positions_m[:, 0, 0], [0.1745, 0.1746])
    assert read_nexus_csv(path, unit="mm", keep_virtual=True).labels == ("LFHD", "LHipAngles")


def test_csv_without_trajectories_names_the_sections_found(tmp_path: Path) -> None:
    path = tmp_path / "devices.csv"
    path.write_text("Devices,,\n2000,,\n,,EMG\nFrame,Sub Frame,V\n,,V\n1,0,0.1\n")
    with pytest.raises(
        ViconFileError, match=r"no Trajectories section \(sections found: \['Devices'\]\)"
    ):
        read_nexus_csv(path)


def test_csv_with_frames_out_of_order_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "order.csv"
    path.write_text(_NEXUS_CSV.replace("3,0,1.7", "2,0,1.7"))
    with pytest.raises(ViconFileError, match=r"line 8\): frame 2 follows frame 2"):
        read_nexus_csv(path)


# --------------------------------------------------------------------------------------------
# the real Vicon Nexus 2.4 files
# --------------------------------------------------------------------------------------------

# The CSV prints 6 significant digits, so values of 1000–9999 mm keep two decimals: rounding error
# up to 0.005 mm, plus float32 storage in the C3D. Measured max |C3D − CSV| = 0.004995 mm.
CSV_VS_C3D_ATOL_M = 6e-6


def test_real_c3d_and_csv_exports_agree(shared_data: Path) -> None:
    t0 = time.perf_counter()
    c3d = read_c3d(shared_data / "vicon" / "nexus24_markers_analogs.c3d", isolate=True)
    elapsed = time.perf_counter() - t0
    csv = read_nexus_csv(shared_data / "vicon" / "nexus24_markers.csv")
    assert c3d.labels == csv.labels
    assert len(c3d.labels) == 51
    assert (c3d.rate_hz, csv.rate_hz, c3d.n_frames, csv.n_frames) == (100.0, 100.0, 580, 580)
    assert c3d.first_frame == csv.first_frame == 1
    np.testing.assert_array_equal(c3d.valid, csv.valid)
    assert c3d.gap_fraction == pytest.approx(0.0103, abs=1e-4)
    diff = np.nanmax(np.abs(c3d.positions_m - csv.positions_m))
    assert diff <= CSV_VS_C3D_ATOL_M, f"max |C3D - CSV| = {diff * 1e3:.6f} mm"
    assert c3d.metadata["software"] == "Vicon Nexus"
    assert c3d.metadata["software_version"] == "2.4.0.91647h"
    assert elapsed < 10.0


def test_real_c3d_numpy_decoder_matches_ezc3d(shared_data: Path) -> None:
    path = shared_data / "vicon" / "nexus24_markers_analogs.c3d"
    layout = validate_c3d(path)
    xyz, residual = vicon._decode_point_block(layout, path.read_bytes())
    ez = read_c3d(path, isolate=False)
    np.testing.assert_array_equal(xyz[ez.valid] * 1e-3, ez.positions_m[ez.valid])
    np.testing.assert_array_equal(residual < 0, ~ez.valid)


def _read_with_fourth_word(
    tmp_path: Path, fmt: str, value: float
) -> tuple[MarkerTrajectories, MarkerTrajectories]:
    """A float C3D of :func:`_trajectories` whose frame 0, point 0 fourth word is ``value``
    packed as ``fmt``, and what the reader makes of it with every warning an error."""
    import struct
    import warnings

    traj = _trajectories()
    path = write_c3d(tmp_path / "w4.c3d", traj)
    buf = bytearray(path.read_bytes())
    data_start = (struct.unpack_from("<H", buf, 16)[0] - 1) * 512  # header word 9 (1-based)
    struct.pack_into(fmt, buf, data_start + 12, value)
    path.write_bytes(bytes(buf))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return traj, read_c3d(path, isolate=False)


def test_a_damaged_fourth_word_reads_as_a_gap_without_an_undefined_cast(tmp_path: Path) -> None:
    """A float file whose residual word is a huge float (a damaged file, a fuzz input): that
    sample is a gap, the others are intact, and numpy is never asked for an undefined cast."""
    traj, back = _read_with_fourth_word(tmp_path, "<f", 1e30)
    assert not back.valid[0, 0]
    np.testing.assert_array_equal(back.valid[1:], traj.valid[1:])
    np.testing.assert_array_equal(back.valid[0, 1:], traj.valid[0, 1:])


def test_a_signalling_nan_reads_as_a_gap_without_a_runtime_warning(tmp_path: Path) -> None:
    """A signalling NaN (a damaged float file) raises the FPU's invalid flag when widened to
    float64: the sample is a gap and nothing is printed on the user's stderr."""
    traj, back = _read_with_fourth_word(tmp_path, "<I", 0x7F800001)
    assert not back.valid[0, 0]
    np.testing.assert_array_equal(back.valid[1:], traj.valid[1:])


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="the cap is Linux-only")
def test_a_damaged_count_that_sends_the_native_reader_after_gigabytes_is_refused(
    tmp_path: Path,
) -> None:
    """ROTATION:RATIO = -1 (fuzz input #2991, seed 17) made ezc3d map 12 GB over 45-64 s for
    a 2.5 kB file; the child's capped address space turns it into a clean error at once."""
    from mocaprig.calib.c3d_layout import validate_c3d

    path = write_c3d(tmp_path / "rot.c3d", _trajectories())
    offset = validate_c3d(path).parameter_offsets["ROTATION:RATIO"]
    buf = bytearray(path.read_bytes())
    struct.pack_into("<h", buf, offset, -1)
    path.write_bytes(bytes(buf))
    with pytest.raises(ViconFileError, match=r"ask the C3D reader for more than \d+ MiB"):
        read_c3d(path)
    assert c3d_decode.isolate_memory_budget(2560) < 300 << 20


def test_a_force_plate_count_beyond_its_type_list_is_refused_before_the_native_reader(
    tmp_path: Path,
) -> None:
    """FORCE_PLATFORM:USED = 802 in a 2.5 kB file (fuzz input #7262, seed 17): ezc3d spent 15 s
    before its own error; the layout check refuses it at once, naming both parameters."""
    import struct

    from mocaprig.calib.c3d_layout import validate_c3d

    path = write_c3d(tmp_path / "fp.c3d", _trajectories())
    offset = validate_c3d(path).parameter_offsets["FORCE_PLATFORM:USED"]
    buf = bytearray(path.read_bytes())
    struct.pack_into("<h", buf, offset, 802)
    path.write_bytes(bytes(buf))
    with pytest.raises(ViconFileError, match=r"FORCE_PLATFORM:USED is 802.*TYPE describes 0"):
        read_c3d(path)
