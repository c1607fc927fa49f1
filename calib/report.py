"""Figures of a Vicon calibration (``mocaprig calibrate vicon --report DIR``).

Per camera: a histogram of the bundle adjustment's reprojection errors (inliers and rejected),
the image with the observed blobs and the Vicon markers projected with the coarse pose (before)
and the final pose (after), and the clock alignment (each stretch's reprojection offset minus the
fitted clock line, with its 1σ). For the Vicon trial: the clapper-marker distance around each
clap with the contact instant. Written with matplotlib's Agg backend as PNG.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from mocaprig.acquire.device_id import DeviceId
from mocaprig.calib.registration import project_points
from mocaprig.calib.vicon_calibration import ViconCalibrationResult
from mocaprig.errors import CalibrationError

__all__ = ["write_report"]

_log = logging.getLogger(__name__)


def _safe(name: str) -> str:
    return name.replace("/", "_")


def write_report(
    result: ViconCalibrationResult, out_dir: str | Path, *, overwrite: bool = False
) -> list[Path]:
    """Write the figures into ``out_dir`` (created); returns their paths.

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
    paths: list[Path] = []
    cams = {c.name: c for c in result.calibration.cameras}
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
        paths.append(p)

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
        paths.append(p)

    clocks = {k.device: k for k in result.calibration.clocks}
    for name, (t_dev, delta, sigma) in result.clock_fits.items():
        if name not in clocks or len(t_dev) == 0:
            continue
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
        paths.append(p)
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
        paths.append(p)

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
    paths.append(p)
    _log.info("wrote %d figures into %s", len(paths), out)
    return paths
