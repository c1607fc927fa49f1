"""``mocaprig doctor``: is this capture PC and its rig ready? Each finding with its fix.

The first command a lab runs with its devices plugged in. It checks, in order:

1. **libusb**: pyusb finds a libusb-1.0 backend (the DAVIS driver and pyrealsense2 need it);
2. **DAVIS**: each camera on the bus is readable (udev permissions), is a DAVIS240C (chip id,
   the FX2 board) with a logic release the driver knows, and streams: a short run delivers
   packets, with no device-side or host-side drops;
3. **D415**: each camera's firmware is new enough for hardware sync, its USB link is USB 3, its
   frames carry per-frame metadata (hardware timestamps: without them nothing about sync can be
   verified), and — with two or more cameras — the sync cable works: a short
   :func:`~acquire.d415_sync.run_sync_check` says whether every slave is really triggered;
4. **sync box**: it answers ``HELLO`` with the protocol this toolkit speaks, and in ``LISTEN`` it
   counts the master's pulses at the camera rate.

Every finding is a :class:`Finding`: ``ok``, ``warn`` (works, but look) or ``fix`` (will not work
as it is), with what to do. Library code: it returns a :class:`DoctorReport` and never prints.
With ``mock=True`` the devices are the simulated rig (faults injectable), the host checks
(libusb) stay real.
"""

from __future__ import annotations

import enum
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Final

from mocaprig.errors import DeviceError, ValidationError

__all__ = [
    "DOCTOR_FAULTS",
    "DoctorReport",
    "Finding",
    "Verdict",
    "check_libusb",
    "run_doctor",
]

_log = logging.getLogger(__name__)

#: Faults ``run_doctor(mock=True, faults=...)`` can inject, ``device:fault``.
DOCTOR_FAULTS: Final = (
    "davis:unplug",
    "davis:usb-bandwidth",
    "d415:slave-trigger-cut",
    "d415:no-metadata",
    "d415:disconnect",
    "syncbox:no-reply",
    "syncbox:unwired",
)
_LIBUSB_FIX: Final = (
    "install libusb-1.0 (Debian/Ubuntu: sudo apt-get install libusb-1.0-0; Fedora: "
    "sudo dnf install libusb1) and run the command again"
)
_METADATA_FIX: Final = (
    "per-frame metadata is missing: the kernel's uvcvideo driver drops it; apply librealsense's "
    "kernel patch (scripts/patch-realsense-ubuntu-lts-hwe.sh) or use a pyrealsense2 built with "
    "FORCE_RSUSB_BACKEND=ON (realsense-d415.md §2.8)"
)


class Verdict(enum.Enum):
    """How a finding stands."""

    OK = "ok"
    WARN = "warn"
    FIX = "fix"


@dataclass(frozen=True, slots=True)
class Finding:
    """One check: the device or host part it is about, what was seen and what to do."""

    subject: str
    """``host``, ``davis/<serial>``, ``d415/<serial>``, ``d415 rig`` or ``syncbox``."""
    check: str
    verdict: Verdict
    detail: str
    fix: str = ""

    def as_dict(self) -> dict[str, str]:
        return {
            "subject": self.subject,
            "check": self.check,
            "verdict": self.verdict.value,
            "detail": self.detail,
            "fix": self.fix,
        }


@dataclass(frozen=True, slots=True)
class DoctorReport:
    """Every finding, in check order."""

    findings: tuple[Finding, ...]
    mock: bool = False
    faults: tuple[str, ...] = field(default=())

    @property
    def ok(self) -> bool:
        """No finding needs a fix (warnings allowed)."""
        return not any(f.verdict is Verdict.FIX for f in self.findings)

    def as_dict(self) -> dict[str, Any]:
        return {
            "ok": self.ok,
            "mock": self.mock,
            "faults": list(self.faults),
            "findings": [f.as_dict() for f in self.findings],
        }


def check_libusb() -> Finding:
    """Whether pyusb finds a libusb-1.0 backend."""
    try:
        import usb.backend.libusb1

        backend = usb.backend.libusb1.get_backend()
    except ImportError as err:  # pyusb itself missing: a broken install
        return Finding(
            "host",
            "pyusb",
            Verdict.FIX,
            f"pyusb cannot be imported ({err})",
            "reinstall mocaprig (pip install -e .)",
        )
    if backend is None:
        return Finding("host", "libusb", Verdict.FIX, "no libusb-1.0 library found", _LIBUSB_FIX)
    return Finding("host", "libusb", Verdict.OK, "libusb-1.0 found")


