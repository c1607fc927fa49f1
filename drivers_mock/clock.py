"""Device clocks: how each simulated device's own time relates to the session clock.

The *session clock* is the world's true time, integer nanoseconds from the start of the
simulated session (``t_ns``). Every device keeps its own clock, modelled as an affine map plus
timestamping jitter (realsense-d415.md §4.5: ``host = offset + (1 + ppm·1e-6)·device``)::

    device_ns(t_ns) = offset_ns + t_ns · (1 + drift_ppm · 1e-6)
    device_ticks(t_ns) = floor((device_ns(t_ns) + jitter(t_ns)) / unit_ns)

``jitter`` is zero-mean Gaussian with standard deviation ``jitter_ns``; it is a deterministic
function of ``(seed, t_ns)`` (a counter-based hash), so the same instant always gets the same
stamp and no generator state is shared between callers. The inverse, :meth:`DeviceClock.session_ns`,
undoes the affine part only; stamping then un-stamping a time returns it to within one tick plus
the jitter.

Defaults (see :func:`davis_clock`, :func:`d415_clock`, :func:`vicon_clock`):

* DAVIS240C: 1 µs ticks (davis240c-usb.md §7), arbitrary offset of seconds, drift ±30 ppm,
  1 µs jitter;
* D415: hardware clock in µs (realsense-d415.md §2.5, the u32 wrap is the D415 mock's business),
  offset = seconds of uptime, drift ±50 ppm, 5 µs jitter;
* Vicon: a frame clock (ticks in ns; frame ``n`` is at device time ``n / rate``), offset = the
  frames counted since the Vicon system started, drift ±10 ppm, no jitter (genlocked cameras).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from mocaprig.errors import ValidationError

__all__ = ["DeviceClock", "d415_clock", "davis_clock", "hash_normal", "vicon_clock"]

I64 = npt.NDArray[np.int64]

_MASK64 = np.uint64(0xFFFFFFFFFFFFFFFF)


def _splitmix64(x: npt.NDArray[np.uint64]) -> npt.NDArray[np.uint64]:
    with np.errstate(over="ignore"):
        z = x + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return z ^ (z >> np.uint64(31))


def _hash_normal(seed: int, t_ns: I64) -> npt.NDArray[np.float64]:
    """Standard normal values, a deterministic function of ``(seed, t_ns)`` (Box–Muller)."""
    key = t_ns.astype(np.uint64) ^ _splitmix64(np.array([seed & 0xFFFFFFFFFFFFFFFF], np.uint64))
    h1 = _splitmix64(key)
    h2 = _splitmix64(h1 ^ np.uint64(0xD1B54A32D192ED03))
    u1 = ((h1 >> np.uint64(11)).astype(np.float64) + 0.5) / 2.0**53
    u2 = (h2 >> np.uint64(11)).astype(np.float64) / 2.0**53
    out: npt.NDArray[np.float64] = np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * np.pi * u2)
    return out


def hash_normal(seed: int, keys: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Standard normal values, a deterministic function of ``(seed, key)`` for integer keys
    (e.g. session ns): the same instant always gets the same draw, whoever asks."""
    return _hash_normal(seed, _as_int64(keys, "keys"))


def _as_int64(x: npt.ArrayLike, name: str) -> I64:
    arr = np.asarray(x)
    if arr.dtype.kind not in "iu":
        if arr.dtype.kind == "f" and np.all(np.isfinite(arr)) and np.all(arr == np.round(arr)):
            return arr.astype(np.int64)
        msg = f"{name} must be integers (nanoseconds or ticks), got dtype {arr.dtype}"
        raise ValidationError(msg)
    return arr.astype(np.int64)


