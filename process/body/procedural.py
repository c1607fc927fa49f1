"""Built-in procedural motions: the simulator's default actor motion when no BVH is given.

Every motion is generated from a small "score" of joint-angle key shapes eased with minimum-jerk
profiles (zero velocity and acceleration at each key), repeated for the requested length, with
seeded take-to-take variation:

* tempo (x0.88-1.12) and amplitude (x0.88-1.08) factors (every take starts at the beginning of
  its cycle, from a standing pose, so takes chain smoothly in :func:`session_motion`);
* smooth per-take noise on every angle (a few tenths of a degree to ~1 degree) and on the root
  heading, so no two seeds give the same take.

Angles are clipped into ``DOF_LIMITS_RAD``. The root stays facing +Y (plus the heading noise);
its height is set through the forward kinematics so the feet stand on the floor (z = 0): the
lowest sole point (heel, ball of the foot or toe tip, see :func:`floor_clearance_m`) touches it,
which puts the ankle joints at ``shape.ankle_height_m`` when standing flat. Jumping jacks leave
the ground on ballistic arcs. The root's horizontal position follows the supporting foot (both
feet when standing), so planted feet do not slide.

Motions (:data:`PROCEDURAL_MOTIONS`):

``t_pose``
    The static calibration stance: arms abducted 90 degrees, held still (tiny sway).
``clap``
    Hand claps in front of the chest at ~2 Hz; the palms meet (centres ~3 cm apart).
``jumping_jacks``
    ~1.1 s cycles: jump out (legs apart, arms overhead), jump in; ~0.2 s flights.
``punch_kick``
    From a boxing guard: right jab, left cross (extensions ~0.18 s), right front kick.
``squat``
    Slow bodyweight squats (hip ~95, knee ~110 degrees), arms forward.
``wave``
    Raise the right arm and wave the forearm side to side at ~2 Hz, lower it.
``karate``
    From a horse-riding stance with fists chambered at the hips: fast reverse punches
    (extension ~0.15 s, peak hand speed ~5-10 m/s) and snapping front kicks.
``freestyle``
    No score: random key poses every 0.45-1.2 s (tempo applied), eased from one to the next
    with minimum-jerk profiles, starting from a standing pose. Each key draws the arms, the
    spine and the neck anywhere within their limits (pulled toward the rest pose by a random
    factor), and the legs as one of three stances: both feet planted with a symmetric knee
    bend, or one foot planted (bent a little, kept flat) and the other leg free within its
    limits; a third of the keys bend over at the hips (the pelvis tilted forward 20-85
    degrees, the hips flexed by as much so the legs keep their stance, hip flexion at most
    120 degrees). It covers poses the scored actions never reach; it is made for single-frame
    training data: feet can slide while the stance changes.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.ndimage import gaussian_filter1d
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from mocaprig.errors import ValidationError
from mocaprig.process.body.kinematics import Kinematics, forward_kinematics
from mocaprig.process.body.motion import Motion, concatenate
from mocaprig.process.body.shape import HEEL_FRACTION, BodyShape
from mocaprig.process.body.skeleton import DOF_LIMITS_RAD, DOF_NAMES, JOINT_INDEX, NUM_DOF, POSE_DIM
from mocaprig.validation import check_positive

__all__ = [
    "PROCEDURAL_MOTIONS",
    "floor_clearance_m",
    "make_motion",
    "session_motion",
]

_log = logging.getLogger(__name__)

PROCEDURAL_MOTIONS: tuple[str, ...] = (
    "t_pose",
    "clap",
    "jumping_jacks",
    "punch_kick",
    "squat",
    "wave",
    "karate",
    "freestyle",
)

_G_M_S2 = 9.81
_DOF = {name: i for i, name in enumerate(DOF_NAMES)}
_LIMITS_DEG = np.rad2deg(DOF_LIMITS_RAD)

FloatArray = npt.NDArray[np.float64]


# --------------------------------------------------------------------------------------------
# Floor contact


def floor_clearance_m(kin: Kinematics, shape: BodyShape) -> FloatArray:
    """Height of the lowest sole point above the floor (z = 0), shape ``(...)``, metres.

    The sole is modelled by three spheres per foot that touch the floor in the rest stance:
    the heel (behind and below the ankle, radius ``foot_radius_m``), the ball of the foot
    (ToeBase joint, ``foot_radius_m``) and the toe tip (ToeEnd joint, ``toe_radius_m``).
    Negative values mean the foot is below the floor.
    """
    p = kin.positions_m
    r = kin.rotations
    heel_local = np.array(
        [0.0, -HEEL_FRACTION * shape.foot_length_m, shape.foot_radius_m - shape.ankle_height_m]
    )
    out: list[FloatArray] = []
    for side in ("Right", "Left"):
        foot = JOINT_INDEX[f"{side}Foot"]
        heel_z = p[..., foot, 2] + r[..., foot, 2, :] @ heel_local
        out.append(heel_z - shape.foot_radius_m)
        out.append(p[..., JOINT_INDEX[f"{side}ToeBase"], 2] - shape.foot_radius_m)
        out.append(p[..., JOINT_INDEX[f"{side}ToeEnd"], 2] - shape.toe_radius_m)
    return np.asarray(np.min(np.stack(out, axis=-1), axis=-1))


# --------------------------------------------------------------------------------------------
# Score helpers (angles in degrees, (T, 27))


def _ease(x: FloatArray) -> FloatArray:
    """Minimum-jerk ramp 0 -> 1 over x in [0, 1] (clamped outside)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def _pulse(t: FloatArray, start: float, rise: float, hold: float, fall: float) -> FloatArray:
    """0 -> 1 (min-jerk over ``rise``), hold, 1 -> 0 (over ``fall``); times in seconds."""
    return _ease((t - start) / rise) - _ease((t - start - rise - hold) / fall)


