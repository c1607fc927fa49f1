"""Fuzz campaign over every reader of outside data (issue 17, item 4).

Each reader gets valid seed inputs, made by our writers and the mocks (and the real files of
``/work/shared/data`` when present, with ``--shared``), then mutated: truncation at every
structural boundary and at random points, bit flips, byte runs overwritten, inserted or
deleted, counts and sizes set to huge or negative values where the format has them (C3D header
and parameter words, MCAP record, string and chunk lengths, BVH channel and frame counts, CSV
header numbers, the checkpoint's config and tensors), wrong units, NaN/inf, empty files and
binary garbage. Each input is read once and classified:

- ``clean``: a :class:`mocaprig.errors.MocaprigError` whose message names the file (its path,
  its name, or the object read: the sync box's port) and says more than that;
- ``read``: the reader returned (``correct`` when a no-op mutation gave the seed's own result;
  ``accepted`` otherwise);
- ``crash``: any other exception, or a ``MocaprigError`` that does not name the file (the first
  few are printed with the mutation; ``--save-crashes DIR`` keeps the inputs);
- ``hang``: the read took longer than the reader's bound (``signal.setitimer`` in-process; the
  C3D reader runs its native decoder in a child process of its own with its own timeout);
- ``over_alloc``: the read's peak Python allocation (``tracemalloc``, numpy included) exceeded
  64 MiB + ``alloc_factor`` x the file size, or a child process the read waited for (the C3D
  reader's native decoder) set a new peak resident size above 384 MiB + ``alloc_factor`` x the
  file size. Process peak RSS growth is reported per reader too (it sees what tracemalloc does
  not: torch tensors, native code).

The sync box is fuzzed over its serial line (a pyserial URL handler ``fuzz://FILE`` that answers
each command with the next segment of the file, segments separated by ASCII RS, 0x1E), the
DAVIS decoder over its USB byte stream (decoded in the reader's 8 kB transfers); both inputs are
files too.

Usage: ``python benchmarks/fuzz_readers.py --inputs 200 [--readers bvh,c3d] [--seed 0]``.
Prints one line per reader (with one example input per kind of failure) and one JSON object as
its last line (``--json`` prints only it); ``--check`` makes any failure the exit status.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import dataclasses
import hashlib
import io
import json
import logging
import math
import os
import platform
import random
import re
import resource
import signal
import struct
import sys
import tempfile
import time
import traceback
import tracemalloc
import types
import zlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mocaprig.errors import MocaprigError

__all__ = [
    "READERS",
    "Mutation",
    "ReaderResult",
    "ReaderSpec",
    "mutations",
    "run_reader",
]

SHARED_DATA = Path("/work/shared/data")
MIB = 1 << 20
#: Hostile replacements for a number in a text format.
HOSTILE_NUMBERS: tuple[str, ...] = (
    "0",
    "-1",
    "-0",
    "1",
    "-2147483649",
    "2147483648",
    "4294967296",
    "9223372036854775808",
    "-9223372036854775809",
    "99999999999999999999999999",
    "1e308",
    "-1e308",
    "1e999",
    "1e-320",
    "nan",
    "NaN",
    "inf",
    "-inf",
    "Infinity",
    "0x10",
    "1_0",
    "",
    "--1",
    "1.2.3",
    "١٢",
    "1e",
)
#: A child decoder's resident size allowed before the file's share: its interpreter and
#: libraries (128 MiB) and the C3D child's address-space budget (256 MiB, c3d_decode).
_CHILD_RSS_BASE = 384 * 1024 * 1024
HOSTILE_INT16: tuple[int, ...] = (0, 1, -1, 2, 255, 256, 32767, -32768, 512, 4096)
HOSTILE_U64: tuple[int, ...] = (
    0,
    1,
    2**31,
    2**32 - 1,
    2**32,
    2**40,
    2**62,
    2**63 - 1,
    2**63,
    2**64 - 1,
)
HOSTILE_FLOATS: tuple[float, ...] = (
    math.nan,
    math.inf,
    -math.inf,
    0.0,
    -1.0,
    1e38,
    -1e38,
    1e-45,
    3.4e38,
)
_NUMBER = re.compile(rb"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


# ------------------------------------------------------------------------------ records


@dataclass(frozen=True, slots=True)
class Mutation:
    """One fuzz input: ``data`` (written to a file ending in ``suffix``) and how it was made."""

    name: str
    data: bytes = field(repr=False)
    suffix: str
    noop: bool = False


@dataclass(frozen=True, slots=True)
class Seed:
    """A valid input of a reader and its file suffix."""

    name: str
    data: bytes = field(repr=False)
    suffix: str


@dataclass(frozen=True, slots=True)
class ReaderSpec:
    """A reader under fuzz.

    Attributes:
        name: Short name (``--readers``).
        seeds: Valid inputs, written under the given folder if needed.
        read: Reads one file; returns a value comparable across reads (see :func:`canon`).
        boundaries: Structural cut points of a seed (record starts, lines, parameter entries).
        structured: One format-aware mutation of a seed (or None: fall back to a generic one).
        subjects: Strings of which a clean error message must contain one (default: the path
            and the file name).
        time_bound_s: A read longer than this is a hang.
        alloc_factor: Allowed peak allocation = 64 MiB + alloc_factor x file size.
    """

    name: str
    seeds: Callable[[Path], list[Seed]]
    read: Callable[[Path], object]
    boundaries: Callable[[bytes], list[int]]
    structured: Callable[[bytes, random.Random], tuple[str, bytes] | None]
    subjects: Callable[[Path], tuple[str, ...]] = lambda p: (str(p), p.name)
    time_bound_s: float = 5.0
    alloc_factor: int = 32


@dataclass(slots=True)
class ReaderResult:
    """What one reader did with its inputs (see the module doc for the classes)."""

    reader: str
    inputs: int = 0
    clean_errors: int = 0
    reads: int = 0
    correct: int = 0
    accepted: int = 0
    noop_mismatch: int = 0
    crashes: int = 0
    vague_errors: int = 0
    hangs: int = 0
    over_alloc: int = 0
    peak_alloc_bytes: int = 0
    rss_growth_kib: int = 0
    #: the largest child process so far (the C3D reader's isolated decoder), KiB
    child_peak_rss_kib: int = 0
    seconds: float = 0.0
    examples: list[str] = field(default_factory=list)
    #: failures by kind (``crash KeyError at bvh.py``...): how many inputs each
    kinds: dict[str, int] = field(default_factory=dict)

    @property
    def failures(self) -> int:
        """Crashes (vague errors included), hangs, over-allocations and wrong no-op reads."""
        return self.crashes + self.hangs + self.over_alloc + self.noop_mismatch

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready figures."""
        d = {k: v for k, v in dataclasses.asdict(self).items() if k != "examples"}
        d["seconds"] = round(self.seconds, 2)
        d["inputs_per_s"] = round(self.inputs / self.seconds, 2) if self.seconds else None
        d["examples"] = self.examples[:10]
        return d


