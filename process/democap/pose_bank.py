"""Pose bank: real body poses as extra starts of the skeleton solve.

The network's estimates are the solve's starts, and where the network is far off (a body bent
double, hanging from a bar, a pose of an activity it never saw) every start is, and the solve
ends in a minimum no gradient step leaves, although the true pose explains the cloud far
better (docs/democap.md, "Pose bank"). The bank is a fixed set of real poses, independent of
the network: the medoids of a k-means over the joint positions of motion-capture frames (the
corpus's ``train`` split, :func:`build_pose_bank`), each stored with its heading removed on the
reference body (1.75 m). :func:`bank_starts` places every bank pose at every heading of a
ring on a cloud, scaled to the body's estimated height and to a shorter and a taller body
(:attr:`BankSearch.height_scales`), slides each onto the cloud
(translation-only ICP), scores it by how well it explains the cloud (both ways, bounded), and
returns the best few as starts for :func:`.solve.solve_skeleton`.

The committed bank (:data:`DEFAULT_POSE_BANK`, 256 poses of the 27 training clips at 10 Hz) is
made by ``mocaprig democap pose-bank --corpus DIR``.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt
import torch
from scipy.cluster.vq import kmeans2
from scipy.spatial.transform import Rotation

from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body import BvhClip, retarget_bvh
from mocaprig.process.body.kinematics import democap_joints, forward_kinematics
from mocaprig.process.body.markers import MarkerSet
from mocaprig.process.body.shape import BodyShape
from mocaprig.process.body.skeleton import POSE_DIM
from mocaprig.process.democap.artifact import load_artifact, save_artifact
from mocaprig.process.democap.solve import REFERENCE_HEIGHT_M
from mocaprig.validation import check_finite, check_positive, check_shape

__all__ = [
    "DEFAULT_POSE_BANK",
    "BankSearch",
    "PoseBank",
    "bank_starts",
    "build_pose_bank",
    "load_pose_bank",
    "reference_poses",
    "save_pose_bank",
]

_log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

#: The committed bank (module doc).
DEFAULT_POSE_BANK = Path(__file__).resolve().parent / "data" / "pose_bank.npz"
#: Height of the body the bank's poses are stored on (m; the solve's reference body); starts
#: are scaled from it.
_BANK_HEIGHT_M = REFERENCE_HEIGHT_M
_FORMAT_VERSION = 1


@dataclass(frozen=True, slots=True)
class PoseBank:
    """P real poses, heading removed.

    Attributes:
        poses: (P, 33) pose vectors (:mod:`process.body.skeleton`) on the reference body
            (1.75 m): the root turned so that the body's forward axis (+Y) has no heading
            about +Z (its tilt kept), the root's floor position (x, y) 0, its height kept.
        source: names of the clips the poses come from.
    """

    poses: FloatArray
    source: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        check_finite(check_shape(self.poses, ["P", POSE_DIM], name="PoseBank.poses"))
        if len(self.poses) == 0:
            msg = "PoseBank.poses is empty; a bank needs at least one pose"
            raise ValidationError(msg)

    def __len__(self) -> int:
        return int(self.poses.shape[0])


@dataclass(frozen=True, slots=True)
class BankSearch:
    """How :func:`bank_starts` searches the bank (lengths in metres).

    Attributes:
        headings: headings tried per pose, evenly round the vertical.
        starts: starts returned per cloud, each of a different bank pose.
        screen: placements (pose, heading) that go on to the coarse round: the best by
            the score at ``screen_gate_m`` with the centroids of cloud and placement met.
        screen_gate_m: the screen's gate (wide: the centroids meet only roughly).
        keep: placements that go on from the coarse round to the fine one.
        subsample: points of the cloud used in the coarse round (all in the fine one).
        gate_m: the score's gate ``c`` (Geman–McClure, as the solve's energy).
        icp_gate_m: pairs farther apart than this do not move a placement (first round;
            shrinking by 0.7 a step to 0.06 m).
        energy_per_point: the predictor searches the bank only for clouds whose first
            solve's selection energy (:attr:`.solve.SolveResult.energy`) per cloud point is
            above this: a cloud the network's starts explain well is left alone (on the
            validation sets 6–28 % of the frames are searched, for all of the gain).
        height_scales: the bank is placed on the body's estimated height times each of
            these, ``starts`` starts each: the estimate comes from a solve that explained
            the cloud poorly, and on a body off the model it is often what went wrong (a
            2.2 m subject solved 1.75 m tall). The default spans the solve's own height
            range (:attr:`.solve.SolveOptions.height_range`).
    """

    headings: int = 12
    starts: int = 3
    screen: int = 512
    screen_gate_m: float = 0.15
    keep: int = 128
    subsample: int = 96
    gate_m: float = 0.05
    icp_gate_m: float = 0.15
    energy_per_point: float = 0.6
    height_scales: tuple[float, ...] = (0.87, 1.0, 1.15)

    def __post_init__(self) -> None:
        for name in ("headings", "starts", "screen", "keep", "subsample"):
            if int(getattr(self, name)) < 1:
                msg = f"BankSearch.{name} must be >= 1, got {getattr(self, name)}"
                raise ValidationError(msg)
        check_positive(self.gate_m, name="BankSearch.gate_m")
        check_positive(self.icp_gate_m, name="BankSearch.icp_gate_m")
        check_positive(self.screen_gate_m, name="BankSearch.screen_gate_m")
        if not self.energy_per_point >= 0.0:
            msg = f"BankSearch.energy_per_point must be >= 0, got {self.energy_per_point}"
            raise ValidationError(msg)
        scales = tuple(float(f) for f in self.height_scales)
        if not scales or not all(np.isfinite(f) and f > 0 for f in scales):
            msg = (
                "BankSearch.height_scales must be one or more positive factors, "
                f"got {self.height_scales!r}"
            )
            raise ValidationError(msg)
        object.__setattr__(self, "height_scales", scales)


def _without_heading(poses: FloatArray) -> FloatArray:
    """Poses (P, 33) with the root's heading about +Z and its floor position removed."""
    r = Rotation.from_rotvec(poses[:, :3]).as_matrix()
    fwd = r[:, :, 1]
    psi = np.arctan2(-fwd[:, 0], fwd[:, 1])
    level = Rotation.from_euler("z", -psi[:, None]).as_matrix() @ r
    out = poses.copy()
    out[:, :3] = Rotation.from_matrix(level).as_rotvec()
    out[:, 3:5] = 0.0
    return out