def _both(a: FloatArray, dof: str, value: FloatArray | float) -> None:
    a[:, _DOF[f"left_{dof}"]] += value
    a[:, _DOF[f"right_{dof}"]] += value


def _side(a: FloatArray, side: str, dof: str, value: FloatArray | float) -> None:
    a[:, _DOF[f"{side}_{dof}"]] += value


@dataclass(frozen=True, slots=True)
class _Take:
    """One take's timing and variation."""

    t: FloatArray  # (T,) seconds from the start
    tempo: float
    amp: float
    phase_s: float
    shape: BodyShape
    rng: np.random.Generator

    def cycle(self, period_s: float) -> tuple[FloatArray, float]:
        """Time within the current cycle (s) and the cycle's length, tempo applied."""
        p = period_s / self.tempo
        return (self.t + self.phase_s * p) % p, p


@dataclass(frozen=True, slots=True)
class _Score:
    angles_deg: FloatArray  # (T, 27)
    support: FloatArray  # (T, 2): weight of the right and left foot as the anchor
    flight_m: FloatArray  # (T,) extra root height in flight
    noise_deg: float = 0.8
    pitch_deg: FloatArray | None = None  # (T,) pelvis tilted forward about its X axis


def _stance_feet(a: FloatArray, knee: FloatArray | float, hip: FloatArray | float) -> None:
    """Bend both legs with the feet flat: dorsiflexion = knee flexion - hip flexion."""
    _both(a, "knee_flexion", knee)
    _both(a, "hip_flexion", hip)
    _both(a, "ankle_dorsiflexion", np.asarray(knee) - np.asarray(hip))


def _zeros(take: _Take) -> tuple[FloatArray, FloatArray, FloatArray]:
    n = take.t.size
    return np.zeros((n, NUM_DOF)), np.full((n, 2), 0.5), np.zeros(n)


def _t_pose(take: _Take) -> _Score:
    a, sup, fl = _zeros(take)
    _both(a, "shoulder_abduction", 90.0)
    return _Score(a, sup, fl, noise_deg=0.25)


