"""The main job on the simulated rig: ``mocaprig demo``.

It runs the whole toolkit as far as it exists and reports its figures against ground truth.
Today: simulate a session (truth + Vicon C3D/CSV) -> record it through the real drivers talking
to the mock devices (``session.mcap``; :func:`drivers_mock.session.record_session`) -> ``info``
on the recording, the D415 sync check (:class:`mocaprig.acquire.d415_sync.SyncChecker`) over
the recorded frame timing, the DAVIS decode statistics and the pairing of the DAVIS trigger
pulses with the D415 master's frames -> read the Vicon exports back through the product reader
(:mod:`mocaprig.calib.vicon`) -> compare with the truth -> calibrate the D415s and the DAVIS
clock against the Vicon trial (:mod:`calib.vicon_calibration`), write its report
(:data:`CALIBRATION_REPORT`: figures beside the JSON, :mod:`calib.report`) and score the
calibration against the truth -> DeMoCap figures of the committed ``lite`` checkpoint on
held-out simulated takes (:func:`process.democap.demo_figures`) and, where the motion corpus is
there, on its test split of real motion (:func:`process.democap.evaluate.unseen_real`, the
headline protocol) -> DeMoCap replay of the
recording with that calibration (:func:`process.democap.run_replay`: ``results.mcap``,
``results.c3d``, ``results.csv``; every :data:`REPLAY_EVERY`-th rig instant) scored against the
truth, with the reconstructed skeleton against the truth (:data:`SKELETON_FIGURE`) -> the
actor calibrated from the recording (:func:`process.democap.replay.fit_subject`,
:data:`SUBJECT_FILE`) and the replay solved as that subject -> DeMoCap live on the mock rig
-> ``mocaprig process`` on the session (in-process; run again, it keeps the finished outputs)
-> EventCap on a short simulated DAVIS take with truth, scored with the paper's baselines
(:func:`process.eventcap.evaluate.evaluate_take`; synthetic detections, labelled so) -> with
``davis_dvs``, ``eventcap run`` on the demo's own recording (synthetic detections and the
simulator's true DAVIS calibration standing in for ``calibrate board``), scored against the
truth -> a summary figure and report. Stages not built yet are listed in the report as pending,
never faked; a stage that fails is reported as failed and the command exits 1. ``progress``
reports every stage.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from mocaprig import __version__
from mocaprig.acquire.device_id import DeviceId
from mocaprig.calib.vicon import MarkerTrajectories, read_c3d, read_nexus_csv
from mocaprig.drivers_mock.session import SimulationResult, simulate_session
from mocaprig.drivers_mock.truth import Truth, read_truth
from mocaprig.errors import MocaprigError, ProcessingError, RecordingError, ValidationError
from mocaprig.json_values import to_jsonable

if TYPE_CHECKING:
    from mocaprig.process.democap.replay import ReplayResult

__all__ = [
    "CALIBRATION_REPORT",
    "REPLAY_EVERY",
    "SKELETON_FIGURE",
    "SUBJECT_FILE",
    "UNSEEN_REAL_FRAMES",
    "DemoReport",
    "run_demo",
]

_log = logging.getLogger(__name__)

Progress = Callable[[int, int], None]
#: A stage-aware progress callback ``(stage, done, total)`` (as ``process.eventcap.run``'s).
StageReport = Callable[[str, int, int], None]

#: Stages of the main job not built yet; the report lists them as pending.
_PENDING_STAGES: tuple[tuple[str, str], ...] = ()
#: The EventCap stage's take: an excerpt of fast punches and kicks (the karate scenario after
#: its static start), simulated by the realistic DAVIS240C, scored batch by batch. The DAVIS
#: is simulated until the frames of the stage's batches are complete, not to the scenario's
#: end: the DVS costs ~20 s of CPU per simulated second.
EVENTCAP_TAKE: dict[str, Any] = {"scenario": "karate", "seconds": 3.0, "start_s": 1.6}
#: Batches (40 ms each) the demo's EventCap stages run.
EVENTCAP_BATCHES = 6
#: Where on the DAVIS timeline (s) ``eventcap run`` starts on the demo's own recording.
EVENTCAP_RUN_START_S = 1.6
#: ``mocaprig process`` in the demo: DeMoCap on every n-th rig instant of the session, in spans
#: of this many instants (so that the demo joins spans, as a cluster run does).
PROCESS_EVERY = 15
PROCESS_SPAN = 4

#: The demo's figure of the replayed DeMoCap skeleton against the truth (in its folder).
SKELETON_FIGURE = "democap_skeleton.png"
#: The demo's calibration report folder (``calibrate vicon --report``; ``index.html`` in it).
CALIBRATION_REPORT = "calibration_report"

#: The words the demo's progress shows for the EventCap stages' steps.
_EVENTCAP_STAGES = {"eventcap": "batches", "linear": "*_linear baseline", "all": "*_all baseline"}
_EVENTCAP_RUN_STAGES = {"index": "indexing", "batches": "batches", "write": "writing"}

#: The demo replays every n-th rig instant of its recording (10 Hz of the 30 Hz D415s) to keep
#: its extra time small.
REPLAY_EVERY = 3
#: Instants of the recording the demo calibrates its actor from (``democap subject``).
SUBJECT_INSTANTS = 24
#: The demo's subject file (in its folder).
SUBJECT_FILE = "democap_subject.json"
#: The replay with the calibrated subject runs on every n-th instant (half the replay's).
SUBJECT_REPLAY_EVERY = 2 * REPLAY_EVERY
#: Seconds of the mock rig the demo runs ``democap live`` on.
LIVE_SECONDS = 1.0
#: What the demo's simulated DeMoCap figures hold out: they are the ``in-distribution``
#: protocol (docs/democap.md, "Protocols"): the procedural actions, body sampler and D415 model
#: of training. The held-out real-motion figure is the ``democap_unseen_real`` stage (a
#: small budget of ``democap eval --protocol unseen-real``).
_IN_DISTRIBUTION = (
    "bodies and takes never trained on; the actions, body sampler and observation model are "
    "training's (the real-motion figure: democap_unseen_real)"
)
#: Frames per clip of the demo's ``unseen-real`` figure (11 test clips, one new body each; the
#: docs' figure is ``democap eval --protocol unseen-real``: 20 frames per clip, 3 seeds).
UNSEEN_REAL_FRAMES = 8
_IN_DISTRIBUTION_RECORDING = (
    "a simulated recording of the demo's scenario (procedural actions on a simulated actor): "
    "in-distribution, through the real measurement and calibration"
)


def _staged(
    progress: Callable[[str], Progress | None] | None,
    prefix: str,
    labels: Mapping[str, str] | None = None,
) -> StageReport | None:
    """A ``(stage, done, total)`` callback drawing one bar per stage from the ``progress``
    factory, labelled ``prefix`` and the stage's words (``labels``; default: its name)."""
    if progress is None:
        return None
    factory = progress
    words = dict(labels or {})
    bars: dict[str, Progress | None] = {}

    def report(name: str, done: int, total: int) -> None:
        if name not in bars:
            bars[name] = factory(f"{prefix} {words.get(name, name)}")
        bar = bars[name]
        if bar is not None:
            bar(done, total)

    return report


