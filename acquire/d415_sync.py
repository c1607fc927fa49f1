"""Hardware-sync verification for a D415 rig, as a streaming checker (realsense-d415.md §2.6).

"Frames are arriving" proves nothing: a slave in ``inter_cam_sync_mode`` 2 free-runs silently
when its trigger is lost (§2.4). :class:`SyncChecker` is fed the :class:`FrameTiming` of every
camera's framesets, in any interleaving across cameras, and checks:

* **timestamp domain**: ``system_time`` means no metadata; nothing can be verified (§2.6.1);
* **per-camera sanity**: ``0 ≤ frame_timestamp − sensor_timestamp ≤ 10⁶/fps`` µs (§2.6.2);
* **counter continuity**: ``frame_counter`` +1 per frame; gaps are drops, backward steps are
  counter resets (ESD, §2.4) (§2.6.3);
* **slave vs master, phase**: frames are paired by a constant counter offset (established once
  by time: global time when both cameras report it, else host receive time; §2.5), and each
  slave's hardware timestamps are fitted against the master's as
  ``t_slave = offset + (1 + drift)·t_master``. The residual of each new pair against a fit of
  the pairs older than one second is the **phase error**. A slave that *loses* its trigger shows
  a phase jump (its self-trigger timeout) or a phase walk (its own period, i.e. a different
  rate). Both are caught by a gate (``|r| > max(phase_tolerance_us, gate_sigma·σ)``) and a
  two-sided CUSUM on ``r/σ`` (σ: the locked jitter); the CUSUM's start dates the onset. A rate
  test compares the slope of each 2 s block with the recent blocks' slopes, for slow walks that
  began before the fit had much history;
* **slave vs master, rates** (Intel's check, the "somewhat counter-intuitive aspect of time
  stamps" of the multi-camera white paper, quoted in realsense-ros #2323 and #1889 and
  librealsense #14131): each camera stamps frames with its own crystal. A *synced* slave exposes
  when the master does, so its hardware timestamps drift against the master's at the crystals'
  rate difference (tens of ppm); a slave that was *never* triggered steps one nominal period of
  its own clock per frame, like the master, so the difference of their hardware timestamps
  stays constant (drift ≈ 0). The checker does not rely on that premise alone: it also measures
  each crystal against the host (the SDK's global time when both cameras report it, else the
  lower envelope of the host receive times) and from it the **walk** of the slave's exposures
  against the master's in host time, ``(1 + drift)/(1 + crystal) − 1``: 0 when locked, the
  period mismatch when free-running, in either timestamp domain. A walk resolved away from 0
  flags ``free-running``; a hardware drift of ≈ 0 (Intel's "constant difference") flags
  ``free-running`` too, unless the walk is measured ≈ 0 as well (the two crystals agree: then
  timestamps cannot tell, ``sync-unverified``, verify with the LED test); a run too short to
  resolve the drift gets the non-failing ``too-short`` warning (run 10 s). With global time on,
  the rule reads the other way round on ``timestamp_ms``: synced cameras' global timestamps
  keep a constant difference and free-running ones drift (#1889: the offset is small with
  global time off);
* **identical timestamps** across cameras mean sync is off or time is host-made (§0.2).

Times in reports are seconds on the master's hardware clock since its first frame.
"""

from __future__ import annotations

import enum
import logging
import math
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Final

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.depth_camera import (
    DepthCamera,
    FrameSet,
    FrameTiming,
    MetadataPolicy,
    SensorOptions,
    StreamConfig,
    SyncMode,
    TimestampDomain,
)
from mocaprig.errors import DeviceError, ValidationError
from mocaprig.timebase import U32Unwrapper
from mocaprig.validation import check_positive

__all__ = [
    "FAILING_FLAGS",
    "CameraHealth",
    "CameraSyncReport",
    "SyncCheckConfig",
    "SyncChecker",
    "SyncFlag",
    "SyncHealth",
    "SyncReport",
    "capture",
    "configure_rig",
    "iter_framesets",
    "run_sync_check",
    "start_rig",
]

_log = logging.getLogger(__name__)

"""The D415 hardware clock is a u32 µs counter (§2.5)."""


class SyncFlag(enum.Enum):
    """What the checker found about one camera."""

    NO_FRAMES = "no-frames"
    NO_HARDWARE_TIMESTAMPS = "no-hardware-timestamps"
    FRAME_DROPS = "frame-drops"
    TOO_MANY_DROPS = "too-many-drops"
    COUNTER_RESET = "counter-reset"
    TIMESTAMP_ORDER = "timestamp-order"
    NO_MASTER = "no-master"
    MULTIPLE_MASTERS = "multiple-masters"
    NOT_SYNCED = "not-synced"
    UNMATCHED = "unmatched"
    FREE_RUNNING = "free-running"
    """The slave captures on its own timer: a phase jump or walk, its exposures walking against
    the master's in host time, or hardware timestamps keeping a constant difference with the
    master's (Intel: synced cameras' timestamps drift apart)."""
    IDENTICAL_TIMESTAMPS = "identical-timestamps"
    SYNC_UNVERIFIED = "sync-unverified"
    """The timestamps cannot tell a locked slave from a free-running one: its hardware drift and
    its walk against the master are both ≈ 0, i.e. the two crystals agree within the resolution
    (a few % of camera pairs). Verify with the LED test (docs/d415-timing.md)."""
    TOO_SHORT = "too-short"
    """Warning: the run is too short to resolve a slave's rates (the drift's standard error
    exceeds ``rate_tolerance_ppm``), so Intel's rate check was not made; run longer (10 s)."""


FAILING_FLAGS: Final = frozenset(SyncFlag) - {
    SyncFlag.FRAME_DROPS,
    SyncFlag.COUNTER_RESET,
    SyncFlag.TOO_SHORT,
}
"""Flags that make a check fail. Drops up to ``max_drop_fraction``, counter resets (which the
recorder handles) and a run too short for the rate check are reported but do not by themselves
fail it."""


