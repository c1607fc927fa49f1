#!/usr/bin/env python3
"""Build the sync box firmware for an Arduino Uno/Nano without the Arduino IDE, and measure it.

Uses only the Debian/Ubuntu packages ``gcc-avr``, ``binutils-avr``, ``avr-libc`` and
``arduino-core-avr`` (the Arduino AVR core in ``/usr/share/arduino/hardware/arduino/avr``), with
the compiler flags of that core's ``platform.txt`` (``-Os -flto``, as the IDE builds) plus
``-Wall -Wextra -Werror`` for the sketch::

    python3 firmware/syncbox/build.py --out build/firmware            # uno and nano
    python3 firmware/syncbox/build.py --out build/firmware --board uno --latency

Each board gives ``<out>/<board>/syncbox.elf`` and ``syncbox.hex`` (flash it with
``avrdude -p m328p -c arduino -P /dev/ttyACM0 -b 115200 -U flash:w:syncbox.hex:i``; Nano with
the old bootloader: ``-b 57600``). ``--latency`` prints the cycle counts of the pulse interrupts
read from the disassembly (docs/syncbox-protocol.md, "Latency"). Standard library only; the tests
(tests/firmware/) import it by path.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import os
import re
import shutil
import subprocess
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

SKETCH = Path(__file__).resolve().parent / "syncbox.ino"
CORE_ROOT = Path(os.environ.get("ARDUINO_AVR_CORE", "/usr/share/arduino/hardware/arduino/avr"))
TOOLS = ("avr-gcc", "avr-g++", "avr-gcc-ar", "avr-objcopy", "avr-size", "avr-nm", "avr-objdump")
#: The Debian packages that provide TOOLS and CORE_ROOT.
DEBIAN_PACKAGES = ("gcc-avr", "binutils-avr", "avr-libc", "arduino-core-avr")
F_CPU = 16_000_000
ARDUINO_VERSION = "10807"  # the core's version (1.8.7), as the IDE passes it


@dataclass(frozen=True)
class Board:
    """One board of the core's boards.txt."""

    name: str
    define: str  # ARDUINO_<define>, e.g. AVR_UNO
    variant: str
    mcu: str
    flash_max: int  # bytes the bootloader leaves for the sketch
    ram_max: int


# Fallbacks when boards.txt cannot be read; read_boards() prefers the installed file.
_DEFAULT_BOARDS = {
    "uno": Board("uno", "AVR_UNO", "standard", "atmega328p", 32256, 2048),
    "nano": Board("nano", "AVR_NANO", "eightanaloginputs", "atmega328p", 30720, 2048),
}
# boards.txt key prefix of the properties of each board (the Nano's default CPU menu entry).
_BOARD_KEYS = {"uno": ("uno.", "uno."), "nano": ("nano.", "nano.menu.cpu.atmega328.")}


def missing_tools() -> list[str]:
    """What of the toolchain is absent here (tool names, the core folder); empty = ready."""
    missing = [t for t in TOOLS if shutil.which(t) is None]
    if not (CORE_ROOT / "cores" / "arduino" / "Arduino.h").is_file():
        missing.append(f"Arduino AVR core ({CORE_ROOT})")
    return missing


def read_boards() -> dict[str, Board]:
    """Uno and Nano as the installed core's boards.txt defines them."""
    path = CORE_ROOT / "boards.txt"
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return dict(_DEFAULT_BOARDS)
    props: dict[str, str] = {}
    for raw in text.splitlines():
        line = raw.strip()
        if line and not line.startswith("#") and "=" in line:
            key, value = line.split("=", 1)
            props[key.strip()] = value.strip()
    boards: dict[str, Board] = {}
    for name, default in _DEFAULT_BOARDS.items():
        base, cpu = _BOARD_KEYS[name]

        def get(key: str, fallback: str, base: str = base, cpu: str = cpu) -> str:
            return props.get(cpu + key, props.get(base + key, fallback))

        boards[name] = Board(
            name=name,
            define=get("build.board", default.define),
            variant=get("build.variant", default.variant),
            mcu=get("build.mcu", default.mcu),
            flash_max=int(get("upload.maximum_size", str(default.flash_max))),
            ram_max=int(get("upload.maximum_data_size", str(default.ram_max))),
        )
    return boards


