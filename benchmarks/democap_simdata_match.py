"""Does DeMoCap's simulated training data look like what the real measurement pipeline gives?

Compares, on simulated recordings with truth (``mocaprig simulate``: the mock D415 renders IR and
depth images; :mod:`mocaprig.calib.markers` finds the blobs, reads their depth and lifts them), the
per-camera and fused marker statistics with those of the marker-level observation model that
trains DeMoCap (:mod:`process.democap.simdata`), on the *same* poses and the *same* cameras:

* the recording: every ``--every``-th rig instant of each session; each camera's frame is
  measured (:func:`calib.markers.measure_recording`); the truth is the world at that camera's
  mid-exposure (``truth/d415_captures.npz`` gives each frame's exposure in session time; the
  scenario is rebuilt from ``truth/scenario.json`` for the skin normals and the body capsules);
  cameras are the *true* poses and intrinsics (no calibration error enters);
* simdata: :func:`~mocaprig.process.democap.simdata.observe` on the scenario's body, marker set and
  poses at the same instants, seen by the same cameras (``--sim-repeats`` draws per instant).

Both go through the same analysis: per view, blobs are matched to the projected true markers
(Hungarian, gate ``--gate-px``). Per marker and view: the angle between the skin normal and the
line of sight; the *normalised gap*, the clearance of the segment camera → marker centre from
the nearest body capsule surface (its own limb included) as an angle at the closest approach,
in units of the marker's angular radius (≥ 1: the sphere wholly in view, 0: half, ≤ −1: none;
"clear" = ≥ 0); the distance in the image to the nearest projected marker that is not farther
(blob merging); detection, the depth error (lifted camera Z minus the true centre's) and the
blob centre error. Blobs matched to no body marker are strays, on the suit (within 30 mm of a
capsule surface) or off the body (in the recordings: the clapperboard's two markers). Fusion is
the replay's: camera → world, capture-box crop, 10 mm single-linkage merge over all views (as
:func:`mocaprig.calib.markers.merge_views`); per instant the points, the markers with a point, the
markers whose detections stay in two or more points, the points with no body marker in them,
and each point's distance to the nearest true marker.

Also reported: the cloud size and per-view detection of the training distribution itself
(:func:`mocaprig.process.democap.dataset.make_sample`: random bodies, placements and rigs), and with
``--network`` the committed checkpoint's MPJPE on the measured clouds and on simdata's clouds
of the same instants (does the network meet the same difficulty?).

Prints a table and, as its last line, one JSON object (``measured``, ``simdata``, per-statistic
``comparison`` with ``tolerance`` and ``within``, ``training_distribution``, ``network``).

Run (≈ 2 min wall in all on the shared 2-core machine, 70 s of it measuring the 2,396 frames
of 599 instants, which ``--cache`` keeps for the next run)::

    nice -n 10 .venv/bin/python benchmarks/democap_simdata_match.py \
        --sessions /tmp/sim30_s3 /tmp/sim30_s7 --cache /tmp/simmatch --network

The sessions measured for docs/democap.md: ``mocaprig simulate``, 30 s, seeds 3 and 7, default
scenario, 4 D415s, D415 streams only (any simulated session with ``truth/`` will do).
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from mocaprig.process.body import Motion, democap_joints, forward_kinematics
from mocaprig.process.body.surface import capsules
from mocaprig.process.democap import simdata

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

W, H = 848, 480
MERGE_RADIUS_M = 0.010
#: Angle bins (deg) of the detection-rate table.
ANGLE_EDGES = (0.0, 30.0, 60.0, 75.0, 90.0, 105.0, 120.0, 180.0)
#: Camera-Z bins (m) of the depth-error table.
Z_EDGES = (1.5, 2.2, 2.6, 3.0, 4.0)
#: Normalised-gap bins (occlusion) of the detection and depth-error tables.
GAP_EDGES = (-1e9, -1.0, -0.5, 0.0, 0.5, 0.9, 1e9)


# ----------------------------------------------------------------------------- geometry


def _seg_dist(p0: F64, p1: F64, q0: F64, q1: F64) -> tuple[F64, F64]:
    """Distance between segments [p0, p1] and [q0, q1] (broadcast) and the parameter s on p."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a = np.sum(d1 * d1, -1)
    e = np.sum(d2 * d2, -1)
    f = np.sum(d2 * r, -1)
    c = np.sum(d1 * r, -1)
    b = np.sum(d1 * d2, -1)
    den = a * e - b * b
    s = np.where(den > 1e-12, np.clip((b * f - c * e) / np.where(den > 1e-12, den, 1.0), 0, 1), 0)
    t = (b * s + f) / np.where(e > 1e-12, e, 1.0)
    lo, hi = t < 0, t > 1
    t = np.clip(t, 0.0, 1.0)
    a = np.where(a > 1e-12, a, 1.0)
    s = np.where(lo, np.clip(-c / a, 0, 1), np.where(hi, np.clip((b - c) / a, 0, 1), s))
    diff = (p0 + s[..., None] * d1) - (q0 + t[..., None] * d2)
    return np.asarray(np.linalg.norm(diff, axis=-1)), np.asarray(s)


