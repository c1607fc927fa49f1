"""Command-line entry points of the acquisition side: ``mocaprig davis ...`` and ``devices``.

Handlers are thin: they parse, call a typed function that returns an exit code, and print.
Heavy modules (numpy decoding, pyusb) are imported inside the functions so ``mocaprig --help``
stays fast. ``--mock`` loads the DAVIS240C mock through the ``mocaprig.mocks`` entry point;
acquire/ never imports drivers_mock/.

``mocaprig devices`` asks every function in :data:`DEVICE_PROBERS` for what it sees; the D415
and sync-box drivers add theirs there (a name -> ``(mock: bool) -> list[DeviceListing]``).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mocaprig.cli import add_json_flag, emit_json, usage_handler
from mocaprig.errors import DeviceError, RecordingError
from mocaprig.progress import ProgressBar, StatusLine

if TYPE_CHECKING:
    from mocaprig.acquire.davis240c import Davis240C
    from mocaprig.acquire.davis240c_decode import DavisPacket

_log = logging.getLogger(__name__)

__all__ = [
    "DEVICE_PROBERS",
    "DecodeSummary",
    "DeviceListing",
    "davis_config",
    "davis_decode",
    "davis_info",
    "davis_stream",
    "decode_raw_file",
    "list_devices",
    "load_decoded",
    "probe_d415",
    "probe_davis",
    "probe_syncbox",
    "register_davis",
    "register_devices",
]

_DAVIS_EPILOG = """\
examples:
  mocaprig davis info --mock                     serial, firmware/logic, SYSINFO, master/slave
  mocaprig davis stream --seconds 5 --raw-out cap.bin
      stream 5 s from the first DAVIS240C, live rates on stderr, raw bulk bytes to cap.bin
  mocaprig davis decode cap.bin --out cap.npz --json
      decode a raw capture: events, frames, IMU and specials into one .npz
  mocaprig davis config --bias-preset default --set APS.EXPOSURE=8000 --set IMU.ACCEL_FULL_SCALE=2

Run `mocaprig davis SUBCOMMAND --help` for each subcommand's options.
"""

_DECODE_EPILOG = """\
examples:
  mocaprig davis decode cap.bin --out cap.npz
  mocaprig davis decode cap.bin --out cap.npz --json     one JSON object: counts, span, skipped

The .npz holds: events (t µs int64, x, y, p), specials (t, type = libcaer special type, data),
imu (t, accel_g[3], gyro_dps[3], temp_c), frame_meta (one row per APS frame: times in µs,
exposure_cycles, position_x/y, size_x/y, offset) and frame_pixels (all frames' uint16 pixels,
0..1023, row-major, concatenated; frame i is frame_pixels[offset : offset + size_y*size_x]).
Read it back with acquire.commands.load_decoded(path).
"""

_INFO_EPILOG = """\
examples:
  mocaprig davis info                 the first DAVIS240C on the bus
  mocaprig davis info --serial 00000042 --json
  mocaprig davis info --mock          the simulated camera
"""

_CONFIG_EPILOG = """\
examples:
  mocaprig davis config --mock --json                    write the defaults, show what was set
  mocaprig davis config --bias-preset pyaer
  mocaprig davis config --set APS.EXPOSURE=8000 --set BIAS.ONBN=6/200 \\
                        --set EXTINPUT.DETECT_RISING_EDGES=1

--set takes MODULE.PARAM=VALUE with libcaer names (MUX, DVS, APS, IMU, EXTINPUT, BIAS, CHIP,
USB). Host units: APS EXPOSURE / FRAME_INTERVAL and EXTINPUT lengths in µs, USB
EARLY_PACKET_DELAY in 125 µs slots, BIAS as COARSE/FINE or the raw 16-bit value. The settings
last while the camera stays powered.
"""

_STREAM_EPILOG = """\
examples:
  mocaprig davis stream --mock --seconds 2
  mocaprig davis stream --seconds 10 --raw-out cap.bin --json
      keep the raw bulk bytes (from the timestamp reset on) for `mocaprig davis decode`