# ------------------------------------------------------------------------------ helpers


def canon(x: object) -> object:
    """A hashable, NaN-safe digest of a reader's result (arrays by bytes, records by fields)."""
    if isinstance(x, np.ndarray):
        return ("ndarray", x.dtype.str, x.shape, np.ascontiguousarray(x).tobytes())
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return (type(x).__name__, *(canon(getattr(x, f.name)) for f in dataclasses.fields(x)))
    if isinstance(x, Mapping):
        return tuple(sorted((str(k), canon(v)) for k, v in x.items()))
    if isinstance(x, list | tuple):
        return tuple(canon(v) for v in x)
    if isinstance(x, float):
        return "nan" if math.isnan(x) else x
    if hasattr(x, "SerializeToString"):  # protobuf messages
        return bytes(x.SerializeToString())
    if hasattr(x, "detach"):  # torch tensors
        return canon(x.detach().cpu().numpy())
    return x


def digest(x: object) -> str:
    """Short hash of :func:`canon`."""
    return hashlib.sha256(repr(canon(x)).encode()).hexdigest()[:16]


def line_starts(data: bytes) -> list[int]:
    """Offsets just after each newline (and 0): the text formats' structural boundaries."""
    return [0, *(m.end() for m in re.finditer(rb"\n", data))]


def text_mutation(
    data: bytes, rng: random.Random, words: Sequence[bytes] = ()
) -> tuple[str, bytes]:
    """A number replaced by a hostile one, a ``words`` entry replaced by garbage, or a line
    deleted, duplicated, swapped or cut."""
    lines = data.split(b"\n")
    kind = rng.choice(
        (
            "number",
            "number",
            "number",
            "word",
            "line-del",
            "line-dup",
            "line-swap",
            "line-cut",
            "line-garbage",
        )
    )
    if kind == "number":
        nums = list(_NUMBER.finditer(data))
        if nums:
            m = rng.choice(nums)
            new = rng.choice(HOSTILE_NUMBERS).encode()
            return f"number@{m.start()} {m.group()!r}->{new!r}", data[: m.start()] + new + data[
                m.end() :
            ]
    if kind == "word" and words:
        present = [w for w in words if w in data]
        if present:
            w = rng.choice(present)
            at = [m.start() for m in re.finditer(re.escape(w), data)]
            pos = rng.choice(at)
            new = rng.choice((b"", b"X", w * 2, w.upper(), b"\xff\xfe", b"furlong", b"nan"))
            return f"word@{pos} {w!r}->{new!r}", data[:pos] + new + data[pos + len(w) :]
    i = rng.randrange(len(lines)) if lines else 0
    if kind == "line-del" and lines:
        return f"line-del {i}", b"\n".join(lines[:i] + lines[i + 1 :])
    if kind == "line-dup" and lines:
        return f"line-dup {i}", b"\n".join(lines[: i + 1] + lines[i:])
    if kind == "line-swap" and len(lines) > 1:
        j = rng.randrange(len(lines))
        lines[i], lines[j] = lines[j], lines[i]
        return f"line-swap {i} {j}", b"\n".join(lines)
    if kind == "line-cut" and lines and lines[i]:
        k = rng.randrange(len(lines[i]))
        lines[i] = lines[i][:k]
        return f"line-cut {i} at {k}", b"\n".join(lines)
    garbage = rng.randbytes(rng.randrange(1, 80))
    return f"line-garbage {i}", b"\n".join([*lines[:i], garbage, *lines[i:]])


def _generic(seed: bytes, rng: random.Random, boundaries: Sequence[int]) -> tuple[str, bytes, bool]:
    """One generic mutation: ``(name, data, noop)``."""
    n = len(seed)
    r = rng.random()
    if r < 0.03:
        return "noop", seed, True
    if r < 0.05:
        return "empty", b"", False
    if r < 0.10:
        size = rng.choice((1, 7, 64, 512, 4096, max(1, n)))
        head = seed[: rng.choice((0, 4, 8, 16))]
        body = head + rng.randbytes(size)
        return f"garbage {size} B after {len(head)} seed bytes", body, False
    if r < 0.25 and boundaries:
        cut = max(0, min(n, rng.choice(boundaries) + rng.choice((-1, 0, 0, 0, 1))))
        return f"cut@boundary {cut}/{n}", seed[:cut], False
    if r < 0.35:
        cut = rng.randrange(n + 1)
        return f"cut@{cut}/{n}", seed[:cut], False
    if r < 0.70 and n:
        buf = bytearray(seed)
        flips = [(rng.randrange(n), rng.randrange(8)) for _ in range(rng.choice((1, 1, 2, 4, 8)))]
        for pos, bit in flips:
            buf[pos] ^= 1 << bit
        return f"bitflip {flips}", bytes(buf), False
    if n:
        pos = rng.randrange(n)
        length = rng.choice((1, 2, 4, 8, 64, 512))
        op = rng.choice(("zero", "ff", "random", "insert", "delete", "duplicate"))
        if op == "zero":
            return f"zero {length}@{pos}", seed[:pos] + bytes(length) + seed[pos + length :], False
        if op == "ff":
            return f"ff {length}@{pos}", seed[:pos] + b"\xff" * length + seed[pos + length :], False
        if op == "random":
            junk = rng.randbytes(length)
            return f"random {length}@{pos}", seed[:pos] + junk + seed[pos + length :], False
        if op == "insert":
            junk = rng.randbytes(length)
            return f"insert {length}@{pos}", seed[:pos] + junk + seed[pos:], False
        if op == "delete":
            return f"delete {length}@{pos}", seed[:pos] + seed[pos + length :], False
        return f"duplicate {length}@{pos}", seed[: pos + length] + seed[pos:], False
    return "empty", b"", False