@dataclass(frozen=True)
class View:
    """One camera: intrinsics ``k`` (3, 3) and world -> camera ``r_cw`` (3, 3), centre (3,)."""

    k: F64
    r_cw: F64
    centre: F64

    def to_cam(self, p: F64) -> F64:
        return np.asarray((p - self.centre) @ self.r_cw.T)

    def project(self, p: F64) -> tuple[F64, F64]:
        c = self.to_cam(p)
        z = c[..., 2]
        zs = np.where(z > 1e-6, z, np.nan)
        uv = np.stack(
            [
                self.k[0, 0] * c[..., 0] / zs + self.k[0, 2],
                self.k[1, 1] * c[..., 1] / zs + self.k[1, 2],
            ],
            -1,
        )
        return uv, z


@dataclass(frozen=True)
class World:
    """The truth of one camera's frame: body markers, normals, capsules, clapperboard."""

    markers: F64  # (53, 3)
    normals: F64  # (53, 3)
    caps_a: F64  # (C, 3)
    caps_b: F64
    caps_r: F64  # (C,)
    clapper: F64  # (K, 3), K = 0 for simdata
    joints: F64  # (19, 3) DeMoCap joints


def marker_features(world: World, view: View, radius_m: float) -> dict[str, F64]:
    """Per body marker: camera Z, normal angle (deg), uv and the normalised gap.

    The normalised gap is the clearance of the segment camera -> marker centre from the
    nearest body capsule surface (its own limb included), as an angle at the closest approach,
    in units of the marker's angular radius: >= 1 the sphere is wholly in view, 0 half of it
    (a straight occluding edge through its centre), <= -1 none of it.
    """
    m = world.markers
    v = view.centre - m
    dist = np.linalg.norm(v, axis=-1)
    ang = np.degrees(np.arccos(np.clip(np.sum(v * world.normals, -1) / dist, -1.0, 1.0)))
    uv, z = view.project(m)
    start = np.broadcast_to(view.centre, m.shape)
    d, s = _seg_dist(start[:, None, :], m[:, None, :], world.caps_a[None], world.caps_b[None])
    z_seg = np.maximum(s * z[:, None], 0.05)
    gap = ((d - world.caps_r[None]) * z[:, None] / (z_seg * radius_m)).min(axis=1)
    return {"z": z, "angle": ang, "u": uv[:, 0], "v": uv[:, 1], "gap": gap}


def match(uv_blob: F64, uv_true: F64, gate_px: float) -> I64:
    """Index of the true point matched to each blob (-1: none), Hungarian within ``gate_px``."""
    out = np.full(uv_blob.shape[0], -1, np.int64)
    if uv_blob.shape[0] == 0:
        return out
    ok = np.all(np.isfinite(uv_true), axis=1)
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return out
    cost = np.linalg.norm(uv_blob[:, None] - uv_true[None, idx], axis=-1)
    big = 1e6
    c = np.where(cost <= gate_px, cost, big)
    r, col = linear_sum_assignment(c)
    good = c[r, col] < big
    out[r[good]] = idx[col[good]]
    return out


def merge_labels(points: F64, radius_m: float) -> I64:
    """Single-linkage cluster label of each point (as :func:`calib.markers.merge_views`)."""
    n = points.shape[0]
    if n == 0:
        return np.zeros(0, np.int64)
    pairs = cKDTree(points).query_pairs(radius_m, output_type="ndarray")
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return np.asarray(connected_components(g, directed=False)[1], np.int64)


# ----------------------------------------------------------------------------- records


@dataclass
class Records:
    """Flat per-(marker, view), per-blob and per-instant records of one source."""

    mv: dict[str, list[F64]]
    blob: dict[str, list[F64]]
    view: dict[str, list[float]]
    inst: dict[str, list[float]]
    fused_dist: list[F64]
    clouds: list[F64]
    joints: list[F64]

    @classmethod
    def empty(cls) -> Records:
        return cls({}, {}, {}, {}, [], [], [])

    def add(self, table: dict[str, list[Any]], row: dict[str, Any]) -> None:
        for key, val in row.items():
            table.setdefault(key, []).append(val)

    def arrays(self) -> dict[str, dict[str, F64]]:
        def cat(t: dict[str, list[Any]]) -> dict[str, F64]:
            return {
                k: np.concatenate([np.atleast_1d(np.asarray(x, np.float64)) for x in v])
                for k, v in t.items()
            }

        fd = np.concatenate(self.fused_dist) if self.fused_dist else np.zeros(0)
        return {
            "mv": cat(self.mv),
            "blob": cat(self.blob),
            "view": cat(self.view),
            "inst": cat(self.inst),
            "fused": {"dist": fd},
        }