"""

_DEVICES_EPILOG = """\
examples:
  mocaprig devices              every camera found: kind, serial, bus/address, versions
  mocaprig devices --mock --json
"""


# -- typed functions -----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class DecodeSummary:
    """What :func:`decode_raw_file` wrote."""

    raw_path: Path
    out_path: Path
    bytes_in: int
    events: int
    frames: int
    imu_samples: int
    specials_by_type: dict[str, int]
    t_first_us: int | None
    t_last_us: int | None
    stats: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """Plain-JSON view."""
        return {
            "raw": str(self.raw_path),
            "out": str(self.out_path),
            "bytes": self.bytes_in,
            "events": self.events,
            "frames": self.frames,
            "imu_samples": self.imu_samples,
            "specials": self.specials_by_type,
            "t_first_us": self.t_first_us,
            "t_last_us": self.t_last_us,
            "span_s": None
            if self.t_first_us is None or self.t_last_us is None
            else (self.t_last_us - self.t_first_us) * 1e-6,
            "skipped_words": self.stats.get("skipped_words", 0),
            "stats": self.stats,
        }


def decode_raw_file(
    raw_path: str | Path,
    out_path: str | Path,
    *,
    chunk_bytes: int = 1 << 20,
    progress: Callable[[int, int], None] | None = None,
) -> DecodeSummary:
    """Decode a raw EP 0x82 capture into an .npz (layout: ``mocaprig davis decode --help``).

    The file is read and decoded ``chunk_bytes`` at a time through one decoder;
    ``progress(bytes_decoded, bytes_total)`` after each chunk.

    Raises:
        RecordingError: the input cannot be read or the output cannot be written.
    """
    import numpy as np

    from mocaprig.acquire.davis240c_decode import (
        IMU_SAMPLE_DTYPE,
        SPECIAL_DTYPE,
        ApsFrame,
        DavisDecoder,
        SpecialType,
    )
    from mocaprig.acquire.events import EVENT_DTYPE

    raw_path, out_path = Path(raw_path), Path(out_path)
    if not raw_path.is_file():
        msg = f"raw capture {raw_path} does not exist; record one with `mocaprig davis stream`"
        raise RecordingError(msg)
    dec = DavisDecoder()
    events, imu, specials = [], [], []
    frames: list[ApsFrame] = []
    try:
        total = raw_path.stat().st_size
        done = 0
        with raw_path.open("rb") as fh:
            while chunk := fh.read(chunk_bytes):
                pkt = dec.decode(chunk)
                events.append(pkt.events)
                imu.append(pkt.imu)
                specials.append(pkt.specials)
                frames.extend(pkt.frames)
                done += len(chunk)
                if progress is not None:
                    progress(done, total)
    except OSError as err:
        msg = f"cannot read raw capture {raw_path}: {err}"
        raise RecordingError(msg) from err
    ev = np.concatenate(events) if events else np.empty(0, EVENT_DTYPE)
    im = np.concatenate(imu) if imu else np.empty(0, IMU_SAMPLE_DTYPE)
    sp = np.concatenate(specials) if specials else np.empty(0, SPECIAL_DTYPE)
    meta = np.empty(len(frames), _FRAME_META_DTYPE)
    offset = 0
    for i, f in enumerate(frames):
        h, w = f.pixels.shape
        meta[i] = (
            f.t_start_frame_us,
            f.t_end_frame_us,
            f.t_start_exposure_us,
            f.t_end_exposure_us,
            f.exposure_cycles,
            f.position_x,
            f.position_y,
            w,
            h,
            offset,
            f.global_shutter,
        )
        offset += h * w
    pixels = (
        np.concatenate([f.pixels.ravel() for f in frames]) if frames else np.empty(0, np.uint16)
    )
    try:
        out_path.parent.mkdir(parents=True, exist_ok=True)
        with out_path.open("wb") as fh:
            np.savez_compressed(
                fh,
                events=ev,
                specials=sp,
                imu=im,
                frame_meta=meta,
                frame_pixels=pixels,
            )
    except OSError as err:
        msg = f"cannot write {out_path}: {err}"
        raise RecordingError(msg) from err
    types, counts = np.unique(sp["type"], return_counts=True)
    names = {int(m): m.name for m in SpecialType}
    by_type = {names.get(int(t), str(int(t))): int(c) for t, c in zip(types, counts, strict=True)}
    return DecodeSummary(
        raw_path=raw_path,
        out_path=out_path,
        bytes_in=dec.stats.bytes_in,
        events=int(ev.size),
        frames=len(frames),
        imu_samples=int(im.size),
        specials_by_type=by_type,
        t_first_us=int(ev["t"][0]) if ev.size else None,
        t_last_us=int(ev["t"][-1]) if ev.size else None,
        stats=dec.stats.as_dict(),
    )


_FRAME_META_DTYPE: Any = [
    ("t_start_frame_us", "<i8"),
    ("t_end_frame_us", "<i8"),
    ("t_start_exposure_us", "<i8"),
    ("t_end_exposure_us", "<i8"),
    ("exposure_cycles", "<i8"),
    ("position_x", "<u2"),
    ("position_y", "<u2"),
    ("size_x", "<u2"),
    ("size_y", "<u2"),
    ("offset", "<i8"),
    ("global_shutter", "u1"),
]


def load_decoded(path: str | Path) -> dict[str, Any]:
    """Read an .npz written by :func:`decode_raw_file`.

    Returns a dict with ``events``, ``specials``, ``imu`` (structured arrays) and ``frames``
    (a list of :class:`mocaprig.acquire.davis240c_decode.ApsFrame`).
    """
    import numpy as np

    from mocaprig.acquire.davis240c_decode import ApsFrame

    with np.load(Path(path), allow_pickle=False) as z:
        meta, pix = z["frame_meta"], z["frame_pixels"]
        frames = []
        for m in meta:
            h, w, off = int(m["size_y"]), int(m["size_x"]), int(m["offset"])
            frames.append(
                ApsFrame(
                    t_start_frame_us=int(m["t_start_frame_us"]),
                    t_end_frame_us=int(m["t_end_frame_us"]),
                    t_start_exposure_us=int(m["t_start_exposure_us"]),
                    t_end_exposure_us=int(m["t_end_exposure_us"]),
                    exposure_cycles=int(m["exposure_cycles"]),
                    position_x=int(m["position_x"]),
                    position_y=int(m["position_y"]),
                    pixels=pix[off : off + h * w].reshape(h, w).copy(),
                    global_shutter=bool(m["global_shutter"]),
                )
            )
        return {
            "events": z["events"],
            "specials": z["specials"],
            "imu": z["imu"],
            "frames": frames,
        }


def _open_davis(*, mock: bool, serial: str | None, **options: Any) -> Davis240C:
    from mocaprig.acquire.davis240c import Davis240C, load_mock_backend

    backend = load_mock_backend() if mock else None
    return Davis240C.open(serial=serial, backend=backend, **options)


def davis_decode(raw: Path, out: Path, *, as_json: bool) -> int:
    """``mocaprig davis decode``: exit code 0."""
    bar = ProgressBar("decode", unit="kB")
    summary = decode_raw_file(
        raw, out, progress=lambda done, total: bar(done // 1000, total // 1000)
    )
    if as_json:
        emit_json(summary.as_dict())
        return 0
    d = summary.as_dict()
    span = "" if d["span_s"] is None else f" over {d['span_s']:.3f} s"
    specials = ", ".join(f"{k} {v}" for k, v in d["specials"].items()) or "none"
    print(
        f"decoded {summary.bytes_in} bytes: {summary.events} events{span}, "
        f"{summary.frames} frames, {summary.imu_samples} IMU samples; specials: {specials}; "
        f"skipped words: {d['skipped_words']} -> {summary.out_path}"
    )
    return 0


def davis_info(*, mock: bool, serial: str | None, as_json: bool) -> int:
    """``mocaprig davis info``: exit code 0."""
    with _open_davis(mock=mock, serial=serial, send_default_config=False) as cam:
        info = cam.info.as_dict()
    if as_json:
        emit_json(info)
        return 0
    c = info["clocks"]
    print(
        f"{info['device_string']}  bus {info['bus']} address {info['address']}\n"
        f"  firmware {info['firmware_version']}, logic {info['logic_version']}."
        f"{info['logic_patch']}, chip id {info['chip_id']}\n"
        f"  role: {'master' if info['device_is_master'] else 'slave'}\n"
        f"  DVS {info['dvs_size_x']}x{info['dvs_size_y']}, APS {info['aps_size_x']}x"
        f"{info['aps_size_y']} (global shutter: {info['aps_has_global_shutter']}), "
        f"IMU type {info['imu_type']}\n"
        f"  clocks: logic {c['logic_mhz']} MHz, ADC {c['adc_mhz']} MHz, USB {c['usb_mhz']} MHz,"
        f" deviation {c['deviation_x1000'] / 1000:g}"
    )
    return 0


def davis_config(
    *,
    mock: bool,
    serial: str | None,
    bias_preset: str,
    settings: list[str],
    as_json: bool,
) -> int:
    """``mocaprig davis config``: write a bias preset + defaults, then ``--set`` writes."""
    from mocaprig.acquire.davis240c_config import bias_set, parse_setting

    bias_set(bias_preset)  # validate the name before touching the device
    writes = []
    with _open_davis(mock=mock, serial=serial, bias_preset=bias_preset) as cam:
        for text in settings:
            wr = parse_setting(text, clocks=cam.info.clocks)
            cam.config_set(wr.module, wr.param, wr.value)
            name = text.split("=", 1)[0].strip().upper()
            writes.append((name, wr, cam.config_get(wr.module, wr.param)))
        serial_no = cam.serial
    rows = [
        {"name": n, "module": int(w.module), "param": int(w.param), "value": w.value, "readback": r}
        for n, w, r in writes
    ]
    if as_json:
        emit_json({"serial": serial_no, "bias_preset": bias_preset, "writes": rows})
        return 0
    print(f"DAVIS240C {serial_no}: defaults with bias preset {bias_preset!r} written")
    for row in rows:
        ok = "ok" if row["readback"] == row["value"] else f"reads back {row['readback']}"
        if row["name"] == "MUX.TIMESTAMP_RESET" and row["value"]:
            ok = "pulsed (1 then 0: the device timestamps restart at 0)"
        print(f"  {row['name']} ({row['module']}/{row['param']}) = {row['value']}: {ok}")
    return 0


def davis_stream(
    *,
    mock: bool,
    serial: str | None,
    seconds: float,
    raw_out: Path | None,
    as_json: bool,
) -> int:
    """``mocaprig davis stream``: stream for ``seconds``, live status line, JSON summary."""
    from mocaprig.validation import check_positive

    check_positive(seconds, name="--seconds")
    if raw_out is not None and raw_out.exists():
        msg = f"{raw_out} exists already, not overwriting; choose another --raw-out"
        raise RecordingError(msg)
    totals = {"events": 0, "frames": 0, "imu_samples": 0, "specials": 0, "packets": 0}
    status = _StatusLine()
    sink = raw_out.open("wb") if raw_out is not None else None
    error: DeviceError | None = None
    try:
        with _open_davis(mock=mock, serial=serial, raw_sink=sink) as cam:
            cam.start()
            t0 = time.monotonic()
            deadline = t0 + seconds
            try:
                while (now := time.monotonic()) < deadline:
                    pkt = cam.get_packet(timeout_s=min(0.1, max(deadline - now, 0.0)))
                    if pkt is not None:
                        _count(totals, pkt)
                    elif not cam.running:
                        # The reader ended (an unplug, a USB error): the decoder may still
                        # hold packets; the reader's error comes once they are taken.
                        for pkt in cam.packets(timeout_s=5.0):
                            _count(totals, pkt)
                        break
                    status(totals, cam, now - t0)
            except DeviceError as exc:
                error = exc
            device_dropped: dict[str, int] = {}
            if error is None:
                try:
                    device_dropped = cam.device_drop_counts()
                except DeviceError as exc:  # unplugged after the last packet
                    error = exc
            cam.stop()
            with contextlib.suppress(DeviceError):  # the error, if any, is already in hand
                while (pkt := cam.get_packet(0)) is not None:
                    _count(totals, pkt)
            elapsed = time.monotonic() - t0
            stats = cam.stats()
            serial_no = cam.serial
    except BaseException:
        if sink is not None and raw_out is not None:
            sink.close()
            if raw_out.stat().st_size == 0:
                raw_out.unlink()  # nothing was captured: do not block the next --raw-out
        raise
    finally:
        if sink is not None:
            sink.close()
    status.done()
    event_rate = totals["events"] / elapsed if elapsed > 0 else 0.0
    summary = {
        "serial": serial_no,
        "seconds": elapsed,
        **totals,
        "event_rate_hz": event_rate,
        "frame_rate_hz": totals["frames"] / elapsed if elapsed > 0 else 0.0,
        "device_dropped": device_dropped,
        "raw_out": None if raw_out is None else str(raw_out),
        "error": None if error is None else str(error),
        "stats": stats.as_dict(),
    }
    if as_json:
        emit_json(summary)
    else:
        print(
            f"DAVIS240C {serial_no}: {elapsed:.2f} s, {totals['events']} events "
            f"({event_rate / 1e3:.1f} k/s), {totals['frames']} frames, "
            f"{totals['imu_samples']} IMU samples, {totals['specials']} specials; dropped "
            f"packets {stats.packets_dropped}, raw bytes {stats.raw_bytes_dropped}"
        )
    if error is not None:
        print(f"ERROR: {error}", file=sys.stderr)
        return 1
    return 0


def _count(totals: dict[str, int], pkt: DavisPacket) -> None:
    totals["packets"] += 1
    totals["events"] += int(pkt.events.size)
    totals["frames"] += len(pkt.frames)
    totals["imu_samples"] += int(pkt.imu.size)
    totals["specials"] += int(pkt.specials.size)


class _StatusLine:
    """``davis stream``'s live figures on the :class:`~mocaprig.progress.StatusLine`."""

    def __init__(self) -> None:
        self._line = StatusLine()
        self._prev: tuple[float, int, int] = (0.0, 0, 0)

    def __call__(self, totals: dict[str, int], cam: Davis240C, elapsed: float) -> None:
        if not self._line.due():
            return
        t_prev, ev_prev, fr_prev = self._prev
        dt = max(elapsed - t_prev, 1e-9)
        ev_rate = (totals["events"] - ev_prev) / dt
        fr_rate = (totals["frames"] - fr_prev) / dt
        s = cam.stats()
        self._line.show(
            f"{elapsed:6.1f} s  {ev_rate / 1e3:8.1f} k ev/s  {fr_rate:5.1f} fps  "
            f"drops: {s.packets_dropped} pkts, {s.raw_bytes_dropped} raw B, "
            f"{s.decode.frames_dropped} frames"
        )
        self._prev = (elapsed, totals["events"], totals["frames"])

    def done(self) -> None:
        self._line.done()


