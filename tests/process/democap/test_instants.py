"""Rig instants: the online grouper and the whole-recording grouping are one rule."""

from __future__ import annotations

import numpy as np
import pytest

from mocaprig.errors import ValidationError
from mocaprig.process.democap.instants import InstantGrouper, group_instants

PERIOD = 33_333_333


def _rig(seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    base = 1_000_000_000 + PERIOD * np.arange(40, dtype=np.int64)
    out = {}
    for cam in ("d415/a", "d415/b", "d415/c"):
        t = base + rng.integers(-3_000_000, 3_000_000, base.size)
        keep = rng.random(base.size) > 0.1  # dropped frames
        out[cam] = np.sort(t[keep])
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_online_grouping_of_interleaved_frames_equals_the_whole_recording_grouping(
    seed: int,
) -> None:
    ref = _rig(seed)
    batch = group_instants(ref, ref)
    grouper: InstantGrouper[int] = InstantGrouper(sorted(ref), batch.period_ns)
    # A live rig delivers the cameras' frames interleaved, each camera in its own order.
    arrivals = sorted((int(t), c) for c, ts in ref.items() for t in ts)
    rng = np.random.default_rng(seed)
    jittered = sorted(arrivals, key=lambda a: a[0] + int(rng.integers(0, 20_000_000)))
    per_cam: dict[str, list[int]] = {c: [] for c in ref}
    for t, c in jittered:
        per_cam[c].append(t)
    online = []
    cursor = dict.fromkeys(ref, 0)
    for _, c in jittered:  # keep each camera's order, interleave across cameras
        t = per_cam[c][cursor[c]]
        cursor[c] += 1
        online.extend(grouper.push(c, t, t, t))
    online.extend(grouper.flush())
    assert [g.instant for g in online] == list(batch.instants)
    assert all(g.items == dict(g.instant.frames) for g in online)


def test_a_silent_camera_holds_instants_back_only_for_max_lag() -> None:
    grouper: InstantGrouper[str] = InstantGrouper(
        ["d415/a", "d415/b"], PERIOD, max_lag_ns=3 * PERIOD
    )
    done = []
    for k in range(10):  # d415/b never delivers
        done.extend(grouper.push("d415/a", k * PERIOD, k * PERIOD, f"a{k}"))
    assert [g.items["d415/a"] for g in done] == [f"a{k}" for k in range(6)]
    assert [g.items["d415/a"] for g in grouper.flush()] == ["a6", "a7", "a8", "a9"]


def test_the_grouper_refuses_unknown_cameras_and_frames_out_of_order() -> None:
    grouper: InstantGrouper[None] = InstantGrouper(["d415/a"], PERIOD)
    grouper.push("d415/a", 100, 100, None)
    with pytest.raises(ValidationError, match="out of order"):
        grouper.push("d415/a", 50, 50, None)
    with pytest.raises(ValidationError, match="not one of"):
        grouper.push("d415/z", 200, 200, None)
    with pytest.raises(ValidationError, match="period"):
        InstantGrouper(["d415/a"], 0)
