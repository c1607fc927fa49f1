"""A mock DAVIS240C (FX2 board, logic 18) behind a pyusb ``IBackend``.

Plug it in where the real device is found: ``usb.core.find(idVendor=0x152A, idProduct=0x841B,
backend=mock_backend())``. Everything is written from ``davis240c-usb.md`` (the "note"), not
from the driver, so a test can catch the two disagreeing:

* descriptors (§1, §12): VID 0x152A, PID 0x841B, bcdDevice 0x0004 (FX2 firmware 4), bcdUSB
  2.00, EP0 64 bytes, one configuration (1), interface 0 alt 0 with the bulk IN endpoint 0x82
  (512 bytes; the debug endpoint 0x81 is FX3-only, §1.2), string 3 = the 8-character serial;
* vendor requests (§2): 0xBF OUT/IN with 4-byte big-endian values (other lengths stall), 0xC2
  OUT batches of 6-byte entries applied in order; the register file of
  :mod:`mocaprig.drivers_mock.davis240c_registers`;
* the data path (§5, §7, §12): nothing reaches EP 0x82 unless MUX RUN and USB RUN are set; the
  timestamp counter runs only with MUX TIMESTAMP_RUN; DVS and APS need RUN_CHIP and their own
  RUN bit, the IMU one of its RUN_* bits, the external input RUN_DETECTOR; MUX TIMESTAMP_RESET
  resets device time; ``clear_halt(0x82)`` drops unsent data (§12.9);
* time: ``pacing="asap"`` advances device time by ``chunk_us`` per step inside ``bulk_read``
  (deterministic, for tests); ``pacing="realtime"`` lets device time follow the wall clock while
  the counter runs (for live demos). One call simulates at most ``_CATCH_UP_WALL_S`` of wall
  time: on a machine too loaded to simulate in real time, device time falls behind the wall
  clock (logged once) instead of a catch-up that never ends starving the host's reads;
* the output FIFO: between the logic and the host there is only ``fifo_bytes`` of buffering.
  While the host reads nothing (:meth:`Davis240CBackend.stall_host`, deterministic) device time
  runs on, the FIFO fills, and then the logic drops DVS / ext-input words (counted in MUX
  STATISTICS_DVS_DROPPED / STATISTICS_EXTINPUT_DROPPED) and holds APS / IMU words and wraps
  until the host reads again (note §3.1, §7.1);
* per-instance identity: ``read_only`` replaces read-only registers (ORIENTATION_INFO, the DVS
  HAS_* filter flags, the chip id...), ``power_on`` writable ones (a filter left on by another
  program), ``product_id`` the USB PID. The data path renders what the ORIENTATION_INFO
  registers say: with DVS bit 2 the Y words carry the column; the APS flips reverse the
  readout order;
* faults (:class:`DavisFaults`): unplug, a stalled endpoint, an odd-length transfer, a
  device-side timestamp reset, a USB bandwidth cap (DVS drops counted in MUX
  STATISTICS_DVS_DROPPED), the 0xFFFF wrap race.

Fault times are **device uptime** µs: the time the timestamp counter has run since power-on,
which timestamp resets do not rewind.
"""

from __future__ import annotations

import dataclasses
import errno
import importlib.util
import logging
import math
import struct
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import numpy.typing as npt
import usb.backend
import usb.core

from mocaprig.acquire.events import empty_events, make_events
from mocaprig.drivers_mock.davis240c_encoder import DavisWordEncoder, EncoderConfig
from mocaprig.drivers_mock.davis240c_registers import (
    APS,
    DVS,
    EXTINPUT,
    IMU,
    MUX,
    USB,
    DavisModule,
    RegisterFile,
)
from mocaprig.drivers_mock.davis_activity import (
    EXT_INPUT_DTYPE,
    IMU_DTYPE,
    ApsExposure,
    DavisActivity,
    DavisActivitySource,
    ExtInputEdge,
)
from mocaprig.errors import ValidationError

if TYPE_CHECKING:
    from mocaprig.drivers_mock.clock import DeviceClock
    from mocaprig.drivers_mock.scenario import Scenario

__all__ = [
    "DAVIS240C_PID",
    "DAVIS_VID",
    "Davis240CBackend",
    "DavisFaults",
    "Pacing",
    "SyntheticDavisSource",
    "mock_backend",
]

_log = logging.getLogger(__name__)

#: USB IDs of an FX2 DAVIS board (note §1.1).
DAVIS_VID = 0x152A
DAVIS240C_PID = 0x841B

#: Closed choice of time pacing.
Pacing = Literal["asap", "realtime"]

_DATA_EP = 0x82
_EP0_MAX_PACKET = 64
_BULK_MAX_PACKET = 512
_VR_FPGA_CONFIG = 0xBF
_VR_FPGA_CONFIG_MULTIPLE = 0xC2
_STR_MANUFACTURER, _STR_PRODUCT, _STR_SERIAL = 1, 2, 3
_LANGID_EN_US = 0x0409
#: Session length of the simulated world when the caller gives none (s).
_DEFAULT_SECONDS = 30.0
#: Device time a blocking read (timeout 0) may simulate before giving up (asap pacing).
_MAX_INFINITE_WAIT_US = 10_000_000
#: Wall time one realtime catch-up may spend simulating before it hands the device back (s).
_CATCH_UP_WALL_S = 0.05
#: Device-time lag behind the wall clock that is logged as a warning (realtime pacing, µs).
_LAG_WARN_US = 1_000_000

# libusb1 error codes and strings as pyusb's libusb1 backend reports them.
_LIBUSB_ERROR_NO_DEVICE = -4
_LIBUSB_ERROR_TIMEOUT = -7
_LIBUSB_ERROR_PIPE = -9
_LIBUSB_ERROR_INVALID_PARAM = -2
_LIBUSB_ERROR_NOT_FOUND = -5
_LIBUSB_ERROR_IO = -1


def _fill(buff: Any, payload: bytes | bytearray) -> int:
    """Copy ``payload`` into the start of a pyusb ``array('B')`` (or any writable buffer)."""
    view = memoryview(buff).cast("B")
    n = min(len(view), len(payload))
    view[:n] = payload[:n]
    return n


def _no_device() -> usb.core.USBError:
    return usb.core.USBError(
        "No such device (it may have been disconnected)", _LIBUSB_ERROR_NO_DEVICE, errno.ENODEV
    )


def _timeout() -> usb.core.USBTimeoutError:
    return usb.core.USBTimeoutError("Operation timed out", _LIBUSB_ERROR_TIMEOUT, errno.ETIMEDOUT)