# -- devices -------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class DeviceListing:
    """One device found by a prober of ``mocaprig devices``.

    Attributes:
        kind: Device kind, e.g. "DAVIS240C", "D415", "syncbox".
        serial: Serial number, or None when unreadable.
        location: Where it is (``bus 1 address 5``, ``/dev/ttyUSB0``...).
        details: Versions and other kind-specific facts (plain JSON values).
        error: Why something could not be read, or None.
    """

    kind: str
    serial: str | None
    location: str
    details: dict[str, Any] = field(default_factory=dict)
    error: str | None = None

    def as_dict(self) -> dict[str, Any]:
        """Plain-JSON view."""
        return {
            "kind": self.kind,
            "serial": self.serial,
            "location": self.location,
            "details": self.details,
            "error": self.error,
        }


Prober = Callable[[bool], list[DeviceListing]]


def probe_davis(mock: bool) -> list[DeviceListing]:
    """DAVIS cameras on the bus (or the mock's) as :class:`DeviceListing` rows."""
    from mocaprig.acquire.davis240c import find_davis, load_mock_backend
    from mocaprig.acquire.doctor import Verdict, check_libusb

    backend = load_mock_backend() if mock else None
    libusb = check_libusb()
    if backend is None and libusb.verdict is Verdict.FIX:
        msg = f"{libusb.detail}: {libusb.fix}"
        raise DeviceError(msg)
    return [
        DeviceListing(
            kind="DAVIS240C" if d.product_id == 0x841B else "DAVIS (FX3)",
            serial=d.serial,
            location=f"bus {d.bus} address {d.address}",
            details={
                "product_id": f"{d.product_id:04x}",
                "firmware_version": d.firmware_version,
                "logic_version": d.logic_version,
                "logic_patch": d.logic_patch,
            },
            error=d.error,
        )
        for d in find_davis(backend=backend)
    ]


