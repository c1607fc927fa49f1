"""A fixed-seed subset of the reader fuzz campaign (``benchmarks/fuzz_readers.py``) and checks
that its classification of outcomes is right."""

from __future__ import annotations

import importlib.util
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from mocaprig.errors import RecordingError

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "fuzz_readers.py"
#: Inputs per reader in ``make test``: every reader sees its structural cuts and each kind of
#: mutation; C3D runs its native decoder in a child process (~0.3 s an input), so fewer.
INPUTS = {"c3d": 6, "checkpoint": 16, "davis-words": 16}
DEFAULT_INPUTS = 40


def _load() -> ModuleType:
    spec = importlib.util.spec_from_file_location("fuzz_readers_bench", SCRIPT)
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


fz: Any = _load()


@pytest.mark.parametrize("name", sorted(fz.READERS))
def test_reader_survives_the_fixed_seed_campaign(name: str, tmp_path: Path) -> None:
    n = INPUTS.get(name, DEFAULT_INPUTS)
    res = fz.run_reader(fz.READERS[name], n, seed=0, workdir=tmp_path)
    assert res.inputs == n
    assert res.failures == 0, "\n".join(res.examples)
    assert res.clean_errors + res.reads == n


def _spec(read: Any, *, time_bound_s: float = 2.0) -> Any:
    seed = fz.Seed("s", b"0123456789\n" * 8, ".txt")
    return fz.ReaderSpec(
        "probe",
        lambda folder: [seed],
        read,
        fz.line_starts,
        lambda data, rng: None,
        time_bound_s=time_bound_s,
    )


def _seed_only(path: Path) -> bytes:
    data = path.read_bytes()
    if data != b"0123456789\n" * 8:
        msg = f"{path}: not the seed ({len(data)} bytes)"
        raise RecordingError(msg)
    return data


def test_an_error_naming_the_file_is_clean_and_the_seed_reads_correctly(tmp_path: Path) -> None:
    res = fz.run_reader(_spec(_seed_only), 60, seed=1, workdir=tmp_path)
    assert res.failures == 0
    assert res.clean_errors > 0
    assert res.correct == res.reads  # only no-op mutations read, all equal to the seed's read
    assert res.correct > 0


def test_a_plain_exception_is_a_crash_named_with_its_mutation(tmp_path: Path) -> None:
    def read(path: Path) -> bytes:
        data = _seed_only(path) if path.read_bytes() == b"0123456789\n" * 8 else b""
        if not data:
            raise KeyError("boom")
        return data

    res = fz.run_reader(_spec(read), 20, seed=2, workdir=tmp_path)
    assert res.crashes > 0
    assert res.clean_errors == 0
    assert any("crash KeyError" in e and "probe #" in e for e in res.examples)


def test_an_error_that_does_not_name_the_file_is_a_crash(tmp_path: Path) -> None:
    def read(path: Path) -> bytes:
        if path.read_bytes() != b"0123456789\n" * 8:
            raise RecordingError("something is wrong with some file somewhere")
        return b""

    res = fz.run_reader(_spec(read), 20, seed=3, workdir=tmp_path)
    assert res.vague_errors == res.crashes > 0


def test_a_read_past_the_bound_is_a_hang(tmp_path: Path) -> None:
    def read(path: Path) -> bytes:
        if path.read_bytes() != b"0123456789\n" * 8:
            time.sleep(5)
        return b""

    t0 = time.perf_counter()
    res = fz.run_reader(_spec(read, time_bound_s=0.05), 4, seed=4, workdir=tmp_path)
    assert res.hangs == res.inputs - res.reads > 0
    assert time.perf_counter() - t0 < 2


def test_an_allocation_beyond_the_bound_is_reported(tmp_path: Path) -> None:
    def read(path: Path) -> int:
        return len(bytearray(80 << 20)) + len(path.read_bytes())

    res = fz.run_reader(_spec(read), 3, seed=5, workdir=tmp_path)
    assert res.over_alloc == 3
    assert res.peak_alloc_bytes >= 80 << 20


def test_mutations_are_reproducible_and_start_with_structural_cuts() -> None:
    spec = fz.READERS["rig-file"]
    seeds = spec.seeds(Path())
    first = list(fz.mutations(spec, seeds, 40, 7))
    again = list(fz.mutations(spec, seeds, 40, 7))
    assert [m.data for m in first] == [m.data for m in again]
    assert first[0].name.endswith(f"cut@boundary 0/{len(seeds[0].data)}")
    assert sum("cut@boundary" in m.name for m in first[:10]) == 10
    assert len({m.data for m in first}) > 30
