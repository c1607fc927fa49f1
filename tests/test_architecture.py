"""The tree's import rules (DESIGN.md, docs/architecture.md).

- Installed, everything lives under ``mocaprig``; the four fixed folders are
  ``mocaprig.acquire``, ``mocaprig.calib``, ``mocaprig.process`` and ``mocaprig.drivers_mock``.
- Imports flow ``process -> calib -> acquire -> the bottom layer``; nothing but tests imports the
  mocks, not even dynamically (``importlib.import_module("mocaprig.drivers_mock...")``).
- The bottom layer (errors, validation, time base, progress, JSON values) imports no package;
  no library module imports the CLI (``mocaprig.cli``) or a command module.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("acquire", "calib", "process", "drivers_mock")

# package -> mocaprig subpackages it must never import
FORBIDDEN: dict[str, set[str]] = {
    "acquire": {"calib", "process", "drivers_mock"},
    "calib": {"process", "drivers_mock"},
    "process": {"drivers_mock"},
    "drivers_mock": set(),
}
_BOTTOM = ("errors", "validation", "timebase", "progress", "json_values")


def _is_command_module(path: Path) -> bool:
    return path.name == "cli.py" or path.name.startswith("commands")


def _imported_modules(path: Path) -> set[str]:
    """Every absolute module name imported by ``path``, statically or through importlib."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
        elif (
            isinstance(node, ast.Call)
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
            and (
                (isinstance(node.func, ast.Attribute) and node.func.attr in _DYNAMIC)
                or (isinstance(node.func, ast.Name) and node.func.id in _DYNAMIC)
            )
        ):
            names.add(node.args[0].value)
    return names


_DYNAMIC = {"import_module", "find_spec", "__import__", "importorskip"}


def _subpackages(names: set[str]) -> set[str]:
    return {n.split(".")[1] for n in names if n.startswith("mocaprig.") and n.count(".") >= 1}


def _library_files(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


@pytest.mark.slow
def test_every_import_goes_through_the_mocaprig_namespace() -> None:
    offenders = []
    for package in PACKAGES:
        for path in _library_files(package):
            bare = {n for n in _imported_modules(path) if n.split(".")[0] in PACKAGES}
            if bare:
                offenders.append(f"{path.relative_to(ROOT)} imports {sorted(bare)}")
    assert not offenders, "import the packages as mocaprig.<package>:\n" + "\n".join(offenders)


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_package_imports_flow_one_way(package: str) -> None:
    offenders = []
    for path in _library_files(package):
        bad = _subpackages(_imported_modules(path)) & FORBIDDEN[package]
        if bad:
            offenders.append(f"{path.relative_to(ROOT)} imports {sorted(bad)}")
    assert not offenders, "imports must flow process -> calib -> acquire:\n" + "\n".join(offenders)


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_library_modules_never_import_the_cli(package: str) -> None:
    offenders = []
    for path in _library_files(package):
        if _is_command_module(path):
            continue
        for name in _imported_modules(path):
            parts = name.split(".")
            if name.startswith("mocaprig.cli") or any(p.startswith("commands") for p in parts):
                offenders.append(f"{path.relative_to(ROOT)} imports {name}")
    assert not offenders, "library code never imports the command layer:\n" + "\n".join(offenders)


def test_the_bottom_layer_imports_no_package() -> None:
    offenders = []
    for stem in _BOTTOM:
        path = ROOT / "mocaprig" / f"{stem}.py"
        assert path.is_file(), f"{path} is missing"
        bad = _subpackages(_imported_modules(path)) - set(_BOTTOM)
        if bad:
            offenders.append(f"{path.relative_to(ROOT)} imports {sorted(bad)}")
    assert not offenders, "the bottom layer stands alone:\n" + "\n".join(offenders)


def test_the_import_check_sees_dynamic_imports(tmp_path: Path) -> None:
    path = tmp_path / "sneaky.py"
    path.write_text(
        "import importlib\nm = importlib.import_module('mocaprig.drivers_mock.d415')\n",
        encoding="utf-8",
    )
    assert "drivers_mock" in _subpackages(_imported_modules(path))


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_library_code_never_prints(package: str) -> None:
    offenders = []
    for path in _library_files(package):
        if _is_command_module(path):
            continue  # the command layer is where printing belongs
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name)
                and node.func.id == "print"
            ):
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not offenders, "library code logs, never prints:\n" + "\n".join(offenders)


@pytest.mark.parametrize("package", [*sorted(FORBIDDEN), "mocaprig"])
def test_every_package_declares_its_public_names(package: str) -> None:
    missing = []
    paths = (
        sorted((ROOT / "mocaprig").glob("*.py"))
        if package == "mocaprig"
        else _library_files(package)
    )
    for path in paths:
        if path.name.startswith("_") and path.name != "__init__.py":
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        has_all = any(
            isinstance(node, ast.Assign | ast.AnnAssign)
            and any(
                isinstance(t, ast.Name) and t.id == "__all__"
                for t in (node.targets if isinstance(node, ast.Assign) else [node.target])
            )
            for node in tree.body
        )
        if not has_all and tree.body:
            missing.append(str(path.relative_to(ROOT)))
    assert not missing, "public modules declare __all__:\n" + "\n".join(missing)


def test_the_namespace_links_point_at_the_fixed_folders() -> None:
    for package in PACKAGES:
        link = ROOT / "mocaprig" / package
        assert link.is_symlink(), f"{link} must be a link to ../{package}"
        assert link.resolve() == (ROOT / package).resolve()
