"""The 53-marker DeMoCap set: canonical order, skin placement, symmetry and jitter."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest
import torch

from mocaprig.errors import ValidationError
from mocaprig.process.body.kinematics import (
    forward_kinematics,
    forward_kinematics_torch,
    neutral_pose,
)
from mocaprig.process.body.markers import (
    COMMON_MARKERS,
    MARKER_NAMES,
    MarkerSet,
    marker_positions,
    marker_positions_torch,
)
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.body.skeleton import JOINT_INDEX
from mocaprig.process.body.surface import CAPSULE_NAMES, capsules, signed_distance
from tests.process.body._body_helpers import random_poses

SHAPE = BodyShape.from_height(1.75)
MARKERS = MarkerSet.for_shape(SHAPE)
IDX = {n: i for i, n in enumerate(MARKER_NAMES)}

# democap-method.md §6.1, copied from the table (not from our module).
DOC_ORDER = [
    *("ARIEL", "C7", "CLAV"),
    *("LANK", "LBHD", "LBSH", "LBWT", "LELB", "LFHD", "LFRM", "LFSH", "LFWT", "LHEL", "LIEL"),
    *("LIHAND", "LIWR", "LKNE", "LKNI", "LMT1", "LMT5", "LOHAND", "LOWR", "LSHN", "LTHI"),
    *("LTOE", "LUPA"),
    *("RANK", "RBHD", "RBSH", "RBWT", "RELB", "RFHD", "RFRM", "RFSH", "RFWT", "RHEL", "RIEL"),
    *("RIHAND", "RIWR", "RKNE", "RKNI", "RMT1", "RMT5", "ROHAND", "ROWR", "RSHN", "RTHI"),
    *("RTOE", "RUPA"),
    *("STRN", "T10"),
]


def _neutral_markers(markers: MarkerSet = MARKERS) -> npt.NDArray[np.float64]:
    return marker_positions(neutral_pose(SHAPE), SHAPE, markers)


def test_names_follow_the_canonical_democap_order() -> None:
    assert len(MARKER_NAMES) == 53
    assert len(set(MARKER_NAMES)) == 53
    assert list(COMMON_MARKERS) == DOC_ORDER
    assert list(COMMON_MARKERS) == sorted(COMMON_MARKERS)
    assert MARKER_NAMES[51:] == ("MBWT", "MFWT")
    assert MARKERS.names == MARKER_NAMES


def test_side_waist_variant_puts_lmwt_rmwt_last() -> None:
    markers = MarkerSet.for_shape(SHAPE, waist="LMWT_RMWT")
    assert markers.names[:51] == COMMON_MARKERS
    assert markers.names[51:] == ("LMWT", "RMWT")
    pos = _neutral_markers(markers)
    hips = SHAPE.hips_height_m
    assert pos[51, 0] < -0.1 < 0.1 < pos[52, 0]  # left and right sides of the waist
    assert abs(pos[51, 2] - hips) < 0.1


def test_unknown_waist_variant_is_rejected() -> None:
    with pytest.raises(ValidationError, match="waist must be one of"):
        MarkerSet.for_shape(SHAPE, waist="XX")  # type: ignore[arg-type]


def test_jittered_markers_stay_within_3_cm_of_their_capsule_in_random_poses() -> None:
    rng = np.random.default_rng(20)
    shape = BodyShape.sample(rng)
    markers = MarkerSet.for_shape(shape).jittered(rng)
    kin = forward_kinematics(random_poses(rng, 40), shape)
    pos = marker_positions(kin, shape, markers)
    sd = signed_distance(pos, capsules(kin, shape))  # (40, 53, C)
    own = sd[:, np.arange(53), markers.capsule_index]
    assert np.all(np.abs(own) <= 0.03)


def test_markers_ride_rigidly_one_marker_radius_off_their_capsule() -> None:
    """Without jitter every marker sits where its capsule cannot move under it: on the same
    joint, or (KNE/KNI) on the knee axis of the shank's upper sphere."""
    rng = np.random.default_rng(24)
    shape = BodyShape.sample(rng)
    markers = MarkerSet.for_shape(shape)
    kin = forward_kinematics(random_poses(rng, 40), shape)
    pos = marker_positions(kin, shape, markers)
    sd = signed_distance(pos, capsules(kin, shape))
    own = sd[:, np.arange(53), markers.capsule_index]
    np.testing.assert_allclose(own, markers.marker_radius_m, atol=1e-9)


def test_markers_are_not_buried_in_the_neutral_body() -> None:
    pos = _neutral_markers()
    sd = signed_distance(pos, capsules(neutral_pose(SHAPE), SHAPE))
    assert sd.min() > 0.0  # every marker is visible from outside the surface