@dataclass(frozen=True, slots=True)
class SyncCheckConfig:
    """Thresholds of :class:`SyncChecker` (defaults suit D415s at 30–90 fps)."""

    fps: int = 30
    """Nominal frame rate of every camera."""
    warmup_s: float = 1.0
    """Seconds of matched pairs that start the slave-vs-master fit before alarms are armed
    (only the gate is armed then). Shorter fits extrapolate badly and raise false alarms."""
    trust_lag_s: float = 0.5
    """A pair enters the reference fit only this long after it was seen (not yet alarmed)."""
    phase_tolerance_us: float = 250.0
    """Phase errors beyond this (or ``gate_sigma`` jitters) flag free-run at once."""
    gate_sigma: float = 8.0
    cusum_k_sigma: float = 1.0
    """CUSUM allowance per pair, in jitters."""
    cusum_h_sigma: float = 16.0
    """CUSUM alarm threshold, in jitters."""
    block_s: float = 2.0
    """Length of the blocks of the rate test (s)."""
    block_z: float = 5.0
    """Rate-test threshold: a block's slope this many standard errors from the recent ones."""
    block_history: int = 15
    """Blocks the rate test compares with (30 s: follows slow thermal drift of the crystals)."""
    fit_bias_sigma: float = 3.0
    """Extra CUSUM allowance: this many standard errors of the reference fit at the pair."""
    jitter_floor_us: float = 2.0
    """Lower bound of the jitter estimate σ (µs; timestamps are integer µs)."""
    identical_tolerance_us: float = 0.5
    """Slave and master timestamps closer than this count as identical."""
    identical_fraction: float = 0.9
    """Fraction of the last ``fps`` pairs that must be identical to flag it."""
    max_drop_fraction: float = 0.01
    """Drops above this fraction of the expected frames fail the check."""
    max_timestamp_order_fraction: float = 0.01
    rate_tolerance_ppm: float = 1.0
    """Rates closer than this (ppm) count as equal (hardware drift ≈ 0, walk ≈ 0)."""
    rate_sigmas: float = 4.0
    """Standard errors a rate must lie beyond ``rate_tolerance_ppm`` to count as resolved."""
    global_time_min_s: float = 2.0
    """Seconds of ``global_time`` frames per camera before its crystal is read from them."""
    envelope_bins: int = 10
    """Time bins of the lower-envelope fit of host receive times (no global time)."""

    def __post_init__(self) -> None:
        check_positive(self.fps, name="fps")
        check_positive(self.phase_tolerance_us, name="phase_tolerance_us")
        check_positive(self.jitter_floor_us, name="jitter_floor_us")
        check_positive(self.warmup_s, name="warmup_s")

    @property
    def warmup_pairs(self) -> int:
        """Matched pairs of the warm-up."""
        return max(3, round(self.warmup_s * self.fps))

    @property
    def period_us(self) -> float:
        """Nominal frame period (µs)."""
        return 1e6 / self.fps


@dataclass(frozen=True, slots=True)
class CameraHealth:
    """Live state of one camera (:meth:`SyncChecker.health`)."""

    serial: str
    role: SyncMode
    frames: int
    drops: int
    fps_measured: float | None
    locked: bool | None
    """``True``/``False`` for a slave once armed; ``None`` for the master or while warming up."""
    phase_error_us: float | None
    jitter_us: float | None
    flags: tuple[SyncFlag, ...]


@dataclass(frozen=True, slots=True)
class SyncHealth:
    """Live summary of a running check."""

    ok: bool
    elapsed_s: float
    cameras: Mapping[str, CameraHealth]


@dataclass(frozen=True, slots=True)
class CameraSyncReport:
    """Final findings for one camera."""

    serial: str
    role: SyncMode
    frames: int
    drops: int
    counter_resets: int
    fps_measured: float | None
    timestamp_domain: TimestampDomain | None
    matched_pairs: int
    drift_ppm: float | None
    """Hardware-timestamp rate vs the master's, ``(dt_slave/dt_master − 1)·10⁶`` (locked pairs):
    the crystals' difference when synced, ≈ 0 when free-running (Intel's check)."""
    crystal_ppm: float | None
    """The slave's crystal vs the master's, measured against the host (``rate_reference``)."""
    walk_ppm: float | None
    """Rate of the slave's exposures against the master's in host time: ≈ 0 when locked."""
    rate_reference: str | None
    """``"global-time"`` or ``"host-arrival"``: what ``crystal_ppm`` was measured against."""
    offset_us: float | None
    """Fitted slave − master timestamp offset at the first pair (µs, includes counter offset)."""
    jitter_us: float | None
    """RMS phase error while locked (µs)."""
    max_phase_error_us: float | None
    """Largest |phase error| over all pairs, wrapped to half a frame period (µs)."""
    free_running_since_s: float | None
    """Estimated onset of free-running (master clock, s since its first frame)."""
    free_running_detected_s: float | None
    """When the checker raised the flag (same clock)."""
    flags: tuple[SyncFlag, ...]

    @property
    def ok(self) -> bool:
        """No failing flag."""
        return not (set(self.flags) & FAILING_FLAGS)


@dataclass(frozen=True, slots=True)
class SyncReport:
    """Final report of a sync check."""

    ok: bool
    fps: int
    duration_s: float
    master: str | None
    cameras: Mapping[str, CameraSyncReport] = field(default_factory=dict)

    def to_dict(self) -> dict[str, object]:
        """Plain JSON-able dict (enums as their values)."""
        cams: dict[str, object] = {}
        for serial, c in self.cameras.items():
            cams[serial] = {
                "ok": c.ok,
                "role": c.role.name.lower(),
                "frames": c.frames,
                "drops": c.drops,
                "counter_resets": c.counter_resets,
                "fps_measured": c.fps_measured,
                "timestamp_domain": None
                if c.timestamp_domain is None
                else c.timestamp_domain.value,
                "matched_pairs": c.matched_pairs,
                "drift_ppm": c.drift_ppm,
                "crystal_ppm": c.crystal_ppm,
                "walk_ppm": c.walk_ppm,
                "rate_reference": c.rate_reference,
                "offset_us": c.offset_us,
                "jitter_us": c.jitter_us,
                "max_phase_error_us": c.max_phase_error_us,
                "free_running_since_s": c.free_running_since_s,
                "free_running_detected_s": c.free_running_detected_s,
                "flags": [f.value for f in c.flags],
            }
        return {
            "ok": self.ok,
            "fps": self.fps,
            "duration_s": self.duration_s,
            "master": self.master,
            "cameras": cams,
        }


