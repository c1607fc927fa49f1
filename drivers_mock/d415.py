"""Mock RealSense D415 cameras: the ``DepthCamera`` protocol over the simulated world.

:func:`mock_cameras` (entry point ``mocaprig.mocks: d415``) returns one :class:`MockD415` per
rig D415 (master first), all sharing one :class:`MockD415Rig`: one world (a seeded
:class:`~drivers_mock.scenario.Scenario`), one master pulse timeline, one USB bandwidth budget.
Images come from :mod:`mocaprig.drivers_mock.d415_render`; this module owns timing, sync and faults.

Timing and sync (realsense-d415.md §2.3–§2.5, §4.5)
=====================================================

* Each camera keeps its own hardware clock, the scenario's ``DeviceClock`` (``d415-0`` …),
  stamped in µs and wrapped to u32 (§2.5). Its frame counter starts at an arbitrary value and
  grows by one per capture (dropped captures leave gaps, §4.5).
* Mode 0 (default) and 1 (master) free-run at the self-timed period of their own crystal:
  ``(1 + free_run_period_ppm·1e-6)/fps`` device seconds (:class:`~drivers_mock.rig.D415Timing`;
  0 ppm by default, the premise of Intel's "unsynced timestamps keep a constant difference"),
  i.e. ``1/(fps·(1 + ppm·1e-6))`` session seconds for a clock of ``ppm``; the first capture
  comes ``startup_ms`` plus a random phase after ``start()``.
* The master emits one pulse per capture while it streams, at its exposure start or at its
  readout start (= end of exposure), as ``D415Timing.pulse_at`` says (undocumented for the
  D415, §2.2; docs/d415-timing.md). The timing comes from the scenario's rig
  (``Rig.d415_timing``) unless ``timing=`` is given.
* A slave (mode 2) starts its exposure ``D415Timing.trigger_to_exposure_us`` after each pulse it
  receives (``trigger_delay_us=`` overrides it; plus ``trigger_jitter_us`` Gaussian jitter,
  §4.5). With no pulse for ``trigger_timeout_ms`` after its last capture (or after ``start()``)
  it triggers itself and free-runs at its own self-timed period (§2.4, silently): its frames
  are then stamped one own period apart, not locked to the master, until a pulse arrives
  again before its next self-trigger. Pulses less than 35 % of a period after the previous
  exposure start are ignored (the sensor is busy), so a free-running slave re-locks on the
  first pulse outside that window. The timeout value is not documented; 50 ms (1.5 frame
  periods at 30 fps) is assumed, and so is the 35 %.
* ``global_time_enabled`` (default on, as on a real D415, §2.7): ``timestamp_ms`` switches from
  the ``hardware_clock`` domain to ``global_time`` ``D415Timing.global_time_ready_s`` (1.5 s)
  after ``start()``: the frame timestamp mapped onto the host's epoch clock, with a per-unit
  offset and rate error and per-frame jitter (``D415Timing.global_time_*``). The metadata
  timestamps stay on the hardware clock.
* Per frame (§2.8, §4.5): ``sensor_timestamp`` = device µs at mid-exposure; ``frame_timestamp``
  = device µs at the start of the USB transfer, ``exposure/2 + 0.3·period`` later (so
  ``0 ≤ frame − sensor ≤ 10⁶/fps``, §2.6); the host receives the frame after the transfer
  (``bytes / usb_mb_per_s``) and a USB latency of 0.5–2.5 ms; ``time_of_arrival`` is host epoch ms
  (the simulated host clock is the session clock plus ``host_epoch_ns``);
  ``FrameTiming.host_time_ns`` is the session time of arrival (the mock host's monotonic clock);
  ``timestamp_ms`` = ``frame_timestamp_us / 1000`` in the ``hardware_clock`` domain (until
  global time is ready).
* ``metadata=False`` (or the fault ``no-metadata``) emulates a kernel without the UVC metadata
  patch (§0.5, §4.5): domain ``system_time``, no device timestamps, a host-made counter without
  gaps, ``timestamp_ms`` = host epoch ms.

Pacing
======

``"asap"`` (deterministic, for tests): each ``poll()`` advances that camera's simulated time to
its next frame and returns it at once; cameras are independent, so framesets of different
cameras need not come in time order (the protocol allows it). A camera started later starts at
the rig's simulated "now" (the latest arrival delivered so far). ``"realtime"``: frames become
available when the wall clock (since the first ``start()``) reaches their arrival time;
``poll(timeout_s)`` waits up to ``timeout_s`` for it. When the simulated session ends, ``poll``
returns ``None`` (no more frames ever arrive).

Faults (:class:`D415Fault`, names usable on a command line)
===========================================================

``slave-trigger-cut``  the slave stops receiving pulses at ``at_s`` (default 1 s) and free-runs
                       after the timeout; ``camera`` defaults to the first slave.
``drops``              random bursty (Gilbert) capture losses: ``rate`` per frame (default 2 %),
                       mean burst ``burst`` frames; counter gaps; all cameras unless ``camera``.
``incomplete-frame``   with probability ``rate`` (default 2 %) a delivered frame's rows from a
                       random row on are zero in IR and depth ("incomplete video frame", §4.6).
``disconnect``         from ``at_s`` (default 1 s) every call raises ``DeviceError`` (the camera
                       is gone); a disconnected master stops emitting pulses. ``camera`` defaults
                       to the last camera.
``bandwidth-cap``      the cameras share ``mbps`` (default 1000 Mb/s; §1.7: 293 Mb/s per camera
                       at 848×480@30 with depth + IR): while the streaming cameras' sum exceeds
                       it, captures are lost with probability ``1 − cap/sum``, in bursts.
``no-metadata``        as ``metadata=False``.
``counter-reset``      an ESD event (§2.4, #6461): at ``at_s`` (default 1 s) the frame counter of
                       ``camera`` (default the last) restarts at 0.

``clock-wrap``         the u32 µs hardware clock of ``camera`` (default all) wraps to 0 at ``at_s``
                       (default 1 s; §2.5, it happens every 71.6 min of uptime).
``trigger-dropout``    an intermittent sync cable: each pulse is missed by ``camera`` (default
                       all slaves) with probability ``rate`` (default 2 %), from ``at_s`` on.

A restart (``stop()`` then ``start()``) also restarts the counter at 0 (§4.5); the first
``start()`` begins at an arbitrary value.

A fault string is ``kind`` or ``kind:key=value,key=value`` (keys ``camera``, ``at_s``, ``rate``,
``burst``, ``mbps``), e.g. ``slave-trigger-cut:camera=d415-2,at_s=2.5`` or ``drops:rate=0.1``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, fields, replace
from types import TracebackType
from typing import Any, Final, Literal, Self, get_args

import numpy as np

from mocaprig.acquire.depth_camera import (
    D415_PRODUCT_NAME,
    CameraInfo,
    D415Frame,
    Extrinsics,
    FrameSet,
    FrameTiming,
    Intrinsics,
    SensorOptions,
    StreamConfig,
    StreamKind,
    SyncMode,
    TimestampDomain,
    check_sync_mode,
)
from mocaprig.drivers_mock.d415_render import (
    DepthModel,
    IrModel,
    IrSettings,
    Quality,
    RenderedFrame,
    Room,
    SceneRenderer,
    mode_intrinsics,
)
from mocaprig.drivers_mock.rig import D415Spec, D415Timing
from mocaprig.drivers_mock.scenario import Scenario, build_scenario, stream_rng
from mocaprig.errors import DeviceDisconnectedError, DeviceError, ValidationError

__all__ = [
    "FAULT_KINDS",
    "CaptureRecord",
    "D415Fault",
    "FaultKind",
    "MockD415",
    "MockD415Rig",
    "Pacing",
    "mock_cameras",
    "parse_faults",
]

_log = logging.getLogger(__name__)

FaultKind = Literal[
    "slave-trigger-cut",
    "drops",
    "incomplete-frame",
    "disconnect",
    "bandwidth-cap",
    "no-metadata",
    "counter-reset",
    "clock-wrap",
    "trigger-dropout",
]
#: Fault names, as accepted by :meth:`D415Fault.parse`.
FAULT_KINDS: Final[tuple[str, ...]] = get_args(FaultKind)

Pacing = Literal["asap", "realtime"]

_U32: Final = 1 << 32
#: Default session length (s) when the factory builds the world itself.
DEFAULT_SECONDS: Final = 10.0
#: 2026-01-01T00:00:00Z: the simulated host's epoch clock at session time 0.
DEFAULT_HOST_EPOCH_NS: Final = 1_767_225_600_000_000_000


@dataclass(frozen=True, slots=True)
class D415Fault:
    """One injected fault (module doc for the kinds and their defaults).

    Attributes:
        kind: The fault name.
        camera: Rig name (``"d415-1"``), serial or list index (``"1"``) of the camera it hits;
            ``None`` = the kind's default (first slave, last camera, or all cameras).
        at_s: Session time (s) it starts (trigger cut, disconnect); drops and incomplete frames
            start at it too when given.
        rate: Probability per frame (drops, incomplete frames).
        burst: Mean burst length in frames (drops, bandwidth cap).
        mbps: USB budget shared by all cameras (Mb/s; bandwidth cap).
    """

    kind: FaultKind
    camera: str | None = None
    at_s: float | None = None
    rate: float = 0.02
    burst: float = 2.0
    mbps: float = 1000.0

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            msg = f"unknown D415 fault {self.kind!r}; choose one of {list(FAULT_KINDS)}"
            raise ValidationError(msg)
        if not (0.0 <= self.rate <= 1.0):
            msg = f"D415 fault {self.kind}: rate must lie in [0, 1], got {self.rate!r}"
            raise ValidationError(msg)
        if not (self.burst >= 1.0 and self.mbps > 0):
            msg = f"D415 fault {self.kind}: burst must be >= 1 frame and mbps > 0"
            raise ValidationError(msg)
        if self.at_s is not None and not (np.isfinite(self.at_s) and self.at_s >= 0):
            msg = f"D415 fault {self.kind}: at_s must be a time >= 0 s, got {self.at_s!r}"
            raise ValidationError(msg)

    @classmethod
    def parse(cls, text: str) -> D415Fault:
        """Parse ``kind`` or ``kind:key=value,...`` (module doc).

        Raises:
            ValidationError: unknown kind or key, or a malformed value.
        """
        kind, _, rest = text.strip().partition(":")
        if kind not in FAULT_KINDS:
            msg = f"unknown D415 fault {kind!r} in {text!r}; choose one of {list(FAULT_KINDS)}"
            raise ValidationError(msg)
        kw: dict[str, Any] = {}
        keys = {f.name for f in fields(cls)} - {"kind"}
        for item in filter(None, (p.strip() for p in rest.split(","))):
            key, eq, value = item.partition("=")
            if not eq or key not in keys:
                msg = f"D415 fault {text!r}: expected key=value with a key in {sorted(keys)}"
                raise ValidationError(msg)
            try:
                kw[key] = value if key == "camera" else float(value)
            except ValueError as err:
                msg = f"D415 fault {text!r}: {key} must be a number, got {value!r}"
                raise ValidationError(msg) from err
        return cls(kind, **kw)  # type: ignore[arg-type]


def parse_faults(
    faults: Iterable[str | D415Fault] | str | D415Fault | None,
) -> tuple[D415Fault, ...]:
    """Normalise faults given as strings, :class:`D415Fault` objects or ``None``."""
    if faults is None:
        return ()
    if isinstance(faults, str | D415Fault):
        faults = [faults]
    out: list[D415Fault] = []
    for f in faults:
        if isinstance(f, D415Fault):
            out.append(f)
        else:
            out.extend(D415Fault.parse(p) for p in str(f).split(";") if p.strip())
    return tuple(out)


@dataclass(frozen=True, slots=True)
class CaptureRecord:
    """Ground truth of one capture of one camera (delivered or not).

    Attributes:
        frame_counter: The hardware counter of the capture.
        exposure_start_ns: Session time the exposure started.
        exposure_ns: Exposure length (ns).
        arrival_ns: Session time the host received it.
        triggered: ``True`` if it was started by a master pulse (slave), ``False`` if the camera
            triggered itself (free-run, master, mode 0).
        pulse_ns: The master pulse that triggered it (session ns), or ``None``.
        outcome: ``"delivered"``, ``"incomplete"``, ``"dropped"`` or ``"bandwidth"``.
    """

    frame_counter: int
    exposure_start_ns: int
    exposure_ns: int
    arrival_ns: int
    triggered: bool
    pulse_ns: int | None
    outcome: str

    @property
    def mid_exposure_ns(self) -> int:
        """Session time of the middle of the exposure (what ``sensor_timestamp`` stamps)."""
        return self.exposure_start_ns + self.exposure_ns // 2


@dataclass(slots=True)
class _Capture:
    counter: int
    t_start: int
    exposure_ns: int
    t_tx: int
    arrival: int
    triggered: bool
    pulse: int | None


class MockD415Rig:
    """The shared world of a set of mock D415: scenario, master timeline, USB budget.

    Built by :func:`mock_cameras`; its cameras are :attr:`cameras` (rig order, master first).
    """

    def __init__(
        self,
        scenario: Scenario,
        *,
        specs: Sequence[D415Spec],
        faults: Sequence[D415Fault] = (),
        pacing: Pacing = "asap",
        quality: Quality = "fast",
        metadata: bool = True,
        images: bool = True,
        trigger_timeout_ms: float = 50.0,
        trigger_delay_us: float | None = None,
        trigger_jitter_us: float = 5.0,
        startup_ms: float = 60.0,
        usb_mb_per_s: float = 350.0,
        host_epoch_ns: int = DEFAULT_HOST_EPOCH_NS,
        depth_model: DepthModel | None = None,
        ir_model: IrModel | None = None,
        room: Room | None = None,
        timing: D415Timing | None = None,
        global_time_enabled: bool = True,
    ) -> None:
        if pacing not in get_args(Pacing):
            msg = f"pacing must be one of {get_args(Pacing)}, got {pacing!r}"
            raise ValidationError(msg)
        if quality not in ("fast", "full"):
            msg = f"quality must be 'fast' or 'full', got {quality!r}"
            raise ValidationError(msg)
        timing = scenario.rig.d415_timing if timing is None else timing
        if trigger_delay_us is not None:
            timing = replace(timing, trigger_to_exposure_us=float(trigger_delay_us))
        if not (trigger_timeout_ms > 0 and trigger_jitter_us >= 0):
            msg = "trigger_timeout_ms must be > 0 and trigger_jitter_us >= 0"
            raise ValidationError(msg)
        self.scenario = scenario
        self.pacing: Pacing = pacing
        self.quality: Quality = quality
        self.metadata = bool(metadata)
        self.images = bool(images)
        self.trigger_timeout_ns = round(trigger_timeout_ms * 1e6)
        self.timing = timing
        self.global_time_enabled = bool(global_time_enabled)
        self.trigger_delay_ns = round(timing.trigger_to_exposure_us * 1e3)
        self.trigger_jitter_ns = float(trigger_jitter_us) * 1e3
        self.startup_ns = round(startup_ms * 1e6)
        self.usb_bytes_per_ns = usb_mb_per_s * 1e6 / 1e9
        self.host_epoch_ns = int(host_epoch_ns)
        self.depth_model = depth_model or DepthModel()
        self.ir_model = ir_model or IrModel()
        self.room = room or Room()
        self.faults = tuple(faults)
        self._lock = threading.RLock()
        self._now_ns = 0
        self._wall0_ns: int | None = None
        self.cameras: list[MockD415] = [MockD415(self, spec, i) for i, spec in enumerate(specs)]
        for f in self.faults:
            if f.kind == "no-metadata":
                self.metadata = False
            else:
                self._resolve(f)  # fail early on a bad camera reference

    # -- fault targets -------------------------------------------------------------------

    def _resolve(self, fault: D415Fault) -> list[MockD415]:
        cams = self.cameras
        if fault.camera is None:
            if fault.kind == "slave-trigger-cut":
                slaves = [c for c in cams if c.sync_mode is SyncMode.SLAVE]
                return slaves[:1] if slaves else cams[1:2]
            if fault.kind in ("disconnect", "counter-reset"):
                return cams[-1:]
            return list(cams)
        for c in cams:
            if fault.camera in (c.spec.name, c.spec.serial, str(c.index)):
                return [c]
        names = [c.spec.name for c in cams]
        msg = f"D415 fault {fault.kind}: no camera {fault.camera!r}; the rig has {names}"
        raise ValidationError(msg)

    def faults_for(self, cam: MockD415, kind: str) -> list[D415Fault]:
        """The faults of ``kind`` that hit ``cam``."""
        return [f for f in self.faults if f.kind == kind and cam in self._resolve(f)]

    # -- time -------------------------------------------------------------------------------

    def now_ns(self) -> int:
        """The rig's simulated session time now (asap: latest arrival; realtime: wall clock)."""
        with self._lock:
            if self.pacing == "realtime":
                if self._wall0_ns is None:
                    self._wall0_ns = time.monotonic_ns()
                return time.monotonic_ns() - self._wall0_ns
            return self._now_ns

    @property
    def session_t0_monotonic_ns(self) -> int:
        """``time.monotonic_ns()`` of session time 0 in ``"realtime"`` pacing (set on first use;
        pass it to :func:`drivers_mock.syncbox.mock_syncbox` to share the pulse timeline)."""
        with self._lock:
            if self._wall0_ns is None:
                self._wall0_ns = time.monotonic_ns()
            return self._wall0_ns

    def advance(self, t_ns: int) -> None:
        """Move the simulated "now" forward (asap pacing; a camera starts at "now")."""
        with self._lock:
            self._now_ns = max(self._now_ns, int(t_ns))

    @property
    def master(self) -> MockD415 | None:
        """The camera configured as sync master (the first one), if any."""
        for c in self.cameras:
            if c.sync_mode is SyncMode.MASTER:
                return c
        return None

    def next_pulse(self, after_ns: int, listener: MockD415) -> int | None:
        """The first master pulse at or after ``after_ns`` that reaches ``listener``."""
        m = self.master
        if m is None or m is listener:
            return None
        t = m.pulse_at_or_after(after_ns)
        dropouts = self.faults_for(listener, "trigger-dropout")
        for _ in range(10_000):
            if t is None:
                return None
            for f in self.faults_for(listener, "slave-trigger-cut"):
                cut = round((1.0 if f.at_s is None else f.at_s) * 1e9)
                if t >= cut:
                    return None
            if not any(self._pulse_missed(f, listener, t) for f in dropouts):
                return t
            t = m.pulse_at_or_after(t + 1)
        return None

    def _pulse_missed(self, fault: D415Fault, listener: MockD415, t_ns: int) -> bool:
        """Whether ``listener`` misses the pulse at ``t_ns`` (``trigger-dropout``: a seeded,
        per-pulse draw, so the same pulse is always missed or always received)."""
        if fault.at_s is not None and t_ns < fault.at_s * 1e9:
            return False
        rng = np.random.default_rng([self.scenario.seed, listener.index, t_ns])
        return bool(rng.random() < fault.rate)

    def aggregate_bits_per_s(self) -> float:
        """The streaming cameras' combined USB payload (depth Z16 + IR Y8, §1.7)."""
        return float(sum(c.bits_per_s for c in self.cameras if c.is_streaming))


