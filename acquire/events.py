"""The canonical event representation: one numpy structured dtype for polarity events.

Every array of DVS events in mocaprig (decoder output, simulator output, recordings read back,
EventCap input) has dtype :data:`EVENT_DTYPE`:

====  ======  ==========================================================================
name  type    meaning
====  ======  ==========================================================================
t     int64   timestamp, µs, in the device's clock (never rewritten by acquisition)
x     uint16  column, 0 = left of the image as seen on screen (0..239 on a DAVIS240C)
y     uint16  row, 0 = top of the image (0..179 on a DAVIS240C)
p     uint8   polarity: 1 = ON (brighter), 0 = OFF (darker)
====  ======  ==========================================================================

Events are sorted by ``t`` (non-decreasing) wherever a function says it returns a stream.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from mocaprig.errors import ValidationError

__all__ = ["EVENT_DTYPE", "check_events", "empty_events", "make_events"]

EVENT_DTYPE = np.dtype([("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])


def make_events(
    t: npt.ArrayLike, x: npt.ArrayLike, y: npt.ArrayLike, p: npt.ArrayLike
) -> npt.NDArray[np.void]:
    """Build an event array from columns (t in µs; p truthy = ON). Inputs are not modified.

    Raises:
        ValidationError: the columns differ in length or are not one-dimensional.
    """
    cols = [np.asarray(c) for c in (t, x, y, p)]
    if any(c.ndim != 1 for c in cols) or len({c.shape[0] for c in cols}) != 1:
        shapes = ", ".join(str(c.shape) for c in cols)
        msg = f"event columns t, x, y, p must be 1-D and of equal length, got {shapes}"
        raise ValidationError(msg)
    out = np.empty(cols[0].shape[0], dtype=EVENT_DTYPE)
    out["t"] = cols[0]
    out["x"] = cols[1]
    out["y"] = cols[2]
    out["p"] = cols[3] != 0
    return out


def empty_events() -> npt.NDArray[np.void]:
    """An empty event array of the canonical dtype."""
    return np.empty(0, dtype=EVENT_DTYPE)


def check_events(events: npt.ArrayLike, *, name: str = "events") -> npt.NDArray[np.void]:
    """Return ``events`` if it is a 1-D array of :data:`EVENT_DTYPE`, else raise.

    Raises:
        ValidationError: wrong dtype or shape; the message shows the expected dtype.
    """
    arr = np.asarray(events)
    if arr.dtype != EVENT_DTYPE or arr.ndim != 1:
        msg = (
            f"{name} must be a 1-D array of dtype {EVENT_DTYPE.descr}, got shape {arr.shape} "
            f"dtype {arr.dtype}; build it with acquire.events.make_events"
        )
        raise ValidationError(msg)
    return arr