@dataclass
class BuildResult:
    """One board's build."""

    board: str
    elf: Path
    hex: Path
    flash_bytes: int  # .text + .data
    ram_bytes: int  # .data + .bss (static; the stack comes on top)
    flash_max: int
    ram_max: int
    warnings: list[str] = field(default_factory=list)


class BuildError(RuntimeError):
    """A compiler or linker step failed; the message holds its command and output."""


def _run(cmd: list[str], cwd: Path | None = None) -> str:
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        msg = f"{' '.join(cmd)}\nexit {proc.returncode}\n{proc.stdout}{proc.stderr}"
        raise BuildError(msg)
    return proc.stdout + proc.stderr


def _common_flags(board: Board) -> list[str]:
    return [
        f"-mmcu={board.mcu}",
        f"-DF_CPU={F_CPU}L",
        f"-DARDUINO={ARDUINO_VERSION}",
        f"-DARDUINO_{board.define}",
        "-DARDUINO_ARCH_AVR",
        f"-I{CORE_ROOT / 'cores' / 'arduino'}",
        f"-I{CORE_ROOT / 'variants' / board.variant}",
    ]


# platform.txt's compiler.{c,cpp,S}.flags (less -MMD).
_C_FLAGS = ["-c", "-g", "-Os", "-std=gnu11", "-ffunction-sections", "-fdata-sections"]
_C_FLAGS += ["-flto", "-fno-fat-lto-objects"]
_CXX_FLAGS = ["-c", "-g", "-Os", "-std=gnu++11", "-fpermissive", "-fno-exceptions"]
_CXX_FLAGS += ["-ffunction-sections", "-fdata-sections", "-fno-threadsafe-statics"]
_CXX_FLAGS += ["-Wno-error=narrowing", "-flto"]
# gcc-avr 5.4's <float.h> lacks DECIMAL_DIG in C++ (WString.cpp needs it); gcc >= 6 defines it
# with these very tokens, so the definition is harmless there.
_CORE_CXX_FLAGS = ["-DDECIMAL_DIG=__DECIMAL_DIG__"]
_S_FLAGS = ["-c", "-g", "-x", "assembler-with-cpp", "-flto"]
_LINK_FLAGS = ["-Os", "-g", "-flto", "-fuse-linker-plugin", "-Wl,--gc-sections"]
# The sketch is held to more than the IDE's default (no warnings at all): every warning fails.
STRICT = ["-Wall", "-Wextra", "-Werror"]


def _compile_core(board: Board, obj_dir: Path) -> Path:
    """The Arduino core as a static library (the core's own code at the IDE's warning level)."""
    obj_dir.mkdir(parents=True, exist_ok=True)
    core_src = CORE_ROOT / "cores" / "arduino"
    jobs: list[list[str]] = []
    objects: list[Path] = []
    for src in sorted(core_src.iterdir()):
        if src.suffix not in (".c", ".cpp", ".S"):
            continue
        obj = obj_dir / (src.name + ".o")
        objects.append(obj)
        if src.suffix == ".c":
            cmd = ["avr-gcc", *_C_FLAGS]
        elif src.suffix == ".cpp":
            cmd = ["avr-g++", *_CXX_FLAGS, *_CORE_CXX_FLAGS]
        else:
            cmd = ["avr-gcc", *_S_FLAGS]
        jobs.append([*cmd, *_common_flags(board), str(src), "-o", str(obj)])
    workers = min(8, os.cpu_count() or 1)
    with concurrent.futures.ThreadPoolExecutor(max_workers=workers) as pool:
        list(pool.map(_run, jobs))
    archive = obj_dir / "core.a"
    archive.unlink(missing_ok=True)
    _run(["avr-gcc-ar", "rcs", str(archive), *map(str, objects)])
    return archive