# ---------------------------------------------------------------------------------------------


@dataclass(slots=True)
class _Sums:
    """Running least-squares sums of y on x (x, y relative to the first point)."""

    n: int = 0
    sx: float = 0.0
    sy: float = 0.0
    sxx: float = 0.0
    sxy: float = 0.0

    def add(self, x: float, y: float, sign: int = 1) -> None:
        self.n += sign
        self.sx += sign * x
        self.sy += sign * y
        self.sxx += sign * x * x
        self.sxy += sign * x * y

    def leverage(self, x: float) -> float:
        """``1/n + (x − x̄)²/Sxx``: the variance of the fit at ``x`` in units of σ²."""
        if self.n == 0:
            return 1.0
        mx = self.sx / self.n
        vxx = self.sxx - self.n * mx * mx
        if self.n < 2 or vxx <= 0:
            return 1.0
        return 1.0 / self.n + (x - mx) ** 2 / vxx

    def vxx(self) -> float:
        """Spread of x about its mean (Σ(x − x̄)²)."""
        return 0.0 if self.n == 0 else self.sxx - self.sx * self.sx / self.n

    def fit(self) -> tuple[float, float] | None:
        """``(intercept, slope)``; slope 1 when the x spread is too small."""
        if self.n == 0:
            return None
        mx, my = self.sx / self.n, self.sy / self.n
        vxx = self.sxx - self.n * mx * mx
        if self.n < 2 or vxx <= 1e-6 * max(1.0, self.sxx):
            return my - mx, 1.0
        slope = (self.sxy - self.n * mx * my) / vxx
        return my - slope * mx, slope


@dataclass(slots=True)
class _Cam:
    serial: str
    role: SyncMode
    frames: int = 0
    drops: int = 0
    resets: int = 0
    duplicates: int = 0
    order_violations: int = 0
    no_hw: int = 0
    domain: TimestampDomain | None = None
    last_counter: int | None = None
    first_counter: int | None = None
    unwrap: U32Unwrapper = field(default_factory=U32Unwrapper)
    first_ts_us: int | None = None
    last_ts_us: int | None = None
    epoch: int = 0
    """Bumped at each counter reset (pairing is re-established)."""
    host_samples: list[tuple[int, int]] = field(default_factory=list)
    """(unwrapped hardware µs, host receive ns) of every frame: the crystal vs the host."""
    global_samples: list[tuple[int, float]] = field(default_factory=list)
    """(unwrapped hardware µs, global-time µs) of every ``global_time`` frame."""
    # master only: counter -> (ts_us, host_ns, timestamp_ms, domain)
    history: OrderedDict[int, tuple[int, int, float, TimestampDomain]] = field(
        default_factory=OrderedDict
    )


@dataclass(slots=True)
class _Pending:
    counter: int
    ts_us: int
    host_ns: int
    timestamp_ms: float
    domain: TimestampDomain


@dataclass(slots=True)
class _Link:
    """One slave (or default-mode camera) followed against the master."""

    cam: _Cam
    delta: int | None = None
    epoch: tuple[int, int] = (-1, -1)
    pending: deque[_Pending] = field(default_factory=deque)
    unmatched: int = 0
    pairs: int = 0
    x0: int = 0
    y0: int = 0
    ref: _Sums = field(default_factory=_Sums)
    prev: tuple[_Sums, int, int] | None = None
    """The longest earlier segment (before a counter reset): sums, x0, y0."""
    lag: deque[tuple[float, float, float]] = field(default_factory=deque)  # (t_s, x, y)
    warm: list[tuple[float, float]] = field(default_factory=list)
    sigma2: float | None = None
    cusum_pos: float = 0.0
    cusum_neg: float = 0.0
    run_start_pos: float | None = None
    run_start_neg: float | None = None
    free_since: float | None = None
    free_detected: float | None = None
    last_residual: float | None = None
    max_phase: float = 0.0
    identical: deque[bool] = field(default_factory=deque)
    identical_flag: bool = False
    block: _Sums = field(default_factory=_Sums)
    block_start: float = 0.0
    blocks: deque[tuple[float, float]] = field(default_factory=deque)
    """(slope, standard error) of the recent locked blocks."""


def _span_s(samples: Sequence[tuple[int, float]]) -> float:
    """Seconds of device time the samples cover."""
    return 0.0 if len(samples) < 2 else (samples[-1][0] - samples[0][0]) / 1e6


def _line(x: npt.NDArray[np.float64], y: npt.NDArray[np.float64]) -> tuple[float, float, float]:
    """Least-squares ``(slope, intercept, residual σ)`` of ``y`` on ``x``."""
    mx, my = float(x.mean()), float(y.mean())
    vxx = float(((x - mx) ** 2).sum())
    slope = float(((x - mx) * (y - my)).sum() / vxx)
    res = y - (my + slope * (x - mx))
    dof = max(1, x.size - 2)
    return slope, my - slope * mx, float(math.sqrt(float((res**2).sum()) / dof))


def _ols(samples: Sequence[tuple[int, float]]) -> tuple[float, float] | None:
    """``(dy/dx, standard error)`` of (device µs, global-time µs) samples."""
    if len(samples) < 10:
        return None
    arr = np.asarray(samples, np.float64)
    x, y = arr[:, 0] - arr[0, 0], arr[:, 1] - arr[0, 1]
    if float(np.ptp(x)) <= 0:
        return None
    slope, _b, sigma = _line(x, y)
    se = max(sigma, 1.0) / math.sqrt(float(((x - x.mean()) ** 2).sum()))
    return slope, se