def probe_d415(mock: bool) -> list[DeviceListing]:
    """RealSense D415 cameras (or the mock rig's) as :class:`DeviceListing` rows."""
    from mocaprig.acquire.realsense import list_d415_devices

    return [
        DeviceListing(
            kind="D415",
            serial=info.serial,
            location=f"USB {info.usb_type}" if info.usb_type else "USB",
            details={"name": info.name, "firmware": info.firmware, "usb_type": info.usb_type},
            error=None if info.is_usb3 else "USB 2 link: 848x480@90 and 1280x720 are unavailable",
        )
        for info in list_d415_devices(mock=mock)
    ]


def probe_syncbox(mock: bool) -> list[DeviceListing]:
    """Sync boxes that answer ``HELLO`` on a USB-serial port (or the mock box)."""
    from mocaprig.acquire.syncbox import SyncBox, find_syncboxes, open_mock_syncbox

    def identify(port: str) -> DeviceListing:
        with SyncBox(port, boot_timeout_s=2.5, max_reopen=0) as sb:
            ident = sb.identity
        details = {} if ident is None else {"protocol": ident.version, "board": ident.board}
        return DeviceListing(kind="syncbox", serial=None, location=port, details=details)

    if mock:
        with open_mock_syncbox() as box:
            return [identify(box.port)]
    rows: list[DeviceListing] = []
    for port in find_syncboxes():
        try:
            rows.append(identify(port))
        except DeviceError as err:
            # Other USB-serial bridges (GPS, Arduinos with other sketches) are not listed.
            _log.debug("%s is not a sync box: %s", port, err)
    return rows


