"""Ground truth export: layout, round trip, refusal to overwrite."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mocaprig.drivers_mock.scenario import build_scenario
from mocaprig.drivers_mock.truth import read_truth, write_truth
from mocaprig.errors import RecordingError


@pytest.fixture(scope="module")
def world():
    return build_scenario("tpose", seed=4, seconds=3.0)


def test_truth_round_trip_matches_the_scenario(world, tmp_path) -> None:
    folder = write_truth(world, tmp_path, rate_hz=200.0)
    assert folder == tmp_path / "truth"
    truth = read_truth(tmp_path)
    assert truth.t_ns.dtype == np.int64
    assert truth.t_ns[0] == 0
    assert truth.t_ns[-1] == 3_000_000_000
    assert truth.t_ns.size == 601
    np.testing.assert_allclose(truth.markers_m, world.markers_m(truth.t_ns))
    np.testing.assert_allclose(truth.clapper_m, world.clapper_markers_m(truth.t_ns))
    assert truth.marker_names == world.marker_names
    assert len(truth.marker_names) == 53
    assert truth.joint_names[0] == "Hips"
    assert truth.joints_m.shape == (601, 26, 3)
    assert truth.clap_times_ns == world.clap_times_ns
    assert truth.clocks == dict(world.clocks)
    assert truth.seed == 4
    assert truth.scenario_name == "tpose"
    cam = truth.cameras["d415-0"]
    np.testing.assert_allclose(cam.K, world.camera("d415-0").K)
    np.testing.assert_allclose(cam.T_world_cam, world.camera_pose("d415-0"))


def test_scenario_json_states_units_frames_and_serials(world, tmp_path) -> None:
    write_truth(world, tmp_path, rate_hz=50.0)
    meta = json.loads((tmp_path / "truth" / "scenario.json").read_text())
    assert meta["units"]["length"].startswith("m")
    assert "OpenCV" in meta["frames"]["camera"]
    assert [d["role"] for d in meta["rig"]["d415"]] == ["master", "slave", "slave", "slave"]
    assert all(len(d["serial"]) == 12 for d in meta["rig"]["d415"])
    assert {c["name"] for c in meta["clocks"]} == {
        "davis",
        "d415-0",
        "d415-1",
        "d415-2",
        "d415-3",
        "vicon",
    }
    assert meta["software"].startswith("mocaprig")
    assert len(meta["markers"]["offsets_m"]) == 53


def test_write_truth_refuses_a_non_empty_folder(world, tmp_path) -> None:
    write_truth(world, tmp_path, rate_hz=50.0)
    with pytest.raises(RecordingError, match="not empty"):
        write_truth(world, tmp_path, rate_hz=50.0)
    write_truth(world, tmp_path, rate_hz=50.0, overwrite=True)


def test_read_truth_names_the_missing_files(tmp_path) -> None:
    with pytest.raises(RecordingError, match=r"truth\.npz"):
        read_truth(tmp_path)
