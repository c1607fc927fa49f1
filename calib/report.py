"""Figures of a Vicon calibration (``mocaprig calibrate vicon --report DIR``).

Per camera: a histogram of the bundle adjustment's reprojection errors (inliers and rejected),
the image with the observed blobs and the Vicon markers projected with the coarse pose (before)
and the final pose (after), and the clock alignment (each stretch's reprojection offset minus the
fitted clock line, with its 1σ). For the rig: every clock fit beside its measurements and
residuals (``clocks.png``), the cameras' frusta in 3D beside the Vicon markers' volume
(``rig_3d.png``, :mod:`calib.report_rig`). For the Vicon trial: the clapper-marker distance
around each clap with the contact instant. Written with matplotlib's Agg backend as PNG, with
``summary.json`` and ``index.html`` (the figures beside the JSON, :mod:`calib.report_html`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mocaprig.acquire.device_id import DeviceId
from mocaprig.calib.registration import project_points
from mocaprig.calib.report_html import write_index
from mocaprig.calib.report_rig import write_rig_figure
from mocaprig.calib.vicon_calibration import ViconCalibrationResult
from mocaprig.errors import CalibrationError

if TYPE_CHECKING:
    from mocaprig.calib.vicon_records import MarkerTrajectories

__all__ = ["CalibrationReport", "write_report"]

_log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class CalibrationReport:
    """The files of a calibration report.

    Attributes:
        index: ``index.html``: the figures beside the summary.
        summary: ``summary.json``: the calibration's figures.
        figures: The PNGs, in page order.
    """

    index: Path
    summary: Path
    figures: tuple[Path, ...]


def _safe(name: str) -> str:
    return name.replace("/", "_")


def write_report(
    result: ViconCalibrationResult,
    out_dir: str | Path,
    *,
    overwrite: bool = False,
    trajectories: MarkerTrajectories | None = None,
    summary: Mapping[str, Any] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> CalibrationReport:
    """Write the figures, ``summary.json`` and ``index.html`` into ``out_dir`` (created).

    Args:
        result: The calibration and its diagnostics.
        out_dir: The report folder.
        overwrite: Write into a folder that holds files.
        trajectories: The Vicon trial (its markers' extent is the volume drawn beside the rig);
            None: ``result.trajectories``, and when that is None too, the static start's only.
        summary: The JSON shown beside the figures (default: ``result.summary()``).
        progress: ``(figures_done, figures_total)`` callback.

    Raises:
        CalibrationError: ``out_dir`` holds files and ``overwrite`` is False.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    if out.exists() and any(out.iterdir()) and not overwrite:
        msg = f"report folder {out} is not empty; pass --overwrite to write into it"
        raise CalibrationError(msg)
    out.mkdir(parents=True, exist_ok=True)
    if trajectories is None:
        trajectories = result.trajectories
    clocks = {k.device: k for k in result.calibration.clocks}
    fits = {n: f for n, f in result.clock_fits.items() if n in clocks and len(f[0])}
    total = 2 * len(result.registrations) + len(fits) + bool(result.vicon_claps) + 4
    figures: list[tuple[Path, str]] = []

    def done(path: Path, caption: str) -> None:
        figures.append((path, caption))
        if progress is not None:
            progress(len(figures), total)

    cams = {c.name: c for c in result.calibration.cameras}
    p = write_rig_figure(
        result.calibration.cameras,
        out / "rig_3d.png",
        static_markers_m=result.vicon.cloud_m,
        trial_markers_m=None if trajectories is None else trajectories.positions_m,
        title="the calibrated rig in the Vicon frame",
    )
    done(p, "the rig in 3D: camera frusta beside the Vicon markers and the volume they span")
    p = _write_clocks(result, out / "clocks.png")
    done(p, "clock fits: each camera's reprojection offsets against its clock line, residuals")
    for name, reg in result.registrations.items():
        cam = cams[name]
        b = reg.bundle
        fig, ax = plt.subplots(figsize=(6, 4))
        hi = max(1.0, float(np.percentile(b.residuals_px, 99)))
        bins = np.linspace(0.0, hi, 40).tolist()
        ax.hist(b.residuals_px[b.inliers], bins=bins, label=f"inliers ({b.n_inliers})")
        ax.hist(
            np.clip(b.residuals_px[~b.inliers], 0, hi),
            bins=bins,
            label=f"rejected ({int((~b.inliers).sum())})",
            alpha=0.7,
        )
        ax.set_xlabel("reprojection error (px)")
        ax.set_ylabel("observations")
        ax.set_title(f"{name}: RMS {b.reprojection_rms_px:.3f} px")
        ax.legend()
        p = out / f"residuals_{_safe(name)}.png"
        fig.tight_layout()
        fig.savefig(p, dpi=100)
        plt.close(fig)
        done(p, f"{name}: reprojection errors of the bundle adjustment")

        fig, axes = plt.subplots(1, 2, figsize=(12, 4), sharex=True, sharey=True)
        ref = result.vicon.cloud_m
        for ax, T, title in (
            (axes[0], reg.T_world_cam_coarse, "before: coarse alignment"),
            (axes[1], reg.T_world_cam, "after: bundle adjustment"),
        ):
            uv, z = project_points(ref, T, cam.K, cam.distortion)
            ok = np.isfinite(uv).all(axis=1) & (z > 0)
            ax.scatter(reg.obs_uv_px[:, 0], reg.obs_uv_px[:, 1], s=12, c="k", label="blobs")
            ax.scatter(uv[ok, 0], uv[ok, 1], s=30, facecolors="none", edgecolors="r", label="Vicon")
            ax.set_xlim(0, cam.width)
            ax.set_ylim(cam.height, 0)
            ax.set_aspect("equal")
            ax.set_title(f"{name} {title}")
        axes[0].legend(loc="lower right")
        p = out / f"overlay_{_safe(name)}.png"
        fig.tight_layout()
        fig.savefig(p, dpi=100)
        plt.close(fig)
        done(p, f"{name}: Vicon markers projected before and after the bundle adjustment")

    for name, (t_dev, delta, sigma) in fits.items():
        k = clocks[name]
        line = (k.to_reference_ns(t_dev.astype(np.int64)) - t_dev).astype(np.float64)
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.errorbar((t_dev - t_dev[0]) * 1e-9, (delta - line) * 1e-6, yerr=sigma * 1e-6, fmt="o")
        ax.axhline(0.0, color="k", lw=0.8)
        ax.set_xlabel("device time since the first stretch (s)")
        ax.set_ylabel("offset − clock line (ms)")
        ax.set_title(f"{name}: drift {k.drift_ppm:.1f} ppm, σ {k.offset_sigma_ns * 1e-6:.3f} ms")
        p = out / f"clock_{_safe(name)}.png"
        fig.tight_layout()
        fig.savefig(p, dpi=100)
        plt.close(fig)
        done(p, f"{name}: clock residuals (stretch offsets minus the clock line, 1σ)")
    if result.vicon_claps:
        fig, axes = plt.subplots(
            1, len(result.vicon_claps), figsize=(5 * len(result.vicon_claps), 3.5)
        )
        for ax, clap in zip(np.atleast_1d(axes), result.vicon_claps, strict=True):
            ax.plot((clap.curve_t_ns - clap.t_ns) * 1e-6, clap.curve * 1e3, ".-")
            ax.axvline(0.0, color="r", lw=0.8)
            ax.set_xlabel("Vicon time − contact (ms)")
            ax.set_ylabel("clapper marker distance (mm)")
            ax.set_title(f"Vicon clap at {clap.t_ns * 1e-9:.3f} s ± {clap.sigma_ns * 1e-6:.2f} ms")
        p = out / "vicon_claps.png"
        fig.tight_layout()
        fig.savefig(p, dpi=100)
        plt.close(fig)
        done(p, "Vicon claps: clapper-marker distance around each contact")

    fig, ax = plt.subplots(figsize=(6, 4))
    names = list(result.registrations)
    rms = [result.registrations[n].bundle.reprojection_rms_px for n in names]
    ax.bar(range(len(names)), rms)
    ax.set_xticks(range(len(names)), [DeviceId.parse(n).serial or n for n in names], rotation=20)
    ax.set_ylabel("reprojection RMS (px)")
    ax.set_title("per-camera reprojection")
    p = out / "reprojection_per_camera.png"
    fig.tight_layout()
    fig.savefig(p, dpi=100)
    plt.close(fig)
    done(p, "reprojection RMS per camera")
    summary_path, index = write_index(
        out,
        title="Vicon calibration report",
        figures=figures,
        summary=result.summary() if summary is None else summary,
        notes=result.notes,
    )
    if progress is not None:
        progress(total, total)
    _log.info("wrote %d figures and %s into %s", len(figures), index.name, out)
    return CalibrationReport(
        index=index, summary=summary_path, figures=tuple(p for p, _ in figures)
    )


def _write_clocks(result: ViconCalibrationResult, path: Path) -> Path:
    """Every clock mapping beside the measurements it was fitted to, and their residuals.

    Top: per camera, each reprojection stretch's offset (reference − device) and the clock line,
    both minus the line's value at the first stretch (so the slope is the drift; ms). Bottom:
    the residuals with their 1σ. Clocks without stretches (the DAVIS, from pulses) are listed
    with their method, drift and σ.
    """
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 7), layout="constrained")
    top, bottom = fig.subplots(2, 1, sharex=True)
    listed: list[str] = []
    for k in result.calibration.clocks:
        fit = result.clock_fits.get(k.device)
        label = DeviceId.parse(k.device).serial or k.device
        if fit is None or len(fit[0]) == 0:
            sigma_us = k.offset_sigma_ns * 1e-3
            method = k.method or "clock"
            listed.append(
                f"{k.device}: {method}, drift {k.drift_ppm:+.2f} ppm, σ {sigma_us:.1f} µs"
            )
            continue
        t_dev, delta, sigma = (np.asarray(a, dtype=np.float64) for a in fit)
        t0 = t_dev[0]
        line = (k.to_reference_ns(t_dev.astype(np.int64)) - t_dev).astype(np.float64)
        base = line[0]
        t_s = (t_dev - t0) * 1e-9
        span = np.linspace(t_dev[0], t_dev[-1], 50)
        line_span = (k.to_reference_ns(span.astype(np.int64)) - span).astype(np.float64)
        (drawn,) = top.plot((span - t0) * 1e-9, (line_span - base) * 1e-6, lw=1.2)
        top.errorbar(
            t_s, (delta - base) * 1e-6, yerr=sigma * 1e-6, fmt="o", ms=4,
            color=drawn.get_color(),
            label=f"{label}: {k.method or 'clock'}, {k.drift_ppm:+.2f} ppm",
        )  # fmt: skip
        bottom.errorbar(
            t_s, (delta - line) * 1e-6, yerr=sigma * 1e-6, fmt="o", ms=4,
            color=drawn.get_color(), label=label,
        )  # fmt: skip
    top.set_ylabel("offset − offset at first stretch (ms)")
    top.set_title("clock fits (lines) and the reprojection stretches they rest on (points)")
    bottom.axhline(0.0, color="k", lw=0.8)
    bottom.set_xlabel("device time since the camera's first stretch (s)")
    bottom.set_ylabel("residual (ms)")
    bottom.set_title("residuals: stretch offset − clock line (1σ bars)")
    for ax in (top, bottom):
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    if listed:
        fig.suptitle("\n".join(listed), fontsize=8)
    fig.savefig(path, dpi=100)
    return path
