"""The DAVIS240C driver's split: every name users import still comes from ``davis240c``, each
module holds what its name says, and the modules import each other without a cycle."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

from mocaprig.acquire import (
    davis240c,
    davis240c_discovery,
    davis240c_libusb,
    davis240c_reader,
)

ROOT = Path(__file__).resolve().parents[2]
MODULES = ("davis240c", "davis240c_libusb", "davis240c_discovery", "davis240c_reader")

# Everything ``davis240c`` exported before the split (and that users import from it).
PUBLIC = {
    "DATA_ENDPOINT": davis240c_libusb,
    "PRODUCT_ID_FX2": davis240c_libusb,
    "PRODUCT_ID_FX3": davis240c_libusb,
    "VENDOR_ID": davis240c_libusb,
    "UDEV_RULE": davis240c_discovery,
    "DavisUsbDevice": davis240c_discovery,
    "find_davis": davis240c_discovery,
    "load_mock_backend": davis240c_discovery,
    "StreamStats": davis240c_reader,
}
OWN = (
    "REQUIRED_FIRMWARE_FX2",
    "REQUIRED_FIRMWARE_FX3",
    "REQUIRED_LOGIC_PATCH",
    "REQUIRED_LOGIC_VERSION",
    "Davis240C",
    "DavisInfo",
    "DavisPacket",
)


@pytest.mark.parametrize("name", sorted(PUBLIC))
def test_moved_names_are_still_exported_by_the_device_module(name: str) -> None:
    assert name in davis240c.__all__
    assert getattr(davis240c, name) is getattr(PUBLIC[name], name)
    assert name in PUBLIC[name].__all__


def test_the_device_module_keeps_its_own_names() -> None:
    for name in OWN:
        assert name in davis240c.__all__
        assert hasattr(davis240c, name)
    assert set(davis240c.__all__) == set(PUBLIC) | set(OWN)


@pytest.mark.parametrize("stem", MODULES)
def test_every_public_name_exists_and_internals_are_underscored(stem: str) -> None:
    module = importlib.import_module(f"mocaprig.acquire.{stem}")
    assert module.__doc__
    for name in module.__all__:
        assert hasattr(module, name), f"{stem}.__all__ names {name}, which is missing"
        assert not name.startswith("_")


def _davis_imports(stem: str) -> set[str]:
    tree = ast.parse((ROOT / "acquire" / f"{stem}.py").read_text(encoding="utf-8"))
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            leaf = node.module.rsplit(".", 1)[-1]
            if node.module.startswith("mocaprig.acquire.") and leaf in MODULES:
                found.add(leaf)
    return found


def test_the_modules_import_each_other_without_a_cycle() -> None:
    graph = {stem: _davis_imports(stem) for stem in MODULES}
    assert graph["davis240c_libusb"] == set()
    assert graph["davis240c_discovery"] == {"davis240c_libusb"}
    assert graph["davis240c_reader"] == {"davis240c_libusb"}
    assert graph["davis240c"] == {"davis240c_libusb", "davis240c_discovery", "davis240c_reader"}
    # A topological order exists (the check above already implies it; kept for later edits).
    done: set[str] = set()
    while len(done) < len(graph):
        ready = {m for m, deps in graph.items() if m not in done and deps <= done}
        assert ready, f"import cycle among {sorted(set(graph) - done)}"
        done |= ready
