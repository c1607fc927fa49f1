"""Shared fixtures: the real files in ../shared/data (skipped visibly when absent)."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    """The folder of real files, or a visible skip on a user's clone that has none."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (only the project's CI has it)")
    return SHARED_DATA


def pytest_addoption(parser: pytest.Parser) -> None:
    """``--hardware``: also run device-contract tests against real devices on this machine."""
    parser.addoption(
        "--hardware",
        action="store_true",
        default=False,
        help="run the device-contract tests against real hardware too (DAVIS240C on USB)",
    )