def _arm_ik(
    shape: BodyShape, base_deg: FloatArray, target_m: FloatArray, prefer_deg: FloatArray
) -> FloatArray:
    """Right-arm (flexion, abduction, internal rotation, elbow flexion) in degrees putting the
    palm centre (midway wrist -> knuckles) at ``target_m`` (body frame, root at the origin)."""
    names = [
        "right_shoulder_flexion",
        "right_shoulder_abduction",
        "right_shoulder_internal_rotation",
        "right_elbow_flexion",
    ]
    idx = [_DOF[n] for n in names]
    lo = DOF_LIMITS_RAD[idx, 0]
    hi = DOF_LIMITS_RAD[idx, 1]
    hand, knuckle = JOINT_INDEX["RightHand"], JOINT_INDEX["RightHandEnd"]

    def residual(x: FloatArray) -> FloatArray:
        pose = np.zeros(POSE_DIM)
        pose[6:] = np.deg2rad(base_deg)
        pose[[6 + i for i in idx]] = x
        p = forward_kinematics(pose, shape).positions_m
        palm = 0.5 * (p[hand] + p[knuckle])
        return np.concatenate([palm - target_m, 0.02 * (x - np.deg2rad(prefer_deg))])

    x0 = np.clip(np.deg2rad(prefer_deg), lo + 1e-6, hi - 1e-6)
    sol = least_squares(residual, x0, bounds=(lo, hi), xtol=1e-10, ftol=1e-10)
    return np.asarray(np.rad2deg(sol.x))


def _clap(take: _Take) -> _Score:
    a, sup, fl = _zeros(take)
    s = take.shape
    base = np.zeros(NUM_DOF)
    rest = forward_kinematics(np.zeros(POSE_DIM), s).positions_m
    chest = rest[JOINT_INDEX["Spine2"]]
    reach = 0.17 * s.height_m
    prefer = np.array([70.0, 0.0, 20.0, 40.0])
    closed = _arm_ik(s, base, chest + np.array([0.016, reach, 0.06]), prefer)
    opened = _arm_ik(
        s, base, chest + np.array([0.13 + 0.08 * take.amp, 0.85 * reach, 0.06]), prefer
    )
    tc, p = take.cycle(0.5)
    closeness = ((1.0 + np.cos(2.0 * np.pi * tc / p)) / 2.0) ** 1.5
    for k, dof in enumerate(
        ("shoulder_flexion", "shoulder_abduction", "shoulder_internal_rotation", "elbow_flexion")
    ):
        _both(a, dof, opened[k] + closeness * (closed[k] - opened[k]))
    _stance_feet(a, 4.0, 3.0)
    _both(a, "hip_abduction", 4.0)
    return _Score(a, sup, fl, noise_deg=0.3)


def _jumping_jacks(take: _Take) -> _Score:
    a, sup, fl = _zeros(take)
    tc, p = take.cycle(1.1)
    flight = 0.2
    t_out, t_in = 0.02 * p, 0.52 * p
    legs = _ease((tc - t_out) / flight) - _ease((tc - t_in) / flight)
    arms = _ease((tc - t_out) / (0.46 * p)) - _ease((tc - t_in) / (0.46 * p))
    _both(a, "hip_abduction", 20.0 * take.amp * legs)
    _both(a, "shoulder_abduction", min(172.0, 160.0 * take.amp) * arms)
    _both(a, "elbow_flexion", 10.0 + 10.0 * np.sin(np.pi * arms))
    knee = np.full(tc.shape, 6.0)
    ankle_extra = np.zeros(tc.shape)
    for start in (t_out, t_in):
        s_f = tc - start
        in_flight = (s_f >= 0.0) & (s_f <= flight)
        fl = fl + np.where(in_flight, 0.5 * _G_M_S2 * s_f * (flight - s_f), 0.0)
        ankle_extra += np.where(in_flight, -25.0 * np.sin(np.pi * s_f / flight), 0.0)
        nxt = (t_in if start == t_out else t_out + p) - (start + flight)
        s_st = ((tc - start - flight) % p) / nxt
        in_stance = (s_st >= 0.0) & (s_st <= 1.0) & ~in_flight
        knee = knee + np.where(in_stance, 24.0 * take.amp * np.sin(np.pi * s_st), 0.0)
    hip = 0.6 * (knee - 6.0) + 3.0
    _stance_feet(a, knee, hip)
    _both(a, "ankle_dorsiflexion", ankle_extra)
    return _Score(a, sup, fl)


