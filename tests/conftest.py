"""Shared fixtures: the real files in ../shared/data (skipped visibly when absent)."""

from __future__ import annotations

import contextlib
import io
import os
import shutil
import subprocess
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from mocaprig.calib.calibration import Calibration
from mocaprig.drivers_mock.truth import Truth

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
#: The @mcap/core (TypeScript) reader the compatibility checks run (tests/compat/check.mjs).
COMPAT = Path(__file__).resolve().parent / "compat"


@pytest.fixture(autouse=True, scope="session")
def _compiler_cache_under_tmp(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """torch.compile (the live predictor) writes its caches under the session's temporary
    folder, not the user's ``/tmp/torchinductor_*``."""
    import torch._inductor.config as inductor

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path_factory.mktemp("inductor")))
        # precompiled headers go to the default folder whatever the variable says
        mp.setattr(inductor, "cpp_cache_precompile_headers", False)
        yield


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


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Run the files with ``slow`` tests first, the end-to-end ones (``tests/e2e``) first of all,
    each file's tests together and in their own order.

    ``make unit`` hands whole files to its pytest-xdist workers as they free up
    (``--dist loadfile --no-loadscope-reorder``). Handed out last, one file of minutes (the
    demo) kept one worker busy for minutes after the other had run out of work; handed out
    first, the many quick files even out the two workers at the end.
    """
    slow_files = {item.path for item in items if item.get_closest_marker("slow")}
    e2e = Path(__file__).resolve().parent / "e2e"

    def rank(item: pytest.Item) -> int:
        if item.path not in slow_files:
            return 2
        return 0 if e2e in item.path.parents else 1

    items.sort(key=rank)  # stable: within a rank, the collection order


def built_once(
    tmp_path_factory: pytest.TempPathFactory, name: str, build: Callable[[Path], object]
) -> Path:
    """The folder ``name`` of this test run, made by ``build(folder)`` once per run: under
    pytest-xdist by the first worker to ask (under a lock, in the run's folder above every
    worker's own), wherever the test files that need it landed."""
    from filelock import FileLock

    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent
    folder = base / name
    with FileLock(str(base / f"{name}.lock")):
        if not (folder / "complete").exists():
            build(folder)
            (folder / "complete").touch()
    return folder


@pytest.fixture(scope="session")
def rig_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One 6 s session of ``mocaprig simulate`` (seed 5, two D415s, the DAVIS without its DVS
    and the sync box): the folder with ``session.mcap``, ``vicon/`` and ``truth/``; the
    command's ``--json`` report is ``simulate.json`` beside that folder. Shared by the
    recording, calibration and sync tests (6 s: a slave D415 is tied to the master by frame
    counters only over >= 5 s of frames); tests write beside it, never into it.

    Built once per run (:func:`built_once`), whichever pytest-xdist worker asks first."""
    from mocaprig.cli import main

    def build(root: Path) -> None:
        argv = ["-q", "simulate", "--seconds", "6", "--seed", "5", "--cameras", "2"]
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            code = main([*argv, "--out", str(root / "take"), "--json"])
        if code != 0:
            msg = f"mocaprig simulate exited {code}"
            raise RuntimeError(msg)
        (root / "simulate.json").write_text(buf.getvalue(), encoding="utf-8")

    return built_once(tmp_path_factory, "rig-session", build) / "take"


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
    see the same world, so the calibration and truth serve a live run on them too.

    Built once per run (:func:`built_once`), whichever pytest-xdist worker asks first."""
    from mocaprig.calib.calibration import read_calibration, write_calibration
    from mocaprig.calib.vicon_calibration import calibrate_vicon
    from mocaprig.drivers_mock import simulate_session
    from mocaprig.drivers_mock.truth import read_truth

    def build(root: Path) -> None:
        sim = simulate_session(root / "sim", seed=5, seconds=4.0, devices=("d415",), cameras=4)
        cal = calibrate_vicon(sim.out_dir / "session.mcap", sim.c3d_path).calibration
        write_calibration(cal, root / "calib.toml")

    root = built_once(tmp_path_factory, "calibrated-session", build)
    calib = root / "calib.toml"
    session = root / "sim" / "session.mcap"
    truth = read_truth(root / "sim")
    return CalibratedSession(root, session, calib, read_calibration(calib), truth, 5, 4.0)


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
