"""Is EventCap's memory bounded by the batch, not by the take? (issue 15, memory)

Simulates two DAVIS sessions (``mocaprig simulate --devices davis --davis-dvs``, karate, the
same seed), a short one and a long one, writes their synthetic detections and DAVIS
calibration (``drivers_mock.eventcap_session``), then runs ``mocaprig eventcap run`` in a child
process on ``--batches`` batches near the start and near the end of each recording, and once on
``3 × --batches`` near the start of the long one. Each child's peak resident memory comes from
``os.wait4`` (its own ``ru_maxrss``), so the runs do not see one another.

Prints one line per run and one JSON object as its last line. The simulation dominates the
time: about 13 s CPU per simulated second (60 s: ~13 min on a 2-core machine). Run::

    .venv/bin/python benchmarks/eventcap_memory.py                 # 5 s and 60 s
    .venv/bin/python benchmarks/eventcap_memory.py --long-s 20 --batches 4
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from mocaprig.drivers_mock.eventcap_session import write_session_inputs

_FRAME_S = 0.04  # the simulator's APS interval
_LEAD_S = 1.0  # past the static start of the karate scenario


def _simulate(out: Path, seconds: float, seed: int) -> float:
    t0 = time.perf_counter()
    cmd = [sys.executable, "-m", "mocaprig.cli", "-q", "simulate", "--scenario", "karate"]
    cmd += ["--seed", str(seed), "--seconds", f"{seconds:g}", "--devices", "davis"]
    cmd += ["--davis-dvs", "--out", str(out), "--json"]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    write_session_inputs(
        out, detections_path=out / "det.json", calibration_path=out / "calib.toml", seed=seed
    )
    return time.perf_counter() - t0


def _run(sim: Path, start_s: float, batches: int, tag: str) -> dict[str, Any]:
    out = sim / f"results-{tag}.mcap"
    cmd = [sys.executable, "-m", "mocaprig.cli", "-q", "eventcap", "run"]
    cmd += [str(sim / "session.mcap"), "--calib", str(sim / "calib.toml")]
    cmd += ["--detections", str(sim / "det.json"), "--shape", str(sim / "truth/scenario.json")]
    cmd += ["--out", str(out), "--start", f"{start_s:.3f}", "--batches", str(batches)]
    cmd += ["--overwrite", "--json"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    assert proc.stdout is not None
    stdout = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        msg = f"eventcap run failed ({proc.returncode}): {' '.join(cmd)}"
        raise SystemExit(msg)
    summary = json.loads(stdout)
    return {
        "start_s": round(start_s, 3),
        "batches": batches,
        "peak_rss_mb": round(usage.ru_maxrss / 1024, 1),  # Linux: KiB
        "wall_s": round(time.perf_counter() - t0, 1),
        "tracking_frames": summary.get("tracking_frames"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--short-s", type=float, default=5.0, help="short recording (s)")
    ap.add_argument("--long-s", type=float, default=60.0, help="long recording (s)")
    ap.add_argument("--batches", type=int, default=8, help="batches per run")
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--workdir", type=Path, default=None, help="keep the sessions here")
    args = ap.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        root = args.workdir if args.workdir is not None else Path(tmp)
        runs: dict[str, dict[str, Any]] = {}
        sizes: dict[str, float] = {}
        sim_s: dict[str, float] = {}
        for name, seconds in (("short", args.short_s), ("long", args.long_s)):
            sim = root / f"{name}-{seconds:g}s"
            if not (sim / "calib.toml").exists():
                sim_s[name] = round(_simulate(sim, seconds, args.seed), 1)
            sizes[name] = round((sim / "session.mcap").stat().st_size / 1e6, 1)
            end_s = seconds - 0.5 - (args.batches + 1) * _FRAME_S
            for pos, start in (("start", _LEAD_S), ("end", end_s)):
                tag = f"{name}-{pos}"
                runs[tag] = _run(sim, start, args.batches, tag)
                print(f"{tag}: {seconds:g} s recording ({sizes[name]} MB): {runs[tag]}", flush=True)
            if name == "long":
                tag = "long-start-3x"
                runs[tag] = _run(sim, _LEAD_S, 3 * args.batches, tag)
                print(f"{tag}: {runs[tag]}", flush=True)
    peak = {k: v["peak_rss_mb"] for k, v in runs.items()}
    print(
        json.dumps(
            {
                "machine": platform.machine(),
                "cpus": os.cpu_count(),
                "short_s": args.short_s,
                "long_s": args.long_s,
                "recording_mb": sizes,
                "simulate_s": sim_s,
                "runs": runs,
                "peak_rss_mb": peak,
                "long_over_short_end": round(peak["long-end"] / peak["short-end"], 3),
            }
        )
    )


if __name__ == "__main__":
    main()