@dataclass(frozen=True, slots=True)
class DeviceClock:
    """An affine device clock with seeded timestamping jitter (module doc for the equations).

    Attributes:
        name: The device it belongs to (``"davis"``, ``"d415-0"``, ``"vicon"``).
        offset_ns: Device time (ns) at session time 0.
        drift_ppm: Rate error (ppm): the device clock advances ``1 + drift_ppm·1e-6`` device
            seconds per session second.
        jitter_ns: Standard deviation (ns) of the stamping jitter (≥ 0).
        unit_ns: The device's native tick (ns): 1000 for a µs counter.
        seed: Seed of the jitter hash.

    Raises:
        ValidationError: negative jitter, a non-positive unit or ``|drift_ppm| >= 1e4``.
    """

    name: str
    offset_ns: int
    drift_ppm: float
    jitter_ns: float = 0.0
    unit_ns: int = 1000
    seed: int = 0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.jitter_ns) and self.jitter_ns >= 0):
            msg = f"clock {self.name!r}: jitter_ns must be >= 0, got {self.jitter_ns!r}"
            raise ValidationError(msg)
        if self.unit_ns <= 0:
            msg = f"clock {self.name!r}: unit_ns must be a positive integer, got {self.unit_ns!r}"
            raise ValidationError(msg)
        if not (np.isfinite(self.drift_ppm) and abs(self.drift_ppm) < 1e4):
            msg = f"clock {self.name!r}: drift_ppm must be finite and below 1e4 in magnitude"
            raise ValidationError(msg)
        object.__setattr__(self, "offset_ns", int(self.offset_ns))
        object.__setattr__(self, "unit_ns", int(self.unit_ns))

    @property
    def rate(self) -> float:
        """Device seconds per session second, ``1 + drift_ppm·1e-6``."""
        return 1.0 + self.drift_ppm * 1e-6

    def device_ns(self, t_ns: npt.ArrayLike) -> I64:
        """Device time (ns) of session times, without jitter or quantisation.

        Args:
            t_ns: Session times (int ns), any shape.

        Returns:
            Device times (int64 ns), same shape.
        """
        t = _as_int64(t_ns, "t_ns")
        drift = np.round(t.astype(np.float64) * (self.drift_ppm * 1e-6)).astype(np.int64)
        out: I64 = self.offset_ns + t + drift
        return out

    def device_ticks(
        self, t_ns: npt.ArrayLike, *, unit_ns: int | None = None, jitter: bool = True
    ) -> I64:
        """The device's timestamps of session instants, in its native unit.

        Args:
            t_ns: Session times (int ns), any shape.
            unit_ns: Tick length (ns); default the clock's ``unit_ns``.
            jitter: Add the seeded stamping jitter (default).

        Returns:
            Ticks (int64), ``floor((device_ns + jitter) / unit_ns)``, same shape.
        """
        unit = self.unit_ns if unit_ns is None else int(unit_ns)
        if unit <= 0:
            msg = f"clock {self.name!r}: unit_ns must be > 0, got {unit}"
            raise ValidationError(msg)
        t = _as_int64(t_ns, "t_ns")
        d = self.device_ns(t)
        if jitter and self.jitter_ns > 0:
            noise = _hash_normal(self.seed, t.reshape(-1)).reshape(t.shape)
            d = d + np.round(noise * self.jitter_ns).astype(np.int64)
        out: I64 = np.floor_divide(d, unit)
        return out

    def session_ns(self, ticks: npt.ArrayLike, *, unit_ns: int | None = None) -> I64:
        """Session times (int ns) of device timestamps: the inverse of the affine part.

        Args:
            ticks: Device timestamps in ``unit_ns`` (int), any shape.
            unit_ns: Tick length (ns); default the clock's ``unit_ns``.

        Returns:
            Session times (int64 ns), same shape.
        """
        unit = self.unit_ns if unit_ns is None else int(unit_ns)
        x = _as_int64(ticks, "ticks") * unit - self.offset_ns
        eps = self.drift_ppm * 1e-6
        corr = np.round(x.astype(np.float64) * (eps / (1.0 + eps))).astype(np.int64)
        out: I64 = x - corr
        return out

    def to_dict(self) -> dict[str, object]:
        """A JSON-ready description (every parameter)."""
        return {
            "name": self.name,
            "offset_ns": self.offset_ns,
            "drift_ppm": self.drift_ppm,
            "jitter_ns": self.jitter_ns,
            "unit_ns": self.unit_ns,
            "seed": self.seed,
        }

    @classmethod
    def from_dict(cls, d: dict[str, object]) -> DeviceClock:
        """Rebuild a clock from :meth:`to_dict`'s output."""
        try:
            return cls(
                str(d["name"]),
                int(d["offset_ns"]),  # type: ignore[call-overload]
                float(d["drift_ppm"]),  # type: ignore[arg-type]
                float(d["jitter_ns"]),  # type: ignore[arg-type]
                int(d["unit_ns"]),  # type: ignore[call-overload]
                int(d["seed"]),  # type: ignore[call-overload]
            )
        except (KeyError, TypeError, ValueError) as err:
            msg = f"clock description {d!r} is incomplete or malformed ({err}); rewrite the truth"
            raise ValidationError(msg) from err


def _seed(rng: np.random.Generator) -> int:
    return int(rng.integers(0, 2**62))


def davis_clock(rng: np.random.Generator, *, name: str = "davis") -> DeviceClock:
    """A DAVIS240C clock: µs ticks, offset 0.5–20 s, drift ±30 ppm, 1 µs jitter."""
    return DeviceClock(
        name,
        offset_ns=int(rng.uniform(0.5, 20.0) * 1e9),
        drift_ppm=float(rng.uniform(-30.0, 30.0)),
        jitter_ns=1000.0,
        unit_ns=1000,
        seed=_seed(rng),
    )


def d415_clock(rng: np.random.Generator, *, name: str) -> DeviceClock:
    """A D415 hardware clock: µs ticks, offset 10–3000 s of uptime, drift ±50 ppm, 5 µs jitter."""
    return DeviceClock(
        name,
        offset_ns=int(rng.uniform(10.0, 3000.0) * 1e9),
        drift_ppm=float(rng.uniform(-50.0, 50.0)),
        jitter_ns=5000.0,
        unit_ns=1000,
        seed=_seed(rng),
    )


def vicon_clock(
    rng: np.random.Generator, *, rate_hz: float = 120.0, name: str = "vicon"
) -> DeviceClock:
    """The Vicon frame clock: ns ticks, offset = 10⁴–10⁶ whole frames, drift ±10 ppm, no jitter.

    Frame ``n`` of the Vicon system happens at device time ``round(n · 1e9 / rate_hz)`` ns.
    """
    frames = int(rng.integers(10_000, 1_000_000))
    return DeviceClock(
        name,
        offset_ns=round(frames * 1e9 / rate_hz),
        drift_ppm=float(rng.uniform(-10.0, 10.0)),
        jitter_ns=0.0,
        unit_ns=1,
        seed=_seed(rng),
    )