def reference_poses(clips: Sequence[BvhClip], *, rate_hz: float) -> FloatArray:
    """Every clip retargeted onto the reference body (:data:`.solve.REFERENCE_HEIGHT_M`),
    thinned to about ``rate_hz``: pose vectors (N, 33), clip after clip (the frames the bank
    and the pose prior are made from)."""
    check_positive(rate_hz, name="rate_hz")
    ref = BodyShape.from_height(_BANK_HEIGHT_M)
    poses = []
    for i, clip in enumerate(clips):
        step = max(1, round(1.0 / (clip.frame_time_s * rate_hz)))
        thin = replace(clip, frames=clip.frames[::step], frame_time_s=clip.frame_time_s * step)
        poses.append(retarget_bvh(thin, ref).poses)
        _log.info("clip %d/%d %s: %d frames", i + 1, len(clips), clip.name, len(thin.frames))
    return np.concatenate(poses) if poses else np.zeros((0, POSE_DIM))


def build_pose_bank(
    clips: Sequence[BvhClip], *, size: int = 256, rate_hz: float = 10.0, seed: int = 0
) -> PoseBank:
    """A bank of ``size`` poses from motion clips: each clip retargeted onto the reference body
    (thinned to about ``rate_hz``), every frame's heading removed, k-means (seeded) over the
    frames' joint positions relative to the pelvis's floor point, and each cluster's medoid
    (the frame nearest its centre) kept: real poses, within the joint limits the retarget
    keeps. Fewer than ``size`` poses when clusters come out empty.

    Raises:
        ValidationError: no clip, ``size`` < 1, a non-positive rate, or fewer frames than
            ``size``.
    """
    if not clips:
        msg = "build_pose_bank needs at least one clip"
        raise ValidationError(msg)
    if size < 1:
        msg = f"size must be >= 1, got {size}"
        raise ValidationError(msg)
    check_positive(rate_hz, name="rate_hz")
    ref = BodyShape.from_height(_BANK_HEIGHT_M)
    all_poses = _without_heading(reference_poses(clips, rate_hz=rate_hz))
    if len(all_poses) < size:
        msg = f"the clips give {len(all_poses)} frames at {rate_hz} Hz, fewer than size={size}"
        raise ValidationError(msg)
    j = democap_joints(forward_kinematics(all_poses, ref))
    feat = (j - j[:, :1] * np.array([1.0, 1.0, 0.0])).reshape(len(j), -1)
    centres, label = kmeans2(feat, size, seed=np.random.default_rng(seed), minit="++", iter=30)
    medoids = []
    for k in range(size):
        idx = np.flatnonzero(label == k)
        if len(idx):
            medoids.append(int(idx[np.argmin(((feat[idx] - centres[k]) ** 2).sum(-1))]))
    return PoseBank(poses=all_poses[np.array(medoids)], source=tuple(c.name for c in clips))


