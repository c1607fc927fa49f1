"""C3DFrameWriter: a C3D written block by block is the file write_c3d writes at once."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocaprig.calib.c3d_layout import validate_c3d
from mocaprig.calib.c3d_read import read_c3d
from mocaprig.calib.c3d_write import C3DFrameWriter, write_c3d
from mocaprig.calib.vicon_records import MarkerTrajectories, ViconFileError


def _trajectories(frames: int, markers: int, first: int, seed: int) -> MarkerTrajectories:
    rng = np.random.default_rng(seed)
    pos = rng.normal(size=(frames, markers, 3))
    pos[1, 0] = np.nan  # a gap
    res = np.abs(rng.normal(size=(frames, markers))) * 1e-4
    return MarkerTrajectories(
        labels=tuple(f"M{i}" for i in range(markers)),
        rate_hz=1000.0,
        positions_m=pos,
        residuals_m=res,
        first_frame=first,
        source_unit="mm",
        source="test",
        metadata={},
    )


@pytest.mark.parametrize(
    ("frames", "markers", "first", "block"),
    [
        (5, 19, 1, 2),  # data shorter than a block
        (64, 2, 1, 7),  # data that fill whole 512-byte blocks: ezc3d adds a block
        (70_000, 1, 3, 4_096),  # past the 16-bit frame count
    ],
)
def test_blocks_give_the_bytes_write_c3d_gives_at_once(
    tmp_path: Path, frames: int, markers: int, first: int, block: int
) -> None:
    tr = _trajectories(frames, markers, first, seed=frames)
    whole = write_c3d(tmp_path / "whole.c3d", tr)
    with C3DFrameWriter(
        tmp_path / "blocks.c3d", labels=tr.labels, rate_hz=1000.0, first_frame=first
    ) as w:
        for i in range(0, frames, block):
            w.write(tr.positions_m[i : i + block], tr.residuals_m[i : i + block])
    assert (tmp_path / "blocks.c3d").read_bytes() == whole.read_bytes()
    layout = validate_c3d(tmp_path / "blocks.c3d")
    assert layout.n_frames == frames
    assert layout.first_frame == first


def test_frames_read_back_with_their_gaps(tmp_path: Path) -> None:
    tr = _trajectories(6, 3, 1, seed=1)
    path = tmp_path / "r.c3d"
    with C3DFrameWriter(path, labels=tr.labels, rate_hz=1000.0) as w:
        w.write(tr.positions_m[:4])
        w.write(tr.positions_m[4:])
    back = read_c3d(path)
    assert back.labels == tr.labels
    assert np.isnan(back.positions_m[1, 0]).all()
    ok = np.isfinite(tr.positions_m)
    np.testing.assert_allclose(back.positions_m[ok], tr.positions_m[ok], atol=1e-6)


def test_an_existing_file_is_kept_and_a_failed_write_leaves_nothing(tmp_path: Path) -> None:
    path = tmp_path / "r.c3d"
    path.write_bytes(b"keep")
    with pytest.raises(ViconFileError, match="exists"):
        C3DFrameWriter(path, labels=("a",), rate_hz=100.0)
    assert path.read_bytes() == b"keep"
    out = tmp_path / "new.c3d"

    def interrupted() -> None:
        with C3DFrameWriter(out, labels=("a",), rate_hz=100.0) as w:
            w.write(np.zeros((2, 1, 3)))
            raise RuntimeError("stopped")

    with pytest.raises(RuntimeError, match="stopped"):
        interrupted()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.c3d"]


def test_a_writer_without_frames_writes_no_file(tmp_path: Path) -> None:
    w = C3DFrameWriter(tmp_path / "r.c3d", labels=("a",), rate_hz=100.0)
    with pytest.raises(ViconFileError, match="no frames"):
        w.close()
    assert list(tmp_path.iterdir()) == []
