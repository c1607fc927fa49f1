"""RPG events text files (``t x y p`` lines, t in s): read, write, import into a recording.

The format of the RPG event-camera dataset (``events.txt``): one event a line, the time in
seconds with up to 9 decimals (ns), an optional ``width height`` first line.
:func:`read_events_txt` parses the times exactly to the ns, :func:`export_events_txt` writes them
back, and :func:`import_events_txt` stores a file's events in a new recording.
"""

from __future__ import annotations

import dataclasses
import decimal
import io
import itertools
from collections.abc import Callable
from pathlib import Path
from typing import TextIO

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.events import check_events, make_events
from mocaprig.acquire.recorder import Recorder
from mocaprig.acquire.recording_format import MAX_EVENT_PACKET_SPAN_US, EventPacket, topic
from mocaprig.errors import RecordingError, ValidationError
from mocaprig.validation import check_range

__all__ = [
    "ImportedEvents",
    "RpgEventText",
    "export_events_txt",
    "import_events_txt",
    "read_events_txt",
]


@dataclasses.dataclass(frozen=True, slots=True, eq=False)
class RpgEventText:
    """What :func:`read_events_txt` read from an RPG events text file.

    Attributes:
        events: :data:`~acquire.events.EVENT_DTYPE`, file order; ``t`` (µs) is ``t_ns // 1000``
            (floor).
        t_ns: The times exactly as written (int64 ns), same order as ``events``.
        width: From the optional ``width height`` first line, else ``None``.
        height: As ``width``.
    """

    events: npt.NDArray[np.void] = dataclasses.field(repr=False)
    t_ns: npt.NDArray[np.int64] = dataclasses.field(repr=False)
    width: int | None
    height: int | None