class MockD415:
    """One simulated D415 (the ``DepthCamera`` protocol; see the module doc)."""

    def __init__(self, rig: MockD415Rig, spec: D415Spec, index: int) -> None:
        self.rig = rig
        self.spec = spec
        self.index = index
        self.clock = rig.scenario.clocks[spec.name]
        self._info = CameraInfo(
            serial=spec.serial,
            name=D415_PRODUCT_NAME,
            firmware=spec.firmware,
            usb_type="3.2",
            product_line="D400",
        )
        self._stream: StreamConfig | None = None
        self._options = SensorOptions()
        self._sync = SyncMode.DEFAULT
        self._streaming = False
        self._closed = False
        self._disconnected = False
        self._renderer: SceneRenderer | None = None
        self._rng = stream_rng(rig.scenario.seed, f"d415-mock-{spec.serial}")
        self._counter = int(self._rng.integers(0, 100_000))
        self._host_counter = 0
        self._runs = 0
        self._start_ns = 0
        self._stop_ns: int | None = None
        self._last_start: int | None = None
        self._free_anchor: tuple[int, int] | None = None  # (t_first, k) of self-timed captures
        self._k = 0
        self._free_running = False
        self._pending: _Capture | None = None
        self._drop_bad = False
        self._bw_bad = False
        self._resets_done: set[int] = set()
        #: Deliver synced frames without metadata (``True``) or refuse them, like the adapter.
        self.allow_no_metadata = False
        self._warned_no_metadata = False
        # Undocumented timing of this unit (D415Timing), drawn from streams of their own so
        # the default world's other draws are unchanged.
        t = rig.timing
        unit = stream_rng(rig.scenario.seed, f"d415-unit-timing-{spec.serial}")
        self.free_run_period_ppm = t.free_run_period_ppm + t.free_run_period_spread_ppm * float(
            unit.normal()
        )
        self._gt_offset_ns = t.global_time_offset_us * 1e3 * float(unit.normal())
        self._gt_rate = t.global_time_rate_ppm * 1e-6 * float(unit.normal())
        self._gt_rng = stream_rng(rig.scenario.seed, f"d415-global-time-{spec.serial}")
        #: Every capture since construction, delivered or not (ground truth for tests).
        self.captures: list[CaptureRecord] = []
        #: The render behind the last delivered frameset (marker truth), or ``None``.
        self.last_render: RenderedFrame | None = None

    # -- protocol: identity ------------------------------------------------------------------

    @property
    def info(self) -> CameraInfo:
        """Identity strings (serial from the rig, firmware 5.16.0.1, USB 3.2)."""
        return self._info

    @property
    def depth_scale_m(self) -> float:
        """Metres per Z16 unit (the spec's 0.001)."""
        return float(self.spec.depth_scale_m)

    @property
    def sync_mode(self) -> SyncMode:
        """The configured ``inter_cam_sync_mode``."""
        return self._sync

    @property
    def is_streaming(self) -> bool:
        """``True`` between :meth:`start` and :meth:`stop`."""
        return self._streaming

    @property
    def stream(self) -> StreamConfig:
        """The configured mode (the default 848×480@30 until configured)."""
        return self._stream or StreamConfig()

    @property
    def bits_per_s(self) -> float:
        """USB payload of this camera's depth + IR streams (b/s, §1.7)."""
        s = self.stream
        return float(s.width * s.height * 3 * 8 * s.fps)

    def _check_alive(self) -> None:
        if self._closed:
            msg = f"D415 {self.spec.serial} (mock) is closed"
            raise DeviceError(msg)
        if self._disconnected:
            msg = (
                f"D415 {self.spec.serial} (mock) was disconnected (injected fault); "
                "check the USB cable and hub, then reopen the camera"
            )
            raise DeviceDisconnectedError(msg)

    # -- protocol: configuration ----------------------------------------------------------------

    def configure(
        self, *, stream: StreamConfig, options: SensorOptions, sync_mode: SyncMode
    ) -> None:
        """Set mode, exposure/gain/laser and sync mode; only while stopped (§2.3).

        Raises:
            DeviceError: streaming, closed or disconnected.
            ValidationError: a sync mode above 2, or an exposure longer than the frame period.
        """
        self._check_alive()
        if self._streaming:
            msg = (
                f"D415 {self.spec.serial}: cannot configure while streaming "
                "(inter_cam_sync_mode is read-only while the sensor is open); stop() first"
            )
            raise DeviceError(msg)
        mode = check_sync_mode(int(sync_mode), serial=self.spec.serial)
        options.check_fits(stream)
        self._stream, self._options, self._sync = stream, options, mode

    def intrinsics(self) -> Intrinsics:
        """Intrinsics of the configured mode (the rig's K scaled per §1.2/§1.4; zero coeffs).

        Raises:
            DeviceError: not configured yet (as the real adapter).
        """
        self._check_alive()
        if self._stream is None:
            msg = f"D415 {self.spec.serial}: call configure() first (intrinsics depend on the mode)"
            raise DeviceError(msg)
        k = mode_intrinsics(self.spec.ir_left.K, self._stream.width, self._stream.height)
        return Intrinsics(
            width=self._stream.width,
            height=self._stream.height,
            fx=float(k[0, 0]),
            fy=float(k[1, 1]),
            ppx=float(k[0, 2]),
            ppy=float(k[1, 2]),
        )

    def extrinsics_ir_to_depth(self) -> Extrinsics:
        """Identity: depth is computed in the left imager's frame (§1.2)."""
        self._check_alive()
        return Extrinsics()

    # -- protocol: streaming ---------------------------------------------------------------------

    def start(self) -> None:
        """Open the sensor and start streaming at the rig's current simulated time.

        Raises:
            DeviceError: already streaming, closed or disconnected.
        """
        self._check_alive()
        if self._streaming:
            msg = f"D415 {self.spec.serial} is already streaming"
            raise DeviceError(msg)
        s = self.stream
        if self.rig.images and (
            self._renderer is None
            or (self._renderer.width, self._renderer.height) != (s.width, s.height)
        ):
            self._renderer = SceneRenderer(
                self.rig.scenario,
                self.spec,
                width=s.width,
                height=s.height,
                depth_scale_m=self.depth_scale_m,
                depth_model=self.rig.depth_model,
                ir_model=self.rig.ir_model,
                room=self.rig.room,
                quality=self.rig.quality,
            )
        self._start_ns = self.rig.now_ns()
        self._stop_ns = None
        self._last_start = None
        self._pending = None
        self._k = 0
        self._free_running = False
        if self._runs > 0:
            self._counter = 0  # a stream restart resets the hardware counter (§4.5)
        phase = int(self._rng.integers(0, self._period_ns()))
        self._free_anchor = (self._start_ns + self.rig.startup_ns + phase, 0)
        self._runs += 1
        self._streaming = True
        _log.debug("mock D415 %s started (%s, %s)", self.spec.serial, s, self._sync.name)

    def stop(self) -> None:
        """Stop streaming (no-op when stopped)."""
        if not self._streaming:
            return
        self._streaming = False
        self._stop_ns = max(self.rig.now_ns(), self._last_start or 0)
        self._pending = None

    def close(self) -> None:
        """Stop and release the device (idempotent)."""
        if self._streaming and not self._disconnected:
            self.stop()
        self._streaming = False
        self._closed = True

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- timeline ----------------------------------------------------------------------------

    def _own_period(self) -> float:
        """Self-timed frame period: ``1/fps`` of this camera's own clock, times its unit's
        ``1 + free_run_period_ppm·1e-6`` (:class:`D415Timing`), in session ns."""
        return 1e9 / self.stream.fps / self.clock.rate * (1.0 + self.free_run_period_ppm * 1e-6)

    def _period_ns(self) -> int:
        """Self-timed frame period (:meth:`_own_period`), rounded to ns."""
        return round(self._own_period())

    def _self_timed(self, k: int) -> int:
        anchor = self._free_anchor
        if anchor is None:
            msg = f"D415 {self.spec.serial}: not started"
            raise DeviceError(msg)
        t0, k0 = anchor
        return t0 + round((k - k0) * self._own_period())

    def _pulse_lag_ns(self) -> int:
        """Pulse after the master's exposure start: 0, or its exposure (``readout-start``)."""
        if self.rig.timing.pulse_at == "readout-start":
            return int(self._options.exposure_us) * 1000
        return 0

    def pulse_at_or_after(self, t_ns: int) -> int | None:
        """The first sync pulse this camera (as master) emits at or after ``t_ns``.

        The master emits one pulse per self-timed capture, at its exposure start or at its
        readout start (``D415Timing.pulse_at``).
        """
        if self._sync is not SyncMode.MASTER or self._free_anchor is None:
            return None
        if not self._streaming and self._stop_ns is None:
            return None
        t0, _ = self._free_anchor
        t0 += self._pulse_lag_ns()
        period = self._own_period()
        k = max(0, int(np.ceil((t_ns - t0) / period)))
        t = t0 + round(k * period)
        if t < t_ns:
            t = t0 + round((k + 1) * period)
        end = self._stop_ns
        for f in self.rig.faults_for(self, "disconnect"):
            cut = round((1.0 if f.at_s is None else f.at_s) * 1e9)
            end = cut if end is None else min(end, cut)
        if end is not None and t >= end:
            return None
        return t

    def _next_start(self) -> tuple[int, bool, int | None]:
        """Exposure start of the next capture: (session ns, triggered, pulse)."""
        if self._sync is not SyncMode.SLAVE:
            t = self._self_timed(self._k)
            self._k += 1
            return t, False, None
        rig = self.rig
        period = self._period_ns()
        if self._last_start is None:
            lo = self._start_ns + rig.startup_ns
            deadline = lo + rig.trigger_timeout_ns
        else:
            # Pulses too soon after the previous exposure start are ignored (the sensor is
            # still busy with that frame; assumed: 35 % of a period).
            lo = self._last_start + round(0.35 * period)
            wait = period if self._free_running else rig.trigger_timeout_ns
            deadline = self._last_start + wait
        pulse = rig.next_pulse(lo, self)
        if pulse is not None and pulse + rig.trigger_delay_ns <= deadline:
            jitter = round(self._rng.normal(0.0, rig.trigger_jitter_ns))
            if self._free_running:
                _log.debug("mock D415 %s: pulses again, locked", self.spec.serial)
            self._free_running = False
            return pulse + rig.trigger_delay_ns + jitter, True, pulse
        if not self._free_running:
            _log.debug("mock D415 %s: no trigger, free-running", self.spec.serial)
        self._free_running = True
        return deadline, False, None

    def _make_capture(self) -> _Capture:
        t_start, triggered, pulse = self._next_start()
        for f in self.rig.faults_for(self, "counter-reset"):
            at = round((1.0 if f.at_s is None else f.at_s) * 1e9)
            if (self._last_start or -1) < at <= t_start and at not in self._resets_done:
                self._resets_done.add(at)
                self._counter = 0
                _log.info("mock D415 %s: injected counter reset (ESD)", self.spec.serial)
        self._last_start = t_start
        s = self.stream
        exposure_ns = int(self._options.exposure_us) * 1000
        period = 1e9 / s.fps
        t_tx = t_start + exposure_ns + round(0.3 * period)
        transfer = round(s.width * s.height * 3 / self.rig.usb_bytes_per_ns)
        latency = round(self._rng.uniform(0.5e6, 2.5e6))
        cap = _Capture(
            counter=self._counter,
            t_start=t_start,
            exposure_ns=exposure_ns,
            t_tx=t_tx,
            arrival=t_tx + transfer + latency,
            triggered=triggered,
            pulse=pulse,
        )
        self._counter = (self._counter + 1) % _U32
        return cap

    def _lost(self, cap: _Capture) -> str | None:
        """Why a capture is lost (drops, bandwidth), or ``None``."""
        rig = self.rig
        # A hidden world parameter: the master loses its first captures (its pulses still go
        # out), so its first recorded frame is not its first pulse.
        lost_first = rig.scenario.world_params.master_dropped_frames
        master = self._sync is SyncMode.MASTER
        if lost_first and master and self._runs == 1 and self._k <= lost_first:
            return "dropped"
        for f in rig.faults_for(self, "drops"):
            if f.at_s is not None and cap.t_start < f.at_s * 1e9:
                continue
            self._drop_bad = _gilbert(self._rng, self._drop_bad, f.rate, f.burst)
            if self._drop_bad:
                return "dropped"
        for f in rig.faults_for(self, "bandwidth-cap"):
            total = rig.aggregate_bits_per_s()
            p = max(0.0, 1.0 - f.mbps * 1e6 / total) if total > 0 else 0.0
            self._bw_bad = _gilbert(self._rng, self._bw_bad, p, f.burst)
            if self._bw_bad:
                return "bandwidth"
        return None

    def _wrap_shift(self) -> int:
        """µs added to the hardware clock so that it wraps at a ``clock-wrap`` fault's time."""
        for f in self.rig.faults_for(self, "clock-wrap"):
            at = round((1.0 if f.at_s is None else f.at_s) * 1e9)
            ticks = int(self.clock.device_ticks(np.array([at], np.int64), jitter=False)[0])
            return (-ticks) % _U32
        return 0

    def _disconnect_at(self) -> int | None:
        times = [
            round((1.0 if f.at_s is None else f.at_s) * 1e9)
            for f in self.rig.faults_for(self, "disconnect")
        ]
        return min(times) if times else None

    # -- protocol: frames ----------------------------------------------------------------------

    def poll(self, timeout_s: float = 0.0) -> FrameSet | None:
        """The next frameset (module doc for pacing), or ``None``.

        Raises:
            DeviceError: not streaming, closed, or disconnected (injected fault).
        """
        self._check_alive()
        if not self._streaming:
            msg = f"D415 {self.spec.serial} is not streaming; call start() first"
            raise DeviceError(msg)
        rig = self.rig
        while True:
            if self._pending is None:
                cap = self._make_capture()
                cut = self._disconnect_at()
                if cut is not None and cap.t_start >= cut:
                    self._disconnected = True
                    self._streaming = False
                    self._stop_ns = cut
                    _log.info("mock D415 %s: injected disconnect", self.spec.serial)
                    self._check_alive()
                if cap.arrival <= rig.scenario.duration_ns:
                    why = self._lost(cap)
                    if why is not None:
                        self._record(cap, why)
                        continue
                self._pending = cap
            cap = self._pending
            if cap.arrival > rig.scenario.duration_ns:
                # The simulated session is over: no frame will ever arrive.
                if rig.pacing == "realtime":
                    time.sleep(max(0.0, timeout_s))
                return None
            if rig.pacing == "realtime":
                wait_s = (cap.arrival - rig.now_ns()) * 1e-9
                if wait_s > timeout_s:
                    time.sleep(max(0.0, timeout_s))
                    return None
                if wait_s > 0:
                    time.sleep(wait_s)
            self._pending = None
            rig.advance(cap.arrival)
            return self._deliver(cap)

    def _record(self, cap: _Capture, outcome: str) -> None:
        self.captures.append(
            CaptureRecord(
                frame_counter=cap.counter,
                exposure_start_ns=cap.t_start,
                exposure_ns=cap.exposure_ns,
                arrival_ns=cap.arrival,
                triggered=cap.triggered,
                pulse_ns=cap.pulse,
                outcome=outcome,
            )
        )

    def _deliver(self, cap: _Capture) -> FrameSet:
        o = self._options
        settings = IrSettings(o.exposure_us, o.gain, o.laser_power_mw, o.emitter_enabled)
        frame_rng = stream_rng(
            self.rig.scenario.seed, f"d415-frame-{self.spec.serial}-{self._runs}-{cap.counter}"
        )
        rendered: RenderedFrame | None = None
        if self.rig.images and self._renderer is not None:
            rendered = self._renderer.render(cap.t_start, settings, frame_rng)
            depth, ir = rendered.depth_z16, rendered.ir_y8
        else:
            depth = np.zeros((self.stream.height, self.stream.width), np.uint16)
            ir = np.zeros((self.stream.height, self.stream.width), np.uint8)
        outcome = "delivered"
        for f in self.rig.faults_for(self, "incomplete-frame"):
            if f.at_s is not None and cap.t_start < f.at_s * 1e9:
                continue
            if self._rng.random() < f.rate:
                row = int(self._rng.integers(1, depth.shape[0]))
                depth[row:] = 0
                ir[row:] = 0
                outcome = "incomplete"
        self._record(cap, outcome)
        self.last_render = rendered
        timing = self._timing(cap)
        return FrameSet(
            serial=self.spec.serial,
            infrared=D415Frame(StreamKind.INFRARED_LEFT, ir, timing),
            depth=D415Frame(StreamKind.DEPTH, depth, timing),
            depth_scale_m=self.depth_scale_m,
        )

    def _timing(self, cap: _Capture) -> FrameTiming:
        rig = self.rig
        arrival_epoch_ns = rig.host_epoch_ns + cap.arrival
        if not rig.metadata:
            if self._sync is not SyncMode.DEFAULT and not self.allow_no_metadata:
                msg = (
                    f"D415 {self.spec.serial} (mock, {self._sync.name.lower()}): frames carry no "
                    "hardware timestamps (no UVC metadata), so synced capture is refused; "
                    "enable metadata (kernel patch or RSUSB backend) or force it with "
                    "allow_no_metadata=True (--allow-no-metadata)"
                )
                raise DeviceError(msg)
            if not self._warned_no_metadata:
                self._warned_no_metadata = True
                _log.warning(
                    "mock D415 %s: NO FRAME METADATA: system_time stamps, host-made counters",
                    self.spec.serial,
                )
            self._host_counter += 1
            return FrameTiming(
                frame_counter=self._host_counter,
                sensor_timestamp_us=None,
                frame_timestamp_us=None,
                time_of_arrival_ms=arrival_epoch_ns // 1_000_000,
                timestamp_domain=TimestampDomain.SYSTEM_TIME,
                host_time_ns=cap.arrival,
                timestamp_ms=arrival_epoch_ns / 1e6,
            )
        mid = cap.t_start + cap.exposure_ns // 2
        shift = self._wrap_shift()
        sensor_us, frame_us = (
            (int(x) + shift) % _U32
            for x in self.clock.device_ticks(np.array([mid, cap.t_tx], np.int64))
        )
        domain, stamp_ms = TimestampDomain.HARDWARE_CLOCK, frame_us / 1000.0
        timing = rig.timing
        ready_ns = self._start_ns + round(timing.global_time_ready_s * 1e9)
        if rig.global_time_enabled and cap.t_tx >= ready_ns:
            # The keeper maps the device clock onto the host's (realsense-d415.md §2.7), with
            # an offset error, a residual rate error and jitter of its own.
            err_ns = (
                self._gt_offset_ns
                + self._gt_rate * (cap.t_tx - ready_ns)
                + timing.global_time_jitter_us * 1e3 * float(self._gt_rng.normal())
            )
            domain = TimestampDomain.GLOBAL_TIME
            stamp_ms = (rig.host_epoch_ns + cap.t_tx + err_ns) / 1e6
        return FrameTiming(
            frame_counter=cap.counter,
            sensor_timestamp_us=sensor_us,
            frame_timestamp_us=frame_us,
            time_of_arrival_ms=arrival_epoch_ns // 1_000_000,
            timestamp_domain=domain,
            host_time_ns=cap.arrival,
            timestamp_ms=stamp_ms,
        )

    def __repr__(self) -> str:
        return (
            f"MockD415({self.spec.name}, serial={self.spec.serial}, {self.stream}, "
            f"{self._sync.name.lower()}, {'streaming' if self._streaming else 'stopped'})"
        )


