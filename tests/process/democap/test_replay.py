"""DeMoCap replay on a recording (``mocaprig democap run``): instants, outputs, accuracy.

One simulated session (4 s, seed 5, four D415s: the rig DeMoCap is trained for) is recorded,
calibrated against its Vicon trial and replayed once for the whole module (~40 s on the shared
2-core machine); the checks read the outputs back with independent readers (ezc3d, the mcap
reader with the protobuf decoder) and score the joints against the simulated truth.
"""

from __future__ import annotations

import csv
import dataclasses
import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from mocaprig.calib.calibration import Calibration
from mocaprig.cli import main
from mocaprig.drivers_mock.truth import Truth, democap_truth_at
from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body import DEMOCAP_JOINTS, DEMOCAP_PARENTS, MARKER_NAMES
from mocaprig.process.democap import DemocapPredictor
from mocaprig.process.democap.evaluate import evaluate
from mocaprig.process.democap.replay import (
    CLOUD_TOPIC,
    JOINTS_TOPIC,
    MARKERS_TOPIC,
    METADATA_NAME,
    ReplayResult,
    fit_subject,
    group_instants,
    join_spans,
    output_paths,
    plan_replay,
    replay_span,
    run_replay,
    score_replay,
)
from mocaprig.process.democap.subject import load_subject
from tests.conftest import CalibratedSession

LABELS = [*MARKER_NAMES, *(f"J_{j}" for j in DEMOCAP_JOINTS)]


# ------------------------------------------------------------------------------ instants


def _times(n: int, period: int, start: int) -> np.ndarray:
    return start + period * np.arange(n, dtype=np.int64)


def test_group_instants_pairs_synchronised_frames_and_keeps_partial_instants() -> None:
    period = 33_333_333
    rng = np.random.default_rng(0)
    ref = {
        "d415/a": _times(10, period, 1_000_000_000),
        "d415/b": np.delete(_times(10, period, 1_000_000_000), 4),  # dropped frame 4
        "d415/c": _times(10, period, 1_000_000_000) + rng.integers(-2_000_000, 2_000_000, 10),
    }
    dev = {c: t - 77 for c, t in ref.items()}  # device clocks: any offset
    g = group_instants(dev, ref)
    assert abs(g.period_ns - period) < 3_000_000
    assert len(g.instants) == 10
    counts = [len(i.frames) for i in g.instants]
    assert counts == [3, 3, 3, 3, 2, 3, 3, 3, 3, 3]
    assert "d415/b" not in g.instants[4].frames
    assert g.instants[4].frames["d415/a"] == ref["d415/a"][4] - 77
    t = np.array([i.t_ref_ns for i in g.instants])
    assert np.all(np.abs(t - ref["d415/a"]) < 2_000_000)


