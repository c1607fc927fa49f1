"""Rig instants: the frames of the hardware-synchronised D415s that exposed together.

The D415s are hardware synchronised (the slaves expose on the master's pulses), so the frames of
one instant agree on the calibration's reference clock to its accuracy (≈ 1 ms). Frames are
taken in reference-time order (ties by camera); a frame joins the open instant when it lies
within ``tolerance`` × the frame period of that instant's first frame and its camera is not in
it yet, otherwise it opens a new instant. An instant seen by fewer cameras (a dropped frame)
is still an instant.

One rule, two drivers: :class:`InstantGrouper` applies it online to frames as a live rig
delivers them (the replay and ``democap live`` both feed :class:`~.live.LivePipeline` from it or
from :func:`group_instants`), and :func:`group_instants` runs the same grouper over a whole
recording's frame times.
"""

from __future__ import annotations

import heapq
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Final, Generic, NamedTuple, TypeVar

import numpy as np
import numpy.typing as npt

from mocaprig.errors import ValidationError

__all__ = [
    "INSTANT_TOLERANCE",
    "GroupedInstant",
    "Grouping",
    "Instant",
    "InstantGrouper",
    "group_instants",
]

#: Frames within this fraction of the frame period of an instant's first frame join it.
INSTANT_TOLERANCE: Final = 0.25
#: Frame period assumed when no camera has two frames (30 Hz).
_NOMINAL_PERIOD_NS: Final = 33_333_333

T = TypeVar("T")


@dataclass(frozen=True, slots=True)
class Instant:
    """One rig instant: the frames of the cameras that exposed together.

    Attributes:
        t_ref_ns: Mean reference time of its frames (ns, calibration's reference clock).
        frames: Camera label -> device time of its frame (ns, the camera's own clock).
    """

    t_ref_ns: int
    frames: Mapping[str, int]


@dataclass(frozen=True, slots=True)
class GroupedInstant(Generic[T]):
    """An :class:`Instant` with what was pushed for each of its frames (camera -> item)."""

    instant: Instant
    items: Mapping[str, T] = field(repr=False)


class Grouping(NamedTuple):
    """What :func:`group_instants` returns."""

    instants: tuple[Instant, ...]
    period_ns: int
    """Median frame period on the reference clock (ns)."""


def _check_tolerance(tolerance: float) -> float:
    if not 0.0 < float(tolerance) < 0.5:
        msg = f"tolerance must lie in (0, 0.5) frame periods, got {tolerance!r}"
        raise ValidationError(msg)
    return float(tolerance)