def export_events_txt(
    events: npt.NDArray[np.void],
    out: TextIO,
    *,
    t_ns: npt.NDArray[np.int64] | None = None,
    header: tuple[int, int] | None = None,
) -> None:
    """Write events as RPG ``t x y p`` lines, t in s with 9 decimals (``0.000011001 158 145 1``).

    Times come from ``t_ns`` (exact ns, same order as ``events``) when given, else from
    ``events["t"]`` (µs, so the last three decimals are ``000``). ``header=(width, height)``
    writes that first line (E2VID-style tools want it); the RPG dataset's ``events.txt`` has
    none, so by default there is none. Negative times get a leading ``-``.

    Raises:
        ValidationError: ``t_ns`` does not have one entry per event.
    """
    ev = check_events(events)
    if t_ns is None:
        t = ev["t"].astype(np.int64) * 1000
    else:
        t = np.asarray(t_ns, dtype=np.int64)
        if t.shape != ev.shape:
            msg = f"t_ns has shape {t.shape}, events {ev.shape}; give one ns time per event"
            raise ValidationError(msg)
    if header is not None:
        out.write(f"{header[0]} {header[1]}\n")
    a = np.abs(t)
    lines = "".join(
        [
            f"{s}{sec}.{ns:09d} {x} {y} {p}\n"
            for s, sec, ns, x, y, p in zip(
                np.where(t < 0, "-", "").tolist(),
                (a // 1_000_000_000).tolist(),
                (a % 1_000_000_000).tolist(),
                ev["x"].tolist(),
                ev["y"].tolist(),
                ev["p"].tolist(),
                strict=True,
            )
        ]
    )
    out.write(lines)


def read_events_txt(path: Path) -> RpgEventText:
    """Read an RPG events text file: ``t x y p`` per line, t in s; the first line may be
    ``width height``; blank lines and ``#`` comments are skipped.

    Times are parsed exactly to the ns (decimal digits, no float): ``0.000011001`` is 11001 ns.
    Digits beyond the 9th decimal must be zeros (a finer time cannot be represented; the line is
    refused rather than silently rounded). Exponent notation (``1.5e-3``) is accepted and parsed
    exactly too. Negative times are read as such (``import-events`` refuses them).

    Raises:
        RecordingError: the file cannot be read, is not ASCII text, or has a malformed line or
            a time finer than 1 ns (its line number is given).
    """
    try:
        data = path.read_bytes()
    except OSError as err:
        msg = f"cannot read {path}: {err.strerror or err}; check the path"
        raise RecordingError(msg) from err
    fast = _read_events_txt_fast(data)
    if fast is not None:
        return fast
    return _read_events_txt_lines(path, data)


def _read_events_txt_fast(data: bytes) -> RpgEventText | None:
    """Vectorised reading of the plain layout (``T X Y P``, single spaces, T as ``digits`` or
    ``digits.digits`` with at most 9 decimals); ``None`` for anything else, which
    :func:`_read_events_txt_lines` then reads (or reports) line by line. Same result as it."""
    lines = data.splitlines()
    width = height = None
    if lines and not lines[0].startswith(b"#") and len(first := lines[0].split()) == 2:
        if not (first[0].isdigit() and first[1].isdigit()):
            return None
        width, height = int(first[0]), int(first[1])
        lines = lines[1:]
    if b"#" in data or b"" in lines:
        lines = [ln for ln in lines if ln and not ln.startswith(b"#")]
    arr = np.array(lines, dtype=np.bytes_)
    if arr.size == 0:
        return None
    if not (np.strings.count(arr, b" ") == 3).all():
        return None
    t, _, rest = np.strings.partition(arr, b" ")
    x, _, rest = np.strings.partition(rest, b" ")
    y, _, p = np.strings.partition(rest, b" ")
    if not all(bool(np.strings.isdigit(c).all()) for c in (x, y, p)):
        return None
    dot = np.strings.find(t, b".")
    n_frac = np.where(dot < 0, 0, np.strings.str_len(t) - dot - 1)
    digits = np.strings.replace(t, b".", b"", 1)
    if (
        not bool(np.strings.isdigit(digits).all())
        or int(n_frac.max()) > 9
        or int((np.strings.str_len(digits) + 9 - n_frac).max()) > 18
        or (x.dtype.itemsize > 18 or y.dtype.itemsize > 18 or p.dtype.itemsize > 18)
    ):
        return None
    t_ns = _digits_to_int(digits) * 10 ** (9 - n_frac).astype(np.int64)
    x_i, y_i, p_i = (_digits_to_int(c) for c in (x, y, p))
    if int(x_i.max()) >= 2**16 or int(y_i.max()) >= 2**16:
        return None
    return RpgEventText(make_events(t_ns // 1000, x_i, y_i, p_i), t_ns, width, height)


def _digits_to_int(col: npt.NDArray[np.bytes_]) -> npt.NDArray[np.int64]:
    """int64 values of a fixed-width bytes array of 1..18 ASCII digits (checked by the caller);
    digit arithmetic on the byte matrix, much faster than ``astype(np.int64)``."""
    width = col.dtype.itemsize
    m = np.ascontiguousarray(col).view(np.uint8).reshape(col.size, width)
    n_digits = np.strings.str_len(col)
    value = np.zeros(col.size, np.int64)
    for j in range(width):
        value = np.where(j < n_digits, value * 10 + (m[:, j].astype(np.int64) - 48), value)
    return value


def _read_events_txt_lines(path: Path, data: bytes | None = None) -> RpgEventText:
    if data is None:
        data = path.read_bytes()
    width = height = None
    ts: list[int] = []
    xs: list[int] = []
    ys: list[int] = []
    ps: list[int] = []
    try:
        text = data.decode("ascii")
    except UnicodeDecodeError as err:
        lineno = data.count(b"\n", 0, err.start) + 1
        msg = (
            f"{path}:{lineno}: byte {data[err.start]:#04x} is not ASCII; an RPG events file is "
            "plain 't x y p' text: is it the right file?"
        )
        raise RecordingError(msg) from err
    for lineno, line in enumerate(io.StringIO(text, newline=None), 1):
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        try:
            if lineno == 1 and len(tok) == 2:
                width, height = int(tok[0]), int(tok[1])
                continue
            if len(tok) != 4:
                bad = f"expected 4 columns, got {len(tok)}"
                raise ValueError(bad)
            ts.append(_seconds_to_ns(tok[0]))
            xs.append(_coordinate(tok[1], "x"))
            ys.append(_coordinate(tok[2], "y"))
            ps.append(int(tok[3]))
        except ValueError as err:
            msg = (
                f"{path}:{lineno}: not an RPG event line ('t x y p', t in s with at most 9 "
                f"decimals): {line.strip()!r} ({err}); fix or remove that line"
            )
            raise RecordingError(msg) from err
    t_ns = np.asarray(ts, dtype=np.int64)
    return RpgEventText(make_events(t_ns // 1000, xs, ys, ps), t_ns, width, height)


def _coordinate(text: str, name: str) -> int:
    """A pixel coordinate as the event dtype holds it (uint16)."""
    v = int(text)
    if not 0 <= v < 2**16:
        bad = f"{name} = {v} is not a pixel coordinate (0..65535)"
        raise ValueError(bad)
    return v


def _seconds_to_ns(text: str) -> int:
    """Exact ns of a decimal seconds string (``-0.000011001`` -> -11001)."""
    neg = text.startswith("-")
    body = text[1:] if text[:1] in "+-" else text
    whole, _, frac = body.partition(".")
    if (whole.isdigit() and (frac.isdigit() or not frac)) or (not whole and frac.isdigit()):
        if len(frac) > 9:
            if frac[9:].strip("0"):
                bad = f"time {text} has digits beyond 9 decimals (finer than 1 ns)"
                raise ValueError(bad)
            frac = frac[:9]
        ns = int(whole or "0") * 1_000_000_000 + int(frac.ljust(9, "0") if frac else "0")
    else:  # exponent form, exact (a precision that holds every digit)
        ctx = decimal.Context(prec=len(body) + 9, traps=[decimal.InvalidOperation])
        try:
            if "_" in body:
                raise decimal.InvalidOperation
            d = ctx.scaleb(ctx.create_decimal(body), 9)
        except ArithmeticError as err:
            bad = f"time {text!r} is not a decimal number of seconds"
            raise ValueError(bad) from err
        if not d.is_finite() or d != d.to_integral_value():
            bad = f"time {text} is not a whole number of ns"
            raise ValueError(bad)
        ns = int(d)
    if ns >= 2**63:
        bad = f"time {text} is beyond the int64 ns range"
        raise ValueError(bad)
    return -ns if neg else ns


#: The largest log_time an import writes (ns): MCAP stores u64, the readers' numpy int64.
_MAX_LOG_TIME_NS = (1 << 63) - 1


@dataclasses.dataclass(frozen=True, slots=True)
class ImportedEvents:
    """What :func:`import_events_txt` stored.

    Attributes:
        events: Events imported.
        packets: Event packets written.
        width: Sensor width given to the packets (argument, else the file's header, else 240).
        height: As ``width`` (default 180).
    """

    events: int
    packets: int
    width: int
    height: int


def import_events_txt(
    src: Path,
    out: Path,
    *,
    width: int | None,
    height: int | None,
    serial: str = "imported",
    packet_us: int = 10_000,
    epoch_ns: int = 0,
    progress: Callable[[int, int], None] | None = None,
) -> ImportedEvents:
    """Store the events of an RPG events text file ``src`` in a new recording ``out``
    (``progress(packets_written, packets)`` as they are written).

    Events go to ``/davis/<serial>/events`` in packets of ``packet_us``, with their exact ns
    times (:attr:`EventPacket.t_ns`), so ``export --format txt`` gives the same lines back.

    One clock for the whole file: there is no host receive time, so every message's
    ``log_time`` — the packets' (their first event's time) and the recorder's own
    ``/diagnostics``, ``/log`` and summary times — is on the file's time base shifted by
    ``epoch_ns``: ``log_time = epoch_ns + t_ns``. With the default 0 that is the file's own
    time (ns since its t = 0); pass the Unix time of the file's t = 0 to put the recording on
    Unix time. The ``import`` metadata record states the epoch (``epoch_ns``).

    Raises:
        ValidationError: ``packet_us`` or ``epoch_ns`` out of range.
        RecordingError: a malformed line, events outside ``width`` x ``height``, negative
            times, times that overflow the clock after the epoch shift, or ``out`` cannot be
            written.
    """
    check_range(packet_us, 1, MAX_EVENT_PACKET_SPAN_US, name="packet_us")
    check_range(epoch_ns, 0, _MAX_LOG_TIME_NS, name="epoch_ns")
    txt = read_events_txt(src)
    events, t_ns = txt.events, txt.t_ns
    w = width if width is not None else (txt.width if txt.width is not None else 240)
    h = height if height is not None else (txt.height if txt.height is not None else 180)
    if events.size and (int(events["x"].max()) >= w or int(events["y"].max()) >= h):
        msg = f"{src}: events fall outside {w}x{h}; pass --width/--height"
        raise RecordingError(msg)
    if events.size and int(t_ns.min()) < 0:
        msg = f"{src}: negative timestamps cannot be stored (the mono encoding needs t >= 0)"
        raise RecordingError(msg)
    if events.size and epoch_ns + int(t_ns.max()) > _MAX_LOG_TIME_NS:
        msg = (
            f"{src}: the last event time {int(t_ns.max())} ns plus the epoch {epoch_ns} ns "
            "overflows the recording clock (int64 ns); pass a smaller --epoch-ns"
        )
        raise RecordingError(msg)
    # The recorder's own messages are stamped on the events' clock (the time of the packet
    # being written), so the file has one time base.
    now = [epoch_ns + (int(t_ns[0]) if events.size else 0)]
    rec = Recorder(
        out,
        compression="zstd",
        queue_messages=1 << 30,
        queue_bytes=1 << 62,
        min_free_disk_bytes=0,
        metadata={"import": {"source": src.name, "format": "rpg-txt", "width": str(w),
                             "height": str(h), "epoch_ns": str(epoch_ns),
                             "log_time": "epoch_ns + the file's time (ns)"}},
        clock_ns=lambda: now[0],
    )  # fmt: skip
    frame_id = f"davis_{serial}"
    n = 0
    with rec:
        hd = rec.add_stream(
            topic("davis", serial, "events"), EventPacket, metadata={"serial": serial}
        )
        if events.size:
            # Runs of one packet_us bin: each spans < packet_us µs <= 2**32 ns (one packet).
            bins = (t_ns - t_ns[0]) // (packet_us * 1000)
            edges = [0, *(np.flatnonzero(np.diff(bins)) + 1).tolist(), events.size]
            for lo, hi in itertools.pairwise(edges):
                if progress is not None:
                    progress(n, len(edges) - 1)
                now[0] = epoch_ns + int(t_ns[lo])
                ok = rec.put(
                    hd,
                    EventPacket(events[lo:hi], w, h, n, frame_id, t_ns=t_ns[lo:hi]),
                    log_time_ns=now[0],
                    sequence=n,
                )
                if not ok:
                    msg = f"importing {src}: a packet was dropped; this is a bug, report it"
                    raise RecordingError(msg)
                n += 1
            if progress is not None:
                progress(n, len(edges) - 1)
    return ImportedEvents(events=int(events.size), packets=n, width=w, height=h)