#: Device probers of ``mocaprig devices``, by name; a failing prober is reported, not fatal.
DEVICE_PROBERS: dict[str, Prober] = {
    "davis": probe_davis,
    "d415": probe_d415,
    "syncbox": probe_syncbox,
}


def list_devices(*, mock: bool, as_json: bool) -> int:
    """``mocaprig devices``: ask every prober; a failing prober is reported, not fatal."""
    rows: list[DeviceListing] = []
    failures: dict[str, str] = {}
    for name, prober in DEVICE_PROBERS.items():
        try:
            rows.extend(prober(mock))
        except (DeviceError, OSError) as err:
            failures[name] = str(err)
    if as_json:
        emit_json({"devices": [r.as_dict() for r in rows], "prober_errors": failures})
        return 0
    if not rows:
        print("no devices found" + (" (mock)" if mock else ""))
    for r in rows:
        det = ", ".join(f"{k} {v}" for k, v in r.details.items())
        note = f"  [{r.error}]" if r.error else ""
        print(f"{r.kind:<12} {r.serial or '?':<12} {r.location:<22} {det}{note}")
    for name, why in failures.items():
        print(f"{name}: cannot probe: {why}", file=sys.stderr)
    return 0


# -- registration --------------------------------------------------------------------------------


def _formatter() -> type[argparse.HelpFormatter]:
    return argparse.RawDescriptionHelpFormatter


