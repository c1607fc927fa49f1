"""Calibration figures over random hidden worlds (issue 16, item 3).

For each world seed: ``simulate_session(..., world="random")`` (30 s, 4 D415 + the DAVIS
without DVS, the Vicon C3D with its ``D415_SYNC`` channel), then
:func:`calib.vicon_calibration.calibrate_vicon` twice on the same files, with the sync channel
and without it (``sync_channel=None``: video clocks), each scored against the truth by
:func:`evaluate_calibration`. A calibration that refuses (``CalibrationError``) is counted and
its message kept: a refusal naming what is unobservable is an acceptable outcome, a silently
wrong figure is not. Prints per figure the worst and the 95th percentile (over cameras × worlds)
of each mode, then one JSON object as the last line (every per-world row included).

    nice -n 10 .venv/bin/python benchmarks/calibrate_worlds.py --worlds 20
    nice -n 10 .venv/bin/python benchmarks/calibrate_worlds.py --worlds 1 --seconds 8 --keep w
    .venv/bin/python benchmarks/calibrate_worlds.py --rows run1.json run2.json   # merge runs

``--keep DIR`` keeps each world's session (about 4 GB for 30 s) and reuses it when it is there,
so a changed estimator can be re-run on the same worlds without simulating them again.
``--rows`` summarises the JSON lines of earlier runs (the last line of each) as one run.

Figures (absolute errors; D415 offsets at the session midpoint): ``rotation_deg``,
``translation_mm``, ``d415_offset_us``, ``d415_drift_ppm``, ``davis_vs_d415_us`` (the DAVIS ↔
D415-master error, ``clock_error_vs_via_us``) and ``davis_whole_periods`` (that error in whole
frame periods, rounded: any non-zero is a pairing error).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np

from mocaprig.calib.vicon_calibration import calibrate_vicon, evaluate_calibration
from mocaprig.calib.vicon_calibration_options import CalibrationOptions
from mocaprig.drivers_mock.session import simulate_session
from mocaprig.errors import MocaprigError

#: Frame period of the D415s (µs), to count whole-period DAVIS pairing errors.
_PERIOD_US = 1e6 / 30.0

_FIGURES = (
    "rotation_deg",
    "translation_mm",
    "d415_offset_us",
    "d415_drift_ppm",
    "davis_vs_d415_us",
    "davis_whole_periods",
)


def _calibrate(root: Path, *, sync: bool) -> dict[str, Any]:
    """One calibration of a simulated session, scored against its truth."""
    opt = CalibrationOptions(sync_channel="D415_SYNC" if sync else None)
    t0 = time.process_time()
    try:
        result = calibrate_vicon(root / "session.mcap", root / "vicon" / "session.c3d", options=opt)
    except MocaprigError as err:
        return {"refused": str(err), "cpu_s": round(time.process_time() - t0, 1)}
    cpu = time.process_time() - t0
    ev = evaluate_calibration(result.calibration, root)
    row: dict[str, Any] = {"cpu_s": round(cpu, 1), "cameras": [], "notes": list(result.notes)}
    for d in ev.devices:
        if d.device.startswith("d415/"):
            row["cameras"].append(
                {
                    "device": d.device,
                    "rotation_deg": abs(d.rotation_error_deg),
                    "translation_mm": abs(d.translation_error_mm),
                    "d415_offset_us": abs(d.clock_offset_error_ms) * 1e3,
                    "d415_drift_ppm": abs(d.drift_error_ppm),
                }
            )
        elif d.device.startswith("davis/"):
            err_us = d.clock_error_vs_via_us
            row["davis_vs_d415_us"] = abs(err_us)
            row["davis_whole_periods"] = (
                abs(round(err_us / _PERIOD_US)) if math.isfinite(err_us) else math.nan
            )
    row["davis_missing"] = "davis_vs_d415_us" not in row
    return row


def _world_row(seed: int, seconds: float, keep: Path | None) -> dict[str, Any]:
    tmp = Path(tempfile.mkdtemp(prefix=f"world{seed}-"))
    root = (keep / f"world{seed}") if keep is not None else tmp / "sim"
    try:
        t0 = time.perf_counter()
        complete = (root / "vicon" / "session.c3d").is_file() and (
            root / "truth" / "davis_clock.json"
        ).is_file()
        if not complete:  # absent, or a run cut short: simulate (again)
            simulate_session(
                root,
                seed=seed,
                seconds=seconds,
                devices=("davis", "d415"),
                cameras=4,
                world="random",
                overwrite=True,
            )
        sim_s = time.perf_counter() - t0
        world = json.loads((root / "truth" / "scenario.json").read_text())["world"]
        row: dict[str, Any] = {"seed": seed, "simulate_s": round(sim_s, 1), "world": world}
        row["sync"] = _calibrate(root, sync=True)
        row["video"] = _calibrate(root, sync=False)
        return row
    except Exception as err:  # a crash of one world is a finding, not the end of the run
        return {
            "seed": seed,
            "crashed": f"{type(err).__name__}: {err}",
            "trace": traceback.format_exc(),
        }
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _summary(rows: list[dict[str, Any]], mode: str) -> dict[str, Any]:
    values: dict[str, list[float]] = {f: [] for f in _FIGURES}
    refused: list[str] = []
    for r in rows:
        m = r.get(mode)
        if m is None:
            continue
        if "refused" in m:
            refused.append(f"world {r['seed']}: {m['refused']}")
            continue
        for c in m["cameras"]:
            for f in ("rotation_deg", "translation_mm", "d415_offset_us", "d415_drift_ppm"):
                values[f].append(float(c[f]))
        for f in ("davis_vs_d415_us", "davis_whole_periods"):
            if f in m:
                values[f].append(float(m[f]))
    out: dict[str, Any] = {"refused": refused}
    for f, v in values.items():
        arr = np.asarray(v, dtype=np.float64)
        nan = int(np.count_nonzero(~np.isfinite(arr)))
        fin = arr[np.isfinite(arr)]
        out[f] = {
            "n": int(arr.size),
            "nan": nan,
            "p95": float(np.percentile(fin, 95)) if fin.size else math.nan,
            "worst": float(fin.max()) if fin.size else math.nan,
        }
    return out


_LABELS = {
    "rotation_deg": ("rotation error (°)", "{:.3f}"),
    "translation_mm": ("camera centre error (mm)", "{:.2f}"),
    "d415_offset_us": ("D415 ↔ Vicon offset error (µs)", "{:.1f}"),
    "d415_drift_ppm": ("D415 ↔ Vicon drift error (ppm)", "{:.2f}"),
    "davis_vs_d415_us": ("DAVIS ↔ D415 master error (µs)", "{:.1f}"),
    "davis_whole_periods": ("DAVIS pairing error (whole periods)", "{:.0f}"),
}


def _markdown(summary: dict[str, Any], rows: list[dict[str, Any]], seconds: float) -> str:
    """The summary as the markdown table the docs quote (so they cannot drift from it)."""
    seeds = ", ".join(str(r["seed"]) for r in rows)
    lines = [
        (
            f"{len(rows)} random worlds (seeds {seeds}), {seconds:g} s, 4 D415 + DAVIS; p95 and "
            "worst over cameras × worlds (DAVIS: over worlds)"
        ),
        "",
        "| figure | sync channel: p95 | worst | video only: p95 | worst |",
        "|---|---|---|---|---|",
    ]
    for f in _FIGURES:
        label, fmt = _LABELS[f]
        cells = []
        for mode in ("sync", "video"):
            v = summary[mode][f]
            nan = f" ({v['nan']} NaN)" if v["nan"] else ""
            cells += [fmt.format(v["p95"]), fmt.format(v["worst"]) + nan]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    for mode in ("sync", "video"):
        for r in summary[mode]["refused"]:
            lines.append(f"\nrefused ({mode}): {r}")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--worlds", type=int, default=20, help="random worlds (default 20)")
    parser.add_argument("--first-seed", type=int, default=1000, help="seed of the first world")
    parser.add_argument("--seconds", type=float, default=30.0, help="session length (s)")
    parser.add_argument("--keep", type=Path, default=None, help="keep (or reuse) sessions here")
    parser.add_argument(
        "--rows", type=Path, nargs="+", default=None, help="summarise earlier runs' JSON lines"
    )
    args = parser.parse_args()

    t0 = time.perf_counter()
    rows: list[dict[str, Any]] = []
    if args.rows:
        for path in args.rows:
            last = path.read_text(encoding="utf-8").strip().splitlines()[-1]
            rows.extend(json.loads(last)["rows"])
        args.worlds = len(rows)
        args.first_seed = min(int(r["seed"]) for r in rows)
    for i in range(0 if args.rows else args.worlds):
        seed = args.first_seed + i
        row = _world_row(seed, args.seconds, args.keep)
        rows.append(row)
        done = time.perf_counter() - t0
        if "crashed" in row:
            print(f"world {seed}: CRASHED {row['crashed']}", flush=True)
            continue
        for mode in ("sync", "video"):
            m = row[mode]
            if "refused" in m:
                print(f"world {seed} [{mode}]: refused: {m['refused']}", flush=True)
                continue
            cams = m["cameras"]
            print(
                f"world {seed} [{mode}]: rot ≤ {max(c['rotation_deg'] for c in cams):.3f}°, "
                f"trans ≤ {max(c['translation_mm'] for c in cams):.2f} mm, D415 offset ≤ "
                f"{max(c['d415_offset_us'] for c in cams):.1f} µs, drift ≤ "
                f"{max(c['d415_drift_ppm'] for c in cams):.2f} ppm, DAVIS–D415 "
                f"{m.get('davis_vs_d415_us', math.nan):.1f} µs ({done:.0f} s so far)",
                flush=True,
            )
    summary = {mode: _summary(rows, mode) for mode in ("sync", "video")}
    for mode, s in summary.items():
        label = "with the Vicon sync channel" if mode == "sync" else "video only (no sync channel)"
        print(f"{label}: {len(s['refused'])} refused")
        for f in _FIGURES:
            v = s[f]
            print(
                f"  {f:<20} p95 {v['p95']:10.3f}   worst {v['worst']:10.3f}   "
                f"(n {v['n']}, nan {v['nan']})"
            )
    print(_markdown(summary, rows, args.seconds))
    out = {
        "benchmark": "calibrate_worlds",
        "worlds": args.worlds,
        "crashed": sum("crashed" in r for r in rows),
        "first_seed": args.first_seed,
        "seeds": [int(r["seed"]) for r in rows],
        "session_seconds": args.seconds,
        "cameras": 4,
        "wall_s": round(time.perf_counter() - t0, 1),
        "machine": (
            f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"
        ),
        "summary": summary,
        "rows": rows,
    }
    print(json.dumps(out, default=float))


if __name__ == "__main__":
    main()
