"""The simulated session the end-to-end tests of EventCap and ``mocaprig process`` share."""

from __future__ import annotations

from pathlib import Path

import pytest

from mocaprig.cli import main
from tests.conftest import built_once


@pytest.fixture(scope="session")
def karate_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3 s karate session (seed 2) of ``mocaprig simulate`` with the DAVIS and its DVS and two
    D415s (the slow part, ~60 s once): the folder with ``session.mcap``, ``truth/`` and
    ``vicon/``. Tests add their own side files beside it, never replace its files.

    Built once per run (``built_once`` of tests/conftest.py), whichever pytest-xdist worker
    asks first."""

    def build(folder: Path) -> None:
        argv = ["simulate", "--scenario", "karate", "--seed", "2", "--seconds", "3"]
        argv += ["--cameras", "2", "--devices", "davis,d415", "--davis-dvs"]
        assert main(["-q", *argv, "--out", str(folder / "take")]) == 0

    return built_once(tmp_path_factory, "karate-session", build) / "take"