def test_markers_are_mirror_symmetric_in_the_neutral_pose() -> None:
    pos = _neutral_markers()
    for name, i in IDX.items():
        if name.startswith("L"):
            np.testing.assert_allclose(pos[i] * [-1, 1, 1], pos[IDX["R" + name[1:]]], atol=1e-12)
        elif not name.startswith("R"):
            assert abs(pos[i, 0]) < 1e-12, name  # central markers sit on the midline


def test_marker_segments_match_the_anatomy() -> None:
    joint_of = dict(zip(MARKERS.names, MARKERS.joint_index, strict=True))
    assert joint_of["ARIEL"] == JOINT_INDEX["Head"]
    assert joint_of["RELB"] == JOINT_INDEX["RightArm"]  # epicondyles belong to the humerus
    assert joint_of["LOWR"] == JOINT_INDEX["LeftForeArm"]
    assert joint_of["RTOE"] == JOINT_INDEX["RightToeBase"]
    assert joint_of["LFWT"] == JOINT_INDEX["Hips"]
    assert CAPSULE_NAMES[MARKERS.capsule_index[IDX["RTHI"]]] == "right_thigh"


def test_neutral_marker_layout_is_anatomically_plausible() -> None:
    p = _neutral_markers()
    z = p[:, 2]
    assert int(np.argmax(z)) == IDX["ARIEL"]
    assert abs(z[IDX["ARIEL"]] - SHAPE.height_m) < 0.02
    assert p[IDX["CLAV"], 1] > 0 > p[IDX["C7"], 1]  # front / back of the trunk
    assert p[IDX["STRN"], 1] > 0 > p[IDX["T10"], 1]
    assert p[IDX["LFHD"], 1] > 0 > p[IDX["LBHD"], 1]
    assert p[IDX["RFWT"], 1] > 0 > p[IDX["RBWT"], 1]
    for s, sign in (("R", 1.0), ("L", -1.0)):
        assert sign * (p[IDX[s + "ELB"], 0] - p[IDX[s + "IEL"], 0]) > 0.05  # lateral vs medial
        assert sign * (p[IDX[s + "KNE"], 0] - p[IDX[s + "KNI"], 0]) > 0.05
        assert sign * (p[IDX[s + "MT5"], 0] - p[IDX[s + "MT1"], 0]) > 0.03
        assert p[IDX[s + "OWR"], 1] > p[IDX[s + "IWR"], 1]  # thumb side forward at rest
        assert p[IDX[s + "HEL"], 1] < p[IDX[s + "ANK"], 1] < p[IDX[s + "TOE"], 1]
        assert z[IDX[s + "SHN"]] < z[IDX[s + "KNE"]] < z[IDX[s + "THI"]] < z[IDX[s + "FWT"]]
        assert z[IDX[s + "OWR"]] < z[IDX[s + "ELB"]] < z[IDX[s + "UPA"]] < z[IDX[s + "FSH"]]
        assert max(z[IDX[s + "HEL"]], z[IDX[s + "TOE"]], z[IDX[s + "MT1"]]) < 0.1


def test_jitter_slides_markers_along_the_skin() -> None:
    rng = np.random.default_rng(21)
    jittered = MARKERS.jittered(rng, sigma_m=0.01)
    moved = np.linalg.norm(jittered.offsets_m - MARKERS.offsets_m, axis=-1)
    assert 0.005 < np.median(moved) < 0.02  # ~ sigma * sqrt(2) for 2 tangential axes
    # still one marker radius off its own capsule, in the neutral pose
    pos = _neutral_markers(jittered)
    sd = signed_distance(pos, capsules(neutral_pose(SHAPE), SHAPE))
    own = sd[np.arange(53), jittered.capsule_index]
    np.testing.assert_allclose(own, MARKERS.marker_radius_m, atol=1e-12)
    # the original set is untouched and a seed reproduces the jitter
    np.testing.assert_array_equal(MARKERS.offsets_m, MarkerSet.for_shape(SHAPE).offsets_m)
    again = MARKERS.jittered(np.random.default_rng(21), sigma_m=0.01)
    np.testing.assert_array_equal(again.offsets_m, jittered.offsets_m)


def test_jitter_rejects_a_negative_sigma() -> None:
    with pytest.raises(ValidationError, match="sigma_m"):
        MARKERS.jittered(np.random.default_rng(0), sigma_m=-0.01)


def test_marker_positions_accept_poses_or_kinematics() -> None:
    q = random_poses(np.random.default_rng(22), 3)
    a = marker_positions(q, SHAPE, MARKERS)
    b = marker_positions(forward_kinematics(q, SHAPE), SHAPE, MARKERS)
    assert a.shape == (3, 53, 3)
    np.testing.assert_array_equal(a, b)


def test_torch_marker_positions_match_numpy() -> None:
    q = random_poses(np.random.default_rng(23), 5)
    pos, rot = forward_kinematics_torch(torch.tensor(q), SHAPE)
    got = marker_positions_torch(pos, rot, MARKERS).numpy()
    np.testing.assert_allclose(got, marker_positions(q, SHAPE, MARKERS), atol=1e-12)