class InstantGrouper(Generic[T]):
    """Group frames into rig instants as they arrive (module doc).

    Each camera must deliver its frames in time order. A frame is grouped once every camera
    has delivered one at least as late (nothing earlier can still come), or once it is
    ``max_lag_ns`` older than the newest frame (a camera that stopped delivering holds nothing
    up for longer); :meth:`flush` groups the rest.

    Args:
        cameras: The camera labels.
        period_ns: The frame period on the reference clock (ns).
        tolerance: Fraction of the period (0 < tolerance < 0.5).
        max_lag_ns: How long a frame may wait for the other cameras (ns); None waits until
            every camera has caught up (or :meth:`flush`).

    Raises:
        ValidationError: no or duplicate cameras, a period ≤ 0, ``tolerance`` out of range.
    """

    def __init__(
        self,
        cameras: Sequence[str],
        period_ns: int,
        *,
        tolerance: float = INSTANT_TOLERANCE,
        max_lag_ns: int | None = None,
    ) -> None:
        cams = list(cameras)
        if not cams or len(set(cams)) != len(cams):
            msg = f"cameras must be one or more distinct labels, got {cams!r}"
            raise ValidationError(msg)
        if int(period_ns) <= 0:
            msg = f"the frame period must be > 0 ns, got {period_ns!r}"
            raise ValidationError(msg)
        self._index = {c: i for i, c in enumerate(cams)}
        self._cams = cams
        self._tol = _check_tolerance(tolerance) * int(period_ns)
        self._max_lag = None if max_lag_ns is None else int(max_lag_ns)
        self._latest: dict[str, int] = {}
        self._heap: list[tuple[int, int, int, int, T]] = []  # (t_ref, cam, n, t_dev, item)
        self._n = 0
        self._members: dict[str, tuple[int, int, T]] = {}  # camera -> (t_dev, t_ref, item)
        self._first = 0

    def push(self, camera: str, t_ref_ns: int, t_dev_ns: int, item: T) -> list[GroupedInstant[T]]:
        """Add one frame; returns the instants it completed (in time order).

        Raises:
            ValidationError: an unknown camera, or a frame earlier than its camera's last.
        """
        if camera not in self._index:
            msg = f"camera {camera!r} is not one of the grouper's {self._cams}"
            raise ValidationError(msg)
        t = int(t_ref_ns)
        last = self._latest.get(camera)
        if last is not None and t < last:
            msg = f"{camera}: frame at {t} ns arrives after one at {last} ns (out of order)"
            raise ValidationError(msg)
        self._latest[camera] = t
        heapq.heappush(self._heap, (t, self._index[camera], self._n, int(t_dev_ns), item))
        self._n += 1
        ready = min(self._latest.values()) if len(self._latest) == len(self._cams) else None
        if self._max_lag is not None:
            lagged = max(self._latest.values()) - self._max_lag
            ready = lagged if ready is None else max(ready, lagged)
        return [] if ready is None else self._release(ready)

    def flush(self) -> list[GroupedInstant[T]]:
        """Group every frame still waiting and close the open instant."""
        out = self._release(None)
        out.extend(self._close())
        return out

    def _release(self, up_to: int | None) -> list[GroupedInstant[T]]:
        out: list[GroupedInstant[T]] = []
        while self._heap and (up_to is None or self._heap[0][0] <= up_to):
            t, ci, _, d, item = heapq.heappop(self._heap)
            cam = self._cams[ci]
            if self._members and t - self._first <= self._tol and cam not in self._members:
                self._members[cam] = (d, t, item)
            else:
                out.extend(self._close())
                self._members = {cam: (d, t, item)}
                self._first = t
            if len(self._members) == len(self._cams):
                out.extend(self._close())  # full: no other frame can join it
        if up_to is not None and self._members and up_to > self._first + self._tol:
            out.extend(self._close())  # every frame that could join it has been seen
        return out

    def _close(self) -> list[GroupedInstant[T]]:
        if not self._members:
            return []
        members = dict(sorted(self._members.items()))
        self._members = {}
        t_mean = round(float(np.mean([r for _, r, _ in members.values()])))
        inst = Instant(t_mean, {c: d for c, (d, _, _) in members.items()})
        return [GroupedInstant(inst, {c: it for c, (_, _, it) in members.items()})]


def group_instants(
    t_dev_ns: Mapping[str, npt.ArrayLike],
    t_ref_ns: Mapping[str, npt.ArrayLike],
    *,
    tolerance: float = INSTANT_TOLERANCE,
) -> Grouping:
    """Group the frames of hardware-synchronised cameras into instants (module doc).

    Args:
        t_dev_ns: Per camera, the device times of its frames (ns).
        t_ref_ns: Per camera, the same frames on the reference clock (ns), same shape.
        tolerance: Fraction of the median frame period (0 < tolerance < 0.5).

    Returns:
        The instants in time order and the median frame period (ns; 30 Hz when no camera has
        two frames).

    Raises:
        ValidationError: mismatched cameras or shapes, or ``tolerance`` out of range.
    """
    _check_tolerance(tolerance)
    if set(t_dev_ns) != set(t_ref_ns):
        msg = (
            "t_dev_ns and t_ref_ns must have the same cameras: "
            f"{sorted(t_dev_ns)} vs {sorted(t_ref_ns)}"
        )
        raise ValidationError(msg)
    cams = sorted(t_dev_ns)
    dev = {c: np.asarray(t_dev_ns[c], dtype=np.int64).reshape(-1) for c in cams}
    ref = {c: np.asarray(t_ref_ns[c], dtype=np.int64).reshape(-1) for c in cams}
    for c in cams:
        if dev[c].shape != ref[c].shape:
            msg = f"{c}: {dev[c].size} device times but {ref[c].size} reference times"
            raise ValidationError(msg)
    steps = [np.diff(np.sort(ref[c])) for c in cams if ref[c].size > 1]
    period = int(np.median(np.concatenate(steps))) if steps else _NOMINAL_PERIOD_NS
    if period <= 0:
        msg = f"the frames' reference times do not advance (median period {period} ns)"
        raise ValidationError(msg)
    if not cams:
        return Grouping((), period)
    grouper: InstantGrouper[None] = InstantGrouper(cams, period, tolerance=tolerance)
    grouped: list[GroupedInstant[None]] = []
    for c in cams:
        order = np.argsort(ref[c], kind="stable")
        for t, d in zip(ref[c][order].tolist(), dev[c][order].tolist(), strict=True):
            grouped.extend(grouper.push(c, t, d, None))
    grouped.extend(grouper.flush())
    return Grouping(tuple(g.instant for g in grouped), period)
