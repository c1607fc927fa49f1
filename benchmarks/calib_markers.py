"""Benchmark D415 marker measurement (issue 6): frames/s of one camera at 848×480.

Renders a handful of frames of the simulated world with the mock D415 renderer (default
scenario, the camera that sees most markers), then times :func:`calib.markers.measure_frame`
(blobs + robust depth + deprojection) over them on one core, best of several repeats (the
machine is shared). Prints one JSON object as its last line (``frames_per_s``, target ≥ 200).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np

from mocaprig.calib.markers import detect_blobs, measure_frame
from mocaprig.drivers_mock.d415_render import IrSettings, SceneRenderer
from mocaprig.drivers_mock.scenario import build_scenario


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=8, help="distinct frames rendered")
    parser.add_argument("--loops", type=int, default=40, help="passes over the frames per repeat")
    parser.add_argument("--repeats", type=int, default=5, help="repeats; the best is reported")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    sc = build_scenario("default", seed=args.seed, seconds=6)
    renderer = SceneRenderer(sc, sc.rig.d415[0])
    rng = np.random.default_rng(args.seed)
    frames = [
        renderer.render(1_500_000_000 + i * 500_000_000, IrSettings(), rng)
        for i in range(args.frames)
    ]
    n_blobs = [detect_blobs(f.ir_y8)[0].shape[0] for f in frames]

    def run(fn: str) -> float:
        best = float("inf")
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            for _ in range(args.loops):
                for f in frames:
                    if fn == "blobs":
                        detect_blobs(f.ir_y8)
                    else:
                        measure_frame(f.ir_y8, f.depth_z16, renderer.K)
            best = min(best, (time.perf_counter() - t0) / (args.loops * len(frames)))
        return best

    t_frame = run("measure")
    t_blobs = run("blobs")
    result = {
        "benchmark": "calib_markers",
        "width": 848,
        "height": 480,
        "blobs_per_frame": float(np.mean(n_blobs)),
        "frames_per_s": round(1.0 / t_frame, 1),
        "ms_per_frame": round(t_frame * 1e3, 3),
        "detect_blobs_ms": round(t_blobs * 1e3, 3),
        "target_frames_per_s": 200,
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
    }
    print(f"measure_frame: {result['ms_per_frame']} ms/frame ({result['frames_per_s']} frames/s)")
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