def analyse_instant(
    rec: Records,
    worlds: list[World],
    views: list[View],
    uvs: list[F64],
    xyzs: list[F64],
    *,
    gate_px: float,
    radius_m: float,
) -> None:
    """Match, featurise and fuse one rig instant (views' blobs ``uv`` px, ``xyz`` camera m)."""
    world_pts, labels = [], []
    n_markers = worlds[0].markers.shape[0]
    for cam, (world, view, uv, xyz) in enumerate(zip(worlds, views, uvs, xyzs, strict=True)):
        feat = marker_features(world, view, radius_m)
        uv_all = np.concatenate(
            [np.stack([feat["u"], feat["v"]], 1), view.project(world.clapper)[0]]
        )
        z_all = np.concatenate([feat["z"], view.to_cam(world.clapper)[:, 2]])
        j = match(uv, uv_all, gate_px)
        has_z = np.isfinite(xyz[:, 2])
        det = np.zeros(n_markers, bool)
        zmeas = np.full(n_markers, np.nan)
        du = np.full(n_markers, np.nan)
        dv = np.full(n_markers, np.nan)
        body = (j >= 0) & (j < n_markers)
        det[j[body]] = True
        zmeas[j[body]] = xyz[body, 2]
        du[j[body]] = uv[body, 0] - feat["u"][j[body]]
        dv[j[body]] = uv[body, 1] - feat["v"][j[body]]
        inside = (feat["z"] > 0.3) & (feat["u"] >= 0) & (feat["u"] <= W - 1)
        inside &= (feat["v"] >= 0) & (feat["v"] <= H - 1)
        # Nearest other projected marker (px, the clapperboard's included) that is not more
        # than 5 cm farther from the camera (blob merging).
        dd = np.linalg.norm(uv_all[:n_markers, None] - uv_all[None], axis=-1)
        dd[np.arange(n_markers), np.arange(n_markers)] = np.inf
        dd = np.where(z_all[None] < feat["z"][:, None] + 0.05, dd, np.inf)
        rec.add(
            rec.mv,
            {
                "cam": np.full(n_markers, cam, float),
                "marker": np.arange(n_markers, dtype=float),
                **feat,
                "inside": inside.astype(float),
                "det": det.astype(float),
                "has_z": (det & np.isfinite(zmeas)).astype(float),
                "dz": zmeas - feat["z"],
                "du": du,
                "dv": dv,
                "nn_px": np.nan_to_num(dd.min(axis=1), nan=np.inf, posinf=1e3),
            },
        )
        # Blobs not matched to a body marker: strays, on the suit (within 30 mm of a capsule
        # surface) or off the body (for the recordings: the clapperboard's markers).
        kind = np.where(body, 0.0, 2.0)
        stray = np.flatnonzero(~body & has_z)
        if stray.size:
            p = xyz[stray] @ view.r_cw + view.centre
            ab = world.caps_b - world.caps_a
            t = np.clip(
                np.einsum("pci,ci->pc", p[:, None] - world.caps_a[None], ab)
                / np.maximum(np.einsum("ci,ci->c", ab, ab), 1e-12),
                0.0,
                1.0,
            )
            q = world.caps_a[None] + t[..., None] * ab[None]
            surf = (np.linalg.norm(p[:, None] - q, axis=-1) - world.caps_r[None]).min(axis=1)
            kind[stray] = np.where(np.abs(surf) < 0.03, 2.0, 3.0)
        rec.add(rec.blob, {"kind": kind, "has_z": has_z.astype(float)})
        rec.add(
            rec.view,
            {
                "view_blobs": float(uv.shape[0]),
                "view_clapper": float(np.sum(j >= n_markers)),
                "view_on_suit": float(np.sum(kind == 2)),
                "view_off_body": float(np.sum(kind == 3)),
                "view_det": float(det.sum()),
                "view_inside": float(inside.sum()),
            },
        )
        p = xyz[has_z] @ view.r_cw + view.centre
        world_pts.append(p)
        labels.append(np.where(body, j, np.where(j >= n_markers, n_markers, -1))[has_z])
    pts = np.concatenate(world_pts)
    lab = np.concatenate(labels)
    box = np.asarray(simdata.CAPTURE_BOX_M)
    keep = np.all((pts >= box[:, 0]) & (pts <= box[:, 1]), axis=1)
    pts, lab = pts[keep], lab[keep]
    cl = merge_labels(pts, MERGE_RADIUS_M)
    n_clusters = int(cl.max()) + 1 if cl.size else 0
    clusters_per_marker = np.array(
        [np.unique(cl[lab == m]).size for m in range(n_markers)], dtype=float
    )
    ghost_only = n_clusters - np.unique(cl[(lab >= 0) & (lab < n_markers)]).size
    # Fused points (cluster means) and their distance to the nearest true body marker.
    if n_clusters:
        sums = np.zeros((n_clusters, 3))
        np.add.at(sums, cl, pts)
        fused = sums / np.bincount(cl, minlength=n_clusters)[:, None]
        d = np.linalg.norm(fused[:, None] - worlds[0].markers[None], axis=-1).min(axis=1)
        rec.fused_dist.append(d)
        rec.clouds.append(fused)
        rec.joints.append(worlds[0].joints)
    rec.add(
        rec.inst,
        {
            "points": float(n_clusters),
            "dup_markers": float(np.sum(clusters_per_marker >= 2)),
            "extra_points": float(np.sum(np.maximum(clusters_per_marker - 1, 0))),
            "seen": float(np.sum(clusters_per_marker >= 1)),
            "non_marker_points": float(ghost_only),
        },
    )