def save_pose_bank(bank: PoseBank, path: Path, *, overwrite: bool = False) -> Path:
    """Write ``bank`` to ``path`` (.npz; float32 poses, the source clips).

    Raises:
        RecordingError: ``path`` exists and ``overwrite`` is False, or cannot be written.
    """
    return save_artifact(
        path,
        "pose bank",
        {"poses": bank.poses.astype(np.float32)},
        source=bank.source,
        version=_FORMAT_VERSION,
        overwrite=overwrite,
    )


def load_pose_bank(path: Path | None = None) -> PoseBank:
    """Read a bank written by :func:`save_pose_bank` (default: :data:`DEFAULT_POSE_BANK`).

    Raises:
        ProcessingError: the file is missing, not a bank, or of another format version.
    """
    path = DEFAULT_POSE_BANK if path is None else Path(path)
    arrays, source = load_artifact(
        path,
        "pose bank",
        ("poses",),
        version=_FORMAT_VERSION,
        rebuild="mocaprig democap pose-bank",
    )
    poses = arrays["poses"]
    try:
        return PoseBank(poses=poses, source=source)
    except ValidationError as exc:
        msg = f"pose bank {path} is not a bank of poses ({exc})"
        raise ProcessingError(msg) from exc


def _templates(bank: PoseBank, headings: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Markers (P·H, 53, 3) float32 and DeMoCap joints (P·H, 19, 3) float64 of every bank pose
    at every heading, on the reference body (placement ``p·H + h``); made once per bank and
    heading count, not per call (the live solve calls once a frame)."""
    poses = np.ascontiguousarray(bank.poses, np.float64)
    return _templates_of(poses.tobytes(), poses.shape[0], headings)


@functools.lru_cache(maxsize=4)
def _templates_of(poses: bytes, count: int, headings: int) -> tuple[torch.Tensor, torch.Tensor]:
    ref = BodyShape.from_height(_BANK_HEIGHT_M)
    ms = MarkerSet.for_shape(ref)
    kin = forward_kinematics(np.frombuffer(poses, np.float64).reshape(count, POSE_DIM), ref)
    ji = ms.joint_index
    mk = kin.positions_m[:, ji] + (kin.rotations[:, ji] @ ms.offsets_m[..., None])[..., 0]
    jt = democap_joints(kin)
    psi = np.arange(headings) * (2.0 * np.pi / headings)
    rz = Rotation.from_euler("z", psi[:, None]).as_matrix()
    m = np.einsum("hab,pmb->phma", rz, mk).reshape(-1, mk.shape[1], 3)
    j = np.einsum("hab,pmb->phma", rz, jt).reshape(-1, jt.shape[1], 3)
    return torch.from_numpy(m).float(), torch.from_numpy(j)


_CHUNK = 256


def _d2(x: torch.Tensor, pts: torch.Tensor, pn: torch.Tensor) -> torch.Tensor:
    """Squared distances (C, M, N) of markers x (C, M, 3) to points pts (N, 3) with squared
    norms pn (N,): one matrix product, no square root (torch.cdist takes one)."""
    c, m, _ = x.shape
    d2 = torch.addmm(pn, x.reshape(c * m, 3), pts.T, alpha=-2.0).view(c, m, -1)
    return d2.add_(x.square().sum(2, keepdim=True)).clamp_(min=0.0)


def _badness(d2: torch.Tensor, c: float) -> torch.Tensor:
    """How badly each placement explains the cloud (C,) from its distances (C, M, N): the
    Geman–McClure (gate ``c``) of every marker's nearest point plus every point's nearest
    marker, m²."""
    cc = c * c
    dm, dp = d2.amin(2), d2.amin(1)
    return (cc * dm / (cc + dm)).sum(1) + (cc * dp / (cc + dp)).sum(1)


def _score(m: torch.Tensor, pts: torch.Tensor, t: torch.Tensor, c: float) -> torch.Tensor:
    """:func:`_badness` of placements' markers (C, M, 3) moved by t (C, 3) on pts (N, 3),
    in chunks of placements whose distances stay in the cache."""
    pn = pts.square().sum(1)
    out = torch.empty(len(t), dtype=pts.dtype)
    for lo in range(0, len(t), _CHUNK):
        x = m[lo : lo + _CHUNK] + t[lo : lo + _CHUNK, None]
        out[lo : lo + _CHUNK] = _badness(_d2(x, pts, pn), c)
    return out


def _slide(
    m: torch.Tensor, pts: torch.Tensor, t: torch.Tensor, steps: int, gate_m: float, c: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Translation-only ICP of placements' markers (C, M, 3), moved by t (C, 3), onto pts
    (N, 3): each step by the mean offset of the nearest pairs both ways within the gate
    (shrinking by 0.7 a step to 0.06 m) -> the translations and :func:`_badness` (gate
    ``c``) after them. In chunks of placements."""
    pn = pts.square().sum(1)
    t_out = torch.empty_like(t)
    score = torch.empty(len(t), dtype=pts.dtype)
    for lo in range(0, len(t), _CHUNK):
        mc, tc = m[lo : lo + _CHUNK], t[lo : lo + _CHUNK]
        gate = gate_m
        for _ in range(steps):
            x = mc + tc[:, None]
            d2 = _d2(x, pts, pn)
            # numpy's argmin: several times torch's min-with-indices on these shapes
            a = d2.numpy()
            im = torch.from_numpy(a.argmin(2))
            ip = torch.from_numpy(a.argmin(1))
            dm = torch.gather(d2, 2, im[..., None])[..., 0]
            dp = torch.gather(d2, 1, ip[:, None])[:, 0]
            wm = (dm < gate**2).to(x.dtype)
            wp = (dp < gate**2).to(x.dtype)
            rm = pts[im] - x
            rp = pts[None] - torch.gather(x, 1, ip[..., None].expand(-1, -1, 3))
            num = (rm * wm[..., None]).sum(1) + (rp * wp[..., None]).sum(1)
            tc = tc + num / (wm.sum(1) + wp.sum(1)).clamp(min=1.0)[:, None]
            gate = max(gate * 0.7, 0.06)
        score[lo : lo + _CHUNK] = _badness(_d2(mc + tc[:, None], pts, pn), c)
        t_out[lo : lo + _CHUNK] = tc
    return t_out, score


def bank_starts(
    clouds: Sequence[npt.ArrayLike],
    heights_m: npt.ArrayLike,
    bank: PoseBank,
    *,
    search: BankSearch | None = None,
) -> tuple[FloatArray, FloatArray]:
    """The bank's best placements on each cloud, as solve starts (module doc).

    Args:
        clouds: B fused clouds (N_i, 3), world, m.
        heights_m: (B,) the body's estimated standing height per cloud (the bank is scaled
            to it).
        bank: the poses.
        search: how (default :class:`BankSearch`).

    Returns:
        markers (S, B, 53, 3) and DeMoCap joints (S, B, 19, 3), world, m: for each of the
        search's ``height_scales`` in turn, the ``starts`` best placements of distinct poses
        per cloud on a body of that multiple of ``heights_m``, best first (S = ``starts`` ×
        the scales; fewer poses in the bank than ``starts``: placements repeat).

    Raises:
        ValidationError: ``heights_m`` not one positive height per cloud, a cloud of the
            wrong shape or with no point.
    """
    opt = search or BankSearch()
    h = np.asarray(check_finite(check_shape(heights_m, [len(clouds)], name="heights_m")), float)
    if (h <= 0).any():
        msg = f"heights_m must be positive, got {h[h <= 0][:3]}"
        raise ValidationError(msg)
    tm, tj = _templates(bank, opt.headings)
    n_start = opt.starts
    n_s = n_start * len(opt.height_scales)
    out_m = np.empty((n_s, len(clouds), tm.shape[1], 3))
    out_j = np.empty((n_s, len(clouds), tj.shape[1], 3))
    for b, cloud in enumerate(clouds):
        p = np.asarray(check_finite(check_shape(cloud, ["N", 3], name="cloud")), np.float32)
        if len(p) == 0:
            msg = f"cloud {b} has no point; the pose bank cannot place a body on it"
            raise ValidationError(msg)
        pts = torch.from_numpy(p)
        for i, f in enumerate(opt.height_scales):
            rows = slice(i * n_start, (i + 1) * n_start)
            out_m[rows, b], out_j[rows, b] = _place(pts, float(h[b]) * f, tm, tj, opt)
    return out_m, out_j


def _place(
    pts: torch.Tensor, height_m: float, tm: torch.Tensor, tj: torch.Tensor, opt: BankSearch
) -> tuple[FloatArray, FloatArray]:
    """The ``opt.starts`` best placements of distinct bank poses on one cloud (N, 3), the
    bank scaled to ``height_m``: markers (starts, 53, 3) and joints (starts, 19, 3), m."""
    n_start = opt.starts
    s = height_m / _BANK_HEIGHT_M
    m = tm * s
    t = pts.mean(0) - m.mean(1)
    # screen: every placement where the centroids meet, scored on a subsample of the
    # cloud taken evenly through it (the same points whatever else is in the call) at a
    # wide gate; coarse: the best ``screen`` slid onto the subsample; fine: the best
    # ``keep`` of those slid onto the whole cloud.
    few = pts[np.linspace(0, len(pts) - 1, min(opt.subsample, len(pts))).round().astype(int)]
    go = torch.argsort(_score(m, few, t, opt.screen_gate_m))[: opt.screen]
    t_go, sc = _slide(m[go], few, t[go], 3, opt.icp_gate_m, opt.gate_m)
    top = torch.argsort(sc)[: opt.keep]
    best = go[top]
    fine_gate = min(opt.icp_gate_m, 0.10)
    t_best, sc = _slide(m[best], pts, t_go[top], 3, fine_gate, opt.gate_m)
    order = torch.argsort(sc).tolist()
    picked: list[int] = []
    poses: set[int] = set()
    for k in order:
        pose = int(best[k]) // opt.headings
        if pose not in poses:
            poses.add(pose)
            picked.append(k)
        if len(picked) == n_start:
            break
    picked += [picked[-1]] * (n_start - len(picked))
    out_m = np.empty((n_start, tm.shape[1], 3))
    out_j = np.empty((n_start, tj.shape[1], 3))
    for i, k in enumerate(picked):
        c = int(best[k])
        shift = t_best[k].double()
        out_m[i] = (m[c].double() + shift).numpy()
        out_j[i] = (s * tj[c] + shift).numpy()
    return out_m, out_j