def _pipe() -> usb.core.USBError:
    return usb.core.USBError("Pipe error", _LIBUSB_ERROR_PIPE, errno.EPIPE)


def _not_found() -> usb.core.USBError:
    return usb.core.USBError("Entity not found", _LIBUSB_ERROR_NOT_FOUND, errno.ENOENT)


def _invalid_param() -> usb.core.USBError:
    return usb.core.USBError("Invalid parameter", _LIBUSB_ERROR_INVALID_PARAM, errno.EINVAL)


def _io_error() -> usb.core.USBError:
    return usb.core.USBError("Input/Output Error", _LIBUSB_ERROR_IO, errno.EIO)


@dataclass(frozen=True, slots=True)
class DavisFaults:
    """Faults to inject; times are device uptime µs (module doc).

    Attributes:
        unplug_at_us: From this uptime on the device is gone: every I/O raises ``USBError``
            with errno ENODEV ("No such device (it may have been disconnected)") and it no
            longer enumerates.
        stall_at_us: Start of a stalled bulk endpoint: the output FIFO cannot drain, so bulk
            reads time out (``USBTimeoutError``) while device time runs on; DVS and ext-input
            words are dropped per the MUX DROP_* flags, APS/IMU words wait, wraps pile up
            (4096 pending force a timestamp reset, note §7.1).
        stall_us: Length of the stall (device µs).
        odd_packet_at_us: The first transfer at or after this uptime ends in the middle of a
            word (odd byte count); the word's other byte starts the next transfer.
        timestamp_reset_at_us: The device resets its timestamp by itself (as a slave does when
            its master resets, note §11.3): a TS-reset word goes out and time restarts at 0.
        bandwidth_bytes_per_s: USB throughput cap; DVS events beyond it are dropped (MUX
            DROP_DVS_ON_TRANSFER_STALL) and counted in MUX STATISTICS_DVS_DROPPED.
        wrap_race: Produce the 0xFFFF timestamp of note §7.1 at every rollover that has data.
    """

    unplug_at_us: int | None = None
    stall_at_us: int | None = None
    stall_us: int = 0
    odd_packet_at_us: int | None = None
    timestamp_reset_at_us: int | None = None
    bandwidth_bytes_per_s: float | None = None
    wrap_race: bool = False

    def __post_init__(self) -> None:
        if self.stall_us < 0:
            msg = f"DavisFaults.stall_us must be >= 0, got {self.stall_us}"
            raise ValidationError(msg)
        if self.bandwidth_bytes_per_s is not None and not self.bandwidth_bytes_per_s > 0:
            msg = "DavisFaults.bandwidth_bytes_per_s must be > 0 (or None for no cap)"
            raise ValidationError(msg)

    def stalled(self, uptime_us: int) -> bool:
        """Whether the endpoint is stalled at this uptime."""
        return self.stall_at_us is not None and (
            self.stall_at_us <= uptime_us < self.stall_at_us + self.stall_us
        )


# -- descriptors ---------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _DeviceDescriptor:
    bLength: int
    bDescriptorType: int
    bcdUSB: int
    bDeviceClass: int
    bDeviceSubClass: int
    bDeviceProtocol: int
    bMaxPacketSize0: int
    idVendor: int
    idProduct: int
    bcdDevice: int
    iManufacturer: int
    iProduct: int
    iSerialNumber: int
    bNumConfigurations: int
    bus: int
    address: int
    port_number: int
    port_numbers: tuple[int, ...]
    speed: int

    def to_bytes(self) -> bytes:
        return struct.pack(
            "<BBHBBBBHHHBBBB",
            self.bLength,
            self.bDescriptorType,
            self.bcdUSB,
            self.bDeviceClass,
            self.bDeviceSubClass,
            self.bDeviceProtocol,
            self.bMaxPacketSize0,
            self.idVendor,
            self.idProduct,
            self.bcdDevice,
            self.iManufacturer,
            self.iProduct,
            self.iSerialNumber,
            self.bNumConfigurations,
        )


@dataclass(frozen=True, slots=True)
class _ConfigurationDescriptor:
    bLength: int = 9
    bDescriptorType: int = 2
    wTotalLength: int = 9 + 9 + 7
    bNumInterfaces: int = 1
    bConfigurationValue: int = 1
    iConfiguration: int = 0
    bmAttributes: int = 0x80  # bus powered
    bMaxPower: int = 250  # 2 mA units; not documented in the note (unverified)
    extra_descriptors: tuple[int, ...] = ()

    def to_bytes(self) -> bytes:
        return struct.pack(
            "<BBHBBBBB",
            self.bLength,
            self.bDescriptorType,
            self.wTotalLength,
            self.bNumInterfaces,
            self.bConfigurationValue,
            self.iConfiguration,
            self.bmAttributes,
            self.bMaxPower,
        )


@dataclass(frozen=True, slots=True)
class _InterfaceDescriptor:
    bLength: int = 9
    bDescriptorType: int = 4
    bInterfaceNumber: int = 0
    bAlternateSetting: int = 0
    bNumEndpoints: int = 1
    bInterfaceClass: int = 0xFF  # vendor specific
    bInterfaceSubClass: int = 0
    bInterfaceProtocol: int = 0
    iInterface: int = 0
    extra_descriptors: tuple[int, ...] = ()

    def to_bytes(self) -> bytes:
        return struct.pack(
            "<9B",
            self.bLength,
            self.bDescriptorType,
            self.bInterfaceNumber,
            self.bAlternateSetting,
            self.bNumEndpoints,
            self.bInterfaceClass,
            self.bInterfaceSubClass,
            self.bInterfaceProtocol,
            self.iInterface,
        )


@dataclass(frozen=True, slots=True)
class _EndpointDescriptor:
    bLength: int = 7
    bDescriptorType: int = 5
    bEndpointAddress: int = _DATA_EP
    bmAttributes: int = 0x02  # bulk
    wMaxPacketSize: int = _BULK_MAX_PACKET
    bInterval: int = 0
    bRefresh: int = 0
    bSynchAddress: int = 0
    extra_descriptors: tuple[int, ...] = ()

    def to_bytes(self) -> bytes:
        return struct.pack(
            "<BBBBHB",
            self.bLength,
            self.bDescriptorType,
            self.bEndpointAddress,
            self.bmAttributes,
            self.wMaxPacketSize,
            self.bInterval,
        )


@dataclass(slots=True)
class _Handle:
    """What ``open_device`` returns; pyusb passes it back on every call."""

    open: bool = True