def _gilbert(rng: np.random.Generator, bad: bool, p: float, burst: float) -> bool:
    """One step of a two-state (Gilbert) loss chain with stationary loss ``p``, mean burst."""
    if p <= 0.0:
        return False
    if p >= 1.0:
        return True
    leave_bad = 1.0 / burst
    enter_bad = min(1.0, p * leave_bad / (1.0 - p))
    return bool(rng.random() >= leave_bad) if bad else bool(rng.random() < enter_bad)


def mock_cameras(
    *,
    scenario: str | Scenario = "default",
    seed: int = 0,
    seconds: float | None = None,
    count: int | None = None,
    faults: Iterable[str | D415Fault] | str | D415Fault | None = (),
    fault: str | D415Fault | None = None,
    pacing: Pacing = "asap",
    quality: Quality = "fast",
    metadata: bool = True,
    images: bool = True,
    trigger_timeout_ms: float = 50.0,
    depth_model: DepthModel | None = None,
    ir_model: IrModel | None = None,
    room: Room | None = None,
    timing: D415Timing | None = None,
    global_time_enabled: bool = True,
    **kwargs: Any,
) -> list[MockD415]:
    """Mock D415 cameras over one simulated world (entry point ``mocaprig.mocks: d415``).

    Args:
        scenario: A scenario name (built with ``seed`` and ``seconds``) or a built
            :class:`Scenario` (then ``seed``/``seconds`` are ignored).
        seed: The world's seed.
        seconds: Session length (s) when building the scenario (default 10 s); frames stop
            arriving at its end.
        count: Use only the first ``count`` rig cameras (default all four).
        faults: Faults (:class:`D415Fault` or strings, module doc); ``fault`` adds one more
            (the name the ``mocaprig d415 --mock-fault`` option passes).
        pacing: ``"asap"`` (deterministic simulated time) or ``"realtime"``.
        quality: Render noise quality, ``"fast"`` (noise banks) or ``"full"``.
        metadata: ``False`` emulates missing per-frame metadata (``system_time``).
        images: ``False`` skips rendering and delivers all-zero images (timing, sync and
            fault tests at ~0.2 ms per frameset).
        trigger_timeout_ms: A slave's wait for a pulse before it free-runs.
        depth_model, ir_model, room: Image model parameters (:mod:`drivers_mock.d415_render`).
        timing: The undocumented sync timing (:class:`~drivers_mock.rig.D415Timing`; default:
            the scenario rig's ``d415_timing``).
        global_time_enabled: The SDK option (on by default on a real D415): frames switch from
            ``hardware_clock`` to ``global_time`` ``timing.global_time_ready_s`` after start.
        **kwargs: Further :class:`MockD415Rig` options (``trigger_delay_us``,
            ``trigger_jitter_us``, ``startup_ms``, ``usb_mb_per_s``, ``host_epoch_ns``).

    Returns:
        The cameras in rig order (``d415-0`` first), unconfigured (sync mode 0).

    Raises:
        ValidationError: unknown scenario, fault or option; a bad ``count``.
    """
    allowed = {"trigger_delay_us", "trigger_jitter_us", "startup_ms", "usb_mb_per_s"}
    allowed |= {"host_epoch_ns"}
    unknown = sorted(set(kwargs) - allowed)
    if unknown:
        msg = f"mock_cameras(): unknown option(s) {unknown}; known extras: {sorted(allowed)}"
        raise ValidationError(msg)
    world = (
        scenario
        if isinstance(scenario, Scenario)
        else build_scenario(
            scenario, seed=seed, seconds=DEFAULT_SECONDS if seconds is None else seconds
        )
    )
    specs = list(world.rig.d415)
    if count is not None:
        if not (1 <= count <= len(specs)):
            msg = f"mock_cameras(): count must lie in 1..{len(specs)}, got {count}"
            raise ValidationError(msg)
        specs = specs[:count]
    all_faults = parse_faults(faults) + parse_faults(fault)
    rig = MockD415Rig(
        world,
        specs=specs,
        faults=all_faults,
        pacing=pacing,
        quality=quality,
        metadata=metadata,
        images=images,
        trigger_timeout_ms=trigger_timeout_ms,
        depth_model=depth_model,
        ir_model=ir_model,
        room=room,
        timing=timing,
        global_time_enabled=global_time_enabled,
        **kwargs,
    )
    return list(rig.cameras)
