"""Per-pixel event index and the closest-event search of EventCap (paper Eqs. 12–13).

:func:`build_event_index` sorts one batch window's events by (pixel, time) once (a CSR layout:
``indptr[p]:indptr[p + 1]`` are pixel ``p = y·W + x``'s events in time order). Queries:

* :func:`events_at`: the events of one pixel in a time window (two ``searchsorted``);
* :func:`closest_events`: for many query pixels ``s_b`` at once, the event ``e = (u, t)``
  minimising ``D = λ_dist·((t_f − t)/(t_N − t_0))² + ‖s_b − u‖²`` (Eq. 12) among the events of
  an 8×8 patch around ``s_b`` whose time lies in ``[t_f − T_b/2, t_f + T_b/2]`` (both ends
  included).

An 8×8 patch has no centre pixel; the patch is offsets ``−4..+3`` in x and y from ``s_b``
(``−(P//2) .. P − P//2 − 1`` for patch size ``P``), so an odd ``P`` (e.g. 9) gives the
symmetric patch. Within one pixel the best event is the one nearest in time to ``t_f`` (the
spatial term is fixed), found for all query pixels together by one ``searchsorted`` on the
combined key ``pixel·span + (t − t_min)``; the only Python loop is over the P² patch offsets.
Ties go to the earlier offset (row-major, ``dy`` then ``dx``), then to the earlier event.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.events import EVENT_DTYPE, check_events
from mocaprig.errors import ValidationError
from mocaprig.validation import check_finite, check_positive, check_shape

__all__ = [
    "LAMBDA_DIST",
    "ClosestEvents",
    "EventIndex",
    "build_event_index",
    "closest_events",
    "events_at",
    "patch_offsets",
]

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]

#: Paper value of λ_dist (Eq. 12).
LAMBDA_DIST = 4.0


@dataclass(frozen=True, slots=True, eq=False)
class EventIndex:
    """Events of one window sorted by (pixel, time), with per-pixel offsets (CSR).

    Attributes:
        width, height: sensor size, px.
        indptr: (H·W + 1,) int64; pixel ``p = y·W + x`` owns rows ``indptr[p]:indptr[p + 1]``.
        t_us: event times (M,) int64, µs, sorted within each pixel.
        polarity: (M,) uint8, 1 = ON.
        source_index: row of each event in the array the index was built from (M,) int64.
        key: ``pixel·span_us + (t_us − t_min_us)`` (M,) int64, globally sorted.
        t_min_us: smallest time held (0 when empty).
        span_us: the key's time stride, ``t_max − t_min + 1``.
    """

    width: int
    height: int
    indptr: IntArray = field(repr=False)
    t_us: IntArray = field(repr=False)
    polarity: npt.NDArray[np.uint8] = field(repr=False)
    source_index: IntArray = field(repr=False)
    key: IntArray = field(repr=False)
    t_min_us: int
    span_us: int

    @property
    def num_events(self) -> int:
        """Number of events held."""
        return int(self.t_us.shape[0])


@dataclass(frozen=True, slots=True, eq=False)
class ClosestEvents:
    """Result of :func:`closest_events` for Q query pixels.

    Attributes:
        found: whether the patch held an event in the time window (Q,) bool.
        uv: pixel of the closest event (Q, 2) int64 as ``(x, y)``; -1 where none.
        t_us: its time (Q,) int64, µs; 0 where none.
        distance: its ``D`` of Eq. 12 (Q,), px²; ``inf`` where none.
        source_index: its row in the events the index was built from (Q,) int64; -1 where none.
    """

    found: npt.NDArray[np.bool_] = field(repr=False)
    uv: IntArray = field(repr=False)
    t_us: IntArray = field(repr=False)
    distance: FloatArray = field(repr=False)
    source_index: IntArray = field(repr=False)


def build_event_index(
    events: npt.ArrayLike,
    *,
    width: int,
    height: int,
    t_start_us: int | None = None,
    t_end_us: int | None = None,
) -> EventIndex:
    """Index ``events`` (canonical dtype) by pixel and time; built once per batch window.

    Args:
        events: events of :data:`acquire.events.EVENT_DTYPE` (any order).
        width, height: sensor size, px (240×180 DAVIS240C, 346×260 DAVIS346).
        t_start_us, t_end_us: keep only events with ``t_start_us <= t <= t_end_us`` (µs);
            ``None``: no limit on that side.

    Returns:
        :class:`EventIndex` (the input is not modified).

    Raises:
        ValidationError: wrong dtype, a non-positive sensor size, events outside the sensor,
            or a time span too long for the 64-bit key (split the recording into windows).
    """
    ev = check_events(events)
    if int(width) <= 0 or int(height) <= 0:
        msg = f"sensor size must be positive, got {width}x{height}"
        raise ValidationError(msg)
    w, h = int(width), int(height)
    keep = np.ones(ev.shape[0], dtype=bool)
    if t_start_us is not None:
        keep &= ev["t"] >= int(t_start_us)
    if t_end_us is not None:
        keep &= ev["t"] <= int(t_end_us)
    rows = np.flatnonzero(keep)
    sel = ev[rows]
    x = sel["x"].astype(np.int64)
    y = sel["y"].astype(np.int64)
    if x.size and (x.max() >= w or y.max() >= h):
        msg = (
            f"events reach pixel ({int(x.max())}, {int(y.max())}) outside the {w}x{h} sensor; "
            "pass the recording's sensor size (DAVIS240C 240x180, DAVIS346 346x260)"
        )
        raise ValidationError(msg)
    t = sel["t"].astype(np.int64)
    t_min = int(t.min()) if t.size else 0
    span = int(t.max()) - t_min + 1 if t.size else 1
    if span > np.iinfo(np.int64).max // (w * h + 1):
        msg = (
            f"events span {span} µs, too long to index at {w}x{h}; "
            "index one batch window at a time (t_start_us, t_end_us)"
        )
        raise ValidationError(msg)
    pix = y * w + x
    key = pix * span + (t - t_min)
    order = np.argsort(key, kind="stable")
    counts = np.bincount(pix, minlength=w * h)
    indptr = np.zeros(w * h + 1, dtype=np.int64)
    np.cumsum(counts, out=indptr[1:])
    return EventIndex(
        width=w,
        height=h,
        indptr=indptr,
        t_us=t[order],
        polarity=sel["p"][order].astype(np.uint8),
        source_index=rows[order].astype(np.int64),
        key=key[order],
        t_min_us=t_min,
        span_us=span,
    )


def events_at(
    index: EventIndex, x: int, y: int, *, t_start_us: int, t_end_us: int
) -> npt.NDArray[np.void]:
    """Events of pixel ``(x, y)`` with ``t_start_us <= t <= t_end_us``, in time order.

    Returns:
        A new array of :data:`acquire.events.EVENT_DTYPE`.

    Raises:
        ValidationError: the pixel is outside the sensor.
    """
    if not (0 <= x < index.width and 0 <= y < index.height):
        msg = f"pixel ({x}, {y}) is outside the {index.width}x{index.height} sensor"
        raise ValidationError(msg)
    p = y * index.width + x
    lo, hi = int(index.indptr[p]), int(index.indptr[p + 1])
    ts = index.t_us[lo:hi]
    a = lo + int(np.searchsorted(ts, t_start_us, side="left"))
    b = lo + int(np.searchsorted(ts, t_end_us, side="right"))
    out = np.empty(max(b - a, 0), dtype=EVENT_DTYPE)
    out["t"] = index.t_us[a:b]
    out["x"] = x
    out["y"] = y
    out["p"] = index.polarity[a:b]
    return out


def patch_offsets(patch_size: int) -> IntArray:
    """Offsets ``(P², 2)`` as ``(dx, dy)`` of a P×P patch: ``−(P//2) .. P − P//2 − 1``."""
    if int(patch_size) < 1:
        msg = f"patch_size must be >= 1, got {patch_size}"
        raise ValidationError(msg)
    r = np.arange(int(patch_size), dtype=np.int64) - int(patch_size) // 2
    dy, dx = np.meshgrid(r, r, indexing="ij")
    return np.stack([dx.ravel(), dy.ravel()], axis=-1)


def closest_events(
    index: EventIndex,
    query_uv: npt.ArrayLike,
    *,
    t_ref_us: int,
    half_window_us: int,
    batch_duration_us: int,
    lambda_dist: float = LAMBDA_DIST,
    patch_size: int = 8,
) -> ClosestEvents:
    """The closest event (Eq. 12–13) to each query pixel within a patch and a time window.

    Args:
        index: the batch window's :class:`EventIndex`.
        query_uv: query pixels ``s_b`` (Q, 2) as integer ``(x, y)``; pixels off the sensor
            simply see fewer patch pixels.
        t_ref_us: the tracking frame's time ``t_f``, µs.
        half_window_us: half the time window, µs (``T_b/2`` in the paper).
        batch_duration_us: ``t_N − t_0``, µs, the normaliser of the time term.
        lambda_dist: weight of the time term (paper: 4).
        patch_size: patch side P in pixels (paper: 8, offsets ``−4..+3``).

    Returns:
        :class:`ClosestEvents`.

    Raises:
        ValidationError: wrong shapes, non-integer pixels, negative window, non-positive batch
            duration or a negative ``lambda_dist``.
    """
    q = np.asarray(check_finite(check_shape(query_uv, ["Q", 2], name="query_uv")))
    if q.size and not np.all(q == np.round(q)):
        msg = "query_uv must hold integer pixel positions (x, y)"
        raise ValidationError(msg)
    q = q.astype(np.int64)
    if half_window_us < 0:
        msg = f"half_window_us must be >= 0, got {half_window_us}"
        raise ValidationError(msg)
    check_positive(float(batch_duration_us), name="batch_duration_us")
    if not lambda_dist >= 0:
        msg = f"lambda_dist must be >= 0, got {lambda_dist}"
        raise ValidationError(msg)
    n = q.shape[0]
    best_d = np.full(n, np.inf)
    best_row = np.full(n, -1, dtype=np.int64)
    t_lo, t_hi = int(t_ref_us) - int(half_window_us), int(t_ref_us) + int(half_window_us)
    w, h = index.width, index.height
    if n and index.num_events:
        # Time of the reference, clipped into the key's time range so it stays in its pixel.
        t_rel = int(np.clip(int(t_ref_us) - index.t_min_us, 0, index.span_us - 1))
        scale = float(lambda_dist) / float(batch_duration_us) ** 2
        m = index.num_events
        for dx, dy in patch_offsets(patch_size):
            px, py = q[:, 0] + dx, q[:, 1] + dy
            inside = (px >= 0) & (px < w) & (py >= 0) & (py < h)
            pix = np.where(inside, py * w + px, 0)
            lo, hi = index.indptr[pix], index.indptr[pix + 1]
            pos = np.searchsorted(index.key, pix * index.span_us + t_rel, side="left")
            spatial = float(dx * dx + dy * dy)
            # Candidates: the last event before t_ref and the first at/after it.
            for cand in (pos - 1, pos):
                ok = inside & (cand >= lo) & (cand < hi)
                c = np.clip(cand, 0, max(m - 1, 0))
                tc = index.t_us[c]
                ok &= (tc >= t_lo) & (tc <= t_hi)
                dt = (tc - int(t_ref_us)).astype(np.float64)
                d = scale * dt * dt + spatial
                better = ok & (d < best_d)
                best_d = np.where(better, d, best_d)
                best_row = np.where(better, c, best_row)
    found = best_row >= 0
    rows = np.where(found, best_row, 0)
    uv = np.full((n, 2), -1, dtype=np.int64)
    t_out = np.zeros(n, dtype=np.int64)
    src = np.full(n, -1, dtype=np.int64)
    if np.any(found):
        pix = index.key[rows[found]] // index.span_us
        uv[found, 0] = pix % w
        uv[found, 1] = pix // w
        t_out[found] = index.t_us[rows[found]]
        src[found] = index.source_index[rows[found]]
    return ClosestEvents(found=found, uv=uv, t_us=t_out, distance=best_d, source_index=src)
