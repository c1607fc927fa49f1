"""The solve's committed data files (the pose bank, the pose prior): one npz layout.

Each file holds its arrays, a ``format_version`` and a ``source`` (the clip names it was built
from). Written in one piece; read back with errors that name the file and the command that
rebuilds it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from mocaprig.errors import ProcessingError, RecordingError

__all__ = ["load_artifact", "save_artifact"]


def save_artifact(
    path: Path,
    noun: str,
    arrays: Mapping[str, npt.ArrayLike],
    *,
    source: Sequence[str],
    version: int,
    overwrite: bool,
) -> Path:
    """Write ``arrays``, ``source`` and ``version`` to ``path`` (compressed npz).

    Raises:
        RecordingError: ``path`` exists and ``overwrite`` is False, or cannot be written.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        msg = f"{noun} {path} exists; pass overwrite=True (--overwrite) to replace it"
        raise RecordingError(msg)
    data: dict[str, Any] = {k: np.asarray(v) for k, v in arrays.items()}
    data["format_version"] = np.array(version)
    data["source"] = np.array(list(source), dtype=str)
    try:
        with path.open("wb") as f:
            np.savez_compressed(f, **data)
    except OSError as exc:
        msg = f"{noun} {path} cannot be written ({exc})"
        raise RecordingError(msg) from exc
    return path


def load_artifact(
    path: Path, noun: str, keys: Sequence[str], *, version: int, rebuild: str
) -> tuple[dict[str, npt.NDArray[np.float64]], tuple[str, ...]]:
    """The float64 arrays ``keys`` and the source of a file :func:`save_artifact` wrote.

    Raises:
        ProcessingError: the file is missing or unreadable (saying to run ``rebuild``), or of
            another format version.
    """
    try:
        with np.load(path, allow_pickle=False) as z:
            found = int(z["format_version"])
            arrays = {k: np.asarray(z[k], np.float64) for k in keys}
            source = tuple(str(s) for s in z["source"])
    except (OSError, KeyError, ValueError) as exc:
        msg = f"{noun} {path} cannot be read ({exc}); rebuild it with `{rebuild}`"
        raise ProcessingError(msg) from exc
    if found != version:
        msg = f"{noun} {path}: format_version {found}, this code reads {version}"
        raise ProcessingError(msg)
    return arrays, source
