"""The clapperboard: a hinged prop with one retro-reflective marker on each arm's tip.

Geometry (world frame, metres): the hinge axis passes through ``hinge_m`` and is horizontal,
perpendicular to the arm direction ``u = (cos yaw, sin yaw, 0)``. The bottom arm is fixed and
horizontal, its top face at the hinge; the top arm rotates about the hinge axis by the opening
angle ``θ(t)`` (0 = closed, the two arms stacked). Each arm is ``arm_thickness_m`` thick; the
markers (radius ``marker_radius_m``) sit on the outer faces at ``arm_length_m`` from the hinge::

    BOTTOM = hinge + L·u − (h + r)·ẑ
    TOP    = hinge + L·(cos θ·u + sin θ·ẑ) + (h + r)·(−sin θ·u + cos θ·ẑ)

so at contact (θ = 0) the marker centres are ``2r + 2h`` apart: twice the marker radius plus
the board thickness (both arms).

Each clap ``k`` at ``clap_times_ns[k]`` (the contact instant) follows a realistic profile:
opening over ``opening_s`` (quintic ease, 0 → θmax of 30–40°), holding open ``hold_s``, then
closing in ``closing_s`` (60–120 ms) under constant angular acceleration from rest,
``θ = θmax·(1 − s²)`` with ``s`` going 0 → 1, so the arm is fastest at contact
(``2·θmax/closing_s`` ≈ 10–20 rad/s). It then stays closed until the next clap opens.

Those are the nominal world's values. A random world (:mod:`mocaprig.drivers_mock.world`) widens
the closing to 30–300 ms, changes the law to ``θ = θmax·(1 − s^p)`` (``closing_power`` p: 2 is
constant angular acceleration; larger p slams harder at the end) and may add a bounce: after
contact the arm reopens by ``bounce_rad`` along a half sine over ``bounce_s`` and closes again.
The clap instant stays the first contact.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from mocaprig.errors import ValidationError
from mocaprig.validation import check_finite, check_shape

__all__ = ["CLAPPER_MARKERS", "Clapperboard", "make_clapperboard"]

F64 = npt.NDArray[np.float64]

#: Marker names, in the order of the marker axis of :meth:`Clapperboard.markers_m`.
CLAPPER_MARKERS: tuple[str, str] = ("TOP", "BOTTOM")

#: Sessions must be at least this long for the two claps (plus the static start) to fit.
MIN_SESSION_S = 3.0


@dataclass(frozen=True, slots=True, eq=False)
class Clapperboard:
    """A hinged clapperboard with two tip markers (geometry and timing in the module doc).

    Attributes:
        hinge_m: A point of the hinge axis in the world (m), shape ``(3,)``.
        yaw_rad: Heading of the arms about +Z (rad); 0 points the arms along +X.
        clap_times_ns: Contact instants (session ns), increasing.
        open_angles_rad: Maximum opening of each clap (rad), one per clap.
        closing_s: Closing duration of each clap (s), one per clap.
        opening_s: Opening duration (s).
        hold_s: Time held fully open before closing (s).
        arm_length_m: Hinge-to-marker distance along an arm (m).
        arm_thickness_m: Thickness of one arm (m); the board is twice that when closed.
        marker_radius_m: Marker radius (m).
        closing_power: Exponent ``p`` of the closing law ``θmax·(1 − s^p)`` (2: constant
            angular acceleration from rest).
        bounce_rad: Reopening after contact (rad); 0: the arm stays closed.
        bounce_s: Duration of that bounce (s).

    Raises:
        ValidationError: inconsistent lengths, unordered or overlapping claps, bad geometry.
    """

    hinge_m: F64 = field(repr=False)
    yaw_rad: float
    clap_times_ns: tuple[int, ...]
    open_angles_rad: tuple[float, ...]
    closing_s: tuple[float, ...]
    opening_s: float = 0.4
    hold_s: float = 0.25
    arm_length_m: float = 0.30
    arm_thickness_m: float = 0.010
    marker_radius_m: float = 0.007
    closing_power: float = 2.0
    bounce_rad: float = 0.0
    bounce_s: float = 0.0

    def __post_init__(self) -> None:
        hinge = np.array(check_finite(check_shape(self.hinge_m, [3], name="hinge_m")), float)
        hinge.setflags(write=False)
        object.__setattr__(self, "hinge_m", hinge)
        n = len(self.clap_times_ns)
        if n == 0 or len(self.open_angles_rad) != n or len(self.closing_s) != n:
            msg = (
                "Clapperboard: give at least one clap and one open angle and closing time per "
                f"clap (got {n} claps, {len(self.open_angles_rad)} angles, "
                f"{len(self.closing_s)} closing times)"
            )
            raise ValidationError(msg)
        if any(not (0.0 < a < np.pi / 2) for a in self.open_angles_rad):
            msg = "Clapperboard: open angles must lie in (0, π/2) rad"
            raise ValidationError(msg)
        if any(c <= 0 for c in self.closing_s) or self.opening_s <= 0 or self.hold_s < 0:
            msg = "Clapperboard: closing_s and opening_s must be > 0 and hold_s >= 0"
            raise ValidationError(msg)
        if not (self.closing_power >= 1.0 and 0.0 <= self.bounce_rad < np.pi / 4):
            msg = "Clapperboard: closing_power must be >= 1 and bounce_rad in [0, π/4)"
            raise ValidationError(msg)
        if self.bounce_s < 0 or (self.bounce_rad > 0 and self.bounce_s <= 0):
            msg = "Clapperboard: bounce_s must be >= 0, and > 0 with a bounce"
            raise ValidationError(msg)
        if min(self.arm_length_m, self.arm_thickness_m, self.marker_radius_m) <= 0:
            msg = "Clapperboard: arm length, arm thickness and marker radius must be > 0"
            raise ValidationError(msg)
        for k in range(1, n):
            if self._open_start_ns(k) <= self.clap_times_ns[k - 1]:
                msg = (
                    f"Clapperboard: clap {k} starts opening before clap {k - 1} has closed; "
                    "space the claps further apart"
                )
                raise ValidationError(msg)

    @property
    def contact_distance_m(self) -> float:
        """Marker-centre distance when closed: ``2·marker_radius_m + 2·arm_thickness_m``."""
        return 2.0 * self.marker_radius_m + 2.0 * self.arm_thickness_m

    @property
    def marker_names(self) -> tuple[str, str]:
        """``("TOP", "BOTTOM")``."""
        return CLAPPER_MARKERS

    def _open_start_ns(self, k: int) -> int:
        span_s = self.opening_s + self.hold_s + self.closing_s[k]
        return int(self.clap_times_ns[k] - round(span_s * 1e9))

    def angle_rad(self, t_ns: npt.ArrayLike) -> F64:
        """Opening angle ``θ`` (rad) at session times (int ns), same shape as ``t_ns``."""
        t = np.asarray(t_ns, dtype=np.int64)
        out = np.zeros(t.shape, dtype=np.float64)
        for k, tc in enumerate(self.clap_times_ns):
            amax = self.open_angles_rad[k]
            t_close = tc - round(self.closing_s[k] * 1e9)
            t_hold = t_close - round(self.hold_s * 1e9)
            t_open = self._open_start_ns(k)
            dt = (t - t_open).astype(np.float64) * 1e-9
            x = np.clip(dt / self.opening_s, 0.0, 1.0)
            opening = amax * x * x * x * (x * (6.0 * x - 15.0) + 10.0)
            s = np.clip((t - t_close).astype(np.float64) * 1e-9 / self.closing_s[k], 0.0, 1.0)
            # s * s keeps the nominal law's floating-point values exactly.
            law = s * s if self.closing_power == 2.0 else s**self.closing_power
            closing = amax * (1.0 - law)
            theta = np.where(t < t_hold, opening, np.where(t < t_close, amax, closing))
            theta = np.where((t >= t_open) & (t < tc), theta, 0.0)
            out = np.maximum(out, theta)
            if self.bounce_rad > 0:
                b = (t - tc).astype(np.float64) * 1e-9 / self.bounce_s
                bounce = np.where((b > 0) & (b < 1), self.bounce_rad * np.sin(np.pi * b), 0.0)
                out = np.maximum(out, bounce)
        return out

    def markers_m(self, t_ns: npt.ArrayLike) -> F64:
        """Marker centres (m) at session times: shape ``t_ns.shape + (2, 3)``, TOP then BOTTOM."""
        theta = self.angle_rad(t_ns)
        u = np.array([np.cos(self.yaw_rad), np.sin(self.yaw_rad), 0.0])
        z = np.array([0.0, 0.0, 1.0])
        off = self.arm_thickness_m + self.marker_radius_m
        c = np.cos(theta)[..., None]
        s = np.sin(theta)[..., None]
        top = self.hinge_m + self.arm_length_m * (c * u + s * z) + off * (-s * u + c * z)
        bottom = np.broadcast_to(self.hinge_m + self.arm_length_m * u - off * z, top.shape)
        return np.stack([top, bottom], axis=-2)

    def to_dict(self) -> dict[str, object]:
        """A JSON-ready description."""
        return {
            "hinge_m": self.hinge_m.tolist(),
            "yaw_rad": self.yaw_rad,
            "clap_times_ns": list(self.clap_times_ns),
            "open_angles_rad": list(self.open_angles_rad),
            "closing_s": list(self.closing_s),
            "opening_s": self.opening_s,
            "hold_s": self.hold_s,
            "arm_length_m": self.arm_length_m,
            "arm_thickness_m": self.arm_thickness_m,
            "marker_radius_m": self.marker_radius_m,
            "closing_power": self.closing_power,
            "bounce_rad": self.bounce_rad,
            "bounce_s": self.bounce_s,
            "contact_distance_m": self.contact_distance_m,
            "marker_names": list(CLAPPER_MARKERS),
        }


def make_clapperboard(
    rng: np.random.Generator,
    *,
    seconds: float,
    static_start_s: float,
    closing_s: tuple[float, float] = (0.06, 0.12),
    closing_power: float = 2.0,
    bounce_rad: float = 0.0,
    bounce_s: float = 0.0,
) -> Clapperboard:
    """The scenario's clapperboard: in front of the actor, two claps.

    The hinge sits ≈ 0.8 m in front of the actor (+Y) and ≈ 0.35 m to its right at ≈ 1.25 m,
    the arms pointing away from the actor (+X, ± 10°), so every camera sees it. The first clap
    lands ≈ 0.8 s after the static start, the second ≈ 0.5 s before the end.

    Args:
        rng: The seeded generator (consumed).
        seconds: Session length (s), at least 3 s.
        static_start_s: Length of the static start (s).
        closing_s: Range (s) each clap's closing duration is drawn from.
        closing_power: The closing law's exponent (:class:`Clapperboard`).
        bounce_rad: Reopening after contact (rad).
        bounce_s: Duration of the bounce (s).

    Raises:
        ValidationError: the session is too short for two claps after the static start.
    """
    first_s = static_start_s + 0.8 + rng.uniform(0.0, 0.1)
    last_s = seconds - 0.5 - rng.uniform(0.0, 0.1)
    if seconds < MIN_SESSION_S or last_s - first_s < 0.85:
        msg = (
            f"a {seconds:g} s session with a {static_start_s:g} s static start is too short for "
            f"the two clapperboard claps; simulate at least {MIN_SESSION_S:g} s and at least "
            f"{static_start_s + 2.4:g} s"
        )
        raise ValidationError(msg)
    hinge = np.array([0.35, 0.8, 1.25]) + rng.normal(0.0, 0.03, size=3)
    return Clapperboard(
        hinge_m=hinge,
        yaw_rad=float(np.radians(rng.uniform(-10.0, 10.0))),
        clap_times_ns=(round(first_s * 1e9), round(last_s * 1e9)),
        open_angles_rad=tuple(float(np.radians(rng.uniform(30.0, 40.0))) for _ in range(2)),
        closing_s=tuple(float(rng.uniform(*closing_s)) for _ in range(2)),
        closing_power=closing_power,
        bounce_rad=bounce_rad,
        bounce_s=bounce_s,
    )