# ----------------------------------------------------------------------------- sources


@dataclass(frozen=True)
class Session:
    """The instants of one recording: per instant and camera, the blobs and the truth time."""

    name: str
    views: list[View]
    t_mid_ns: I64  # (I, K) each camera's mid-exposure, session ns
    uv: list[list[F64]]  # [instant][camera] (N, 2) px
    xyz: list[list[F64]]  # [instant][camera] (N, 3) camera frame, m (NaN: no depth)


def _rig(truth_meta: dict[str, Any]) -> list[tuple[str, str, View]]:
    out = []
    for d in truth_meta["rig"]["d415"]:
        k = np.asarray(d["ir_left"]["K"], np.float64)
        t = np.asarray(d["ir_left"]["T_world_cam"], np.float64)
        out.append((d["name"], str(d["serial"]), View(k, t[:3, :3].T.copy(), t[:3, 3].copy())))
    return out


def measure_session(folder: Path, every: int, cache: Path | None) -> Session:
    """Measure every ``every``-th instant of a simulated recording (cached as npz)."""
    from mocaprig.acquire.recording import Recording
    from mocaprig.calib.markers import frame_times, measure_recording
    from mocaprig.drivers_mock.truth import read_truth

    truth = read_truth(folder)
    rig = _rig(dict(truth.meta))
    cache_file = None if cache is None else cache / f"{folder.name}_every{every}.npz"
    if cache_file is not None and cache_file.exists():
        z = np.load(cache_file)
        counts, t_mid = z["counts"], z["t_mid_ns"]
        uv_flat, xyz_flat = z["uv"], z["xyz"]
    else:
        cap = np.load(folder / "truth" / "d415_captures.npz")
        starts, mids = [], []
        for name, serial, _ in rig:
            key = f"{name}__{serial}"
            ok = cap[f"{key}__delivered"].astype(bool)
            s = cap[f"{key}__exposure_start_ns"][ok]
            order = np.argsort(s)
            starts.append(s[order])
            mids.append(s[order] + cap[f"{key}__exposure_ns"][ok][order] // 2)
        with Recording(folder / "session.mcap") as rec:
            t_dev = frame_times(rec)
            labels = [f"d415/{serial}" for _, serial, _ in rig]
            for lab, s in zip(labels, starts, strict=True):
                if t_dev[lab].size != s.size:
                    msg = f"{lab}: {t_dev[lab].size} frames recorded, {s.size} delivered"
                    raise SystemExit(msg)
            picks = []  # (I, K) capture indices
            for i in range(0, starts[0].size, every):
                row = [i]
                for s in starts[1:]:
                    j = int(np.argmin(np.abs(s - starts[0][i])))
                    row.append(j if abs(int(s[j]) - int(starts[0][i])) < 5_000_000 else -1)
                if min(row) >= 0:
                    picks.append(row)
            pk = np.asarray(picks, np.int64)
            wanted = {lab: t_dev[lab][pk[:, c]].tolist() for c, lab in enumerate(labels)}
            measured = measure_recording(rec, frames_t_dev_ns=wanted, progress=True)
        t_mid = np.stack([mids[c][pk[:, c]] for c in range(len(rig))], axis=1)
        uv_l, xyz_l, cnt = [], [], []
        for i in range(pk.shape[0]):
            for lab in labels:
                f = measured[lab][i]
                if f.t_dev_ns != wanted[lab][i]:
                    msg = f"{lab}: frame {i} measured out of order"
                    raise SystemExit(msg)
                uv_l.append(f.uv_px)
                xyz_l.append(f.xyz_cam_m)
                cnt.append(f.n_markers)
        counts = np.asarray(cnt, np.int64).reshape(pk.shape)
        uv_flat, xyz_flat = np.concatenate(uv_l), np.concatenate(xyz_l)
        if cache_file is not None:
            cache.mkdir(parents=True, exist_ok=True)  # type: ignore[union-attr]
            np.savez(cache_file, counts=counts, t_mid_ns=t_mid, uv=uv_flat, xyz=xyz_flat)
    off = np.concatenate([[0], np.cumsum(counts.ravel())])
    uv: list[list[F64]] = []
    xyz: list[list[F64]] = []
    for i in range(counts.shape[0]):
        k = i * counts.shape[1]
        uv.append([uv_flat[off[k + c] : off[k + c + 1]] for c in range(counts.shape[1])])
        xyz.append([xyz_flat[off[k + c] : off[k + c + 1]] for c in range(counts.shape[1])])
    return Session(folder.name, [v for _, _, v in rig], t_mid, uv, xyz)


def _scenario(folder: Path) -> Any:
    from mocaprig.drivers_mock.scenario import build_scenario
    from mocaprig.drivers_mock.truth import read_truth

    truth = read_truth(folder)
    return build_scenario(truth.scenario_name, seed=truth.seed, seconds=truth.seconds)


def _worlds(scenario: Any, t_ns: I64) -> list[World]:
    ws = scenario.sample(t_ns)
    kin = forward_kinematics(ws.pose, scenario.shape)
    caps = capsules(kin, scenario.shape)
    joints = democap_joints(kin)
    return [
        World(
            ws.markers_m[i],
            ws.marker_normals[i],
            caps.a_m[i],
            caps.b_m[i],
            caps.radius_m,
            ws.clapper_m[i],
            joints[i],
        )
        for i in range(t_ns.size)
    ]


def analyse_recording(folder: Path, sess: Session, rec: Records, gate_px: float) -> Any:
    """The recording's records; returns the scenario (for the simdata run)."""
    scenario = _scenario(folder)
    n_inst, n_cam = sess.t_mid_ns.shape
    worlds = _worlds(scenario, sess.t_mid_ns.ravel())
    radius = float(scenario.markers.marker_radius_m)
    for i in range(n_inst):
        analyse_instant(
            rec,
            worlds[i * n_cam : (i + 1) * n_cam],
            sess.views,
            sess.uv[i],
            sess.xyz[i],
            gate_px=gate_px,
            radius_m=radius,
        )
    return scenario


def analyse_simdata(
    scenario: Any, sess: Session, rec: Records, gate_px: float, repeats: int, seed: int
) -> float:
    """simdata's records on the same poses and cameras; returns ms per observation."""
    t_ref = sess.t_mid_ns[:, 0]
    pose = scenario.sample(t_ref).pose
    frames = simdata.pose_frames(Motion("recording", 30.0, pose), scenario.shape, scenario.markers)
    cams = [simdata.Camera(v.centre, v.r_cw, float(v.k[0, 0])) for v in sess.views]
    k_sim = [
        np.array(
            [[c.focal_px, 0, simdata.IMAGE_W / 2], [0, c.focal_px, simdata.IMAGE_H / 2], [0, 0, 1]]
        )
        for c in cams
    ]
    views = [View(k, c.r_cw, c.centre_m) for k, c in zip(k_sim, cams, strict=True)]
    radius = float(scenario.markers.marker_radius_m)
    rng = np.random.default_rng(seed)
    spent = 0.0
    n = 0
    for i in range(frames.num_frames):
        world = World(
            frames.markers_m[i],
            frames.normals[i],
            frames.caps_a_m[i],
            frames.caps_b_m[i],
            frames.caps_radius_m,
            np.zeros((0, 3)),
            frames.joints_m[i],
        )
        for _ in range(repeats):
            t0 = time.perf_counter()
            pts, _ = simdata.observe(frames, i, cams, rng)
            spent += time.perf_counter() - t0
            n += 1
            uvs, xyzs = [], []
            for v, p in zip(views, pts, strict=True):
                uv, _ = v.project(p)
                uvs.append(uv)
                xyzs.append(v.to_cam(p))
            analyse_instant(
                rec, [world] * len(cams), views, uvs, xyzs, gate_px=gate_px, radius_m=radius
            )
    return 1e3 * spent / max(n, 1)


# ----------------------------------------------------------------------------- statistics


def _mad(x: F64) -> float:
    return float(np.median(np.abs(x - np.median(x)))) if x.size else float("nan")


def _rate(x: npt.NDArray[Any]) -> float:
    return float(np.mean(x)) if x.size else float("nan")


def statistics(tabs: dict[str, dict[str, F64]]) -> dict[str, float]:
    """The compared statistics of one source (rates in [0, 1], depths in mm, lateral in px)."""
    mv, blob, view, inst = tabs["mv"], tabs["blob"], tabs["view"], tabs["inst"]
    out: dict[str, float] = {}
    det = mv["det"] > 0
    inside = mv["inside"] > 0
    out["det_per_view"] = _rate(det)
    out["det_of_in_image"] = _rate(det[inside])
    for lo, hi in itertools.pairwise(ANGLE_EDGES):
        sel = inside & (mv["angle"] >= lo) & (mv["angle"] < hi) & (mv["gap"] >= 0.0)
        out[f"det_angle_{lo:.0f}_{hi:.0f}_clear"] = _rate(det[sel])
    for lo, hi in itertools.pairwise(GAP_EDGES):
        sel = inside & (mv["gap"] >= lo) & (mv["gap"] < hi) & (mv["nn_px"] >= 10)
        out[f"det_gap_{lo:g}_{hi:g}"] = _rate(det[sel])
    sel = inside & (mv["gap"] >= 0.0) & (mv["nn_px"] < 5.0)
    out["det_neighbour_within_5px"] = _rate(det[sel])
    has = mv["has_z"] > 0
    dz = mv["dz"][has] * 1e3
    out["dz_median_mm"] = float(np.median(dz))
    out["dz_mad_mm"] = _mad(dz)
    for q in (1, 5, 10, 25, 75, 90, 95, 99):
        out[f"dz_p{q}_mm"] = float(np.percentile(dz, q))
    out["dz_below_-50mm"] = _rate(dz < -50)
    out["dz_above_+30mm"] = _rate(dz > 30)
    # Against distance: bias and spread of fully visible markers (the D415's noise), and the
    # share of the occlusion tail (the error distribution is bimodal: its median is not a
    # stable figure).
    for lo, hi in itertools.pairwise(Z_EDGES):
        sel = has & (mv["z"] >= lo) & (mv["z"] < hi)
        d = mv["dz"][sel & (mv["gap"] >= 0.9)] * 1e3
        out[f"dz_median_clear_z_{lo:g}_{hi:g}_mm"] = float(np.median(d)) if d.size else np.nan
        out[f"dz_mad_clear_z_{lo:g}_{hi:g}_mm"] = _mad(d)
        out[f"dz_below_-30mm_z_{lo:g}_{hi:g}"] = _rate(mv["dz"][sel] < -0.03)
    for lo, hi in itertools.pairwise(ANGLE_EDGES):
        sel = has & (mv["angle"] >= lo) & (mv["angle"] < hi)
        d = mv["dz"][sel] * 1e3
        out[f"dz_median_angle_{lo:.0f}_{hi:.0f}_mm"] = float(np.median(d)) if d.size else np.nan
    for name, sel in (
        ("clear", has & (mv["gap"] >= 0.9)),
        ("partly_hidden", has & (mv["gap"] < 0.5)),
    ):
        d = mv["dz"][sel] * 1e3
        out[f"dz_median_{name}_mm"] = float(np.median(d))
        out[f"dz_p10_{name}_mm"] = float(np.percentile(d, 10))
        out[f"dz_p90_{name}_mm"] = float(np.percentile(d, 90))
    lat = np.hypot(mv["du"], mv["dv"])[det]
    for q in (50, 90, 99):
        out[f"lateral_p{q}_px"] = float(np.percentile(lat, q))
    out["blobs_per_view"] = float(np.mean(view["view_blobs"]))
    out["stray_on_suit_per_view"] = float(np.mean(view["view_on_suit"]))
    out["stray_off_body_per_view"] = float(np.mean(view["view_off_body"]))
    out["clapperboard_blobs_per_view"] = float(np.mean(view["view_clapper"]))
    out["stray_with_depth"] = _rate(blob["has_z"][blob["kind"] >= 2])
    out["points_per_cloud"] = float(np.mean(inst["points"]))
    out["points_per_cloud_sd"] = float(np.std(inst["points"]))
    out["markers_seen"] = float(np.mean(inst["seen"]))
    out["markers_with_unmerged_duplicates"] = float(np.mean(inst["dup_markers"]))
    out["duplicate_points"] = float(np.mean(inst["extra_points"]))
    out["non_marker_points"] = float(np.mean(inst["non_marker_points"]))
    fd = tabs["fused"]["dist"] * 1e3
    out["fused_dist_median_mm"] = float(np.median(fd))
    out["fused_within_30mm"] = _rate(fd < 30)
    return out


#: Tolerances of the comparison: (statistic, kind, value); kind "abs" = |sim - meas| <= value,
#: "rel" = |sim - meas| <= value·|meas|.
TOLERANCES: tuple[tuple[str, str, float], ...] = (
    ("det_per_view", "abs", 0.03),
    ("det_angle_0_30_clear", "abs", 0.04),
    ("det_angle_30_60_clear", "abs", 0.04),
    ("det_angle_60_75_clear", "abs", 0.04),
    ("det_angle_75_90_clear", "abs", 0.06),
    ("det_angle_90_105_clear", "abs", 0.06),
    ("det_angle_105_120_clear", "abs", 0.06),
    ("det_gap_-1_-0.5", "abs", 0.1),
    ("det_gap_-0.5_0", "abs", 0.08),
    ("det_neighbour_within_5px", "abs", 0.1),
    ("dz_median_mm", "abs", 3.0),
    ("dz_mad_mm", "abs", 3.0),
    ("dz_p5_mm", "abs", 15.0),
    ("dz_p10_mm", "abs", 10.0),
    ("dz_p25_mm", "abs", 5.0),
    ("dz_p75_mm", "abs", 3.0),
    ("dz_p95_mm", "abs", 4.0),
    ("dz_below_-50mm", "abs", 0.03),
    ("dz_median_clear_z_2.2_2.6_mm", "abs", 3.0),
    ("dz_median_clear_z_2.6_3_mm", "abs", 3.0),
    ("dz_mad_clear_z_2.2_2.6_mm", "abs", 2.0),
    ("dz_mad_clear_z_2.6_3_mm", "abs", 2.0),
    ("dz_below_-30mm_z_2.2_2.6", "abs", 0.04),
    ("dz_below_-30mm_z_2.6_3", "abs", 0.04),
    ("dz_median_clear_mm", "abs", 3.0),
    ("dz_median_partly_hidden_mm", "abs", 10.0),
    ("dz_p10_partly_hidden_mm", "abs", 20.0),
    ("lateral_p50_px", "abs", 0.1),
    ("lateral_p90_px", "abs", 0.3),
    ("stray_on_suit_per_view", "rel", 0.15),
    ("stray_off_body_per_view", "rel", 0.2),
    ("points_per_cloud", "rel", 0.05),
    ("markers_seen", "abs", 1.5),
    ("markers_with_unmerged_duplicates", "rel", 0.1),
    ("non_marker_points", "rel", 0.15),
    ("fused_dist_median_mm", "abs", 2.0),
    ("fused_within_30mm", "abs", 0.04),
)


def compare(meas: dict[str, float], sim: dict[str, float]) -> dict[str, dict[str, Any]]:
    """Per toleranced statistic: measured, simdata, tolerance and whether it is met."""
    out = {}
    for key, kind, tol in TOLERANCES:
        m, s = meas[key], sim[key]
        lim = tol if kind == "abs" else tol * abs(m)
        out[key] = {
            "measured": round(m, 4),
            "simdata": round(s, 4),
            "tolerance": f"±{tol:g}" if kind == "abs" else f"±{100 * tol:g} %",
            "within": bool(abs(s - m) <= lim),
        }
    return out


def training_clouds(samples: int, seed: int) -> dict[str, float]:
    """Cloud size and per-camera detection of the training distribution (dataset.py)."""
    from mocaprig.process.democap.dataset import make_pool, make_sample

    pool = make_pool(seed, "train", takes=12, seconds=2.0)
    rng = np.random.default_rng(seed)
    pts, det = [], []
    for i in range(samples):
        take = pool[i % len(pool)]
        smp = make_sample(take, int(rng.integers(take.num_frames)), rng, augment=False)
        pts.append(smp.raw_m.shape[0])
        cams = simdata.sample_rig(rng)
        _, d = simdata.observe(take, int(rng.integers(take.num_frames)), cams, rng)
        det.append(d.mean())
    return {
        "points_per_cloud": float(np.mean(pts)),
        "points_per_cloud_sd": float(np.std(pts)),
        "det_per_view": float(np.mean(det)),
    }


def network_errors(measured: Records, simulated: Records, sim_repeats: int) -> dict[str, Any]:
    """MPJPE (17 joints, mm) of the committed checkpoint on the measured fused clouds and on
    simdata's clouds of the same instants: does the network meet the same difficulty?"""
    import torch

    from mocaprig.process.democap.evaluate import EVAL_JOINTS
    from mocaprig.process.democap.infer import DemocapPredictor

    torch.set_num_threads(1)
    pred = DemocapPredictor(solve=False)  # the network on these clouds, as it was measured
    out: dict[str, Any] = {
        "checkpoint": f"{pred.checkpoint.config.name} ({pred.checkpoint.epoch} epochs)"
    }
    for name, rec in (("measured", measured), ("simdata", simulated)):
        err = []
        for k in range(0, len(rec.clouds), 16):
            batch = [c if c.shape[0] >= 2 else np.zeros((2, 3)) for c in rec.clouds[k : k + 16]]
            for p, j in zip(pred.predict_many(batch), rec.joints[k : k + 16], strict=True):
                err.append(
                    np.linalg.norm(p.joints_m[list(EVAL_JOINTS)] - j[list(EVAL_JOINTS)], axis=1)
                )
        e = np.concatenate(err) * 1e3
        out[f"mpjpe_{name}_mm"] = round(float(np.mean(e)), 1)
        out[f"pck50_{name}"] = round(float(np.mean(e < 50.0)), 3)
    out["sim_repeats"] = sim_repeats
    return out


def _fmt(v: float) -> str:
    if not np.isfinite(v):
        return "—"
    return f"{v:.3f}" if abs(v) < 1 else f"{v:.1f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sessions", nargs="+", type=Path, default=[Path("/tmp/sim30_s3"), Path("/tmp/sim30_s7")]
    )
    parser.add_argument("--every", type=int, default=3, help="every n-th rig instant")
    parser.add_argument("--cache", type=Path, default=None, help="folder caching measurements")
    parser.add_argument("--gate-px", type=float, default=3.0, help="blob-marker matching gate")
    parser.add_argument("--sim-repeats", type=int, default=2, help="simdata draws per instant")
    parser.add_argument("--train-samples", type=int, default=200, help="training-set samples")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--dump", type=Path, default=None, help="write the records (npz)")
    parser.add_argument(
        "--network",
        action="store_true",
        help="also run the committed checkpoint on both sets of clouds (MPJPE)",
    )
    args = parser.parse_args()

    measured, simulated = Records.empty(), Records.empty()
    ms_obs = []
    instants = 0
    for k, folder in enumerate(args.sessions):
        t0 = time.monotonic()
        sess = measure_session(folder, args.every, args.cache)
        t1 = time.monotonic()
        scenario = analyse_recording(folder, sess, measured, args.gate_px)
        ms_obs.append(
            analyse_simdata(
                scenario, sess, simulated, args.gate_px, args.sim_repeats, args.seed + k
            )
        )
        instants += sess.t_mid_ns.shape[0]
        print(
            f"{folder}: {sess.t_mid_ns.shape[0]} instants, measured in {t1 - t0:.0f} s, "
            f"analysed in {time.monotonic() - t1:.0f} s"
        )
    tabs = {"meas": measured.arrays(), "sim": simulated.arrays()}
    if args.dump is not None:
        flat: dict[str, Any] = {
            f"{src}.{tab}.{col}": arr
            for src, t in tabs.items()
            for tab, cols in t.items()
            for col, arr in cols.items()
        }
        np.savez(args.dump, **flat)
    st_meas, st_sim = statistics(tabs["meas"]), statistics(tabs["sim"])
    train = training_clouds(args.train_samples, args.seed) if args.train_samples else {}
    cmp = compare(st_meas, st_sim)
    print(f"{'statistic':42s} {'measured':>10s} {'simdata':>10s} {'tolerance':>10s}  ok")
    for key in st_meas:
        row = cmp.get(key)
        tol = row["tolerance"] if row else ""
        ok = ("yes" if row["within"] else "NO") if row else ""
        print(f"{key:42s} {_fmt(st_meas[key]):>10s} {_fmt(st_sim[key]):>10s} {tol:>10s}  {ok}")
    if train:
        print(
            f"training distribution ({args.train_samples} samples, 4 cameras): "
            f"{train['points_per_cloud']:.1f} ± {train['points_per_cloud_sd']:.1f} points per "
            f"cloud, {100 * train['det_per_view']:.1f} % of the markers detected per view"
        )
    net = network_errors(measured, simulated, args.sim_repeats) if args.network else {}
    if net:
        print(
            f"network {net['checkpoint']}: MPJPE {net['mpjpe_measured_mm']} mm on the measured "
            f"clouds, {net['mpjpe_simdata_mm']} mm on simdata's clouds of the same instants "
            f"(PCK@50 {net['pck50_measured']} / {net['pck50_simdata']})"
        )
    within = sum(r["within"] for r in cmp.values())
    print(f"{within}/{len(cmp)} toleranced statistics within tolerance")
    result = {
        "benchmark": "democap_simdata_match",
        "sessions": [str(p) for p in args.sessions],
        "instants": instants,
        "sim_repeats": args.sim_repeats,
        "gate_px": args.gate_px,
        "measured": {k: round(v, 4) for k, v in st_meas.items()},
        "simdata": {k: round(v, 4) for k, v in st_sim.items()},
        "comparison": cmp,
        "within": within,
        "toleranced": len(cmp),
        "training_distribution": train,
        "network": net,
        "simdata_ms_per_observation": round(float(np.mean(ms_obs)), 3),
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
