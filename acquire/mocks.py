"""Finding the mock devices: the ``mocaprig.mocks`` entry points.

``mocaprig.acquire`` never imports ``mocaprig.drivers_mock``; a ``--mock`` flag loads the mock's
factory by name through this entry-point group (``pyproject.toml``), so the mocks stay an
installable plug-in at the real boundaries.
"""

from __future__ import annotations

import importlib.metadata
from collections.abc import Callable
from typing import Any, Final

from mocaprig.errors import DeviceError

__all__ = ["MOCKS_GROUP", "load_mock_factory"]

MOCKS_GROUP: Final = "mocaprig.mocks"


def load_mock_factory(name: str) -> Callable[..., Any]:
    """Load the mock factory registered as ``name`` in the ``mocaprig.mocks`` entry points.

    Raises:
        DeviceError: no such entry point, or it cannot be imported.
    """
    eps = importlib.metadata.entry_points(group=MOCKS_GROUP)
    if name not in eps.names:
        msg = (
            f"no mock '{name}' is registered in the '{MOCKS_GROUP}' entry points; "
            "reinstall mocaprig (pip install -e .) so drivers_mock is available"
        )
        raise DeviceError(msg)
    try:
        factory: Callable[..., Any] = eps[name].load()
    except Exception as err:  # an import error in the mock package, whatever its type
        msg = f"cannot load the mock '{name}' ({eps[name].value}): {err}"
        raise DeviceError(msg) from err
    return factory