def _parse_faults(faults: Sequence[str], *, mock: bool) -> dict[str, set[str]]:
    out: dict[str, set[str]] = {"davis": set(), "d415": set(), "syncbox": set()}
    if faults and not mock:
        msg = "faults can only be injected into the mocks; add --mock"
        raise ValidationError(msg)
    for f in faults:
        if f not in DOCTOR_FAULTS:
            msg = f"unknown fault {f!r}; choose from {', '.join(DOCTOR_FAULTS)}"
            raise ValidationError(msg)
        device, _, name = f.partition(":")
        out[device].add(name)
    return out


# -- DAVIS ----------------------------------------------------------------------------------------


def _davis_findings(*, mock: bool, faults: set[str], seconds: float) -> list[Finding]:
    from mocaprig.acquire.davis240c import Davis240C, find_davis, load_mock_backend

    # The mock takes its faults by name (drivers_mock.davis240c_usb.mock_backend).
    backend = None
    if mock:
        backend = load_mock_backend(fault=sorted(faults)) if faults else load_mock_backend()
    found = find_davis(backend=backend)
    if not found:
        return [
            Finding(
                "davis",
                "present",
                Verdict.WARN,
                "no DAVIS camera on the bus",
                "plug the DAVIS240C into a USB port (USB 2 is enough) if the rig has one",
            )
        ]
    out: list[Finding] = []
    for dev in found:
        subject = f"davis/{dev.serial or '?'}"
        if dev.error is not None:
            out.append(
                Finding(
                    subject,
                    "access",
                    Verdict.FIX,
                    dev.error,
                    "install the udev rule (mocaprig davis info --help shows it), "
                    "replug the camera",
                )
            )
            continue
        out.append(Finding(subject, "access", Verdict.OK, f"bus {dev.bus} address {dev.address}"))
        try:
            with Davis240C.open(serial=dev.serial, backend=backend) as cam:
                info = cam.info
                out.append(_davis_identity(subject, info))
                out.append(_davis_stream(subject, cam, seconds))
        except DeviceError as err:
            out.append(
                Finding(
                    subject,
                    "stream",
                    Verdict.FIX,
                    str(err),
                    "check the USB cable and port, then run `mocaprig doctor` again",
                )
            )
    return out


def _davis_identity(subject: str, info: Any) -> Finding:
    text = (
        f"chip id {info.chip_id}, firmware {info.firmware_version}, logic "
        f"{info.logic_version}.{info.logic_patch}, {info.dvs_size_x}x{info.dvs_size_y}"
    )
    if int(info.chip_id) != 2:
        return Finding(
            subject,
            "identity",
            Verdict.FIX,
            text + ": not a DAVIS240C",
            "this toolkit drives the DAVIS240C (chip id 2) only",
        )
    return Finding(subject, "identity", Verdict.OK, text)


#: How long the DAVIS stream check waits for the first packet before it says "nothing" (s).
_DAVIS_FIRST_DATA_S = 10.0


def _davis_stream(subject: str, cam: Any, seconds: float) -> Finding:
    packets = events = frames = imu = 0
    cam.start()
    try:
        # ``seconds`` of streaming counted from the first packet: a camera (or a mock building
        # its world) may take a moment to start, which is not what this check measures.
        deadline = time.monotonic() + _DAVIS_FIRST_DATA_S
        started = False
        while time.monotonic() < deadline:
            pkt = cam.get_packet(timeout_s=0.1)
            if pkt is None:
                continue
            if not started:
                started = True
                deadline = time.monotonic() + seconds
            packets += 1
            events += int(pkt.events.size)
            frames += len(pkt.frames)
            imu += int(pkt.imu.size)
    finally:
        cam.stop()
    st = cam.stats()
    text = (
        f"{packets} packets: {events} events, {frames} frames, {imu} IMU samples in {seconds:g} s"
    )
    dropped = int(st.packets_dropped) + int(st.raw_bytes_dropped)
    device_drops = int(sum(cam.device_drop_counts().values()))
    if packets == 0:
        return Finding(
            subject,
            "stream",
            Verdict.FIX,
            text,
            "the camera delivers nothing: replug it; check `mocaprig davis info`",
        )
    if dropped or device_drops:
        return Finding(
            subject,
            "stream",
            Verdict.WARN,
            f"{text}; dropped: {st.packets_dropped} packets, {st.raw_bytes_dropped} raw "
            f"bytes on the host, {device_drops} events on the device",
            "give the DAVIS its own USB controller or lower the event rate (biases)",
        )
    return Finding(subject, "stream", Verdict.OK, text)


# -- D415 -----------------------------------------------------------------------------------------