def _lower_envelope(samples: Sequence[tuple[int, int]], bins: int) -> tuple[float, float] | None:
    """``(host µs per device µs, standard error)`` from (device µs, host receive ns) samples.

    Host receive times are capture + transfer + a latency that is never below its minimum, so
    the lower envelope, not the mean, follows the clocks: the minimum of each time bin (after
    removing the current slope estimate) is fitted, twice.
    """
    if len(samples) < 4 * max(3, bins):
        return None
    arr = np.asarray(samples, np.float64)
    x = arr[:, 0] - arr[0, 0]
    u = (arr[:, 1] - arr[0, 1]) / 1e3 - x  # host µs minus device µs
    if float(np.ptp(x)) <= 0:
        return None
    slope, _b, _s = _line(x, u)
    chunks = np.array_split(np.arange(x.size), max(3, bins))
    se = math.inf
    for _ in range(2):
        picks = np.array([c[np.argmin(u[c] - slope * x[c])] for c in chunks if c.size])
        xs, us = x[picks], u[picks]
        slope, _b, sigma = _line(xs, us)
        se = max(sigma, 1.0) / math.sqrt(float(((xs - xs.mean()) ** 2).sum()))
    return 1.0 + slope, se


class SyncChecker:
    """Streaming sync verification over the timing records of every camera of a rig.

    Args:
        roles: serial → the ``inter_cam_sync_mode`` each camera was configured with.
        config: thresholds; ``config.fps`` must be the cameras' fps.
        external_trigger: every camera is a slave of an external generator (the sync box,
            docs/wiring.md topology B); the first serial is then the reference. A trigger lost
            by the reference itself shows as every other camera flagged.

    Example::

        checker = SyncChecker({"A": SyncMode.MASTER, "B": SyncMode.SLAVE}, SyncCheckConfig(fps=30))
        checker.feed("A", frameset_a.timing)
        checker.feed("B", frameset_b.timing)
        checker.report().ok
    """

    def __init__(
        self,
        roles: Mapping[str, SyncMode],
        config: SyncCheckConfig | None = None,
        *,
        external_trigger: bool = False,
    ) -> None:
        if not roles:
            msg = "SyncChecker needs at least one camera"
            raise ValidationError(msg)
        self.config = SyncCheckConfig() if config is None else config
        self._cams = {s: _Cam(s, SyncMode(r)) for s, r in roles.items()}
        masters = sorted(s for s, r in roles.items() if r is SyncMode.MASTER)
        self._master_flags: set[SyncFlag] = set()
        if external_trigger:
            if masters:
                self._master_flags.add(SyncFlag.MULTIPLE_MASTERS)  # a master fights the box
        elif not masters:
            self._master_flags.add(SyncFlag.NO_MASTER)
        elif len(masters) > 1:
            self._master_flags.add(SyncFlag.MULTIPLE_MASTERS)
        self._ref = masters[0] if masters else sorted(roles)[0]
        self._links = {s: _Link(c) for s, c in self._cams.items() if s != self._ref}
        self._lag_pairs = max(1, round(self.config.trust_lag_s * self.config.fps))

    @property
    def reference(self) -> str:
        """Serial of the camera others are compared with (the master)."""
        return self._ref

    # -- feeding ---------------------------------------------------------------------------

    def feed(self, serial: str, timing: FrameTiming) -> None:
        """Add one frameset's timing of camera ``serial``.

        Raises:
            ValidationError: ``serial`` was not declared in ``roles``.
        """
        cam = self._cams.get(serial)
        if cam is None:
            msg = f"camera {serial} is not part of this sync check ({sorted(self._cams)})"
            raise ValidationError(msg)
        cam.domain = timing.timestamp_domain
        counter = timing.frame_counter
        if cam.last_counter is not None:
            if counter == cam.last_counter:
                cam.duplicates += 1
                return
            if counter < cam.last_counter:
                cam.resets += 1
                cam.epoch += 1
                cam.history.clear()
            elif counter > cam.last_counter + 1:
                cam.drops += counter - cam.last_counter - 1
        if cam.first_counter is None:
            cam.first_counter = counter
        cam.last_counter = counter
        cam.frames += 1
        if not timing.has_hardware_timestamps:
            cam.no_hw += 1
            return
        sensor_ts = timing.sensor_timestamp_us
        frame_ts = timing.frame_timestamp_us
        if sensor_ts is None or frame_ts is None:  # for the type checker; has_hw checked both
            return
        if not 0 <= frame_ts - sensor_ts <= self.config.period_us:
            cam.order_violations += 1
        ts = cam.unwrap(sensor_ts)
        if cam.first_ts_us is None:
            cam.first_ts_us = ts
        cam.last_ts_us = ts
        cam.host_samples.append((ts, timing.host_time_ns))
        if timing.timestamp_domain is TimestampDomain.GLOBAL_TIME and math.isfinite(
            timing.timestamp_ms
        ):
            cam.global_samples.append((ts, timing.timestamp_ms * 1e3))
        item = _Pending(
            counter, ts, timing.host_time_ns, timing.timestamp_ms, timing.timestamp_domain
        )
        if serial == self._ref:
            cam.history[counter] = (ts, timing.host_time_ns, timing.timestamp_ms, item.domain)
            while len(cam.history) > 8 * self.config.fps:
                cam.history.popitem(last=False)
            for link in self._links.values():
                self._drain(link)
        else:
            link = self._links[serial]
            link.pending.append(item)
            self._drain(link)

    def _t_s(self, master_ts_us: int) -> float:
        first = self._cams[self._ref].first_ts_us
        return 0.0 if first is None else (master_ts_us - first) / 1e6

    def _establish(self, link: _Link, item: _Pending) -> bool:
        master = self._cams[self._ref]
        if not master.history:
            return False
        half = self.config.period_us / 2
        use_global = item.domain is TimestampDomain.GLOBAL_TIME
        best: tuple[float, int] | None = None
        for mc, (_ts, host_ns, tms, dom) in master.history.items():
            if use_global and dom is TimestampDomain.GLOBAL_TIME:
                dt_us = abs(tms - item.timestamp_ms) * 1e3
            else:
                dt_us = abs(host_ns - item.host_ns) / 1e3
            if best is None or dt_us < best[0]:
                best = (dt_us, mc)
        if best is None or best[0] > half:
            return False
        link.delta = item.counter - best[1]
        link.epoch = (master.epoch, link.cam.epoch)
        return True

    def _drain(self, link: _Link) -> None:
        master = self._cams[self._ref]
        cap = 8 * self.config.fps
        cfg_period_ns = self.config.period_us * 1e3
        while link.pending:
            item = link.pending[0]
            if link.delta is not None and link.epoch != (master.epoch, link.cam.epoch):
                self._restart_segment(link)  # a counter reset on either side: pair again
            if link.delta is None and not self._establish(link, item):
                newest_host = next(reversed(master.history.values()))[1] if master.history else None
                gone = newest_host is not None and newest_host > item.host_ns + 2 * cfg_period_ns
                if len(link.pending) > cap or gone:
                    link.pending.popleft()  # no master capture will ever match it
                    link.unmatched += 1
                    continue
                return
            delta = link.delta
            if delta is None:
                return
            mc = item.counter - delta
            hit = master.history.get(mc)
            if hit is None:
                latest = next(reversed(master.history)) if master.history else None
                if latest is not None and latest >= mc:
                    link.pending.popleft()  # the master dropped that capture
                    link.unmatched += 1
                    continue
                if len(link.pending) > cap:
                    link.pending.popleft()
                    link.unmatched += 1
                    continue
                return
            link.pending.popleft()
            same_global = (
                hit[3] is TimestampDomain.GLOBAL_TIME
                and item.domain is TimestampDomain.GLOBAL_TIME
                and abs(hit[2] - item.timestamp_ms) * 1e3 <= self.config.identical_tolerance_us
            )
            self._pair(link, hit[0], item.ts_us, same_global=same_global)

    @staticmethod
    def _restart_segment(link: _Link) -> None:
        if link.ref.n > (link.prev[0].n if link.prev else 0):
            link.prev = (link.ref, link.x0, link.y0)
        link.delta = None
        link.ref = _Sums()
        link.lag.clear()
        link.warm.clear()
        link.sigma2 = None
        link.cusum_pos = link.cusum_neg = 0.0
        link.block = _Sums()
        link.blocks.clear()

    # -- the phase model -------------------------------------------------------------------

    def _pair(self, link: _Link, m_ts: int, s_ts: int, *, same_global: bool) -> None:
        cfg = self.config
        t_s = self._t_s(m_ts)
        link.pairs += 1
        same = same_global or abs(s_ts - m_ts) <= cfg.identical_tolerance_us
        link.identical.append(same)
        if len(link.identical) > cfg.fps:
            link.identical.popleft()
        if len(link.identical) >= min(cfg.fps, 10) and sum(
            link.identical
        ) >= cfg.identical_fraction * len(link.identical):
            link.identical_flag = True
        if link.ref.n == 0 and not link.warm:
            link.x0, link.y0 = m_ts, s_ts
        x, y = float(m_ts - link.x0), float(s_ts - link.y0)
        if link.sigma2 is None:  # warming up: only the gate is armed
            early = link.ref.fit()
            if early is not None:
                r0 = y - (early[0] + early[1] * x)
                link.last_residual = r0
                link.max_phase = max(link.max_phase, abs(math.remainder(r0, cfg.period_us)))
                if link.free_since is None and abs(r0) > cfg.phase_tolerance_us:
                    link.free_since = link.free_detected = t_s
                if link.free_since is not None:
                    return
            link.warm.append((x, y))
            link.ref.add(x, y)
            if len(link.warm) >= cfg.warmup_pairs:
                fit = link.ref.fit()
                if fit is not None:
                    a, b = fit
                    res = [yy - (a + b * xx) for xx, yy in link.warm]
                    dof = max(1, len(res) - 2)
                    link.sigma2 = max(sum(r * r for r in res) / dof, cfg.jitter_floor_us**2)
                    if link.ref.vxx() > 0:
                        se = math.sqrt(link.sigma2 / link.ref.vxx())
                        link.blocks.append((b, se))
                link.warm.clear()
            return
        fit = link.ref.fit()
        if fit is None:
            return
        a, b = fit
        r = y - (a + b * x)
        link.last_residual = r
        period = cfg.period_us
        wrapped = abs(math.remainder(r, period))
        link.max_phase = max(link.max_phase, wrapped)
        if link.free_since is not None:
            return  # sticky: the session is compromised from the onset on
        sigma = math.sqrt(link.sigma2)
        # The reference fit is uncertain where it extrapolates (leverage): normalise by the
        # prediction std, and widen the CUSUM allowance by the fit's possible bias there (a slope
        # error is the same for every following pair, so the CUSUM would integrate it).
        lev = link.ref.leverage(x)
        z = r / (sigma * math.sqrt(1.0 + lev))
        allowance = cfg.cusum_k_sigma + cfg.fit_bias_sigma * math.sqrt(lev / (1.0 + lev))
        if link.cusum_pos == 0.0:
            link.run_start_pos = t_s
        if link.cusum_neg == 0.0:
            link.run_start_neg = t_s
        link.cusum_pos = max(0.0, link.cusum_pos + z - allowance)
        link.cusum_neg = max(0.0, link.cusum_neg - z - allowance)
        gate = max(cfg.phase_tolerance_us, cfg.gate_sigma * sigma)
        alarm_pos = link.cusum_pos > cfg.cusum_h_sigma
        alarm_neg = link.cusum_neg > cfg.cusum_h_sigma
        if abs(r) > gate or alarm_pos or alarm_neg:
            starts = [t_s]
            if alarm_pos and link.run_start_pos is not None:
                starts.append(link.run_start_pos)
            if alarm_neg and link.run_start_neg is not None:
                starts.append(link.run_start_neg)
            link.free_since = min(starts)
            link.free_detected = t_s
            link.lag.clear()  # pairs of the last second are suspect: never trust them
            return
        if self._block_test(link, t_s, x, y, sigma):
            return
        if abs(z) < 4.0:
            link.sigma2 += (r * r - link.sigma2) / 200.0
            link.sigma2 = max(link.sigma2, cfg.jitter_floor_us**2)
        link.lag.append((t_s, x, y))
        while link.lag and len(link.lag) > self._lag_pairs:
            _t, lx, ly = link.lag.popleft()
            link.ref.add(lx, ly)

    def _block_test(self, link: _Link, t_s: float, x: float, y: float, sigma: float) -> bool:
        """Rate test: the slope of each ``block_s`` block against the recent blocks' slopes.

        A locked slave's rate vs the master is its crystal's (constant over seconds); a slave
        that starts to free-run takes its own rate. This catches slow walks the CUSUM missed
        before its adaptive reference absorbed them. Returns ``True`` when it raised the flag.
        """
        cfg = self.config
        if link.block.n == 0:
            link.block_start = t_s
        link.block.add(x, y)
        if t_s - link.block_start < cfg.block_s or link.block.n < 10:
            return False
        fit, vxx = link.block.fit(), link.block.vxx()
        link.block = _Sums()
        if fit is None or vxx <= 0:
            return False
        slope, se = fit[1], sigma / math.sqrt(vxx)
        if link.blocks:
            weights = [1.0 / (e * e) for _b, e in link.blocks]
            ref = sum(b * w for (b, _e), w in zip(link.blocks, weights, strict=True)) / sum(weights)
            z = (slope - ref) / math.sqrt(se * se + 1.0 / sum(weights))
            if abs(z) > cfg.block_z:
                link.free_since = link.block_start
                link.free_detected = t_s
                link.lag.clear()
                return True
            if abs(z) > cfg.block_z / 2:
                return False  # suspect: keep it out of the reference the next block meets
        link.blocks.append((slope, se))
        while len(link.blocks) > cfg.block_history:
            link.blocks.popleft()
        return False

    # -- results ---------------------------------------------------------------------------

    def _flags(self, serial: str, *, final: bool) -> tuple[SyncFlag, ...]:
        cam = self._cams[serial]
        cfg = self.config
        flags: set[SyncFlag] = set()
        if cam.frames == 0:
            if final:
                flags.add(SyncFlag.NO_FRAMES)
            return tuple(sorted(flags, key=lambda f: f.value))
        if cam.no_hw:
            flags.add(SyncFlag.NO_HARDWARE_TIMESTAMPS)
        if cam.drops:
            flags.add(SyncFlag.FRAME_DROPS)
            if cam.drops > cfg.max_drop_fraction * (cam.frames + cam.drops):
                flags.add(SyncFlag.TOO_MANY_DROPS)
        if cam.resets:
            flags.add(SyncFlag.COUNTER_RESET)
        if cam.order_violations > cfg.max_timestamp_order_fraction * cam.frames:
            flags.add(SyncFlag.TIMESTAMP_ORDER)
        if len(self._cams) > 1:
            flags |= self._master_flags
            if cam.role is SyncMode.DEFAULT:
                flags.add(SyncFlag.NOT_SYNCED)
        link = self._links.get(serial)
        if link is not None:
            if link.free_since is not None:
                flags.add(SyncFlag.FREE_RUNNING)
            if link.identical_flag:
                flags.add(SyncFlag.IDENTICAL_TIMESTAMPS)
            if final and link.pairs == 0 and not cam.no_hw:
                flags.add(SyncFlag.UNMATCHED)
        return tuple(sorted(flags, key=lambda f: f.value))

    def _fps(self, cam: _Cam) -> float | None:
        if cam.first_ts_us is None or cam.last_ts_us is None or cam.last_ts_us == cam.first_ts_us:
            return None
        if cam.first_counter is None or cam.last_counter is None or cam.resets:
            return None
        return (cam.last_counter - cam.first_counter) / ((cam.last_ts_us - cam.first_ts_us) / 1e6)

    def _elapsed(self) -> float:
        m = self._cams[self._ref]
        if m.first_ts_us is None or m.last_ts_us is None:
            return 0.0
        return (m.last_ts_us - m.first_ts_us) / 1e6

    def _host_rates(self, a: _Cam, b: _Cam) -> tuple[float, float, float, float, str] | None:
        """Host time per device µs of cameras ``a`` and ``b`` with standard errors, and the
        reference: global time when both have enough of it, else the host receive times."""
        need = self.config.global_time_min_s
        if all(_span_s(c.global_samples) >= need for c in (a, b)):
            fits = [_ols(c.global_samples) for c in (a, b)]
            ref = "global-time"
        else:
            fits = [_lower_envelope(c.host_samples, self.config.envelope_bins) for c in (a, b)]
            ref = "host-arrival"
        fa, fb = fits
        if fa is None or fb is None:
            return None
        return fa[0], fa[1], fb[0], fb[1], ref

    def _rate_verdict(
        self, link: _Link, sums: _Sums, fit: tuple[float, float] | None
    ) -> tuple[float | None, float | None, str | None, SyncFlag | None] | None:
        """Intel's rate check for one slave: ``(crystal_ppm, walk_ppm, reference, flag)``.

        ``drift`` (hardware timestamps vs the master's), ``crystal`` (the slave's crystal vs the
        master's, against the host) and ``walk = (1 + drift)/(1 + crystal) − 1`` (the slave's
        exposures vs the master's in host time): locked means walk ≈ 0 and, per Intel, a drift
        away from 0; free-running means a walk, or a drift of ≈ 0 that the walk cannot excuse.
        """
        cfg = self.config
        is_slave = link.cam.role is SyncMode.SLAVE
        if not is_slave or fit is None or sums.n < cfg.warmup_pairs or sums.vxx() <= 0:
            return None
        tol, k = cfg.rate_tolerance_ppm * 1e-6, cfg.rate_sigmas
        sigma = math.sqrt(link.sigma2) if link.sigma2 is not None else cfg.jitter_floor_us
        drift, sd_drift = fit[1] - 1.0, sigma / math.sqrt(sums.vxx())
        rates = self._host_rates(self._cams[self._ref], link.cam)
        crystal = walk = None
        reference: str | None = None
        sd_walk = math.inf
        if rates is not None:
            r_m, se_m, r_s, se_s, reference = rates
            crystal = r_m / r_s - 1.0
            sd_crystal = math.hypot(se_m / r_m, se_s / r_s)
            walk = (1.0 + drift) / (1.0 + crystal) - 1.0
            sd_walk = math.hypot(sd_drift, sd_crystal)
        flag: SyncFlag | None = None
        if walk is not None and abs(walk) > tol + k * sd_walk:
            flag = SyncFlag.FREE_RUNNING  # its exposures walk against the master's
        elif abs(drift) <= tol + k * sd_drift:
            walk_zero = walk is not None and abs(walk) <= tol + k * sd_walk and sd_walk <= tol
            if sd_drift > tol:
                flag = SyncFlag.TOO_SHORT  # the drift is not resolved yet
            elif walk_zero:
                flag = SyncFlag.SYNC_UNVERIFIED  # the two crystals agree
            else:
                flag = SyncFlag.FREE_RUNNING  # Intel: a constant difference is not synced
        ppm = 1e6
        return (
            None if crystal is None else crystal * ppm,
            None if walk is None else walk * ppm,
            reference,
            flag,
        )

    def health(self) -> SyncHealth:
        """Live summary (cheap; call it once a second)."""
        cams: dict[str, CameraHealth] = {}
        ok = True
        for serial, cam in self._cams.items():
            flags = self._flags(serial, final=False)
            ok = ok and not (set(flags) & FAILING_FLAGS)
            link = self._links.get(serial)
            locked: bool | None = None
            phase = jitter = None
            if link is not None and link.free_since is not None:
                locked = False
            elif link is not None and link.sigma2 is not None:
                locked = True
            if link is not None:
                phase = link.last_residual
                jitter = None if link.sigma2 is None else math.sqrt(link.sigma2)
            cams[serial] = CameraHealth(
                serial=serial,
                role=cam.role,
                frames=cam.frames,
                drops=cam.drops,
                fps_measured=self._fps(cam),
                locked=locked,
                phase_error_us=phase,
                jitter_us=jitter,
                flags=flags,
            )
        return SyncHealth(ok=ok, elapsed_s=self._elapsed(), cameras=cams)

    def report(self) -> SyncReport:
        """Final report (the checker can keep being fed afterwards)."""
        cams: dict[str, CameraSyncReport] = {}
        for serial, cam in self._cams.items():
            link = self._links.get(serial)
            drift = offset = jitter = max_phase = since = detected = None
            crystal = walk = None
            reference: str | None = None
            pairs = 0
            flags = self._flags(serial, final=True)
            if link is not None:
                pairs = link.pairs
                sums = _Sums(link.ref.n, link.ref.sx, link.ref.sy, link.ref.sxx, link.ref.sxy)
                x0, y0 = link.x0, link.y0
                if link.free_since is None:
                    for _t, lx, ly in link.lag:
                        sums.add(lx, ly)
                if link.prev is not None and link.prev[0].n > sums.n:
                    sums, x0, y0 = link.prev
                fit = sums.fit() if sums.n >= 2 else None
                if fit is not None:
                    offset = fit[0] + (y0 - x0)
                    drift = (fit[1] - 1.0) * 1e6
                if link.sigma2 is not None:
                    jitter = math.sqrt(link.sigma2)
                if link.pairs > 1:
                    max_phase = link.max_phase
                since, detected = link.free_since, link.free_detected
                verdict = self._rate_verdict(link, sums, fit)
                if verdict is not None:
                    crystal, walk, reference, flag = verdict
                    if flag is not None and since is None and not link.identical_flag:
                        flags = tuple(sorted({*flags, flag}, key=lambda f: f.value))
                        if flag is SyncFlag.FREE_RUNNING:
                            since, detected = self._t_s(link.x0), self._elapsed()
            cams[serial] = CameraSyncReport(
                serial=serial,
                role=cam.role,
                frames=cam.frames,
                drops=cam.drops,
                counter_resets=cam.resets,
                fps_measured=self._fps(cam),
                timestamp_domain=cam.domain,
                matched_pairs=pairs,
                drift_ppm=drift,
                crystal_ppm=crystal,
                walk_ppm=walk,
                rate_reference=reference,
                offset_us=offset,
                jitter_us=jitter,
                max_phase_error_us=max_phase,
                free_running_since_s=since,
                free_running_detected_s=detected,
                flags=flags,
            )
        ok = all(c.ok for c in cams.values())
        return SyncReport(
            ok=ok,
            fps=self.config.fps,
            duration_s=self._elapsed(),
            master=self._ref if SyncFlag.NO_MASTER not in self._master_flags else None,
            cameras=cams,
        )


