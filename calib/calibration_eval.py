"""A calibration scored against a simulated session's truth (``mocaprig calibrate evaluate``).

:func:`evaluate_calibration` compares a calibration with the truth the simulator wrote
(``SIMDIR/truth/scenario.json`` and ``truth/davis_clock.json``, read directly: calib/ never
imports the simulator): per device, the pose errors and the clock errors.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np

from mocaprig.calib.calibration import Calibration, ClockMapping
from mocaprig.calib.registration import rotation_error_deg
from mocaprig.errors import CalibrationError
from mocaprig.timebase import U32_US_WRAP

__all__ = ["DeviceEvaluation", "Evaluation", "evaluate_calibration"]

_U32_NS: Final = U32_US_WRAP * 1000


@dataclass(frozen=True, slots=True)
class DeviceEvaluation:
    """Errors of one device against the truth (NaN where the calibration lacks that part).

    Attributes:
        device: The calibration's label (``"d415/<serial>"``, ``"davis/<serial>"``).
        truth_name: The simulated world's name of the device (``"d415-0"``, ``"davis"``).
        rotation_error_deg: Angle between calibrated and true camera orientation (deg).
        translation_error_mm: Distance between calibrated and true camera centres (mm).
        clock_offset_error_ms: Mapped minus true Vicon time at the session midpoint (ms).
        drift_error_ppm: Calibrated minus true drift (ppm).
        clock_error_vs_via_us: For a mapping derived through another device's (method
            ``"pulses via <device>"``): its offset error minus that device's, i.e. the error of
            the DAVIS ↔ D415 mapping itself (µs); NaN otherwise.
    """

    device: str
    truth_name: str
    rotation_error_deg: float = math.nan
    translation_error_mm: float = math.nan
    clock_offset_error_ms: float = math.nan
    drift_error_ppm: float = math.nan
    clock_error_vs_via_us: float = math.nan


@dataclass(frozen=True, slots=True)
class Evaluation:
    """A calibration scored against truth.

    Attributes:
        truth_dir: The session folder read.
        devices: One entry per device found in both.
        missing: Truth devices the calibration does not describe.
    """

    truth_dir: str
    devices: tuple[DeviceEvaluation, ...]
    missing: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON-able view (NaN → null in ``emit_json``)."""
        return {
            "truth": self.truth_dir,
            "devices": [
                {
                    "device": d.device,
                    "truth_name": d.truth_name,
                    "rotation_error_deg": d.rotation_error_deg,
                    "translation_error_mm": d.translation_error_mm,
                    "clock_offset_error_ms": d.clock_offset_error_ms,
                    "drift_error_ppm": d.drift_error_ppm,
                    "clock_error_vs_via_us": d.clock_error_vs_via_us,
                }
                for d in self.devices
            ],
            "missing": list(self.missing),
        }


def _read_scenario(truth_dir: Path) -> dict[str, Any]:
    for cand in (truth_dir / "truth" / "scenario.json", truth_dir / "scenario.json"):
        if cand.is_file():
            try:
                data: dict[str, Any] = json.loads(cand.read_text(encoding="utf-8"))
            except (OSError, ValueError) as err:
                msg = f"cannot read the truth file {cand}: {err}"
                raise CalibrationError(msg) from err
            return data
    msg = (
        f"{truth_dir}: no truth/scenario.json; give the folder `mocaprig simulate --out` wrote "
        "(or its truth/ folder)"
    )
    raise CalibrationError(msg)


def _read_davis_clock(root: Path) -> dict[str, Any] | None:
    """``truth/davis_clock.json`` (the recorded DAVIS time base), or None when absent."""
    for cand in (root / "truth" / "davis_clock.json", root / "davis_clock.json"):
        if cand.is_file():
            try:
                data: dict[str, Any] = json.loads(cand.read_text(encoding="utf-8"))
            except (OSError, ValueError) as err:
                msg = f"cannot read the truth file {cand}: {err}"
                raise CalibrationError(msg) from err
            return data
    return None