def build(board_name: str, out_dir: Path, sketch: Path = SKETCH) -> BuildResult:
    """Compile and link ``sketch`` for one board into ``out_dir/<board>/``.

    Raises:
        BuildError: a step failed (with ``-Werror``, any warning in the sketch, compile or link).
        KeyError: unknown board.
    """
    board = read_boards()[board_name]
    work = out_dir / board.name
    work.mkdir(parents=True, exist_ok=True)
    core = _compile_core(board, work / "core")
    sketch_obj = work / "syncbox.ino.o"
    warnings = _run(
        [
            "avr-g++",
            *_CXX_FLAGS,
            *STRICT,
            *_common_flags(board),
            "-x",
            "c++",
            str(sketch),
            "-o",
            str(sketch_obj),
        ]
    )
    elf = work / "syncbox.elf"
    warnings += _run(
        [
            "avr-gcc",
            *_LINK_FLAGS,
            *STRICT,
            f"-mmcu={board.mcu}",
            "-o",
            str(elf),
            str(sketch_obj),
            str(core),
            "-lm",
        ]
    )
    hex_path = work / "syncbox.hex"
    _run(["avr-objcopy", "-O", "ihex", "-R", ".eeprom", str(elf), str(hex_path)])
    sizes = _section_sizes(elf)
    return BuildResult(
        board=board.name,
        elf=elf,
        hex=hex_path,
        flash_bytes=sizes.get(".text", 0) + sizes.get(".data", 0),
        ram_bytes=sizes.get(".data", 0) + sizes.get(".bss", 0) + sizes.get(".noinit", 0),
        flash_max=board.flash_max,
        ram_max=board.ram_max,
        warnings=[w for w in warnings.splitlines() if w.strip()],
    )


def _section_sizes(elf: Path) -> dict[str, int]:
    sizes: dict[str, int] = {}
    for line in _run(["avr-size", "-A", str(elf)]).splitlines():
        parts = line.split()
        if len(parts) >= 2 and parts[0].startswith(".") and parts[1].isdigit():
            sizes[parts[0]] = int(parts[1])
    return sizes


# -- the pulse interrupts, read from the binary ------------------------------------------------

#: Vector numbers (ATmega328P): INT0 = 1 (LISTEN, D2 edge), TIMER1_OVF = 13 (GENERATE).
PULSE_VECTORS = {"INT0": 1, "TIMER1_OVF": 13}
#: The other interrupts the core runs (they delay a pulse interrupt that arrives meanwhile).
OTHER_VECTORS = {"TIMER0_OVF (millis)": 16, "USART_RX": 18, "USART_UDRE": 19}
PINB_IO = 0x03  # I/O address of PINB: a write of 1 to bit 2 flips D10
#: ATmega328P datasheet, "Interrupt Response Time": 4 cycles minimum from the request to the
#: vector (the PC pushed, I cleared), after the instruction in progress completes.
INTERRUPT_RESPONSE_CYCLES = 4

# Cycles per instruction on the ATmega328P (AVRe+ core, 16-bit PC; datasheet "Instruction Set
# Summary"). Branches: (not taken, taken); skips: (no skip, skip of a 1-word instruction,
# skip of a 2-word one).
_CYCLES = {
    "push": 2, "pop": 2, "in": 1, "out": 1, "sbi": 2, "cbi": 2, "ldi": 1, "lds": 2, "sts": 2,
    "ld": 2, "ldd": 2, "st": 2, "std": 2, "lpm": 3, "mov": 1, "movw": 1, "clr": 1, "eor": 1,
    "and": 1, "andi": 1, "or": 1, "ori": 1, "com": 1, "neg": 1, "inc": 1, "dec": 1, "add": 1,
    "adc": 1, "adiw": 2, "sub": 1, "subi": 1, "sbc": 1, "sbci": 1, "sbiw": 2, "cp": 1, "cpc": 1,
    "cpi": 1, "tst": 1, "lsl": 1, "lsr": 1, "rol": 1, "ror": 1, "asr": 1, "swap": 1, "bst": 1,
    "bld": 1, "ser": 1, "mul": 2, "muls": 2, "mulsu": 2, "fmul": 2, "cli": 1, "sei": 1, "nop": 1,
    "rjmp": 2, "jmp": 3, "ijmp": 2, "rcall": 3, "call": 4, "icall": 3, "ret": 4, "reti": 4,
    "sbr": 1, "cbr": 1, "sec": 1, "clc": 1, "sen": 1, "cln": 1, "sez": 1, "clz": 1, "wdr": 1,
}  # fmt: skip
_BRANCH = re.compile(r"^br[a-z]{2}$")
_SKIP = {"sbrc", "sbrs", "sbic", "sbis", "cpse"}


