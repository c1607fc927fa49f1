"""Writing a pipeline's output files (DeMoCap replay, EventCap run): the one atomic replace."""

from __future__ import annotations

from pathlib import Path

from mocaprig.errors import ProcessingError

__all__ = ["replace_atomically"]


def replace_atomically(tmp: Path, dst: Path, *, overwrite: bool) -> None:
    """Move the finished ``tmp`` onto ``dst``; refuse (and remove ``tmp``) when ``dst`` appeared
    meanwhile and ``overwrite`` is False.

    Raises:
        ProcessingError: ``dst`` exists and ``overwrite`` is False.
    """
    if dst.exists() and not overwrite:
        tmp.unlink(missing_ok=True)
        msg = f"{dst} appeared while writing; pass --overwrite to replace it"
        raise ProcessingError(msg)
    tmp.replace(dst)