def _d415_findings(*, mock: bool, faults: set[str], seconds: float) -> list[Finding]:
    from mocaprig.acquire.camera_backends import open_cameras
    from mocaprig.acquire.d415_sync import run_sync_check
    from mocaprig.acquire.realsense import MIN_SYNC_FIRMWARE

    if mock:
        opts: dict[str, Any] = {"seed": 0, "seconds": max(3.0, seconds + 1.0), "images": False}
        opts["faults"] = sorted(faults - {"no-metadata"})
        opts["metadata"] = "no-metadata" not in faults
        cameras = open_cameras("mock", **opts)
    else:
        cameras = open_cameras("realsense")
    if not cameras:
        return [
            Finding(
                "d415",
                "present",
                Verdict.WARN,
                "no D415 found",
                "plug the D415s into USB 3 ports (`rs-enumerate-devices` lists what the SDK sees)",
            )
        ]
    out: list[Finding] = []
    try:
        for cam in cameras:
            info = cam.info
            subject = f"d415/{info.serial}"
            fw = _version(info.firmware)
            if fw is None or fw < MIN_SYNC_FIRMWARE:
                out.append(
                    Finding(
                        subject,
                        "firmware",
                        Verdict.FIX,
                        f"firmware {info.firmware}",
                        "update to 5.9.15.1 or later for hardware sync "
                        "(rs-fw-update, Intel's D400 firmware page)",
                    )
                )
            else:
                out.append(Finding(subject, "firmware", Verdict.OK, f"firmware {info.firmware}"))
            if str(info.usb_type).startswith("3"):
                out.append(Finding(subject, "usb", Verdict.OK, f"USB {info.usb_type}"))
            else:
                out.append(
                    Finding(
                        subject,
                        "usb",
                        Verdict.FIX,
                        f"USB {info.usb_type or '?'} link",
                        "use a USB 3 port and cable: USB 2 limits the modes and the frame rate",
                    )
                )
        report = run_sync_check(cameras, seconds=seconds)
        for serial, cam_report in report.cameras.items():
            subject = f"d415/{serial}"
            if cam_report.timestamp_domain in _NO_METADATA:
                out.append(
                    Finding(
                        subject,
                        "metadata",
                        Verdict.FIX,
                        "frames carry no hardware timestamps",
                        _METADATA_FIX,
                    )
                )
            else:
                out.append(Finding(subject, "metadata", Verdict.OK, "hardware timestamps present"))
        out.append(_sync_finding(report, len(cameras)))
    except DeviceError as err:
        out.append(
            Finding(
                "d415 rig",
                "stream",
                Verdict.FIX,
                str(err),
                "check the cameras' USB cables and power, then run doctor again",
            )
        )
    finally:
        for cam in cameras:
            cam.close()
    return out


def _sync_finding(report: Any, n_cameras: int) -> Finding:
    if n_cameras < 2:
        return Finding("d415 rig", "sync", Verdict.OK, "one camera: nothing to synchronise")
    bad = {s: c for s, c in report.cameras.items() if not getattr(c, "ok", True)}
    flags = sorted({str(getattr(fl, "value", fl)) for c in bad.values() for fl in c.flags})
    blind = [s for s, c in report.cameras.items() if c.timestamp_domain in _NO_METADATA]
    if blind and not report.ok:
        return Finding(
            "d415 rig",
            "sync",
            Verdict.FIX,
            f"sync cannot be verified: {', '.join(sorted(blind))} deliver no hardware timestamps",
            _METADATA_FIX,
        )
    if report.ok:
        return Finding(
            "d415 rig",
            "sync",
            Verdict.OK,
            f"{n_cameras} cameras locked to the master over {report.duration_s:.1f} s",
        )
    return Finding(
        "d415 rig",
        "sync",
        Verdict.FIX,
        f"not synchronised: {', '.join(sorted(bad)) or 'the rig'} ({', '.join(flags) or 'failed'})",
        "check the sync cable from the master's pin 5 to every slave's pin 5 and the common "
        "ground on pin 9 (docs/wiring.md); `mocaprig d415 check-sync` shows each camera",
    )


def _no_metadata_domains() -> tuple[Any, ...]:
    from mocaprig.acquire.depth_camera import TimestampDomain

    return (None, TimestampDomain.SYSTEM_TIME)


_NO_METADATA: Final = _no_metadata_domains()


def _version(text: str) -> tuple[int, ...] | None:
    try:
        return tuple(int(p) for p in str(text).split("."))
    except ValueError:
        return None


# -- sync box -------------------------------------------------------------------------------------


def _syncbox_findings(*, mock: bool, faults: set[str], listen_s: float) -> list[Finding]:
    from mocaprig.acquire.syncbox import (
        PROTOCOL_VERSION,
        SyncBox,
        find_syncboxes,
        open_mock_syncbox,
    )

    if mock:
        opts: dict[str, Any] = {}
        if "no-reply" in faults:
            opts.update(fault="no-reply", fault_after_commands=1)
        if "unwired" in faults:
            opts["listen_hz"] = None
        with open_mock_syncbox(**opts) as box:
            return _one_syncbox(box.port, listen_s, PROTOCOL_VERSION, SyncBox)
    ports = find_syncboxes()
    if not ports:
        return [
            Finding(
                "syncbox",
                "present",
                Verdict.WARN,
                "no USB-serial port found",
                "plug the sync box in if the rig uses one (docs/wiring.md)",
            )
        ]
    out: list[Finding] = []
    for port in ports:
        out.extend(_one_syncbox(port, listen_s, PROTOCOL_VERSION, SyncBox))
    return out


