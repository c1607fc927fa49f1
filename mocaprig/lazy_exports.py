"""Package namespaces whose public names are imported on first use (PEP 562).

A package that re-exports its submodules' names would import all of them, torch included
(~3 s), whenever any one submodule is imported — ``mocaprig --help`` imports every command
module. Such a package lists ``{submodule: names}`` once and takes its module ``__getattr__``
from :func:`lazy_getattr`; type checkers see the same names through ``if TYPE_CHECKING``
imports.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any

__all__ = ["lazy_getattr"]


def lazy_getattr(package: str, exports: Mapping[str, Sequence[str]]) -> Callable[[str], Any]:
    """A module ``__getattr__`` for ``package``: ``exports`` maps each submodule (relative
    name) to the public names it defines; a name is imported from it on first access and
    kept in the package's namespace.

    Raises:
        ValueError: a name is also a submodule's: importing that submodule anywhere would
            replace the name in the package by the module (an eager import binds it after).
    """
    where = {name: module for module, names in exports.items() for name in names}
    clash = sorted(set(where) & set(exports))
    if clash:
        msg = f"{package}: lazy names {clash} are also submodules; export them from their modules"
        raise ValueError(msg)

    def __getattr__(name: str) -> Any:
        module = where.get(name)
        if module is None:
            msg = f"module {package!r} has no attribute {name!r}"
            raise AttributeError(msg)
        value = getattr(importlib.import_module(f"{package}.{module}"), name)
        setattr(sys.modules[package], name, value)  # later lookups skip this function
        return value

    return __getattr__