def _guard(a: FloatArray) -> None:
    _both(a, "shoulder_flexion", 40.0)
    _both(a, "shoulder_abduction", 12.0)
    _both(a, "shoulder_internal_rotation", 35.0)
    _both(a, "elbow_flexion", 125.0)
    a[:, _DOF["spine_flexion"]] += 5.0


def _punch(
    a: FloatArray, side: str, strike: FloatArray, *, chamber: tuple[float, ...], twist: float
) -> None:
    """Add a straight punch of ``side`` (strike 0 -> 1) from the ``chamber`` arm angles
    (flexion, abduction, internal rotation, elbow flexion, pronation) to full extension."""
    extended = (88.0, 4.0, 10.0, 5.0, 70.0)
    dofs = (
        "shoulder_flexion",
        "shoulder_abduction",
        "shoulder_internal_rotation",
        "elbow_flexion",
        "elbow_pronation",
    )
    for dof, c, e in zip(dofs, chamber, extended, strict=True):
        _side(a, side, dof, (e - c) * strike)
    a[:, _DOF["spine_axial_twist"]] += (twist if side == "right" else -twist) * strike


def _front_kick(
    a: FloatArray, side: str, t: FloatArray, start: float, times: tuple[float, float, float, float]
) -> FloatArray:
    """Add a snapping front kick of ``side``: chamber, snap, re-chamber, lower (seconds).

    Returns the kick's activity (0..1) for the support weights."""
    c, s, r, lo = times
    up = _ease((t - start) / c) - _ease((t - start - c - s - r) / lo)
    snap = _ease((t - start - c) / s) - _ease((t - start - c - s) / r)
    _side(a, side, "hip_flexion", 72.0 * up)
    _side(a, side, "knee_flexion", 90.0 * up - 88.0 * snap)
    _side(a, side, "ankle_dorsiflexion", -30.0 * snap - 10.0 * up)
    return np.asarray(_pulse(t, start - 0.1, 0.1, c + s + r + lo, 0.1))


def _punch_kick(take: _Take) -> _Score:
    a, sup, fl = _zeros(take)
    tc, p = take.cycle(2.6)
    _guard(a)
    _stance_feet(a, 12.0, 8.0)
    _both(a, "hip_abduction", 6.0)
    ext = float(np.clip(0.18 / take.tempo, 0.15, 0.25))
    chamber = (40.0, 12.0, 35.0, 125.0, 0.0)
    _punch(a, "right", _pulse(tc, 0.25 * take.tempo, ext, 0.06, 0.25), chamber=chamber, twist=15)
    _punch(a, "left", _pulse(tc, 0.95 * take.tempo, ext, 0.06, 0.25), chamber=chamber, twist=20)
    kick = _front_kick(a, "right", tc, 1.6 * take.tempo, (0.16, 0.13, 0.18, 0.22))
    sup[:, 0] = 0.5 * (1.0 - kick)
    sup[:, 1] = 1.0 - sup[:, 0]
    # The kicking leg's ankle no longer follows the flat-foot rule while it is off the floor.
    _side(a, "right", "ankle_dorsiflexion", -kick * (12.0 - 8.0))
    del p
    return _Score(a, sup, fl)


def _squat(take: _Take) -> _Score:
    a, sup, fl = _zeros(take)
    tc, p = take.cycle(3.2)
    down, hold = 0.375 * p, 0.125 * p
    depth = _pulse(tc, 0.0625 * p, down, hold, down)
    hip = 95.0 * take.amp * depth + 2.0
    knee = 110.0 * take.amp * depth + 3.0
    _stance_feet(a, knee, hip)
    _both(a, "hip_abduction", 6.0)
    a[:, _DOF["spine_flexion"]] += 25.0 * take.amp * depth
    _both(a, "shoulder_flexion", 85.0 * depth)
    _both(a, "elbow_flexion", 8.0)
    return _Score(a, sup, fl)


