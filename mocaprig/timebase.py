"""The one unwrap of the devices' wrapping microsecond stamps.

The D415 hardware timestamp and the sync box's pulse stamps are unsigned 32-bit microsecond
counters: they wrap every 2**32 µs (71.6 min). Device time is never rewritten in a recording
(DESIGN.md, "Time"); it is unwrapped once, where it is read, by the functions here. A backward
step of more than half the range is a wrap; a smaller one is a genuine step back (a reset or
reordering) and is kept as it is.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import numpy as np
import numpy.typing as npt

__all__ = ["U32_US_WRAP", "U32Unwrapper", "unwrap_u32", "unwrap_u32_from"]

U32_US_WRAP: Final = 1 << 32
"""Period of a u32 µs device counter, µs."""
_HALF: Final = U32_US_WRAP >> 1


@dataclass(slots=True)
class U32Unwrapper:
    """Unwrap one stream of u32 µs stamps as they arrive (in receive order).

    ``unwrapper(raw_us)`` returns the stamp plus the wraps seen so far, µs (int64 range).
    """

    last_raw_us: int | None = None
    wrap_us: int = 0

    def __call__(self, raw_us: int) -> int:
        if self.last_raw_us is not None and raw_us < self.last_raw_us - _HALF:
            self.wrap_us += U32_US_WRAP
        self.last_raw_us = raw_us
        return raw_us + self.wrap_us


def unwrap_u32(stamps_us: npt.ArrayLike) -> npt.NDArray[np.int64]:
    """Unwrapped copy of a sequence of u32 µs stamps in receive order, shape (N,), µs int64."""
    raw = np.asarray(stamps_us, dtype=np.int64).reshape(-1)
    if raw.size == 0:
        return raw.copy()
    wraps = np.concatenate([[0], np.cumsum(np.diff(raw) < -_HALF)])
    out: npt.NDArray[np.int64] = raw + wraps * U32_US_WRAP
    return out


def unwrap_u32_from(stamp_us: int, anchor_us: int) -> int:
    """The first value of ``stamp_us + k·2**32`` (k ≥ 0) at or after ``anchor_us``, µs.

    For random access into a stream whose first stamp is ``anchor_us``: exact for streams shorter
    than one wrap (71.6 min).
    """
    k = -((stamp_us - anchor_us) // U32_US_WRAP)
    return stamp_us + max(k, 0) * U32_US_WRAP
