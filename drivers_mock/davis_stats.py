"""Event-stream statistics for comparing the DAVIS simulator with real DAVIS recordings.

The measures of ``docs/davis-sim.md`` (issue 15): event rate, ON fraction, same-pixel interval
percentiles, isolated (background-activity) events per pixel, and the contrast threshold seen
through events per unit of log-intensity change. Events are
:data:`mocaprig.acquire.events.EVENT_DTYPE` arrays (``t`` in µs); the sensor size is always a
parameter (240×180 DAVIS240C, 346×260 DAVIS346).

The simulated scenes the measures run on (a static world, a DAVIS346 rig, a global light ramp)
are here too, so the benchmark and the tests use the same ones.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.events import check_events
from mocaprig.drivers_mock.davis240c_render import log_intensity
from mocaprig.drivers_mock.rig import PinholeCamera
from mocaprig.errors import ValidationError
from mocaprig.validation import check_finite, check_positive, check_shape

if TYPE_CHECKING:
    from mocaprig.drivers_mock.davis240c_sim import DavisSimulator
    from mocaprig.drivers_mock.scenario import Scenario

__all__ = [
    "ContrastFit",
    "EventStats",
    "as_davis346",
    "event_stats",
    "fit_contrast",
    "isolated_mask",
    "ramp_contrast",
    "same_pixel_intervals_us",
    "static_world",
]

_log = logging.getLogger(__name__)

I64 = npt.NDArray[np.int64]
F64 = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class EventStats:
    """Summary statistics of one event stream.

    Attributes:
        events: Number of events.
        duration_s: Time span used for the rates (s).
        events_per_s: ``events / duration_s``.
        on_fraction: Fraction of ON events (NaN without events).
        active_pixels: Pixels with at least one event.
        interval_count: Number of same-pixel intervals (consecutive events of one pixel).
        interval_min_ms: Shortest same-pixel interval (ms; NaN without intervals).
        interval_p1_ms: 1st percentile of the same-pixel intervals (ms).
        interval_p50_ms: Median same-pixel interval (ms).
        interval_under_1p5ms: Fraction of same-pixel intervals shorter than 1.5 ms.
        isolated_fraction: Fraction of events with no other event in their 3×3 neighbourhood
            (own pixel included) within ``±isolation_us``.
        isolated_hz_per_pixel: Isolated events per sensor pixel per second.
    """

    events: int
    duration_s: float
    events_per_s: float
    on_fraction: float
    active_pixels: int
    interval_count: int
    interval_min_ms: float
    interval_p1_ms: float
    interval_p50_ms: float
    interval_under_1p5ms: float
    isolated_fraction: float
    isolated_hz_per_pixel: float


def _check_size(sensor_size: tuple[int, int]) -> tuple[int, int]:
    w, h = (int(v) for v in sensor_size)
    if w < 1 or h < 1:
        msg = f"sensor_size must be (width, height) with both >= 1, got {sensor_size}"
        raise ValidationError(msg)
    return w, h


def _pixel_index(events: npt.NDArray[np.void], width: int, height: int) -> I64:
    x = events["x"].astype(np.int64)
    y = events["y"].astype(np.int64)
    if x.size and (int(x.max()) >= width or int(y.max()) >= height):
        msg = (
            f"events lie outside a {width}×{height} sensor (x up to {int(x.max())}, y up to "
            f"{int(y.max())}); pass the recording's sensor_size"
        )
        raise ValidationError(msg)
    out: I64 = y * width + x
    return out


def same_pixel_intervals_us(
    events: npt.ArrayLike, *, sensor_size: tuple[int, int], same_polarity: bool = False
) -> I64:
    """Times between consecutive events of the same pixel (µs, int64, any order).

    Args:
        events: Event array (any time order).
        sensor_size: ``(width, height)`` in pixels.
        same_polarity: Only pair events of equal polarity (ON with ON, OFF with OFF).

    Raises:
        ValidationError: not an event array, or events outside the sensor.
    """
    ev = check_events(events)
    w, h = _check_size(sensor_size)
    key = _pixel_index(ev, w, h)
    if same_polarity:
        key = key * 2 + ev["p"].astype(np.int64)
    t = ev["t"].astype(np.int64)
    order = np.lexsort((t, key))
    k, ts = key[order], t[order]
    same = k[1:] == k[:-1]
    out: I64 = (ts[1:] - ts[:-1])[same]
    return out


def isolated_mask(
    events: npt.ArrayLike,
    *,
    sensor_size: tuple[int, int],
    window_us: int = 5000,
    radius_px: int = 1,
) -> npt.NDArray[np.bool_]:
    """Which events have no other event within ``±window_us`` in their neighbourhood.

    The neighbourhood is the ``(2·radius_px + 1)²`` square around the event's pixel, the pixel
    itself included (data README: "no other event at the same pixel or its 8 neighbours within
    ±5 ms"). Result is in the input's order.

    Raises:
        ValidationError: not an event array, events outside the sensor or a negative window.
    """
    ev = check_events(events)
    w, h = _check_size(sensor_size)
    if window_us < 0 or radius_px < 0:
        msg = f"window_us and radius_px must be >= 0, got {window_us}, {radius_px}"
        raise ValidationError(msg)
    n = ev.size
    if n == 0:
        return np.zeros(0, dtype=bool)
    x = ev["x"].astype(np.int64)
    y = ev["y"].astype(np.int64)
    pix = _pixel_index(ev, w, h)
    t = ev["t"].astype(np.int64)
    t = t - int(t.min())
    # One sortable key per event: pixel-major, time-minor, with a time span per pixel wide
    # enough that a ±window search never leaks into the next pixel.
    span = int(t.max()) + 2 * int(window_us) + 2
    key = pix * span + t + int(window_us)
    order = np.argsort(key, kind="stable")
    skey = key[order]
    lonely = np.ones(n, dtype=bool)
    for dy in range(-radius_px, radius_px + 1):
        for dx in range(-radius_px, radius_px + 1):
            nx, ny = x + dx, y + dy
            inside = (nx >= 0) & (nx < w) & (ny >= 0) & (ny < h)
            base = (ny * w + nx) * span + int(window_us)
            lo = np.searchsorted(skey, base + t - window_us, side="left")
            hi = np.searchsorted(skey, base + t + window_us, side="right")
            count = hi - lo
            if dx == 0 and dy == 0:
                count = count - 1  # the event itself
            lonely &= ~(inside & (count > 0))
    return lonely


def event_stats(
    events: npt.ArrayLike,
    *,
    sensor_size: tuple[int, int],
    duration_us: int | None = None,
    isolation_us: int = 5000,
) -> EventStats:
    """The :class:`EventStats` of an event stream.

    Args:
        events: Event array.
        sensor_size: ``(width, height)`` in pixels.
        duration_us: Time span for the rates (µs); default: last minus first event time.
        isolation_us: Half-width of the isolation window (µs).

    Raises:
        ValidationError: not an event array, events outside the sensor or a non-positive
            duration.
    """
    ev = check_events(events)
    w, h = _check_size(sensor_size)
    if duration_us is None:
        duration_us = int(ev["t"].max() - ev["t"].min()) if ev.size > 1 else 0
    if duration_us <= 0:
        msg = f"event_stats needs a positive duration, got {duration_us} µs ({ev.size} events)"
        raise ValidationError(msg)
    dur_s = duration_us * 1e-6
    iv = same_pixel_intervals_us(ev, sensor_size=(w, h)).astype(np.float64) * 1e-3
    lonely = isolated_mask(ev, sensor_size=(w, h), window_us=isolation_us)
    nan = float("nan")
    return EventStats(
        events=int(ev.size),
        duration_s=dur_s,
        events_per_s=ev.size / dur_s,
        on_fraction=float(ev["p"].mean()) if ev.size else nan,
        active_pixels=int(np.unique(_pixel_index(ev, w, h)).size),
        interval_count=int(iv.size),
        interval_min_ms=float(iv.min()) if iv.size else nan,
        interval_p1_ms=float(np.percentile(iv, 1.0)) if iv.size else nan,
        interval_p50_ms=float(np.median(iv)) if iv.size else nan,
        interval_under_1p5ms=float(np.mean(iv < 1.5)) if iv.size else nan,
        isolated_fraction=float(lonely.mean()) if ev.size else nan,
        isolated_hz_per_pixel=float(lonely.sum()) / (w * h) / dur_s,
    )


@dataclass(frozen=True, slots=True)
class ContrastFit:
    """Contrast thresholds recovered from events and log-intensity changes.

    Attributes:
        c_on: ON threshold (ln units): log-intensity rise per ON event.
        c_off: OFF threshold (ln units): log-intensity fall per OFF event.
        offset_up_ln: Rise at which the fitted ON count line reaches zero (the part of the dead
            band a pixel crosses before its first event; 0 when not fitted).
        offset_down_ln: Same for falls.
        events_per_ln: All events per pixel per unit of ``|ΔL|`` over the samples used.
        samples: Pixel samples used in the fit.
        residual_ln: RMS residual of the net counts about the fitted lines (events).
    """

    c_on: float
    c_off: float
    offset_up_ln: float
    offset_down_ln: float
    events_per_ln: float
    samples: int
    residual_ln: float


def _slope_fit(x: F64, y: F64, *, offsets: bool) -> tuple[float, float, F64]:
    """Least-squares ``y ≈ s·x (+ b)``; returns ``(s, b, residuals)`` (NaN slope if no data)."""
    if x.size == 0:
        return float("nan"), 0.0, np.zeros(0)
    a = np.stack([x, np.ones_like(x)], axis=1) if offsets else x[:, None]
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    b = float(coef[1]) if offsets else 0.0
    return float(coef[0]), b, y - a @ coef


def fit_contrast(
    pairs: Sequence[tuple[npt.ArrayLike, npt.ArrayLike]],
    *,
    min_change_ln: float = 0.3,
    offsets: bool = True,
) -> ContrastFit:
    """Contrast thresholds as the inverse slope of event counts against ``|ΔL|``.

    A pixel whose log intensity rises by ``ΔL`` gives about ``ΔL / C_on`` more ON than OFF
    events (falls: OFF events and ``C_off``), less whatever it misses (dead time, bandwidth).
    Rising and falling pixel samples are fitted separately: net count against ``|ΔL|``, by
    least squares; the threshold is 1 / slope. ``ΔL`` is the regressor because it is the
    quantity known without error in a simulation (counts scatter with the per-pixel threshold
    mismatch, and regressing ``ΔL`` on them would dilute the slope); the result is the
    harmonic mean of the per-pixel thresholds. A pixel that starts a rise right after a fall
    first crosses its whole dead band ``(−C_off, C_on)``; with ``offsets`` an intercept per
    direction absorbs that, and the slope gives the threshold when the samples span a range of
    ``ΔL`` (e.g. nested intervals from one start along a ramp). For pixels whose intensity
    went both ways inside an interval the net count mixes the two thresholds.

    Args:
        pairs: ``(events, delta_log)`` samples: the events of one interval and the
            ``(height, width)`` log-intensity change (ln units) over it.
        min_change_ln: Smallest ``|ΔL|`` of a pixel sample that enters the fit (ln units).
        offsets: Fit an intercept per direction of change.

    Raises:
        ValidationError: not event arrays, a non-finite ``delta_log``, events outside it, or
            fewer than 10 usable samples.
    """
    xs: list[F64] = []
    ys: list[F64] = []
    counts: list[F64] = []
    for events, delta_log in pairs:
        ev = check_events(events)
        dl = np.asarray(delta_log, dtype=np.float64)
        check_shape(dl, ["h", "w"], name="delta_log")
        check_finite(dl, name="delta_log")
        h, w = dl.shape
        pix = _pixel_index(ev, w, h)
        on = ev["p"] != 0
        n_on = np.bincount(pix[on], minlength=w * h).astype(np.float64)
        n_off = np.bincount(pix[~on], minlength=w * h).astype(np.float64)
        target = dl.ravel()
        use = np.abs(target) >= min_change_ln
        xs.append(target[use])
        ys.append((n_on - n_off)[use])
        counts.append((n_on + n_off)[use])
    x = np.concatenate(xs) if xs else np.zeros(0)
    y = np.concatenate(ys) if ys else np.zeros(0)
    if x.size < 10:
        msg = (
            f"fit_contrast: only {x.size} pixel samples change by >= {min_change_ln} ln; "
            "use longer intervals or a lower min_change_ln"
        )
        raise ValidationError(msg)
    up = x > 0
    s_up, b_up, r_up = _slope_fit(x[up], y[up], offsets=offsets)
    s_dn, b_dn, r_dn = _slope_fit(-x[~up], -y[~up], offsets=offsets)
    resid = np.concatenate([r_up, r_dn])

    def inv(s: float) -> float:
        return 1.0 / s if np.isfinite(s) and s > 0 else float("nan")

    return ContrastFit(
        c_on=inv(s_up),
        c_off=inv(s_dn),
        offset_up_ln=-b_up * inv(s_up) if offsets else 0.0,
        offset_down_ln=-b_dn * inv(s_dn) if offsets else 0.0,
        events_per_ln=float(np.concatenate(counts).sum() / np.abs(x).sum()),
        samples=int(x.size),
        residual_ln=float(np.sqrt(np.mean(resid**2))) if resid.size else float("nan"),
    )


# --------------------------------------------------------------------------------------------
# simulated scenes for the measures


def static_world(sc: Scenario, t_ns: int) -> Scenario:
    """``sc`` with the actor holding its pose at ``t_ns`` and the clapperboard kept closed.

    Only noise (and light changes) make events in it: the background-activity measure.
    """
    from mocaprig.process.body.motion import Motion

    pose = sc.pose(np.array([int(t_ns)], dtype=np.int64))
    cb = sc.clapperboard
    # One clap a minute after the session's end: closed throughout.
    still = replace(
        cb,
        clap_times_ns=(sc.duration_ns + 60_000_000_000,),
        open_angles_rad=cb.open_angles_rad[:1],
        closing_s=cb.closing_s[:1],
    )
    return replace(sc, motion=Motion("frozen", 1.0, pose), clapperboard=still)


def as_davis346(sc: Scenario) -> Scenario:
    """``sc`` seen by a DAVIS346 (346×260; same 18.5 µm pitch, lens, pose and centre offset)."""
    cam = sc.rig.davis.camera
    k = np.array(cam.K, dtype=np.float64)
    k[0, 2] += (346 - cam.width) / 2.0
    k[1, 2] += (260 - cam.height) / 2.0
    cam346 = PinholeCamera(cam.name, 346, 260, k, cam.distortion, cam.T_world_cam)
    return replace(sc, rig=replace(sc.rig, davis=replace(sc.rig.davis, camera=cam346)))


def ramp_contrast(
    sim: DavisSimulator, *, steps: int = 8, min_change_ln: float = 0.6
) -> tuple[ContrastFit, ContrastFit]:
    """``C_on`` from a rising and ``C_off`` from a falling half-period of a light ramp.

    ``sim`` must be fresh (no window fetched yet) and light its world with a sinusoidal
    flicker (``DavisLook.flicker_hz``, e.g. 0.5–1 Hz and depth 0.5: slow enough that dead time
    and bandwidth lose < 3 % of ``ΔL``). The
    pixels adapt at the darkest instant; the samples are nested intervals from there (and from
    the brightest instant) to ``steps`` points along the half period, each with the true
    per-pixel ``ΔL`` of the noise-free renders. Samples under ``min_change_ln`` are left out:
    below about ``C_on + C_off`` not every pixel has crossed its dead band yet and the count is
    not linear in ``ΔL`` (:func:`fit_contrast`).

    Returns:
        The fit of the rise (its ``c_on``) and of the fall (its ``c_off``).

    Raises:
        ValidationError: no flicker in ``sim``'s world, or too few changing pixels.
    """
    hz = float(sim.renderer.look.flicker_hz)
    check_positive(hz, name="the simulator's DavisLook.flicker_hz")
    if sim.renderer.look.flicker_depth <= 0:
        msg = "ramp_contrast needs a DavisLook with flicker_depth > 0 (a light ramp)"
        raise ValidationError(msg)
    period_us = round(1e6 / hz)
    # DavisLook flicker is 1 + depth·sin(2π f t): darkest at 3/4 of a period, brightest at
    # 5/4; the slope is zero there, so the pixels' low-pass lag is too.
    t_dark, t_bright = 3 * period_us // 4, 5 * period_us // 4
    fits: list[ContrastFit] = []
    for a, b in ((t_dark, t_bright), (t_bright, t_bright + period_us // 2)):
        ev = sim.activity(a, b).events
        l_a = log_intensity(sim.render_intensity(int(sim.session_ns(a))))
        pairs = []
        for k in range(1, steps + 1):
            t = a + (b - a) * k // steps
            l_t = log_intensity(sim.render_intensity(int(sim.session_ns(t))))
            pairs.append((ev[ev["t"] < t], l_t - l_a))
        fits.append(fit_contrast(pairs, min_change_ln=min_change_ln))
    return fits[0], fits[1]