def _wave(take: _Take) -> _Score:
    a, sup, fl = _zeros(take)
    tc, p = take.cycle(4.5)
    raise_s = 0.7 / 4.5 * p
    wave_s = 2.4 / 4.5 * p
    up = _pulse(tc, 0.05 * p, raise_s, wave_s, raise_s)
    _side(a, "right", "shoulder_abduction", 95.0 * take.amp * up)
    _side(a, "right", "elbow_flexion", 95.0 * up)
    swing = 22.0 * take.amp * np.sin(2.0 * np.pi * 2.2 * take.tempo * tc)
    _side(a, "right", "shoulder_internal_rotation", (-65.0 + swing) * up)
    _both(a, "shoulder_abduction", 5.0)
    _side(a, "left", "elbow_flexion", 10.0)
    a[:, _DOF["neck_axial_rotation"]] += 5.0 * up
    _stance_feet(a, 4.0, 3.0)
    return _Score(a, sup, fl)


def _karate(take: _Take) -> _Score:
    a, sup, fl = _zeros(take)
    tc, p = take.cycle(3.6)
    _stance_feet(a, 22.0, 14.0)
    _both(a, "hip_abduction", 14.0)
    chamber = (-25.0, 10.0, 0.0, 100.0, -80.0)
    for dof, v in zip(
        (
            "shoulder_flexion",
            "shoulder_abduction",
            "shoulder_internal_rotation",
            "elbow_flexion",
            "elbow_pronation",
        ),
        chamber,
        strict=True,
    ):
        _both(a, dof, v)
    ext = float(np.clip(0.16 / take.tempo, 0.15, 0.2))
    _punch(a, "right", _pulse(tc, 0.3 * take.tempo, ext, 0.15, 0.35), chamber=chamber, twist=18)
    _punch(a, "left", _pulse(tc, 1.2 * take.tempo, ext, 0.15, 0.35), chamber=chamber, twist=18)
    kick = _front_kick(a, "right", tc, 2.1 * take.tempo, (0.12, 0.09, 0.12, 0.18))
    sup[:, 0] = 0.5 * (1.0 - kick)
    sup[:, 1] = 1.0 - sup[:, 0]
    _side(a, "right", "ankle_dorsiflexion", -kick * (22.0 - 14.0))
    del p
    return _Score(a, sup, fl)


#: Per-DOF (low, high) ranges (degrees) the free ``freestyle`` keys draw from: the limits,
#: except where the extremes look like nothing a person does on purpose.
_FREE_RANGE_DEG: dict[str, tuple[float, float]] = {
    "spine_flexion": (-15.0, 60.0),
    "spine_lateral_bend": (-25.0, 25.0),
    "spine_axial_twist": (-30.0, 30.0),
    "neck_flexion": (-30.0, 40.0),
    "neck_axial_rotation": (-60.0, 60.0),
    "shoulder_flexion": (-40.0, 175.0),
    "shoulder_abduction": (-20.0, 170.0),
    "shoulder_internal_rotation": (-80.0, 80.0),
    "elbow_flexion": (0.0, 140.0),
    "elbow_pronation": (-80.0, 75.0),
    "hip_flexion": (-25.0, 110.0),
    "hip_abduction": (-15.0, 40.0),
    "hip_internal_rotation": (-40.0, 30.0),
    "knee_flexion": (0.0, 130.0),
    "ankle_dorsiflexion": (-40.0, 15.0),
    "ankle_inversion": (-15.0, 20.0),
}


def _free_angle(rng: np.random.Generator, dof: str, pull: float) -> float:
    lo, hi = _FREE_RANGE_DEG[dof]
    return pull * float(rng.uniform(lo, hi))


_ARM_DOFS = (
    "shoulder_flexion",
    "shoulder_abduction",
    "shoulder_internal_rotation",
    "elbow_flexion",
    "elbow_pronation",
)
_LEG_DOFS = (
    "hip_flexion",
    "hip_abduction",
    "hip_internal_rotation",
    "knee_flexion",
    "ankle_dorsiflexion",
    "ankle_inversion",
)


