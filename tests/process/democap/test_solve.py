"""The skeleton solve: its derivatives, its shape model, and what it recovers."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from mocaprig.errors import ValidationError
from mocaprig.process.body import (
    DEMOCAP_JOINT_INDEX,
    DEMOCAP_JOINTS,
    DOF_LIMITS_RAD,
    DOF_NAMES,
    LENGTH_FIELDS,
    MARKER_NAMES,
    RADIUS_FIELDS,
    BodyShape,
    MarkerSet,
    democap_joints,
    forward_kinematics,
    make_motion,
    marker_positions,
    rest_offsets,
)
from mocaprig.process.democap import solve as S
from mocaprig.process.democap.pose_prior import load_pose_prior
from mocaprig.process.democap.simdata import in_frustum, pose_frames, sample_rig


def _take(seed: int) -> tuple[BodyShape, np.ndarray, np.ndarray]:
    """A sampled body doing jumping jacks: (shape, markers (T, 53, 3), joints (T, 19, 3))."""
    rng = np.random.default_rng(seed)
    shape = BodyShape.sample(rng)
    markers = MarkerSet.for_shape(shape).jittered(rng, sigma_m=0.005)
    motion = make_motion("jumping_jacks", seconds=1.0, rng=rng, rate_hz=10.0, shape=shape)
    pf = pose_frames(motion, shape, markers)
    return shape, pf.markers_m, pf.joints_m


def _cloud(markers: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """What a rig might see: most markers, some twice, with noise, and a few stray points."""
    keep = markers[rng.random(len(markers)) > 0.1]
    twice = keep[rng.random(len(keep)) < 0.5]
    strays = markers.mean(0) + rng.uniform(-0.8, 0.8, (4, 3))
    pts = np.concatenate([keep, twice, strays])
    return pts + rng.normal(0.0, 0.004, pts.shape)


def _turned(p: np.ndarray, deg: float) -> np.ndarray:
    c = p.reshape(-1, 3).mean(0)
    r = Rotation.from_euler("z", deg, degrees=True).as_matrix()
    return np.asarray((p - c) @ r.T + c)


def _mpjpe_mm(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b, axis=-1).mean() * 1000.0)


def test_normal_equations_are_the_gauss_newton_model_of_the_energy() -> None:
    """The analytic JᵀWr equals half the autograd gradient of the energy, for every term,
    with the body model's shape prior and with a calibrated subject's (their marker
    corrections held), and the committed pose prior."""
    _, mk, jt = _take(3)
    rng = np.random.default_rng(0)
    clouds = [_cloud(m, rng) for m in mk[:4]]
    b, opt = S._basis(), S.SolveOptions()
    tm = mk[:4] + rng.normal(0, 0.02, mk[:4].shape)
    tj = jt[:4] + rng.normal(0, 0.02, jt[:4].shape)
    s0 = S._initial_state(tm, tj, b)
    mid = (b.lo + b.hi) / 2
    half = (b.hi - b.lo) / 2
    s = S._State(
        s0.root_r,
        s0.root_t,
        mid + torch.from_numpy(rng.uniform(-0.5, 0.5, (4, 27))) * half,
        s0.z + torch.from_numpy(rng.normal(0, 0.05, s0.z.shape)),
        torch.from_numpy(rng.normal(0, 0.01, (4, 53, 3))),
    )
    subject = S.SubjectCalibration(
        shape_z=np.r_[1.1, 0.95, rng.normal(0, 0.05, 15)],
        marker_offsets_m=rng.normal(0, 0.01, (53, 3)),
        frames=8,
    )
    prior = S._Prior.of([subject, None, subject, None], opt, load_pose_prior())
    n = max(len(c) for c in clouds)
    cloud = np.full((4, n, 3), 1e3)
    mask = np.zeros((4, n))
    for i, c in enumerate(clouds):
        cloud[i, : len(c)], mask[i, : len(c)] = c, 1.0
    t_cloud, t_mask, t_tm, t_tj = (torch.from_numpy(a) for a in (cloud, mask, tm, tj))
    data = S._Data(t_cloud, t_mask, t_tm, t_tj, prior)
    for w in (
        S._Weights(False, 0.0, 1.0, 0.03, 0.03, None),
        S._Weights(True, 0.05, 0.015, 0.05, 0.08, 0.1),
    ):
        q = S._pose(s, b)
        _, aux = S._energy_terms(q, s, data, w, opt)
        _, g = S._normal_equations(s, q, aux, data, opt, b)
        d = torch.zeros(4, S._NP, dtype=torch.float64, requires_grad=True)
        moved = s.step(d, b.lo - 10.0, b.hi + 10.0)  # no clamp: its gradient would be 0
        e, _ = S._energy_terms(S._pose(moved, b), moved, data, w, opt)
        e.sum().backward()  # type: ignore[no-untyped-call]
        assert d.grad is not None
        torch.testing.assert_close(d.grad / 2, g, rtol=1e-9, atol=1e-9)


def test_the_shape_basis_reproduces_sampled_bodies() -> None:
    """Rest offsets are exact; the worst marker offset within 2 mm for half of the sampled
    bodies (1.55-1.95 m) and within 15 mm for all."""
    b = S._basis()
    f0 = b.f0.numpy()
    rng = np.random.default_rng(5)
    worst = []
    for _ in range(40):
        shape = BodyShape.sample(rng)
        f = np.array([getattr(shape, k) for k in LENGTH_FIELDS + RADIUS_FIELDS])
        h = shape.height_m / S.REFERENCE_HEIGHT_M
        rel = f / h
        off = h * np.tensordot(rel, b.d_off.numpy(), 1)
        np.testing.assert_allclose(off, rest_offsets(shape), atol=1e-12)
        mo = h * (b.m_off0.numpy() + np.tensordot(rel - f0, b.d_moff.numpy(), 1))
        worst.append(np.linalg.norm(mo - MarkerSet.for_shape(shape).offsets_m, axis=1).max())
    assert np.median(worst) < 0.002
    assert max(worst) < 0.015


def test_the_first_guess_reads_every_angle_off_the_estimate() -> None:
    """From exact markers and joints of random poses anywhere within the limits (arms over
    the head, legs crossed), the first guess is near the pose before any step: the spine's
    half-and-half split and joints with fewer than three DoF are what it approximates."""
    ref = BodyShape.from_height(S.REFERENCE_HEIGHT_M)
    rng = np.random.default_rng(0)
    n = 60
    poses = np.zeros((n, 33))
    poses[:, :3] = rng.normal(0, 1, (n, 3))
    poses[:, 3:6] = rng.normal(0, 0.5, (n, 3))
    poses[:, 6:] = rng.uniform(DOF_LIMITS_RAD[:, 0], DOF_LIMITS_RAD[:, 1], (n, 27))
    kin = forward_kinematics(poses, ref)
    markers = marker_positions(kin, ref, MarkerSet.for_shape(ref))
    joints = kin.positions_m[:, list(DEMOCAP_JOINT_INDEX)]
    b = S._basis()
    guess = S._pose(S._initial_state(markers, joints, b), b).joints.numpy()
    err = np.linalg.norm(guess - joints, axis=-1)
    assert np.median(err) < 0.015
    assert err.mean(axis=1).max() < 0.06


def test_solve_recovers_the_body_from_a_noisy_estimate() -> None:
    shape, mk, jt = _take(7)
    rng = np.random.default_rng(1)
    clouds = [_cloud(m, rng) for m in mk]
    # an estimate 4 cm off everywhere, as a network's might be
    est_m = mk + rng.normal(0, 0.04, mk.shape)
    est_j = jt + rng.normal(0, 0.04, jt.shape)
    res = S.solve_skeleton(clouds, est_m[None], est_j[None])
    assert _mpjpe_mm(est_j, jt) > 55.0
    assert _mpjpe_mm(res.joints_m, jt) < 15.0
    assert _mpjpe_mm(res.markers_m, mk) < 20.0
    assert np.all(np.abs(res.height_m - shape.height_m) < 0.06)
    ang = res.poses[:, 6:]
    assert np.all((ang >= DOF_LIMITS_RAD[:, 0] - 1e-12) & (ang <= DOF_LIMITS_RAD[:, 1] + 1e-12))
    assert np.all(res.hypothesis == 0)


def test_the_start_that_explains_the_cloud_wins() -> None:
    """A good start and one turned away by 90 deg: the good one is kept, in either order."""
    _, mk, jt = _take(11)
    rng = np.random.default_rng(2)
    clouds = [_cloud(m, rng) for m in mk[:3]]
    good = (mk[:3] + rng.normal(0, 0.02, mk[:3].shape), jt[:3])
    bad = (
        np.array([_turned(m, 90.0) for m in mk[:3]]),
        np.array([_turned(j, 90.0) for j in jt[:3]]),
    )
    for order, want in (((good, bad), 0), ((bad, good), 1)):
        res = S.solve_skeleton(
            clouds, np.stack([o[0] for o in order]), np.stack([o[1] for o in order])
        )
        assert np.all(res.hypothesis == want)
        assert _mpjpe_mm(res.joints_m, jt[:3]) < 15.0


def test_the_bent_start_turns_the_body_above_the_hips_forward() -> None:
    _, mk, jt = _take(3)
    b = S._basis()
    m2, j2 = S._bent(mk[:1], jt[:1], 0.8, b)
    legs_m, legs_j = b.leg_points[: len(mk[0])], b.leg_points[len(mk[0]) :]
    np.testing.assert_array_equal(m2[0, legs_m], mk[0, legs_m])
    np.testing.assert_array_equal(j2[0, legs_j], jt[0, legs_j])
    r, l_ = (jt[0, i] for i in b.hip_joints)
    pivot = (r + l_) / 2
    for a, c in ((mk[0], m2[0]), (jt[0], j2[0])):  # a turn: distances to the pivot kept
        np.testing.assert_allclose(
            np.linalg.norm(a - pivot, axis=1), np.linalg.norm(c - pivot, axis=1), atol=1e-12
        )
    neck = DEMOCAP_JOINTS.index("Neck")
    facing = np.cross(np.array([0.0, 0.0, 1.0]), r - l_)  # forward, for a body facing it
    lean = np.dot(j2[0, neck] - jt[0, neck], facing / np.linalg.norm(facing))
    assert lean > 0.2  # the neck went forward by ~ 0.5 m · sin(46 deg)
    assert j2[0, neck, 2] < jt[0, neck, 2] - 0.1


def test_the_limb_search_frees_an_arm_stuck_on_the_wrong_side() -> None:
    """An estimate right but for the left arm (hanging where the truth holds it up and out):
    the gradient steps leave it where it is, the limb search brings it back."""
    rng = np.random.default_rng(4)
    shape = BodyShape.sample(rng)
    ms = MarkerSet.for_shape(shape)
    motion = make_motion("jumping_jacks", seconds=1.0, rng=rng, rate_hz=10.0, shape=shape)
    abd = DOF_NAMES.index("left_shoulder_abduction")
    truth = motion.poses[np.argsort(motion.poses[:, 6 + abd])[-3:]]  # arms up the most
    assert np.all(np.rad2deg(truth[:, 6 + abd]) > 80.0)
    wrong = truth.copy()
    for name, deg in (("abduction", 0.0), ("flexion", 0.0), ("internal_rotation", 0.0)):
        wrong[:, 6 + DOF_NAMES.index(f"left_shoulder_{name}")] = np.deg2rad(deg)
    kin_t, kin_w = forward_kinematics(truth, shape), forward_kinematics(wrong, shape)
    mk, jt = marker_positions(kin_t, shape, ms), democap_joints(kin_t)
    est_m, est_j = marker_positions(kin_w, shape, ms), democap_joints(kin_w)
    clouds = [_cloud(m, rng) for m in mk]
    hand = DEMOCAP_JOINTS.index("LeftHand")
    assert np.all(np.linalg.norm(est_j[:, hand] - jt[:, hand], axis=-1) > 0.5)
    off = S.solve_skeleton(
        clouds, est_m[None], est_j[None], options=S.SolveOptions(limb_search=False)
    )
    on = S.solve_skeleton(clouds, est_m[None], est_j[None])
    assert np.all(np.linalg.norm(off.joints_m[:, hand] - jt[:, hand], axis=-1) > 0.3)
    assert np.all(np.linalg.norm(on.joints_m[:, hand] - jt[:, hand], axis=-1) < 0.1)
    assert _mpjpe_mm(on.joints_m, jt) < 10.0
    assert np.all(on.energy < off.energy)


def test_the_limb_grids_cover_each_limb_within_its_limits() -> None:
    limbs = S._limbs()
    assert len(limbs) == 5  # four limbs, then the head
    moving = np.zeros(len(limbs[0].markers), int)
    for limb in limbs:
        lo, hi = DOF_LIMITS_RAD[limb.dofs.numpy()].T
        g = limb.grid.numpy()
        assert np.all((g >= lo) & (g <= hi))
        assert len(np.unique(g, axis=0)) == len(g) >= (150 if limb is not limbs[-1] else 15)
        moving += limb.markers.numpy()
    assert moving.max() == 1  # no marker moves with two limbs
    head = {MARKER_NAMES[i] for i in np.flatnonzero(limbs[-1].markers.numpy())}
    assert {"LFHD", "RFHD", "LBHD", "RBHD"} <= head
    # the trunk's markers (pelvis, spine, clavicles) move with none
    assert 10 <= int((moving == 0).sum()) < len(moving) // 3
    with pytest.raises(ValidationError, match="limb_keep"):
        S.SolveOptions(limb_keep=())
    with pytest.raises(ValidationError, match="limb_keep"):
        S.SolveOptions(limb_keep=(4, 0))


def test_limb_candidates_score_as_the_fully_posed_body_does() -> None:
    """The limb search poses only the limb's subtree per candidate; its scores equal the
    selection energy of each candidate posed whole (minus the held markers' constant part)."""
    _, mk, jt = _take(3)
    rng = np.random.default_rng(4)
    clouds = [_cloud(m, rng) for m in mk[:3]]
    b = S._basis()
    s = S._initial_state(mk[:3], jt[:3], b)
    data = S._data(clouds, mk[:3], jt[:3])
    for limb in S._limbs():
        # the held DoF differ from the state's (an earlier limb has moved since)
        moved = torch.clamp(
            s.angles + torch.from_numpy(rng.normal(0, 0.2, s.angles.shape)), b.lo, b.hi
        )
        cand = moved[:, None].repeat(1, 7, 1)
        cand[:, 1:, limb.dofs] = limb.grid[rng.choice(len(limb.grid), 6, replace=False)]
        got = S._limb_energies(s, cand, data, limb, 0.1)
        whole = (
            torch.stack(
                [
                    S._selection_energy(
                        S._pose(S._State(s.root_r, s.root_t, cand[:, k], s.z, s.m_fix), b),
                        data,
                        0.1,
                    )
                    for k in range(7)
                ],
                dim=1,
            )
            * 0.1**2
        )
        held = S._pose(S._State(s.root_r, s.root_t, cand[:, 0], s.z, s.m_fix), b).markers[
            :, ~limb.markers
        ]
        d_h = torch.cdist(held, data.cloud).min(dim=2).values
        const = S._gm(d_h**2, 0.1)[0].sum(1)
        torch.testing.assert_close(got, whole - const[:, None], rtol=1e-9, atol=1e-9)


def test_the_solve_sees_what_the_rig_sees() -> None:
    """Its view test is simdata.in_frustum's, per problem and camera list (padded rigs)."""
    rng = np.random.default_rng(6)
    rigs = [sample_rig(rng, num_cameras=n) for n in (4, 2, 3)]
    # a real camera's own principal point and image size (a live rig's view)
    rigs[1][0] = replace(rigs[1][0], principal_px=(600.0, 300.0), size_px=(1280, 720))
    pts = rng.uniform([-3.0, -3.0, -0.5], [3.0, 3.0, 3.0], (3, 400, 3))
    views = S._Views.of(rigs)
    got = views.seen(torch.from_numpy(pts)).numpy()
    want = np.array([in_frustum(p, rig).any(axis=0) for p, rig in zip(pts, rigs, strict=True)])
    assert 0.1 < want.mean() < 0.9  # the test has both
    np.testing.assert_array_equal(got, want.astype(float))


def test_a_marker_no_camera_sees_is_not_charged_for_its_missing_point() -> None:
    """Hands over the head above the cameras' view have no points: with the rig's views the
    selection energy charges only the markers a camera could have seen; the solve still fits."""
    _, mk, jt = _take(3)
    rng = np.random.default_rng(2)
    rig = sample_rig(rng)
    frame = int(np.argmax(mk[:, :, 2].max(axis=1)))  # arms highest
    # the body raised until its hands are over the view's top edge; the cloud is what is seen
    lift = 2.05 - mk[frame, :, 2].max()
    m, j = mk[frame] + (0, 0, lift), jt[frame] + (0, 0, lift)
    seen = in_frustum(m, rig).any(axis=0)
    assert 3 <= (~seen).sum() < 20
    cloud = m[seen] + rng.normal(0, 0.003, (int(seen.sum()), 3))
    b = S._basis()
    q = S._pose(S._initial_state(m[None], j[None], b), b)
    blind = S._selection_energy(q, S._data([cloud], m[None], j[None]), 0.03)
    aware = S._selection_energy(q, S._data([cloud], m[None], j[None], S._Views.of([rig])), 0.03)
    model_seen = S._Views.of([rig]).seen(q.markers)[0].numpy().astype(bool)
    d = np.linalg.norm(q.markers[0].numpy()[~model_seen, None] - cloud[None], axis=-1).min(1)
    charge = float((d**2 / (0.03**2 + d**2)).sum())  # ρ_c / c² of the unseen markers
    assert charge > 3.0
    np.testing.assert_allclose(float(blind[0] - aware[0]), charge, rtol=1e-9)
    est_m, est_j = m + rng.normal(0, 0.02, m.shape), j + rng.normal(0, 0.02, j.shape)
    sol = S.solve_skeleton([cloud], est_m[None, None], est_j[None, None], views=[rig])
    assert _mpjpe_mm(sol.joints_m[0], j) < 15.0
    with pytest.raises(ValidationError, match="one camera list per cloud"):
        S.solve_skeleton([cloud], est_m[None, None], est_j[None, None], views=[rig, rig])


def test_a_marker_outside_the_crop_box_is_not_charged_either() -> None:
    """A raised hand inside a camera's view but above the crop box's top has no point (the
    pipeline dropped it): with the crop box the solve does not charge it for that."""
    rng = np.random.default_rng(6)
    rig = sample_rig(rng)
    pts = rng.uniform([-1.0, -1.0, 0.0], [1.0, 1.0, 2.4], (1, 300, 3))
    box = ((-2.2, 2.2), (-2.2, 2.2), (-0.1, 1.5))
    views = S._Views.of([rig])
    cropped = S._Views.of([rig], box)
    in_view = views.seen(torch.from_numpy(pts)).numpy()[0].astype(bool)
    got = cropped.seen(torch.from_numpy(pts)).numpy()[0].astype(bool)
    np.testing.assert_array_equal(got, in_view & (pts[0, :, 2] <= 1.5))
    assert (in_view & (pts[0, :, 2] > 1.5)).sum() > 10  # the test has both
    # the box survives the solve's row selections
    assert cropped.rows(0, 1).box is not None
    assert cropped.take(np.array([0, 0])).box is not None
    _, mk, jt = _take(3)
    m, j = mk[0], jt[0]
    cloud = m[m[:, 2] <= 1.5]
    est_m, est_j = m[None, None], j[None, None]
    sol = S.solve_skeleton([cloud], est_m, est_j, views=[rig], crop_box_m=box)
    assert _mpjpe_mm(sol.joints_m[0], j) < 15.0
    with pytest.raises(ValidationError, match="crop_box_m needs views"):
        S.solve_skeleton([cloud], est_m, est_j, crop_box_m=box)
    with pytest.raises(ValidationError, match="lo <= hi"):
        S.solve_skeleton([cloud], est_m, est_j, views=[rig], crop_box_m=((1, 0), (0, 1), (0, 1)))


def test_bad_inputs_are_refused() -> None:
    _, mk, jt = _take(3)
    cloud = mk[0]
    with pytest.raises(ValidationError, match="at least 2"):
        S.solve_skeleton([cloud[:1]], mk[None, :1], jt[None, :1])
    with pytest.raises(ValidationError, match="markers_m"):
        S.solve_skeleton([cloud], mk[None, :2], jt[None, :2])
    with pytest.raises(ValidationError, match="finite"):
        S.solve_skeleton([cloud * np.nan], mk[None, :1], jt[None, :1])
    with pytest.raises(ValidationError, match="height_range"):
        S.SolveOptions(height_range=(1.1, 1.2))
    empty = S.solve_skeleton([], np.zeros((2, 0, 53, 3)), np.zeros((2, 0, 19, 3)))
    assert empty.joints_m.shape == (0, 19, 3)


def test_a_subject_calibration_finds_the_subjects_height_and_a_marker_stuck_elsewhere() -> None:
    """A tall subject whose elbow marker sits 2.5 cm off where the marker set puts it: the
    calibration from their frames finds both, and the solve given it places that marker
    where it is."""
    rng = np.random.default_rng(11)
    shape = BodyShape.from_height(1.92)
    ms = MarkerSet.for_shape(shape)
    k = MARKER_NAMES.index("LELB")
    delta = np.array([0.025, 0.0, 0.0])  # across the bone, in the segment's frame
    moved = replace(ms, offsets_m=ms.offsets_m + np.where(np.arange(53)[:, None] == k, delta, 0))
    motion = make_motion("wave", seconds=2.0, rng=rng, rate_hz=5.0, shape=shape)
    pf = pose_frames(motion, shape, moved)
    mk, jt = pf.markers_m, pf.joints_m
    clouds = [m[rng.random(53) > 0.1] + rng.normal(0, 0.003, (1, 3)) for m in mk]
    est_m, est_j = mk + rng.normal(0, 0.03, mk.shape), jt + rng.normal(0, 0.03, jt.shape)
    first = S.solve_skeleton(clouds, est_m[None], est_j[None])
    cal = S.calibrate_subject(clouds, first)
    assert cal.frames == len(clouds)
    np.testing.assert_allclose(cal.marker_offsets_m[k], delta, atol=0.005)
    assert np.delete(np.linalg.norm(cal.marker_offsets_m, axis=1), k).max() < 0.01
    assert abs(cal.shape_z[0] * S.REFERENCE_HEIGHT_M - 1.92) < 0.03
    again = S.solve_skeleton(clouds, est_m[None], est_j[None], subjects=[cal] * len(clouds))
    err_first = np.linalg.norm(first.markers_m[:, k] - mk[:, k], axis=-1).mean()
    err_again = np.linalg.norm(again.markers_m[:, k] - mk[:, k], axis=-1).mean()
    assert err_again < 0.5 * err_first
    with pytest.raises(ValidationError, match="at least 3"):
        S.calibrate_subject(clouds[:2], first)
    with pytest.raises(ValidationError, match="one per cloud"):
        S.solve_skeleton(clouds, est_m[None], est_j[None], subjects=[cal])
