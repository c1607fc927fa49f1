"""Tests of the motion corpus split, the evaluation protocols and the skipped-frame rule."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mocaprig.cli import main
from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.democap.checkpoint import DEFAULT_CHECKPOINT, Checkpoint, load_checkpoint
from mocaprig.process.democap.commands import PROTOCOL_CHOICES
from mocaprig.process.democap.config import DemocapConfig
from mocaprig.process.democap.corpus import (
    ACTIVITIES,
    CORPUS_SPLITS,
    load_split,
    read_corpus_clips,
    subject_of,
)
from mocaprig.process.democap.dataset import make_pool, make_sample, simulate_sample
from mocaprig.process.democap.evaluate import (
    BODY_PERTURBATIONS,
    PROTOCOLS,
    evaluate,
    leave_one_activity_out,
    off_model,
    perturbed,
    trained_observation_jitter,
    unseen_real,
)
from mocaprig.process.democap.infer import DemocapPredictor
from mocaprig.process.democap.model import build_network
from mocaprig.process.democap.simdata import (
    Camera,
    ObservationModel,
    PoseFrames,
    in_frustum,
    merge_views,
    observe,
    sample_rig,
)
from mocaprig.process.democap.train import TrainOptions, train

needs_ckpt = pytest.mark.skipif(
    not DEFAULT_CHECKPOINT.is_file(), reason="the committed lite checkpoint is absent"
)


def _moved(take: PoseFrames, offset_m: tuple[float, float, float]) -> PoseFrames:
    d = np.asarray(offset_m)
    return replace(
        take,
        markers_m=take.markers_m + d,
        joints_m=take.joints_m + d,
        caps_a_m=take.caps_a_m + d,
        caps_b_m=take.caps_b_m + d,
    )


def _untrained(cfg: DemocapConfig, trained: list[str] | None = None) -> DemocapPredictor:
    ck = Checkpoint(config=cfg, model=build_network(cfg), train_motions=trained or [])
    return DemocapPredictor(ck, rotations=1)


# ---------------------------------------------------------------------------- the split table


def test_committed_split_is_by_subject_and_tags_every_clip() -> None:
    table = load_split()
    assert len(table.clips) == 44
    assert [len(table.in_split(s)) for s in CORPUS_SPLITS] == [27, 6, 11]
    subjects = [set(table.subjects(s)) for s in CORPUS_SPLITS]
    assert subjects == [{1, 5, 6, 9}, {3, 8}, {2, 7}]
    assert all(c.activity in ACTIVITIES for c in table.clips)
    assert set(table.activities()) == set(ACTIVITIES)
    assert subject_of("cmu_05_02") == 5
    # the test split holds activities the training split never shows
    train_acts = {c.activity for c in table.in_split("train")}
    assert {"jump", "strike", "everyday"} <= {c.activity for c in table.in_split("test")}
    assert not {"jump", "strike", "everyday"} & train_acts


def test_split_table_names_every_corpus_file(shared_data: Path) -> None:
    files = {p.stem for p in (shared_data / "motion" / "corpus").glob("*.bvh")}
    assert files == {c.name for c in load_split().clips}


def test_split_table_refuses_a_subject_in_two_splits(tmp_path: Path) -> None:
    bad = tmp_path / "split.toml"
    bad.write_text(
        'format_version = 1\n[train]\ncmu_01_01 = "walk"\n[validation]\ncmu_03_01 = "walk"\n'
        '[test]\ncmu_01_06 = "walk"\n',
        encoding="utf-8",
    )
    with pytest.raises(ValidationError, match="subject 1 is in both"):
        load_split(bad)
    bad.write_text(
        'format_version = 1\n[train]\ncmu_01_01 = "yoga"\n[validation]\ncmu_03_01 = "walk"\n'
        '[test]\ncmu_02_01 = "walk"\n',
        encoding="utf-8",
    )
    with pytest.raises(ValidationError, match="activity 'yoga'"):
        load_split(bad)
    with pytest.raises(ValidationError, match="cannot be read"):
        load_split(tmp_path / "missing.toml")
    with pytest.raises(ValidationError, match=r"lacks cmu_02_01\.bvh"):
        read_corpus_clips(tmp_path, load_split().in_split("test")[:1])


def test_protocol_choices_match_the_evaluation() -> None:
    assert PROTOCOL_CHOICES == PROTOCOLS


# ------------------------------------------------------------------ observation model, skips


def test_validation_and_test_streams_use_different_bodies() -> None:
    val = make_pool(0, "validation", takes=3, seconds=0.3)
    test = make_pool(0, "test", takes=3, seconds=0.3)
    for v in val:
        for t in test:
            assert not np.allclose(v.caps_radius_m, t.caps_radius_m)


def test_observation_model_knobs_move_the_cloud() -> None:
    take = make_pool(0, "test", takes=1, seconds=0.3)[0]

    def points(model: ObservationModel) -> int:
        rng = np.random.default_rng(3)
        views, _ = observe(take, 0, sample_rig(rng), rng, model=model)
        return int(merge_views(views).shape[0])

    nominal = points(ObservationModel())
    assert points(ObservationModel(detection=0.0, strays=0.0)) == 0
    assert points(ObservationModel(detection=0.5)) < nominal
    assert points(ObservationModel(strays=3.0)) > nominal
    with pytest.raises(ValidationError, match="noise"):
        ObservationModel(noise=-1.0)
    with pytest.raises(ValidationError, match="occlusion"):
        ObservationModel(occlusion=2.0)


def test_in_frustum_is_the_cameras_view() -> None:
    cams = sample_rig(np.random.default_rng(0))
    pts = np.array([[0.0, 0.0, 0.9], [0.0, 0.0, 6.0], [9.0, 0.0, 0.9]])
    seen = in_frustum(pts, cams)
    assert seen.shape == (4, 3)
    assert seen[:, 0].all()
    assert not seen[:, 1].any()
    assert not seen[:, 2].all()


def test_in_frustum_uses_each_cameras_principal_point_and_image_size() -> None:
    cam = Camera(centre_m=np.zeros(3), r_cw=np.eye(3), focal_px=600.0)
    # 1 m ahead, 0.8 m to the right: u = 424 + 480 = 904 px, past the simulated 848
    right = np.array([[0.8, 0.0, 1.0]])
    assert not in_frustum(right, [cam]).any()
    wide = replace(cam, principal_px=(640.0, 360.0), size_px=(1280, 720))
    assert in_frustum(right, [wide]).all()  # u = 1120 of 1280
    # the principal point moves the view: cx = 100 puts x = -0.2 m at u = -20
    left = np.array([[-0.2, 0.0, 1.0]])
    assert in_frustum(left, [cam]).all()
    assert not in_frustum(left, [replace(cam, principal_px=(100.0, 240.0))]).any()


def test_a_frame_out_of_view_is_skipped_and_counted(tiny_config: DemocapConfig) -> None:
    take = make_pool(0, "test", takes=1, seconds=0.5)[0]
    far = _moved(take, (30.0, 0.0, 0.0))  # outside the capture box: no point survives
    rng = np.random.default_rng(0)
    assert simulate_sample(far, 0, rng, augment=False) is None
    with pytest.raises(ProcessingError, match="fewer than 2 points"):
        make_sample(far, 0, rng, augment=False)
    pred = _untrained(tiny_config)
    rep = evaluate(pred, frames_per_take=3, pool=[take, far])
    assert rep.frames_requested == 6
    assert rep.skipped_frames == 3
    assert rep.metrics.frames == 3
    with pytest.raises(ProcessingError, match="none of the 3 frames"):
        evaluate(pred, frames_per_take=3, pool=[far])


def test_figures_inside_the_volume(tiny_config: DemocapConfig) -> None:
    take = make_pool(0, "test", takes=1, seconds=0.5)[0]
    aside = _moved(take, (1.9, 0.0, 0.0))  # in the capture box, pelvis out of some views
    pred = _untrained(tiny_config)
    rep = evaluate(pred, frames_per_take=4, pool=[take])
    assert rep.inside_share == 1.0
    assert rep.inside_metrics is not None
    assert rep.inside_metrics.mpjpe_mm == pytest.approx(rep.metrics.mpjpe_mm)
    mixed = evaluate(pred, frames_per_take=4, pool=[take, aside])
    assert mixed.skipped_frames == 0
    assert mixed.inside_metrics is not None
    assert 0.5 <= mixed.inside_share < 1.0
    assert mixed.inside_metrics.frames == round(8 * mixed.inside_share)
    d = mixed.to_dict()
    assert d["inside_volume"]["share"] == mixed.inside_share
    assert d["skipped_frames"] == 0


# ------------------------------------------------------------------------- corpus protocols


def _small_split(tmp_path: Path) -> Path:
    path = tmp_path / "split.toml"
    path.write_text(
        'format_version = 1\n[train]\ncmu_09_06 = "run"\n[validation]\ncmu_08_01 = "walk"\n'
        '[test]\ncmu_02_03 = "run"\ncmu_07_12 = "walk"\n',
        encoding="utf-8",
    )
    return path


@pytest.mark.slow
def test_unseen_real_flags_and_leaves_out_trained_clips(
    shared_data: Path, tmp_path: Path, tiny_config: DemocapConfig
) -> None:
    corpus = shared_data / "motion" / "corpus"
    table = load_split(_small_split(tmp_path))
    pred = _untrained(tiny_config, trained=["cmu_07_12", "cmu_09_06"])
    res = unseen_real(pred, corpus, split=table, frames_per_clip=2)
    assert res.trained_clips == ("cmu_07_12",)
    assert res.clips == ("cmu_02_03",)
    assert res.report is not None
    assert set(res.report.metrics.per_action_mm) == {"cmu_02_03"}
    d = res.to_dict()
    assert d["protocol"] == "unseen-real"
    assert "cmu_07_12" in d["note"]
    om = off_model(pred, corpus, split=table, frames_per_clip=2)
    assert om.protocol == "off-model"
    assert om.clips == ("cmu_02_03",)
    assert "does not mirror" in om.holds_out
    loao = {
        r.label: r for r in leave_one_activity_out(pred, corpus, split=table, frames_per_clip=1)
    }
    assert set(loao) == {"walk", "run"}
    # run: cmu_09_06 (train split) was trained on, so the activity was seen; its other clip
    # is still measured; walk: the only non-validation clip was trained on
    assert loao["run"].trained_on
    assert loao["run"].clips == ("cmu_02_03",)
    assert loao["walk"].report is None
    assert loao["walk"].trained_clips == ("cmu_07_12",)


@pytest.mark.slow
def test_training_takes_corpus_clips_and_validates_on_its_own_split(
    shared_data: Path, tmp_path: Path, tiny_config: DemocapConfig
) -> None:
    corpus = shared_data / "motion" / "corpus"
    table = load_split(_small_split(tmp_path))
    train_clips = tuple(read_corpus_clips(corpus, table.in_split("train")))
    val_clips = tuple(read_corpus_clips(corpus, table.in_split("validation")))
    opts = TrainOptions(
        epochs=1,
        seed=0,
        takes=1,
        threads=1,
        corpus=train_clips,
        corpus_subjects=1,
        validation_motions=val_clips,
    )
    out = tmp_path / "c.pt"
    ck = train(out, opts, config=tiny_config)
    assert ck.train_motions == ["cmu_09_06"]
    hist = load_checkpoint(out).history[-1]
    assert hist["val_corpus_mpjpe_mm"] > 0
    assert hist["val_mpjpe_mm"] > 0
    with pytest.raises(ValidationError, match="both trained on and in the validation set"):
        train(
            tmp_path / "d.pt",
            replace(opts, validation_motions=train_clips),
            config=tiny_config,
        )


# ----------------------------------------------------------------------------------- the CLI


@needs_ckpt
@pytest.mark.slow
def test_perturbed_figures_say_where_their_scales_lie_against_training_jitter(
    tiny_config: DemocapConfig,
) -> None:
    ck = Checkpoint(
        config=tiny_config,
        model=build_network(tiny_config),
        history=[{"observation_jitter": 0.0}, {"observation_jitter": 0.3}],
    )
    assert trained_observation_jitter(ck) == pytest.approx(0.3)
    pred = DemocapPredictor(ck, rotations=1, solve=False)
    res = perturbed(pred, frames_per_take=1, scales=(0.5, 0.8), bodies=False)
    notes = {r.label: r.note for r in res}
    assert "[0.7, 1.3]" in notes["detection x0.5"]
    assert "every moved scale lies outside it" in notes["detection x0.5"]
    assert "inside it for detection" in notes["detection x0.8"]
    assert "inside it for noise, occlusion, strays:" in notes["all harder"]
    assert "inside it for detection:" in notes["all easier"]
    plain = _untrained(tiny_config)
    assert trained_observation_jitter(plain.checkpoint) == 0.0


def test_cli_eval_perturbed_labels_each_figure(capsys: pytest.CaptureFixture[str]) -> None:
    # Only the labels and the budget are checked here, not the accuracy, so the network runs
    # alone: the solve would add a minute on these 84 frames (its figures: docs/democap.md).
    args = ["democap", "eval", "--protocol", "perturbed", "--frames", "1", "--no-solve"]
    assert main([*args, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["protocol"] == "perturbed"
    labels = [r["label"] for r in out["results"]]
    assert labels[:2] == ["detection x0.5", "detection x1.5"]
    assert labels[8:10] == ["all harder", "all easier"]
    assert labels[10:] == [label for label, _ in BODY_PERTURBATIONS]
    assert len(labels) == 14
    assert all(r["frames"] + r["skipped_frames"] == 6 for r in out["results"])
    assert all("share" in r["inside_volume"] for r in out["results"])
    bad = ["democap", "eval", "--protocol", "perturbed", "--all-cameras", "--frames", "1"]
    assert main(bad) != 0
    assert "--all-cameras" in capsys.readouterr().err


@needs_ckpt
def test_cli_eval_in_distribution_is_labelled(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["democap", "eval", "--frames", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["protocol"] == "in-distribution"
    assert out["label"] == "in-distribution"
    assert out["frames"] == 6
    assert out["inside_volume"]["share"] == 1.0
    assert out["results"][0]["budget"] == {"frames_per_take": 1, "subjects": 1, "seed": 0}
    assert out["solve"] is True
    assert main(["democap", "eval", "--frames", "1", "--no-solve", "--json"]) == 0
    raw = json.loads(capsys.readouterr().out)
    assert raw["solve"] is False
    assert raw["frames"] == 6
    assert raw["mpjpe_mm"] != out["mpjpe_mm"]


@pytest.mark.slow
@needs_ckpt
def test_cli_eval_unseen_real(shared_data: Path, capsys: pytest.CaptureFixture[str]) -> None:
    corpus = shared_data / "motion" / "corpus"
    args = ["democap", "eval", "--protocol", "unseen-real", "--corpus", str(corpus)]
    # the labels and the split (the accuracy tests below run the solve)
    assert main([*args, "--frames", "1", "--no-solve", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["protocol"] == "unseen-real"
    assert len(out["clips"]) == 11
    assert out["trained_clips"] == []
    assert out["frames"] + out["skipped_frames"] == 11
    assert out["mpjpe_mm"] > 0


# The committed checkpoint (449 epochs, the corpus's train split in the last 260) on these
# small unseen-real sets (11 test clips x 4 frames, seeds 11-13, 2026-12-07), inside the rig's
# view (81-84 % of the frames), with the skeleton solve (the default): 10.2 / 9.8 / 10.7 mm,
# PCK@50 0.995 / 0.997 / 0.987. The network alone measured 46.2 / 50.9 / 45.3 mm, 0.76 / 0.72
# / 0.73 (the 189-epoch one, trained on simulation only: 63.8 / 66.6 mm on seeds 11 / 12; an
# earlier solve with the 377-epoch network, as this test first measured it: 19.6 / 16.9 /
# 15.9 mm). The bound leaves about
# 20 % over the worst, so a broken solve (or a network that gives it bad starts) fails.
@pytest.mark.slow
@needs_ckpt
@pytest.mark.parametrize("seed", [11, 12, 13])
def test_committed_lite_model_accuracy_on_unseen_real_motion(shared_data: Path, seed: int) -> None:
    res = unseen_real(
        DemocapPredictor(), shared_data / "motion" / "corpus", frames_per_clip=4, seed=seed
    )
    assert res.trained_clips == ()
    assert res.report is not None
    inside = res.to_dict()["inside_volume"]
    assert inside["share"] > 0.7
    assert inside["mpjpe_mm"] < 13.0
    assert inside["pck50"] > 0.97


def test_cli_train_refuses_an_unknown_held_out_activity(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "x.pt"
    args = ["democap", "train", "--out", str(out), "--epochs", "1", "--hold-out-activity", "yoga"]
    assert main(args) != 0
    assert "yoga" in capsys.readouterr().err
    both = ["democap", "train", "--out", str(out), "--no-corpus", "--corpus", str(tmp_path)]
    assert main([*both, "--epochs", "1"]) != 0
    assert not out.exists()
