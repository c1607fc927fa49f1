"""The simulated session the end-to-end tests of EventCap and ``mocaprig process`` share."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from mocaprig.cli import main


@pytest.fixture(scope="session")
def karate_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3 s karate session (seed 2) of ``mocaprig simulate`` with the DAVIS and its DVS and two
    D415s (the slow part, ~60 s once): the folder with ``session.mcap``, ``truth/`` and
    ``vicon/``. Tests add their own side files beside it, never replace its files.

    Under pytest-xdist the workers share one simulation (made by the first to ask, under a
    lock, in the run's common temporary folder), wherever their test files landed."""
    from filelock import FileLock

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # this run's folder, above every worker's own
    sim = root / "karate-session" / "take"
    done = sim.parent / "complete"
    with FileLock(str(root / "karate-session.lock")):
        if not done.exists():
            argv = ["simulate", "--scenario", "karate", "--seed", "2", "--seconds", "3"]
            argv += ["--cameras", "2", "--devices", "davis,d415", "--davis-dvs", "--out", str(sim)]
            assert main(["-q", *argv]) == 0
            done.touch()
    return sim