def _unseen_real_figures(
    corpus_dir: Path,
    seed: int,
    progress: Callable[[str], Progress | None] | None = None,
    *,
    frames_per_clip: int = UNSEEN_REAL_FRAMES,
) -> dict[str, Any]:
    """The headline protocol on a small budget: the committed checkpoint on the corpus's test
    split (real motion of performers it never saw), 4 cameras, its default inference
    (ensemble and skeleton solve); the figures over the frames inside the cameras' view and
    over all frames; then the same clips on subjects the body model does not mirror (the
    ``off-model`` protocol, under ``"off_model"``), frame by frame and, from the same run, with
    each clip's subject calibrated from its frames (under ``"off_model"["subject_calibrated"]``).
    ``progress`` makes each figure's ``(frames estimated, frames)`` callback from its stage
    label (``"democap unseen-real"``, ``"democap off-model"``)."""
    from mocaprig.process.democap.evaluate import off_model, unseen_real
    from mocaprig.process.democap.infer import DemocapPredictor

    report = _staged(progress, "democap")  # the figures report as "unseen-real", "off-model"
    predictor = DemocapPredictor()
    res = unseen_real(
        predictor,
        corpus_dir,
        seed=seed,
        frames_per_clip=frames_per_clip,
        progress=report,
    )
    # one run gives both off-model figures: the calibration's first solve is frame by frame
    off = off_model(
        DemocapPredictor(predictor.checkpoint, subject_calibration=1),
        corpus_dir,
        seed=seed,
        frames_per_clip=frames_per_clip,
        progress=report,
    )
    if res.report is None or off.report is None:
        msg = f"DeMoCap unseen-real on {corpus_dir}: {res.note or off.note}"
        raise ProcessingError(msg)
    c = off.to_dict()
    o = c.pop("frame_by_frame", c)  # no solve (a network without markers): one figure
    d = res.to_dict()
    inside = d["inside_volume"]
    keys = ("frames", "share", "mpjpe_mm", "mpmpe_mm", "pck50")
    off_figures: dict[str, Any] = {
        "protocol": off.protocol,
        "holds_out": off.holds_out,
        "frames": c["frames"],
        "skipped_frames": c["skipped_frames"],
        "mpjpe_mm": o["mpjpe_mm"],
        "pck50": o["pck50"],
        "inside_volume": {k: o["inside_volume"][k] for k in keys},
    }
    if c["subject_calibration"]:
        off_figures["subject_calibrated"] = {
            "rounds": c["subject_calibration"],
            "frames": c["frames"],
            "mpjpe_mm": c["mpjpe_mm"],
            "pck50": c["pck50"],
            "inside_volume": {k: c["inside_volume"][k] for k in keys},
        }
    return {
        "protocol": res.protocol,
        "holds_out": res.holds_out,
        "corpus": str(corpus_dir),
        "clips": list(res.clips),
        "trained_clips": list(res.trained_clips),
        "budget": res.budget,
        "config": predictor.checkpoint.config.name,
        "epochs": predictor.checkpoint.epoch,
        "rotations": predictor.rotations,
        "solve": predictor.solves,
        "num_cameras": d["num_cameras"],
        "frames": d["frames"],
        "skipped_frames": d["skipped_frames"],
        "mpjpe_mm": d["mpjpe_mm"],
        "mpmpe_mm": d["mpmpe_mm"],
        "pck50": d["pck50"],
        "inside_volume": {k: inside[k] for k in keys},
        "per_clip_mm": d["per_action_mm"],
        "note": res.note,
        "off_model": off_figures,
    }


def _replay_figures(
    sim: SimulationResult,
    out: Path,
    calib_path: Path,
    truth: Truth,
    progress: Progress | None = None,
) -> tuple[dict[str, Any], ReplayResult]:
    """DeMoCap replay of the demo's recording with its calibration, scored against the truth;
    writes :data:`SKELETON_FIGURE` (the reconstructed skeleton against the truth). Returns
    the figures and the replay."""
    from mocaprig.drivers_mock.truth import democap_truth_at
    from mocaprig.process.democap import run_replay, score_replay

    result = run_replay(
        sim.out_dir / "session.mcap",
        calib_path,
        out=out / "results.mcap",
        every=REPLAY_EVERY,
        overwrite=True,
        progress=progress,
    )
    true_m, true_j = democap_truth_at(truth, result.t_ref_ns, clock=result.reference_clock)
    m = score_replay(result, true_j, true_m)
    s = result.summary()
    figure = _skeleton_figure(
        out / SKELETON_FIGURE, result.t_ref_ns, result.joints_m, true_j, mpjpe_mm=m.mpjpe_mm
    )
    return {
        "skeleton_figure": str(figure),
        "results_mcap": s["outputs"]["mcap"],
        "results_c3d": s["outputs"]["c3d"],
        "results_csv": s["outputs"]["csv"],
        "cameras": len(result.cameras),
        "instants": result.instants,
        "instants_total": result.instants_total,
        "every": result.every,
        "instants_by_camera_count": s["instants_by_camera_count"],
        "mean_points_per_instant": result.mean_points,
        "mpjpe_mm": m.mpjpe_mm,
        "mpmpe_mm": m.mpmpe_mm,
        "pck50": m.pck50,
        "checkpoint": result.checkpoint,
        "rotations": result.rotations,
        "solve": result.solve,
        "seconds": s["seconds"],
        "timings_s": s["timings_s"],
        "protocol": "in-distribution",
        "holds_out": _IN_DISTRIBUTION_RECORDING,
    }, result