@dataclass(frozen=True)
class Insn:
    """One disassembled instruction."""

    addr: int
    size: int  # bytes
    op: str
    args: str


def disassemble(elf: Path) -> dict[str, list[Insn]]:
    """``avr-objdump -d``: instructions per function symbol."""
    funcs: dict[str, list[Insn]] = {}
    current: list[Insn] | None = None
    head = re.compile(r"^([0-9a-f]+) <([^>]+)>:$")
    line_re = re.compile(r"^\s*([0-9a-f]+):\s+((?:[0-9a-f]{2} )+)\s*([a-z]+)\s*([^;]*)")
    for line in _run(["avr-objdump", "-d", str(elf)]).splitlines():
        m = head.match(line)
        if m:
            current = funcs.setdefault(m.group(2), [])
            continue
        m = line_re.match(line)
        if m and current is not None:
            nbytes = len(m.group(2).split())
            current.append(Insn(int(m.group(1), 16), nbytes, m.group(3), m.group(4).strip()))
    return funcs


def symbols(elf: Path) -> dict[str, int]:
    """Function/object symbol → address (``avr-nm``)."""
    out: dict[str, int] = {}
    for line in _run(["avr-nm", str(elf)]).splitlines():
        parts = line.split()
        if len(parts) == 3:
            out[parts[2]] = int(parts[0], 16)
    return out


def _cycles(insn: Insn, worst: bool) -> int:
    if _BRANCH.match(insn.op):
        return 2 if worst else 1
    if insn.op in _SKIP:
        return 3 if worst else 1
    if insn.op not in _CYCLES:
        msg = f"no cycle count for {insn.op!r} at {insn.addr:#x}: extend _CYCLES"
        raise BuildError(msg)
    return _CYCLES[insn.op]


@dataclass(frozen=True)
class PulseIsr:
    """What the binary says about one pulse interrupt."""

    vector: str
    symbol: str
    address: int
    vector_jump_cycles: int  # the vector table's jmp to the handler
    cycles_to_toggle: int  # handler instructions up to and including the PINB write
    toggle_insn: str
    first_insn: str


def _toggles_d10(insn: Insn) -> bool:
    args = [a.strip() for a in insn.args.split(",")]
    if insn.op == "sbi" and len(args) == 2:
        return int(args[0], 0) == PINB_IO and int(args[1], 0) == 2
    return insn.op == "out" and int(args[0], 0) == PINB_IO


def pulse_isrs(elf: Path) -> dict[str, PulseIsr]:
    """Each pulse vector's handler and the cycles from its entry to the D10 (PINB) write.

    The handler must run straight (no branch) to that write, as the firmware's does.

    Raises:
        BuildError: a handler is missing, or does not write PINB before any branch.
    """
    funcs = disassemble(elf)
    vectors = funcs.get("__vectors", [])
    out: dict[str, PulseIsr] = {}
    for name, num in PULSE_VECTORS.items():
        sym = f"__vector_{num}"
        insns = funcs.get(sym)
        if not insns:
            msg = f"{sym} ({name}) is not a function of its own in {elf}"
            raise BuildError(msg)
        entry = next((i for i in vectors if i.addr == num * 4), None)
        if entry is None or entry.op != "jmp" or int(entry.args.split()[0], 16) != insns[0].addr:
            msg = f"the vector table's entry {num} does not jump to {sym}: {entry}"
            raise BuildError(msg)
        cycles = 0
        for insn in insns:
            if _BRANCH.match(insn.op) or insn.op in _SKIP or insn.op in ("call", "rcall", "jmp"):
                msg = f"{sym}: {insn.op} at {insn.addr:#x} comes before the D10 write"
                raise BuildError(msg)
            cycles += _cycles(insn, worst=True)
            if _toggles_d10(insn):
                break
        else:
            msg = f"{sym} never writes PINB (the D10 toggle)"
            raise BuildError(msg)
        out[name] = PulseIsr(
            vector=name,
            symbol=sym,
            address=insns[0].addr,
            vector_jump_cycles=_cycles(entry, worst=True),
            cycles_to_toggle=cycles,
            toggle_insn=f"{insn.op} {insn.args}",
            first_insn=f"{insns[0].op} {insns[0].args}",
        )
    return out


