"""The D415 clocks from the Vicon sync channel.

With a sync channel in the Vicon trial (``CalibrationOptions.sync_channel``, default
``D415_SYNC``: the sync box's toggle output on a Vicon analog input, docs/wiring.md §7), the
master's clock is the line through the channel's edges paired with its frames
(``calib.sync_edges.clock_from_sync_edges``, the video clock as the pairing prior), and every
camera tied to it by frame counters in the pool gets it through its tie plus its trigger delay
(:func:`sync_clocks`). :func:`sync_channel_inputs` gathers what that needs (:class:`SyncInputs`);
without the channel, or when it is unusable, the video clocks stay and a note says why.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.recording import Recording
from mocaprig.calib.calibration import ClockMapping
from mocaprig.calib.sync_edges import SyncEdges
from mocaprig.calib.vicon_calibration_frames import CalibCamera
from mocaprig.calib.vicon_calibration_options import (
    CalibrationOptions,
    D415PulseTiming,
)
from mocaprig.calib.vicon_calibration_pooled_clock import Tie, through_tie
from mocaprig.errors import CalibrationError, ValidationError

__all__ = ["SyncInputs", "sync_channel_edges", "sync_channel_inputs", "sync_clocks"]

_log = logging.getLogger(__name__)

I64 = npt.NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class SyncInputs:
    """The Vicon sync channel's edges and the D415 master they come from (or why not).

    ``frame_delay_ns`` and ``delays_ns`` follow the assumed pulse timing; ``master_exposure_ns``
    and ``exposures_ns`` (every other camera's exposure) let :func:`sync_clocks` try the other
    convention too (None / empty: it cannot).
    """

    edges: SyncEdges | None
    master: str | None = None
    master_frames_ns: I64 = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    frame_delay_ns: int = 0
    delays_ns: Mapping[str, float] = field(default_factory=dict)
    note: str = ""
    master_exposure_ns: float | None = None
    exposures_ns: Mapping[str, float] = field(default_factory=dict)


def sync_channel_edges(vicon_path: Path, opt: CalibrationOptions) -> tuple[SyncEdges | None, str]:
    """The edges of the Vicon trial's sync channel (Vicon clock), or ``None`` and a note saying
    why not (option off, no analog section or no such channel, unreadable or flat channel)."""
    from mocaprig.calib.sync_edges import find_sync_edges
    from mocaprig.calib.vicon import ViconFileError, read_c3d_analogs
    from mocaprig.calib.vicon_times import analog_times_ns

    label = opt.sync_channel
    fallback = "the D415 clocks come from the video"
    if label is None:
        return None, f"clock: sync channel not used (option); {fallback}"
    if vicon_path.suffix.lower() == ".csv":
        return None, (
            f"clock: a Nexus CSV export holds no analog channel (export the trial as C3D to use "
            f"the sync channel {label!r}); {fallback}"
        )
    try:
        analogs = read_c3d_analogs(vicon_path)
    except ViconFileError as err:
        return None, f"clock: no sync channel: {err}; {fallback}"
    try:
        values = analogs.channel(label)
    except ValidationError as err:
        return None, (
            f"clock: {err}; {fallback} (drift good to ~10 ppm only: record the sync box's "
            "toggle output on a Vicon analog input, docs/wiring.md §7)"
        )
    name = analogs.labels[analogs.index(label)]
    try:
        edges = find_sync_edges(analog_times_ns(analogs), values, channel=name, edge_model="fit")
        return edges, ""
    except CalibrationError as err:
        return None, f"clock: {err}; {fallback}"


def sync_channel_inputs(
    vicon_path: Path,
    rec: Recording,
    cams: Sequence[CalibCamera],
    frames_ns: Mapping[str, I64],
    opt: CalibrationOptions,
) -> SyncInputs:
    """The sync channel's edges (:func:`sync_channel_edges`), the master's frame stamps (those
    of the frames read for the calibration: the windows spread over the session pin the line
    to well under a µs and 0.1 ppm, and reading every ``frame_info`` would decompress the
    whole recording), its frame delay (stamp minus pulse, ±half its exposure as
    ``opt.pulse_timing`` says: the stamp is mid-exposure, the pulse at the exposure start or
    at the readout start) and, per other camera, its exposure's delay after the master's
    (``D415PulseTiming.slave_delay_ns``: the trigger delay plus half the exposure difference,
    plus the master's exposure when the pulse ends it). A missing or unusable channel gives
    ``edges=None`` and a note saying why."""
    fallback = "the D415 clocks come from the video"
    edges, note = sync_channel_edges(vicon_path, opt)
    if edges is None:
        return SyncInputs(None, note=note)
    name = edges.channel
    master = next((c for c in cams if c.sync_mode == 1), None)
    if master is None:
        return SyncInputs(
            None,
            note=(
                f"clock: sync channel {name!r} found but no calibrated D415 was recorded as the "
                f"sync master (sync_mode 1); {fallback}"
            ),
        )

    def exposure_ns(c: CalibCamera) -> float | None:
        return None if c.exposure_us is None else float(c.exposure_us) * 1e3

    exp_m = exposure_ns(master)
    if exp_m is None:
        return SyncInputs(
            None,
            note=f"clock: {master.name}'s metadata has no options.exposure_us; {fallback}",
        )
    timing = opt.pulse_timing
    exposures = {c.name: exposure_ns(c) or exp_m for c in cams if c is not master}
    return SyncInputs(
        edges,
        master.name,
        np.unique(np.asarray(frames_ns[master.name], dtype=np.int64)),
        timing.master_frame_delay_ns(exp_m),
        {c: timing.slave_delay_ns(exp_m, e) for c, e in exposures.items()},
        master_exposure_ns=exp_m,
        exposures_ns=exposures,
    )


#: Whole edge periods tried either side of a sync-channel mapping (see :func:`sync_clocks`).
_SYNC_PERIOD_SHIFTS: Final = 3


def _disagreement_ns(a: ClockMapping, b: ClockMapping) -> float:
    """|a − b| (ns) of two mappings of one device at ``a``'s anchor."""
    t = np.array([a.anchor_ns], dtype=np.int64)
    return abs(float(a.to_reference_ns(t)[0] - b.to_reference_ns(t)[0]))


_PhaseFit = tuple[D415PulseTiming, ClockMapping, float, int]

#: A convention's reprojection cost must be below this fraction of the other's to choose it.
_PHASE_COST_RATIO: Final = 0.97


def _choose_pulse_phase(
    m: str,
    fits: Sequence[_PhaseFit],
    timings: Sequence[D415PulseTiming],
    exposure_ns: float,
    mappings: Mapping[str, ClockMapping],
    own: Mapping[str, ClockMapping] | None,
    score: Callable[[str, ClockMapping], float] | None,
    best_period: Callable[[str, ClockMapping], tuple[ClockMapping, int]],
    opt: CalibrationOptions,
) -> tuple[_PhaseFit, str]:
    """The master's sync clock under the pulse convention the data tell, and a note (see
    :func:`sync_clocks`); each fit is ``(timing, mapping, |mapping − video| ns, periods)``."""
    by_timing = {f[0]: f[1] for f in fits}
    base_t, base = fits[0][0], fits[0][1]
    cands: list[_PhaseFit] = []
    for timing in timings:
        derived = timing not in by_timing
        mapping = by_timing.get(timing) or dataclasses.replace(
            base,
            offset_ns=base.offset_ns
            + timing.master_frame_delay_ns(exposure_ns)
            - base_t.master_frame_delay_ns(exposure_ns),
        )
        mapping, shift = best_period(m, mapping)
        cands.append((timing, mapping, float(derived), shift))
    video = own.get(m) if own is not None else None
    source = "its own video clock"
    if video is None or not math.isfinite(video.offset_ns):
        video, source = mappings[m], "the pooled video clock"
    gaps = [_disagreement_ns(c[1], video) for c in cands]
    ranked = sorted(range(len(cands)), key=lambda i: gaps[i])
    assumed = timings[0]
    names = " / ".join(c[0].describe() for c in cands)
    # The video clock tells only if it sits near one convention's clock and far from the other
    # (it is itself good to ≈ 0.1–1 ms; on a short or poor take it can be off by more).
    if gaps[ranked[0]] < 0.25 * exposure_ns and gaps[ranked[1]] > 0.75 * exposure_ns:
        best = cands[ranked[0]]
        note = (
            f"clock: pulse phase measured: {best[0].describe()} (the sync clock agrees with "
            f"{source} within {gaps[ranked[0]] / 1e3:.0f} µs, the other convention "
            f"{gaps[ranked[1]] / 1e3:.0f} µs off); the slave delay is that convention's "
            "published value, not measured"
        )
        return (best[0], best[1], gaps[ranked[0]], best[3]), note
    costs = [score(m, c[1]) for c in cands] if score is not None else []
    if costs and all(math.isfinite(c) for c in costs):
        lo = int(np.argmin(costs))
        if costs[lo] < _PHASE_COST_RATIO * costs[1 - lo]:
            best = cands[lo]
            note = (
                f"clock: pulse phase measured: {best[0].describe()} by the reprojection cost of "
                f"{m}'s frames ({costs[lo]:.4g} vs {costs[1 - lo]:.4g}; {source} is "
                f"{gaps[lo] / 1e3:.0f} / {gaps[1 - lo] / 1e3:.0f} µs from {names}); the slave "
                "delay is that convention's published value, not measured"
            )
            return (best[0], best[1], gaps[lo], best[3]), note
    told = (
        f"{source} is {gaps[0] / 1e3:.0f} / {gaps[1] / 1e3:.0f} µs from the sync clocks of "
        f"{names} (it tells only within a quarter exposure of one and three quarters of the "
        f"other; the exposure is {exposure_ns / 1e3:.0f} µs)"
        + (
            f", and their reprojection costs ({costs[0]:.4g} / {costs[1]:.4g}) do not differ either"
            if costs
            else ""
        )
    )
    keep = next(c for c in cands if c[0] == assumed)
    if opt.force:
        note = (
            f"clock: pulse phase NOT observable in this recording ({told}): {assumed.describe()} "
            "assumed (--force); a wrong one puts every D415 and DAVIS clock one exposure out"
        )
        _log.info("%s", note)
        return (keep[0], keep[1], gaps[cands.index(keep)], keep[3]), note
    msg = (
        f"{m}: the D415 pulse phase (where the master's sync pulse falls in its exposure) is "
        f"not observable in this recording: {told}. A wrong guess would put every D415 and "
        "DAVIS clock one exposure out, so the calibration is refused. Measure it once for "
        "the rig (docs/d415-timing.md §4) and pass --d415-pulse-at exposure-start|readout-start "
        "with --no-measure-pulse-phase, or record a take with faster marker motion, or pass "
        "--force to keep the assumed convention"
    )
    raise CalibrationError(msg)


def sync_clocks(
    sync: SyncInputs,
    mappings: Mapping[str, ClockMapping],
    ties: Mapping[str, Tie],
    opt: CalibrationOptions,
    score: Callable[[str, ClockMapping], float] | None = None,
    timing_out: list[D415PulseTiming] | None = None,
    *,
    own: Mapping[str, ClockMapping] | None = None,
) -> tuple[dict[str, ClockMapping], list[str]]:
    """The D415 clocks from the sync channel: the master's by its edges (the video mapping as
    the pairing prior), every camera tied to the pool's pivot (``ties``, from
    :func:`pooled_clocks`) through its tie, the master's tie inverted and the master's mapping,
    plus its exposure's delay after the master's. Cameras without a tie keep ``mappings``
    (video), and so does every camera when the master's fit fails; notes say so.

    The edges fix each clock only up to whole periods (a periodic train pairs as well one edge
    over): when the video prior is off by more than a quarter period (on the 30 s seed-11
    session the master's pooled video clock was 41 ms off), or a tie's counter shift is one
    frame off, the mapping is a whole period out. So each camera's mapping is moved by the
    number of edge periods (±:data:`_SYNC_PERIOD_SHIFTS`) whose ``score`` (the reprojection cost
    of its frames) is lowest; no move on a tie.

    Where the master's pulse falls (its exposure start or its readout start) moves its sync
    clock by one whole exposure. With ``opt.measure_pulse_phase`` both conventions' clocks are
    made (a convention whose edges do not pair within the prior is the other's clock moved by
    the difference of their frame delays) and the data choose: the one that agrees with the
    master's video clock (``own``: its clock from its own frames, which no convention enters;
    else ``mappings``) within a quarter exposure when the other is three quarters of an
    exposure off, else the one whose
    reprojection cost (``score``) is clearly lower. When neither tells, the phase is not
    observable in this recording: :class:`CalibrationError` names it and what to pass (with
    ``opt.force`` the assumed convention stays and a note says so). The convention used is
    appended to ``timing_out``.

    Raises:
        CalibrationError: the pulse phase is not observable and ``opt.force`` is off."""
    from mocaprig.calib.sync_edges import clock_from_sync_edges

    out = dict(mappings)
    m, edges = sync.master, sync.edges
    if m is None or edges is None or m not in mappings:
        return out, []
    period = float(np.median(np.diff(np.sort(edges.t_ns)))) if edges.count > 1 else 0.0
    moved: list[str] = []

    def best_period(name: str, mapping: ClockMapping) -> tuple[ClockMapping, int]:
        if score is None or not period > 0:
            return mapping, 0
        cands = [
            dataclasses.replace(mapping, offset_ns=mapping.offset_ns + round(k * period))
            for k in range(-_SYNC_PERIOD_SHIFTS, _SYNC_PERIOD_SHIFTS + 1)
        ]
        costs = [score(name, c) for c in cands]
        k = int(np.argmin(costs))
        if costs[k] < 0.99 * costs[_SYNC_PERIOD_SHIFTS]:
            return cands[k], k - _SYNC_PERIOD_SHIFTS
        return mapping, 0

    def note_move(name: str, shift: int) -> None:
        if shift:
            moved.append(f"{name} {shift:+d}")
            _log.info("%s: sync clock moved by %+d edge periods (reprojection cost)", name, shift)

    # Without the master's exposure both conventions give the same frame delay: one fit.
    timings = opt.pulse_timings() if sync.master_exposure_ns is not None else (opt.pulse_timing,)
    assumed = timings[0]
    fits: list[_PhaseFit] = []
    failure: CalibrationError | None = None
    for timing in timings:
        delay = (
            sync.frame_delay_ns
            if sync.master_exposure_ns is None
            else timing.master_frame_delay_ns(sync.master_exposure_ns)
        )
        try:
            fit = clock_from_sync_edges(
                m,
                edges,
                sync.master_frames_ns,
                prior=mappings[m],
                frame_delay_ns=delay,
                edge_delay_ns=round(opt.sync_latency_us * 1e3),
            )
        except CalibrationError as err:
            failure = failure or err
            continue
        fits.append((timing, fit, 0.0, 0))
    if not fits:
        _log.warning("%s", failure)
        return out, [f"clock: {failure}; the D415 clocks come from the video"]
    phase_note = ""
    if len(timings) == 2 and sync.master_exposure_ns is not None:
        chosen, phase_note = _choose_pulse_phase(
            m, fits, timings, sync.master_exposure_ns, mappings, own, score, best_period, opt
        )
    else:
        first = next((f for f in fits if f[0] is assumed), fits[0])
        moved_map, periods = best_period(m, first[1])
        chosen = (first[0], moved_map, 0.0, periods)
    timing, mmap, _, shift = chosen
    note_move(m, shift)
    if timing_out is not None:
        timing_out.append(timing)
    delays = dict(sync.delays_ns)
    if sync.master_exposure_ns is not None and sync.exposures_ns:
        exp_m = sync.master_exposure_ns
        delays = {c: timing.slave_delay_ns(exp_m, e) for c, e in sync.exposures_ns.items()}
    out[m] = mmap
    done = [m]
    tm = ties.get(m)
    if tm is not None and len(ties) >= 2:
        # The pivot's clock → the master's (its tie inverted) → Vicon (the sync line).
        anchor_p = mmap.anchor_ns + tm.a_ns + tm.s * (mmap.anchor_ns - tm.centre_ns)
        pivot_map = ClockMapping(
            device="pivot",
            reference=mmap.reference,
            offset_ns=round(mmap.anchor_ns + mmap.offset_ns - anchor_p),
            drift_ppm=((1.0 + mmap.drift_ppm * 1e-6) / (1.0 + tm.s) - 1.0) * 1e6,
            anchor_ns=round(anchor_p),
            drift_sigma_ppm=mmap.drift_sigma_ppm,
        )
        for c, tie in ties.items():
            if c == m or c not in out:
                continue
            mc = through_tie(
                c,
                tie,
                pivot_map,
                delay_ns=delays.get(c, 0.0),
                method=f"{mmap.method} via {m} (frame tie)",
            )
            sigma = math.hypot(
                mmap.offset_sigma_ns,
                tie.rms_ns / math.sqrt(max(tie.pairs, 1)),
                tm.rms_ns / math.sqrt(max(tm.pairs, 1)),
            )
            out[c], c_shift = best_period(c, dataclasses.replace(mc, offset_sigma_ns=sigma))
            note_move(c, c_shift)
            done.append(c)
    notes = [phase_note] if phase_note else []
    notes += [
        f"clock: {m} from the Vicon sync channel {edges.channel!r} ({edges.count} edges, "
        f"τ {edges.tau_ns / 1e3:.0f} µs; ±{mmap.offset_sigma_ns / 1e3:.1f} µs, "
        f"±{mmap.drift_sigma_ppm:.3f} ppm)"
        + (f", {len(done) - 1} more D415 through their frame ties" if len(done) > 1 else "")
    ]
    if moved:
        notes.append(
            "clock: whole edge periods chosen by the reprojection cost (the video prior or a "
            f"frame tie was a period out): {', '.join(moved)}"
        )
    for c in mappings:
        if c not in done:
            notes.append(f"{c}: video clock: it is not tied to {m}'s frames")
    # Cross-check against the video clocks (a wrong trigger delay or tie shows here).
    diffs = []
    for c in done:
        t = np.array([out[c].anchor_ns], dtype=np.int64)
        d_us = float(out[c].to_reference_ns(t)[0] - mappings[c].to_reference_ns(t)[0]) / 1e3
        diffs.append(f"{c} {d_us:+.0f} µs / {out[c].drift_ppm - mappings[c].drift_ppm:+.1f} ppm")
    notes.append("clock: sync channel minus video clock: " + "; ".join(diffs))
    return out, notes
