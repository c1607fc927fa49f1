"""Packages whose public names are imported on first use (``mocaprig.lazy_exports``)."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

from mocaprig.lazy_exports import lazy_getattr

LAZY_PACKAGES = ["mocaprig.process.democap", "mocaprig.process.eventcap", "mocaprig.process.batch"]


@pytest.mark.parametrize("package", LAZY_PACKAGES)
def test_every_public_name_resolves_to_its_submodules_object(package: str) -> None:
    pkg = importlib.import_module(package)
    exported = {name for names in pkg._EXPORTS.values() for name in names}
    assert exported <= set(pkg.__all__)
    for module, names in pkg._EXPORTS.items():
        sub = importlib.import_module(f"{package}.{module}")
        for name in names:
            assert getattr(pkg, name) is getattr(sub, name), name
    namespace: dict[str, object] = {}
    exec(f"from {package} import *", namespace)  # the star import a user may write
    assert set(pkg.__all__) <= set(namespace)


def test_an_unknown_name_is_an_attribute_error_naming_the_package() -> None:
    get = lazy_getattr("mocaprig.process.democap", {"infer": ("DemocapPredictor",)})
    with pytest.raises(
        AttributeError, match=r"'mocaprig\.process\.democap' has no attribute 'nope'"
    ):
        get("nope")
    with pytest.raises(ImportError):
        from mocaprig.process.democap import nope  # noqa: F401


def test_a_name_that_is_also_a_submodule_is_refused() -> None:
    # Importing the submodule `evaluate` sets the package's `evaluate` to the module, so a lazy
    # function of that name would be lost as soon as anything imported its module.
    with pytest.raises(ValueError, match=r"lazy names \['evaluate'\] are also submodules"):
        lazy_getattr("mocaprig.process.democap", {"evaluate": ("evaluate", "EvalReport")})


def test_the_command_line_is_built_without_importing_torch() -> None:
    # Every command module is imported to build the parser (`mocaprig --help`): torch takes
    # seconds to import and only the commands that run a network need it.
    code = (
        "import sys\n"
        "from mocaprig.cli import _build_parser\n"
        "_build_parser()\n"
        "print(sorted(m for m in ('torch', 'dask', 'cv2') if m in sys.modules))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    assert "torch" not in out.stdout, out.stdout
