"""EventCap's evaluation: AE, absolute MPJPE, the linear baseline and Size.sec (paper §4).

**Pose error** (paper §4.1, Tables 1–2; eventcap-method.md §1.1). Tracking runs at 1 kHz; the
ground truth of the paper is at 100 fps, so errors are taken on every 10th tracking frame. AE is
the mean per-joint error after each frame is aligned to the truth by Procrustes analysis
(:func:`mocaprig.process.metrics.procrustes_align`): rotation and translation, and a scale only
when asked (the paper does not say; :attr:`TrackingErrors.with_scale` records the choice). The
absolute MPJPE, without any alignment, is reported beside it. Procrustes minimises the squared
error, so the per-frame RMS after alignment never exceeds the RMS before; the mean Euclidean
error (AE) is below MPJPE in practice but not by theorem. Both come per frame, per batch (the
frames between two APS frames) and as mean ± standard deviation over the evaluated frames, plus
AE.raw (frames at APS times) and AE.nonRaw (the others) as in Table 1.

**Linear baseline** (Table 1, "*_linear"): keypoints at the APS frames interpolated linearly to
every tracking frame (:func:`upsample_linear`).

**Size.sec** (Tables 1–2): bytes of raw input per second of capture (:func:`data_rate`). The
paper's units are binary: its "51.5 GB" for one minute of 640×480 RGB at 1000 fps is
640·480·3·1000·60 B / 2³⁰, so MB here is 2²⁰ B (:data:`MB`). Events count as either

* ``"canonical"``: the in-memory record, ``EVENT_DTYPE.itemsize`` = 13 B (int64 t, uint16 x, y,
  uint8 p), or
* ``"davis_usb"``: the DAVIS240C's own USB stream of 16-bit words (:func:`davis_usb_event_bytes`:
  one X word per event, one Y word per row and timestamp, a timestamp word per new µs and a wrap
  word per 32 768 µs);

APS frames count ``aps_frame_bytes`` each (240×180 8-bit = 43 200 B by default); the reference is
``reference_fps`` frames per second of ``reference_frame_bytes`` each (1000 fps of 240×180
8-bit = 41.20 MB/s). The paper's own 58.59 MB/s is 61 440 B per frame at 1000 fps, which no
240×180 8-bit frame gives; its assumptions are not stated.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.events import EVENT_DTYPE, check_events
from mocaprig.errors import ValidationError
from mocaprig.process.metrics import point_errors, procrustes_align
from mocaprig.validation import check_finite, check_positive, check_shape

__all__ = [
    "DAVIS240C_FRAME_BYTES",
    "DAVIS_TIMESTAMP_WRAP_US",
    "EVAL_STEP_FRAMES",
    "MB",
    "DataRate",
    "EventEncoding",
    "TrackingErrors",
    "data_rate",
    "davis_usb_event_bytes",
    "evaluate_tracking",
    "upsample_linear",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Evaluate every 10th tracking frame (1 kHz tracking, 100 fps ground truth in the paper).
EVAL_STEP_FRAMES = 10
#: One 240×180 8-bit grey frame, bytes.
DAVIS240C_FRAME_BYTES = 240 * 180
#: The paper's MB: 2**20 bytes.
MB = 2**20
#: The DAVIS 15-bit timestamp word wraps every 2**15 µs.
DAVIS_TIMESTAMP_WRAP_US = 2**15

#: How events are counted in Size.sec.
EventEncoding = Literal["canonical", "davis_usb"]


@dataclass(frozen=True, slots=True)
class TrackingErrors:
    """Errors of a tracked sequence on its evaluated frames (mm).

    Attributes:
        frame_indices: (E,) tracking-frame indices evaluated (every ``step``-th from ``offset``).
        ae_mm: (E,) per-frame AE: mean joint error after Procrustes.
        mpjpe_mm: (E,) per-frame absolute MPJPE (no alignment).
        batch_indices: (B,) batch of each row of the per-batch arrays (frame // batch_frames).
        batch_ae_mm: (B,) mean AE of the evaluated frames of each batch.
        batch_mpjpe_mm: (B,) mean absolute MPJPE per batch.
        ae_mean_mm: Mean of ``ae_mm`` (the paper's AE).
        ae_std_mm: Standard deviation of ``ae_mm`` over frames (the paper's STD; ddof 0).
        mpjpe_mean_mm: Mean of ``mpjpe_mm``.
        mpjpe_std_mm: Standard deviation of ``mpjpe_mm``.
        ae_raw_mean_mm: Mean AE at the APS frames (frame % batch_frames == 0); None if none.
        ae_nonraw_mean_mm: Mean AE at the other frames; None if none.
        with_scale: Whether the Procrustes alignment fitted a scale.
        step: Frame step of the evaluation.
        batch_frames: Tracking frames per batch (APS interval in ms at 1 kHz).
    """

    frame_indices: IntArray = field(repr=False)
    ae_mm: FloatArray = field(repr=False)
    mpjpe_mm: FloatArray = field(repr=False)
    batch_indices: IntArray = field(repr=False)
    batch_ae_mm: FloatArray = field(repr=False)
    batch_mpjpe_mm: FloatArray = field(repr=False)
    ae_mean_mm: float
    ae_std_mm: float
    mpjpe_mean_mm: float
    mpjpe_std_mm: float
    ae_raw_mean_mm: float | None
    ae_nonraw_mean_mm: float | None
    with_scale: bool
    step: int
    batch_frames: int

    def summary(self) -> str:
        """One line: AE ± STD with the alignment used, absolute MPJPE, frames evaluated."""
        align = "similarity (R, t, s)" if self.with_scale else "rigid (R, t)"
        return (
            f"AE {self.ae_mean_mm:.1f} ± {self.ae_std_mm:.1f} mm ({align} Procrustes per frame), "
            f"MPJPE {self.mpjpe_mean_mm:.1f} ± {self.mpjpe_std_mm:.1f} mm, "
            f"{self.ae_mm.size} frames (every {self.step}th)"
        )


def evaluate_tracking(
    pred_mm: npt.ArrayLike,
    true_mm: npt.ArrayLike,
    *,
    step: int = EVAL_STEP_FRAMES,
    offset: int = 0,
    batch_frames: int = 40,
    with_scale: bool = False,
) -> TrackingErrors:
    """AE and absolute MPJPE of a 1 kHz tracking on every ``step``-th frame.

    Args:
        pred_mm: (F, K, 3) tracked joints, one row per tracking frame, mm.
        true_mm: (F, K, 3) true joints in the same frame and order, mm. Rows that are not
            evaluated may hold NaN (ground truth exists only every ``step`` frames).
        step: Evaluate frames ``offset, offset + step, ...`` (paper: 10).
        offset: First evaluated frame.
        batch_frames: Tracking frames per batch; frames ``b·batch_frames`` are APS frames.
        with_scale: Also fit a scale in the Procrustes alignment.

    Raises:
        ValidationError: shapes differ, bad step/offset, or non-finite evaluated rows.
    """
    p_all = check_shape(pred_mm, ["F", "K", 3], name="pred_mm")
    t_all = check_shape(true_mm, list(p_all.shape), name="true_mm")
    if step < 1 or batch_frames < 1 or not 0 <= offset < p_all.shape[0]:
        msg = (
            f"need step >= 1, batch_frames >= 1 and 0 <= offset < {p_all.shape[0]} frames; got "
            f"step={step}, batch_frames={batch_frames}, offset={offset}"
        )
        raise ValidationError(msg)
    idx = np.arange(offset, p_all.shape[0], step, dtype=np.int64)
    p = np.asarray(check_finite(p_all[idx], name="pred_mm (evaluated frames)"), np.float64)
    t = np.asarray(check_finite(t_all[idx], name="true_mm (evaluated frames)"), np.float64)
    mpjpe = point_errors(p, t).mean(axis=1)
    aligned = procrustes_align(p, t, with_scale=with_scale).aligned
    ae = point_errors(aligned, t).mean(axis=1)
    batch = idx // batch_frames
    batches = np.unique(batch)
    raw = idx % batch_frames == 0
    return TrackingErrors(
        frame_indices=idx,
        ae_mm=ae,
        mpjpe_mm=mpjpe,
        batch_indices=batches,
        batch_ae_mm=np.array([ae[batch == b].mean() for b in batches]),
        batch_mpjpe_mm=np.array([mpjpe[batch == b].mean() for b in batches]),
        ae_mean_mm=float(ae.mean()),
        ae_std_mm=float(ae.std()),
        mpjpe_mean_mm=float(mpjpe.mean()),
        mpjpe_std_mm=float(mpjpe.std()),
        ae_raw_mean_mm=float(ae[raw].mean()) if raw.any() else None,
        ae_nonraw_mean_mm=float(ae[~raw].mean()) if (~raw).any() else None,
        with_scale=with_scale,
        step=step,
        batch_frames=batch_frames,
    )


def upsample_linear(
    key_t_us: npt.ArrayLike, key_joints: npt.ArrayLike, t_us: npt.ArrayLike
) -> FloatArray:
    """The "*_linear" baseline: joints at the APS frames interpolated linearly in time.

    Args:
        key_t_us: (M,) strictly increasing APS times, µs (M >= 2).
        key_joints: (M, K, D) joints at those times (any unit).
        t_us: (F,) times to fill, µs, inside [key_t_us[0], key_t_us[-1]].

    Returns:
        (F, K, D) interpolated joints.

    Raises:
        ValidationError: shapes, non-increasing key times or times outside the keys.
    """
    from scipy.interpolate import make_interp_spline

    kt = np.asarray(check_shape(key_t_us, ["M"], name="key_t_us"), np.float64)
    kj = np.asarray(
        check_finite(check_shape(key_joints, [kt.size, "K", "D"], name="key_joints")),
        np.float64,
    )
    tt = np.asarray(check_shape(t_us, ["F"], name="t_us"), np.float64)
    if kt.size < 2 or np.any(np.diff(kt) <= 0):
        msg = "key_t_us needs at least 2 strictly increasing times"
        raise ValidationError(msg)
    if tt.size and (tt.min() < kt[0] or tt.max() > kt[-1]):
        msg = (
            f"t_us spans [{tt.min():.0f}, {tt.max():.0f}] µs, outside the keys "
            f"[{kt[0]:.0f}, {kt[-1]:.0f}]; linear interpolation does not extrapolate"
        )
        raise ValidationError(msg)
    return np.asarray(make_interp_spline(kt, kj, k=1, axis=0)(tt), np.float64)


def davis_usb_event_bytes(events: npt.NDArray[np.void]) -> int:
    """Bytes the DAVIS240C's USB stream spends on these polarity events (2-byte words).

    Per the device's word format (shared docs/davis240c-usb.md §7–8): one X word per event, one
    Y word per (timestamp, row) group, one 15-bit timestamp word per distinct µs that is not a
    multiple of 32 768, and one wrap word per 32 768 µs rollover between the first and last
    event.
    APS, IMU and special words are not counted.

    Raises:
        ValidationError: not an event array or not sorted by time.
    """
    ev = check_events(events)
    if ev.size == 0:
        return 0
    t = ev["t"].astype(np.int64)
    if np.any(np.diff(t) < 0):
        msg = "events are not sorted by t; sort them before counting USB words"
        raise ValidationError(msg)
    groups = np.unique(np.stack([t, ev["y"].astype(np.int64)]), axis=1).shape[1]
    times = np.unique(t)
    stamps = int(np.count_nonzero(times % DAVIS_TIMESTAMP_WRAP_US))
    wraps = int(t[-1] // DAVIS_TIMESTAMP_WRAP_US - t[0] // DAVIS_TIMESTAMP_WRAP_US)
    return 2 * (int(ev.size) + int(groups) + stamps + wraps)


@dataclass(frozen=True, slots=True)
class DataRate:
    """Size.sec: raw input per second of capture, ours vs frame baselines.

    Attributes:
        duration_us: Length of the processed interval, µs.
        n_events: Events in it.
        event_bytes: Their size under ``event_encoding``.
        n_aps_frames: APS frames used.
        aps_bytes: Their size.
        event_encoding: How events were counted.
        reference_fps: Frame rate of the high-fps reference (paper: 1000).
        reference_frame_bytes: Bytes per reference frame.
    """

    duration_us: int
    n_events: int
    event_bytes: int
    n_aps_frames: int
    aps_bytes: int
    event_encoding: EventEncoding
    reference_fps: float
    reference_frame_bytes: int

    @property
    def seconds(self) -> float:
        """Duration, s."""
        return self.duration_us * 1e-6

    @property
    def bytes_per_event(self) -> float:
        """Mean bytes per event (NaN without events)."""
        return self.event_bytes / self.n_events if self.n_events else float("nan")

    @property
    def events_bytes_per_s(self) -> float:
        """Event bytes per second."""
        return self.event_bytes / self.seconds

    @property
    def aps_bytes_per_s(self) -> float:
        """APS bytes per second: the "*_linear" baselines' input."""
        return self.aps_bytes / self.seconds

    @property
    def ours_bytes_per_s(self) -> float:
        """Events plus APS frames per second: EventCap's input."""
        return self.events_bytes_per_s + self.aps_bytes_per_s

    @property
    def reference_bytes_per_s(self) -> float:
        """High-fps frames per second: the "*_all" / "*_refer" baselines' input."""
        return self.reference_fps * self.reference_frame_bytes

    @property
    def ratio(self) -> float:
        """Ours / reference (paper: 2.02 / 58.59 ≈ 3.4 %)."""
        return self.ours_bytes_per_s / self.reference_bytes_per_s

    def summary(self) -> str:
        """One line in the paper's MB (2**20 B) per second."""
        return (
            f"Size.sec ours {self.ours_bytes_per_s / MB:.3f} MB/s (events "
            f"{self.events_bytes_per_s / MB:.3f} at {self.bytes_per_event:.2f} B/event, "
            f"{self.event_encoding}; APS {self.aps_bytes_per_s / MB:.3f}), "
            f"{self.reference_fps:g} fps frames {self.reference_bytes_per_s / MB:.2f} MB/s, "
            f"ratio {100 * self.ratio:.2f} %"
        )


def data_rate(
    events: npt.NDArray[np.void],
    *,
    t_start_us: int,
    t_end_us: int,
    n_aps_frames: int,
    event_encoding: EventEncoding = "canonical",
    aps_frame_bytes: int = DAVIS240C_FRAME_BYTES,
    reference_fps: float = 1000.0,
    reference_frame_bytes: int = DAVIS240C_FRAME_BYTES,
) -> DataRate:
    """Size.sec of the events in ``[t_start_us, t_end_us)`` plus ``n_aps_frames`` APS frames.

    Args:
        events: Event array (:data:`~mocaprig.acquire.events.EVENT_DTYPE`), sorted by ``t``.
        t_start_us: Start of the processed interval, µs.
        t_end_us: End (exclusive), µs.
        n_aps_frames: APS frames used in the interval.
        event_encoding: ``"canonical"`` (13 B per event) or ``"davis_usb"``.
        aps_frame_bytes: Bytes per APS frame.
        reference_fps: Frame rate of the high-fps reference.
        reference_frame_bytes: Bytes per reference frame.

    Raises:
        ValidationError: an empty interval, negative counts or an unknown encoding.
    """
    ev = check_events(events)
    if t_end_us <= t_start_us or n_aps_frames < 0 or aps_frame_bytes < 0:
        msg = (
            f"need t_end_us > t_start_us and non-negative frame counts and sizes; got "
            f"[{t_start_us}, {t_end_us}), n_aps_frames={n_aps_frames}, "
            f"aps_frame_bytes={aps_frame_bytes}"
        )
        raise ValidationError(msg)
    check_positive(reference_fps, name="reference_fps")
    check_positive(reference_frame_bytes, name="reference_frame_bytes")
    if np.any(np.diff(ev["t"].astype(np.int64)) < 0):
        msg = "events are not sorted by t; sort them before measuring Size.sec"
        raise ValidationError(msg)
    lo, hi = np.searchsorted(ev["t"], [t_start_us, t_end_us], side="left")
    used = ev[lo:hi]
    if event_encoding == "canonical":
        ev_bytes = int(used.size) * EVENT_DTYPE.itemsize
    elif event_encoding == "davis_usb":
        ev_bytes = davis_usb_event_bytes(used)
    else:  # reachable from untyped callers
        msg = f"unknown event_encoding {event_encoding!r}; use 'canonical' or 'davis_usb'"  # type: ignore[unreachable]
        raise ValidationError(msg)
    return DataRate(
        duration_us=int(t_end_us - t_start_us),
        n_events=int(used.size),
        event_bytes=ev_bytes,
        n_aps_frames=int(n_aps_frames),
        aps_bytes=int(n_aps_frames) * int(aps_frame_bytes),
        event_encoding=event_encoding,
        reference_fps=float(reference_fps),
        reference_frame_bytes=int(reference_frame_bytes),
    )