def mutations(spec: ReaderSpec, seeds: Sequence[Seed], n: int, seed: int) -> Iterator[Mutation]:
    """``n`` inputs: first every structural cut of every seed (at most a quarter of ``n``),
    then random mutations, about half of them format-aware."""
    rng = random.Random(seed)
    cuts = [(s, b) for s in seeds for b in spec.boundaries(s.data)]
    quota = min(len(cuts), n // 4)
    step = len(cuts) / quota if quota else 1.0
    for k in range(quota):
        s, b = cuts[int(k * step)]
        yield Mutation(
            f"{s.name}: cut@boundary {b}/{len(s.data)}", s.data[:b], s.suffix, b == len(s.data)
        )
    for _ in range(n - quota):
        s = rng.choice(seeds)
        if rng.random() < 0.5:
            got = spec.structured(s.data, rng)
            if got is not None:
                yield Mutation(f"{s.name}: {got[0]}", got[1], s.suffix, got[1] == s.data)
                continue
        name, data, _ = _generic(s.data, rng, spec.boundaries(s.data))
        yield Mutation(f"{s.name}: {name}", data, s.suffix, data == s.data)


class _Hang(BaseException):
    """Raised by the timer in a read that ran past its bound (not an Exception: readers that
    catch Exception must not swallow it)."""


def _on_alarm(signum: int, frame: types.FrameType | None) -> None:
    raise _Hang


def _names_subject(err: BaseException, subjects: Sequence[str]) -> bool:
    text = str(err)
    return any(s and s in text and len(text) >= len(s) + 15 for s in subjects)


def run_reader(
    spec: ReaderSpec,
    n: int,
    *,
    seed: int = 0,
    workdir: Path,
    extra_seeds: Sequence[Seed] = (),
    save_crashes: Path | None = None,
    max_seconds: float | None = None,
) -> ReaderResult:
    """Run ``n`` fuzz inputs through ``spec.read`` (stop early after ``max_seconds``)."""
    res = ReaderResult(spec.name)
    seed_dir = workdir / f"{spec.name}-seeds"
    seed_dir.mkdir(parents=True, exist_ok=True)
    seeds = [*spec.seeds(seed_dir), *extra_seeds]
    case = workdir / spec.name
    case.mkdir(exist_ok=True)
    expected: dict[bytes, str] = {}
    for s in seeds:  # read where the inputs will be: results may hold their path
        p = case / f"input{s.suffix}"
        p.write_bytes(s.data)
        expected[s.data] = digest(spec.read(p))  # a seed that does not read is a harness bug
    old = signal.signal(signal.SIGALRM, _on_alarm)
    started = tracemalloc.is_tracing()
    if not started:
        tracemalloc.start()
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    try:
        for k, mut in enumerate(mutations(spec, seeds, n, seed)):
            if max_seconds is not None and time.perf_counter() - t0 > max_seconds:
                break
            path = case / f"input{mut.suffix}"
            path.write_bytes(mut.data)
            res.inputs += 1
            tracemalloc.reset_peak()
            base = tracemalloc.get_traced_memory()[0]
            child0 = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
            verdict = ""
            signal.setitimer(signal.ITIMER_REAL, spec.time_bound_s)
            try:
                out = spec.read(path)
            except _Hang:
                verdict = "hang"
            except MocaprigError as err:
                signal.setitimer(signal.ITIMER_REAL, 0)
                if _names_subject(err, spec.subjects(path)):
                    res.clean_errors += 1
                else:
                    verdict = f"vague {type(err).__name__}: {err}"
            except Exception as err:  # the point of the campaign: anything else is a crash
                signal.setitimer(signal.ITIMER_REAL, 0)
                tb = traceback.extract_tb(err.__traceback__)[-1]
                where = f"{Path(tb.filename).name}:{tb.lineno}"
                verdict = f"crash {type(err).__name__} at {where}: {str(err)[:200]}"
            else:
                signal.setitimer(signal.ITIMER_REAL, 0)
                res.reads += 1
                if mut.noop:
                    if digest(out) == expected.get(mut.data):
                        res.correct += 1
                    else:
                        res.noop_mismatch += 1
                        verdict = "no-op mismatch: read differently from its seed"
                else:
                    res.accepted += 1
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
            peak = tracemalloc.get_traced_memory()[1] - base
            res.peak_alloc_bytes = max(res.peak_alloc_bytes, peak)
            # ru_maxrss (KiB on Linux) is the peak over every child waited for: a new peak
            # above the bound was set by this input's child.
            child = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
            child_bound = _CHILD_RSS_BASE + spec.alloc_factor * len(mut.data)
            if peak > 64 * MIB + spec.alloc_factor * len(mut.data):
                res.over_alloc += 1
                verdict = verdict or f"over-alloc: {peak / MIB:.0f} MiB for {len(mut.data)} B"
            elif child > child0 and child * 1024 > child_bound:
                res.over_alloc += 1
                verdict = verdict or (
                    f"over-alloc: child RSS {child / 1024:.0f} MiB for {len(mut.data)} B"
                )
            if verdict:
                if verdict == "hang":
                    res.hangs += 1
                elif verdict.startswith(("crash", "vague")):
                    res.crashes += 1
                    res.vague_errors += verdict.startswith("vague")
                kind = verdict.split(": ", 1)[0]  # "crash KeyError at x.py:12": one example each
                res.kinds[kind] = res.kinds.get(kind, 0) + 1
                if res.kinds[kind] == 1:
                    res.examples.append(f"[{spec.name} #{k}] {mut.name} -> {verdict}")
                if save_crashes is not None:
                    save_crashes.mkdir(parents=True, exist_ok=True)
                    (save_crashes / f"{spec.name}-{k}{mut.suffix}").write_bytes(mut.data)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
        if not started:
            tracemalloc.stop()
    res.seconds = time.perf_counter() - t0
    res.rss_growth_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0
    res.child_peak_rss_kib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return res


# ------------------------------------------------------------------------------ C3D


def _c3d_trajectories(seed: int, n_frames: int) -> Any:
    from mocaprig.calib.vicon_records import MarkerTrajectories

    rng = np.random.default_rng(seed)
    pos = rng.uniform(-1.0, 1.0, (n_frames, 3, 3))
    pos[3, 1] = np.nan
    res = rng.choice([0.0, 0.0005, 0.0012], size=(n_frames, 3))
    return MarkerTrajectories(("S:a", "S:b", "S:c"), 120.0, pos, res)


def _c3d_seeds(folder: Path) -> list[Seed]:
    from mocaprig.calib.c3d_write import write_c3d
    from mocaprig.calib.vicon_records import AnalogChannels

    rng = np.random.default_rng(7)
    analogs = AnalogChannels(("sync", "force"), 240.0, rng.normal(size=(24, 2)), ("V", "N"), 120.0)
    out = []
    for i, (unit, an) in enumerate((("mm", analogs), ("m", None))):
        p = write_c3d(folder / f"seed{i}.c3d", _c3d_trajectories(i, 12), unit=unit, analogs=an)  # type: ignore[arg-type]
        out.append(Seed(f"c3d seed{i}", p.read_bytes(), ".c3d"))
    return out


def _read_c3d(path: Path) -> object:
    from mocaprig.calib.c3d_read import read_c3d, read_c3d_analogs

    traj = read_c3d(path)
    try:
        analogs = read_c3d_analogs(path)
    except MocaprigError as err:
        if "analog" not in str(err).lower():
            raise
        analogs = None
    return (traj, analogs)


def _c3d_params(data: bytes) -> list[tuple[str, int, int]]:
    """``(field, offset, size)`` of the header words and every parameter entry's fields
    (Intel layout, as our writer makes it)."""
    out: list[tuple[str, int, int]] = [("header.param_block", 0, 1)]
    out += [(f"header.word{w}", 2 * w - 2, 2) for w in (2, 3, 4, 5, 6, 9, 10)]
    out += [("header.scale", 12, 4), ("header.rate", 20, 4)]
    if len(data) < 512 or not 1 <= data[0] <= len(data) // 512:
        return out
    start = (data[0] - 1) * 512
    out += [("param.blocks", start + 2, 1), ("param.processor", start + 3, 1)]
    pos = start + 4
    for _ in range(500):
        if pos + 2 > len(data):
            break
        n_name = abs(struct.unpack_from("<b", data, pos)[0])
        if n_name == 0:
            break
        gid = struct.unpack_from("<b", data, pos + 1)[0]
        out += [("entry.name_len", pos, 1), ("entry.group", pos + 1, 1)]
        off_at = pos + 2 + n_name
        if off_at + 2 > len(data):
            break
        nxt = struct.unpack_from("<h", data, off_at)[0]
        out.append(("entry.next", off_at, 2))
        if gid > 0 and off_at + 4 <= len(data):
            typ = struct.unpack_from("<b", data, off_at + 2)[0]
            ndim = data[off_at + 3]
            out += [("entry.type", off_at + 2, 1), ("entry.ndims", off_at + 3, 1)]
            out += [("entry.dim", off_at + 4 + d, 1) for d in range(ndim)]
            body = off_at + 4 + ndim
            if typ in (2, 4) and body + typ <= len(data):
                out.append((f"entry.value{typ}", body, typ))
        if nxt <= 0:
            break
        pos = off_at + nxt
    return out


def _c3d_boundaries(data: bytes) -> list[int]:
    return sorted({*range(0, len(data) + 1, 512), *(o for _, o, _ in _c3d_params(data))})


def _c3d_structured(data: bytes, rng: random.Random) -> tuple[str, bytes] | None:
    fields = _c3d_params(data)
    name, off, size = rng.choice(fields)
    if off + size > len(data):
        return None
    buf = bytearray(data)
    if size == 4 and (name in ("header.scale", "header.rate") or rng.random() < 0.5):
        v: float | int = rng.choice(HOSTILE_FLOATS)
        struct.pack_into("<f", buf, off, v)
    elif size == 4:
        v = rng.choice(HOSTILE_INT16)
        struct.pack_into("<i", buf, off, v)
    elif size == 2:
        v = rng.choice(HOSTILE_INT16)
        struct.pack_into("<h", buf, off, v)
    else:
        v = rng.choice((0, 1, 2, 3, 4, 83, 84, 85, 86, 127, 128, 255, -1 & 0xFF))
        buf[off] = v
    return f"{name}@{off}={v}", bytes(buf)


# ------------------------------------------------------------------------------ Nexus CSV


def _csv_seeds(folder: Path) -> list[Seed]:
    from mocaprig.drivers_mock.vicon import ViconCapture, write_nexus_csv

    rng = np.random.default_rng(3)
    pts = rng.uniform(-1, 1, (20, 3, 3))
    pts[4, 1] = np.nan
    cap = ViconCapture(
        labels=("S:a", "S:b", "clapper:TOP"),
        rate_hz=100.0,
        start_field=1,
        frame_t_ns=np.arange(20, dtype=np.int64) * 10_000_000,
        points_m=pts,
        residuals_mm=np.where(np.isnan(pts[..., 0]), -1.0, 0.5),
        clean_m=pts,
    )
    p = write_nexus_csv(cap, folder / "seed.csv")
    return [Seed("csv seed", p.read_bytes(), ".csv")]


def _read_csv(path: Path) -> object:
    from mocaprig.calib.nexus_csv import read_nexus_csv

    return read_nexus_csv(path)


def _csv_structured(data: bytes, rng: random.Random) -> tuple[str, bytes] | None:
    return text_mutation(data, rng, (b"mm", b"Trajectories", b"Frame", b"Sub Frame", b",", b"S:a"))


# ------------------------------------------------------------------------------ MCAP

_MCAP_MAGIC = b"\x89MCAP0\r\n"


def _mcap_seeds(folder: Path) -> list[Seed]:
    from mocaprig.acquire.events import make_events
    from mocaprig.acquire.recorder import Attachment, Recorder
    from mocaprig.acquire.recording_format import IMU_DTYPE, EventPacket, ImageMsg, ImuPacket, topic

    out = []
    for comp in ("none", "zstd", "lz4"):
        rng = np.random.default_rng(1)
        t = np.sort(rng.integers(0, 300_000, 600)).astype(np.int64)
        ev = make_events(t, rng.integers(0, 240, t.size), rng.integers(0, 180, t.size), t % 2)
        imu = np.zeros(10, IMU_DTYPE)
        imu["t"] = np.arange(10) * 1000
        path = folder / f"rec-{comp}.mcap"
        meta = {"rig": {"name": "lab-a"}, "device/davis/00000042": {"firmware": "18"}}
        att = [Attachment("calibration/davis.json", "application/json", b'{"k": 1}')]
        with Recorder(
            path,
            metadata=meta,
            attachments=att,
            chunk_size_bytes=4096,
            compression=comp,
            min_free_disk_bytes=0,
        ) as rec:
            he = rec.add_stream(topic("davis", "00000042", "events"), EventPacket)
            hi = rec.add_stream(topic("davis", "00000042", "imu"), ImuPacket)
            hf = rec.add_stream(topic("davis", "00000042", "frame"), ImageMsg)
            for i, lo in enumerate(range(0, 600, 100)):
                rec.put(
                    he,
                    EventPacket(ev[lo : lo + 100], seq=i),
                    log_time_ns=(i + 1) * 10**7,
                    sequence=i,
                )
            rec.put(hi, ImuPacket(imu, 0), log_time_ns=10**7, sequence=0)
            img = rng.integers(0, 1024, (18, 24)).astype(np.uint16)
            rec.put(hf, ImageMsg(img, "mono16", 1000), log_time_ns=2 * 10**7, sequence=0)
        out.append(Seed(f"recording ({comp})", path.read_bytes(), ".mcap"))
    return out


def _results_seeds(folder: Path) -> list[Seed]:
    from mocaprig.acquire.recorder import Recorder
    from mocaprig.acquire.recording_format import SceneUpdateMsg
    from mocaprig.process.scene import capsule_scene, points_scene

    rng = np.random.default_rng(2)
    path = folder / "results.mcap"
    with Recorder(
        path,
        metadata={"democap": {"checkpoint": "lite"}},
        compression="none",
        chunk_size_bytes=4096,
        min_free_disk_bytes=0,
    ) as rec:
        hj = rec.add_stream("/democap/joints", SceneUpdateMsg, metadata={"units": "m"})
        ht = rec.add_stream("/eventcap/template", SceneUpdateMsg, metadata={"units": "m"})
        for i in range(5):
            t = (i + 1) * 33_000_000
            pts = rng.uniform(-1, 1, (19, 3))
            rec.put(
                hj,
                points_scene(
                    "joints",
                    "world",
                    t,
                    pts,
                    0.03,
                    (1.0, 0.0, 0.0, 1.0),
                    {"k": "v"},
                    bones=[(0, 1), (1, 2)],
                ),
                log_time_ns=t,
                sequence=i,
            )
            a, b = rng.uniform(-1, 1, (4, 3)), rng.uniform(-1, 1, (4, 3))
            rec.put(
                ht,
                capsule_scene("template", "world", t, a, b, np.full(4, 0.05)),
                log_time_ns=t,
                sequence=i,
            )
    return [Seed("results (none)", path.read_bytes(), ".mcap")]


def _read_recording(path: Path) -> object:
    from mocaprig.acquire.recording import Recording, info

    with Recording(path) as r:
        msgs = [(m.topic, m.log_time_ns, m.sequence, canon(m.decode())) for m in r.messages()]
        got = (r.topics, r.metadata(), [(a.name, a.data) for a in r.attachments()], msgs)
    return (got, info(path).as_dict())


def _mcap_records(data: bytes) -> list[tuple[int, int, int]]:
    """``(offset, opcode, length)`` of each top-level record."""
    out = []
    pos = len(_MCAP_MAGIC)
    while pos + 9 <= len(data):
        op = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        out.append((pos, op, length))
        if pos + 9 + length > len(data):
            break
        pos += 9 + length
    return out


def _mcap_boundaries(data: bytes) -> list[int]:
    recs = _mcap_records(data)
    return sorted(
        {0, len(_MCAP_MAGIC), *(o for o, _, _ in recs), *(o + 9 for o, _, _ in recs), len(data)}
    )


def _mcap_structured(data: bytes, rng: random.Random) -> tuple[str, bytes] | None:
    recs = _mcap_records(data)
    if not recs:
        return None
    buf = bytearray(data)
    off, op, length = rng.choice(recs)
    kind = rng.choice(("length", "opcode", "field", "field", "payload", "payload"))
    if kind == "length":
        v = rng.choice((*HOSTILE_U64, length + 1, length - 1, len(data)))
        struct.pack_into("<Q", buf, off + 1, v & (2**64 - 1))
        return f"record {op:#x}@{off} length {length}->{v}", bytes(buf)
    if kind == "opcode":
        v = rng.randrange(256)
        buf[off] = v
        return f"record {op:#x}@{off} opcode->{v:#x}", bytes(buf)
    body = off + 9
    if kind == "field":
        # A length-like field inside the record: u32 string/map lengths and u64 sizes sit at
        # many places; pick an aligned spot in the first 64 bytes of the body.
        width = rng.choice((4, 8))
        at = body + rng.randrange(0, max(1, min(length, 64) - width + 1))
        if at + width > len(buf):
            return None
        v = rng.choice(HOSTILE_U64) & ((1 << (8 * width)) - 1)
        struct.pack_into("<I" if width == 4 else "<Q", buf, at, v)
        return f"record {op:#x}@{off} u{8 * width}@{at}->{v}", bytes(buf)
    # Payload bytes of an uncompressed chunk, with its CRC made right again: reaches the
    # message decoders behind the chunk's integrity check.
    chunks = [(o, ln) for o, code, ln in recs if code == 0x06]
    if not chunks:
        return None
    off, length = rng.choice(chunks)
    body = off + 9
    (clen,) = struct.unpack_from("<I", data, body + 28)
    comp = data[body + 32 : body + 32 + clen]
    rec_at = body + 32 + clen + 8
    end = off + 9 + length
    if comp != b"" or rec_at >= end:
        return None
    flips = [(rng.randrange(rec_at, end), rng.randrange(8)) for _ in range(rng.choice((1, 2, 4)))]
    for pos, bit in flips:
        buf[pos] ^= 1 << bit
    struct.pack_into("<I", buf, body + 24, zlib.crc32(bytes(buf[rec_at:end])))
    return f"chunk@{off} payload bitflip {flips} (crc fixed)", bytes(buf)


# ------------------------------------------------------------------------------ BVH


def _bvh_seeds(folder: Path) -> list[Seed]:
    from mocaprig.process.body.bvh_export import bvh_text
    from mocaprig.process.body.shape import BodyShape
    from mocaprig.process.body.skeleton import POSE_DIM

    rng = np.random.default_rng(4)
    poses = rng.normal(scale=0.2, size=(6, POSE_DIM))
    poses[:, 2] += 1.0
    text = bvh_text(poses, BodyShape.from_height(1.75), rate_hz=60.0)
    return [Seed("bvh seed", text.encode(), ".bvh")]


def _read_bvh(path: Path) -> object:
    from mocaprig.process.body.bvh import read_bvh

    return read_bvh(path)


def _bvh_structured(data: bytes, rng: random.Random) -> tuple[str, bytes] | None:
    r = rng.random()
    if r < 0.4:
        key = rng.choice((rb"CHANNELS (\d+)", rb"Frames:\s*(\d+)", rb"Frame Time:\s*(\S+)"))
        found = list(re.finditer(key, data))
        if found:
            m = rng.choice(found)
            new = rng.choice(HOSTILE_NUMBERS).encode()
            return (
                f"{key.split(b' ')[0].decode()}@{m.start(1)} {m.group(1)!r}->{new!r}",
                data[: m.start(1)] + new + data[m.end(1) :],
            )
    words = (
        b"ROOT",
        b"JOINT",
        b"End Site",
        b"OFFSET",
        b"CHANNELS",
        b"{",
        b"}",
        b"MOTION",
        b"Xrotation",
        b"Zposition",
        b"HIERARCHY",
    )
    return text_mutation(data, rng, words)


# ------------------------------------------------------------------------------ RPG text


def _rpg_seeds(folder: Path) -> list[Seed]:
    from mocaprig.acquire.events import make_events
    from mocaprig.acquire.rpg_text import export_events_txt

    rng = np.random.default_rng(5)
    t = np.sort(rng.integers(0, 1_000_000, 200))
    ev = make_events(t, rng.integers(0, 240, 200), rng.integers(0, 180, 200), t % 2)
    out = []
    for i, t_ns in enumerate((None, t * 1000 + rng.integers(0, 1000, 200))):
        buf = io.StringIO()
        export_events_txt(ev, buf, header=(240, 180), t_ns=t_ns)
        out.append(Seed(f"rpg seed{i}", buf.getvalue().encode(), ".txt"))
    return out


def _read_rpg(path: Path) -> object:
    from mocaprig.acquire.rpg_text import read_events_txt

    return read_events_txt(path)


def _rpg_structured(data: bytes, rng: random.Random) -> tuple[str, bytes] | None:
    return text_mutation(data, rng, (b" ", b"\n", b"."))


# ------------------------------------------------------------------------------ rig file

_RIG = b"""format_version = 1
mock = false

[session]
name = "lab-a 2025-03-02"
notes = "walk + jumps, subject S03"

[[d415]]
serial = "819612070593"
role = "master"
mode = "848x480@30"
exposure_us = 8500
gain = 16
laser_power_mw = 150
emitter = true

[[d415]]
serial = "819612070311"
role = "slave"

[davis]
serial = "02460045"
bias_preset = "default"

[syncbox]
port = "/dev/ttyACM0"
mode = "generate"
rate_hz = 30
width_us = 100
"""


def _rig_seeds(folder: Path) -> list[Seed]:
    return [Seed("rig seed", _RIG, ".toml")]


def _read_rig(path: Path) -> object:
    from mocaprig.acquire.rig_file import load_rig_file

    return load_rig_file(path)


def _toml_structured(data: bytes, rng: random.Random) -> tuple[str, bytes] | None:
    if rng.random() < 0.4:
        found = list(re.finditer(rb"= (.+)\n", data))
        if found:
            m = rng.choice(found)
            new = rng.choice(
                (
                    b"-1",
                    b"0",
                    b"1e999",
                    b"nan",
                    b"inf",
                    b"-inf",
                    b"9223372036854775807",
                    b"[]",
                    b"{}",
                    b'"x"',
                    b"true",
                    b"[1, 2]",
                    b'"\xff"',
                    b"1979-05-27",
                    b'"' + b"9" * 40 + b'"',
                    b"{a = 1}",
                    b'"\\u0000"',
                )
            )
            return f"value@{m.start(1)} {m.group(1)!r}->{new!r}", data[: m.start(1)] + new + data[
                m.end(1) :
            ]
    return text_mutation(data, rng, (b"[[d415]]", b"[davis]", b"[syncbox]", b"=", b'"'))


# ------------------------------------------------------------------------------ calibration


def _calibration_seeds(folder: Path) -> list[Seed]:
    from mocaprig.calib.calibration import (
        Calibration,
        CameraCalibration,
        ClockMapping,
        calibration_bytes,
    )

    rng = np.random.default_rng(6)
    cams = []
    for i, serial in enumerate(("123", "456")):
        t = np.eye(4)
        t[:3, 3] = rng.uniform(-4, 4, 3)
        k = np.array([[615.0, 0, 424.5], [0, 615.0, 239.5], [0, 0, 1]])
        cams.append(
            CameraCalibration(
                f"d415/{serial}",
                "d415",
                serial,
                848,
                480,
                k,
                np.zeros(5),
                t,
                residuals={"rms_px": 0.2 + i},
            )
        )
    cal = Calibration(
        cameras=tuple(cams),
        clocks=(
            ClockMapping(
                "d415/123",
                "vicon",
                offset_ns=-5_000_123,
                drift_ppm=12.5,
                anchor_ns=10**12,
                offset_sigma_ns=80.0,
                method="clap+xcorr",
            ),
            ClockMapping("davis/0246", "vicon", offset_ns=42, method="pulses"),
        ),
        statistics={"cameras": 2},
        software_version="0.1.0",
    )
    return [
        Seed("calibration toml", calibration_bytes(cal, fmt="toml"), ".toml"),
        Seed("calibration json", calibration_bytes(cal, fmt="json"), ".json"),
    ]


def _read_calibration(path: Path) -> object:
    from mocaprig.calib.calibration import read_calibration

    return read_calibration(path)


def _calibration_structured(data: bytes, rng: random.Random) -> tuple[str, bytes] | None:
    if data.lstrip().startswith(b"{") and rng.random() < 0.5:
        found = list(re.finditer(rb'": ([^,\n\]}]+)', data))
        if found:
            m = rng.choice(found)
            new = rng.choice(
                (
                    b"-1",
                    b"NaN",
                    b"Infinity",
                    b"-Infinity",
                    b"1e999",
                    b"[]",
                    b"{}",
                    b'"x"',
                    b"null",
                    b"[[1]]",
                    b"99999999999999999999999",
                )
            )
            return f"json value@{m.start(1)} ->{new!r}", data[: m.start(1)] + new + data[m.end(1) :]
    return _toml_structured(data, rng)


# ------------------------------------------------------------------------------ checkpoint


def _checkpoint_seeds(folder: Path) -> list[Seed]:
    import torch

    from mocaprig.process.body import DEMOCAP_JOINTS, MARKER_NAMES
    from mocaprig.process.democap.checkpoint import Checkpoint, save_checkpoint
    from mocaprig.process.democap.config import DemocapConfig
    from mocaprig.process.democap.model import build_network

    torch.manual_seed(0)
    cfg = DemocapConfig(
        name="tiny",
        input_px=64,
        stem_channels=8,
        feature_channels=8,
        width=4,
        stage_branches=(2,),
        stage_modules=(1,),
        stage_units=(1,),
        batch_size=4,
        samples_per_epoch=8,
    )
    model = build_network(cfg, num_markers=len(MARKER_NAMES), num_joints=len(DEMOCAP_JOINTS))
    path = folder / "tiny.pt"
    save_checkpoint(Checkpoint(cfg, model, epoch=3, seed=1, history=[{"loss": 0.5}]), path)
    return [Seed("checkpoint tiny", path.read_bytes(), ".pt")]


def _read_checkpoint(path: Path) -> object:
    from mocaprig.process.democap.checkpoint import load_checkpoint

    ck = load_checkpoint(path)
    return (ck.config.to_dict(), ck.epoch, ck.seed, ck.history, ck.model.state_dict())


def _zip_boundaries(data: bytes) -> list[int]:
    marks = (b"PK\x03\x04", b"PK\x01\x02", b"PK\x05\x06")
    return sorted(
        {0, len(data), *(m.start() for k in marks for m in re.finditer(re.escape(k), data))}
    )


_HOSTILE_OBJECTS: tuple[object, ...] = (
    None,
    -1,
    0,
    10**12,
    -(10**12),
    math.nan,
    math.inf,
    "x",
    [],
    {},
    [1, 2],
    {"a": 1},
    True,
    2**62,
)


def _checkpoint_structured(data: bytes, rng: random.Random) -> tuple[str, bytes] | None:
    import torch

    ckpt = _checkpoint_dict(data)
    d = copy.deepcopy(ckpt)
    where = rng.choice(("top", "config", "config", "tensor", "tensor", "names"))
    if where == "top":
        key = rng.choice(sorted(d))
        val = rng.choice(_HOSTILE_OBJECTS)
        d[key] = val
        what = f"{key}={val!r}"
    elif where == "config":
        key = rng.choice(sorted(d["config"]))
        val = rng.choice((*_HOSTILE_OBJECTS, 10**6, 4096, (10**6,), (2, 2, 2, 2), "relu"))
        if rng.random() < 0.15:
            del d["config"][key]
            what = f"config.{key} removed"
        else:
            d["config"][key] = val
            what = f"config.{key}={val!r}"
    elif where == "tensor":
        key = rng.choice(sorted(d["model"]))
        t = d["model"][key]
        op = rng.choice(("nan", "inf", "shape", "drop", "dtype", "huge-shape", "empty"))
        if op == "nan" and t.is_floating_point():
            d["model"][key] = torch.full_like(t, math.nan)
        elif op == "inf" and t.is_floating_point():
            d["model"][key] = torch.full_like(t, math.inf)
        elif op == "shape":
            d["model"][key] = t.reshape(-1)[: max(0, t.numel() - 1)]
        elif op == "drop":
            del d["model"][key]
        elif op == "dtype":
            d["model"][key] = t.to(torch.int64)
        elif op == "huge-shape":
            d["model"][key] = torch.zeros(1).expand(1 << 20, 1 << 20)
        else:
            d["model"][key] = torch.empty(0)
        what = f"model[{key}] {op}"
    else:
        key = rng.choice(("marker_names", "joint_names"))
        d[key] = d[key][: rng.randrange(len(d[key]))] + rng.choice(([], ["x"], [None], [1]))
        what = f"{key} changed"
    buf = io.BytesIO()
    torch.save(d, buf)
    return what, buf.getvalue()


_CKPT_CACHE: dict[bytes, dict[str, Any]] = {}


def _checkpoint_dict(data: bytes) -> dict[str, Any]:
    key = hashlib.sha256(data).digest()
    if key not in _CKPT_CACHE:
        import torch

        _CKPT_CACHE[key] = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    return _CKPT_CACHE[key]


# ------------------------------------------------------------------------------ sync box


class _ScriptedPort:
    """The far side of a serial line: each command line written is answered with the next
    segment of the script file (segments separated by 0x1E)."""

    def __init__(self, path: str) -> None:
        self._segments = Path(path).read_bytes().split(b"\x1e")
        self._out = bytearray()
        self._in = b""

    def write(self, data: bytes) -> int:
        self._in += data
        while b"\n" in self._in:
            _, self._in = self._in.split(b"\n", 1)
            if self._segments:
                self._out += self._segments.pop(0)
        return len(data)

    def read(self, size: int) -> bytes:
        if not self._out:
            time.sleep(0.001)
            return b""
        got = bytes(self._out[:size])
        del self._out[:size]
        return got

    @property
    def waiting(self) -> int:
        return len(self._out)


def _install_fuzz_url() -> None:
    """Register the ``fuzz://FILE`` pyserial URL (pyserial's own protocol-handler lookup)."""
    import serial
    from serial.serialutil import SerialBase

    if "mocaprig_fuzz_serial.protocol_fuzz" in sys.modules:
        return

    class Serial(SerialBase):  # type: ignore[misc]
        def open(self) -> None:
            self._port_obj = _ScriptedPort(self.portstr.split("://", 1)[1])
            self.is_open = True

        def close(self) -> None:
            self.is_open = False

        def _reconfigure_port(self) -> None:
            pass

        @property
        def in_waiting(self) -> int:
            return self._port_obj.waiting

        def read(self, size: int = 1) -> bytes:
            return self._port_obj.read(size)

        def write(self, data: bytes) -> int:
            return self._port_obj.write(bytes(data))

        def flush(self) -> None:
            pass

    pkg = types.ModuleType("mocaprig_fuzz_serial")
    pkg.__path__ = []
    mod = types.ModuleType("mocaprig_fuzz_serial.protocol_fuzz")
    mod.Serial = Serial  # type: ignore[attr-defined]
    sys.modules["mocaprig_fuzz_serial"] = pkg
    sys.modules["mocaprig_fuzz_serial.protocol_fuzz"] = mod
    serial.protocol_handler_packages.append("mocaprig_fuzz_serial")


_SYNCBOX_SCRIPT = b"\x1e".join(
    (
        b"MOCAPRIG-SYNCBOX 1 uno toggle\r\n",  # HELLO
        b"STATUS IDLE 30 100 0 123456\r\n",  # STATUS
        # START 30 100, then reports (the last one after a u32 wrap of the box clock)
        (
            b"PULSES 0 100\r\nOK START 30 100\r\nPULSES 30 1000100\r\nPULSES 60 4294967000\r\n"
            b"PULSES 90 703\r\n"
        ),
        b"STATUS GENERATE 30 100 90 1000\r\n",  # STATUS
        b"OK STOP 91\r\n",  # STOP
    )
)


def _syncbox_seeds(folder: Path) -> list[Seed]:
    return [Seed("syncbox session", _SYNCBOX_SCRIPT, ".serial")]


def _read_syncbox(path: Path) -> object:
    from mocaprig.acquire import syncbox

    _install_fuzz_url()
    # The wait for a quiet line after the banner is real time (0.15 s an input); the parsing
    # under test does not depend on it.
    setattr(syncbox, "SETTLE_S", 0.0)  # noqa: B010
    logging.getLogger(syncbox.__name__).setLevel(logging.ERROR)
    with syncbox.SyncBox(
        f"fuzz://{path}", timeout_s=0.02, boot_timeout_s=0.05, max_reopen=0
    ) as box:
        s1 = box.status()
        box.start(hz=30, width_us=100)
        reports = [(r.count, r.total, r.t_us) for r in box.read_reports(0.0)]
        s2 = box.status()
        n = box.stop()
        return (box.identity, s1, reports, s2, n)


def _syncbox_structured(data: bytes, rng: random.Random) -> tuple[str, bytes] | None:
    r = rng.random()
    if r < 0.15:
        pos = rng.randrange(len(data) + 1)
        junk = rng.choice(
            (
                b"x" * 2000,
                rng.randbytes(300),
                b"PULSES 5 10\r\n" * 50,
                b"\r" * 100,
                b"ERR\r\n",
                b"ERR x y z\r\n",
                b"MOCAPRIG-SYNCBOX\r\n",
                b"MOCAPRIG-SYNCBOX 1\r\n",
            )
        )
        return f"insert {len(junk)} B@{pos}", data[:pos] + junk + data[pos:]
    return text_mutation(
        data, rng, (b"OK", b"PULSES", b"STATUS", b"GENERATE", b"\r\n", b"\x1e", b"MOCAPRIG-SYNCBOX")
    )


def _syncbox_subjects(path: Path) -> tuple[str, ...]:
    return (f"fuzz://{path}",)


# ------------------------------------------------------------------------------ DAVIS words


def _davis_seeds(folder: Path) -> list[Seed]:
    from mocaprig.acquire.events import make_events
    from mocaprig.drivers_mock.davis240c_encoder import encode_stream
    from mocaprig.drivers_mock.davis_activity import IMU_DTYPE, ApsExposure, DavisActivity

    rng = np.random.default_rng(8)
    t = np.sort(rng.integers(0, 70_000, 400))
    ev = make_events(t, rng.integers(0, 240, t.size), rng.integers(0, 180, t.size), t % 2)
    imu = np.zeros(3, IMU_DTYPE)
    imu["t"] = [5_000, 25_000, 45_000]
    exp = ApsExposure(20_000, 24_000, rng.uniform(0, 1023, (180, 240)))
    plain = DavisActivity(t0_us=0, t1_us=70_000, events=ev, imu=imu)
    framed = DavisActivity(t0_us=0, t1_us=70_000, events=ev, exposures=(exp,), imu=imu)
    return [
        Seed("davis events+imu", encode_stream([plain], seed=1), ".bin"),
        Seed("davis events+imu+frame", encode_stream([framed], seed=1), ".bin"),
    ]


def _read_davis(path: Path) -> object:
    from mocaprig.acquire.davis240c_decode import DavisDecoder

    data = path.read_bytes()
    dec = DavisDecoder()
    packets = [dec.decode(data[i : i + 8192]) for i in range(0, len(data), 8192)]
    return (
        [
            (p.events, p.imu, p.specials, [(f.t_us, f.pixels_16bit) for f in p.frames])
            for p in packets
        ],
        dec.stats.as_dict(),
    )


def _davis_boundaries(data: bytes) -> list[int]:
    return sorted({0, len(data), *range(1, len(data), 4093), *range(8192, len(data), 8192)})


def _davis_structured(data: bytes, rng: random.Random) -> tuple[str, bytes] | None:
    words = np.frombuffer(data[: len(data) // 2 * 2], "<u2").copy()
    if words.size == 0:
        return None
    hostile = (
        0x0000,
        0x0001,
        0x0008,
        0x0009,
        0x000A,
        0x000B,
        0x000C,
        0x000D,
        0x000E,
        0x000F,
        0x0005,
        0x0007,
        0x1FFF,
        0x10B3,
        0x2FFF,
        0x3FFF,
        0x4FFF,
        0x5000,
        0x51FF,
        0x52FF,
        0x53FF,
        0x5FFF,
        0x6FFF,
        0x7FFF,
        0x7001,
        0x8000,
        0xFFFF,
    )
    k = rng.choice((1, 2, 8, 64))
    at = [rng.randrange(words.size) for _ in range(k)]
    vals = [rng.choice(hostile) for _ in range(k)]
    op = rng.choice(("set", "insert"))
    if op == "set":
        words[at] = vals
        out = words.tobytes()
    else:
        w = words.tolist()
        for a, v in sorted(zip(at, vals, strict=True), reverse=True):
            w.insert(a, v)
        out = np.asarray(w, "<u2").tobytes()
    return f"words {op} {list(zip(at, [hex(v) for v in vals], strict=True))[:8]}", out


def _davis_subjects(path: Path) -> tuple[str, ...]:
    return (str(path), "DAVIS", "davis")


# ------------------------------------------------------------------------------ registry


def _shared_seeds(name: str) -> list[Seed]:
    """Real files of ``/work/shared/data`` for a reader (none when absent)."""
    files = {
        "c3d": ("vicon/nexus24_markers_analogs.c3d",),
        "nexus-csv": ("vicon/nexus24_markers.csv",),
        "bvh": ("motion/cmu_131_01_scaled.bvh",),
    }.get(name, ())
    return [
        Seed(f"shared {f}", (SHARED_DATA / f).read_bytes(), Path(f).suffix)
        for f in files
        if (SHARED_DATA / f).is_file()
    ]


READERS: dict[str, ReaderSpec] = {
    s.name: s
    for s in (
        ReaderSpec(
            "c3d", _c3d_seeds, _read_c3d, _c3d_boundaries, _c3d_structured, time_bound_s=60.0
        ),
        ReaderSpec("nexus-csv", _csv_seeds, _read_csv, line_starts, _csv_structured),
        ReaderSpec(
            "mcap-recording",
            _mcap_seeds,
            _read_recording,
            _mcap_boundaries,
            _mcap_structured,
            alloc_factor=256,
        ),
        ReaderSpec(
            "mcap-results",
            _results_seeds,
            _read_recording,
            _mcap_boundaries,
            _mcap_structured,
            alloc_factor=256,
        ),
        ReaderSpec("bvh", _bvh_seeds, _read_bvh, line_starts, _bvh_structured),
        ReaderSpec("rpg-text", _rpg_seeds, _read_rpg, line_starts, _rpg_structured),
        ReaderSpec("rig-file", _rig_seeds, _read_rig, line_starts, _toml_structured),
        ReaderSpec(
            "calibration",
            _calibration_seeds,
            _read_calibration,
            line_starts,
            _calibration_structured,
        ),
        ReaderSpec(
            "checkpoint",
            _checkpoint_seeds,
            _read_checkpoint,
            _zip_boundaries,
            _checkpoint_structured,
            time_bound_s=20.0,
        ),
        ReaderSpec(
            "syncbox",
            _syncbox_seeds,
            _read_syncbox,
            line_starts,
            _syncbox_structured,
            subjects=_syncbox_subjects,
        ),
        ReaderSpec(
            "davis-words",
            _davis_seeds,
            _read_davis,
            _davis_boundaries,
            _davis_structured,
            subjects=_davis_subjects,
        ),
    )
}


def main(argv: Sequence[str] | None = None) -> int:
    """Run the campaign; with ``--check``, exit 1 when any reader crashed, hung or
    over-allocated."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--inputs", type=int, default=200, help="inputs per reader (default 200)")
    ap.add_argument("--readers", default=",".join(READERS), help="comma-separated reader names")
    ap.add_argument("--seed", type=int, default=0, help="RNG seed of the mutations")
    ap.add_argument("--shared", action="store_true", help=f"add the real files of {SHARED_DATA}")
    ap.add_argument("--max-seconds", type=float, default=None, help="stop a reader after this")
    ap.add_argument("--save-crashes", type=Path, default=None, help="keep crashing inputs here")
    ap.add_argument("--json", action="store_true", help="print only the JSON line")
    ap.add_argument("--check", action="store_true", help="exit 1 on any crash, hang, over-alloc")
    args = ap.parse_args(argv)
    names = [n.strip() for n in args.readers.split(",") if n.strip()]
    unknown = [n for n in names if n not in READERS]
    if unknown:
        ap.error(f"unknown reader(s) {unknown}; known: {', '.join(READERS)}")
    logging.basicConfig(level=logging.CRITICAL)  # readers log warnings on every bad input
    results = []
    with tempfile.TemporaryDirectory(prefix="fuzz-readers-") as tmp:
        for name in names:
            spec = READERS[name]
            extra = _shared_seeds(name) if args.shared else []
            r = run_reader(
                spec,
                args.inputs,
                seed=args.seed,
                workdir=Path(tmp),
                extra_seeds=extra,
                save_crashes=args.save_crashes,
                max_seconds=args.max_seconds,
            )
            results.append(r)
            if not args.json:
                print(
                    f"{name:15s} inputs {r.inputs:6d}  clean errors {r.clean_errors:6d}  reads "
                    f"{r.reads:6d} (correct {r.correct}, accepted {r.accepted})  crashes "
                    f"{r.crashes:4d}  hangs {r.hangs}  over-alloc {r.over_alloc}  peak alloc "
                    f"{r.peak_alloc_bytes / MIB:7.1f} MiB  RSS +{r.rss_growth_kib / 1024:.0f} MiB  "
                    f"{r.seconds:7.1f} s ({r.inputs / max(r.seconds, 1e-9):.1f}/s)"
                )
                for ex in r.examples[:10]:
                    print("    " + ex)
    print(
        json.dumps(
            {
                "inputs_per_reader": args.inputs,
                "seed": args.seed,
                "readers": {r.reader: r.as_dict() for r in results},
                "total_failures": sum(r.failures for r in results),
                "cpus": os.cpu_count(),
                "python": platform.python_version(),
            }
        )
    )
    return 1 if args.check and any(r.failures for r in results) else 0


if __name__ == "__main__":
    with contextlib.suppress(BrokenPipeError):
        sys.exit(main())
