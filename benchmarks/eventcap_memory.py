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
    .venv/bin/python benchmarks/eventcap_memory.py --whole   # whole takes (~1.5 h for 60 s)

Each run's resident memory is also sampled every 2 s (``/proc``), giving its rise after the
first minute (``rss_after_settle_mb``) and a coarse trace.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
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


def _rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def _sample(pid: int, every_s: float, samples: list[tuple[float, float]]) -> None:
    """Resident memory of ``pid`` every ``every_s`` until it exits: ``(s since start, MB)``."""
    t0 = time.perf_counter()
    while True:
        rss = _rss_mb(pid)
        if rss is None:
            return
        samples.append((round(time.perf_counter() - t0, 1), round(rss, 1)))
        time.sleep(every_s)


def _run(sim: Path, start_s: float, batches: int | None, tag: str) -> dict[str, Any]:
    out = sim / f"results-{tag}.mcap"
    cmd = [sys.executable, "-m", "mocaprig.cli", "-q", "eventcap", "run"]
    cmd += [str(sim / "session.mcap"), "--calib", str(sim / "calib.toml")]
    cmd += ["--detections", str(sim / "det.json"), "--shape", str(sim / "truth/scenario.json")]
    cmd += ["--out", str(out), "--start", f"{start_s:.3f}"]
    if batches is not None:
        cmd += ["--batches", str(batches)]
    cmd += ["--overwrite", "--json"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    samples: list[tuple[float, float]] = []
    sampler = threading.Thread(target=_sample, args=(proc.pid, 2.0, samples), daemon=True)
    sampler.start()
    assert proc.stdout is not None
    stdout = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    sampler.join()
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        msg = f"eventcap run failed ({proc.returncode}): {' '.join(cmd)}"
        raise SystemExit(msg)
    summary = json.loads(stdout)
    wall = time.perf_counter() - t0
    # Resident memory after the first minute of batches (or after the first 20 % of a short
    # run): what grows with the take shows as a rise from its start to its end.
    settle = min(60.0, 0.2 * wall)
    later = [mb for t, mb in samples if t >= settle]
    return {
        "start_s": round(start_s, 3),
        "batches": summary.get("batches"),
        "peak_rss_mb": round(usage.ru_maxrss / 1024, 1),  # Linux: KiB
        "wall_s": round(wall, 1),
        "tracking_frames": summary.get("tracking_frames"),
        "rss_after_settle_mb": {
            "first": later[0] if later else None,
            "max": max(later) if later else None,
            "last": later[-1] if later else None,
        },
        "rss_trace_mb": samples[:: max(1, len(samples) // 20)],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--short-s", type=float, default=5.0, help="short recording (s)")
    ap.add_argument("--long-s", type=float, default=60.0, help="long recording (s)")
    ap.add_argument("--batches", type=int, default=8, help="batches per run")
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--workdir", type=Path, default=None, help="keep the sessions here")
    ap.add_argument(
        "--whole",
        action="store_true",
        help="run each recording's whole take (every batch from 1 s to the end) instead of "
        "--batches near its start and end (60 s: ~1,460 batches, about 90 min)",
    )
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
            if args.whole:
                tag = f"{name}-whole"
                runs[tag] = _run(sim, _LEAD_S, None, tag)
                print(f"{tag}: {seconds:g} s recording ({sizes[name]} MB): {runs[tag]}", flush=True)
                continue
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
                "long_over_short": round(peak["long-whole"] / peak["short-whole"], 3)
                if args.whole
                else round(peak["long-end"] / peak["short-end"], 3),
            }
        )
    )


if __name__ == "__main__":
    main()