def _one_syncbox(port: str, listen_s: float, protocol: int, box_cls: Any) -> list[Finding]:
    subject = f"syncbox {port}"
    try:
        with box_cls(port, boot_timeout_s=2.5, max_reopen=0) as box:
            ident = box.identity
            out = [
                Finding(
                    subject,
                    "protocol",
                    Verdict.OK,
                    f"protocol {ident.version}, board {ident.board}, features "
                    f"{' '.join(ident.features) or 'none'}",
                )
            ]
            box.set_report_interval(200)
            box.listen()
            time.sleep(listen_s)
            count = box.stop()
    except DeviceError as err:
        return [
            Finding(
                subject,
                "protocol",
                Verdict.FIX,
                str(err),
                f"flash firmware/syncbox/syncbox.ino (protocol {protocol}) and check the "
                "port; docs/syncbox-protocol.md",
            )
        ]
    rate = count / listen_s
    if count == 0:
        out.append(
            Finding(
                subject,
                "pulses",
                Verdict.FIX,
                f"LISTEN counted no pulse in {listen_s:g} s",
                "wire the master D415's sync output to the box's input (docs/wiring.md) "
                "and keep the cameras streaming",
            )
        )
    else:
        out.append(
            Finding(
                subject, "pulses", Verdict.OK, f"{count} pulses in {listen_s:g} s ({rate:.1f} Hz)"
            )
        )
    return out


# -- all ------------------------------------------------------------------------------------------


def run_doctor(
    *,
    mock: bool = False,
    faults: Sequence[str] = (),
    seconds: float = 2.0,
    listen_s: float = 1.0,
    on_finding: Callable[[Finding], None] | None = None,
) -> DoctorReport:
    """Run every check (module doc) and return the findings.

    Args:
        mock: Check the simulated rig instead of the devices plugged in (host checks stay real).
        faults: With ``mock``, faults to inject (:data:`DOCTOR_FAULTS`).
        seconds: Length of the DAVIS stream test and of the D415 sync check (camera time).
        listen_s: How long the sync box counts pulses in ``LISTEN`` (wall time).
        on_finding: Called with each finding as it is made (progress for a CLI).

    Raises:
        ValidationError: an unknown fault, or faults without ``mock``.
    """
    by_device = _parse_faults(faults, mock=mock)
    findings: list[Finding] = []
    lock = threading.Lock()

    def add(items: Sequence[Finding]) -> None:
        with lock:
            for f in items:
                findings.append(f)
                if on_finding is not None:
                    on_finding(f)

    libusb = check_libusb()
    add([libusb])
    if libusb.verdict is Verdict.FIX and not mock:
        add(
            [
                Finding(
                    "davis", "present", Verdict.FIX, "not checked: libusb is missing", _LIBUSB_FIX
                )
            ]
        )
    else:
        add(
            _guard(
                "davis",
                lambda: _davis_findings(
                    mock=mock, faults=by_device["davis"], seconds=min(seconds, 1.0)
                ),
            )
        )
    add(
        _guard("d415", lambda: _d415_findings(mock=mock, faults=by_device["d415"], seconds=seconds))
    )
    add(
        _guard(
            "syncbox",
            lambda: _syncbox_findings(mock=mock, faults=by_device["syncbox"], listen_s=listen_s),
        )
    )
    return DoctorReport(tuple(findings), mock=mock, faults=tuple(faults))


def _guard(subject: str, check: Callable[[], list[Finding]]) -> list[Finding]:
    """A check that cannot run (a library missing, a device error) is a finding, not a crash."""
    try:
        return check()
    except DeviceError as err:
        return [Finding(subject, "present", Verdict.FIX, str(err), _fix_for(str(err)))]
    except (ImportError, OSError, ValueError) as err:
        return [
            Finding(
                subject, "present", Verdict.FIX, f"{type(err).__name__}: {err}", _fix_for(str(err))
            )
        ]


def _fix_for(text: str) -> str:
    low = text.lower()
    if "libusb" in low or "backend" in low:
        return _LIBUSB_FIX
    if "pyrealsense2" in low:
        return "pip install 'mocaprig[realsense]' (pyrealsense2 2.59.1; needs libusb-1.0)"
    if "permission" in low:
        return "install the udev rules and replug the device (docs/wiring.md)"
    return "see the message; `mocaprig devices` lists what is plugged in"