# ---------------------------------------------------------------------------------------------
# Running a rig


def configure_rig(
    cameras: Sequence[DepthCamera],
    *,
    stream: StreamConfig | None = None,
    options: SensorOptions | None = None,
    master: str | None = None,
    external_trigger: bool = False,
    allow_no_metadata: bool = False,
) -> dict[str, SyncMode]:
    """Configure every camera in one mode: ``master`` (default: the first) mode 1, others mode 2.

    With ``external_trigger`` every camera is a slave (mode 2) of the sync box. A single camera
    without external trigger runs in mode 0. Returns serial → sync mode.

    Without per-frame metadata (no kernel patch, no RSUSB backend) a synced camera refuses to
    deliver frames (:class:`~mocaprig.errors.DeviceError` at its first frame: sync cannot be
    verified, drops are invisible) unless ``allow_no_metadata`` is set; either way the run is
    announced by a warning naming the fix.
    """
    stream = StreamConfig() if stream is None else stream
    options = SensorOptions() if options is None else options
    if not cameras:
        msg = (
            "no D415 found: check the USB 3 cables and power (`rs-enumerate-devices` lists what "
            "the SDK sees), or try the simulated rig with --mock"
        )
        raise DeviceError(msg)
    serials = [c.info.serial for c in cameras]
    if master is not None and master not in serials:
        msg = f"master D415 {master} is not among the cameras {serials}"
        raise ValidationError(msg)
    master = serials[0] if master is None else master
    roles: dict[str, SyncMode] = {}
    for cam in cameras:
        serial = cam.info.serial
        if external_trigger:
            mode = SyncMode.SLAVE
        elif len(cameras) == 1:
            mode = SyncMode.DEFAULT
        else:
            mode = SyncMode.MASTER if serial == master else SyncMode.SLAVE
        cam.configure(stream=stream, options=options, sync_mode=mode)
        if isinstance(cam, MetadataPolicy):
            cam.allow_no_metadata = allow_no_metadata
        roles[serial] = mode
    return roles