def _subject_figures(
    sim: SimulationResult,
    out: Path,
    calib_path: Path,
    truth: Truth,
    replay: ReplayResult,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """``democap subject`` on the demo's recording (:data:`SUBJECT_INSTANTS` instants), its
    height against the simulated actor's, then the replay with every instant solved as that
    subject (every :data:`SUBJECT_REPLAY_EVERY`-th instant) against the frame-by-frame
    replay at the same instants, both scored against the truth."""
    from mocaprig.drivers_mock.truth import democap_truth_at
    from mocaprig.process.democap import DemocapPredictor, run_replay, score_replay
    from mocaprig.process.democap.replay import fit_subject
    from mocaprig.process.democap.subject import save_subject

    session = sim.out_dir / "session.mcap"
    fit = fit_subject(session, calib_path, instants=SUBJECT_INSTANTS)
    path = save_subject(
        fit.subject,
        out / SUBJECT_FILE,
        source=f"{session}: {fit.t_ref_ns.size} of {fit.instants_total} instants",
        overwrite=True,
    )
    result = run_replay(
        session,
        calib_path,
        out=out / "results_subject.mcap",
        every=SUBJECT_REPLAY_EVERY,
        overwrite=True,
        predictor=DemocapPredictor(subject=fit.subject),
        progress=progress,
    )
    true_m, true_j = democap_truth_at(truth, result.t_ref_ns, clock=result.reference_clock)
    as_subject = score_replay(result, true_j, true_m)
    rows = np.flatnonzero(np.isin(replay.t_ref_ns, result.t_ref_ns))
    same = np.isin(result.t_ref_ns, replay.t_ref_ns[rows])
    alone = replace(
        replay,
        t_ref_ns=replay.t_ref_ns[rows],
        joints_m=replay.joints_m[rows],
        markers_m=replay.markers_m[rows],
    )
    frame_by_frame = score_replay(alone, true_j[same], true_m[same])
    true_height = float(truth.meta["body_shape"]["height_m"])
    heights = fit.summary()["frame_by_frame_height_m"]
    return {
        "subject_file": str(path),
        "instants": int(fit.t_ref_ns.size),
        "instants_total": fit.instants_total,
        "standing_height_m": fit.subject.standing_height_m,
        "true_height_m": true_height,
        "height_error_mm": 1e3 * (fit.subject.standing_height_m - true_height),
        "frame_by_frame_height_m": heights,
        "fit_seconds": fit.seconds,
        "replay_every": result.every,
        "replay_instants": result.instants,
        "mpjpe_mm": as_subject.mpjpe_mm,
        "mpmpe_mm": as_subject.mpmpe_mm,
        "pck50": as_subject.pck50,
        "frame_by_frame_instants": int(rows.size),
        "frame_by_frame_mpjpe_mm": frame_by_frame.mpjpe_mm,
        "frame_by_frame_mpmpe_mm": frame_by_frame.mpmpe_mm,
        "results_mcap": str(result.outputs["mcap"]),
        "seconds": result.timings_s.get("total_s"),
        "protocol": "in-distribution",
        "holds_out": _IN_DISTRIBUTION_RECORDING,
    }


def _live_figures(
    sim: SimulationResult,
    out: Path,
    calib_path: Path,
    truth: Truth,
    cameras: int,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """``democap live`` on the mock rig of the demo's world for :data:`LIVE_SECONDS`: the
    cameras' frame sets -> instants -> the live pipeline -> ``live.mcap``, scored like the
    replay."""
    from mocaprig.acquire.camera_backends import open_cameras
    from mocaprig.calib.calibration import read_calibration
    from mocaprig.drivers_mock.truth import democap_truth_at
    from mocaprig.process.democap.evaluate import EVAL_JOINTS
    from mocaprig.process.democap.live_capture import run_live
    from mocaprig.process.metrics import pose_metrics

    results: list[tuple[Any, Any]] = []

    def on_result(res: Any, inst: Any) -> None:
        results.append((res, inst))
        if progress is not None:
            progress(len(results), 0)  # how many instants a live run gives is not known

    path = out / "live.mcap"
    path.unlink(missing_ok=True)  # the demo owns its folder (--overwrite was checked)
    cams = open_cameras(
        "mock", scenario=sim.scenario.name, seed=sim.seed, seconds=sim.seconds, count=cameras
    )
    try:
        summary = run_live(
            cams,
            read_calibration(calib_path),
            seconds=LIVE_SECONDS,
            out=path,
            on_result=on_result,
        )
    finally:
        for cam in cams:
            cam.close()
    if progress is not None:
        progress(len(results), len(results))
    ok = [(r, i) for r, i in results if r.prediction is not None]
    figures = summary.as_dict()
    if ok:
        t = np.array([i.t_ref_ns for _, i in ok], dtype=np.int64)
        _, true_j = democap_truth_at(truth, t, clock="vicon")
        pred_j = np.stack([r.prediction.joints_m for r, _ in ok])
        keep = list(EVAL_JOINTS)
        m = pose_metrics(pred_j[:, keep] * 1e3, true_j[:, keep] * 1e3)
        figures.update({"mpjpe_mm": m.mpjpe_mm, "pck50": m.pck50})
    figures["note"] = (
        "the mock cameras render on this CPU while the network runs: the rate is the "
        "simulator's, not the pipeline's (benchmarks/democap_infer.py)"
    )
    figures["protocol"] = "in-distribution"
    figures["holds_out"] = _IN_DISTRIBUTION_RECORDING
    return figures


def _eventcap_figures(seed: int, progress: StageReport | None = None) -> dict[str, Any]:
    from mocaprig.drivers_mock.eventcap_take import simulated_take_with_truth
    from mocaprig.process.eventcap.evaluate import evaluate_take

    def simulated(done_us: int, total_us: int) -> None:
        if progress is not None:
            progress("simulate DAVIS (ms)", done_us // 1000, total_us // 1000)

    take = simulated_take_with_truth(
        seed=seed, max_frames=EVENTCAP_BATCHES + 1, progress=simulated, **EVENTCAP_TAKE
    )
    if progress is not None:
        # The batches start now; their first report comes only after the first batch.
        progress("eventcap", 0, EVENTCAP_BATCHES)
    result = evaluate_take(
        take,
        protocol="simulated take (procedural karate excerpt), realistic DAVIS240C",
        seed=seed,
        max_batches=EVENTCAP_BATCHES,
        progress=progress,
    )
    return result.to_json()


def _eventcap_run_figures(
    session: Path, out: Path, seed: int, progress: StageReport | None = None
) -> dict[str, Any]:
    from mocaprig.drivers_mock.eventcap_session import read_session_truth, write_session_inputs
    from mocaprig.process.eventcap.run import run_eventcap

    det, cal = write_session_inputs(
        session,
        detections_path=out / "eventcap_detections.json",
        calibration_path=out / "eventcap_calib.toml",
        seed=seed,
        overwrite=True,
    )

    def report(stage: str, done: int, total: int) -> None:
        if progress is None:
            return
        progress(stage, done, total)
        if stage == "index" and done >= total:
            # The batches start now; their first report comes only after the first batch.
            progress("batches", 0, EVENTCAP_BATCHES)

    result = run_eventcap(
        session / "session.mcap",
        cal,
        out=out / "eventcap.mcap",
        detections=det,
        shape_path=session / "truth" / "scenario.json",
        batches=EVENTCAP_BATCHES,
        start_s=EVENTCAP_RUN_START_S,
        overwrite=True,
        progress=report,
    )
    summary = result.summary()
    truth = read_session_truth(session).keypoints_at(result.t_davis_us)
    err_mm = 1e3 * np.linalg.norm(result.read_keypoints_m()[:, :15] - truth[:, :15], axis=-1)
    return {
        **summary,
        "protocol": "the demo's simulated recording; synthetic detections; the simulator's "
        "true DAVIS calibration",
        "mpjpe_mm": float(err_mm.mean()),
    }


def _csv_rows_by_time(path: Path) -> dict[str, npt.NDArray[np.float64]]:
    """A replay CSV's rows (mm) by their ``time_s`` text."""
    rows: dict[str, npt.NDArray[np.float64]] = {}
    with path.open(encoding="utf-8") as fh:
        next(fh, None)
        for line in fh:
            t, _, rest = line.partition(",")
            rows[t] = np.array(rest.split(","), dtype=np.float64)
    return rows


def _process_figures(
    session_dir: Path, out: Path, calib: Path, bar: Progress | None, replay_csv: Path | None
) -> dict[str, Any]:
    """``mocaprig process`` (in-process engine) on the demo's session with DeMoCap in spans,
    run twice: the second run must find the first's outputs finished and keep them (resume).
    Its rows are compared with the demo's unsplit replay (``replay_csv``) at their shared
    instants: each instant stands alone, so they must be the same."""
    from mocaprig.process.batch.engines import InProcessEngine
    from mocaprig.process.batch.runner import process_sessions
    from mocaprig.process.batch.sessions import find_sessions
    from mocaprig.process.batch.tasks import ProcessSettings

    settings = ProcessSettings(
        methods=("democap",), democap_every=PROCESS_EVERY, democap_span=PROCESS_SPAN
    )
    sessions = find_sessions([session_dir], calib=calib)
    folder = out / "process"
    runs = []
    with InProcessEngine() as engine:
        for k in range(2):
            if bar is not None:
                bar(k, 2)
            runs.append(process_sessions(sessions, out=folder, settings=settings, engine=engine))
    if bar is not None:
        bar(2, 2)
    first, second = (r.to_json() for r in runs)
    job = first["jobs"][0]
    if job["status"] != "done":
        msg = f"mocaprig process on {session_dir}: DeMoCap {job['status']}: {job['error']}"
        raise ProcessingError(msg)
    same: dict[str, Any] = {"vs_replay_instants": 0, "vs_replay_max_diff_mm": None}
    if replay_csv is not None and replay_csv.is_file():
        ours = _csv_rows_by_time(Path(next(p for p in job["outputs"] if p.endswith(".csv"))))
        theirs = _csv_rows_by_time(replay_csv)
        shared = sorted(set(ours) & set(theirs))
        same["vs_replay_instants"] = len(shared)
        if shared:
            diff = max(float(np.max(np.abs(ours[t] - theirs[t]))) for t in shared)
            same["vs_replay_max_diff_mm"] = diff
    return {
        "engine": first["engine"],
        "out": str(folder),
        "methods": list(settings.methods),
        "every": PROCESS_EVERY,
        "span": PROCESS_SPAN,
        "spans": job["details"].get("spans"),
        **same,
        "status": job["status"],
        "seconds": job["seconds"],
        "outputs": len(job["outputs"]),
        "instants": job["details"].get("instants"),
        "rerun_kept": second["skipped"],
        "rerun_seconds": second["seconds"],
    }


def _calibration_figures(
    sim: SimulationResult,
    out: Path,
    traj: MarkerTrajectories,
    progress: Callable[[str], Progress | None],
) -> dict[str, Any]:
    """Calibrate the recorded D415s (and the DAVIS clock) against the Vicon trial, write its
    report (:data:`CALIBRATION_REPORT`), and score it."""
    from mocaprig.calib.calibration import write_calibration
    from mocaprig.calib.report import write_report
    from mocaprig.calib.vicon_calibration import calibrate_vicon, evaluate_calibration

    session = sim.out_dir / "session.mcap"
    result = calibrate_vicon(session, sim.c3d_path, progress=progress("calibrate"))
    calib_path = write_calibration(result.calibration, out / "calib.toml", overwrite=True)
    report = write_report(
        result,
        out / CALIBRATION_REPORT,
        overwrite=True,
        trajectories=traj,
        progress=progress("calibration report"),
    )
    ev = evaluate_calibration(result.calibration, sim.out_dir)
    per_device = ev.as_dict()["devices"]
    cams = [d for d in ev.devices if DeviceId.parse(d.device).kind == "d415"]
    davis = [d for d in ev.devices if DeviceId.parse(d.device).kind == "davis"]

    def worst(values: list[float]) -> float:
        finite = [abs(v) for v in values if np.isfinite(v)]
        return max(finite) if finite else float("nan")

    return {
        "calibration_file": str(calib_path),
        "report": str(report.index),
        "report_figures": [str(p) for p in report.figures],
        "cameras": len(result.calibration.cameras),
        "clocks": len(result.calibration.clocks),
        "notes": list(result.notes),
        "max_rotation_error_deg": worst([d.rotation_error_deg for d in cams]),
        "max_translation_error_mm": worst([d.translation_error_mm for d in cams]),
        "max_d415_clock_offset_error_ms": worst([d.clock_offset_error_ms for d in cams]),
        "max_d415_drift_error_ppm": worst([d.drift_error_ppm for d in cams]),
        "davis_vs_d415_clock_error_us": worst([d.clock_error_vs_via_us for d in davis]),
        "reprojection_rms_px": {
            c.name: c.residuals.get("reprojection_rms_px", float("nan"))
            for c in result.calibration.cameras
        },
        "devices": per_device,
    }


@dataclass(frozen=True, slots=True)
class DemoReport:
    """What :func:`run_demo` produced and measured.

    Attributes:
        out_dir: The demo folder.
        session_dir: The simulated session (truth + Vicon exports).
        figure_path: The summary figure (PNG).
        report_path: ``report.json`` (this report).
        figures: Measured figures (units in the key names).
        stages: Each stage of the main job with ``"done"`` or ``"pending: <why>"``.
        skeleton_figure_path: The replayed DeMoCap skeleton against the truth (PNG); None when
            the replay did not run.
        calibration_report_path: The calibration report's ``index.html``; None when the
            calibration failed.
    """

    out_dir: Path
    session_dir: Path
    figure_path: Path
    report_path: Path
    figures: dict[str, Any] = field(repr=False)
    stages: dict[str, str] = field(repr=False)
    skeleton_figure_path: Path | None = None
    calibration_report_path: Path | None = None

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready summary (what ``demo --json`` prints)."""
        return {
            "out_dir": str(self.out_dir),
            "session_dir": str(self.session_dir),
            "figure": str(self.figure_path),
            "skeleton_figure": _path_or_none(self.skeleton_figure_path),
            "calibration_report": _path_or_none(self.calibration_report_path),
            "report": str(self.report_path),
            "stages": dict(self.stages),
            "figures": dict(self.figures),
        }


def _path_or_none(path: Path | None) -> str | None:
    return None if path is None else str(path)


def _vicon_vs_truth(traj: MarkerTrajectories, truth: Truth) -> dict[str, float]:
    """Error of the C3D read back by the product reader against the clean frame truth."""
    if truth.vicon is None:
        msg = f"the truth in {truth.meta.get('path', '?')} has no Vicon frame truth"
        raise RecordingError(msg)
    clean = truth.vicon.clean_m
    labels = [lab.split(":", 1)[-1] for lab in truth.vicon.labels]
    idx = [traj.index(lab) for lab in labels]
    measured = traj.positions_m[:, idx, :]
    if measured.shape != clean.shape:
        msg = (
            f"the C3D read back has shape {measured.shape} but the Vicon truth has "
            f"{clean.shape}; the reader and the mock writer disagree"
        )
        raise RecordingError(msg)
    err = measured - clean
    ok = np.all(np.isfinite(err), axis=-1)
    err_ok = err[ok]
    return {
        "vicon_error_rms_mm_per_axis": float(np.sqrt(np.mean(err_ok**2)) * 1e3),
        "vicon_error_p99_mm": float(np.percentile(np.linalg.norm(err_ok, axis=-1), 99) * 1e3),
        "vicon_error_max_mm": float(np.max(np.linalg.norm(err_ok, axis=-1)) * 1e3),
        "vicon_gap_fraction": float(1.0 - ok.mean()),
    }


def _recording_figures(path: Path, progress: Progress | None = None) -> dict[str, Any]:
    """``info``, the D415 sync check, DAVIS statistics and trigger pairing of a recording
    (``progress`` over those 3 steps)."""
    from mocaprig.acquire.d415_sync import SyncCheckConfig, SyncChecker
    from mocaprig.acquire.davis240c_decode import SpecialType
    from mocaprig.acquire.depth_camera import SyncMode
    from mocaprig.acquire.device_streams import (
        RecordedD415,
        RecordedDavis,
        d415_devices,
        davis_devices,
        frame_timings,
    )
    from mocaprig.acquire.recording import Recording, info

    def step(done: int) -> None:
        if progress is not None:
            progress(done, 3)

    step(0)
    inf = info(path)
    step(1)
    out: dict[str, Any] = {
        "path": str(path),
        "indexed": inf.indexed,
        "streams": len(inf.streams),
        "messages": sum(s.messages for s in inf.streams),
        "drops": sum(s.drops or 0 for s in inf.streams),
        "mb": path.stat().st_size / 1e6,
        "duration_s": inf.duration_s,
    }
    with Recording(path) as rec:
        roles = {}
        for dev in d415_devices(rec):
            mode = RecordedD415(rec, dev).settings().sync_mode
            if mode is not None:
                roles[dev.serial] = mode
        master_sensor_us: list[int] = []
        master = next((s for s, r in roles.items() if r is SyncMode.MASTER), None)
        if roles:
            checker = SyncChecker(roles, SyncCheckConfig(fps=30))
            for dev, timing in frame_timings(rec):
                checker.feed(dev.serial, timing)
                if dev.serial == master and timing.sensor_timestamp_us is not None:
                    master_sensor_us.append(int(timing.sensor_timestamp_us))
            rep = checker.report()
            out["d415_cameras"] = len(roles)
            out["d415_frames"] = {s: c.frames for s, c in rep.cameras.items()}
            out["d415_sync_ok"] = rep.ok
            out["d415_max_phase_error_us"] = max(
                (c.max_phase_error_us or 0.0 for c in rep.cameras.values()), default=0.0
            )
        step(2)
        cams = davis_devices(rec)
        if cams:
            davis = RecordedDavis(rec, cams[0])
            tr = davis.triggers()
            pulses = tr["t"][tr["type"] == SpecialType.EXTERNAL_INPUT_PULSE].astype(np.int64)
            out["davis_events"] = int(davis.events().size)
            out["davis_frames"] = davis.count("frame")
            out["davis_imu_samples"] = int(davis.imu().size)
            out["davis_trigger_pulses"] = int(pulses.size)
            out["davis_dvs"] = davis.settings().get("dvs.run")
            out.update(_pair_pulses(pulses, np.asarray(master_sensor_us, np.int64)))
    step(3)
    return out


def _pair_pulses(
    pulses_us: npt.NDArray[np.int64], frames_us: npt.NDArray[np.int64]
) -> dict[str, Any]:
    """Pair DAVIS trigger pulses with the D415 master's frames, in order from the first.

    The clocks differ in offset and rate (tens of ppm: ~0.7 ms over 10 s), so the pairing fits
    the affine map between the two clocks' intervals from the first pulse/frame and counts the
    pairs within 100 µs of it (30 fps: a missed pulse or frame shifts the rest by 33 ms).
    """
    n = int(min(pulses_us.size, frames_us.size))
    if n == 0:
        return {"trigger_frame_pairs": 0, "trigger_frame_max_interval_error_us": None}
    dp = (pulses_us[:n] - pulses_us[0]).astype(np.float64)
    df = (frames_us[:n] - frames_us[0]).astype(np.float64)
    if n >= 3:
        slope, icpt = np.polyfit(df, dp, 1)
        err = np.abs(dp - (slope * df + icpt))
    else:
        err = np.abs(dp - df)
    paired = int(np.sum(err < 100))
    return {
        "trigger_frame_pairs": paired,
        "trigger_frame_max_interval_error_us": float(err.max()),
    }


def _summary_figure(
    path: Path,
    sim: SimulationResult,
    truth: Truth,
    traj: MarkerTrajectories,
    rec: dict[str, Any] | None = None,
) -> None:
    import matplotlib as mpl

    mpl.use("Agg", force=False)  # no display on a capture PC's CI or over ssh
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13, 9), layout="constrained")
    axes = fig.subplots(2, 2)
    world = sim.scenario
    t_s = truth.t_ns * 1e-9

    # (a) the rig from above: cameras, their view direction, the actor's markers
    ax = axes[0, 0]
    mid = len(truth.t_ns) // 2
    mk = truth.markers_m[mid]
    ax.scatter(mk[:, 0], mk[:, 1], s=6, c="tab:gray", label="body markers")
    cl = truth.clapper_m[mid]
    ax.scatter(cl[:, 0], cl[:, 1], s=20, c="tab:red", marker="x", label="clapperboard")
    for name, cam in world.rig.cameras.items():
        c = cam.center_m
        look = cam.T_world_cam[:3, 2]
        colour = "tab:purple" if "davis" in name else "tab:blue"
        ax.plot(c[0], c[1], "o", color=colour)
        ax.arrow(c[0], c[1], 0.6 * look[0], 0.6 * look[1], width=0.02, color=colour)
        ax.annotate(name, (c[0], c[1]), textcoords="offset points", xytext=(5, 5), fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("rig from above (D415 blue, DAVIS purple)")
    ax.legend(loc="best", fontsize=8)

    # (b) joint heights over time: the motion
    ax = axes[0, 1]
    for name in ("HeadEnd", "RightHand", "LeftHand", "RightFoot", "LeftFoot"):
        j = truth.joint_names.index(name)
        ax.plot(t_s, truth.joints_m[:, j, 2], label=name, lw=1)
    for tc in truth.clap_times_ns:
        ax.axvline(tc * 1e-9, color="tab:red", ls="--", lw=0.8)
    ax.set_xlabel("session time (s)")
    ax.set_ylabel("height (m)")
    ax.set_title(f"motion '{world.motion_source}' (claps dashed)")
    ax.legend(fontsize=8, ncol=2)

    # (c) clapperboard marker distance: truth vs the Vicon C3D read back
    ax = axes[1, 0]
    d_true = np.linalg.norm(truth.clapper_m[:, 0] - truth.clapper_m[:, 1], axis=-1)
    ax.plot(t_s, d_true * 1e3, label="truth", lw=1)
    if truth.vicon is not None:
        top, bottom = (traj.marker(f"clapper:{n}") for n in truth.clapper_marker_names)
        ax.plot(
            truth.vicon.frame_t_ns * 1e-9,
            np.linalg.norm(top - bottom, axis=-1) * 1e3,
            ".",
            ms=2,
            label="Vicon C3D (read back)",
        )
    ax.set_xlabel("session time (s)")
    ax.set_ylabel("marker distance (mm)")
    ax.set_title("clapperboard")
    ax.legend(fontsize=8)

    # (d) Vicon error histogram
    ax = axes[1, 1]
    if truth.vicon is not None:
        labels = [lab.split(":", 1)[-1] for lab in truth.vicon.labels]
        meas = traj.positions_m[:, [traj.index(lab) for lab in labels], :]
        err = (meas - truth.vicon.clean_m).reshape(-1)
        err = err[np.isfinite(err)] * 1e3
        ax.hist(err, bins=80, color="tab:green")
        sigma = world.rig.vicon.noise_sigma_m * world.noise.vicon_noise_scale * 1e3
        ax.set_title(f"Vicon C3D - truth per axis (σ set to {sigma:.2f} mm)")
    ax.set_xlabel("error (mm)")
    ax.set_ylabel("samples")
    title = f"mocaprig demo: scenario '{world.name}', seed {world.seed}, {world.seconds:g} s"
    if rec is not None:
        title += (
            f"\nsession.mcap: {rec['streams']} streams, {rec['messages']} messages, "
            f"{rec['drops']} dropped, {rec['mb']:.0f} MB; D415 sync ok: {rec.get('d415_sync_ok')}"
            f"\nDAVIS {rec.get('davis_frames')} frames, {rec.get('davis_imu_samples')} IMU, "
            f"{rec.get('davis_trigger_pulses')} trigger pulses "
            f"({rec.get('trigger_frame_pairs')} paired with D415 master frames)"
        )
    fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=90)


def _skeleton_figure(
    path: Path,
    t_ref_ns: npt.NDArray[np.int64],
    pred_joints_m: npt.NDArray[np.float64],
    true_joints_m: npt.NDArray[np.float64],
    *,
    mpjpe_mm: float,
) -> Path:
    """The replayed DeMoCap skeleton against the truth: three instants in 3D (early, middle,
    late), the per-instant joint error over the take and the mean error per joint; the errors
    are over the scored joints (:data:`process.democap.evaluate.EVAL_JOINTS`), as MPJPE is."""
    import matplotlib as mpl

    mpl.use("Agg", force=False)  # no display on a capture PC's CI or over ssh
    from matplotlib.figure import Figure

    from mocaprig.process.body import DEMOCAP_JOINTS, DEMOCAP_PARENTS
    from mocaprig.process.democap.evaluate import EVAL_JOINTS

    keep = list(EVAL_JOINTS)
    err_mm = np.linalg.norm(pred_joints_m - true_joints_m, axis=-1) * 1e3  # (N, 19)
    per_instant = np.nanmean(err_mm[:, keep], axis=1)
    t_s = (t_ref_ns - t_ref_ns[0]) * 1e-9
    n = len(t_ref_ns)
    fig = Figure(figsize=(14, 9), layout="constrained")
    grid = fig.add_gridspec(2, 3)
    bones = [(j, p) for j, p in enumerate(DEMOCAP_PARENTS) if p >= 0]
    for col, frac in enumerate((1 / 6, 1 / 2, 5 / 6)):
        k = min(n - 1, int(frac * n))
        # mplot3d ships no type information: its axes are Any here.
        ax: Any = fig.add_subplot(grid[0, col], projection="3d")
        for joints, colour, label in (
            (true_joints_m[k], "k", "truth"),
            (pred_joints_m[k], "tab:red", "DeMoCap (replay)"),
        ):
            for n_bone, (j, p) in enumerate(bones):
                seg = joints[[j, p]]
                ax.plot(
                    seg[:, 0], seg[:, 1], seg[:, 2], color=colour, lw=2,
                    label=label if n_bone == 0 else None,
                )  # fmt: skip
            ax.scatter(joints[:, 0], joints[:, 1], joints[:, 2], color=colour, s=8)
        both = np.vstack([true_joints_m[k], pred_joints_m[k]])
        both = both[np.isfinite(both).all(axis=1)]
        mid = (both.min(axis=0) + both.max(axis=0)) / 2
        half = max(float(np.ptp(both, axis=0).max()) / 2, 0.1) * 1.1
        ax.set_xlim(mid[0] - half, mid[0] + half)
        ax.set_ylim(mid[1] - half, mid[1] + half)
        ax.set_zlim(mid[2] - half, mid[2] + half)
        ax.set_box_aspect((1.0, 1.0, 1.0))
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_zlabel("z (m)")
        ax.set_title(f"t = {t_s[k]:.2f} s: {per_instant[k]:.1f} mm mean joint error", fontsize=9)
        if col == 0:
            ax.legend(loc="upper left", fontsize=8)
    ax2 = fig.add_subplot(grid[1, :2])
    ax2.plot(t_s, per_instant, ".-", ms=3, lw=0.8, color="tab:red")
    ax2.axhline(mpjpe_mm, color="k", ls="--", lw=0.8, label=f"MPJPE {mpjpe_mm:.1f} mm")
    ax2.set_xlabel("time since the first replayed instant (s)")
    ax2.set_ylabel("mean joint error (mm)")
    ax2.set_title("per instant")
    ax2.legend(fontsize=8)
    ax3 = fig.add_subplot(grid[1, 2])
    per_joint = np.nanmean(err_mm[:, keep], axis=0)
    ax3.barh(range(len(keep)), per_joint, color="tab:red")
    ax3.set_yticks(range(len(keep)), [DEMOCAP_JOINTS[j] for j in keep], fontsize=8)
    ax3.invert_yaxis()
    ax3.set_xlabel("mean error (mm)")
    ax3.set_title("per joint")
    fig.suptitle(
        f"DeMoCap replay of session.mcap against the truth: {n} instants, the demo's "
        "calibration (in-distribution)",
        fontsize=10,
    )
    fig.savefig(path, dpi=90)
    return path


def run_demo(
    out_dir: str | Path,
    *,
    scenario: str = "default",
    seed: int = 0,
    seconds: float = 10.0,
    overwrite: bool = False,
    progress: Callable[[str], Progress | None] | None = None,
    cameras: int = 4,
    davis_dvs: bool = False,
    corpus_dir: str | Path | None = None,
    real_frames: int = UNSEEN_REAL_FRAMES,
) -> DemoReport:
    """Run the main job on the simulated rig and write ``report.json`` and ``summary.png``.

    Args:
        out_dir: The demo folder (must be empty unless ``overwrite``).
        scenario: A simulated scenario name (``mocaprig simulate --help`` lists them).
        seed: World seed.
        seconds: Session length (s).
        overwrite: Replace the outputs of an earlier demo in ``out_dir``.
        progress: Optional factory ``stage label -> (done, total)`` callback.
        cameras: D415 count recorded (4, the rig DeMoCap is trained for: ~1.5 min on 2 cores;
            the first two rig cameras alone stand on one side of the actor, which DeMoCap
            was not trained for, so its replay figures with 2 are not representative).
        davis_dvs: Record DAVIS DVS events too (~20 s CPU per simulated second).
        corpus_dir: The motion corpus for the ``unseen-real`` figure (None: the shared data
            beside the repository, when there; without it the stage is skipped, saying so).
        real_frames: Frames per test clip of the real-motion figures (``unseen-real`` and
            ``off-model``, 11 clips each; that stage takes about half the demo's time at 8).

    Raises:
        RecordingError: the folder is not empty (without ``overwrite``) or a file disagrees.
        ValidationError: ``real_frames`` < 1.
    """
    if isinstance(real_frames, bool) or int(real_frames) != real_frames or real_frames < 1:
        msg = f"real_frames must be an integer >= 1, got {real_frames!r}"
        raise ValidationError(msg)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        msg = f"demo output {out} exists and is not a folder; choose another --out"
        raise RecordingError(msg)
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        msg = f"demo folder {out} is not empty; choose another --out or pass --overwrite"
        raise RecordingError(msg)
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}

    def stage(label: str) -> Progress | None:
        return None if progress is None else progress(label)

    t0 = time.monotonic()
    sim = simulate_session(
        out / "session",
        scenario=scenario,
        seed=seed,
        seconds=seconds,
        overwrite=True,
        progress=progress,
        devices=("davis", "d415", "syncbox"),
        cameras=cameras,
        davis_dvs=davis_dvs,
    )
    timings["simulate_s"] = time.monotonic() - t0
    timings["record_s"] = sim.recording.elapsed_s if sim.recording is not None else 0.0
    t0 = time.monotonic()
    rec_figures = _recording_figures(out / "session" / "session.mcap", stage("check recording"))
    timings["recording_checks_s"] = time.monotonic() - t0

    t0 = time.monotonic()
    traj = read_c3d(sim.c3d_path, strip_subject_prefix=False)
    timings["read_c3d_s"] = time.monotonic() - t0
    csv = read_nexus_csv(sim.csv_path)
    truth = read_truth(sim.out_dir)

    figures: dict[str, Any] = {
        "seconds": sim.seconds,
        "seed": sim.seed,
        "scenario": sim.scenario.name,
        "motion": sim.scenario.motion_source,
        "body_markers": sim.num_body_markers,
        "clapper_markers": sim.num_clapper_markers,
        "vicon_rate_hz": traj.rate_hz,
        "vicon_frames": traj.n_frames,
        "vicon_extent_m": traj.extent_m,
        "clap_times_s": [t * 1e-9 for t in sim.clap_times_ns],
        "vicon_noise_sigma_set_mm": sim.scenario.rig.vicon.noise_sigma_m
        * sim.scenario.noise.vicon_noise_scale
        * 1e3,
    }
    figures["recording"] = rec_figures
    figures.update(_vicon_vs_truth(traj, truth))
    both = np.isfinite(csv.positions_m) & np.isfinite(traj.positions_m)
    gaps_agree = bool(np.array_equal(np.isfinite(csv.positions_m), np.isfinite(traj.positions_m)))
    figures["csv_vs_c3d_max_abs_mm"] = float(
        np.max(np.abs(csv.positions_m[both] - traj.positions_m[both])) * 1e3
    )
    figures["csv_vs_c3d_gaps_agree"] = gaps_agree
    figures["timings_s"] = timings

    stages = {"simulate": "done", "record": "done", "vicon_io": "done"}
    t0 = time.monotonic()
    try:
        figures["calibration"] = _calibration_figures(sim, out, traj, stage)
        stages["calibrate"] = "done"
    except MocaprigError as err:
        # The demo reports a failed stage and goes on; the error says why.
        _log.error("calibration stage failed: %s", err)
        figures["calibration"] = {"error": str(err)}
        stages["calibrate"] = f"failed: {err}"
    timings["calibrate_s"] = time.monotonic() - t0

    t0 = time.monotonic()
    try:
        from mocaprig.process.democap import demo_figures

        figures["democap"] = {
            **demo_figures(
                seed=seed,
                progress=_staged(
                    progress,
                    "democap in-distribution",
                    {"solve": "with the solve", "network": "network alone"},
                ),
            ),
            "protocol": "in-distribution",
            "holds_out": _IN_DISTRIBUTION,
        }
        stages["democap"] = "done (in-distribution: held-out simulated takes)"
    except MocaprigError as err:
        _log.error("DeMoCap stage failed: %s", err)
        figures["democap"] = {"error": str(err)}
        stages["democap"] = f"failed: {err}"
    timings["democap_s"] = time.monotonic() - t0

    t0 = time.monotonic()
    from mocaprig.process.democap.corpus import default_corpus_dir

    corpus = default_corpus_dir() if corpus_dir is None else Path(corpus_dir)
    if corpus is None:
        stages["democap_unseen_real"] = (
            "skipped: the motion corpus (../shared/data/motion/corpus) is not beside this "
            "clone; pass --corpus DIR"
        )
    else:
        try:
            figures["democap_unseen_real"] = _unseen_real_figures(
                corpus, seed, stage, frames_per_clip=real_frames
            )
            stages["democap_unseen_real"] = (
                "done (unseen-real: the corpus test split, real motion of unseen performers)"
            )
        except MocaprigError as err:
            _log.error("DeMoCap unseen-real stage failed: %s", err)
            figures["democap_unseen_real"] = {"error": str(err)}
            stages["democap_unseen_real"] = f"failed: {err}"
    timings["democap_unseen_real_s"] = time.monotonic() - t0

    t0 = time.monotonic()
    replayed: ReplayResult | None = None
    calib_file = figures["calibration"].get("calibration_file")
    if calib_file is None:
        figures["democap_replay"] = {"error": "no calibration (the calibration stage failed)"}
        stages["democap_replay"] = "skipped: needs the calibration, whose stage failed"
    else:
        try:
            figures["democap_replay"], replayed = _replay_figures(
                sim, out, Path(calib_file), truth, stage("democap replay")
            )
            stages["democap_replay"] = "done"
        except MocaprigError as err:
            _log.error("DeMoCap replay stage failed: %s", err)
            figures["democap_replay"] = {"error": str(err)}
            stages["democap_replay"] = f"failed: {err}"
    timings["democap_replay_s"] = time.monotonic() - t0

    t0 = time.monotonic()
    if replayed is None or calib_file is None:
        figures["democap_subject"] = {"error": "no replay (its stage failed or was skipped)"}
        stages["democap_subject"] = "skipped: needs the replay, whose stage did not run"
    else:
        try:
            figures["democap_subject"] = _subject_figures(
                sim, out, Path(calib_file), truth, replayed, stage("democap subject")
            )
            stages["democap_subject"] = "done"
        except MocaprigError as err:
            _log.error("DeMoCap subject stage failed: %s", err)
            figures["democap_subject"] = {"error": str(err)}
            stages["democap_subject"] = f"failed: {err}"
    timings["democap_subject_s"] = time.monotonic() - t0

    t0 = time.monotonic()
    if calib_file is None:
        figures["democap_live"] = {"error": "no calibration (the calibration stage failed)"}
        stages["democap_live"] = "skipped: needs the calibration, whose stage failed"
    else:
        try:
            figures["democap_live"] = _live_figures(
                sim, out, Path(calib_file), truth, cameras, stage("democap live")
            )
            stages["democap_live"] = f"done ({LIVE_SECONDS:g} s of the mock rig)"
        except MocaprigError as err:
            _log.error("DeMoCap live stage failed: %s", err)
            figures["democap_live"] = {"error": str(err)}
            stages["democap_live"] = f"failed: {err}"
    timings["democap_live_s"] = time.monotonic() - t0

    t0 = time.monotonic()
    if calib_file is None:
        figures["process"] = {"error": "no calibration (the calibration stage failed)"}
        stages["process"] = "skipped: needs the calibration, whose stage failed"
    else:
        try:
            replay_csv = figures.get("democap_replay", {}).get("results_csv")
            figures["process"] = _process_figures(
                sim.out_dir,
                out,
                Path(calib_file),
                stage("process"),
                None if replay_csv is None else Path(replay_csv),
            )
            stages["process"] = "done (mocaprig process: DeMoCap in spans, then resumed)"
        except MocaprigError as err:
            _log.error("process stage failed: %s", err)
            figures["process"] = {"error": str(err)}
            stages["process"] = f"failed: {err}"
    timings["process_s"] = time.monotonic() - t0

    t0 = time.monotonic()
    try:
        figures["eventcap"] = _eventcap_figures(
            seed, _staged(progress, "eventcap", _EVENTCAP_STAGES)
        )
        stages["eventcap"] = (
            f"done ({EVENTCAP_BATCHES} batches of a simulated take; synthetic detections)"
        )
    except MocaprigError as err:
        _log.error("EventCap stage failed: %s", err)
        figures["eventcap"] = {"error": str(err)}
        stages["eventcap"] = f"failed: {err}"
    timings["eventcap_s"] = time.monotonic() - t0

    t0 = time.monotonic()
    if not davis_dvs:
        stages["eventcap_run"] = (
            "skipped: the demo records the DAVIS without its DVS unless --davis-dvs "
            "(~20 s of CPU per simulated second)"
        )
    else:
        try:
            figures["eventcap_run"] = _eventcap_run_figures(
                sim.out_dir, out, seed, _staged(progress, "eventcap run", _EVENTCAP_RUN_STAGES)
            )
            stages["eventcap_run"] = f"done ({EVENTCAP_BATCHES} batches of session.mcap)"
        except MocaprigError as err:
            _log.error("EventCap run stage failed: %s", err)
            figures["eventcap_run"] = {"error": str(err)}
            stages["eventcap_run"] = f"failed: {err}"
    timings["eventcap_run_s"] = time.monotonic() - t0

    figure_path = out / "summary.png"
    bar = stage("summary figure")
    if bar is not None:
        bar(0, 1)
    _summary_figure(figure_path, sim, truth, traj, rec_figures)
    if bar is not None:
        bar(1, 1)
    skeleton = figures["democap_replay"].get("skeleton_figure")
    cal_report = figures["calibration"].get("report")

    stages.update({name: f"pending: {why}" for name, why in _PENDING_STAGES})
    report_path = out / "report.json"
    report = DemoReport(
        out_dir=out,
        session_dir=sim.out_dir,
        figure_path=figure_path,
        report_path=report_path,
        figures=figures,
        stages=stages,
        skeleton_figure_path=None if skeleton is None else Path(skeleton),
        calibration_report_path=None if cal_report is None else Path(cal_report),
    )
    payload = {"mocaprig_version": __version__, **report.to_dict()}
    report_path.write_text(json.dumps(to_jsonable(payload), indent=2) + "\n", encoding="utf-8")
    _log.info("demo report written to %s", report_path)
    return report
