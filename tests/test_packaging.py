"""Installed, the project is one import name: `mocaprig`."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_the_wheel_installs_only_the_mocaprig_import_name(tmp_path: Path) -> None:
    pytest.importorskip("setuptools")
    # Built from a copy: a build writes build/ and *.egg-info beside the sources.
    src = tmp_path / "src"
    # The links mocaprig/<package> -> ../<package> are followed: the copy holds the files.
    shutil.copytree(
        ROOT / "mocaprig", src / "mocaprig", ignore=shutil.ignore_patterns("__pycache__")
    )
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    out = tmp_path / "dist"
    run = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
         "--quiet", "-w", str(out), str(src)],
        capture_output=True, text=True, check=False, timeout=300,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr[-2000:]
    (wheel,) = out.glob("mocaprig-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/", 1)[0] for n in names if not n.split("/", 1)[0].endswith(".dist-info")}
    assert tops == {"mocaprig"}
    # The four packages, their data and the committed checkpoint are all inside it.
    for path in (
        "mocaprig/acquire/recorder.py",
        "mocaprig/calib/camera_model.py",
        "mocaprig/process/democap/live.py",
        "mocaprig/drivers_mock/d415.py",
        "mocaprig/acquire/data/99-mocaprig-davis.rules",
        "mocaprig/acquire/schemas/mocaprig.proto",
        "mocaprig/acquire/data/layouts/recording.json",
        "mocaprig/acquire/data/layouts/eventcap.json",
        "mocaprig/process/democap/weights/democap_lite.pt",
        "mocaprig/py.typed",
    ):
        assert path in names, path
    assert not [n for n in names if n.startswith("mocaprig/") and "tests/" in n]


def test_the_editable_install_maps_the_four_folders_into_mocaprig() -> None:
    import mocaprig.acquire
    import mocaprig.calib
    import mocaprig.drivers_mock
    import mocaprig.process

    for mod, folder in (
        (mocaprig.acquire, "acquire"),
        (mocaprig.calib, "calib"),
        (mocaprig.process, "process"),
        (mocaprig.drivers_mock, "drivers_mock"),
    ):
        assert Path(mod.__file__ or "").resolve().parent == (ROOT / folder).resolve()
