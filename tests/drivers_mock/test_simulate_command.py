"""Acceptance: `mocaprig simulate` writes a C3D that matches the exported truth."""

from __future__ import annotations

import json

import ezc3d
import numpy as np
import pytest

from mocaprig.cli import main
from mocaprig.drivers_mock.scenario import build_scenario
from mocaprig.drivers_mock.truth import read_truth


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "d"
    assert (
        main(
            [
                "-q",
                "simulate",
                "--seconds",
                "5",
                "--out",
                str(out),
                "--seed",
                "21",
                "--devices",
                "none",
            ]
        )
        == 0
    )
    return out


def test_simulate_writes_a_c3d_matching_the_truth_within_the_noise(simulated) -> None:
    c3d = ezc3d.c3d(str(simulated / "vicon" / "session.c3d"))
    params = c3d["parameters"]
    labels = params["POINT"]["LABELS"]["value"]
    assert len(labels) == 55
    assert sum(lab.startswith("actor:") for lab in labels) == 53
    assert labels[-2:] == ["clapper:TOP", "clapper:BOTTOM"]
    assert params["POINT"]["RATE"]["value"][0] == 120.0
    assert params["POINT"]["UNITS"]["value"] == ["mm"]

    truth = read_truth(simulated)
    # Frame times through the Vicon clock, from the C3D's own start field.
    low, high = (int(v) for v in params["TRIAL"]["ACTUAL_START_FIELD"]["value"])
    field = (low & 0xFFFF) + (high << 16)
    frames = c3d["data"]["points"].shape[2]
    device_ns = np.round((field - 1 + np.arange(frames)) * 1e9 / 120.0).astype(np.int64)
    t_ns = truth.clocks["vicon"].session_ns(device_ns, unit_ns=1)
    assert 4.5 < frames / 120.0 < 5.0
    # The world rebuilt from the truth's seed, sampled at those instants.
    world = build_scenario(truth.scenario_name, seed=truth.seed, seconds=truth.seconds)
    w = world.sample(t_ns)
    expected_mm = np.concatenate([w.markers_m, w.clapper_m], axis=1) * 1000.0
    measured_mm = np.transpose(c3d["data"]["points"][:3], (2, 1, 0))
    err = measured_mm - expected_mm
    rms_per_axis = np.sqrt(np.nanmean(err**2))
    assert 0.3 < rms_per_axis < 0.8
    gaps = np.isnan(measured_mm[..., 0])
    assert 0.003 < gaps.mean() < 0.03
    residuals = c3d["data"]["meta_points"]["residuals"][0].T
    np.testing.assert_array_equal(residuals < 0, gaps)
    # The 1 kHz truth agrees with the world at its own samples.
    np.testing.assert_allclose(truth.markers_m[::250], world.markers_m(truth.t_ns[::250]))
    # And the stored Vicon truth has the same frame times.
    assert truth.vicon is not None
    np.testing.assert_array_equal(truth.vicon.frame_t_ns, t_ns)


def test_clapperboard_distance_in_the_c3d_is_minimal_at_the_claps(simulated) -> None:
    c3d = ezc3d.c3d(str(simulated / "vicon" / "session.c3d"))
    truth = read_truth(simulated)
    assert truth.vicon is not None
    pts = np.transpose(c3d["data"]["points"][:3], (2, 1, 0))[:, -2:] / 1000.0
    d = np.linalg.norm(pts[:, 0] - pts[:, 1], axis=-1)
    contact = truth.meta["clapperboard"]["contact_distance_m"]
    t = truth.vicon.frame_t_ns
    for tc in truth.clap_times_ns:
        # Open during the last 300 ms before contact (gaps are NaN and skipped) ...
        before = d[(t > tc - 300_000_000) & (t < tc - 17_000_000)]
        assert np.nanmin(before) > contact + 0.003
        # ... and closed, at the contact distance, for 100 ms after it.
        after = d[(t >= tc) & (t < tc + 100_000_000)]
        np.testing.assert_allclose(after[~np.isnan(after)], contact, atol=0.003)


def test_simulate_json_reports_paths_seed_and_claps(tmp_path, capsys) -> None:
    out = tmp_path / "j"
    assert (
        main(
            [
                "-q",
                "simulate",
                "--scenario",
                "tpose",
                "--seconds",
                "3",
                "--out",
                str(out),
                "--json",
                "--devices",
                "none",
            ]
        )
        == 0
    )
    report = json.loads(capsys.readouterr().out)
    assert report["seed"] == 0
    assert report["seconds"] == 3.0
    assert report["body_markers"] == 53
    assert report["clapper_markers"] == 2
    assert report["vicon_rate_hz"] == 120.0
    assert len(report["clap_times_ns"]) == 2
    assert (out / "vicon" / "session.c3d").is_file()
    assert (out / "truth" / "truth.npz").is_file()


def test_simulate_refuses_a_non_empty_folder(tmp_path, capsys) -> None:
    (tmp_path / "keep.txt").write_text("x")
    assert main(["-q", "simulate", "--seconds", "3", "--out", str(tmp_path)]) == 1
    assert "not empty" in capsys.readouterr().err


def test_simulate_refuses_a_too_short_session(tmp_path, capsys) -> None:
    assert main(["-q", "simulate", "--seconds", "1", "--out", str(tmp_path / "s")]) == 1
    assert "too short" in capsys.readouterr().err


def test_simulate_help_has_examples(capsys) -> None:
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    out = capsys.readouterr().out
    assert "examples:" in out
    assert "--scenario" in out
    assert "karate" in out