def _free_limb(a: FloatArray, side: str, dofs: tuple[str, ...], rng: np.random.Generator) -> None:
    """Add one free limb to key ``a`` (1, 27): one pull toward rest for the whole limb."""
    pull = float(rng.uniform(0.3, 1.0))
    for dof in dofs:
        _side(a, side, dof, _free_angle(rng, dof, pull))


#: Share of ``freestyle`` keys bent forward at the hips, and the pelvis tilt they draw (deg).
_BEND_SHARE = 0.35
_BEND_DEG = (20.0, 85.0)
#: Hip flexion a bent key may reach (deg; the limit is 125): a deeper tilt is cut to it.
_HIP_FLEXION_MAX_DEG = 120.0


def _freestyle_key(rng: np.random.Generator) -> tuple[FloatArray, FloatArray, float]:
    """One random key: angles (27,) degrees, support weights (right, left) and the pelvis's
    forward tilt (degrees)."""
    a = np.zeros((1, NUM_DOF))
    pull = float(rng.uniform(0.3, 1.0))
    for dof in ("spine_flexion", "spine_lateral_bend", "spine_axial_twist"):
        a[0, _DOF[dof]] = _free_angle(rng, dof, 0.7 * pull)
    for dof in ("neck_flexion", "neck_axial_rotation"):
        a[0, _DOF[dof]] = _free_angle(rng, dof, pull)
    for side in ("left", "right"):
        _free_limb(a, side, _ARM_DOFS, rng)
    stance = int(rng.integers(3))  # 0: both feet planted, 1: right planted, 2: left planted
    if stance == 0:
        knee = float(rng.uniform(0.0, 110.0)) * float(rng.uniform(0.0, 1.0))
        _stance_feet(a, knee, 0.8 * knee)
        _both(a, "hip_abduction", float(rng.uniform(-3.0, 15.0)))
        support = np.array([0.5, 0.5])
    else:
        planted, free = ("right", "left") if stance == 1 else ("left", "right")
        knee = float(rng.uniform(0.0, 35.0))
        hip = 0.8 * knee
        _side(a, planted, "knee_flexion", knee)
        _side(a, planted, "hip_flexion", hip)
        _side(a, planted, "ankle_dorsiflexion", knee - hip)
        _side(a, planted, "hip_abduction", float(rng.uniform(-5.0, 10.0)))
        _free_limb(a, free, _LEG_DOFS, rng)
        support = np.array([1.0, 0.0]) if stance == 1 else np.array([0.0, 1.0])
    # Bending over to reach the floor tilts the pelvis, not only the spine (whose flexion
    # stops near 60 degrees): the hips flex by the tilt so the legs keep their stance.
    pitch = float(rng.uniform(*_BEND_DEG)) if rng.random() < _BEND_SHARE else 0.0
    hips = [a[0, _DOF[f"{side}_hip_flexion"]] for side in ("left", "right")]
    pitch = max(0.0, min(pitch, _HIP_FLEXION_MAX_DEG - max(hips)))
    _both(a, "hip_flexion", pitch)
    return a[0], support, pitch


def _freestyle(take: _Take) -> _Score:
    a, sup, fl = _zeros(take)
    rng = take.rng
    end = float(take.t[-1])
    times, keys, supports = [0.0], [np.zeros(NUM_DOF)], [np.array([0.5, 0.5])]
    pitches = [0.0]
    while times[-1] <= end:
        times.append(times[-1] + float(rng.uniform(0.45, 1.2)) / take.tempo)
        key, support, pitch = _freestyle_key(rng)
        keys.append(take.amp * key)
        supports.append(support)
        pitches.append(take.amp * pitch)
    k = np.searchsorted(np.asarray(times), take.t, side="right") - 1
    t0 = np.asarray(times)[k]
    t1 = np.asarray(times)[k + 1]
    w = _ease((take.t - t0) / (t1 - t0))[:, None]
    key_arr, sup_arr = np.asarray(keys), np.asarray(supports)
    a += (1.0 - w) * key_arr[k] + w * key_arr[k + 1]
    # Between keys the weight lies on every foot planted at either end (both when the planted
    # foot changes), so the root follows the feet that carry it.
    both = np.maximum(sup_arr[k], sup_arr[k + 1])
    sup[:] = both / both.sum(axis=1, keepdims=True)
    pitch_arr = np.asarray(pitches)
    pitch = (1.0 - w[:, 0]) * pitch_arr[k] + w[:, 0] * pitch_arr[k + 1]
    return _Score(a, sup, fl, noise_deg=1.0, pitch_deg=pitch)


