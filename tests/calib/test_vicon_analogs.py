"""Analog channels of C3D files (calib.vicon): reading, scaling, writing, malformed parameters."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mocaprig.calib import c3d_decode, vicon
from mocaprig.calib.time_align import analog_times_ns, vicon_times_ns
from mocaprig.calib.vicon import (
    AnalogChannels,
    MarkerTrajectories,
    ViconFileError,
    read_c3d,
    read_c3d_analogs,
    write_c3d,
)
from mocaprig.errors import ValidationError

F64 = npt.NDArray[np.float64]


def _trajectories(n_frames: int = 12, first_frame: int = 4001) -> MarkerTrajectories:
    rng = np.random.default_rng(0)
    pos = rng.uniform(-1.0, 1.0, (n_frames, 2, 3))
    pos[3, 1] = np.nan
    return MarkerTrajectories(
        labels=("S:a", "S:b"),
        rate_hz=120.0,
        positions_m=pos,
        residuals_m=np.full((n_frames, 2), 0.0005),
        first_frame=first_frame,
    )


def _analogs(traj: MarkerTrajectories, spf: int = 20) -> AnalogChannels:
    rng = np.random.default_rng(1)
    n = traj.n_frames * spf
    values = np.stack([rng.normal(0.0, 1.0, n), np.where(np.arange(n) % 80 < 40, 0.0, 4.8)], 1)
    return AnalogChannels(
        labels=("EMG.1", "D415_SYNC"),
        rate_hz=traj.rate_hz * spf,
        values=values,
        units=("mV", "V"),
        point_rate_hz=traj.rate_hz,
        first_frame=traj.first_frame,
    )


def _param_data_offset(buf: bytes, group_id: int, name: str) -> tuple[int, int, int]:
    """(offset of the data, type code, value count) of parameter ``name`` in group ``group_id``
    of a file ezc3d wrote (one dimension at most; a locked parameter's name length is negative)."""
    lengths = (len(name), 256 - len(name))
    hits = [buf.find(bytes([n, group_id]) + name.encode(), 512) for n in lengths]
    i = max(hits)
    assert i > 0, name
    body = i + 2 + len(name) + 2
    type_code = struct.unpack_from("b", buf, body)[0]
    n_dims = buf[body + 1]
    dims = list(buf[body + 2 : body + 2 + n_dims])
    count = int(np.prod(dims)) if dims else 1
    return body + 2 + n_dims, type_code, count


@pytest.fixture
def analog_c3d(tmp_path: Path) -> tuple[Path, MarkerTrajectories, AnalogChannels]:
    traj = _trajectories()
    an = _analogs(traj)
    return write_c3d(tmp_path / "a.c3d", traj, analogs=an), traj, an


# ------------------------------------------------------------------------------- round trip


@pytest.mark.parametrize("isolate", [True, False], ids=["isolated", "in-process"])
def test_write_read_round_trip_keeps_the_analog_channels(
    analog_c3d: tuple[Path, MarkerTrajectories, AnalogChannels], isolate: bool
) -> None:
    path, traj, an = analog_c3d
    got = read_c3d_analogs(path, isolate=isolate)
    assert got.labels == an.labels
    assert got.units == an.units
    assert (got.rate_hz, got.point_rate_hz, got.samples_per_frame) == (2400.0, 120.0, 20)
    assert got.first_frame == traj.first_frame
    np.testing.assert_allclose(got.values, an.values, rtol=1e-6, atol=1e-6)  # float32 storage
    assert got.metadata["reader"].startswith("ezc3d")
    np.testing.assert_array_equal(got.channel("d415_sync"), got.values[:, 1])  # any case
    # The points are unaffected and sample 0 of each frame falls on the frame's time.
    back = read_c3d(path, isolate=isolate)
    np.testing.assert_allclose(back.positions_m, traj.positions_m, atol=1e-6)
    at_frames = analog_times_ns(got)[:: got.samples_per_frame]
    np.testing.assert_array_equal(at_frames, vicon_times_ns(back))


def test_write_refuses_analogs_that_do_not_fit_the_trajectories(tmp_path: Path) -> None:
    traj = _trajectories()
    an = _analogs(_trajectories(n_frames=11))
    with pytest.raises(ValidationError, match="analogs do not fit the trajectories"):
        write_c3d(tmp_path / "x.c3d", traj, analogs=an)
    assert not (tmp_path / "x.c3d").exists()


def test_a_file_without_analogs_has_no_channels(tmp_path: Path) -> None:
    path = write_c3d(tmp_path / "n.c3d", _trajectories())
    got = read_c3d_analogs(path)
    assert got.n_channels == 0
    assert got.metadata["reader"] == "none (no analog data)"
    with pytest.raises(ValidationError, match=r"no analog channel 'D415_SYNC'.*channels: none"):
        got.channel("D415_SYNC")


def test_record_rejects_a_rate_that_is_not_a_multiple_and_bad_shapes() -> None:
    with pytest.raises(ValidationError, match="integer multiple"):
        AnalogChannels(("a",), 2000.0, np.zeros((10, 1)), point_rate_hz=120.0)
    with pytest.raises(ValidationError, match="wrong shape"):
        AnalogChannels(("a", "b"), 2400.0, np.zeros((10, 1)), point_rate_hz=120.0)
    with pytest.raises(ValidationError, match="unique"):
        AnalogChannels(("a", "a"), 2400.0, np.zeros((10, 2)), point_rate_hz=120.0)


# ---------------------------------------------------------------------------------- scaling


def test_values_follow_offset_scale_and_gen_scale_with_a_signed_offset(
    analog_c3d: tuple[Path, MarkerTrajectories, AnalogChannels],
) -> None:
    """Physical = (stored − OFFSET) × SCALE × GEN_SCALE (c3d.org), OFFSET signed; ezc3d 1.7.2
    uses |OFFSET|, which the reader corrects."""
    path, _, an = analog_c3d
    buf = bytearray(path.read_bytes())
    layout = vicon.validate_c3d(path)
    alay = vicon._analog_layout(bytes(buf), layout)
    stored = vicon._decode_analog_block(layout, alay, bytes(buf))
    np.testing.assert_allclose(stored, an.values, rtol=1e-6, atol=1e-6)  # written with 1, 0, 1
    pos, code, count = _param_data_offset(bytes(buf), 2, "SCALE")
    assert (code, count) == (4, 2)
    struct.pack_into("<2f", buf, pos, 2.0, 0.5)
    pos, code, count = _param_data_offset(bytes(buf), 2, "OFFSET")
    assert (code, count) == (2, 2)
    struct.pack_into("<2h", buf, pos, 3, -7)
    pos, code, _ = _param_data_offset(bytes(buf), 2, "GEN_SCALE")
    struct.pack_into("<f", buf, pos, 10.0)
    path.write_bytes(bytes(buf))
    expected = (stored - np.array([3.0, -7.0])) * np.array([2.0, 0.5]) * 10.0
    for isolate in (True, False):
        got = read_c3d_analogs(path, isolate=isolate)
        np.testing.assert_allclose(got.values, expected, rtol=1e-6, atol=1e-5)
    import ezc3d

    ez = np.asarray(ezc3d.c3d(str(path))["data"]["analogs"])[0].T
    np.testing.assert_allclose(ez[:, 0], expected[:, 0], rtol=1e-6, atol=1e-5)  # offset > 0
    np.testing.assert_allclose(ez[:, 1], (stored[:, 1] - 7.0) * 5.0, rtol=1e-6, atol=1e-5)


# -------------------------------------------------------------------------------- malformed


def _patch(path: Path, name: str, fmt: str, *values: float) -> None:
    buf = bytearray(path.read_bytes())
    pos, _, _ = _param_data_offset(bytes(buf), 2, name)
    struct.pack_into(fmt, buf, pos, *values)
    path.write_bytes(bytes(buf))


@pytest.mark.parametrize(
    ("name", "fmt", "values", "message"),
    [
        ("USED", "<h", (3,), r"ANALOG:USED says 3 channels but the header stores 40 analog"),
        ("RATE", "<f", (2000.0,), r"ANALOG:RATE is 2000 Hz but the header stores 20 samples"),
        ("GEN_SCALE", "<f", (0.0,), r"ANALOG:GEN_SCALE is 0.0, not a finite non-zero number"),
        ("SCALE", "<f", (float("nan"),), r"ANALOG:SCALE holds 2 values \(some not finite\)"),
    ],
)
def test_malformed_analog_parameters_raise_vicon_file_error(
    analog_c3d: tuple[Path, MarkerTrajectories, AnalogChannels],
    name: str,
    fmt: str,
    values: tuple[float, ...],
    message: str,
) -> None:
    path, _, _ = analog_c3d
    _patch(path, name, fmt, *values)
    with pytest.raises(ViconFileError, match=f"malformed analog parameters: {message}"):
        read_c3d_analogs(path)
    read_c3d(path)  # the points stay readable


def test_a_short_offset_list_is_refused(
    analog_c3d: tuple[Path, MarkerTrajectories, AnalogChannels],
) -> None:
    path, _, _ = analog_c3d
    buf = bytearray(path.read_bytes())
    pos, _, _ = _param_data_offset(bytes(buf), 2, "OFFSET")
    buf[pos - 1] = 1  # the one dimension: 2 → 1 value (the record keeps its length)
    path.write_bytes(bytes(buf))
    with pytest.raises(ViconFileError, match="ANALOG:OFFSET holds 1 values for 2 channels"):
        read_c3d_analogs(path)


def test_a_crash_in_the_isolated_analog_reader_becomes_vicon_file_error(
    analog_c3d: tuple[Path, MarkerTrajectories, AnalogChannels], monkeypatch: pytest.MonkeyPatch
) -> None:
    path, _, _ = analog_c3d
    monkeypatch.setattr(
        c3d_decode, "_CHILD_CODE", "import os, signal; os.kill(os.getpid(), signal.SIGSEGV)"
    )
    with pytest.raises(ViconFileError, match=r"crashed on this file \(killed by signal 11"):
        read_c3d_analogs(path, isolate=True)


# ---------------------------------------------------------------------- the real Nexus file


def test_real_nexus_file_analogs_match_ezc3d(shared_data: Path) -> None:
    import ezc3d

    path = shared_data / "vicon" / "nexus24_markers_analogs.c3d"
    got = read_c3d_analogs(path)
    assert got.n_channels == 38
    assert (got.rate_hz, got.point_rate_hz, got.samples_per_frame) == (2000.0, 100.0, 20)
    assert got.n_samples == 580 * 20
    assert got.labels[:2] == ("Voltage.1", "Voltage.2")
    assert set(got.units) == {"V"}
    c = ezc3d.c3d(str(path))
    assert list(got.labels) == list(c["parameters"]["ANALOG"]["LABELS"]["value"])
    ez = np.asarray(c["data"]["analogs"], dtype=np.float64)[0].T
    np.testing.assert_array_equal(got.values, ez)
    # The numpy decoder (SGI files, > 65535 frames) reads the same values.
    buf = path.read_bytes()
    layout = vicon.validate_c3d(path)
    alay = vicon._analog_layout(buf, layout)
    raw = vicon._decode_analog_block(layout, alay, buf)
    np.testing.assert_allclose((raw - alay.offset) * alay.scale * alay.gen_scale, ez, atol=1e-7)
    assert got.first_frame == read_c3d(path).first_frame


@settings(
    max_examples=15,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    edits=st.lists(
        st.tuples(
            st.integers(min_value=0, max_value=2047), st.integers(min_value=0, max_value=255)
        ),
        min_size=1,
        max_size=6,
    )
)
def test_mutated_analog_files_either_read_or_raise_vicon_file_error(
    analog_c3d: tuple[Path, MarkerTrajectories, AnalogChannels], edits: list[tuple[int, int]]
) -> None:
    """Byte edits in the header and parameter section never escape as anything else."""
    path, _, _ = analog_c3d
    buf = bytearray(path.read_bytes())
    for pos, value in edits:
        if pos < len(buf):
            buf[pos] = value
    mutated = path.with_name("mutated.c3d")
    mutated.write_bytes(bytes(buf))
    try:
        got = read_c3d_analogs(mutated, isolate=True)
    except ViconFileError:
        return
    assert got.values.shape == (got.n_samples, got.n_channels)
