"""Inference: the rotation ensemble and the folded inference copy of the network."""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Callable

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from mocaprig.errors import ValidationError
from mocaprig.process.democap.checkpoint import Checkpoint
from mocaprig.process.democap.config import DemocapConfig, Variant
from mocaprig.process.democap.dataset import make_pool, make_sample
from mocaprig.process.democap.infer import DemocapPredictor, ensemble_rotations
from mocaprig.process.democap.model import build_network
from mocaprig.process.democap.simdata import Camera, sample_rig


def _checkpoint(cfg: DemocapConfig) -> Checkpoint:
    torch.manual_seed(0)
    net = build_network(cfg)
    gen = torch.Generator().manual_seed(1)
    for mod in net.modules():  # running statistics far from (0, 1), so folding them matters
        if isinstance(mod, torch.nn.BatchNorm2d):
            n = mod.num_features
            mod.running_mean = torch.randn(n, generator=gen) * 0.5
            mod.running_var = torch.rand(n, generator=gen) + 0.5
            mod.weight.data.copy_(torch.rand(n, generator=gen) + 0.5)
    return Checkpoint(config=cfg, model=net.eval())


def _cloud() -> np.ndarray:
    pool = make_pool(0, "test", takes=1, seconds=0.5)
    return make_sample(pool[0], 3, np.random.default_rng(0), augment=False, size_px=64).raw_m


def _turned(pred: DemocapPredictor, cloud: np.ndarray, deg: float) -> np.ndarray:
    """Single-shot joints of the cloud turned by ``deg`` about the vertical, turned back."""
    centre = cloud.mean(axis=0)
    r = Rotation.from_euler("z", deg, degrees=True).as_matrix()
    joints = pred.predict((cloud - centre) @ r.T + centre).joints_m
    return np.asarray((joints - centre) @ r + centre)


def test_ensemble_turns_are_spread_over_half_a_turn() -> None:
    turns = ensemble_rotations(3)
    np.testing.assert_allclose(turns[0], np.eye(3))
    angles = [Rotation.from_matrix(r).magnitude() for r in turns]
    np.testing.assert_allclose(np.rad2deg(angles), [0.0, 60.0, 120.0], atol=1e-9)
    for r in turns:  # about the image frame's vertical axis (y)
        np.testing.assert_allclose(r[:, 1], [0.0, 1.0, 0.0], atol=1e-12)
    with pytest.raises(ValidationError, match="rotations must be >= 1"):
        ensemble_rotations(0)


def test_half_turn_adds_nothing_and_ensemble_is_the_median_of_turned_estimates(
    tiny_config: DemocapConfig,
) -> None:
    ck = _checkpoint(tiny_config)
    single = DemocapPredictor(ck, rotations=1, solve=False)
    cloud = _cloud()
    base = single.predict(cloud).joints_m
    # the back view of a cloud is the front view of the cloud turned by 180 degrees
    np.testing.assert_allclose(_turned(single, cloud, 180.0), base, atol=1e-6)
    members = [_turned(single, cloud, deg) for deg in (0.0, 60.0, 120.0)]
    got = DemocapPredictor(ck, rotations=3, solve=False).predict(cloud).joints_m
    np.testing.assert_allclose(got, np.median(members, axis=0), atol=1e-6)
    mean = DemocapPredictor(ck, rotations=3, combine="mean", solve=False).predict(cloud).joints_m
    np.testing.assert_allclose(mean, np.mean(members, axis=0), atol=1e-6)
    assert not np.allclose(got, base, atol=1e-4)  # the ensemble does change the estimate


def test_parallel_passes_give_the_same_estimate(tiny_config: DemocapConfig) -> None:
    ck = _checkpoint(tiny_config)
    clouds = [_cloud(), _cloud()[::2]]
    one = DemocapPredictor(ck, rotations=4, solve=False, workers=1).predict_many(clouds)
    for workers in (2, 3, 8):
        other = DemocapPredictor(ck, rotations=4, solve=False, workers=workers).predict_many(clouds)
        # Split into batches of other sizes, the float32 kernels may sum in another order:
        # the same estimate to float32 noise (~1e-7 m seen), far below a micrometre.
        for a, b in zip(one, other, strict=True):
            np.testing.assert_allclose(a.joints_m, b.joints_m, atol=1e-6)
            np.testing.assert_allclose(a.markers_m, b.markers_m, atol=1e-6)