_GENERATORS: dict[str, Callable[[_Take], _Score]] = {
    "t_pose": _t_pose,
    "clap": _clap,
    "jumping_jacks": _jumping_jacks,
    "punch_kick": _punch_kick,
    "squat": _squat,
    "wave": _wave,
    "karate": _karate,
    "freestyle": _freestyle,
}


def _smooth_noise(
    rng: np.random.Generator, shape: tuple[int, ...], sigma_frames: float
) -> FloatArray:
    """Low-pass Gaussian noise of unit standard deviation along axis 0."""
    white = rng.normal(size=shape)
    smooth = gaussian_filter1d(white, sigma=max(sigma_frames, 1e-3), axis=0, mode="reflect")
    std = float(np.std(smooth)) or 1.0
    return np.asarray(smooth / std)


def _place_root(
    angles_rad: FloatArray,
    yaw_rad: FloatArray,
    support: FloatArray,
    flight_m: FloatArray,
    shape: BodyShape,
    pitch_rad: FloatArray | None = None,
) -> FloatArray:
    """Poses (T, 33) with the root placed so the feet stand on the floor and do not slide;
    ``pitch_rad`` (T,) tilts the pelvis forward (toward +Y, the facing) after the heading."""
    n = angles_rad.shape[0]
    poses = np.zeros((n, POSE_DIM))
    if pitch_rad is None:
        poses[:, 2] = yaw_rad
    else:
        # Heading about world Z, then the forward tilt about the pelvis's X (-X: top to +Y).
        tilt = Rotation.from_euler("ZX", np.stack([yaw_rad, -pitch_rad], axis=-1))
        poses[:, 0:3] = tilt.as_rotvec()
    poses[:, 6:] = angles_rad
    kin = forward_kinematics(poses, shape)
    feet = kin.positions_m[:, [JOINT_INDEX["RightFoot"], JOINT_INDEX["LeftFoot"]], :2]
    step = np.diff(feet, axis=0)  # (T-1, 2, 2)
    root_step = -np.einsum("tk,tkc->tc", support[1:], step)
    root_xy = np.concatenate([np.zeros((1, 2)), np.cumsum(root_step, axis=0)], axis=0)
    root_xy -= feet[0].mean(axis=0)
    poses[:, 3:5] = root_xy
    poses[:, 5] = -floor_clearance_m(kin, shape) + flight_m
    return poses


