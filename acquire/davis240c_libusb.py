"""The DAVIS240C's USB link as pyusb sees it: ids, endpoint, vendor requests and libusb errors.

Shared by discovery (:mod:`mocaprig.acquire.davis240c_discovery`), the device
(:mod:`mocaprig.acquire.davis240c`) and the reader threads
(:mod:`mocaprig.acquire.davis240c_reader`). The protocol is in ``docs/davis240c-usb.md``: vendor
request 0xBF reads/writes one 32-bit register (big-endian), 0xC2 writes several at once; data
arrive on bulk EP 0x82.

Bulk data: pyusb's libusb1 backend offers only synchronous transfers, so
:class:`AsyncBulkReader` reaches libusb's asynchronous API through ctypes, on the very context
and device handle pyusb opened, to keep several bulk transfers queued on EP 0x82 as libcaer does
(8 × 8 KiB, note §1.3); :func:`async_handle` says whether a device offers that.

A libusb failure reaches Python as ``usb.core.USBError`` with ``backend_error_code`` (the libusb
code) and ``errno``; :func:`device_error_class` says which
:class:`~mocaprig.errors.DeviceError` subclass it becomes, and :func:`device_error` builds it
keeping both codes. pyusb is imported lazily (:func:`usb_module`) to keep ``mocaprig --help`` fast.
"""

from __future__ import annotations

import ctypes
import errno
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final

from mocaprig.errors import (
    DeviceBusyError,
    DeviceDisconnectedError,
    DeviceError,
    DeviceNotFoundError,
    DevicePermissionError,
    DeviceTimeoutError,
)

__all__ = [
    "CTRL_TIMEOUT_MS",
    "DATA_ENDPOINT",
    "LIBUSB_ERROR_ACCESS",
    "LIBUSB_ERROR_BUSY",
    "LIBUSB_ERROR_NOT_FOUND",
    "LIBUSB_ERROR_NO_DEVICE",
    "LIBUSB_ERROR_TIMEOUT",
    "PRODUCT_ID_FX2",
    "PRODUCT_ID_FX3",
    "VENDOR_ID",
    "VR_FPGA_CONFIG",
    "VR_FPGA_CONFIG_MULTIPLE",
    "AsyncBulkReader",
    "LibusbHandle",
    "async_handle",
    "ctrl_read",
    "device_error",
    "device_error_class",
    "is_busy",
    "is_no_device",
    "is_permission",
    "is_timeout",
    "usb_module",
]

VENDOR_ID: Final = 0x152A
PRODUCT_ID_FX2: Final = 0x841B  # DAVIS240A/B/C cameras
PRODUCT_ID_FX3: Final = 0x841A  # FX3 boards (DAVIS240C chip on an FX3 dev kit: same words)
DATA_ENDPOINT: Final = 0x82
VR_FPGA_CONFIG: Final = 0xBF
VR_FPGA_CONFIG_MULTIPLE: Final = 0xC2
CTRL_TIMEOUT_MS: Final = 1000

# libusb error codes (pyusb ``USBError.backend_error_code``).
LIBUSB_ERROR_ACCESS: Final = -3
LIBUSB_ERROR_NO_DEVICE: Final = -4
LIBUSB_ERROR_NOT_FOUND: Final = -5
LIBUSB_ERROR_BUSY: Final = -6
LIBUSB_ERROR_TIMEOUT: Final = -7
LIBUSB_ERROR_INTERRUPTED: Final = -10

_log = logging.getLogger(__name__)


def usb_module() -> Any:
    """The ``usb`` package with ``usb.core`` and ``usb.util`` loaded (imported on first use)."""
    import usb.core  # lazy: keep `mocaprig --help` fast
    import usb.util

    return usb


def _codes(err: BaseException) -> tuple[int | None, int | None]:
    """(errno, libusb code) of a pyusb error; None where the error has none."""
    return getattr(err, "errno", None), getattr(err, "backend_error_code", None)


def is_permission(err: BaseException) -> bool:
    """LIBUSB_ERROR_ACCESS / EACCES: the udev rule is missing."""
    en, code = _codes(err)
    return en == errno.EACCES or code == LIBUSB_ERROR_ACCESS


def is_busy(err: BaseException) -> bool:
    """LIBUSB_ERROR_BUSY / EBUSY: another process claimed the interface."""
    en, code = _codes(err)
    return en == errno.EBUSY or code == LIBUSB_ERROR_BUSY