def _add_device_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mock", action="store_true", help="use the simulated DAVIS240C")
    p.add_argument("--serial", help="open the camera with this serial number")


def register_davis(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``mocaprig davis {decode,info,config,stream}``."""
    p = subparsers.add_parser(
        "davis",
        help="DAVIS240C event camera: info, config, stream, decode",
        description="Talk to a DAVIS240C over USB (libusb) and decode its raw stream.",
        epilog=_DAVIS_EPILOG,
        formatter_class=_formatter(),
    )
    sub = p.add_subparsers(dest="davis_command", metavar="SUBCOMMAND")
    p.set_defaults(func=usage_handler(p))

    d = sub.add_parser(
        "decode",
        help="decode a raw EP 0x82 capture into an .npz",
        description="Decode a raw DAVIS240C bulk capture (16-bit LE words) into numpy arrays.",
        epilog=_DECODE_EPILOG,
        formatter_class=_formatter(),
    )
    d.add_argument("raw", type=Path, metavar="RAW.bin", help="raw capture (e.g. --raw-out)")
    d.add_argument("--out", type=Path, required=True, metavar="FILE.npz", help="output file")
    add_json_flag(d)
    d.set_defaults(func=lambda a: davis_decode(a.raw, a.out, as_json=a.json))

    i = sub.add_parser(
        "info",
        help="serial, firmware/logic versions, SYSINFO, master/slave",
        description="Open a DAVIS240C (without changing its settings) and show what it reports.",
        epilog=_INFO_EPILOG,
        formatter_class=_formatter(),
    )
    _add_device_flags(i)
    add_json_flag(i)
    i.set_defaults(func=lambda a: davis_info(mock=a.mock, serial=a.serial, as_json=a.json))

    c = sub.add_parser(
        "config",
        help="write a bias preset and default settings, then MODULE.PARAM=VALUE changes",
        description="Configure a DAVIS240C: libcaer's defaults with a bias preset, then --set.",
        epilog=_CONFIG_EPILOG,
        formatter_class=_formatter(),
    )
    _add_device_flags(c)
    c.add_argument(
        "--bias-preset", default="default", metavar="NAME", help="default, legacy or pyaer"
    )
    c.add_argument(
        "--set",
        dest="settings",
        action="append",
        default=[],
        metavar="MODULE.PARAM=VALUE",
        help="a register write in host units (repeatable)",
    )
    add_json_flag(c)
    c.set_defaults(
        func=lambda a: davis_config(
            mock=a.mock,
            serial=a.serial,
            bias_preset=a.bias_preset,
            settings=a.settings,
            as_json=a.json,
        )
    )

    s = sub.add_parser(
        "stream",
        help="stream for N seconds with a live status line",
        description=(
            "Start a DAVIS240C, show event rate, frame rate and drops on stderr, and optionally "
            "keep the raw bulk bytes."
        ),
        epilog=_STREAM_EPILOG,
        formatter_class=_formatter(),
    )
    _add_device_flags(s)
    s.add_argument("--seconds", type=float, required=True, help="how long to stream")
    s.add_argument("--raw-out", type=Path, metavar="FILE", help="write the raw bulk bytes here")
    add_json_flag(s)
    s.set_defaults(
        func=lambda a: davis_stream(
            mock=a.mock, serial=a.serial, seconds=a.seconds, raw_out=a.raw_out, as_json=a.json
        )
    )


def register_devices(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``mocaprig devices``."""
    p = subparsers.add_parser(
        "devices",
        help="list the rig's devices (DAVIS cameras; D415 and sync box when registered)",
        description="List every device the registered probers find.",
        epilog=_DEVICES_EPILOG,
        formatter_class=_formatter(),
    )
    p.add_argument("--mock", action="store_true", help="list the simulated devices")
    add_json_flag(p)
    p.set_defaults(func=lambda a: list_devices(mock=a.mock, as_json=a.json))