def start_rig(cameras: Sequence[DepthCamera]) -> None:
    """Start the master first, then the slaves (maintainers' advice, realsense-d415.md §2.3)."""
    ordered = sorted(cameras, key=lambda c: c.sync_mode is not SyncMode.MASTER)
    started: list[DepthCamera] = []
    try:
        for cam in ordered:
            cam.start()
            started.append(cam)
    except BaseException:
        for cam in started:
            cam.stop()
        raise


def iter_framesets(
    cameras: Sequence[DepthCamera],
    *,
    seconds: float,
    stall_s: float = 2.0,
    stop: threading.Event | None = None,
) -> Iterator[FrameSet]:
    """Poll started cameras round-robin until each has delivered ``seconds`` of framesets.

    Durations are measured on the framesets' ``host_time_ns`` (simulated cameras run on their
    own clock), from the first frameset of any camera. A camera that delivers nothing for
    ``stall_s`` wall seconds is given up (its absence shows in the results). Setting ``stop``
    ends the polling early.
    """
    check_positive(seconds, name="seconds")
    span_ns = round(seconds * 1e9)
    t0: int | None = None
    done: set[str] = set()
    idle_since: dict[str, float] = {}
    while len(done) < len(cameras) and not (stop is not None and stop.is_set()):
        got = False
        for cam in cameras:
            serial = cam.info.serial
            if serial in done:
                continue
            fs = cam.poll(0.0)
            if fs is None:
                since = idle_since.setdefault(serial, time.monotonic())
                if time.monotonic() - since > stall_s:
                    _log.warning("D415 %s delivered nothing for %.1f s; giving up", serial, stall_s)
                    done.add(serial)
                continue
            idle_since.pop(serial, None)
            got = True
            host_ns = fs.timing.host_time_ns
            t0 = host_ns if t0 is None else t0
            if host_ns - t0 >= span_ns:
                done.add(serial)
                continue
            yield fs
        if not got:
            time.sleep(0.002)