@pytest.mark.parametrize("variant", ["markers-to-pose", "pose", "regression"])
def test_batched_turns_equal_one_pass_per_turn_and_cloud(
    tiny_config: DemocapConfig, variant: Variant
) -> None:
    cfg = dataclasses.replace(tiny_config, variant=variant)
    ck = _checkpoint(cfg)
    clouds = [_cloud(), _cloud()[::2], _cloud()[1::3]]
    pred = DemocapPredictor(ck, rotations=3, solve=False)
    got = pred.predict_many(clouds)
    assert pred.last_timings_s.keys() == {"render_s", "network_s", "decode_s"}
    for cloud, g in zip(clouds, got, strict=True):
        # the median of the turned single shots, each its own pass of one front/back pair
        single = DemocapPredictor(ck, rotations=1, solve=False)
        members = [_turned(single, cloud, d) for d in (0, 60, 120)]
        np.testing.assert_allclose(g.joints_m, np.median(members, axis=0), atol=1e-6)
        assert np.isnan(g.markers_m).all() == (variant == "pose")


def test_worker_threads_are_kept_across_calls(tiny_config: DemocapConfig) -> None:
    ck = _checkpoint(tiny_config)
    before = {t.ident for t in threading.enumerate() if t.name.startswith("democap-turns")}
    pred = DemocapPredictor(ck, rotations=2, solve=False, workers=2)
    pred.predict(_cloud())
    first = {t.ident for t in threading.enumerate() if t.name.startswith("democap-turns")}
    for _ in range(3):
        pred.predict(_cloud())
    again = {t.ident for t in threading.enumerate() if t.name.startswith("democap-turns")}
    assert len(first - before) == 1
    assert again == first  # the same thread serves every call
    assert not any(
        t.name.startswith("democap-turns") for t in _threads_after(DemocapPredictor(ck).predict)
    )


def _threads_after(call: Callable[[np.ndarray], object]) -> list[threading.Thread]:
    """Threads started by ``call`` (a one-worker predictor starts none)."""
    before = set(threading.enumerate())
    call(_cloud())
    return [t for t in threading.enumerate() if t not in before]


def test_inference_copy_matches_the_network_and_leaves_it_untouched(
    tiny_config: DemocapConfig,
) -> None:
    ck = _checkpoint(tiny_config)
    before = {k: v.clone() for k, v in ck.model.state_dict().items()}
    fast = DemocapPredictor(ck, rotations=1, optimise=True, solve=False).predict(_cloud())
    plain = DemocapPredictor(ck, rotations=1, optimise=False, solve=False).predict(_cloud())
    np.testing.assert_allclose(fast.joints_m, plain.joints_m, atol=1e-5)
    np.testing.assert_allclose(fast.markers_m, plain.markers_m, atol=1e-5)
    for k, v in ck.model.state_dict().items():
        torch.testing.assert_close(v, before[k])
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in ck.model.modules())


def test_compiled_network_gives_the_uncompiled_estimates_and_leaves_the_network_untouched(
    tiny_config: DemocapConfig,
) -> None:
    ck = _checkpoint(tiny_config)
    before = {k: v.clone() for k, v in ck.model.state_dict().items()}
    clouds = [_cloud(), _cloud()[::2]]
    plain = DemocapPredictor(ck, rotations=2, solve=False)
    fast = DemocapPredictor(ck, rotations=2, solve=False, compile=True)
    assert fast.compiled
    assert not plain.compiled
    # the first call compiles for its batch, the second runs it; one cloud: another batch
    # size, run uncompiled
    for batch in (clouds, clouds, clouds[:1]):
        for a, b in zip(plain.predict_many(batch), fast.predict_many(batch), strict=True):
            np.testing.assert_allclose(b.joints_m, a.joints_m, atol=1e-5)
            np.testing.assert_allclose(b.markers_m, a.markers_m, atol=1e-5)
    assert fast.compiled
    for k, v in ck.model.state_dict().items():
        torch.testing.assert_close(v, before[k])


def test_warm_up_compiles_for_the_one_cloud_batches_of_a_live_stream(
    tiny_config: DemocapConfig, caplog: pytest.LogCaptureFixture
) -> None:
    pred = DemocapPredictor(_checkpoint(tiny_config), rotations=2, solve=False, compile=True)
    with caplog.at_level(logging.INFO, logger="mocaprig.process.democap.infer"):
        assert pred.warm_up() > 0.0
        compiled_at_warm_up = len(caplog.records)
        pred.predict(_cloud())
        pred.predict(_cloud()[::2])
    messages = [r.getMessage() for r in caplog.records]
    assert sum("compiling the DeMoCap network" in m for m in messages) == 1
    assert compiled_at_warm_up == len(messages)  # the live clouds compiled nothing more
    assert pred.compiled


