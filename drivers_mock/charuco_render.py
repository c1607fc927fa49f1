"""Render a ChArUco board into the simulated rig's cameras, for the ChArUco calibration tests.

The board (``CharucoBoardSpec.board().generateImage`` with a white margin) lies in its plane
``z = 0`` of the board frame (origin at the outer corner of the top-left square, +X along the
columns, +Y down the rows, +Z into the board; ``calib.charuco``'s convention) and is placed in the
world by ``T_world_board``. Each output pixel is supersampled: its rays are undistorted
through the camera's Brown–Conrady model (``cv2.undistortPointsIter``), intersected with the
board plane and looked up in the texture (a copy at about twice the sampling rate, made with
``INTER_AREA`` so far boards do not alias); the samples are box-filtered, blurred (optics) and
given read noise, then quantised like the device: D415 left IR with the emitter off (``mono8``,
no dot pattern) or DAVIS240C APS (10-bit values in ``uint16``). The background is a smooth grey
texture; the back of the board is plain grey.

Board-pose trajectories are pure functions of a seed:

* :func:`intrinsics_poses`: hand-held views in front of one camera, spread over the image
  (stratified cells), at distances where the board fills a chosen fraction of the image width,
  tilted 10–45° about random axes with random roll;
* :func:`shared_poses`: views seen by every camera of a set at once (the board turned towards
  the cameras' mean direction with some tilt), for extrinsics.

:func:`write_board_recording` writes such a session as an MCAP through
:class:`acquire.recorder.Recorder` (D415 ``ir`` topics and DAVIS ``frame`` topics, log time =
the instant, common to all cameras) so the CLI can be tested end to end.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from mocaprig.calib.charuco import CharucoBoardSpec, board_image
from mocaprig.drivers_mock.rig import PinholeCamera, Rig, default_rig, project
from mocaprig.drivers_mock.scenario import stream_rng
from mocaprig.errors import ValidationError

__all__ = [
    "BoardRecording",
    "CameraLook",
    "intrinsics_poses",
    "render_board",
    "shared_poses",
    "write_board_recording",
]

F64 = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]

#: Pixels per metre of the finest texture level (≈ 100 dpi); coarser levels halve it.
_MASTER_PX_PER_M = 4_000.0


@dataclass(frozen=True, slots=True)
class CameraLook:
    """How a camera's image of the board looks.

    Attributes:
        output: ``"ir8"`` (D415 IR, ``uint8``) or ``"aps10"`` (DAVIS APS, 10-bit in ``uint16``).
        full_scale: Counts of a white board at brightness 1 (255·0.85 for IR, 900 for APS).
        read_noise: Gaussian noise σ (counts).
        blur_px: Gaussian optical blur σ (px).
        supersample: Samples per pixel along each axis.
    """

    output: Literal["ir8", "aps10"]
    full_scale: float
    read_noise: float
    blur_px: float = 0.5
    supersample: int = 3

    @staticmethod
    def for_camera(camera: PinholeCamera) -> CameraLook:
        """The look of the rig's DAVIS (240 px wide: APS) or a D415 (IR)."""
        if camera.width <= 346:
            return CameraLook("aps10", 900.0, 2.9, blur_px=0.5, supersample=4)
        return CameraLook("ir8", 220.0, 1.5, blur_px=0.5, supersample=2)


