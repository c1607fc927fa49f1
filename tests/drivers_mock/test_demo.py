"""The demo's DeMoCap skeleton figure and report lines (the demo itself runs in
``tests/e2e/test_demo.py``)."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
import pytest

from mocaprig.drivers_mock.commands import _unseen_real_line
from mocaprig.drivers_mock.demo import SKELETON_FIGURE, _skeleton_figure
from mocaprig.process.body import DEMOCAP_JOINTS


def test_skeleton_figure_is_written_for_a_replay_with_a_missing_joint(tmp_path: Path) -> None:
    rng = np.random.default_rng(11)
    n = 12
    truth = rng.normal([0.0, 0.0, 1.0], 0.4, (n, len(DEMOCAP_JOINTS), 3))
    pred = truth + rng.normal(0.0, 0.03, truth.shape)
    pred[4, 2] = np.nan  # a joint the network did not give
    t_ns = np.arange(n, dtype=np.int64) * 100_000_000 + 5 * 10**9
    path = _skeleton_figure(tmp_path / SKELETON_FIGURE, t_ns, pred, truth, mpjpe_mm=50.0)
    assert path == tmp_path / SKELETON_FIGURE
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert path.stat().st_size > 20_000


def _unseen(inside_mpjpe_mm: float | None) -> dict[str, object]:
    return {
        "protocol": "unseen-real",
        "config": "lite",
        "clips": ["cmu_02_01", "cmu_07_12"],
        "num_cameras": 4,
        "rotations": 3,
        "frames": 16,
        "mpjpe_mm": 51.25,
        "pck50": 0.7,
        "inside_volume": {
            "frames": 0 if inside_mpjpe_mm is None else 12,
            "share": 0.0 if inside_mpjpe_mm is None else 0.75,
            "mpjpe_mm": inside_mpjpe_mm,
            "pck50": None if inside_mpjpe_mm is None else 0.8,
        },
    }


def test_demo_text_names_the_unseen_real_protocol_and_both_frame_sets() -> None:
    line = _unseen_real_line(_unseen(44.94))
    assert "[unseen-real]" in line
    assert "2 real clips of unseen performers" in line
    assert "inside the view (75 % of frames) MPJPE 44.9 mm, PCK@50 80.0 %" in line
    assert "all frames 51.2 mm, 70.0 %" in line
    assert "no frame inside the view" in _unseen_real_line(_unseen(None))
    assert "off-model" not in line
    off = _unseen(30.04)
    off["solve"] = True
    off_model: dict[str, object] = {**_unseen(38.06), "protocol": "off-model"}
    off["off_model"] = off_model
    lines = _unseen_real_line(off).splitlines()
    assert "skeleton solve" in lines[0]
    assert "[off-model]" in lines[1]
    assert "does not mirror" in lines[1]
    assert "MPJPE 38.1 mm" in lines[1]
    assert len(lines) == 2
    off_model["subject_calibrated"] = {**_unseen(25.04), "rounds": 1}
    lines = _unseen_real_line(off).splitlines()
    assert "subject calibrated" in lines[2]
    assert "MPJPE 25.0 mm" in lines[2]


def test_demo_text_says_why_the_unseen_real_figure_is_missing() -> None:
    assert "no motion corpus" in _unseen_real_line({})
    assert "clip cmu_02_01 is missing" in _unseen_real_line({"error": "clip cmu_02_01 is missing"})


@pytest.mark.slow
def test_unseen_real_stage_draws_each_figures_frames(
    shared_data: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from mocaprig.drivers_mock import demo
    from mocaprig.process.democap import infer

    # the stage's bookkeeping, not its accuracy: one frame a clip, the network alone
    monkeypatch.setattr(demo, "UNSEEN_REAL_FRAMES", 1)
    monkeypatch.setattr(infer, "DemocapPredictor", partial(infer.DemocapPredictor, solve=False))
    calls: dict[str, list[tuple[int, int]]] = {}

    def stage(label: str) -> Callable[[int, int], None]:
        return lambda done, total: calls.setdefault(label, []).append((done, total))

    got = demo._unseen_real_figures(shared_data / "motion" / "corpus", 0, stage)
    assert list(calls) == ["democap unseen-real", "democap off-model"]
    for label, frames in (
        ("democap unseen-real", got["frames"]),
        ("democap off-model", got["off_model"]["frames"]),
    ):
        assert calls[label][0] == (0, frames)
        assert calls[label][-1] == (frames, frames)