# -- a small synthetic world ---------------------------------------------------------------------


class SyntheticDavisSource:
    """A cheap :class:`DavisActivitySource` for tests and demos without the renderer.

    A bright vertical bar sweeps across the sensor (one sweep per second): its leading edge
    fires ON events, its trailing edge OFF events, plus uniform background noise. APS exposures
    come every ``frame_interval_us`` (image: the bar on a dark gradient), IMU samples at
    ``imu_rate_hz`` (gravity along −Y plus noise), and the sync pulses of the D415 master
    (``pulse_hz``, 50 µs active-high, realsense-d415.md §5) as RISING/FALLING edges. With a
    scenario, pulse times are the master D415's frame instants mapped through the D415 and
    DAVIS clocks (with their jitter); without, a seeded phase.

    Args:
        seed: Seed of every random draw.
        seconds: Session length; the world is quiet afterwards (``None`` = endless).
        scenario: Optional simulated world whose clocks time the sync pulses.
        event_rate_hz: Mean DVS event rate.
    """

    def __init__(
        self,
        *,
        seed: int = 0,
        seconds: float | None = None,
        scenario: Scenario | None = None,
        event_rate_hz: float = 200_000.0,
    ) -> None:
        self._rng = np.random.default_rng([seed, 0xDA715])
        self._end_ns = None if seconds is None else round(seconds * 1e9)
        self.event_rate_hz = float(event_rate_hz)
        self.exposure_us = 4000
        self.frame_interval_us = 40_000
        # The first exposure leaves room for the global-shutter reset read (≈ 18 ms, §9.3).
        self.exposure_offset_us = 18_000
        self.imu_rate_hz = 1000.0
        self.pulse_hz = 30.0
        self.pulse_width_us = 50
        self._session_at_reset_ns = 0
        self._davis_clock: DeviceClock | None = None
        self._master_clock: DeviceClock | None = None
        if scenario is not None:
            self._davis_clock = scenario.clocks["davis"]
            master = scenario.rig.d415[0]
            self._master_clock = scenario.clocks[master.name]
            self.pulse_hz = float(master.rate_hz)
        self._phase_ns = int(self._rng.integers(0, round(1e9 / self.pulse_hz)))

    def reset(self, *, session_ns: int) -> None:
        """Device time 0 is now session time ``session_ns``."""
        self._session_at_reset_ns = int(session_ns)

    def session_ns(self, t_us: npt.ArrayLike) -> npt.NDArray[np.int64]:
        """Session times (ns) of device times (µs since the last reset)."""
        device_us = np.asarray(t_us, np.int64)
        if self._davis_clock is None:
            out: npt.NDArray[np.int64] = self._session_at_reset_ns + device_us * 1000
            return out
        return (
            self._session_at_reset_ns
            + self._davis_clock.session_ns(device_us, unit_ns=1000)
            - self._davis_clock.session_ns(np.zeros_like(device_us), unit_ns=1000)
        )

    def _device_us(self, session_ns: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
        if self._davis_clock is None:
            out: npt.NDArray[np.int64] = (session_ns - self._session_at_reset_ns) // 1000
            return out
        zero = self._davis_clock.device_ticks(np.array([self._session_at_reset_ns]), jitter=False)
        ticks: npt.NDArray[np.int64] = self._davis_clock.device_ticks(session_ns) - zero[0]
        return ticks

    def _pulse_session_ns(self, s0: int, s1: int) -> npt.NDArray[np.int64]:
        """Session instants of master frame pulses in ``[s0, s1)`` (rising edges)."""
        period = 1e9 / self.pulse_hz
        if self._master_clock is None:
            k0 = math.ceil((s0 - self._phase_ns) / period)
            k1 = math.ceil((s1 - self._phase_ns) / period)
            return np.round(self._phase_ns + np.arange(k0, k1) * period).astype(np.int64)
        # Master frames are at whole periods of the master's own clock.
        d0, d1 = self._master_clock.device_ns(np.array([s0, s1], np.int64)).tolist()
        k = np.arange(math.ceil(d0 / period) - 1, math.ceil(d1 / period) + 1)
        t = self._master_clock.session_ns(np.round(k * period).astype(np.int64), unit_ns=1)
        out: npt.NDArray[np.int64] = t[(t >= s0) & (t < s1)]
        return out

    def _bar_x(self, session_ns: npt.NDArray[np.int64]) -> npt.NDArray[np.float64]:
        phase = (session_ns % 1_000_000_000).astype(np.float64)
        out: npt.NDArray[np.float64] = phase * 280e-9 - 20.0
        return out

    def activity(self, t0_us: int, t1_us: int) -> DavisActivity:
        """The activity in ``[t0_us, t1_us)`` device µs."""
        s0, s1 = (int(v) for v in self.session_ns(np.array([t0_us, t1_us], np.int64)))
        if self._end_ns is not None:
            s1 = min(s1, self._end_ns)
        if s1 <= s0:
            return DavisActivity(t0_us=t0_us, t1_us=t1_us, events=empty_events())
        t_end = t0_us + (s1 - s0) // 1000
        span = t_end - t0_us
        rng = self._rng
        n = int(rng.poisson(self.event_rate_hz * span * 1e-6))
        t = np.sort(rng.integers(t0_us, t_end, n))
        bar = self._bar_x(self.session_ns(t))
        edge = rng.random(n) < 0.5  # leading (ON) or trailing (OFF) edge of a 20 px bar
        x = np.rint(np.where(edge, bar + 20.0, bar) + rng.normal(0.0, 0.7, n))
        noise = rng.random(n) < 0.05
        x = np.where(noise, rng.integers(0, 240, n), x)
        keep = (x >= 0) & (x < 240)
        y = rng.integers(0, 180, n)
        p = np.where(noise, rng.integers(0, 2, n), edge)
        events = make_events(t[keep], x[keep], y[keep], p[keep])

        exposures = []
        fi = max(1, self.frame_interval_us)
        off = self.exposure_offset_us + self.exposure_us  # end of exposure k is off + k·fi
        for k in range(max(0, math.ceil((t0_us - off) / fi)), (t_end - off) // fi + 1):
            start = self.exposure_offset_us + k * fi
            end = start + self.exposure_us
            if t0_us <= end < t_end:
                exposures.append(ApsExposure(start, end, self._frame_image(start)))

        period_us = 1e6 / self.imu_rate_hz
        ks = np.arange(math.ceil(t0_us / period_us), math.ceil(t_end / period_us))
        imu = np.zeros(ks.size, IMU_DTYPE)
        imu["t"] = np.round(ks * period_us).astype(np.int64)
        imu = imu[(imu["t"] >= t0_us) & (imu["t"] < t_end)]
        imu["accel_g"] = np.array([0.0, -1.0, 0.0]) + rng.normal(0.0, 0.01, (imu.size, 3))
        imu["gyro_dps"] = rng.normal(0.0, 0.2, (imu.size, 3))
        imu["temp_c"] = 30.0 + rng.normal(0.0, 0.05, imu.size)

        # Pulses that start up to one width before the window still end inside it.
        margin_ns = self.pulse_width_us * 1000
        rises = self._device_us(self._pulse_session_ns(s0 - margin_ns, s1))
        edges_t = np.concatenate([rises, rises + self.pulse_width_us])
        kinds = np.concatenate(
            [np.full(rises.size, ExtInputEdge.RISING), np.full(rises.size, ExtInputEdge.FALLING)]
        )
        order = np.argsort(edges_t, kind="stable")
        ext = np.zeros(order.size, EXT_INPUT_DTYPE)
        ext["t"], ext["edge"] = edges_t[order], kinds[order]
        ext = ext[(ext["t"] >= t0_us) & (ext["t"] < t_end)]
        return DavisActivity(
            t0_us=t0_us,
            t1_us=t1_us,
            events=events,
            exposures=tuple(exposures),
            imu=imu,
            ext_input=ext,
        )

    def _frame_image(self, start_us: int) -> npt.NDArray[np.float64]:
        xs = np.arange(240, dtype=np.float64)
        image = np.tile(60.0 + 0.8 * xs, (180, 1)) + np.linspace(0.0, 40.0, 180)[:, None]
        bar = float(self._bar_x(self.session_ns(np.array([start_us], np.int64)))[0])
        image[:, (xs >= bar) & (xs < bar + 20.0)] = 900.0
        noisy: npt.NDArray[np.float64] = np.clip(
            image + self._rng.normal(0.0, 3.0, image.shape), 0.0, 1023.0
        )
        return noisy


# -- the device ----------------------------------------------------------------------------------


class Davis240CBackend(usb.backend.IBackend):  # type: ignore[misc]
    """A pyusb backend serving one mock DAVIS240C (see the module doc).

    Args:
        source: What the sensor sees (device µs windows).
        serial: The 8-character serial string (string descriptor 3).
        faults: Faults to inject.
        fault: Faults by name (what ``mocaprig doctor --mock --fault davis:NAME`` passes):
            ``"unplug"`` (gone 20 ms into streaming) and ``"usb-bandwidth"`` (a 200 kB/s link:
            DVS events dropped on the device); combined with ``faults``.
        pacing: ``"asap"`` or ``"realtime"``.
        chunk_us: Device µs simulated per step (≈ the 1 ms early-packet delay, note §1.3).
        latency_us: The encoder's hold-back (:class:`DavisWordEncoder`).
        bus: USB bus number.
        address: USB device address.
        port_number: Port on the hub.
        seed: Seed of the APS reset-level noise.
        buffer_bytes: Bytes the device, FX2 and host buffers hold before the output counts as
            stalled (only reachable with realtime pacing and a host that stops reading).
        fifo_bytes: Output FIFO depth between the logic and the host while the host does not
            read (:meth:`stall_host`). The note gives no figure; the default, 4096 bytes, is
            the FX2's whole endpoint buffer memory (CY7C68013A: 4 KiB for EP2/4/6/8), the most
            EP2 can hold; the logic's own FIFO is not counted (unknown).
        read_only: Read-only register values for this instance (module doc).
        power_on: Power-on values of writable registers for this instance.
        product_id: USB PID (0x841B FX2; 0x841A an FX3 board).
    """

    def __init__(
        self,
        source: DavisActivitySource,
        *,
        serial: str = "00000042",
        faults: DavisFaults | None = None,
        pacing: Pacing = "asap",
        chunk_us: int = 1000,
        latency_us: int = 50_000,
        bus: int = 1,
        address: int = 7,
        port_number: int = 2,
        seed: int = 0,
        buffer_bytes: int = 4 << 20,
        fifo_bytes: int = 4096,
        read_only: Mapping[tuple[int, int], int] | None = None,
        power_on: Mapping[tuple[int, int], int] | None = None,
        product_id: int = DAVIS240C_PID,
    ) -> None:
        super().__init__()
        if fifo_bytes < 2:
            msg = f"fifo_bytes must be >= 2 (one word), got {fifo_bytes}"
            raise ValidationError(msg)
        self._fifo_bytes = int(fifo_bytes)
        self._host_reading = True
        if len(serial) != 8 or not serial.isascii():
            msg = f"serial must be 8 ASCII characters (libcaer skips longer ones), got {serial!r}"
            raise ValidationError(msg)
        if pacing not in ("asap", "realtime"):
            msg = f"pacing must be 'asap' or 'realtime', got {pacing!r}"
            raise ValidationError(msg)
        if chunk_us <= 0:
            msg = f"chunk_us must be > 0, got {chunk_us}"
            raise ValidationError(msg)
        self.serial = serial
        self.faults = faults or DavisFaults()
        self.pacing: Pacing = pacing
        self._chunk_us = int(chunk_us)
        self._buffer_bytes = int(buffer_bytes)
        self._source = source
        self._strings = {
            _STR_MANUFACTURER: "iniVation",
            _STR_PRODUCT: "DAVIS FX2",
            _STR_SERIAL: serial,
        }
        self._device = _DeviceDescriptor(
            bLength=18,
            bDescriptorType=1,
            bcdUSB=0x0200,
            bDeviceClass=0,
            bDeviceSubClass=0,
            bDeviceProtocol=0,
            bMaxPacketSize0=_EP0_MAX_PACKET,
            idVendor=DAVIS_VID,
            idProduct=product_id,
            bcdDevice=0x0004,
            iManufacturer=_STR_MANUFACTURER,
            iProduct=_STR_PRODUCT,
            iSerialNumber=_STR_SERIAL,
            bNumConfigurations=1,
            bus=bus,
            address=address,
            port_number=port_number,
            port_numbers=(port_number,),
            speed=3,  # usb.util.SPEED_HIGH
        )
        self._config = _ConfigurationDescriptor()
        self._interface = _InterfaceDescriptor()
        self._endpoint = _EndpointDescriptor()
        self._configuration = 1
        self._claimed: set[int] = set()
        self.registers = RegisterFile(
            on_timestamp_reset=self._timestamp_reset, read_only=read_only, power_on=power_on
        )
        self._encoder = DavisWordEncoder(
            self._encoder_config(),
            latency_us=latency_us,
            wrap_race=self.faults.wrap_race,
            seed=seed,
        )
        self._out = bytearray()
        self._now_us = 0  # device µs since the last timestamp reset
        self.uptime_us = 0
        """Device µs the timestamp counter has run since power-on."""
        self._session_at_reset_ns = 0
        self._unplugged = False
        self._odd_pending = False
        self._odd_done = False
        self._short_packet = False
        self._carry = 0  # 1 while a word is split across transfers (odd-packet fault)
        self._ts_reset_fault_done = False
        self._anchor_wall: float | None = None
        self._lag_warned = False
        self._lock = threading.RLock()
        self._config_version = -1
        self._held = False
        self._source.reset(session_ns=0)

    # -- test harness ------------------------------------------------------------------------------

    def hold(self) -> None:
        """Freeze device time (asap pacing): reads time out until :meth:`release`.

        For deterministic simulated sessions: hold, start and configure the camera through the
        driver (its timestamp reset then happens at device time 0 = the session instant of the
        last reset), release. Register writes still work while held.
        """
        with self._lock:
            self._held = True

    def release(self) -> None:
        """Let device time run again after :meth:`hold`."""
        with self._lock:
            self._held = False

    def stall_host(self, us: int, *, step_us: int = 100) -> None:
        """The host reads nothing for ``us`` µs: the device runs on (asap pacing).

        Device time advances in ``step_us`` steps; its output goes into the ``fifo_bytes``
        FIFO and, once that is full, DVS and ext-input words are dropped (counted in the MUX
        statistics) while APS / IMU words and wraps wait, as on the device (note §7.1). The
        host sees no gap in the stream afterwards, only fewer events.
        """
        if us < 0 or step_us <= 0:
            msg = f"stall_host needs us >= 0 and step_us > 0, got {us}, {step_us}"
            raise ValidationError(msg)
        with self._lock:
            self._host_reading = False
            try:
                left = int(us)
                while left > 0:
                    dt = min(int(step_us), left)
                    self._step(dt)
                    left -= dt
            finally:
                self._host_reading = True

    # -- device model ------------------------------------------------------------------------------

    def _encoder_config(self) -> EncoderConfig:
        r = self.registers
        m = DavisModule
        roi = (
            min(r.get(m.APS, APS.START_COLUMN_0), 239),
            min(r.get(m.APS, APS.START_ROW_0), 179),
            min(r.get(m.APS, APS.END_COLUMN_0), 239),
            min(r.get(m.APS, APS.END_ROW_0), 179),
        )
        if roi[0] > roi[2] or roi[1] > roi[3]:
            roi = (0, 0, 239, 179)
        dvs_orientation = r.get(m.DVS, DVS.ORIENTATION_INFO)
        aps_orientation = r.get(m.APS, APS.ORIENTATION_INFO)
        return EncoderConfig(
            roi=roi,
            accel_full_scale=r.get(m.IMU, IMU.ACCEL_FULL_SCALE) & 3,
            gyro_full_scale=r.get(m.IMU, IMU.GYRO_FULL_SCALE) & 3,
            run_accelerometer=r.flag(m.IMU, IMU.RUN_ACCELEROMETER),
            run_gyroscope=r.flag(m.IMU, IMU.RUN_GYROSCOPE),
            run_temperature=r.flag(m.IMU, IMU.RUN_TEMPERATURE),
            detect_rising_edges=r.flag(m.EXTINPUT, EXTINPUT.DETECT_RISING_EDGES),
            detect_falling_edges=r.flag(m.EXTINPUT, EXTINPUT.DETECT_FALLING_EDGES),
            detect_pulses=r.flag(m.EXTINPUT, EXTINPUT.DETECT_PULSES),
            pulse_active_high=r.flag(m.EXTINPUT, EXTINPUT.DETECT_PULSE_POLARITY),
            # DETECT_PULSE_LENGTH is in logic-clock cycles (90 MHz, note §2.1).
            pulse_min_length_us=math.ceil(r.get(m.EXTINPUT, EXTINPUT.DETECT_PULSE_LENGTH) / 90),
            drop_dvs_on_transfer_stall=r.flag(m.MUX, MUX.DROP_DVS_ON_TRANSFER_STALL),
            drop_extinput_on_transfer_stall=r.flag(m.MUX, MUX.DROP_EXTINPUT_ON_TRANSFER_STALL),
            bandwidth_bytes_per_s=self.faults.bandwidth_bytes_per_s,
            dvs_invert_xy=bool(dvs_orientation & 4),
            aps_invert_xy=bool(aps_orientation & 4),
            aps_flip_x=bool(aps_orientation & 2),
            aps_flip_y=bool(aps_orientation & 1),
        )

    def _configure_source(self) -> None:
        r, m = self.registers, DavisModule
        # Registers count logic-clock cycles (30 MHz on the DAVIS240C).
        exposure_us = max(1, r.get(m.APS, APS.EXPOSURE) // 30)
        interval_us = max(exposure_us, r.get(m.APS, APS.FRAME_INTERVAL) // 30)
        # Rate = 1 kHz / (1 + SAMPLE_RATE_DIVIDER) with the default DLPF (note §3.4).
        imu_rate_hz = 1000.0 / (1 + r.get(m.IMU, IMU.SAMPLE_RATE_DIVIDER))
        if isinstance(self._source, SyntheticDavisSource):
            self._source.exposure_us = exposure_us
            self._source.frame_interval_us = interval_us
            self._source.imu_rate_hz = imu_rate_hz
            return
        configure = getattr(self._source, "configure", None)
        if callable(configure):
            # The world simulator re-plans its exposures and IMU grid from these settings, and
            # skips the DVS model (most of its cost) while the DVS module is off.
            dvs_on = r.flag(m.MUX, MUX.RUN_CHIP) and r.flag(m.DVS, DVS.RUN)
            configure(
                exposure_us=exposure_us,
                frame_interval_us=interval_us,
                imu_rate_hz=imu_rate_hz,
                dvs_enabled=dvs_on,
            )

    def _gate(self, act: DavisActivity) -> DavisActivity:
        """Keep what the running modules produce (note §3, §5.3)."""
        r, m = self.registers, DavisModule
        chip = r.flag(m.MUX, MUX.RUN_CHIP)
        dvs_on = chip and r.flag(m.DVS, DVS.RUN)
        aps_on = chip and r.flag(m.APS, APS.RUN)
        imu_on = any(
            r.flag(m.IMU, p)
            for p in (IMU.RUN_ACCELEROMETER, IMU.RUN_GYROSCOPE, IMU.RUN_TEMPERATURE)
        )
        ext_on = r.flag(m.EXTINPUT, EXTINPUT.RUN_DETECTOR)
        if dvs_on and aps_on and imu_on and ext_on:
            return act
        return DavisActivity(
            t0_us=act.t0_us,
            t1_us=act.t1_us,
            events=act.events if dvs_on else empty_events(),
            exposures=act.exposures if aps_on else (),
            imu=act.imu if imu_on else np.empty(0, IMU_DTYPE),
            ext_input=act.ext_input if ext_on else np.empty(0, EXT_INPUT_DTYPE),
        )

    def _counter_runs(self) -> bool:
        return self.registers.flag(DavisModule.MUX, MUX.TIMESTAMP_RUN)

    def _producing(self) -> bool:
        r, m = self.registers, DavisModule
        return self._counter_runs() and r.flag(m.MUX, MUX.RUN)

    def _step(self, dt_us: int) -> None:
        """Run the device for ``dt_us`` µs of its own time."""
        if self._unplugged or self._held or not self._counter_runs():
            return
        f = self.faults
        if f.unplug_at_us is not None and self.uptime_us + dt_us > f.unplug_at_us:
            dt_us = max(0, f.unplug_at_us - self.uptime_us)
            self._unplugged = True
            _log.info("DAVIS mock %s: unplugged at uptime %d µs", self.serial, f.unplug_at_us)
        if dt_us:
            self._run(dt_us)
        if (
            f.timestamp_reset_at_us is not None
            and not self._ts_reset_fault_done
            and self.uptime_us >= f.timestamp_reset_at_us
        ):
            self._ts_reset_fault_done = True
            self._timestamp_reset()
        if f.odd_packet_at_us is not None and not self._odd_done:
            self._odd_pending = self.uptime_us >= f.odd_packet_at_us

    def _run(self, dt_us: int) -> None:
        r, m = self.registers, DavisModule
        t0, t1 = self._now_us, self._now_us + dt_us
        if self._config_version != r.version:
            self._config_version = r.version
            self._configure_source()
            self._encoder.configure(self._encoder_config())
        activity = self._source.activity(t0, t1)
        if r.flag(m.MUX, MUX.RUN):
            # The output is blocked by a stall fault, by USB RUN = 0, or when the host does not
            # read and the buffers between the logic and the host are full (realtime pacing).
            blocked = (
                self.faults.stalled(self.uptime_us)
                or not r.flag(m.USB, USB.RUN)
                or len(self._out) >= self._buffer_bytes
                or (not self._host_reading and len(self._out) >= self._fifo_bytes)
            )
            self._out += self._encoder.encode(self._gate(activity), output_blocked=blocked)
            if self._encoder.forced_resets:
                self._forced_reset_seen()
        else:
            # MUX off: the producers' FIFOs are drained, nothing reaches USB (note §3.1).
            self._encoder.advance_idle(t1)
        self._now_us = t1
        self.uptime_us += dt_us
        r.set_statistic(m.MUX, MUX.STATISTICS_DVS_DROPPED, self._encoder.dvs_dropped)
        r.set_statistic(m.MUX, MUX.STATISTICS_EXTINPUT_DROPPED, self._encoder.extinput_dropped)

    def _forced_reset_seen(self) -> None:
        """The encoder forced a TS reset (pending-wrap overflow); it keeps its own time base."""
        _log.warning("DAVIS mock %s: forced timestamp reset after a long stall", self.serial)
        self._encoder.forced_resets = 0

    def _timestamp_reset(self) -> None:
        """MUX TIMESTAMP_RESET pulse or a device-side reset: TS-reset word, time back to 0."""
        words = self._encoder.reset_timestamps()
        if self.registers.flag(DavisModule.MUX, MUX.RUN):
            self._out += words
        # The source knows its clock's drift when it offers ``session_ns`` (DavisSimulator).
        to_session = getattr(self._source, "session_ns", None)
        if callable(to_session):
            self._session_at_reset_ns = int(np.asarray(to_session(self._now_us)).reshape(-1)[0])
        else:
            self._session_at_reset_ns += self._now_us * 1000
        self._now_us = 0
        self._source.reset(session_ns=self._session_at_reset_ns)
        _log.debug("DAVIS mock %s: timestamp reset", self.serial)

    def _sync_realtime(self) -> None:
        """Realtime pacing: run device time up to the wall clock."""
        if self.pacing != "realtime":
            return
        now = time.monotonic()
        if self._anchor_wall is None or not self._counter_runs():
            self._anchor_wall = now
            return
        due = int((now - self._anchor_wall) * 1e6)
        steps = due // self._chunk_us
        done = 0
        while done < steps:
            self._step(self._chunk_us)
            done += 1
            if time.monotonic() - now > _CATCH_UP_WALL_S:
                break
        self._anchor_wall += done * self._chunk_us * 1e-6
        lag_us = due - done * self._chunk_us
        if lag_us > _LAG_WARN_US and not self._lag_warned:
            self._lag_warned = True
            _log.warning(
                "DAVIS mock %s: this machine simulates the camera slower than real time; device "
                "time lags the wall clock by %.1f s (realtime pacing)",
                self.serial,
                lag_us / 1e6,
            )

    # -- IBackend: enumeration and descriptors -----------------------------------------------------

    def enumerate_devices(self) -> list[str]:
        """One device while plugged in."""
        return [] if self._unplugged else [self.serial]

    def get_device_descriptor(self, dev: object) -> _DeviceDescriptor:
        """The DAVIS240C device descriptor (note §1.1, §12)."""
        return self._device

    def get_configuration_descriptor(self, dev: object, config: int) -> _ConfigurationDescriptor:
        """The only configuration (index 0, bConfigurationValue 1)."""
        if config != 0:
            raise IndexError(config)
        return self._config

    def get_interface_descriptor(
        self, dev: object, intf: int, alt: int, config: int
    ) -> _InterfaceDescriptor:
        """Interface 0, alternate setting 0; pyusb probes others until IndexError."""
        if (intf, alt, config) != (0, 0, 0):
            raise IndexError((intf, alt, config))
        return self._interface

    def get_endpoint_descriptor(
        self, dev: object, ep: int, intf: int, alt: int, config: int
    ) -> _EndpointDescriptor:
        """The bulk IN endpoint 0x82 (the FX2 board has no debug endpoint 0x81, note §1.2)."""
        if (ep, intf, alt, config) != (0, 0, 0, 0):
            raise IndexError((ep, intf, alt, config))
        return self._endpoint

    # -- IBackend: handles, configuration, interfaces ----------------------------------------------

    def _alive(self, handle: object | None = None) -> None:
        if self._unplugged:
            raise _no_device()
        if isinstance(handle, _Handle) and not handle.open:
            raise _invalid_param()

    def open_device(self, dev: object) -> _Handle:
        """Open the device."""
        self._alive()
        return _Handle()

    def close_device(self, dev_handle: _Handle) -> None:
        """Close a handle (releases its interfaces)."""
        dev_handle.open = False
        self._claimed.clear()

    def set_configuration(self, dev_handle: _Handle, config_value: int) -> None:
        """Select configuration 1 (or 0 = unconfigured)."""
        self._alive(dev_handle)
        if config_value not in (0, 1):
            raise _not_found()
        self._configuration = config_value

    def get_configuration(self, dev_handle: _Handle) -> int:
        """The active configuration value."""
        self._alive(dev_handle)
        return self._configuration

    def set_interface_altsetting(self, dev_handle: _Handle, intf: int, altsetting: int) -> None:
        """Only interface 0, alternate setting 0 exists."""
        self._alive(dev_handle)
        if (intf, altsetting) != (0, 0):
            raise _not_found()

    def claim_interface(self, dev_handle: _Handle, intf: int) -> None:
        """Claim interface 0."""
        self._alive(dev_handle)
        if intf != 0:
            raise _not_found()
        self._claimed.add(intf)

    def release_interface(self, dev_handle: _Handle, intf: int) -> None:
        """Release an interface."""
        self._claimed.discard(intf)

    def is_kernel_driver_active(self, dev_handle: _Handle, intf: int) -> bool:
        """No kernel driver binds a vendor-class interface."""
        self._alive(dev_handle)
        return False

    def detach_kernel_driver(self, dev_handle: _Handle, intf: int) -> None:
        """Nothing to detach."""
        self._alive(dev_handle)

    def attach_kernel_driver(self, dev_handle: _Handle, intf: int) -> None:
        """Nothing to attach."""
        self._alive(dev_handle)

    def reset_device(self, dev_handle: _Handle) -> None:
        """A USB port reset: unsent data is lost, the logic's registers stay."""
        with self._lock:
            self._alive(dev_handle)
            self._out.clear()
            self._carry = 0

    def clear_halt(self, dev_handle: _Handle, ep: int) -> None:
        """Clear a halt; on EP 0x82 drop any partially sent data (note §12.9)."""
        with self._lock:
            self._alive(dev_handle)
            if ep == _DATA_EP:
                self._out.clear()
                self._carry = 0

    # -- IBackend: transfers -----------------------------------------------------------------------

    def bulk_write(self, dev_handle: _Handle, ep: int, intf: int, data: Any, timeout: int) -> int:
        """The DAVIS has no bulk OUT endpoint."""
        self._alive(dev_handle)
        raise _pipe()

    def bulk_read(self, dev_handle: _Handle, ep: int, intf: int, buff: Any, timeout: int) -> int:
        """Fill ``buff`` from EP 0x82 and return the byte count (see the module doc).

        Thread-safe against ``ctrl_transfer`` (a driver reads on its own thread); realtime
        pacing waits without holding the device lock.
        """
        with self._lock:
            self._alive(dev_handle)
            if ep != _DATA_EP:
                raise _pipe()
            if self._configuration != 1 or 0 not in self._claimed:
                raise _io_error()
            if self.pacing == "asap":
                self._fill_asap(timeout, len(buff))
                return self._take(buff)
        deadline = time.monotonic() + (timeout / 1000.0 if timeout else 10.0)
        while True:
            with self._lock:
                self._sync_realtime()
                self._alive()
                if self._out and not self.faults.stalled(self.uptime_us):
                    return self._take(buff)
            if time.monotonic() >= deadline:
                raise _timeout()
            time.sleep(min(0.001, max(0.0, deadline - time.monotonic())))

    def _take(self, buff: Any) -> int:
        """Move the next transfer's bytes from the device FIFO into ``buff``."""
        n = min(len(buff), len(self._out))
        if self._odd_pending and not self._carry and n >= 2:
            # The fault: this transfer ends in the middle of a word; the next one starts with
            # the word's other byte and is odd too, so the stream realigns.
            n -= 1 - n % 2
            self._odd_pending = False
            self._odd_done = True
            self._carry = 1
        elif n % 2 != self._carry:
            n -= 1  # otherwise transfers carry whole 16-bit words (note §1.2)
        elif self._carry:
            self._carry = 0
        if n <= 0:
            raise _timeout()
        _fill(buff, self._out[:n])
        del self._out[:n]
        return n

    def _fill_asap(self, timeout_ms: int, want: int) -> None:
        """Run device time until the transfer would complete (asap pacing).

        A transfer completes when the host's buffer is full or with a short packet, which the
        device sends once data has waited EARLY_PACKET_DELAY (≈ one step) without filling a
        512-byte packet (note §1.3).
        """
        budget_us = timeout_ms * 1000 if timeout_ms else _MAX_INFINITE_WAIT_US
        waited = 0
        while True:
            self._alive()
            stalled = self.faults.stalled(self.uptime_us)
            if self._out and not stalled and (len(self._out) >= want or self._short_packet):
                return
            if self._held or not self._counter_runs() or waited >= budget_us:
                if self._out and not stalled:
                    return
                raise _timeout()
            before = len(self._out)
            self._step(self._chunk_us)
            waited += self._chunk_us
            self._short_packet = len(self._out) - before < _BULK_MAX_PACKET

    def intr_read(self, dev_handle: _Handle, ep: int, intf: int, buff: Any, timeout: int) -> int:
        """No interrupt endpoint on the FX2 board (EP 0x81 is FX3-only, note §1.2)."""
        self._alive(dev_handle)
        raise _pipe()

    def ctrl_transfer(
        self,
        dev_handle: _Handle,
        bmRequestType: int,
        bRequest: int,
        wValue: int,
        wIndex: int,
        data: Any,
        timeout: int,
    ) -> int:
        """Standard GET_DESCRIPTOR/GET_CONFIGURATION and the vendor requests of note §2."""
        with self._lock:
            return self._control(dev_handle, bmRequestType, bRequest, wValue, wIndex, data)

    def _control(
        self,
        dev_handle: _Handle,
        bmRequestType: int,
        bRequest: int,
        wValue: int,
        wIndex: int,
        data: Any,
    ) -> int:
        self._alive(dev_handle)
        self._sync_realtime()
        device_to_host = bool(bmRequestType & 0x80)
        kind = (bmRequestType >> 5) & 3
        if kind == 0:
            return self._standard_request(device_to_host, bRequest, wValue, wIndex, data)
        if kind == 2 and bRequest == _VR_FPGA_CONFIG:
            # The firmware takes only 4-byte data stages and stalls EP0 otherwise (§2).
            if len(data) != 4:
                raise _pipe()
            if device_to_host:
                _fill(data, self.registers.read(wValue, wIndex).to_bytes(4, "big"))
            else:
                self._write(wValue, wIndex, int.from_bytes(bytes(data), "big"))
            return 4
        if kind == 2 and bRequest == _VR_FPGA_CONFIG_MULTIPLE and not device_to_host:
            raw = bytes(data)
            if wValue == 0 or len(raw) != 6 * wValue:
                raise _pipe()
            for i in range(wValue):
                entry = raw[6 * i : 6 * i + 6]
                self._write(entry[0], entry[1], int.from_bytes(entry[2:], "big"))
            return len(raw)
        raise _pipe()

    def _write(self, module: int, param: int, value: int) -> None:
        was_running = self._counter_runs()
        self.registers.write(module, param, value)
        if self.pacing == "realtime" and was_running != self._counter_runs():
            self._anchor_wall = time.monotonic()

    def _standard_request(
        self, device_to_host: bool, request: int, value: int, index: int, data: Any
    ) -> int:
        if device_to_host and request == 6:  # GET_DESCRIPTOR
            return _fill(data, self._descriptor_bytes(value >> 8, value & 0xFF, index))
        if device_to_host and request == 8:  # GET_CONFIGURATION
            return _fill(data, bytes([self._configuration]))
        if device_to_host and request == 0:  # GET_STATUS
            return _fill(data, bytes(2))
        if not device_to_host and request == 9:  # SET_CONFIGURATION
            self.set_configuration(_Handle(), value)
            return 0
        raise _pipe()

    def _descriptor_bytes(self, dtype: int, index: int, langid: int) -> bytes:
        if dtype == 1:
            return self._device.to_bytes()
        if dtype == 2 and index == 0:
            return self._config.to_bytes() + self._interface.to_bytes() + self._endpoint.to_bytes()
        if dtype == 3:
            if index == 0:
                return bytes([4, 3]) + _LANGID_EN_US.to_bytes(2, "little")
            if index in self._strings:
                text = self._strings[index].encode("utf-16-le")
                return bytes([2 + len(text), 3]) + text
        raise _pipe()


# -- factory -------------------------------------------------------------------------------------


def _simulator_source(world: Scenario) -> DavisActivitySource:
    """Engineer C's renderer-backed ``DavisSimulator`` of ``world``."""
    # Imported by name so that the device model does not depend on the renderer's imports.
    sim = importlib.import_module("mocaprig.drivers_mock.davis240c_sim")
    source: DavisActivitySource = sim.DavisSimulator(world)
    return source


#: Faults by name: the :class:`DavisFaults` fields each one sets.
NAMED_FAULTS: dict[str, dict[str, Any]] = {
    # Early: the simulated world renders slower than real time, so a check that streams for a
    # second of wall time may see only tens of milliseconds of device time.
    "unplug": {"unplug_at_us": 20_000},
    "usb-bandwidth": {"bandwidth_bytes_per_s": 2.0e5},
}


def named_faults(names: Sequence[str], *, base: DavisFaults | None = None) -> DavisFaults:
    """:class:`DavisFaults` with the named faults (:data:`NAMED_FAULTS`) set on ``base``.

    Raises:
        ValidationError: an unknown name.
    """
    fields: dict[str, Any] = {}
    for name in names:
        if name not in NAMED_FAULTS:
            msg = f"unknown DAVIS mock fault {name!r}; choose from {sorted(NAMED_FAULTS)}"
            raise ValidationError(msg)
        fields.update(NAMED_FAULTS[name])
    return dataclasses.replace(base or DavisFaults(), **fields)


def mock_backend(
    *,
    source: DavisActivitySource | None = None,
    scenario: str | Scenario = "default",
    seed: int = 0,
    seconds: float | None = None,
    serial: str | None = None,
    faults: DavisFaults | None = None,
    fault: Sequence[str] | str | None = None,
    pacing: Pacing = "asap",
    **kwargs: Any,
) -> Davis240CBackend:
    """A mock DAVIS240C pyusb backend (entry point ``mocaprig.mocks: davis240c``).

    Args:
        source: What the sensor sees; default: ``DavisSimulator`` (davis240c_sim.py) of
            ``scenario`` when that module is installed, else :class:`SyntheticDavisSource`.
        scenario: Scenario name, built with ``seed`` and ``seconds`` (30 s when ``None``) for
            the simulator, or a built :class:`~mocaprig.drivers_mock.scenario.Scenario`.
        seed: Seed of the world and of the device noise.
        seconds: Session length (the world is quiet afterwards; ``None`` = endless).
        serial: 8-character serial; default the rig's DAVIS serial, or one derived from
            ``seed`` without a world.
        faults: Faults to inject.
        pacing: ``"asap"`` (deterministic) or ``"realtime"`` (follows the wall clock).
        **kwargs: Passed to :class:`Davis240CBackend` (``chunk_us``, ``latency_us``, ``bus``,
            ``address``, ``port_number``, ``fifo_bytes``, ``read_only``, ``power_on``,
            ``product_id``).
    """
    if fault:
        faults = named_faults([fault] if isinstance(fault, str) else list(fault), base=faults)
    world: Scenario | None = None if isinstance(scenario, str) else scenario
    if (
        source is None
        and importlib.util.find_spec("mocaprig.drivers_mock.davis240c_sim") is not None
    ):
        if world is None:
            from mocaprig.drivers_mock.scenario import build_scenario

            length = _DEFAULT_SECONDS if seconds is None else seconds
            world = build_scenario(str(scenario), seed=seed, seconds=length)
        source = _simulator_source(world)
    if source is None:
        source = SyntheticDavisSource(seed=seed, seconds=seconds, scenario=world)
    if serial is None:
        # The rig's DAVIS serial when there is a world, else one derived from the seed.
        serial = world.rig.davis.serial if world is not None else f"{(42 + seed) % 10**8:08d}"
    return Davis240CBackend(
        source, serial=serial, faults=faults, pacing=pacing, seed=seed, **kwargs
    )
