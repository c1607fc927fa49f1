"""The DAVIS240C's streaming threads: a USB reader, a decoder and the queues between them.

:class:`DavisStream` is one streaming session of an opened camera
(:class:`mocaprig.acquire.davis240c.Davis240C` starts and stops it). The *reader* keeps bulk
EP 0x82 drained and hands raw chunks over, in stream order, in a bounded queue; a *decoder*
thread turns them into :class:`~mocaprig.acquire.davis240c_decode.DavisPacket` objects in a
second bounded queue (by count and by payload bytes).

On a real device (pyusb's libusb1 backend) the reader is
:class:`~mocaprig.acquire.davis240c_libusb.AsyncBulkReader`: ``transfers`` bulk transfers of
``transfer_bytes`` stay queued (libcaer: 8 × 8 KiB), so the device's small FIFO is drained while
the host handles earlier data. Synchronous reads from several threads could not keep the order
of the data (a thread can take its sequence number and be preempted before its read is
submitted), so a backend without libusb's asynchronous API (the mock's ``IBackend``) is read by
one thread with one synchronous ``read_size``-byte read at a time (``docs/davis240c.md``).

A slow consumer never blocks the reader: raw chunks that do not fit in the hand-off queue are
dropped but first scanned (vectorised, :func:`~mocaprig.acquire.davis240c_decode.scan_dropped`)
for timestamp wraps, resets, the last timestamp and row, which the decoder applies, so the
times after a dropped chunk stay exact; packets that do not fit are dropped and counted by kind
(:class:`StreamStats`); their special events (timestamp resets, triggers) are kept and delivered
with the next packet.

A USB error other than a timeout (unplugged cable) stops the stream cleanly: everything already
received is decoded and delivered, then :meth:`DavisStream.get` raises
:class:`~mocaprig.errors.DeviceDisconnectedError` (or the
:class:`~mocaprig.errors.DeviceError` subclass the libusb code stands for).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any, BinaryIO, Final

import numpy as np

from mocaprig.acquire.davis240c_decode import (
    DavisDecoder,
    DavisPacket,
    DecodeStats,
    DroppedWords,
    scan_dropped,
)
from mocaprig.acquire.davis240c_libusb import (
    DATA_ENDPOINT,
    AsyncBulkReader,
    async_handle,
    device_error,
    is_no_device,
    is_timeout,
    usb_module,
)
from mocaprig.acquire.events import empty_events
from mocaprig.errors import DeviceDisconnectedError

__all__ = ["DavisStream", "StreamStats"]

_log = logging.getLogger(__name__)

_MAX_CARRIED_SPECIALS: Final = 65536  # specials kept from dropped packets


@dataclass(frozen=True, slots=True)
class StreamStats:
    """A snapshot of the streaming counters since the camera's ``start()``.

    Attributes:
        running: The reader is running.
        transfers_queued: Bulk transfers kept queued (1 = synchronous reads).
        reads: Completed bulk reads.
        bytes_read: Bytes received from EP 0x82.
        read_timeouts: Bulk reads that returned nothing within the read timeout.
        raw_bytes_dropped: Raw bytes dropped because the decoder fell behind (scanned for
            wraps and resets first, so later times stay exact).
        raw_chunks_dropped: Raw chunks (bulk reads) so dropped.
        bytes_discarded_before_reset: Bytes thrown away before our own timestamp reset.
        packets_delivered: Packets handed to the consumer queue.
        packets_dropped: Packets dropped because the consumer queue was full.
        events_dropped: Polarity events in dropped packets.
        frames_dropped: APS frames in dropped packets.
        imu_dropped: IMU samples in dropped packets.
        specials_dropped: Special events dropped (only beyond the carry-over limit).
        decode: The decoder's counters (malformed/skipped words, dropped frames...).
        error: The error that ended the stream, or None.
    """

    running: bool = False
    transfers_queued: int = 0
    reads: int = 0
    bytes_read: int = 0
    read_timeouts: int = 0
    raw_bytes_dropped: int = 0
    raw_chunks_dropped: int = 0
    bytes_discarded_before_reset: int = 0
    packets_delivered: int = 0
    packets_dropped: int = 0
    events_dropped: int = 0
    frames_dropped: int = 0
    imu_dropped: int = 0
    specials_dropped: int = 0
    decode: DecodeStats = field(default_factory=DecodeStats)
    error: str | None = None

    def as_dict(self) -> dict[str, Any]:
        """Plain-JSON view."""
        out: dict[str, Any] = {
            k: getattr(self, k) for k in self.__dataclass_fields__ if k != "decode"
        }
        out["decode"] = self.decode.as_dict()
        return out


class DavisStream:
    """Reader + decoder threads and the two hand-off queues of one streaming session.

    Built by :meth:`mocaprig.acquire.davis240c.Davis240C.start` on an opened, claimed pyusb
    device; :meth:`start` runs the threads, :meth:`get` hands packets to the consumer,
    :meth:`join` stops and waits for both threads (queued packets stay readable).
    """

    def __init__(
        self,
        dev: Any,
        decoder: DavisDecoder,
        *,
        read_size: int,
        read_timeout_ms: int,
        queue_packets: int,
        queue_bytes: int,
        raw_queue_bytes: int,
        discard_until_reset: bool,
        name: str,
        raw_sink: BinaryIO | None,
        transfers: int = 8,
        transfer_bytes: int = 8192,
    ) -> None:
        self._dev = dev
        self._raw_sink = raw_sink
        self._decoder = decoder
        self._read_size = read_size
        self._read_timeout_ms = read_timeout_ms
        self._queue_packets = queue_packets
        self._queue_bytes = queue_bytes
        self._out_bytes = 0
        self._raw_limit = raw_queue_bytes
        self._discard = discard_until_reset
        self._discard_carry = b""
        self._name = name
        self._stop = threading.Event()
        self._raw: collections.deque[tuple[int, bytes | _Lost]] = collections.deque()
        self._raw_bytes = 0
        self._stream_carry = b""  # the odd byte that ends the stream so far (word alignment)
        self._raw_cond = threading.Condition()
        self._reader_done = False
        self._out: collections.deque[DavisPacket] = collections.deque()
        self._out_cond = threading.Condition()
        self._decoder_done = False
        self._carry_specials: list[Any] = []
        self.error: BaseException | None = None
        self._c = dict.fromkeys(
            (
                "reads",
                "bytes_read",
                "read_timeouts",
                "raw_bytes_dropped",
                "raw_chunks_dropped",
                "bytes_discarded_before_reset",
                "packets_delivered",
                "packets_dropped",
                "events_dropped",
                "frames_dropped",
                "imu_dropped",
                "specials_dropped",
            ),
            0,
        )
        self._async: AsyncBulkReader | None = None
        handle = async_handle(dev)
        if handle is not None:
            self._async = AsyncBulkReader(
                handle,
                DATA_ENDPOINT,
                transfers=transfers,
                transfer_bytes=transfer_bytes,
                on_data=self._on_chunk,
                on_error=self._on_async_end,
                name=name,
            )
        self._transfers_queued = transfers if self._async is not None else 1
        self._async_done = threading.Event()
        self._reader = threading.Thread(target=self._read_loop, name=f"davis-{name}-reader")
        self._decoder_thread = threading.Thread(
            target=self._decode_loop, name=f"davis-{name}-decoder"
        )
        self._reader.daemon = True
        self._decoder_thread.daemon = True

    def start(self) -> None:
        """Start the reader (transfers) and the decoder thread.

        Raises:
            DeviceError: the bulk transfers could not be submitted (libusb code kept).
        """
        if self._async is not None:
            usb = usb_module()
            try:
                self._async.start()
            except usb.core.USBError as err:
                msg = f"DAVIS240C {self._name}: cannot queue bulk transfers on EP 0x82: {err}"
                raise device_error(msg, err) from err
            self._reader = threading.Thread(
                target=self._async_watch, name=f"davis-{self._name}-reader", daemon=True
            )
        self._reader.start()
        self._decoder_thread.start()

    def reader_alive(self) -> bool:
        """The reader is running."""
        return self._reader.is_alive()

    def request_stop(self) -> None:
        """Ask the reader to stop (cancel the transfers / end after the current read)."""
        self._stop.set()
        if self._async is not None:
            self._async.request_stop()

    def join(self) -> None:
        """Stop the reader and wait for both threads (the decoder drains what was read)."""
        self.request_stop()
        self._reader.join()
        self._decoder_thread.join()

    # -- asynchronous transfers -----------------------------------------------------------------

    def _async_watch(self) -> None:
        """Stands for the reader thread while the libusb event thread runs the transfers."""
        reader = self._async
        try:
            if reader is not None:
                while reader.is_alive():
                    reader.join(0.1)
        finally:
            with self._raw_cond:
                self._reader_done = True
                self._raw_cond.notify()

    def _on_async_end(self, err: BaseException) -> None:
        if self.error is None:
            self.error = err
            _log.error("DAVIS240C %s: bulk transfers stopped: %s", self._name, err)

    def finished(self) -> bool:
        """Both threads are done and every decoded packet was taken."""
        with self._out_cond:
            return self._decoder_done and not self._out

    # -- reader thread --------------------------------------------------------------------------

    def _read_loop(self) -> None:
        usb = usb_module()
        try:
            while not self._stop.is_set():
                t_call = time.monotonic()
                try:
                    data = self._dev.read(DATA_ENDPOINT, self._read_size, self._read_timeout_ms)
                except usb.core.USBError as err:
                    if is_timeout(err):
                        self._c["read_timeouts"] += 1
                        # A backend that reports a timeout at once (a mock, a device with the
                        # mux off) must not make this thread spin.
                        if time.monotonic() - t_call < self._read_timeout_ms / 2000:
                            time.sleep(0.002)
                        continue
                    self.error = err
                    _log.error("DAVIS240C %s: bulk read failed, stopping: %s", self._name, err)
                    break
                self._on_chunk(bytes(data), time.time_ns())
        except Exception as err:  # pragma: no cover - a bug or a backend misbehaving
            self.error = err
            _log.exception("DAVIS240C %s: reader thread crashed", self._name)
        finally:
            with self._raw_cond:
                self._reader_done = True
                self._raw_cond.notify()

    def _on_chunk(self, chunk: bytes, t_ns: int) -> None:
        """One completed read, in stream order: queue it, or scan and drop it."""
        self._c["reads"] += 1
        self._c["bytes_read"] += len(chunk)
        if not chunk:
            return
        with self._raw_cond:
            carry = self._stream_carry
            odd = (len(carry) + len(chunk)) % 2
            if self._raw_bytes + len(chunk) > self._raw_limit:
                # The decoder is behind: drop the bytes but keep what they do to time.
                data = carry + chunk
                even = len(data) - odd
                words = np.frombuffer(data[:even], dtype="<u2")
                lost = _Lost(scan_dropped(words, dvs_rows=self._y_range), data[even:])
                self._c["raw_bytes_dropped"] += len(chunk)
                self._c["raw_chunks_dropped"] += 1
                self._raw.append((t_ns, lost))
            else:
                self._raw.append((t_ns, chunk))
                self._raw_bytes += len(chunk)
            self._stream_carry = chunk[-1:] if odd else b""
            self._raw_cond.notify()

    @property
    def _y_range(self) -> int:
        o = self._decoder.orientation
        return 240 if o.dvs_invert_xy else 180

    # -- decoder thread -------------------------------------------------------------------------

    def _decode_loop(self) -> None:
        try:
            while True:
                with self._raw_cond:
                    while not self._raw and not self._reader_done:
                        self._raw_cond.wait()
                    if not self._raw:
                        break
                    t_ns, chunk = self._raw.popleft()
                    if isinstance(chunk, bytes):
                        self._raw_bytes -= len(chunk)
                if isinstance(chunk, _Lost):
                    self._gap(chunk, t_ns)
                    continue
                if self._discard:
                    chunk = self._skip_until_reset(chunk)
                    if not chunk:  # still before the reset: show the consumer we are alive
                        self._deliver(DavisPacket(events=empty_events(), host_time_ns=t_ns))
                        continue
                if self._raw_sink is not None:
                    self._raw_sink.write(chunk)
                pkt = self._decoder.decode(chunk)
                self._deliver(
                    DavisPacket(
                        events=pkt.events,
                        frames=pkt.frames,
                        imu=pkt.imu,
                        specials=pkt.specials,
                        host_time_ns=t_ns,
                    )
                )
        except Exception as err:  # pragma: no cover - a decoder bug must not hang consumers
            self.error = self.error or err
            _log.exception("DAVIS240C %s: decoder thread crashed", self._name)
        finally:
            with self._out_cond:
                self._decoder_done = True
                self._out_cond.notify_all()

    def _gap(self, lost: _Lost, t_ns: int) -> None:
        """A dropped chunk: apply its resets/wraps (or keep discarding before our reset)."""
        if self._discard:
            if not lost.words.timestamp_reset:
                self._discard_carry = lost.pending
                self._c["bytes_discarded_before_reset"] += lost.words.n_bytes
                return
            self._discard = False
            self._discard_carry = b""
        pkt = self._decoder.decode_gap(lost.words, pending=lost.pending)
        self._deliver(DavisPacket(events=pkt.events, specials=pkt.specials, host_time_ns=t_ns))

    def _skip_until_reset(self, chunk: bytes) -> bytes:
        data = self._discard_carry + chunk
        even = len(data) - len(data) % 2
        words = np.frombuffer(data[:even], dtype="<u2")
        hit = np.flatnonzero(words == 0x0001)
        if hit.size == 0:
            self._discard_carry = data[even:]
            self._c["bytes_discarded_before_reset"] += even
            return b""
        self._discard = False
        start = 2 * int(hit[0])
        self._c["bytes_discarded_before_reset"] += start
        return data[start:]

    def _deliver(self, pkt: DavisPacket) -> None:
        with self._out_cond:
            if self._carry_specials:
                merged = np.concatenate([*self._carry_specials, pkt.specials])
                pkt = DavisPacket(
                    events=pkt.events,
                    frames=pkt.frames,
                    imu=pkt.imu,
                    specials=merged,
                    host_time_ns=pkt.host_time_ns,
                )
                self._carry_specials = []
            size = _payload_bytes(pkt)
            full = len(self._out) >= self._queue_packets
            if full or (self._out and self._out_bytes + size > self._queue_bytes):
                c = self._c
                c["packets_dropped"] += 1
                c["events_dropped"] += int(pkt.events.size)
                c["frames_dropped"] += len(pkt.frames)
                c["imu_dropped"] += int(pkt.imu.size)
                if pkt.specials.size:
                    carried = sum(int(s.size) for s in self._carry_specials)
                    if carried + pkt.specials.size <= _MAX_CARRIED_SPECIALS:
                        self._carry_specials.append(pkt.specials)
                    else:
                        c["specials_dropped"] += int(pkt.specials.size)
                return
            self._out.append(pkt)
            self._out_bytes += size
            self._c["packets_delivered"] += 1
            self._out_cond.notify()

    # -- consumer side --------------------------------------------------------------------------

    def get(self, timeout_s: float | None) -> DavisPacket | None:
        """The next packet; None after ``timeout_s`` or once the stream ended cleanly.

        Raises:
            DeviceDisconnectedError: the device went away (after every packet was taken).
            DeviceError: the stream ended on another USB error (its libusb code decides the
                subclass).
        """
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._out_cond:
            while not self._out and not self._decoder_done:
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                self._out_cond.wait(remaining)
            if self._out:
                pkt = self._out.popleft()
                self._out_bytes -= _payload_bytes(pkt)
                return pkt
        if self.error is not None:
            err = self.error
            gone = is_no_device(err)
            what = (
                "was disconnected while streaming"
                if gone
                else "stopped streaming after a USB error"
            )
            msg = (
                f"DAVIS240C {self._name} {what} ({err}); everything received before was "
                "delivered. Replug the camera and open it again"
            )
            raise device_error(msg, err, DeviceDisconnectedError if gone else None) from err
        return None

    def stats(self) -> StreamStats:
        """A snapshot of the counters."""
        c = self._c
        return StreamStats(
            running=self._reader.is_alive(),
            transfers_queued=self._transfers_queued,
            decode=self._decoder.stats,
            error=None if self.error is None else str(self.error),
            **c,
        )


@dataclass(frozen=True, slots=True)
class _Lost:
    """A dropped chunk in the hand-off queue: its scan and the odd byte that ended it."""

    words: DroppedWords
    pending: bytes


def _payload_bytes(pkt: DavisPacket) -> int:
    """Memory a queued packet holds (events, frame pixels, IMU samples, specials)."""
    return (
        pkt.events.nbytes
        + pkt.imu.nbytes
        + pkt.specials.nbytes
        + sum(f.pixels.nbytes for f in pkt.frames)
    )
