"""A motion clip: a sequence of pose vectors at a fixed frame rate, and its operations.

A :class:`Motion` holds ``F`` pose vectors of the layout in :mod:`mocaprig.process.body.skeleton`
(``[root axis-angle (3), root translation m (3), 27 angles rad]``) sampled at ``rate_hz``; frame
``i`` is at ``t = i / rate_hz`` seconds from the start of the clip.

Operations are pure: :meth:`Motion.sample`, :meth:`Motion.resample` and :func:`concatenate`
return new arrays or clips and never touch their inputs.

Interpolation:

* the root rotation uses spherical linear interpolation (scipy ``Slerp``) between frames;
* root translation and the 27 joint angles use linear (default) or natural cubic-spline
  interpolation; cubic results are clipped back into the joint limits (a spline can overshoot).

Times outside ``[0, duration_s]`` are either clamped to the nearest end (``out_of_range="clamp"``,
the default: the clip holds its first or last pose) or rejected (``out_of_range="raise"``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, Slerp

from mocaprig.errors import ValidationError
from mocaprig.process.body.skeleton import DOF_LIMITS_RAD, POSE_DIM
from mocaprig.validation import check_finite, check_positive, check_shape

__all__ = ["Interpolation", "Motion", "OutOfRange", "blend_poses", "concatenate"]

Interpolation = Literal["linear", "cubic"]
OutOfRange = Literal["clamp", "raise"]

_ROT = slice(0, 3)
_TRANS = slice(3, 6)
_LINEAR = slice(3, POSE_DIM)


@dataclass(frozen=True, slots=True)
class Motion:
    """A named motion clip.

    Attributes:
        name: A label (e.g. ``"clap"`` or the BVH file stem).
        rate_hz: Frame rate (Hz), > 0.
        poses: Pose vectors, shape ``(F, 33)`` float64, ``F >= 1``, read-only (a copy of the
            array given).

    Raises:
        ValidationError: wrong shape, non-finite values or a non-positive rate.
    """

    name: str
    rate_hz: float
    poses: npt.NDArray[np.float64] = field(repr=False)

    def __post_init__(self) -> None:
        check_positive(float(self.rate_hz), name="Motion.rate_hz")
        poses = check_shape(self.poses, ["F", POSE_DIM], name="Motion.poses")
        if poses.shape[0] < 1:
            msg = f"Motion {self.name!r} has no frames; give at least one pose"
            raise ValidationError(msg)
        check_finite(poses, name="Motion.poses")
        arr = np.array(poses, dtype=np.float64, copy=True)
        arr.setflags(write=False)
        object.__setattr__(self, "poses", arr)
        object.__setattr__(self, "rate_hz", float(self.rate_hz))

    @property
    def num_frames(self) -> int:
        """Number of frames ``F``."""
        return int(self.poses.shape[0])

    @property
    def duration_s(self) -> float:
        """Time from the first to the last frame (s); 0 for a single frame."""
        return (self.num_frames - 1) / self.rate_hz

    @property
    def times_s(self) -> npt.NDArray[np.float64]:
        """Frame times (s) from the start of the clip, shape ``(F,)``."""
        return np.arange(self.num_frames, dtype=np.float64) / self.rate_hz

    def sample(
        self,
        t_s: npt.ArrayLike,
        *,
        method: Interpolation = "linear",
        out_of_range: OutOfRange = "clamp",
    ) -> npt.NDArray[np.float64]:
        """Interpolate the pose at arbitrary times.

        Args:
            t_s: Times (s) from the start of the clip, any shape ``S`` (a scalar gives ``(33,)``).
            method: ``"linear"`` or ``"cubic"`` for root translation and joint angles; the root
                rotation is always slerped.
            out_of_range: ``"clamp"`` holds the first/last pose outside ``[0, duration_s]``;
                ``"raise"`` rejects such times.

        Returns:
            Poses of shape ``S + (33,)`` float64.

        Raises:
            ValidationError: non-finite times, times out of range with ``out_of_range="raise"``,
                or an unknown ``method``.
        """
        t = np.asarray(check_finite(np.asarray(t_s, dtype=np.float64), name="t_s"))
        shape = t.shape
        flat = t.reshape(-1)
        dur = self.duration_s
        eps = 1e-9 * max(1.0, dur)
        if out_of_range not in ("clamp", "raise"):
            msg = f"out_of_range must be 'clamp' or 'raise', got {out_of_range!r}"
            raise ValidationError(msg)
        outside = bool(flat.size) and (flat.min() < -eps or flat.max() > dur + eps)
        if out_of_range == "raise" and outside:
            msg = (
                f"sample times span [{flat.min():.6g}, {flat.max():.6g}] s but motion "
                f"{self.name!r} covers [0, {dur:.6g}] s; pass out_of_range='clamp' to hold "
                "the end poses"
            )
            raise ValidationError(msg)
        if method not in ("linear", "cubic"):
            msg = f"method must be 'linear' or 'cubic', got {method!r}"
            raise ValidationError(msg)
        flat = np.clip(flat, 0.0, dur)
        out = np.empty((flat.size, POSE_DIM), dtype=np.float64)
        if self.num_frames == 1:
            out[:] = self.poses[0]
            return out.reshape(*shape, POSE_DIM)
        times = self.times_s
        rots = Rotation.from_rotvec(np.array(self.poses[:, _ROT]))
        out[:, _ROT] = Slerp(times, rots)(flat).as_rotvec()
        values = self.poses[:, _LINEAR]
        if method == "linear" or self.num_frames < 3:
            idx = np.clip(np.searchsorted(times, flat, side="right") - 1, 0, self.num_frames - 2)
            w = ((flat - times[idx]) * self.rate_hz)[:, None]
            out[:, _LINEAR] = (1.0 - w) * values[idx] + w * values[idx + 1]
        else:
            spline = CubicSpline(times, values, axis=0, bc_type="natural")
            out[:, _LINEAR] = spline(flat)
            out[:, 6:] = np.clip(out[:, 6:], DOF_LIMITS_RAD[:, 0], DOF_LIMITS_RAD[:, 1])
        return out.reshape(*shape, POSE_DIM)

    def resample(self, rate_hz: float, *, method: Interpolation = "linear") -> Motion:
        """The same motion at another frame rate.

        The new clip starts at the same instant and has ``floor(duration_s * rate_hz) + 1``
        frames, so its duration is at most the original's (by less than one new frame period).

        Raises:
            ValidationError: ``rate_hz`` is not a finite number > 0.
        """
        check_positive(float(rate_hz), name="rate_hz")
        n = int(np.floor(self.duration_s * rate_hz + 1e-9)) + 1
        t = np.arange(n, dtype=np.float64) / rate_hz
        return Motion(self.name, float(rate_hz), self.sample(t, method=method))

    def with_name(self, name: str) -> Motion:
        """The same poses under another name."""
        return Motion(name, self.rate_hz, self.poses)


def blend_poses(
    a: npt.ArrayLike, b: npt.ArrayLike, weight: npt.ArrayLike
) -> npt.NDArray[np.float64]:
    """Blend two pose arrays: slerp the root rotation, lerp everything else.

    Args:
        a: Poses, shape ``(..., 33)``.
        b: Poses, same shape as ``a``.
        weight: Blend weight in ``[0, 1]`` (0 gives ``a``), broadcastable to ``a.shape[:-1]``.

    Returns:
        Blended poses, shape of ``a``, float64. Joint angles stay inside any box (the limits)
        that holds both inputs.
    """
    pa = np.asarray(check_shape(a, ["...", POSE_DIM], name="a"), dtype=np.float64)
    pb = np.asarray(check_shape(b, ["...", POSE_DIM], name="b"), dtype=np.float64)
    if pa.shape != pb.shape:
        msg = f"cannot blend poses of shapes {pa.shape} and {pb.shape}"
        raise ValidationError(msg)
    w = np.broadcast_to(np.asarray(weight, dtype=np.float64), pa.shape[:-1])
    lead = pa.shape[:-1]
    fa = pa.reshape(-1, POSE_DIM)
    fb = pb.reshape(-1, POSE_DIM)
    fw = w.reshape(-1)
    out = (1.0 - fw)[:, None] * fa + fw[:, None] * fb
    if fa.shape[0]:
        ra = Rotation.from_rotvec(np.array(fa[:, _ROT]))
        rb = Rotation.from_rotvec(np.array(fb[:, _ROT]))
        delta = (ra.inv() * rb).as_rotvec()
        out[:, _ROT] = (ra * Rotation.from_rotvec(delta * fw[:, None])).as_rotvec()
    return out.reshape(*lead, POSE_DIM)


def _smoothstep(x: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def concatenate(
    motions: Sequence[Motion],
    *,
    blend_s: float = 0.3,
    name: str | None = None,
    rate_hz: float | None = None,
) -> Motion:
    """Join clips one after another with a smooth cross-fade.

    Each later clip is first resampled to the common rate (``rate_hz``, default the first
    clip's), then shifted horizontally (root x, y) so that, at the middle of the overlap, its root
    sits where the previous material's root is: the root does not jump. Root heights are kept
    (they encode how the feet meet the floor) and simply cross-faded. Over the overlap of
    ``blend_s`` seconds (shortened to fit clips shorter than that) the two poses are blended
    with a quintic smoothstep weight (zero velocity and acceleration of the weight at both ends),
    slerping the root rotation and interpolating everything else linearly. With
    ``blend_s == 0`` the clips are butted together with the same horizontal shift.

    The result lasts ``sum(durations) - overlaps`` (plus one frame period per butt joint).

    Args:
        motions: At least one clip.
        blend_s: Overlap length (s), >= 0.
        name: Name of the result (default: the clip names joined with ``"+"``).
        rate_hz: Frame rate of the result (default: the first clip's).

    Raises:
        ValidationError: no clips, or a negative ``blend_s``.
    """
    if len(motions) == 0:
        msg = "concatenate() needs at least one motion"
        raise ValidationError(msg)
    if not (np.isfinite(blend_s) and blend_s >= 0.0):
        msg = f"blend_s must be a finite number >= 0, got {blend_s!r}"
        raise ValidationError(msg)
    rate = float(motions[0].rate_hz if rate_hz is None else check_positive(rate_hz, name="rate_hz"))
    clips = [m if np.isclose(m.rate_hz, rate) else m.resample(rate) for m in motions]
    acc = np.array(clips[0].poses, dtype=np.float64)
    for clip in clips[1:]:
        nxt = np.array(clip.poses, dtype=np.float64)
        n_blend = round(blend_s * rate)
        n_blend = min(n_blend, acc.shape[0], nxt.shape[0])
        if n_blend <= 1:
            shift = acc[-1, 3:5] - nxt[0, 3:5]
            nxt[:, 3:5] += shift
            acc = np.concatenate([acc, nxt], axis=0)
            continue
        mid = n_blend // 2
        shift = acc[acc.shape[0] - n_blend + mid, 3:5] - nxt[mid, 3:5]
        nxt[:, 3:5] += shift
        w = _smoothstep(np.arange(n_blend, dtype=np.float64) / (n_blend - 1))
        blended = blend_poses(acc[-n_blend:], nxt[:n_blend], w)
        acc = np.concatenate([acc[:-n_blend], blended, nxt[n_blend:]], axis=0)
    label = "+".join(m.name for m in motions) if name is None else name
    return Motion(label, rate, acc)
