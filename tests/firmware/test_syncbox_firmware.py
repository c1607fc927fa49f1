"""The sync box firmware builds for Uno and Nano, fits them, and keeps its pulse interrupts apart.

Builds ``firmware/syncbox/syncbox.ino`` with ``firmware/syncbox/build.py`` (avr-gcc and the
Arduino AVR core of the Debian packages ``gcc-avr binutils-avr avr-libc arduino-core-avr``, which
``.ci/run`` installs) into ``tmp_path``, the sketch with ``-Wall -Wextra -Werror``; skips with the
reason when that toolchain is absent. Cycle counts are read from the ELF's disassembly: they are
the figures of docs/syncbox-protocol.md, "Latency".
"""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

BUILD_SCRIPT = Path(__file__).resolve().parents[2] / "firmware" / "syncbox" / "build.py"
BOARDS = ("uno", "nano")
#: RAM left for the stack above the static data (the firmware recurses nowhere; the Serial
#: buffers are static): a generous margin.
STACK_MARGIN = 512


def _load_build() -> ModuleType:
    spec = importlib.util.spec_from_file_location("syncbox_firmware_build", BUILD_SCRIPT)
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


fw: Any = _load_build()


@pytest.fixture(scope="module")
def builds(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """Both boards built once for this module."""
    missing = fw.missing_tools()
    if missing:
        pytest.skip(
            f"AVR toolchain absent ({', '.join(missing)}): install the Debian packages "
            f"{' '.join(fw.DEBIAN_PACKAGES)} to build the sync box firmware (.ci/run does)"
        )
    out = tmp_path_factory.mktemp("firmware")
    return {board: fw.build(board, out) for board in BOARDS}


@pytest.mark.parametrize("board", BOARDS)
def test_builds_without_a_warning_and_fits(builds: dict[str, Any], board: str) -> None:
    res = builds[board]
    assert res.elf.is_file()
    assert res.hex.read_text().startswith(":")  # Intel HEX for avrdude
    assert res.warnings == []  # -Werror would have failed; nothing printed either
    assert 0 < res.flash_bytes <= res.flash_max
    assert res.ram_bytes + STACK_MARGIN <= res.ram_max


def test_boards_as_the_core_defines_them() -> None:
    boards = fw.read_boards()  # the installed boards.txt, else the same built-in values
    assert boards["uno"].define == "AVR_UNO"
    assert boards["nano"].define == "AVR_NANO"
    assert boards["uno"].mcu == boards["nano"].mcu == "atmega328p"


@pytest.mark.parametrize("board", BOARDS)
def test_the_two_pulse_interrupts_are_distinct_and_flip_d10_first(
    builds: dict[str, Any], board: str
) -> None:
    elf = builds[board].elf
    syms = fw.symbols(elf)
    # Two handlers of their own (not one folded into a wrapper that calls the other).
    assert syms["__vector_1"] != syms["__vector_13"]
    isrs = fw.pulse_isrs(elf)  # raises if a vector does not jump to its handler
    for name in ("INT0", "TIMER1_OVF"):
        isr = isrs[name]
        assert isr.first_insn == "sbi 0x03, 2", isr  # PINB bit 2: D10 flips first
        assert isr.vector_jump_cycles == 3
        assert isr.cycles_to_toggle == 2
        # The interrupt request to the flip: response + vector jmp + sbi (docs: 9 cycles).
        assert fw.INTERRUPT_RESPONSE_CYCLES + isr.vector_jump_cycles + isr.cycles_to_toggle == 9
    funcs = fw.disassemble(elf)
    body = syms["__vector_syncbox_pulse"]
    for sym in ("__vector_1", "__vector_13"):
        ops = [(i.op, i.args) for i in funcs[sym]]
        assert len(ops) == 2
        assert ops[1][0] == "jmp"
        assert int(ops[1][1].split()[0], 16) == body  # then the shared counting handler
    assert funcs["__vector_syncbox_pulse"][-1].op == "reti"


@pytest.mark.parametrize("board", BOARDS)
def test_the_other_interrupts_are_bounded(builds: dict[str, Any], board: str) -> None:
    bounds = fw.max_isr_cycles(builds[board].elf)
    assert set(bounds) == {"TIMER0_OVF (millis)", "USART_RX", "USART_UDRE"}
    # docs/syncbox-protocol.md: a pulse interrupt waits at most ~150 cycles (< 10 us) for one.
    assert max(bounds.values()) <= 150


@pytest.mark.parametrize("board", BOARDS)
def test_start_forces_the_output_latch_low(builds: dict[str, Any], board: str) -> None:
    # force_out_low(): a forced compare match (FOC1A = 0x80 into TCCR1C at 0x82) clears OC1A.
    funcs = fw.disassemble(builds[board].elf)
    insns = [i for f in funcs.values() for i in f]
    loads: dict[str, int] = {}
    forced = False
    for insn in insns:
        m = re.match(r"(r\d+), (0x[0-9A-Fa-f]+|\d+)", insn.args)
        if insn.op == "ldi" and m:
            loads[m.group(1)] = int(m.group(2), 0)
        m = re.match(r"0x0*82, (r\d+)", insn.args)
        if insn.op == "sts" and m and loads.get(m.group(1)) == 0x80:
            forced = True
    assert forced, "no write of FOC1A to TCCR1C in the binary"