def test_group_instants_splits_frames_a_third_of_a_period_apart() -> None:
    period = 33_333_333
    ref = {"d415/a": _times(5, period, 0), "d415/b": _times(5, period, period // 3)}
    g = group_instants(ref, ref)
    assert len(g.instants) == 10  # beyond the 1/4-period tolerance: not the same instant
    assert all(len(i.frames) == 1 for i in g.instants)
    assert len(group_instants(ref, ref, tolerance=0.4).instants) == 5


def test_group_instants_refuses_a_tolerance_of_half_a_period() -> None:
    with pytest.raises(ValidationError, match="tolerance"):
        group_instants({}, {}, tolerance=0.5)


def test_democap_parents_form_one_tree_rooted_at_the_hips() -> None:
    assert DEMOCAP_PARENTS[0] == -1
    assert all(0 <= p < j for j, p in enumerate(DEMOCAP_PARENTS) if j)
    assert DEMOCAP_JOINTS[DEMOCAP_PARENTS[DEMOCAP_JOINTS.index("RightArm")]] == "Spine2"


def test_democap_run_help_has_examples(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["democap", "run", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "examples:" in out
    assert "--overwrite" in out


# ------------------------------------------------------------------------------ a session


@dataclass(frozen=True)
class Replayed:
    session: Path
    calib: Path
    calibration: Calibration
    truth: Truth
    predictor: DemocapPredictor
    result: ReplayResult


@pytest.fixture(scope="module")
def replayed(
    tmp_path_factory: pytest.TempPathFactory, calibrated_session: CalibratedSession
) -> Iterator[Replayed]:
    """The shared calibrated session (4 s, seed 5, four D415s) and its replay."""
    cs = calibrated_session
    root = tmp_path_factory.mktemp("replay")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the network is ~10x slower with 2 threads on a busy 2-core box
    try:
        predictor = DemocapPredictor()
        (root / "out").mkdir()
        out = root / "out" / "results.mcap"
        result = run_replay(cs.session, cs.calib, out=out, predictor=predictor)
        yield Replayed(cs.session, cs.calib, cs.calibration, cs.truth, predictor, result)
    finally:
        torch.set_num_threads(threads)


@pytest.fixture
def keep_torch_threads() -> Iterator[None]:
    """``democap run`` sets torch's thread count (its --threads); restore it afterwards."""
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


@pytest.mark.slow
def test_spans_of_a_plan_join_into_the_whole_replay(replayed: Replayed, tmp_path: Path) -> None:
    # Every 7th instant, in two spans run in reverse order: what `mocaprig process` sends to
    # its workers. Each instant stands alone, so the joined result is the unsplit one.
    plan = plan_replay(replayed.session, replayed.calib, every=7)
    spans = plan.spans(len(plan.instants) // 2)
    parts = [
        replay_span(plan.span(a, b), replayed.calibration, predictor=replayed.predictor)
        for a, b in reversed(spans)
    ]
    joined = join_spans(plan, parts, outputs=output_paths(tmp_path / "r.mcap"))
    whole = replay_span(plan, replayed.calibration, predictor=replayed.predictor)
    assert len(parts) >= 2
    np.testing.assert_array_equal(joined.t_ref_ns, whole.t_ref_ns)
    np.testing.assert_array_equal(joined.t_ref_ns, replayed.result.t_ref_ns[::7])
    np.testing.assert_allclose(joined.joints_m, whole.joints_m, atol=1e-9)
    assert len(joined.clouds_m) == joined.instants
    with pytest.raises(ValidationError, match="do not cover"):
        join_spans(plan, parts[:1], outputs=output_paths(tmp_path / "r.mcap"))


@pytest.mark.slow
def test_replay_processes_every_synchronised_instant(replayed: Replayed) -> None:
    r = replayed.result
    assert len(r.cameras) == 4
    frames = min(r.frames_per_camera.values())
    assert frames >= 115  # 30 Hz for 4 s
    assert r.instants == r.instants_total == frames
    assert r.camera_histogram == {4: r.instants}
    assert r.skipped_instants == 0
    assert abs(r.period_ns - 33_333_333) < 100_000
    assert np.all(np.diff(r.t_ref_ns) > 0)
    assert 50 < r.mean_points < 250
    s = r.summary()
    assert s["instants_by_camera_count"] == {"4": r.instants}
    assert json.loads(json.dumps(s))["outputs"]["c3d"].endswith("results.c3d")


@pytest.mark.slow
def test_replay_c3d_reads_back_with_labels_and_one_frame_per_instant(replayed: Replayed) -> None:
    import ezc3d

    r = replayed.result
    c = ezc3d.c3d(str(r.outputs["c3d"]))
    labels = list(c["parameters"]["POINT"]["LABELS"]["value"])
    assert labels == LABELS
    pts = c["data"]["points"]
    assert pts.shape == (4, len(LABELS), r.instants)
    assert c["parameters"]["POINT"]["RATE"]["value"][0] == pytest.approx(30.0, abs=0.01)
    assert c["parameters"]["POINT"]["UNITS"]["value"] == ["mm"]
    hips = pts[:3, LABELS.index("J_Hips"), :].T
    np.testing.assert_allclose(hips, r.joints_m[:, 0] * 1e3, atol=0.01)


@pytest.mark.slow
def test_replay_csv_has_exact_times_and_mm_columns(replayed: Replayed) -> None:
    r = replayed.result
    with r.outputs["csv"].open(encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    m0 = MARKER_NAMES[0]
    assert rows[0][:4] == ["time_s", f"{m0}_x", f"{m0}_y", f"{m0}_z"]
    assert rows[0][-3:] == ["J_LeftToeBase_x", "J_LeftToeBase_y", "J_LeftToeBase_z"]
    assert len(rows) == r.instants + 1
    sec, frac = rows[1][0].split(".")
    assert int(sec) * 10**9 + int(frac) == r.t_ref_ns[0]
    head = rows[1][1 + 3 * len(MARKER_NAMES) : 4 + 3 * len(MARKER_NAMES)]
    np.testing.assert_allclose([float(v) for v in head], r.joints_m[0, 0] * 1e3, atol=0.001)


def _scene_messages(path: Path) -> dict[str, list[tuple[int, object]]]:
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    out: dict[str, list[tuple[int, object]]] = {}
    with path.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            assert schema is not None
            if channel.topic in ("/diagnostics", "/log"):
                continue  # the recorder's own streams (checked below)
            assert schema.name == "foxglove.SceneUpdate"
            out.setdefault(channel.topic, []).append((message.log_time, decoded))
    return out


@pytest.mark.slow
def test_replay_results_are_written_through_the_recorder_losing_nothing(
    replayed: Replayed,
) -> None:
    from mocaprig.acquire.recording import info

    r = replayed.result
    summary = info(r.outputs["mcap"])
    assert summary.drops_total == 0
    scene = [s for s in summary.streams if s.topic.startswith("/democap/")]
    assert sorted(s.messages for s in scene) == [r.instants] * 3
    # One time base in the file: the recorder's diagnostics lie on the reference clock too.
    assert summary.duration_s < (int(r.t_ref_ns[-1]) - int(r.t_ref_ns[0])) / 1e9 + 5.0


@pytest.mark.slow
def test_replay_mcap_has_one_scene_update_per_instant_and_channel(replayed: Replayed) -> None:
    from mcap.reader import make_reader

    r = replayed.result
    msgs = _scene_messages(r.outputs["mcap"])
    assert sorted(msgs) == sorted([MARKERS_TOPIC, JOINTS_TOPIC, CLOUD_TOPIC])
    for topic in msgs:
        assert [t for t, _ in msgs[topic]] == r.t_ref_ns.tolist()
    _, joints = msgs[JOINTS_TOPIC][0]
    (ent,) = joints.entities  # type: ignore[attr-defined]
    assert ent.frame_id == "vicon"
    assert ent.timestamp.ToNanoseconds() == r.t_ref_ns[0]
    meta = {kv.key: kv.value for kv in ent.metadata}
    assert meta["names"].split(",") == list(DEMOCAP_JOINTS)
    assert meta["cameras"] == "4"
    assert [t.text for t in ent.texts] == list(DEMOCAP_JOINTS)
    sphere = ent.spheres[3]
    p = [sphere.pose.position.x, sphere.pose.position.y, sphere.pose.position.z]
    np.testing.assert_allclose(p, r.joints_m[0, 3])
    (bones,) = ent.lines
    assert len(bones.points) == 2 * (len(DEMOCAP_JOINTS) - 1)
    _, markers = msgs[MARKERS_TOPIC][0]
    (ment,) = markers.entities  # type: ignore[attr-defined]
    assert len(ment.spheres) == len(MARKER_NAMES)
    assert {kv.key: kv.value for kv in ment.metadata}["names"].split(",") == list(MARKER_NAMES)
    with r.outputs["mcap"].open("rb") as fh:
        reader = make_reader(fh)
        meta_rec = {m.name: m.metadata for m in reader.iter_metadata()}
        atts = [a.name for a in reader.iter_attachments()]
    assert meta_rec[METADATA_NAME]["instants"] == str(r.instants)
    assert atts == ["calibration.toml"]


@pytest.mark.slow
def test_replay_cloud_lies_on_the_true_markers(replayed: Replayed) -> None:
    """Checkpoint-independent: the fused input points, put in the world by the calibration
    and on the Vicon clock by the clock mappings, sit on the true markers at those instants."""
    r = replayed.result
    clouds = _scene_messages(r.outputs["mcap"])[CLOUD_TOPIC]
    t = np.array([t for t, _ in clouds])
    true_m, _ = democap_truth_at(replayed.truth, t)
    dists = []
    for k, (_, upd) in enumerate(clouds):
        (ent,) = upd.entities  # type: ignore[attr-defined]
        pts = np.array(
            [[s.pose.position.x, s.pose.position.y, s.pose.position.z] for s in ent.spheres]
        )
        dists.append(np.linalg.norm(pts[:, None] - true_m[k][None], axis=-1).min(axis=1))
    d = np.concatenate(dists) * 1e3
    # Measured points lie on the marker's front (7 mm short of its centre), with D415 depth
    # noise (σ ≈ 15 mm at 2.5 m); measured on seed 5: median 15 mm, 67 % within 30 mm.
    assert np.median(d) < 25.0
    assert np.mean(d < 30.0) > 0.55


@pytest.mark.slow
def test_replay_joints_are_within_the_test_set_error_of_the_truth(replayed: Replayed) -> None:
    """The acceptance: the replayed joints are as close to the truth as the same checkpoint's
    joints on its held-out simulated test set (4 cameras), within a stated margin.

    Margin: replay MPJPE <= test-set MPJPE + 10 mm. The training data now model the measured
    clouds (simdata matched to this pipeline: ~130 points for 4 cameras, limb-depth tails,
    strays), so no distribution shift is allowed for; a wrong pose, clock or grouping costs far
    more (2 front cameras only: 157 mm with the earlier checkpoint). Measured with the
    committed lite checkpoint and the skeleton solve on seed 5: 5.8 mm replay (PCK@50 100 %)
    vs 10.4 mm test set (the network alone: 27.8 mm, 89 %, vs 44.0 mm); the replay is also
    held under 10 mm outright.
    """
    r = replayed.result
    true_m, true_j = democap_truth_at(replayed.truth, r.t_ref_ns)
    replay = score_replay(r, true_j, true_m)
    test_set = evaluate(replayed.predictor, seed=0, num_cameras=4, frames_per_take=10).metrics
    assert replay.frames == r.instants
    assert replay.mpjpe_mm <= test_set.mpjpe_mm + 10.0, (replay.mpjpe_mm, test_set.mpjpe_mm)
    assert replay.mpjpe_mm < 10.0


# ------------------------------------------------------------------------------ errors and CLI


@pytest.mark.slow
def test_replay_refuses_a_camera_missing_from_the_calibration(
    replayed: Replayed, tmp_path: Path
) -> None:
    cal = replayed.calibration
    gone = cal.cameras[1].name
    partial = dataclasses.replace(
        cal,
        cameras=tuple(c for c in cal.cameras if c.name != gone),
        clocks=tuple(k for k in cal.clocks if k.device != gone),
    )
    with pytest.raises(ProcessingError, match=rf"camera {gone} has no entry.*calibrate vicon"):
        run_replay(replayed.session, partial, out=tmp_path / "r.mcap")
    no_clock = dataclasses.replace(cal, clocks=tuple(k for k in cal.clocks if k.device != gone))
    with pytest.raises(ProcessingError, match=rf"camera {gone} has no clock mapping"):
        run_replay(replayed.session, no_clock, out=tmp_path / "r.mcap")
    assert not list(tmp_path.iterdir())


@pytest.mark.slow
@pytest.mark.usefixtures("keep_torch_threads")
def test_democap_run_command_prints_json_and_refuses_existing_outputs(
    replayed: Replayed, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "r.mcap"
    argv = [
        "democap", "run", str(replayed.session), "--calib", str(replayed.calib),
        "--out", str(out), "--c3d", str(tmp_path / "pose.c3d"), "--every", "4", "--json",
        "--no-solve",  # the command's outputs and refusals; the replay fixture runs the solve
    ]  # fmt: skip
    assert main(argv) == 0
    s = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert s["every"] == 4
    assert s["instants"] == -(-replayed.result.instants // 4)
    assert s["rate_hz"] == pytest.approx(7.5, abs=0.01)
    assert s["outputs"] == {
        "mcap": str(out),
        "c3d": str(tmp_path / "pose.c3d"),
        "csv": str(tmp_path / "r.csv"),
    }
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pose.c3d", "r.csv", "r.mcap"]
    before = out.stat().st_mtime_ns

    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "exists" in err
    assert "--overwrite" in err
    assert out.stat().st_mtime_ns == before
    assert main([*argv, "--overwrite"]) == 0


@pytest.mark.slow
@pytest.mark.usefixtures("keep_torch_threads")
def test_democap_subject_calibrates_the_actor_and_the_replay_solves_every_instant_as_them(
    replayed: Replayed, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    actor = tmp_path / "actor.json"
    argv = [
        "democap", "subject", str(replayed.session), "--calib", str(replayed.calib),
        "--out", str(actor), "--instants", "16", "--json",
    ]  # fmt: skip
    assert main(argv) == 0
    fit = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert fit["instants"] + fit["skipped_instants"] == 16
    assert fit["out"] == str(actor)
    # The simulated actor's true body: measured on seed 5, 1.556 m against 1.565 m, every
    # length within 1 cm (the head's: the top of the head carries no marker).
    shape = replayed.truth.meta["body_shape"]
    subject = load_subject(actor)
    assert subject.standing_height_m == pytest.approx(fit["standing_height_m"])
    assert abs(subject.standing_height_m - shape["height_m"]) < 0.03
    for k in ("shank_length_m", "thigh_length_m", "upper_arm_length_m", "forearm_length_m"):
        assert abs(subject.segment_lengths_m[k] - shape[k]) < 0.02, k
    assert main(argv) == 1  # the file exists
    assert "--overwrite" in capsys.readouterr().err

    # Every 4th instant solved as the subject: as close to the truth as frame by frame (seed
    # 5: 5.5 mm both; the markers 7.2 against 8.9 mm).
    r = run_replay(
        replayed.session,
        replayed.calib,
        out=tmp_path / "as_subject.mcap",
        every=4,
        predictor=DemocapPredictor(subject=subject),
    )
    assert r.subject_height_m == pytest.approx(subject.standing_height_m)
    true_m, true_j = democap_truth_at(replayed.truth, r.t_ref_ns)
    as_subject = score_replay(r, true_j, true_m)
    alone = replayed.result
    rows = np.flatnonzero(np.isin(alone.t_ref_ns, r.t_ref_ns))
    assert len(rows) == r.instants
    same = dataclasses.replace(
        alone,
        t_ref_ns=alone.t_ref_ns[rows],
        joints_m=alone.joints_m[rows],
        markers_m=alone.markers_m[rows],
    )
    frame_by_frame = score_replay(same, true_j, true_m)
    assert as_subject.mpjpe_mm < 10.0
    assert as_subject.mpjpe_mm < frame_by_frame.mpjpe_mm + 2.0

    # The command takes the file; without the solve it has nothing to hold.
    run = [
        "democap", "run", str(replayed.session), "--calib", str(replayed.calib),
        "--out", str(tmp_path / "cli.mcap"), "--every", "12", "--rotations", "1",
        "--subject", str(actor), "--json",
    ]  # fmt: skip
    assert main(run) == 0
    s = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert s["subject_height_m"] == pytest.approx(subject.standing_height_m)
    assert main([*run, "--no-solve", "--overwrite"]) == 1
    assert "--subject is used by the skeleton solve" in capsys.readouterr().err


@pytest.mark.slow
def test_a_subject_is_fitted_from_the_part_of_the_recording_asked_for(
    replayed: Replayed,
) -> None:
    with pytest.raises(ValidationError, match="end_s"):
        fit_subject(replayed.session, replayed.calib, start_s=2.0, end_s=1.0)
    with pytest.raises(ProcessingError, match=r"instants between 9 and inf s"):
        fit_subject(replayed.session, replayed.calib, start_s=9.0)
    first = plan_replay(replayed.session, replayed.calib).instants[0].t_ref_ns
    fit = fit_subject(replayed.session, replayed.calib, instants=4, start_s=1.0, end_s=1.5)
    assert fit.t_ref_ns.size == 4
    after_s = (fit.t_ref_ns - first) / 1e9
    assert after_s.min() >= 1.0
    assert after_s.max() <= 1.5