def is_timeout(err: BaseException) -> bool:
    """``usb.core.USBTimeoutError``, LIBUSB_ERROR_TIMEOUT or ETIMEDOUT."""
    usb = usb_module()
    en, code = _codes(err)
    return (
        isinstance(err, usb.core.USBTimeoutError)
        or en == errno.ETIMEDOUT
        or code == LIBUSB_ERROR_TIMEOUT
    )


def is_no_device(err: BaseException) -> bool:
    """LIBUSB_ERROR_NO_DEVICE / ENODEV: the device is gone (unplugged)."""
    en, code = _codes(err)
    return en == errno.ENODEV or code == LIBUSB_ERROR_NO_DEVICE


def _is_not_found(err: BaseException) -> bool:
    en, code = _codes(err)
    return en == errno.ENOENT or code == LIBUSB_ERROR_NOT_FOUND


def device_error_class(err: BaseException) -> type[DeviceError]:
    """The :class:`~mocaprig.errors.DeviceError` subclass a pyusb error stands for.

    ACCESS -> permission, BUSY -> busy, TIMEOUT -> timeout, NO_DEVICE -> disconnected,
    NOT_FOUND -> not found; anything else is a plain :class:`~mocaprig.errors.DeviceError`.
    """
    if is_permission(err):
        return DevicePermissionError
    if is_busy(err):
        return DeviceBusyError
    if is_timeout(err):
        return DeviceTimeoutError
    if is_no_device(err):
        return DeviceDisconnectedError
    if _is_not_found(err):
        return DeviceNotFoundError
    return DeviceError


def device_error(
    message: str, err: BaseException, cls: type[DeviceError] | None = None
) -> DeviceError:
    """``cls`` (default: :func:`device_error_class` of ``err``) with ``message`` and the codes
    of ``err`` (``backend_errno``, ``backend_code``); raise it ``from err``."""
    return (cls or device_error_class(err)).from_cause(message, err)


def ctrl_read(dev: Any, module: int, param: int) -> int:
    """Read one 32-bit register with vendor request 0xBF (IN); pyusb errors propagate.

    Raises:
        DeviceError: the device returned another length than 4 bytes.
    """
    data = dev.ctrl_transfer(0xC0, VR_FPGA_CONFIG, module, param, 4, CTRL_TIMEOUT_MS)
    if len(data) != 4:
        msg = f"register ({module}, {param}) read returned {len(data)} bytes instead of 4"
        raise DeviceError(msg)
    return int.from_bytes(bytes(data), "big")


# -- asynchronous bulk transfers (libusb-1.0 through ctypes) -----------------------------------

# enum libusb_transfer_status
_COMPLETED, _ERROR, _TIMED_OUT, _CANCELLED, _STALL, _NO_DEVICE, _OVERFLOW = range(7)
_STATUS_NAMES: Final = ("completed", "error", "timed out", "cancelled", "stall", "no device")
_TRANSFER_TYPE_BULK: Final = 2


class _Transfer(ctypes.Structure):
    """``struct libusb_transfer`` (libusb 1.0 ``libusb.h``), without the ISO descriptors."""


_CALLBACK = ctypes.CFUNCTYPE(None, ctypes.POINTER(_Transfer))
_Transfer._fields_ = [
    ("dev_handle", ctypes.c_void_p),
    ("flags", ctypes.c_uint8),
    ("endpoint", ctypes.c_ubyte),
    ("type", ctypes.c_ubyte),
    ("timeout", ctypes.c_uint),
    ("status", ctypes.c_int),
    ("length", ctypes.c_int),
    ("actual_length", ctypes.c_int),
    ("callback", _CALLBACK),
    ("user_data", ctypes.c_void_p),
    ("buffer", ctypes.c_void_p),
    ("num_iso_packets", ctypes.c_int),
]