def _true_clock_error_ns(
    mapping: ClockMapping,
    dev: Mapping[str, Any],
    vic: Mapping[str, Any],
    t_mid_ns: int,
    wraps: bool,
) -> tuple[float, float]:
    """(offset error ns at the session midpoint, drift error ppm) of a device → Vicon mapping."""
    a = float(dev["drift_ppm"]) * 1e-6
    b = float(vic["drift_ppm"]) * 1e-6
    dev_mid = int(dev["offset_ns"]) + round(t_mid_ns * (1.0 + a))
    ref_mid = int(vic["offset_ns"]) + round(t_mid_ns * (1.0 + b))
    candidates = [dev_mid]
    if wraps:  # a D415's u32 µs clock: the recording's device ns may lack whole wraps
        candidates = [dev_mid - k * _U32_NS for k in range(dev_mid // _U32_NS + 1)]
    errs = [float(mapping.to_reference_ns(c) - ref_mid) for c in candidates]
    # The mapped device time may be on any wrap; the right one is the closest.
    err = min(errs, key=abs)
    drift_true = ((1.0 + b) / (1.0 + a) - 1.0) * 1e6
    return err, mapping.drift_ppm - drift_true


def evaluate_calibration(cal: Calibration, truth_dir: str | Path) -> Evaluation:
    """Score a calibration against a simulated session's truth.

    Per device found in both (matched by serial): rotation error (deg) and camera-centre error
    (mm) of ``T_world_cam``; for each clock mapping, the error of the mapped Vicon time at the
    session midpoint (ms) and of the drift (ppm). Truth clocks: ``device_ns = offset_ns +
    t·(1 + drift_ppm·1e-6)``, Vicon likewise; a D415's device time is its u32 µs hardware clock,
    so the wrap closest to the mapping is used. A DAVIS's recorded time restarts at its
    timestamp reset: it is scored against ``truth/davis_clock.json`` (written by ``mocaprig
    simulate`` with a recording: ``(t − reset_session_ns)·(1 + drift_ppm·1e-6)``); without that
    file its clock error is NaN (the free-running clock of ``scenario.json`` is not what the
    recording holds).

    Raises:
        CalibrationError: the truth folder is unreadable.
    """
    root = Path(truth_dir)
    sc = _read_scenario(root)
    rig = sc.get("rig", {})
    clocks = {c["name"]: c for c in sc.get("clocks", [])}
    t_mid = int(sc.get("duration_ns", 0)) // 2
    davis_base = _read_davis_clock(root)
    entries: list[tuple[str, str, str, Any]] = []  # (label, truth name, kind, T_world_cam)
    for d in rig.get("d415", []):
        entries.append((f"d415/{d['serial']}", d["name"], "d415", d["ir_left"]["T_world_cam"]))
    dv = rig.get("davis")
    if dv:
        entries.append(
            (f"davis/{dv['serial']}", dv.get("name", "davis"), "davis", dv["camera"]["T_world_cam"])
        )
    out: list[DeviceEvaluation] = []
    missing: list[str] = []
    cam_names = {c.name for c in cal.cameras}
    clock_names = {c.device for c in cal.clocks}
    for label, name, kind, T_true in entries:
        if label not in cam_names and label not in clock_names:
            missing.append(label)
            continue
        rot = tr = off = drift = math.nan
        if label in cam_names:
            T = cal.camera(label).T_world_cam
            Tt = np.asarray(T_true, dtype=np.float64)
            rot = rotation_error_deg(T, Tt)
            tr = 1e3 * float(np.linalg.norm(T[:3, 3] - Tt[:3, 3]))
        dev_clock: Mapping[str, Any] | None = clocks.get(name)
        if kind == "davis":
            dev_clock = None
            if davis_base is not None and davis_base.get("device") in (None, label):
                a = float(davis_base["drift_ppm"]) * 1e-6
                reset = int(davis_base["reset_session_ns"])
                dev_clock = {"offset_ns": -round(reset * (1.0 + a)), "drift_ppm": a * 1e6}
        if label in clock_names and dev_clock is not None and "vicon" in clocks:
            err_ns, drift = _true_clock_error_ns(
                cal.clock(label), dev_clock, clocks["vicon"], t_mid, wraps=kind == "d415"
            )
            off = err_ns / 1e6
        out.append(DeviceEvaluation(label, name, rot, tr, off, drift))
    by_label = {d.device: d for d in out}
    for i, d in enumerate(out):
        if d.device not in clock_names:
            continue
        method = cal.clock(d.device).method
        via = by_label.get(method.split(" via ", 1)[1]) if " via " in method else None
        if via is not None:
            rel = 1e3 * (d.clock_offset_error_ms - via.clock_offset_error_ms)
            out[i] = dataclasses.replace(d, clock_error_vs_via_us=rel)
    return Evaluation(truth_dir=str(root), devices=tuple(out), missing=tuple(missing))
