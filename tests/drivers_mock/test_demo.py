"""The demo's DeMoCap skeleton figure (the demo itself runs in ``tests/e2e/test_demo.py``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

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