class _Timeval(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_usec", ctypes.c_long)]


@dataclass(frozen=True, slots=True)
class LibusbHandle:
    """The libusb library, context and device handle behind an opened pyusb device.

    Attributes:
        lib: The libusb-1.0 library (``ctypes.CDLL``, or a stand-in with the same functions).
        ctx: ``libusb_context *`` pyusb's backend created.
        handle: ``libusb_device_handle *`` pyusb opened.
    """

    lib: Any
    ctx: Any
    handle: Any


def async_handle(dev: Any) -> LibusbHandle | None:
    """The libusb pointers of a pyusb device opened by the libusb1 backend, else None.

    A device served by another backend (the mock's ``IBackend``, libusb0, openusb) has no
    libusb handle: the caller then reads synchronously.
    """
    rm: Any = getattr(dev, "_ctx", None)
    backend: Any = getattr(rm, "backend", None)
    if rm is None or backend is None or type(backend).__module__ != "usb.backend.libusb1":
        return None
    name = getattr(getattr(backend, "lib", None), "_name", None)
    if not name:
        return None
    rm.managed_open()
    lib = ctypes.CDLL(name)  # the same loaded library: dlopen returns the same instance
    p_transfer = ctypes.POINTER(_Transfer)
    lib.libusb_alloc_transfer.argtypes = [ctypes.c_int]
    lib.libusb_alloc_transfer.restype = p_transfer
    lib.libusb_free_transfer.argtypes = [p_transfer]
    lib.libusb_free_transfer.restype = None
    lib.libusb_submit_transfer.argtypes = [p_transfer]
    lib.libusb_submit_transfer.restype = ctypes.c_int
    lib.libusb_cancel_transfer.argtypes = [p_transfer]
    lib.libusb_cancel_transfer.restype = ctypes.c_int
    lib.libusb_handle_events_timeout_completed.argtypes = [
        ctypes.c_void_p,
        ctypes.POINTER(_Timeval),
        ctypes.POINTER(ctypes.c_int),
    ]
    lib.libusb_handle_events_timeout_completed.restype = ctypes.c_int
    return LibusbHandle(lib=lib, ctx=backend.ctx, handle=rm.handle.handle)


def _transfer_error(status: int, endpoint: int) -> BaseException:
    usb = usb_module()
    err: BaseException
    if status == _NO_DEVICE:
        err = usb.core.USBError(
            "No such device (it may have been disconnected)", LIBUSB_ERROR_NO_DEVICE, errno.ENODEV
        )
    else:
        name = _STATUS_NAMES[status] if 0 <= status < len(_STATUS_NAMES) else f"status {status}"
        err = usb.core.USBError(f"bulk transfer on EP {endpoint:#04x} ended: {name}", -1, errno.EIO)
    return err


class AsyncBulkReader:
    """``transfers`` bulk IN transfers kept queued on ``endpoint`` (libusb async API).

    Like libcaer's ``usbAllocateTransfers`` / ``usbDataTransferCallback``: every transfer is
    resubmitted as soon as it completes, with no timeout, so the device's FIFO is drained while
    the host handles the previous data. A sequence number is given to each transfer when it is
    submitted (all submissions happen on one thread, in order) and completed data are handed to
    ``on_data(bytes, host_time_ns)`` strictly in that order. A transfer that ends with another
    status than completed (unplugged: NO_DEVICE; macOS reports the others CANCELLED, note §1.3)
    stops the reader: the rest are cancelled and ``on_error`` gets a ``usb.core.USBError``
    carrying the libusb code.

    One thread runs libusb's event loop (``libusb_handle_events_timeout_completed``, 100 ms);
    pyusb's synchronous control transfers on other threads share that loop safely.
    """

    def __init__(
        self,
        usb_handle: LibusbHandle,
        endpoint: int,
        *,
        transfers: int,
        transfer_bytes: int,
        on_data: Callable[[bytes, int], None],
        on_error: Callable[[BaseException], None],
        name: str,
    ) -> None:
        self._h = usb_handle
        self._endpoint = endpoint
        self._n = transfers
        self._size = transfer_bytes
        self._on_data = on_data
        self._on_error = on_error
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._callback = _CALLBACK(self._completed)  # keep alive while transfers exist
        self._buffers = [ctypes.create_string_buffer(transfer_bytes) for _ in range(transfers)]
        self._transfers: list[Any] = []
        self._seq_of = [0] * transfers
        self._next_seq = 0
        self._next_out = 0
        self._ready: dict[int, tuple[bytes, int] | None] = {}
        self._active = 0
        self._cancelled = False
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name=f"davis-{name}-usb", daemon=True)

    def start(self) -> None:
        """Allocate and submit the transfers, then run the event thread.

        Raises:
            usb.core.USBError: a transfer could not be allocated or submitted.
        """
        lib = self._h.lib
        for i in range(self._n):
            t = lib.libusb_alloc_transfer(0)
            if not t:
                self._free()
                raise _transfer_error(_ERROR, self._endpoint)
            tr = t.contents
            tr.dev_handle = self._h.handle
            tr.endpoint = self._endpoint
            tr.type = _TRANSFER_TYPE_BULK
            tr.timeout = 0
            tr.length = self._size
            tr.buffer = ctypes.cast(self._buffers[i], ctypes.c_void_p)
            tr.user_data = i
            tr.callback = self._callback
            self._transfers.append(t)
        failed = False
        with self._lock:
            for i in range(self._n):
                if self._submit(i) < 0:
                    failed = True
                    break
        if failed:
            self._stop.set()
            self._cancelled = True
            self._cancel_all()
            self._drain_events()
            if self._active <= 0:
                self._free()
            raise _transfer_error(_ERROR, self._endpoint)
        self._thread.start()

    def _submit(self, i: int) -> int:
        """Submit transfer ``i`` with the next sequence number (caller holds the lock)."""
        self._seq_of[i] = self._next_seq
        self._next_seq += 1
        rc = int(self._h.lib.libusb_submit_transfer(self._transfers[i]))
        if rc >= 0:
            self._active += 1
        else:
            self._ready[self._seq_of[i]] = None  # keep the order moving
        return rc

    def _completed(self, tp: Any) -> None:
        """libusb callback (on whichever thread handles events)."""
        tr = tp.contents
        i = int(tr.user_data or 0)
        status = int(tr.status)
        t_ns = time.time_ns()
        with self._lock:
            self._active -= 1
            seq = self._seq_of[i]
            if status == _COMPLETED:
                n = int(tr.actual_length)
                self._ready[seq] = (ctypes.string_at(self._buffers[i], n), t_ns)
            else:
                self._ready[seq] = None
            self._flush_ready()
            if status in (_COMPLETED, _TIMED_OUT) and not self._stop.is_set():
                if self._submit(i) < 0 and self.error is None:
                    self.error = _transfer_error(_ERROR, self._endpoint)
                    self._stop.set()
            elif status != _CANCELLED and self.error is None:
                self.error = _transfer_error(status, self._endpoint)
                self._stop.set()
                _log.error("bulk transfer on EP %#04x ended with status %d", self._endpoint, status)

    def _flush_ready(self) -> None:
        while self._next_out in self._ready:
            item = self._ready.pop(self._next_out)
            self._next_out += 1
            if item is not None:
                self._on_data(*item)

    def _cancel_all(self) -> None:
        for t in self._transfers:
            self._h.lib.libusb_cancel_transfer(t)  # NOT_FOUND for idle ones: harmless

    def _drain_events(self) -> None:
        """Handle events until every submitted transfer has called back (bounded)."""
        tv = _Timeval(0, 100_000)
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            with self._lock:
                if self._active <= 0:
                    return
            self._h.lib.libusb_handle_events_timeout_completed(self._h.ctx, ctypes.byref(tv), None)
        _log.warning("%d bulk transfer(s) did not come back after cancel", self._active)

    def _run(self) -> None:
        tv = _Timeval(0, 100_000)
        failures = 0
        try:
            while True:
                with self._lock:
                    if self._active <= 0:
                        break
                    if self._stop.is_set() and not self._cancelled:
                        self._cancelled = True
                        self._cancel_all()
                rc = int(
                    self._h.lib.libusb_handle_events_timeout_completed(
                        self._h.ctx, ctypes.byref(tv), None
                    )
                )
                if rc < 0 and rc != LIBUSB_ERROR_INTERRUPTED:
                    failures += 1
                    if self.error is None:
                        usb = usb_module()
                        self.error = usb.core.USBError("libusb event handling failed", rc)
                    self._stop.set()
                    if failures > 20:
                        break
        finally:
            if self._active <= 0:
                self._free()
            if self.error is not None:
                self._on_error(self.error)

    def _free(self) -> None:
        for t in self._transfers:
            self._h.lib.libusb_free_transfer(t)
        self._transfers = []

    def request_stop(self) -> None:
        """Cancel the transfers (the event thread ends when all came back)."""
        self._stop.set()

    def join(self, timeout_s: float | None = None) -> None:
        """Wait for the event thread."""
        if self._thread.is_alive() or self._thread.ident is not None:
            self._thread.join(timeout_s)

    def is_alive(self) -> bool:
        """The event thread runs (transfers are queued)."""
        return self._thread.is_alive()

    @property
    def transfers(self) -> int:
        """Transfers kept queued."""
        return self._n
