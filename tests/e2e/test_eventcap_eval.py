"""``mocaprig eventcap eval`` end to end: a simulated DAVIS take, EventCap and its baselines."""

from __future__ import annotations

import json

import pytest

from mocaprig.cli import main

#: The test here simulates a take and runs three methods on it: about a minute.
pytestmark = pytest.mark.slow


def test_eventcap_eval_scores_ours_and_both_baselines_on_the_same_frames(
    capsys: pytest.CaptureFixture[str],
) -> None:
    args = ["eventcap", "eval", "--scenario", "karate", "--seconds", "3", "--start", "2.5"]
    code = main([*args, "--seed", "4", "--batches", "2", "--json"])
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert out["detections"] == "synthetic"
    assert out["batches"] == 2
    assert "karate seed 4" in out["take"]
    for method in ("ours", "linear", "all"):
        e = out[method]
        assert e["frames"] == 9  # every 10th 1 kHz frame of 2 × 40 ms, both ends included
        # A 1.7–1.8 m actor 3 m away: errors in mm, far below the body's size.
        assert 0 < e["ae_mm"] < 200
        assert e["ae_mm"] <= e["mpjpe_mm"] + 1e-6
    assert out["ae_ratio_to_linear"] == pytest.approx(
        out["ours"]["ae_mm"] / out["linear"]["ae_mm"], rel=1e-2
    )
    # Events plus 25 fps frames are a fraction of 1000 fps frames (paper: 2.02 vs 58.59 MB/s).
    assert 0 < out["size_sec_mb"] < 0.2 * out["size_sec_reference_mb"]
    assert set(out["stage_seconds_per_batch"]) >= {"edi", "tracking", "batch_fit"}