def test_a_compiler_that_fails_leaves_the_network_running_uncompiled(
    tiny_config: DemocapConfig, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def no_compiler(fn: object, **_: object) -> Callable[..., object]:
        def run(*_a: object) -> object:
            raise RuntimeError("no C++ compiler found\n(details)")

        return run

    monkeypatch.setattr(torch, "compile", no_compiler)
    ck = _checkpoint(tiny_config)
    pred = DemocapPredictor(ck, rotations=2, solve=False, compile=True)
    with caplog.at_level(logging.WARNING, logger="mocaprig.process.democap.infer"):
        got = pred.predict_many([_cloud()])
        again = pred.predict_many([_cloud()])  # not tried again: once is enough to know
    assert not pred.compiled
    assert [r.getMessage().count("no C++ compiler found") for r in caplog.records] == [1]
    want = DemocapPredictor(ck, rotations=2, solve=False).predict_many([_cloud()])
    for g in (got, again):
        np.testing.assert_array_equal(g[0].joints_m, want[0].joints_m)


def test_bad_options_are_refused(tiny_config: DemocapConfig) -> None:
    ck = _checkpoint(tiny_config)
    with pytest.raises(ValidationError, match="combine"):
        DemocapPredictor(ck, combine="max")  # type: ignore[arg-type]
    with pytest.raises(ValidationError, match="workers"):
        DemocapPredictor(ck, workers=0)
    assert DemocapPredictor(ck).predict_many([]) == []


def test_the_solve_fits_the_body_from_the_estimates_and_is_skipped_without_markers(
    tiny_config: DemocapConfig,
) -> None:
    ck = _checkpoint(tiny_config)
    clouds = [_cloud(), _cloud()[::2]]
    raw = DemocapPredictor(ck, rotations=3, solve=False).predict_many(clouds)
    pred = DemocapPredictor(ck, rotations=3)
    assert pred.solves
    got = pred.predict_many(clouds)
    assert "solve_s" in pred.last_timings_s
    for r, g in zip(raw, got, strict=True):
        assert r.pose is None
        assert r.height_m is None
        assert g.pose is not None
        assert g.pose.shape == (33,)
        assert g.height_m is not None
        assert 1.4 < g.height_m < 2.1
        assert not np.allclose(g.joints_m, r.joints_m)
    pose_only = DemocapPredictor(_checkpoint(dataclasses.replace(tiny_config, variant="pose")))
    assert not pose_only.solves
    assert pose_only.predict(_cloud()).pose is None


def test_hypotheses_are_the_ensemble_and_its_turns(tiny_config: DemocapConfig) -> None:
    ck = _checkpoint(tiny_config)
    clouds = [_cloud(), _cloud()[::2]]
    pred = DemocapPredictor(ck, rotations=3)
    markers, joints, turn_m, turn_j = pred.hypotheses(clouds)
    assert markers.shape == (2, 53, 3)
    assert turn_j.shape == (3, 2, 19, 3)
    np.testing.assert_allclose(joints, np.median(turn_j, axis=0))
    np.testing.assert_allclose(markers, np.median(turn_m, axis=0))
    raw = DemocapPredictor(ck, rotations=3, solve=False).predict_many(clouds)
    np.testing.assert_allclose(np.stack([r.joints_m for r in raw]), joints, atol=1e-9)
    empty = pred.hypotheses([])
    assert empty[0].shape == (0, 53, 3)
    assert empty[3].shape == (3, 0, 19, 3)


def test_a_sparse_cloud_is_solved_from_the_larger_ensemble(tiny_config: DemocapConfig) -> None:
    ck = _checkpoint(tiny_config)
    dense, sparse = _cloud(), _cloud()[::3]
    cut = (len(dense) + len(sparse)) // 2
    # without the pose prior (it draws the untrained network's starts to one solution):
    # this test is about which starts the solve gets
    got = DemocapPredictor(
        ck, rotations=3, sparse_rotations=6, sparse_points=cut, pose_prior=False
    ).predict_many([dense, sparse])
    (three,) = DemocapPredictor(
        ck, rotations=3, sparse_rotations=None, pose_prior=False
    ).predict_many([dense])
    (six,) = DemocapPredictor(
        ck, rotations=6, sparse_rotations=None, pose_prior=False
    ).predict_many([sparse])
    np.testing.assert_allclose(got[0].joints_m, three.joints_m, atol=1e-9)
    np.testing.assert_allclose(got[1].joints_m, six.joints_m, atol=1e-6)
    (from_three,) = DemocapPredictor(
        ck, rotations=3, sparse_rotations=None, pose_prior=False
    ).predict_many([sparse])
    assert not np.allclose(got[1].joints_m, from_three.joints_m, atol=1e-6)
    # the single shot stays one network pass, sparse or not
    one = DemocapPredictor(ck, rotations=1, sparse_points=cut).predict_many([sparse])
    alone = DemocapPredictor(ck, rotations=1, sparse_rotations=None).predict_many([sparse])
    np.testing.assert_allclose(one[0].joints_m, alone[0].joints_m, atol=1e-12)


def test_the_rig_views_reach_the_solve_of_each_cloud(tiny_config: DemocapConfig) -> None:
    """Dense and sparse clouds each get their own camera list: the same as solving them one
    at a time with their views; a rig that sees none of the body changes the result."""
    ck = _checkpoint(tiny_config)
    dense, sparse = _cloud(), _cloud()[::3]
    cut = (len(dense) + len(sparse)) // 2
    rig = sample_rig(np.random.default_rng(3))
    far = [Camera(c.centre_m + np.array([0.0, 0.0, 50.0]), c.r_cw, c.focal_px) for c in rig]
    pred = DemocapPredictor(ck, rotations=3, sparse_rotations=6, sparse_points=cut)
    both = pred.predict_many([sparse, dense], views=[far, rig])
    (alone,) = pred.predict_many([sparse], views=[far])
    np.testing.assert_allclose(both[0].joints_m, alone.joints_m, atol=1e-9)
    (blind,) = pred.predict_many([sparse])
    assert not np.allclose(alone.joints_m, blind.joints_m, atol=1e-6)
    with pytest.raises(ValidationError, match="one camera list per cloud"):
        pred.predict_many([sparse, dense], views=[rig])
    # a crop box below the whole body: nothing could have survived the crop, as with `far`
    floor = ((-5.0, 5.0), (-5.0, 5.0), (-1.0, -0.5))
    (cropped,) = pred.predict_many([sparse], views=[rig], crop_box_m=floor)
    (plain,) = pred.predict_many([sparse], views=[rig])
    np.testing.assert_allclose(cropped.joints_m, alone.joints_m, atol=1e-9)
    assert not np.allclose(cropped.joints_m, plain.joints_m, atol=1e-6)
    with pytest.raises(ValidationError, match="crop_box_m needs views"):
        pred.predict_many([sparse], crop_box_m=floor)


def test_the_pose_bank_finds_a_body_the_network_is_far_from(tiny_config: DemocapConfig) -> None:
    """An untrained network's starts leave the solve far off a body bent double; the bank's
    starts find it, and a predictor without the bank stays where the network put it."""
    from mocaprig.process.body.kinematics import democap_joints, forward_kinematics
    from mocaprig.process.body.markers import MarkerSet
    from mocaprig.process.body.shape import BodyShape
    from mocaprig.process.democap.pose_bank import BankSearch, load_pose_bank

    bank = load_pose_bank()
    tilt = Rotation.from_rotvec(bank.poses[:, :3]).as_matrix()[:, 2, 2]
    q = bank.poses[int(np.argmin(tilt))].copy()  # the most bent pose of the bank
    q[3:5] = [0.3, -0.2]
    shape = BodyShape.from_height(1.75)
    kin = forward_kinematics(q[None], shape)
    ms = MarkerSet.for_shape(shape)
    ji = ms.joint_index
    mk = kin.positions_m[0, ji] + (kin.rotations[0, ji] @ ms.offsets_m[..., None])[..., 0]
    rng = np.random.default_rng(8)
    cloud = mk[rng.random(len(mk)) < 0.8] + rng.normal(0.0, 0.003, (1, 3))
    truth = democap_joints(kin)[0]
    ck = _checkpoint(tiny_config)
    (with_bank,) = DemocapPredictor(ck, rotations=1).predict_many([cloud])
    (without,) = DemocapPredictor(ck, rotations=1, pose_bank=False, resolve_rounds=0).predict_many(
        [cloud]
    )
    assert np.linalg.norm(with_bank.joints_m - truth, axis=-1).mean() < 0.03
    assert np.linalg.norm(without.joints_m - truth, axis=-1).mean() > 0.06
    # a cloud explained well enough by the first solve is not searched
    never = BankSearch(energy_per_point=1.0e9)
    (left,) = DemocapPredictor(ck, rotations=1, bank_search=never).predict_many([cloud])
    np.testing.assert_array_equal(left.joints_m, without.joints_m)
    assert DemocapPredictor(ck, solve=False).pose_bank is None


def test_a_poorly_explained_cloud_is_solved_again_from_its_own_solution(
    tiny_config: DemocapConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each round starts from (and is held to) the solution so far, and replaces it only
    where it explains the cloud better; a cloud explained well is not solved again."""
    from mocaprig.process.democap.pose_bank import BankSearch
    from mocaprig.process.democap.solve import SolveResult, solve_skeleton

    calls: list[tuple[np.ndarray, SolveResult]] = []

    def spy(*args: object, **kwargs: object) -> SolveResult:
        out = solve_skeleton(*args, **kwargs)  # type: ignore[arg-type]
        calls.append((np.asarray(args[1]), out))
        return out

    monkeypatch.setattr("mocaprig.process.democap.infer.solve_skeleton", spy)
    ck = _checkpoint(tiny_config)  # untrained: its starts explain the cloud poorly
    cloud = _cloud()
    (once,) = DemocapPredictor(ck, rotations=1, pose_bank=False, resolve_rounds=0).predict_many(
        [cloud]
    )
    assert len(calls) == 1
    first = calls[0][1]
    np.testing.assert_allclose(once.joints_m, first.joints_m[0])
    calls.clear()
    pred = DemocapPredictor(ck, rotations=1, pose_bank=False, resolve_rounds=3)
    (again,) = pred.predict_many([cloud])
    assert 2 <= len(calls) <= 4
    assert "resolve_s" in pred.last_timings_s
    kept = calls[0][1]
    for k, (start, out) in enumerate(calls[1:]):
        np.testing.assert_allclose(start, kept.markers_m[None])  # from the solution so far
        improved = out.energy[0] < kept.energy[0]
        # a round that improves nothing is the last: the next would start from the same
        assert improved or k == len(calls) - 2
        kept = out if improved else kept
    np.testing.assert_allclose(again.joints_m, kept.joints_m[0])
    assert kept.energy[0] <= first.energy[0]
    calls.clear()
    never = BankSearch(energy_per_point=1.0e9)
    DemocapPredictor(ck, rotations=1, bank_search=never, resolve_rounds=2).predict_many([cloud])
    assert len(calls) == 1
    with pytest.raises(ValidationError, match="resolve_rounds"):
        DemocapPredictor(ck, resolve_rounds=-1)


def test_predict_subject_solves_again_with_the_subject_calibrated_from_the_frames(
    tiny_config: DemocapConfig,
) -> None:
    pool = make_pool(0, "test", takes=1, seconds=1.0)
    clouds = [
        make_sample(pool[0], i, np.random.default_rng(i), augment=False, size_px=64).raw_m
        for i in (0, 10, 20, 29)
    ]
    # without the pose prior first: the calibration alone holds the heights together
    pred = DemocapPredictor(
        _checkpoint(tiny_config), rotations=1, pose_bank=False, pose_prior=False
    )
    alone = pred.predict_many(clouds)
    res = pred.predict_subject(clouds, rounds=2)
    got, cal = res.predictions, res.calibration
    # the first solve is the frame-by-frame one
    for a, f in zip(alone, res.frame_by_frame, strict=True):
        np.testing.assert_allclose(a.joints_m, f.joints_m, atol=1e-6)
    assert cal.frames == 4
    assert cal.shape_z.shape == (17,)
    assert cal.marker_offsets_m.shape == (53, 3)
    assert len(got) == 4
    # one body for every frame: the heights agree far better than frame by frame (the
    # untrained network's starts: 0.65 m apart frame by frame, 0.03-0.06 m calibrated,
    # depending on the numerical libraries' build)
    heights = np.array([p.height_m for p in got])
    assert np.ptp(heights) < 0.1 * np.ptp([p.height_m for p in alone])
    assert np.ptp(heights) < 0.08
    assert any(not np.allclose(a.joints_m, g.joints_m) for a, g in zip(alone, got, strict=True))
    # with the prior (the default) too, far better than frame by frame
    held = DemocapPredictor(_checkpoint(tiny_config), rotations=1, pose_bank=False)
    res = held.predict_subject(clouds, rounds=2)
    spread = np.ptp([p.height_m for p in res.predictions])
    assert spread < 0.5 * np.ptp([p.height_m for p in res.frame_by_frame])
    with pytest.raises(ValidationError, match="at least 3"):
        pred.predict_subject(clouds[:2])
    with pytest.raises(ValidationError, match="rounds"):
        pred.predict_subject(clouds, rounds=0)
    with pytest.raises(ValidationError, match="needs the skeleton solve"):
        DemocapPredictor(_checkpoint(tiny_config), solve=False).predict_subject(clouds)
    with pytest.raises(ValidationError, match="subject_calibration"):
        DemocapPredictor(_checkpoint(tiny_config), subject_calibration=-1)