@functools.lru_cache(maxsize=32)
def _texture(spec: CharucoBoardSpec, margin_m: float, level: int) -> npt.NDArray[np.float32]:
    """The board texture at ``_MASTER_PX_PER_M / 2**level`` px/m (a mip-map level)."""
    if level == 0:
        img = board_image(spec, px_per_m=_MASTER_PX_PER_M, margin_m=margin_m)
        out: npt.NDArray[np.float32] = img.astype(np.float32) / 255.0
        return out
    finer = _texture(spec, margin_m, level - 1)
    size = (max(2, finer.shape[1] // 2), max(2, finer.shape[0] // 2))
    return np.asarray(cv2.resize(finer, size, interpolation=cv2.INTER_AREA), np.float32)


@functools.lru_cache(maxsize=16)
def _rays(k_bytes: bytes, d_bytes: bytes, width: int, height: int, ss: int) -> tuple[F32, F32]:
    """Normalised undistorted ray coordinates (a, b) of every sub-pixel sample, ``(H·ss, W·ss)``."""
    k = np.frombuffer(k_bytes, dtype=np.float64).reshape(3, 3)
    d = np.frombuffer(d_bytes, dtype=np.float64)
    off = (np.arange(ss) + 0.5) / ss - 0.5
    u = (np.arange(width)[:, None] + off[None, :]).reshape(-1)
    v = (np.arange(height)[:, None] + off[None, :]).reshape(-1)
    uu, vv = np.meshgrid(u, v)
    pts = np.stack([uu.ravel(), vv.ravel()], axis=1)
    if np.any(d != 0):
        crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 40, 1e-12)
        ab = cv2.undistortPoints(pts.reshape(-1, 1, 2), k, d, R=None, P=None, criteria=crit)
        ab = ab.reshape(-1, 2)
    else:
        ab = np.stack([(pts[:, 0] - k[0, 2]) / k[0, 0], (pts[:, 1] - k[1, 2]) / k[1, 1]], axis=1)
    shape = (height * ss, width * ss)
    return ab[:, 0].reshape(shape).astype(np.float32), ab[:, 1].reshape(shape).astype(np.float32)


def _background(camera: PinholeCamera, rng: np.random.Generator) -> F64:
    small = rng.uniform(0.25, 0.55, size=(6, 8))
    bg = cv2.resize(small, (camera.width, camera.height), interpolation=cv2.INTER_CUBIC)
    return np.asarray(bg, np.float64)


def render_board(
    camera: PinholeCamera,
    spec: CharucoBoardSpec,
    T_world_board: npt.ArrayLike,
    *,
    rng: np.random.Generator,
    look: CameraLook | None = None,
    brightness: float = 1.0,
    margin_m: float | None = None,
) -> npt.NDArray[np.uint8] | npt.NDArray[np.uint16]:
    """The camera's image of the board at ``T_world_board``.

    Args:
        camera: Any camera of the simulated rig (distortion included).
        spec: The board.
        T_world_board: Board-to-world transform ``(4, 4)`` (m).
        rng: Seeded generator for the background and the noise (consumed).
        look: Output type and noise (default: :meth:`CameraLook.for_camera`).
        brightness: Illumination factor of the board (white = ``brightness·full_scale``).
        margin_m: White margin around the squares (m; half a square by default).

    Returns:
        ``uint8`` (IR) or ``uint16`` 10-bit (APS) image of shape ``(H, W)``.
    """
    lk = CameraLook.for_camera(camera) if look is None else look
    T = np.asarray(T_world_board, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        msg = f"render_board(): T_world_board must be a finite 4×4 transform, got {T.shape}"
        raise ValidationError(msg)
    margin = 0.5 * spec.square_length_m if margin_m is None else float(margin_m)
    ss = lk.supersample
    val, cover = _board_layer(camera, spec, T, margin, ss, brightness)
    bg = _background(camera, rng)
    img = val + (1.0 - cover) * bg
    if lk.blur_px > 0:
        img = np.asarray(cv2.GaussianBlur(img, (0, 0), lk.blur_px), np.float64)
    counts = img * lk.full_scale / 0.85 + rng.normal(0.0, lk.read_noise, size=img.shape)
    if lk.output == "ir8":
        return np.clip(np.round(counts), 0, 255).astype(np.uint8)
    return np.clip(np.round(counts), 0, 1023).astype(np.uint16)


def _window(
    camera: PinholeCamera, spec: CharucoBoardSpec, T: F64, margin: float
) -> tuple[int, int, int, int] | None:
    """Pixel bounding box ``(x0, y0, x1, y1)`` (exclusive end) of the board; None if unseen."""
    w_m, h_m = spec.size_m
    s = np.linspace(0.0, 1.0, 33)
    xs = np.concatenate([s, np.ones_like(s), s[::-1], np.zeros_like(s)]) * (w_m + 2 * margin)
    ys = np.concatenate([np.zeros_like(s), s, np.ones_like(s), s[::-1]]) * (h_m + 2 * margin)
    pts = np.stack([xs - margin, ys - margin, np.zeros_like(xs)], axis=1)
    uv, z = project(camera, pts @ T[:3, :3].T + T[:3, 3])
    if np.all(z <= 1e-3):
        return None
    if np.any(z <= 1e-3):
        return 0, 0, camera.width, camera.height
    x0 = max(int(np.floor(np.min(uv[:, 0]))) - 3, 0)
    y0 = max(int(np.floor(np.min(uv[:, 1]))) - 3, 0)
    x1 = min(int(np.ceil(np.max(uv[:, 0]))) + 4, camera.width)
    y1 = min(int(np.ceil(np.max(uv[:, 1]))) + 4, camera.height)
    if x1 <= x0 or y1 <= y0:
        return None
    return x0, y0, x1, y1


def _board_layer(
    camera: PinholeCamera,
    spec: CharucoBoardSpec,
    T: F64,
    margin: float,
    ss: int,
    brightness: float,
) -> tuple[F32, F32]:
    """Board radiance (0 off the board) and the board's pixel coverage, both ``(H, W)``."""
    val_full = np.zeros((camera.height, camera.width), np.float32)
    cover_full = np.zeros((camera.height, camera.width), np.float32)
    win = _window(camera, spec, T, margin)
    if win is None:
        return val_full, cover_full
    x0, y0, x1, y1 = win
    a_all, b_all = _rays(
        np.ascontiguousarray(camera.K, np.float64).tobytes(),
        np.ascontiguousarray(camera.distortion, np.float64).tobytes(),
        camera.width,
        camera.height,
        ss,
    )
    a = a_all[y0 * ss : y1 * ss, x0 * ss : x1 * ss]
    b = b_all[y0 * ss : y1 * ss, x0 * ss : x1 * ss]
    T_cam_board = camera.T_cam_world @ T
    r = [[float(x) for x in row] for row in T_cam_board[:3, :3]]
    t = [float(x) for x in T_cam_board[:3, 3]]
    n = [r[0][2], r[1][2], r[2][2]]
    n_t = n[0] * t[0] + n[1] * t[1] + n[2] * t[2]
    # Ray d = (a, b, 1): s = n·t / n·d; point = s·d; board coords = Rᵀ(point − t). float32.
    nd = n[0] * a + n[1] * b + n[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = n_t / nd
    front = n_t > 0.0
    px = s * a - t[0]
    py = s * b - t[1]
    pz = s - t[2]
    bx = r[0][0] * px + r[1][0] * py + r[2][0] * pz + margin
    by = r[0][1] * px + r[1][1] * py + r[2][1] * pz + margin
    w_m, h_m = spec.size_m
    valid = (s > 0) & np.isfinite(s)
    inside = valid & (bx >= 0) & (by >= 0) & (bx <= w_m + 2 * margin) & (by <= h_m + 2 * margin)
    # Texture level with 1–2 texels per sample at the nearest point of the board.
    depth = np.where(inside, s, np.inf)
    z_min = float(np.min(depth)) if np.any(inside) else 1.0  # ray parameter s = depth z
    rate = max(camera.fx, camera.fy) * ss / max(z_min, 1e-3)
    level = int(np.clip(math.floor(math.log2(_MASTER_PX_PER_M / max(rate, 1.0))), 0, 6))
    tex = _texture(spec, margin, level)
    master = _texture(spec, margin, 0)
    scale_x = tex.shape[1] / master.shape[1] * _MASTER_PX_PER_M
    scale_y = tex.shape[0] / master.shape[0] * _MASTER_PX_PER_M
    map_x = np.where(inside, bx * scale_x - 0.5, -10.0).astype(np.float32)
    map_y = np.where(inside, by * scale_y - 0.5, -10.0).astype(np.float32)
    sampled = cv2.remap(
        tex, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0
    )
    board_val = 0.04 + 0.81 * sampled if front else np.full_like(sampled, 0.5)
    size = (x1 - x0, y1 - y0)
    cover = cv2.resize(inside.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    val = np.where(inside, board_val * brightness, 0.0).astype(np.float32)
    val = np.asarray(cv2.resize(val, size, interpolation=cv2.INTER_AREA), np.float32)
    val_full[y0:y1, x0:x1] = val
    cover_full[y0:y1, x0:x1] = cover
    return val_full, cover_full


def _board_centre(spec: CharucoBoardSpec) -> F64:
    w, h = spec.size_m
    return np.array([w / 2.0, h / 2.0, 0.0])


def _pose_in_camera(spec: CharucoBoardSpec, centre_cam: F64, r_cam_board: F64) -> F64:
    out = np.eye(4)
    out[:3, :3] = r_cam_board
    out[:3, 3] = centre_cam - r_cam_board @ _board_centre(spec)
    return out


def _tilt(rng: np.random.Generator, lo_deg: float, hi_deg: float, roll_deg: float) -> F64:
    phi = rng.uniform(0.0, 2.0 * np.pi)
    axis = np.array([np.cos(phi), np.sin(phi), 0.0])
    tilt = Rotation.from_rotvec(axis * np.radians(rng.uniform(lo_deg, hi_deg)))
    roll = Rotation.from_rotvec([0.0, 0.0, np.radians(rng.uniform(-roll_deg, roll_deg))])
    out: F64 = (tilt * roll).as_matrix()
    return out


def _inside_fraction(camera: PinholeCamera, spec: CharucoBoardSpec, T_world_board: F64) -> float:
    pts = spec.corners_m @ T_world_board[:3, :3].T + T_world_board[:3, 3]
    uv, z = project(camera, pts)
    ok = (
        (z > 0.05)
        & (uv[:, 0] >= 2)
        & (uv[:, 1] >= 2)
        & (uv[:, 0] <= camera.width - 3)
        & (uv[:, 1] <= camera.height - 3)
    )
    return float(np.mean(ok))


def intrinsics_poses(
    camera: PinholeCamera,
    spec: CharucoBoardSpec,
    n: int,
    *,
    seed: int,
    fill: tuple[float, float] = (0.35, 0.7),
    tilt_deg: tuple[float, float] = (10.0, 45.0),
    roll_deg: float = 30.0,
    min_inside: float = 0.6,
) -> F64:
    """Hand-held board poses in front of one camera for its intrinsic calibration.

    The views are spread over a 4×3 grid of image cells (cycled), the board centre on the ray of
    a random point of the cell, at a distance where the board spans ``fill`` of the image width,
    tilted ``tilt_deg`` about a random in-plane axis with ±``roll_deg`` of roll; views with fewer
    than ``min_inside`` of the corners inside the image are redrawn.

    Returns:
        ``T_world_board`` poses, shape ``(n, 4, 4)``.
    """
    rng = stream_rng(seed, f"charuco-intrinsics-{camera.name}")
    w_m, _ = spec.size_m
    out = np.zeros((n, 4, 4))
    cells = [(i, j) for j in range(3) for i in range(4)]
    order = rng.permutation(len(cells))
    for k in range(n):
        ci, cj = cells[order[k % len(cells)]]
        for _ in range(200):
            u = (ci + rng.uniform(0.1, 0.9)) / 4.0 * camera.width
            v = (cj + rng.uniform(0.1, 0.9)) / 3.0 * camera.height
            ray = np.array([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0])
            z = camera.fx * w_m / (rng.uniform(*fill) * camera.width)
            T_cam_board = _pose_in_camera(spec, ray * z, _tilt(rng, *tilt_deg, roll_deg))
            T = camera.T_world_cam @ T_cam_board
            if _inside_fraction(camera, spec, T) >= min_inside:
                break
        out[k] = T
    return out


def shared_poses(
    cameras: Sequence[PinholeCamera],
    spec: CharucoBoardSpec,
    n: int,
    *,
    seed: int,
    min_square_px: float = 12.0,
    max_incidence_deg: float = 60.0,
    tilt_deg: float = 15.0,
    min_inside: float = 0.75,
    max_tries: int = 20_000,
) -> F64:
    """Board poses seen at once by every camera of ``cameras`` (for extrinsics).

    The board centre is drawn in the first camera's view frustum; the board faces the mean of
    the directions to the cameras, tilted up to ``tilt_deg`` with any roll. A pose is kept when,
    in every camera, the front of the board is seen at an incidence below
    ``max_incidence_deg``, squares span at least ``min_square_px`` and at least ``min_inside``
    of the corners fall inside the image.

    Returns:
        ``T_world_board`` poses, shape ``(n, 4, 4)``.

    Raises:
        ValidationError: no such pose found in ``max_tries`` draws (cameras too far apart or
            the board too small).
    """
    rng = stream_rng(seed, "charuco-shared-" + "-".join(c.name for c in cameras))
    first = cameras[0]
    centres_cam = [c.T_world_cam[:3, 3] for c in cameras]
    out: list[F64] = []
    tries = 0
    while len(out) < n:
        tries += 1
        if tries > max_tries:
            msg = (
                f"shared_poses(): found {len(out)} of {n} board poses seen by "
                f"{[c.name for c in cameras]} in {max_tries} draws; use a larger board or "
                "cameras with overlapping views"
            )
            raise ValidationError(msg)
        u = rng.uniform(0.1, 0.9) * first.width
        v = rng.uniform(0.1, 0.9) * first.height
        ray = np.array([(u - first.cx) / first.fx, (v - first.cy) / first.fy, 1.0])
        z = rng.uniform(0.5, 4.0)
        p_world = first.T_world_cam[:3, :3] @ (ray * z) + first.T_world_cam[:3, 3]
        to_cams = [(c - p_world) / np.linalg.norm(c - p_world) for c in centres_cam]
        facing = np.mean(to_cams, axis=0)
        facing /= np.linalg.norm(facing)
        # Board +Z points away from the viewers: z_b = −facing; x_b roughly horizontal.
        z_b = -facing
        x_b = np.cross([0.0, 0.0, 1.0], z_b)
        if np.linalg.norm(x_b) < 1e-6:
            x_b = np.array([1.0, 0.0, 0.0])
        x_b /= np.linalg.norm(x_b)
        y_b = np.cross(z_b, x_b)
        r_wb = np.stack([x_b, y_b, z_b], axis=1) @ _tilt(rng, 0.0, tilt_deg, 180.0)
        T = np.eye(4)
        T[:3, :3] = r_wb
        T[:3, 3] = p_world - r_wb @ _board_centre(spec)
        if all(_visible(c, spec, T, min_square_px, max_incidence_deg, min_inside) for c in cameras):
            out.append(T)
    return np.stack(out)


def _visible(
    camera: PinholeCamera,
    spec: CharucoBoardSpec,
    T_world_board: F64,
    min_square_px: float,
    max_incidence_deg: float,
    min_inside: float,
) -> bool:
    centre = T_world_board[:3, :3] @ _board_centre(spec) + T_world_board[:3, 3]
    sight = centre - camera.T_world_cam[:3, 3]
    dist = float(np.linalg.norm(sight))
    cos_inc = float(T_world_board[:3, 2] @ sight) / dist
    if cos_inc < math.cos(math.radians(max_incidence_deg)):
        return False
    if camera.fx * spec.square_length_m * cos_inc / dist < min_square_px:
        return False
    return _inside_fraction(camera, spec, T_world_board) >= min_inside


@dataclass(frozen=True, slots=True)
class BoardRecording:
    """What :func:`write_board_recording` wrote.

    Attributes:
        path: The MCAP file.
        rig: The simulated rig (truth: ``K``, distortion, ``T_world_cam`` of every camera).
        labels: Camera label (``"d415/<serial>"``, ``"davis/<serial>"``) → rig camera name.
        poses: ``T_world_board`` of every instant, shape ``(T, 4, 4)``.
        t_ns: Log time of every instant (ns), shape ``(T,)``.
    """

    path: Path
    rig: Rig
    labels: dict[str, str]
    poses: F64
    t_ns: npt.NDArray[np.int64]


def _fill(camera: PinholeCamera) -> tuple[float, float]:
    # The DAVIS's 240×180 pixels need the board close up (calibration-vicon.md §3.6).
    return (0.55, 0.9) if camera.width <= 346 else (0.35, 0.7)


def write_board_recording(
    path: Path,
    spec: CharucoBoardSpec,
    *,
    seed: int = 0,
    d415: Sequence[int] = (0,),
    intrinsics_views: int = 16,
    shared_views: int = 12,
    interval_ns: int = 100_000_000,
    start_ns: int = 1_700_000_000_000_000_000,
) -> BoardRecording:
    """Record a simulated ChArUco session: intrinsic views for each camera, then shared views.

    The rig is ``default_rig`` of ``seed`` (the same as the simulated world's). For each camera
    (the chosen D415 indices, then the DAVIS) ``intrinsics_views`` poses from
    :func:`intrinsics_poses`, then ``shared_views`` poses from :func:`shared_poses` seen by all of
    them; every instant is rendered into every camera (an image where the board is out of view
    is still written), one instant each ``interval_ns``. Log time and the image stamp are the
    instant (one clock for all cameras; the board is held still at each pose).

    Raises:
        RecordingError: ``path`` exists (never overwritten).
    """
    from mocaprig.acquire.device_id import DeviceId
    from mocaprig.acquire.recorder import Recorder
    from mocaprig.acquire.recording_format import ImageMsg

    rig = default_rig(stream_rng(seed, "rig"))
    cams: list[tuple[str, PinholeCamera]] = []
    for i in d415:
        d = rig.d415[i]
        cams.append((f"d415/{d.serial}", d.ir_left))
    cams.append((f"davis/{rig.davis.serial}", rig.davis.camera))
    poses = [intrinsics_poses(c, spec, intrinsics_views, seed=seed, fill=_fill(c)) for _, c in cams]
    poses.append(shared_poses([c for _, c in cams], spec, shared_views, seed=seed))
    all_poses = np.concatenate(poses)
    t = start_ns + interval_ns * np.arange(all_poses.shape[0], dtype=np.int64)
    rng = stream_rng(seed, "charuco-render")
    with Recorder(Path(path), metadata={"session": {"mock": "true", "scenario": "charuco",
                                                    "seed": str(seed)}}) as rec:  # fmt: skip
        handles = []
        for label, _ in cams:
            dev = DeviceId.parse(label)
            stream = "ir" if dev.kind == "d415" else "frame"
            meta = {"serial": dev.serial, "device": "D415" if dev.kind == "d415" else "DAVIS240C",
                    "frame_id": dev.frame_id}  # fmt: skip
            handles.append(rec.add_stream(dev.topic(stream), ImageMsg, metadata=meta,
                                          queue_messages=100_000, queue_bytes=1 << 30))  # fmt: skip
        for k, (T, tk) in enumerate(zip(all_poses, t, strict=True)):
            bright = float(rng.uniform(0.7, 1.0))
            for h, (label, cam) in zip(handles, cams, strict=True):
                img = render_board(cam, spec, T, rng=rng, brightness=bright)
                enc = "mono8" if img.dtype == np.uint8 else "mono16"
                frame_id = label.replace("/", "_")
                rec.put(h, ImageMsg(img, enc, int(tk), frame_id), log_time_ns=int(tk), sequence=k)  # type: ignore[arg-type]
    return BoardRecording(Path(path), rig, {lab: c.name for lab, c in cams}, all_poses, t)
