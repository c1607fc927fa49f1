"""Benchmark ``mocaprig calibrate vicon`` on a simulated 60 s session (issue 6).

Simulates the session once (4 D415 through the real recorder, the Vicon C3D and the truth;
``--session DIR`` reuses one), then times :func:`calib.vicon_calibration.calibrate_vicon` (wall
clock, the whole call: reading the recording and the C3D, marker measurement, registration,
clocks) and scores the result against the truth. Prints one JSON object as its last line with
``seconds`` and ``session_seconds``.

    .venv/bin/python benchmarks/calibrate_session.py                 # simulate into a temp dir
    .venv/bin/python benchmarks/calibrate_session.py --session sim60  # reuse (or create) sim60/
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path
from typing import Any

from mocaprig.calib.vicon_calibration import calibrate_vicon, evaluate_calibration
from mocaprig.drivers_mock.session import simulate_session


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--session", type=Path, default=None, help="session folder to (re)use")
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--cameras", type=int, default=4)
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        root = args.session if args.session is not None else Path(tmp) / "sim"
        sim_s = 0.0
        if not (root / "session.mcap").is_file():
            t0 = time.perf_counter()
            simulate_session(
                root, seed=args.seed, seconds=args.seconds, devices=("d415",), cameras=args.cameras
            )
            sim_s = time.perf_counter() - t0
        truth = json.loads((root / "truth" / "scenario.json").read_text())
        session_s = truth["duration_ns"] / 1e9

        t0 = time.perf_counter()
        cpu0 = time.process_time()
        result = calibrate_vicon(root / "session.mcap", root / "vicon" / "session.c3d")
        seconds = time.perf_counter() - t0
        cpu = time.process_time() - cpu0

        ev = evaluate_calibration(result.calibration, root)
        devs = [d for d in ev.devices if d.device.startswith("d415/")]
        rows: list[dict[str, Any]] = [
            {
                "device": d.device,
                "rotation_error_deg": round(d.rotation_error_deg, 4),
                "translation_error_mm": round(d.translation_error_mm, 3),
                "clock_offset_error_ms": round(d.clock_offset_error_ms, 4),
                "drift_error_ppm": round(d.drift_error_ppm, 2),
                "reprojection_rms_px": round(
                    result.registrations[d.device].bundle.reprojection_rms_px, 3
                ),
            }
            for d in devs
        ]
        for r in rows:
            print(
                f"{r['device']}: {r['rotation_error_deg']:.4f} deg, "
                f"{r['translation_error_mm']:.2f} mm, clock {r['clock_offset_error_ms']:+.3f} ms, "
                f"drift {r['drift_error_ppm']:+.1f} ppm, {r['reprojection_rms_px']:.3f} px"
            )
        out = {
            "benchmark": "calibrate_session",
            "seconds": round(seconds, 2),
            "cpu_seconds": round(cpu, 2),
            "session_seconds": session_s,
            "cameras": len(devs),
            "seed": int(truth["seed"]),
            "simulate_seconds": round(sim_s, 1),
            "max_rotation_error_deg": max(r["rotation_error_deg"] for r in rows),
            "max_translation_error_mm": max(r["translation_error_mm"] for r in rows),
            "max_abs_clock_offset_error_ms": max(abs(r["clock_offset_error_ms"]) for r in rows),
            "max_abs_drift_error_ppm": max(abs(r["drift_error_ppm"]) for r in rows),
            "per_camera": rows,
            "machine": f"{platform.machine()}, {platform.python_version()}",
        }
        print(json.dumps(out))


if __name__ == "__main__":
    main()
