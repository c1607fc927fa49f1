"""Shared fixtures: the real files in ../shared/data (skipped visibly when absent)."""

from __future__ import annotations

import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

from mocaprig.calib.calibration import Calibration
from mocaprig.drivers_mock.truth import Truth

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
#: The @mcap/core (TypeScript) reader the compatibility checks run (tests/compat/check.mjs).
COMPAT = Path(__file__).resolve().parent / "compat"


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
        help="run the device-contract tests against real hardware too (DAVIS240C, D415s, sync box)",
    )


@dataclass(frozen=True)
class CalibratedSession:
    """A simulated session recorded through the drivers and calibrated against its Vicon trial."""

    root: Path
    session: Path
    calib: Path
    calibration: Calibration
    truth: Truth
    seed: int
    seconds: float


@pytest.fixture(scope="session")
def calibrated_session(tmp_path_factory: pytest.TempPathFactory) -> CalibratedSession:
    """One 4 s session (seed 5, four D415s, no DAVIS: the rig DeMoCap is trained for), its
    calibration and truth, shared by every test that needs a calibrated recording (~30 s once).
    The mock cameras of the same seed and length (``open_cameras("mock", seed=5, seconds=4)``)
    see the same world, so the calibration and truth serve a live run on them too."""
    from mocaprig.calib.calibration import write_calibration
    from mocaprig.calib.vicon_calibration import calibrate_vicon
    from mocaprig.drivers_mock import simulate_session
    from mocaprig.drivers_mock.truth import read_truth

    root = tmp_path_factory.mktemp("calibrated-session")
    sim = simulate_session(root / "sim", seed=5, seconds=4.0, devices=("d415",), cameras=4)
    session = sim.out_dir / "session.mcap"
    cal = calibrate_vicon(session, sim.c3d_path).calibration
    calib = write_calibration(cal, root / "calib.toml")
    return CalibratedSession(root, session, calib, cal, read_truth(sim.out_dir), 5, 4.0)


@pytest.fixture(scope="session")
def mcap_core_reader(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``tests/compat/check.mjs`` with @mcap/core installed (``npm ci`` once, lockfile pinned),
    or a visible skip without node/npm or offline. The install runs under a lock shared by the
    pytest-xdist workers, so two of them never write node_modules at once."""
    from filelock import FileLock

    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.skip("node/npm are not installed: the @mcap/core compatibility check cannot run")
    # The workers' temporary folders share this parent.
    lock = tmp_path_factory.getbasetemp().parent / "npm-ci-compat.lock"
    with FileLock(str(lock)):
        if not (COMPAT / "node_modules" / "@mcap" / "core").is_dir():
            res = subprocess.run(
                [npm, "ci", "--prefix", str(COMPAT), "--no-audit", "--no-fund"],
                capture_output=True,
                text=True,
                timeout=300,
                check=False,
            )
            if res.returncode != 0:
                pytest.skip(f"npm ci in {COMPAT} failed (offline?): {res.stderr.strip()[-300:]}")
    return COMPAT / "check.mjs"