def make_motion(
    name: str,
    *,
    seconds: float,
    rng: np.random.Generator,
    rate_hz: float = 240.0,
    shape: BodyShape | None = None,
) -> Motion:
    """One take of a built-in procedural motion.

    Args:
        name: One of :data:`PROCEDURAL_MOTIONS`.
        seconds: Length of the take (s); the motion has ``round(seconds * rate_hz) + 1``
            frames.
        rng: Source of the take's variation (tempo, amplitude, phase, noise).
        rate_hz: Frame rate (Hz).
        shape: The subject (default: a 1.75 m Drillis & Contini body); used to stand the feet
            on the floor and to aim the hands (clap).

    Returns:
        The motion, named ``name``, all angles within the limits, facing +Y, feet on the floor
        around the origin.

    Raises:
        ValidationError: unknown name or a non-positive duration or rate.
    """
    if name not in _GENERATORS:
        msg = f"unknown procedural motion {name!r}; choose one of {', '.join(PROCEDURAL_MOTIONS)}"
        raise ValidationError(msg)
    check_positive(float(seconds), name="seconds")
    check_positive(float(rate_hz), name="rate_hz")
    body = shape if shape is not None else BodyShape.from_height(1.75)
    n = round(seconds * rate_hz) + 1
    t = np.arange(n, dtype=np.float64) / rate_hz
    still = name == "t_pose"
    take = _Take(
        t=t,
        tempo=1.0 if still else float(rng.uniform(0.88, 1.12)),
        amp=1.0 if still else float(rng.uniform(0.88, 1.08)),
        phase_s=0.0,
        shape=body,
        rng=rng,
    )
    score = _GENERATORS[name](take)
    noise = _smooth_noise(rng, (n, NUM_DOF + 1), 0.3 * rate_hz)
    angles = score.angles_deg + score.noise_deg * noise[:, :NUM_DOF]
    angles = np.clip(np.deg2rad(angles), DOF_LIMITS_RAD[:, 0], DOF_LIMITS_RAD[:, 1])
    yaw = np.deg2rad(0.5 * score.noise_deg) * noise[:, NUM_DOF]
    pitch = None if score.pitch_deg is None else np.deg2rad(score.pitch_deg)
    poses = _place_root(angles, yaw, score.support, score.flight_m, body, pitch)
    _log.debug(
        "procedural %s: %d frames, tempo %.3f, amplitude %.3f", name, n, take.tempo, take.amp
    )
    return Motion(name, float(rate_hz), poses)


def session_motion(
    names: Sequence[str],
    *,
    seconds: float,
    rng: np.random.Generator,
    static_start_s: float = 2.0,
    rate_hz: float = 240.0,
    shape: BodyShape | None = None,
    blend_s: float = 0.3,
) -> Motion:
    """A whole simulated session: a static T-pose start, then the actions in order.

    The first ``static_start_s`` seconds hold the calibration T-pose (``t_pose``); the rest of
    the ``seconds`` is split evenly between ``names`` (each action's take is lengthened by the
    ``blend_s`` overlap it shares with its predecessor). Clips are joined with
    :func:`mocaprig.process.body.motion.concatenate` (root continuity, smooth cross-fades), then any
    frame whose blended pose would push a foot through the floor has its root raised.

    Args:
        names: Actions from :data:`PROCEDURAL_MOTIONS`, in order (may be empty: T-pose only).
        seconds: Total length (s), > ``static_start_s``.
        rng: Randomness for every take.
        static_start_s: Length of the T-pose start (s), >= 0.
        rate_hz: Frame rate (Hz).
        shape: The subject (default 1.75 m).
        blend_s: Cross-fade between consecutive clips (s).

    Raises:
        ValidationError: unknown names, or lengths that do not fit.
    """
    check_positive(float(seconds), name="seconds")
    unknown = [n for n in names if n not in _GENERATORS]
    if unknown:
        msg = f"unknown procedural motion(s) {unknown}; choose from {', '.join(PROCEDURAL_MOTIONS)}"
        raise ValidationError(msg)
    if not (0.0 <= static_start_s < seconds or (not names and static_start_s >= 0.0)):
        msg = f"static_start_s must lie in [0, seconds={seconds}), got {static_start_s!r}"
        raise ValidationError(msg)
    body = shape if shape is not None else BodyShape.from_height(1.75)
    if not names:
        return make_motion("t_pose", seconds=seconds, rng=rng, rate_hz=rate_hz, shape=body)
    each = (seconds - static_start_s) / len(names)
    clips: list[Motion] = []
    if static_start_s > 0.0:
        clips.append(
            make_motion("t_pose", seconds=static_start_s, rng=rng, rate_hz=rate_hz, shape=body)
        )
    for i, n in enumerate(names):
        length = each + (blend_s if clips or i > 0 else 0.0)
        clips.append(make_motion(n, seconds=length, rng=rng, rate_hz=rate_hz, shape=body))
    joined = concatenate(clips, blend_s=blend_s, name="session:" + "+".join(names))
    poses = np.array(joined.poses)
    clearance = floor_clearance_m(forward_kinematics(poses, body), body)
    poses[:, 5] -= np.minimum(clearance, 0.0)
    return Motion(joined.name, joined.rate_hz, poses)
