"""Benchmark live DeMoCap end to end: 4 D415 IR + depth frames -> joints, per stage, ``lite``
and ``paper``.

The frames are the simulated world (``default`` scenario) rendered by the mock D415 renderer
(:class:`mocaprig.drivers_mock.d415_render.SceneRenderer`, 848×480, the rig's 4 D415s at their true
poses and intrinsics, all four exposing together as on hardware sync), one rig instant every
0.1 s from t = 1 s. All frame sets are rendered before any timing (rendering is not timed).
Each set goes through :class:`process.democap.live.LivePipeline` exactly as live frames would:
per camera :func:`mocaprig.calib.markers.measure_frame` (IR blobs, robust depth, deprojection) ->
camera to world, capture-box crop, 10 mm merge -> :meth:`DemocapPredictor.predict_many`
(normalise + render, network, CoM3D + fusion + inverse normalisation, and any further stage
the predictor reports in ``last_timings_s``).

Configurations (:data:`LITE_CONFIGS`), each timed in rounds that interleave them (the machine
is shared: a load change then hits all of them alike):

* ``live``: :func:`mocaprig.process.democap.live.live_predictor`: the rotation ensemble of
  ``LIVE_ROTATIONS`` (2) turns in one batched network pass on the calling thread, compiled
  (``torch.compile``, the weights frozen; the compile happens on the first warm-up set and
  is reported as ``first_set_s``), in the default pipeline;
* ``live-2thr``: the same compiled, the 2 turns as two passes at once (``workers=2``: the
  second on the predictor's own thread, kept across calls);
* ``live-eager``: the live predictor before it was compiled (2 uncompiled passes at once,
  ``workers=2``): the "before" figure, timed in the same run;
* ``live-eager-1thr``: the 2 turns in one uncompiled batched pass (``workers=1``);
* ``live-solve``: the uncompiled 2-turn ensemble with the skeleton solve (``democap live
  --solve``);
* ``offline``: ``DemocapPredictor()`` as shipped for offline use (``DEFAULT_ROTATIONS``, 3
  turns, one batched pass, then the skeleton solve from 4 starts);
* ``offline-network``: the same without the solve (the network's own estimate);
* ``single``: the paper's single shot (``rotations=1``, no solve, uncompiled).

For each:

* **sequential latency** (:meth:`LivePipeline.process`, one set at a time): median per stage,
  and the throughput of that loop;
* **pipelined throughput** (:meth:`LivePipeline.stream` over all the pre-rendered sets: the
  measurement of set k + 1 overlaps the network of set k): sets per second of wall time;
* **paced at 30 Hz** (``live``, ``live-eager`` and ``single``; the sets released on a 30 Hz
  clock, the D415 rate): the latency from a set's release to its joints, and whether it keeps up.

``fps`` in the last line's JSON is the end-to-end throughput, 4 IR + depth frames -> world
joints, of ``live`` (the live predictor, the pipeline's default ``workers``
:data:`~mocaprig.process.democap.live.DEFAULT_WORKERS`) through the pipelined stream, median over
rounds, on the machine it runs on, as loaded as it is. Each pass also reports the CPU cores
it kept busy on average (process CPU time / wall time): on a shared machine, whether the
second core was there to use at all; and the process CPU time per set of the streamed pass
(the work, which the load changes much less than the rate).

``lite`` is the committed checkpoint; ``paper`` has random weights (its speed does not depend
on them) and is timed on a few sets, as the live predictor and single shot. The MPJPE of the
``lite`` joints on the benchmark's sets against the simulated truth (17 joints, the
evaluation's) is a sanity figure, not an evaluation (40 instants of one take). torch runs
on ``--threads`` threads (default 1: on 2 cores the second one measures the next set; set
here, never by the library).

Run (≈ 80 s on the 2-core machine)::

    .venv/bin/python benchmarks/democap_infer.py --frames 40 --threads 1
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from mocaprig.calib.calibration import Calibration, CameraCalibration
from mocaprig.drivers_mock.d415_render import IrSettings, SceneRenderer
from mocaprig.drivers_mock.scenario import build_scenario
from mocaprig.process.body import democap_joints, forward_kinematics
from mocaprig.process.democap.checkpoint import DEFAULT_CHECKPOINT, Checkpoint, load_checkpoint
from mocaprig.process.democap.config import CONFIGS
from mocaprig.process.democap.evaluate import EVAL_JOINTS
from mocaprig.process.democap.infer import DemocapPredictor
from mocaprig.process.democap.live import (
    DEFAULT_WORKERS,
    LIVE_ROTATIONS,
    LivePipeline,
    LiveResult,
    cameras_from_calibration,
    live_predictor,
)
from mocaprig.process.democap.model import build_network

F64 = npt.NDArray[np.float64]
Pair = tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint16]]
#: One rig instant: camera name -> (IR, depth).
Frames = dict[str, Pair]

#: Spacing of the rendered rig instants (s) and the first one.
STEP_NS = 100_000_000
START_NS = 1_000_000_000
LIVE_HZ = 30.0


def render_scene(seed: int, sets: int) -> tuple[list[Frames], F64, Calibration, float]:
    """Pre-render ``sets`` rig instants: frame sets, true joints (sets, 19, 3), the rig's
    calibration (true poses) and the render time per frame (ms)."""
    seconds = max(6.0, (START_NS + STEP_NS * sets) / 1e9 + 1.0)
    sc = build_scenario("default", seed=seed, seconds=seconds)
    renderers = [SceneRenderer(sc, spec) for spec in sc.rig.d415]
    settings = IrSettings()
    rng = np.random.default_rng(seed)
    out: list[Frames] = []
    t0 = time.perf_counter()
    for i in range(sets):
        frames = {}
        for r in renderers:
            f = r.render(START_NS + i * STEP_NS, settings, rng)
            frames[f"d415/{r.spec.serial}"] = (f.ir_y8, f.depth_z16)
        out.append(frames)
    render_ms = 1e3 * (time.perf_counter() - t0) / (sets * len(renderers))
    t_mid = START_NS + STEP_NS * np.arange(sets) + settings.exposure_us * 500
    kin = forward_kinematics(sc.sample(t_mid).pose, sc.shape)
    joints = np.asarray(democap_joints(kin), np.float64)
    cal = Calibration(
        cameras=tuple(
            CameraCalibration(
                name=f"d415/{r.spec.serial}",
                kind="d415",
                serial=str(r.spec.serial),
                width=r.width,
                height=r.height,
                K=r.K,
                distortion=np.zeros(5),
                T_world_cam=r.T_world_cam,
                source="simulated truth",
            )
            for r in renderers
        )
    )
    return out, joints, cal, render_ms


def _median(results: Sequence[LiveResult]) -> dict[str, float]:
    keys = sorted({k for r in results for k in r.timings_ms})
    return {
        k: float(np.median([r.timings_ms[k] for r in results if k in r.timings_ms])) for k in keys
    }


def _stages(med: dict[str, float]) -> dict[str, float]:
    """Per-stage medians with the per-camera measurements summed up as one figure."""
    cams = [k for k in med if k.startswith("measure_d415/")]
    out = {k: round(v, 3) for k, v in med.items() if k not in cams}
    out["measure_per_camera_ms"] = round(float(np.mean([med[k] for k in cams])), 3)
    return out


def paced(sets: Sequence[Frames], hz: float) -> tuple[Iterator[Frames], list[float]]:
    """The sets released on a ``hz`` clock; the release times (perf_counter) are recorded."""
    released: list[float] = []

    def gen() -> Iterator[Frames]:
        t0 = time.perf_counter()
        for i, s in enumerate(sets):
            wait = t0 + i / hz - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            released.append(time.perf_counter())
            yield s

    return gen(), released


@dataclass
class Round:
    """One pass of one configuration: throughput (sets/s) and CPU cores used on average
    (process CPU time / wall time) of the sequential and the streamed pass."""

    seq_fps: float
    seq_cores: float
    stream_fps: float
    stream_cores: float

    @property
    def stream_cpu_ms(self) -> float:
        """Process CPU time per set in the streamed pass (ms): the work, whatever the load."""
        return 1e3 * self.stream_cores / self.stream_fps


def _timed(fn: Callable[[], list[LiveResult]]) -> tuple[list[LiveResult], float, float]:
    c0, t0 = time.process_time(), time.perf_counter()
    out = fn()
    wall = time.perf_counter() - t0
    return out, len(out) / wall, (time.process_time() - c0) / wall


def run_config(
    predictor: DemocapPredictor,
    cal: Calibration,
    sets: Sequence[Frames],
    warm: Sequence[Frames],
    *,
    workers: int,
) -> tuple[list[LiveResult], Round]:
    """One round of one configuration: a sequential pass (:meth:`LivePipeline.process` set
    after set), then a streamed one (:meth:`LivePipeline.stream`), whose results must equal
    the sequential ones (checked)."""
    with LivePipeline(predictor, cameras_from_calibration(cal), workers=workers) as pipe:
        for s in warm:
            pipe.process(s)
        seq, seq_fps, seq_cores = _timed(lambda: [pipe.process(s) for s in sets])
        streamed, fps, cores = _timed(lambda: list(pipe.stream(sets)))
    for a, b in zip(seq, streamed, strict=True):
        if a.prediction is None or b.prediction is None:
            continue
        if not np.array_equal(a.prediction.joints_m, b.prediction.joints_m):
            msg = f"set {b.index}: streamed joints differ from the sequential ones"
            raise SystemExit(msg)
    return seq, Round(seq_fps, seq_cores, fps, cores)


def run_paced(
    predictor: DemocapPredictor, cal: Calibration, sets: Sequence[Frames], *, workers: int
) -> dict[str, float]:
    """The sets released at :data:`LIVE_HZ`: latency from release to joints (ms)."""
    with LivePipeline(predictor, cameras_from_calibration(cal), workers=workers) as pipe:
        src, released = paced(sets, LIVE_HZ)
        t0 = time.perf_counter()
        lat = []
        for r in pipe.stream(src):
            lat.append(1e3 * (time.perf_counter() - released[r.index]))
        wall = time.perf_counter() - t0
    a = np.asarray(lat)
    return {
        "rate_hz": LIVE_HZ,
        "sets": len(lat),
        "achieved_fps": round(len(lat) / wall, 2),
        "latency_p50_ms": round(float(np.median(a)), 2),
        "latency_p95_ms": round(float(np.percentile(a, 95)), 2),
        "latency_max_ms": round(float(a.max()), 2),
        # Later sets waiting longer than earlier ones = falling behind the cameras.
        "latency_last5_minus_first5_ms": round(float(a[-5:].mean() - a[:5].mean()), 2),
    }


def mpjpe(results: Sequence[LiveResult], joints: F64) -> dict[str, float]:
    """MPJPE (mm) and PCK3D@50 over the evaluation's 17 joints; sets without a prediction are
    counted."""
    sel = list(EVAL_JOINTS)
    err = [
        np.linalg.norm(r.prediction.joints_m[sel] - joints[i][sel], axis=1)
        for i, r in enumerate(results)
        if r.prediction is not None
    ]
    e = 1e3 * np.concatenate(err)
    return {
        "mpjpe_mm": round(float(e.mean()), 1),
        "pck50": round(float(np.mean(e < 50.0)), 3),
        "sets_without_prediction": sum(r.prediction is None for r in results),
        "points_per_cloud": round(float(np.mean([r.points for r in results])), 1),
    }


def _table(rows: dict[str, dict[str, float]]) -> list[str]:
    names = list(rows)
    keys: list[str] = []
    for r in rows.values():
        keys += [k for k in r if k not in keys]
    lines = [f"{'stage (ms)':24s}" + "".join(f"{n:>16s}" for n in names)]
    for k in keys:
        cells = "".join(f"{rows[n][k]:16.2f}" if k in rows[n] else f"{'':16s}" for n in names)
        lines.append(f"{k.removesuffix('_ms'):24s}{cells}")
    return lines


#: The configurations timed: label -> (predictor from the checkpoint, pipeline workers). The
#: first is :func:`~process.democap.live.live_predictor` in the default pipeline: the ``fps``
#: figure.
LITE_CONFIGS: dict[str, tuple[Callable[[Checkpoint], DemocapPredictor], int]] = {
    "live": (live_predictor, DEFAULT_WORKERS),
    "live-2thr": (
        lambda c: DemocapPredictor(
            c, rotations=LIVE_ROTATIONS, solve=False, workers=LIVE_ROTATIONS, compile=True
        ),
        DEFAULT_WORKERS,
    ),
    "live-eager": (
        lambda c: DemocapPredictor(
            c, rotations=LIVE_ROTATIONS, solve=False, workers=LIVE_ROTATIONS
        ),
        DEFAULT_WORKERS,
    ),
    "live-eager-1thr": (
        lambda c: DemocapPredictor(c, rotations=LIVE_ROTATIONS, solve=False, workers=1),
        DEFAULT_WORKERS,
    ),
    "live-solve": (
        lambda c: DemocapPredictor(c, rotations=LIVE_ROTATIONS, workers=LIVE_ROTATIONS),
        DEFAULT_WORKERS,
    ),
    "offline": (DemocapPredictor, DEFAULT_WORKERS),
    "offline-network": (lambda c: DemocapPredictor(c, solve=False), DEFAULT_WORKERS),
    "single": (lambda c: DemocapPredictor(c, rotations=1, solve=False), DEFAULT_WORKERS),
}
PAPER_CONFIGS: dict[str, dict[str, Any]] = {
    "paper": {"rotations": LIVE_ROTATIONS, "workers": LIVE_ROTATIONS, "solve": False},
    "paper-single": {"rotations": 1, "solve": False},
}


def _describe(p: DemocapPredictor, workers: int) -> str:
    solve = " + skeleton solve" if p.solves else ""
    compiled = ", compiled" if p.compiled else ""
    return (
        f"{p.rotations} rotation(s) on {p.workers} thread(s){compiled}{solve}, "
        f"{workers} measuring thread(s)"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40, help="frame sets timed (4 frames each)")
    ap.add_argument("--warmup", type=int, default=5, help="frame sets run before timing")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds per config")
    ap.add_argument("--paper-frames", type=int, default=3, help="frame sets timed for paper")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    load_start = os.getloadavg()

    all_sets, joints, cal, render_ms = render_scene(args.seed, args.warmup + args.frames)
    warm, sets, truth = all_sets[: args.warmup], all_sets[args.warmup :], joints[args.warmup :]
    print(
        f"rendered {len(all_sets)} sets × 4 D415 at 848×480 ({render_ms:.1f} ms per frame, "
        "not timed)"
    )

    ckpt = load_checkpoint(DEFAULT_CHECKPOINT)
    configs: dict[str, tuple[DemocapPredictor, int]] = {}
    first_s: dict[str, float] = {}
    for name, (make, w) in LITE_CONFIGS.items():
        configs[name] = (make(ckpt), w)
        # the first set alone: a compiled predictor compiles here
        with LivePipeline(configs[name][0], cameras_from_calibration(cal), workers=w) as pipe:
            t0 = time.perf_counter()
            pipe.process(warm[0])
            first_s[name] = round(time.perf_counter() - t0, 2)
    seq: dict[str, list[LiveResult]] = {c: [] for c in configs}
    rounds: dict[str, list[Round]] = {c: [] for c in configs}
    for _ in range(args.rounds):
        for name, (pred, w) in configs.items():
            res, rnd = run_config(pred, cal, sets, warm, workers=w)
            seq[name] += res
            rounds[name].append(rnd)
    live = {
        c: run_paced(configs[c][0], cal, sets, workers=configs[c][1])
        for c in ("live", "live-eager", "single")
    }
    accuracy = {c: mpjpe(seq[c][: len(sets)], truth) for c in configs}

    torch.manual_seed(0)
    paper_cfg = CONFIGS["paper"]
    paper_ckpt = Checkpoint(paper_cfg, build_network(paper_cfg).eval())
    paper_seq: dict[str, list[LiveResult]] = {}
    paper_rounds: dict[str, Round] = {}
    paper_params = sum(p.numel() for p in paper_ckpt.model.parameters())
    for name, kw in PAPER_CONFIGS.items():
        pred = DemocapPredictor(paper_ckpt, **kw)
        paper_seq[name], paper_rounds[name] = run_config(
            pred, cal, sets[: args.paper_frames], warm[:1], workers=DEFAULT_WORKERS
        )
        del pred
    load_end = os.getloadavg()

    def med(c: str, key: str) -> float:
        return round(float(np.median([getattr(r, key) for r in rounds[c]])), 2)

    stages = {c: _stages(_median(seq[c])) for c in configs}
    stages |= {c: _stages(_median(r)) for c, r in paper_seq.items()}
    for line in _table(stages):
        print(line)
    for c, (pred, w) in configs.items():
        print(
            f"lite {c} ({_describe(pred, w)}): sequential {med(c, 'seq_fps'):.1f} fps "
            f"({med(c, 'seq_cores'):.2f} cores busy), pipelined {med(c, 'stream_fps'):.1f} fps "
            f"({med(c, 'stream_cores'):.2f} cores busy, {med(c, 'stream_cpu_ms'):.1f} CPU ms "
            f"per set), MPJPE {accuracy[c]['mpjpe_mm']} mm; "
            "rounds (seq / pipelined): "
            + ", ".join(f"{r.seq_fps:.1f} / {r.stream_fps:.1f}" for r in rounds[c])
        )
    for c, v in live.items():
        print(
            f"lite {c} paced at {LIVE_HZ:.0f} Hz: {v['achieved_fps']} fps, latency (release "
            f"to joints) p50 {v['latency_p50_ms']} ms, p95 {v['latency_p95_ms']} ms"
        )
    for c, r in paper_rounds.items():
        print(
            f"{c}: sequential {r.seq_fps:.2f} fps (network {stages[c]['network_ms']:.0f} ms), "
            f"pipelined {r.stream_fps:.2f} fps"
        )
    print(f"load average {load_start[0]:.2f} at the start, {load_end[0]:.2f} at the end")
    result: dict[str, Any] = {
        "benchmark": "democap_infer",
        "what": "4 D415 IR+depth frames (848x480) -> world joints; lite, live predictor "
        f"({_describe(*configs['live'])}), pipelined stream",
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "load_avg_start_end": [round(load_start[0], 2), round(load_end[0], 2)],
        "threads": args.threads,
        "frames": len(sets),
        "rounds": args.rounds,
        "fps": med("live", "stream_fps"),
        "target_fps": 36.0,
        "compiled": configs["live"][0].compiled,
        "lite": {
            c: {
                "config": _describe(pred, w),
                "first_set_s": first_s[c],
                "sequential_ms": stages[c],
                "sequential_fps": med(c, "seq_fps"),
                "sequential_cores_busy": med(c, "seq_cores"),
                "pipelined_fps": med(c, "stream_fps"),
                "pipelined_cores_busy": med(c, "stream_cores"),
                "pipelined_cpu_ms_per_set": med(c, "stream_cpu_ms"),
                "rounds_fps_sequential_pipelined": [
                    [round(r.seq_fps, 2), round(r.stream_fps, 2)] for r in rounds[c]
                ],
                "accuracy": accuracy[c],
            }
            for c, (pred, w) in configs.items()
        },
        "lite_paced": live,
        "paper": {
            c: {
                "frames": len(paper_seq[c]),
                "sequential_ms": stages[c],
                "sequential_fps": round(r.seq_fps, 3),
                "pipelined_fps": round(r.stream_fps, 3),
            }
            for c, r in paper_rounds.items()
        },
        "paper_params": paper_params,
        "lite_params": sum(p.numel() for p in ckpt.model.parameters()),
        "render_ms_per_frame": round(render_ms, 2),
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