def _worst_cycles(funcs: dict[str, list[Insn]], name: str, depth: int = 0) -> int:
    """Upper bound on the cycles of one run of function ``name`` up to its ``ret``/``reti``.

    Every instruction counted once at its worst (branch taken, skip skipping a 2-word
    instruction), and each ``call`` as its 4 cycles plus the callee's bound: an upper bound
    because the code has no loop (checked: no backward branch or jump) and no indirect call.

    Raises:
        BuildError: a loop, an indirect call, or a callee that is not a known function.
    """
    insns = funcs.get(name)
    if not insns or depth > 4:
        msg = f"cannot bound {name}: not a function here, or calls nested too deep"
        raise BuildError(msg)
    by_addr = {i[0].addr: n for n, i in funcs.items() if i}
    total = 0
    for insn in insns:
        rel = re.match(r"\.([+-]\d+)", insn.args)
        if (rel is not None and int(rel.group(1)) < 0) or insn.op in ("icall", "ijmp"):
            msg = f"{name} loops or calls indirectly at {insn.addr:#x}: no simple bound"
            raise BuildError(msg)
        if insn.op in ("call", "rcall"):
            target = int(insn.args.split()[0], 16)
            if target not in by_addr:
                msg = f"{name} calls {target:#x}, not the start of a known function"
                raise BuildError(msg)
            total += _cycles(insn, worst=True) + _worst_cycles(funcs, by_addr[target], depth + 1)
        else:
            total += _cycles(insn, worst=True)
    return total


def max_isr_cycles(elf: Path) -> dict[str, int]:
    """Upper bound on how long each of the core's other interrupts keeps the CPU (cycles).

    From the request to the ``reti``: the response (4), the vector's ``jmp`` (3) and the
    handler's bound (:func:`_worst_cycles`). A pulse interrupt requested meanwhile waits that
    long, plus one main-program instruction after the ``reti`` (datasheet).

    Raises:
        BuildError: a handler's run time has no simple bound (loop, indirect call).
    """
    funcs = disassemble(elf)
    out: dict[str, int] = {}
    for name, num in OTHER_VECTORS.items():
        sym = f"__vector_{num}"
        if sym in funcs:  # else not linked in
            out[name] = INTERRUPT_RESPONSE_CYCLES + 3 + _worst_cycles(funcs, sym)
    return out


def main(argv: list[str] | None = None) -> int:
    """Command line (module doc)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("build/firmware"))
    parser.add_argument("--board", choices=sorted(_DEFAULT_BOARDS), action="append")
    parser.add_argument("--latency", action="store_true", help="print the ISR cycle counts")
    args = parser.parse_args(argv)
    missing = missing_tools()
    if missing:
        sys.stderr.write(
            f"missing: {', '.join(missing)}; install the Debian packages "
            f"{' '.join(DEBIAN_PACKAGES)} (apt-get install)\n"
        )
        return 2
    report: dict[str, object] = {}
    for name in args.board or sorted(_DEFAULT_BOARDS):
        try:
            res = build(name, args.out)
        except BuildError as err:
            sys.stderr.write(f"{name}: build failed:\n{err}\n")
            return 1
        entry: dict[str, object] = {
            k: str(v) if isinstance(v, Path) else v for k, v in asdict(res).items()
        }
        if args.latency:
            entry["pulse_isrs"] = {k: asdict(v) for k, v in pulse_isrs(res.elf).items()}
            entry["other_isr_max_cycles"] = max_isr_cycles(res.elf)
        report[name] = entry
        if res.flash_bytes > res.flash_max or res.ram_bytes > res.ram_max:
            sys.stderr.write(f"{name}: too big: {res.flash_bytes} B flash, {res.ram_bytes} B RAM\n")
            return 1
    sys.stdout.write(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
