"""The simulated session the end-to-end tests of EventCap and ``mocaprig process`` share."""

from __future__ import annotations

from pathlib import Path

import pytest

from mocaprig.cli import main


@pytest.fixture(scope="session")
def karate_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3 s karate session (seed 2) of ``mocaprig simulate`` with the DAVIS and its DVS and two
    D415s (the slow part, ~60 s once): the folder with ``session.mcap``, ``truth/`` and
    ``vicon/``. Tests add their own side files beside it, never replace its files."""
    sim = tmp_path_factory.mktemp("karate") / "take"
    argv = ["simulate", "--scenario", "karate", "--seed", "2", "--seconds", "3", "--cameras", "2"]
    assert main(["-q", *argv, "--devices", "davis,d415", "--davis-dvs", "--out", str(sim)]) == 0
    return sim
