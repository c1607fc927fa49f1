"""Accuracy of Vicon ↔ D415 time alignment on simulated sessions (issue 6).

For each seed: the default scenario, the simulated Vicon, and one or more D415s rendered by the
mock renderer at their 30 Hz frame times over the whole session (the slow part: ≈ 0.1–0.2 s a
frame), markers measured with :func:`mocaprig.calib.markers.measure_frame`. Then claps
(:func:`find_claps_vicon`, :func:`find_claps_d415`) → :func:`clock_from_claps` →
:func:`refine_by_reprojection` with the true extrinsics perturbed by a registration-grade error
(0.1°, 2 mm), and, for comparison, :func:`refine_by_speed`. Errors are against the true clocks:
offset at the start, middle and end of the session, drift. Prints one JSON object as its last
line (``offset_err_ms_mean``/``_max``, ``drift_err_ppm_mean``/``_max``).

Frames are cached under ``--cache`` (default: the system's temp folder) so reruns are fast.
"""

from __future__ import annotations

import argparse
import json
import pickle
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from mocaprig.calib import time_align as ta
from mocaprig.calib.calibration import ClockMapping
from mocaprig.calib.markers import MarkerFrame, measure_frame
from mocaprig.calib.vicon import MarkerTrajectories
from mocaprig.drivers_mock.clock import DeviceClock
from mocaprig.drivers_mock.d415_render import IrSettings, SceneRenderer
from mocaprig.drivers_mock.scenario import Scenario, build_scenario
from mocaprig.drivers_mock.vicon import simulate_vicon


def render(sc: Scenario, cam: int, *, seed: int) -> list[MarkerFrame]:
    spec = sc.rig.d415[cam]
    renderer = SceneRenderer(sc, spec)
    settings = IrSettings()
    clock = sc.clocks[spec.name]
    period = round(1e9 / 30 / clock.rate)
    phase = int(np.random.default_rng(seed).integers(0, period))
    rng = np.random.default_rng(seed)
    out = []
    k = 0
    while (t := phase + k * period) < sc.duration_ns:
        f = renderer.render(int(t), settings, rng)
        t_dev = int(clock.device_ticks(np.array([t + settings.exposure_us * 500]))[0]) * 1000
        out.append(
            measure_frame(
                f.ir_y8,
                f.depth_z16,
                renderer.K,
                camera=f"d415/{spec.serial}",
                t_dev_ns=t_dev,
                frame_counter=k,
            )
        )
        k += 1
    return out


def errors(m: ClockMapping, dev: DeviceClock, ref: DeviceClock, t_dev: list[int]) -> dict[str, Any]:
    out = []
    for t in t_dev:
        truth = ref.offset_ns + (t - dev.offset_ns) / dev.rate * ref.rate
        out.append((float(m.to_reference_ns(np.array([t]))[0]) - truth) / 1e6)
    return {
        "offset_err_ms": out,
        "drift_err_ppm": m.drift_ppm - (ref.rate / dev.rate - 1.0) * 1e6,
        "offset_sigma_ms": m.offset_sigma_ns / 1e6,
        "drift_sigma_ppm": m.drift_sigma_ppm,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--cameras", default="0", help="comma-separated D415 indices")
    parser.add_argument("--every", type=int, default=1, help="use every n-th frame")
    parser.add_argument(
        "--cache", type=Path, default=Path(tempfile.gettempdir()) / "mocaprig-bench-cache"
    )
    args = parser.parse_args()
    args.cache.mkdir(exist_ok=True)
    rows = []
    for seed in range(args.seeds):
        sc = build_scenario("default", seed=seed, seconds=args.seconds)
        cap = simulate_vicon(sc)
        traj = MarkerTrajectories(
            cap.labels,
            cap.rate_hz,
            cap.points_m,
            np.where(cap.residuals_mm < 0, np.nan, cap.residuals_mm / 1000),
            cap.start_field,
        )
        vclaps = ta.find_claps_vicon(traj)
        vt, vs = ta.speed_from_trajectories(traj)
        for cam in (int(c) for c in args.cameras.split(",")):
            path = args.cache / f"frames_s{seed}_c{cam}_{args.seconds:g}.pkl"
            if path.exists():
                frames = pickle.loads(path.read_bytes())
            else:
                frames = render(sc, cam, seed=seed)
                path.write_bytes(pickle.dumps(frames))
            frames = frames[:: args.every]
            spec = sc.rig.d415[cam]
            dev, vicon = sc.clocks[spec.name], sc.clocks["vicon"]
            rng = np.random.default_rng(1000 + seed)
            t_wc = np.array(spec.ir_left.T_world_cam)
            rot = Rotation.from_rotvec(rng.normal(size=3) / np.sqrt(3) * np.radians(0.1))
            t_wc[:3, :3] = rot.as_matrix() @ t_wc[:3, :3]
            t_wc[:3, 3] += rng.normal(size=3) / np.sqrt(3) * 0.002
            ends = [frames[0].t_dev_ns, frames[len(frames) // 2].t_dev_ns, frames[-1].t_dev_ns]
            row: dict[str, Any] = {"seed": seed, "camera": cam, "frames": len(frames)}
            t0 = time.perf_counter()
            try:
                m0 = ta.clock_from_claps(frames[0].camera, ta.find_claps_d415(frames), vclaps)
            except Exception as err:
                row["error"] = str(err)[:200]
                rows.append(row)
                print(json.dumps(row), flush=True)
                continue
            t1 = time.perf_counter()
            m1 = ta.refine_by_reprojection(m0, frames, traj, spec.ir_left.K, t_wc)
            t2 = time.perf_counter()
            dt, ds = ta.speed_from_frames(frames)
            try:
                m2 = ta.refine_by_speed(m0, dt, ds, vt, vs)
                row["speed"] = errors(m2, dev, vicon, ends)
            except Exception as err:
                row["speed"] = {"error": str(err)[:200]}
            row["clap"] = errors(m0, dev, vicon, ends)
            row["reproj"] = errors(m1, dev, vicon, ends)
            row["seconds_claps"] = round(t1 - t0, 3)
            row["seconds_reproj"] = round(t2 - t1, 3)
            rows.append(row)
            print(json.dumps(row), flush=True)
    ok = [r for r in rows if "reproj" in r]
    summary: dict[str, Any] = {
        "benchmark": "calib_time_align",
        "session_s": args.seconds,
        "runs": len(rows),
        "aligned": len(ok),
    }
    for method in ("clap", "reproj"):
        off = np.array([np.abs(r[method]["offset_err_ms"]) for r in ok]).ravel()
        dr = np.array([abs(r[method]["drift_err_ppm"]) for r in ok])
        if off.size:
            summary[f"{method}_offset_err_ms_mean"] = round(float(off.mean()), 4)
            summary[f"{method}_offset_err_ms_max"] = round(float(off.max()), 4)
            summary[f"{method}_drift_err_ppm_mean"] = round(float(dr.mean()), 2)
            summary[f"{method}_drift_err_ppm_max"] = round(float(dr.max()), 2)
    if ok:
        summary["offset_err_ms_mean"] = summary["reproj_offset_err_ms_mean"]
        summary["offset_err_ms_max"] = summary["reproj_offset_err_ms_max"]
        summary["drift_err_ppm_mean"] = summary["reproj_drift_err_ppm_mean"]
        summary["drift_err_ppm_max"] = summary["reproj_drift_err_ppm_max"]
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