def capture(
    cameras: Sequence[DepthCamera],
    *,
    seconds: float,
    on_frameset: Callable[[FrameSet], None],
    stall_s: float = 2.0,
) -> float:
    """Call ``on_frameset`` with every frameset of :func:`iter_framesets`; returns the captured
    span in seconds (host time of the first to the last frameset)."""
    first: int | None = None
    last: int | None = None
    for fs in iter_framesets(cameras, seconds=seconds, stall_s=stall_s):
        host_ns = fs.timing.host_time_ns
        first = host_ns if first is None else first
        last = host_ns if last is None else max(last, host_ns)
        on_frameset(fs)
    return 0.0 if first is None or last is None else (last - first) / 1e9


def run_sync_check(
    cameras: Sequence[DepthCamera],
    *,
    seconds: float,
    stream: StreamConfig | None = None,
    options: SensorOptions | None = None,
    config: SyncCheckConfig | None = None,
    on_health: Callable[[SyncHealth], None] | None = None,
    external_trigger: bool = False,
) -> SyncReport:
    """Configure (first camera = master), start, verify sync for ``seconds``, stop.

    ``on_health`` is called about once per second of capture with the live summary. With
    ``external_trigger`` every camera is a slave of the sync box (start it before). Cameras
    without frame metadata are let through (``allow_no_metadata``): the check reports them
    (``no-hardware-timestamps``) instead of refusing.
    """
    stream = StreamConfig() if stream is None else stream
    roles = configure_rig(
        cameras,
        stream=stream,
        options=options,
        external_trigger=external_trigger,
        allow_no_metadata=True,
    )
    checker = SyncChecker(
        roles,
        SyncCheckConfig(fps=stream.fps) if config is None else config,
        external_trigger=external_trigger,
    )
    next_health = [1.0]

    def feed(fs: FrameSet) -> None:
        checker.feed(fs.serial, fs.timing)
        if on_health is not None and fs.serial == checker.reference:
            h = checker.health()
            if h.elapsed_s >= next_health[0]:
                next_health[0] += 1.0
                on_health(h)

    start_rig(cameras)
    try:
        capture(cameras, seconds=seconds, on_frameset=feed)
    finally:
        for cam in cameras:
            cam.stop()
    report = checker.report()
    for serial, found in report.cameras.items():
        if not found.ok:
            flags = ", ".join(f.value for f in found.flags)
            _log.warning("D415 %s (%s): %s", serial, found.role.name.lower(), flags)
    return report
