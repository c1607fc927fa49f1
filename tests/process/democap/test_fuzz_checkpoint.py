"""The checkpoint reader on damaged files (found by ``benchmarks/fuzz_readers.py``): a clean
:class:`ProcessingError` naming the file, before anything the file says is allocated."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import pytest
import torch

from mocaprig.errors import ProcessingError
from mocaprig.process.body import DEMOCAP_JOINTS, MARKER_NAMES
from mocaprig.process.democap.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from mocaprig.process.democap.config import DemocapConfig
from mocaprig.process.democap.model import build_network


@pytest.fixture
def saved(tmp_path: Path, tiny_config: DemocapConfig) -> dict[str, Any]:
    torch.manual_seed(0)
    model = build_network(
        tiny_config, num_markers=len(MARKER_NAMES), num_joints=len(DEMOCAP_JOINTS)
    )
    p = tmp_path / "ok.pt"
    save_checkpoint(Checkpoint(tiny_config, model), p)
    data: dict[str, Any] = torch.load(p, weights_only=True)
    return data


def _write(tmp_path: Path, data: dict[str, Any]) -> Path:
    p = tmp_path / "bad.pt"
    torch.save(data, p)
    return p


def test_a_config_asking_for_a_huge_network_is_refused_at_once(
    tmp_path: Path, saved: dict[str, Any]
) -> None:
    saved["config"]["stem_units"] = 2**62
    t0 = time.perf_counter()
    with pytest.raises(ProcessingError, match=r"bad\.pt: the stored config asks for \d+ network"):
        load_checkpoint(_write(tmp_path, saved))
    assert time.perf_counter() - t0 < 2.0


def test_a_config_with_wider_layers_than_stored_is_refused(
    tmp_path: Path, saved: dict[str, Any]
) -> None:
    saved["config"]["stem_channels"] = 100_000
    with pytest.raises(ProcessingError, match=r"bad\.pt: the weights do not match the stored"):
        load_checkpoint(_write(tmp_path, saved))


def test_a_weight_viewing_more_values_than_stored_is_refused(
    tmp_path: Path, saved: dict[str, Any]
) -> None:
    key = next(iter(saved["model"]))
    saved["model"][key] = torch.zeros(1).expand(1 << 20, 1 << 20)
    with pytest.raises(ProcessingError, match=rf"bad\.pt: weight {key} .*claims more values"):
        load_checkpoint(_write(tmp_path, saved))


def test_a_weight_holding_nan_is_refused(tmp_path: Path, saved: dict[str, Any]) -> None:
    key = next(k for k, v in saved["model"].items() if v.is_floating_point())
    saved["model"][key] = torch.full_like(saved["model"][key], math.nan)
    with pytest.raises(ProcessingError, match=rf"bad\.pt: weight {key} holds NaN"):
        load_checkpoint(_write(tmp_path, saved))


@pytest.mark.parametrize(("key", "value"), [("joint_names", -1), ("epoch", "x"), ("history", 5)])
def test_a_damaged_entry_is_refused_by_name(
    tmp_path: Path, saved: dict[str, Any], key: str, value: object
) -> None:
    saved[key] = value
    with pytest.raises(ProcessingError, match=r"bad\.pt"):
        load_checkpoint(_write(tmp_path, saved))


def test_a_non_zip_file_is_refused_before_torch_reads_its_length_words(tmp_path: Path) -> None:
    """64 random bytes (fuzz input #7389, seed 17) that torch.load's legacy pickle reader took
    for a 1.8 GB string: refused before any allocation."""
    import tracemalloc

    bad = tmp_path / "garbage.pt"
    bad.write_bytes(
        bytes.fromhex(
            "58a20f526e56acd15adba251986eeee8ef77ed2ce5879ac559b6212bc4991d2191f0cf53d0b6319d5b3785e3771745b26f5b0fccda5e616b2c2244f2839f41a2"
        )
    )
    tracemalloc.start()
    try:
        with pytest.raises(ProcessingError, match="not a torch zip archive"):
            load_checkpoint(bad)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 16 * 2**20


def test_a_zip_end_record_naming_other_disks_is_a_clean_error(
    tmp_path: Path, saved: dict[str, Any]
) -> None:
    """A bit flip in the zip64 end locator's disk number (fuzz input #8949, seed 17): zipfile
    raises BadZipFile from its own check, which is reported as a damaged checkpoint."""
    buf = bytearray(_write(tmp_path, saved).read_bytes())
    locator = buf.rfind(b"PK\x06\x07")
    assert locator > 0, "torch writes a zip64 end locator"
    buf[locator + 4] = 1  # "number of the disk with the zip64 end record"
    bad = tmp_path / "multidisk.pt"
    bad.write_bytes(bytes(buf))
    with pytest.raises(ProcessingError, match="zip structure is damaged"):
        load_checkpoint(bad)
