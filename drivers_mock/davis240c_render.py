"""The DAVIS240C's view of the simulated world: linear irradiance images with texture.

Event cameras only see brightness *changes*, so what matters is texture and contrast
(eventcap-method.md §2.3: a uniformly coloured body gives silhouette events only). The scene is:

* **the actor**: the 22 capsules of :mod:`process.body.surface`, each with a procedural albedo
  fixed to its joint frame (stripes or a checker, plus low-frequency noise, Michelson contrast
  20–60 %), so the texture moves and twists with the segment;
* **the clapperboard**: each arm a thin rod (radius = the arm thickness) with black/white stripes
  along the arm, hinged as :class:`mocaprig.drivers_mock.clapperboard.Clapperboard` says;
* **the room**: an infinite floor (``z = 0``, 0.5 m tiles) and a back wall behind the actor
  (``y = -2.5 m``, a 0.3 m checker), both with low-frequency noise;
* **light**: ambient plus Lambertian from one fixed directional light (no shadows), optional
  sinusoidal flicker (off by default).

Rendering (§4.4 step 3): the exact capsule ray caster :func:`process.body.render_pinhole` on an
undistorted canvas at ``supersample``× the DAVIS resolution (wide enough for the lens's barrel
distortion), remapped through the DAVIS's Brown–Conrady distortion onto the supersampled sensor
grid and box-downsampled to the sensor (240×180 for the DAVIS240C, 346×260 for a DAVIS346, as
the rig's DAVIS camera says). The supersampling gives partial-coverage edge pixels (real
sensors integrate over the pixel area, so edges give graded, not all-or-nothing, changes) and the
bilinear remap adds ≈ 0.25 px of optical blur. Output is linear irradiance in arbitrary units,
typically 0.05–1.

Everything here is a pure function of the scenario and a session time (int ns).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from mocaprig.drivers_mock.rig import project
from mocaprig.drivers_mock.scenario import Scenario
from mocaprig.errors import ValidationError
from mocaprig.validation import check_positive, check_range

__all__ = [
    "DAVIS_SHAPE",
    "SENSOR_SHAPES",
    "DavisLook",
    "DavisRenderer",
    "log_intensity",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: Sensor shape (rows, columns): 180×240 (davis240c-usb.md §13).
DAVIS_SHAPE: tuple[int, int] = (180, 240)

#: Sensor shapes (rows, columns) the renderer accepts: DAVIS240C 180×240, DAVIS346 260×346.
SENSOR_SHAPES: tuple[tuple[int, int], ...] = (DAVIS_SHAPE, (260, 346))

#: ESIM's ``log_eps`` (eventcap-method.md §4.1): L = log(eps + I) for I of order 1.
LOG_EPS = 1e-3

_NUM_BODY = 22
_CLAPPER_TOP = _NUM_BODY
_CLAPPER_BOTTOM = _NUM_BODY + 1


def log_intensity(intensity: npt.ArrayLike) -> F64:
    """``log(LOG_EPS + I)``: the quantity a DVS pixel compares against its thresholds."""
    return np.log(LOG_EPS + np.maximum(np.asarray(intensity, dtype=np.float64), 0.0))


@dataclass(frozen=True, slots=True)
class DavisLook:
    """Appearance of the scene as the DAVIS sees it.

    Attributes:
        ambient: Ambient light level (irradiance units).
        diffuse: Directional light level; a surface facing the light gets ``ambient + diffuse``.
        light_dir_world: Unit vector *towards* the light (world), default above, in front of
            and to the right of the actor, so the side of the body facing the DAVIS is lit.
        body_contrast_range: Michelson contrast range of the body texture (20–60 %, §2.3).
        supersample: Sub-samples per pixel side (2 → 4 rays per pixel).
        flicker_hz: Frequency of a sinusoidal light flicker (0 = off, the default).
        flicker_depth: Relative amplitude of the flicker (0–1).
        wall_y_m: The back wall's plane ``y = wall_y_m`` (behind the actor, facing the DAVIS).
    """

    ambient: float = 0.3
    diffuse: float = 0.7
    light_dir_world: tuple[float, float, float] = (0.3, 0.8, 0.52)
    body_contrast_range: tuple[float, float] = (0.2, 0.6)
    supersample: int = 2
    flicker_hz: float = 0.0
    flicker_depth: float = 0.0
    wall_y_m: float = -2.5

    def __post_init__(self) -> None:
        check_range(self.ambient, 0.0, 10.0, name="DavisLook.ambient")
        check_range(self.diffuse, 0.0, 10.0, name="DavisLook.diffuse")
        if self.ambient + self.diffuse <= 0:
            msg = "DavisLook: ambient + diffuse must be > 0 (the scene would be black)"
            raise ValidationError(msg)
        lo, hi = self.body_contrast_range
        if not (0.0 <= lo <= hi < 1.0):
            msg = f"DavisLook.body_contrast_range must satisfy 0 <= lo <= hi < 1, got {lo}, {hi}"
            raise ValidationError(msg)
        if self.supersample not in (1, 2, 3, 4):
            msg = f"DavisLook.supersample must be 1, 2, 3 or 4, got {self.supersample}"
            raise ValidationError(msg)
        check_range(self.flicker_hz, 0.0, 1e4, name="DavisLook.flicker_hz")
        check_range(self.flicker_depth, 0.0, 1.0, name="DavisLook.flicker_depth")
        if float(np.linalg.norm(self.light_dir_world)) <= 0:
            msg = "DavisLook.light_dir_world must be a non-zero vector"
            raise ValidationError(msg)


@dataclass(frozen=True, slots=True, eq=False)
class _Texture:
    """Procedural albedo parameters, one row per textured part (capsules, then clapper arms)."""

    base: F64  # (P,) mean albedo
    contrast: F64  # (P,) Michelson contrast of the pattern
    kind: npt.NDArray[np.int8]  # (P,) 0 = stripes, 1 = checker
    stripe_dir: F64  # (P, 3) unit vector in the part frame (stripes run across it)
    period_m: F64  # (P,) stripe / checker period
    noise_k: F64  # (P, 3, 3) wave vectors (rad/m) of the low-frequency noise
    noise_phase: F64  # (P, 3)


def _soft_square(x: F64) -> F64:
    # A square wave with soft edges (≈ 1/8 of a period wide), so the texture is band-limited
    # enough for 2× supersampling and gives graded edge crossings instead of aliasing.
    out: F64 = np.tanh(3.0 * np.sin(x)) / np.tanh(3.0)
    return out


def _pattern(tex: _Texture, part: npt.NDArray[np.intp], p_local: F64) -> F64:
    """Albedo of points ``p_local`` (N, 3), metres in their part's frame."""
    d = tex.stripe_dir[part]
    per = tex.period_m[part]
    s = _soft_square(2.0 * np.pi * np.einsum("ij,ij->i", p_local, d) / per)
    # The checker multiplies stripes along two axes perpendicular to the stripe direction.
    e1 = np.cross(d, np.array([0.0, 0.0, 1.0]))
    bad = np.linalg.norm(e1, axis=1) < 1e-6
    e1[bad] = np.cross(d[bad], np.array([1.0, 0.0, 0.0]))
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    s2 = _soft_square(2.0 * np.pi * np.einsum("ij,ij->i", p_local, e1) / per)
    pat = np.where(tex.kind[part] == 1, s * s2, s)
    k = tex.noise_k[part]  # (N, 3, 3)
    noise = np.sin(np.einsum("nkj,nj->nk", k, p_local) + tex.noise_phase[part]).mean(axis=1)
    mixed = 0.7 * pat + 0.3 * noise
    out: F64 = tex.base[part] * (1.0 + tex.contrast[part] * mixed)
    return out


def _make_texture(rng: np.random.Generator, look: DavisLook, axes: F64) -> _Texture:
    n = axes.shape[0]
    lo, hi = look.body_contrast_range
    base = np.asarray(rng.uniform(0.35, 0.75, n), dtype=np.float64)
    contrast = np.asarray(rng.uniform(lo, hi, n), dtype=np.float64)
    kind = np.asarray(rng.random(n) < 0.4, dtype=np.int8)
    # Stripes across the segment axis (rings round a limb) or tilted by up to 60°, so both
    # motion along the limb and twist produce texture events.
    rand = rng.normal(size=(n, 3))
    rand -= np.einsum("ij,ij->i", rand, axes)[:, None] * axes
    rand /= np.linalg.norm(rand, axis=1, keepdims=True)
    tilt = np.asarray(rng.uniform(0.0, np.radians(60.0), n))[:, None]
    stripe_dir = np.cos(tilt) * axes + np.sin(tilt) * rand
    period = np.asarray(rng.uniform(0.05, 0.10, n), dtype=np.float64)
    # Low-frequency noise: wavelengths of 15–40 cm in random directions.
    dirs = rng.normal(size=(n, 3, 3))
    dirs /= np.linalg.norm(dirs, axis=2, keepdims=True)
    noise_k = dirs * (2.0 * np.pi / rng.uniform(0.15, 0.40, (n, 3, 1)))
    phase = rng.uniform(0.0, 2.0 * np.pi, (n, 3))
    return _Texture(base, contrast, kind, stripe_dir, period, noise_k, phase)


def _room_albedo(p: F64, on_floor: npt.NDArray[np.bool_]) -> F64:
    """Albedo of room points (N, 3): floor tiles (0.5 m) or a wall checker (0.3 m)."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    floor = 0.35 * (
        1.0
        + 0.3 * _soft_square(np.pi * x / 0.5) * _soft_square(np.pi * y / 0.5)
        + 0.1 * np.sin(2.1 * x + 1.3 * y)
    )
    wall = 0.5 * (
        1.0
        + 0.35 * _soft_square(np.pi * x / 0.3) * _soft_square(np.pi * z / 0.3)
        + 0.15 * np.sin(1.7 * x - 2.3 * z + 0.5)
    )
    out: F64 = np.where(on_floor, floor, wall)
    return out


def _undistort(k_mat: F64, dist: F64, u: F64, v: F64) -> F64:
    """Normalised undistorted coordinates ``(N, 2)`` of distorted pixels (fixed-point iteration).

    Raises:
        ValidationError: the iteration does not reproduce the pixels to 1e-6 px (a lens model
            too strong to invert this way).
    """
    k1, k2, p1, p2, k3 = (float(c) for c in dist)
    xd = (u - k_mat[0, 2]) / k_mat[0, 0]
    yd = (v - k_mat[1, 2]) / k_mat[1, 1]
    x, y = xd.copy(), yd.copy()
    for _ in range(200):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        x, y = (xd - dx) / radial, (yd - dy) / radial
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    ud = k_mat[0, 0] * (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)) + k_mat[0, 2]
    vd = k_mat[1, 1] * (y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y) + k_mat[1, 2]
    err = float(np.max(np.hypot(ud - u, vd - v)))
    if not err < 1e-6:
        msg = f"cannot invert the DAVIS lens distortion (residual {err:.2g} px); check it"
        raise ValidationError(msg)
    return np.stack([x, y], axis=-1)


@dataclass(frozen=True, slots=True, eq=False)
class _Frames:
    """Rigid frames of every textured part at a batch of times."""

    a_m: F64  # (T, P, 3) capsule end points (world)
    b_m: F64
    rot: F64  # (T, P, 3, 3) part frame -> world
    origin_m: F64  # (T, P, 3)


class DavisRenderer:
    """Renders the scenario through the DAVIS's lens (see the module doc).

    The sensor size is the rig's DAVIS camera's: 240×180 (DAVIS240C) or 346×260 (DAVIS346).

    Args:
        scenario: The simulated world.
        look: Appearance settings.

    The texture is drawn from ``scenario.rng("davis-texture")``, so it is fixed by the seed.
    """

    def __init__(self, scenario: Scenario, *, look: DavisLook | None = None) -> None:
        from mocaprig.process.body.surface import capsule_template

        self.scenario = scenario
        self.look = DavisLook() if look is None else look
        cam = scenario.rig.davis.camera
        if (cam.height, cam.width) not in SENSOR_SHAPES:
            msg = (
                f"the DAVIS camera must be 240×180 (DAVIS240C) or 346×260 (DAVIS346), got "
                f"{cam.width}×{cam.height}; fix the rig's DAVIS camera"
            )
            raise ValidationError(msg)
        self.camera = cam
        #: Sensor shape (rows, columns), from the rig's DAVIS camera.
        self.shape: tuple[int, int] = (int(cam.height), int(cam.width))
        self._tmpl = capsule_template(scenario.shape)
        cb = scenario.clapperboard
        self._clap_radius_m = float(cb.arm_thickness_m)
        axes = np.zeros((_NUM_BODY + 2, 3))
        d = self._tmpl.b_local_m - self._tmpl.a_local_m
        nrm = np.linalg.norm(d, axis=1, keepdims=True)
        axes[:_NUM_BODY] = np.where(nrm > 1e-9, d / np.maximum(nrm, 1e-12), [0.0, 0.0, 1.0])
        axes[_NUM_BODY:] = [1.0, 0.0, 0.0]  # clapper arm frames: x along the arm
        tex = _make_texture(scenario.rng("davis-texture"), self.look, axes)
        # The clapperboard: classic black/white stripes along the arm, 5 cm period.
        for i in (_CLAPPER_TOP, _CLAPPER_BOTTOM):
            tex.base[i], tex.contrast[i], tex.kind[i] = 0.5, 0.8, 0
            tex.stripe_dir[i] = [1.0, 0.0, 0.0]
            tex.period_m[i] = 0.05
        self._tex = tex
        self._light = np.asarray(self.look.light_dir_world, dtype=np.float64)
        self._light = self._light / np.linalg.norm(self._light)
        self._radii = np.concatenate(
            [self._tmpl.radius_m, [self._clap_radius_m, self._clap_radius_m]]
        )
        self._setup_canvas()
        self._probe_local = self._probe_points()
        self._cache_key = b""
        self._cache_img = np.zeros(self.shape)
        #: Images actually ray-cast (cache misses), for profiling.
        self.renders = 0

    # ----------------------------------------------------------------------------------------
    # geometry

    def _setup_canvas(self) -> None:
        cam = self.camera
        s = self.look.supersample
        h, w = self.shape
        # Centres of the sub-pixels in sensor pixel coordinates ((0, 0) = centre of pixel 0).
        us = (np.arange(w * s) + 0.5) / s - 0.5
        vs = (np.arange(h * s) + 0.5) / s - 0.5
        uu, vv = np.meshgrid(us, vs)
        und = _undistort(cam.K, cam.distortion, uu.ravel(), vv.ravel())
        # Canvas: an undistorted pinhole with s× the focal length, just large enough.
        f = cam.fx * s, cam.fy * s
        cu, cv_ = und[:, 0] * f[0], und[:, 1] * f[1]
        margin = 2.0
        u0, v0 = float(cu.min()) - margin, float(cv_.min()) - margin
        self._canvas_w = int(np.ceil(float(cu.max()) - u0 + margin)) + 1
        self._canvas_h = int(np.ceil(float(cv_.max()) - v0 + margin)) + 1
        self._canvas_K = np.array([[f[0], 0.0, -u0], [0.0, f[1], -v0], [0.0, 0.0, 1.0]])
        self._map_x = (cu - u0).reshape(h * s, w * s).astype(np.float32)
        self._map_y = (cv_ - v0).reshape(h * s, w * s).astype(np.float32)
        # Camera-frame rays (z = 1) of every canvas pixel.
        kin = np.linalg.inv(self._canvas_K)
        cu_g, cv_g = np.meshgrid(
            np.arange(self._canvas_w, dtype=np.float64),
            np.arange(self._canvas_h, dtype=np.float64),
        )
        self._rays_cam = np.stack([cu_g, cv_g, np.ones_like(cu_g)], axis=-1) @ kin.T
        self._background = self._render_room()

    def _render_room(self) -> F64:
        """Irradiance of the static room on the canvas (the camera is static)."""
        r_wc = self.camera.T_world_cam[:3, :3]
        c = self.camera.T_world_cam[:3, 3]
        d = self._rays_cam.reshape(-1, 3) @ r_wc.T
        with np.errstate(divide="ignore", invalid="ignore"):
            t_floor = np.where(d[:, 2] < -1e-9, -c[2] / d[:, 2], np.inf)
            t_wall = np.where(d[:, 1] < -1e-9, (self.look.wall_y_m - c[1]) / d[:, 1], np.inf)
        on_floor = t_floor < t_wall
        t = np.minimum(t_floor, t_wall)
        hit = np.isfinite(t)
        p = c + np.where(hit, t, 0.0)[:, None] * d
        alb = _room_albedo(p, on_floor)
        n_floor, n_wall = np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0])
        lam = np.where(
            on_floor, max(float(n_floor @ self._light), 0.0), max(float(n_wall @ self._light), 0.0)
        )
        img = alb * (self.look.ambient + self.look.diffuse * lam)
        # Rays that hit neither plane (none in the default rig) see a dim ceiling.
        img = np.where(hit, img, 0.1 * self.look.ambient)
        out: F64 = img.reshape(self._canvas_h, self._canvas_w)
        return out

    def _probe_points(self) -> F64:
        """Surface points of every part (part frame), used to bound the image motion."""
        pts = np.zeros((_NUM_BODY + 2, 14, 3))
        ca, cb = self._clapper_local()
        a = np.concatenate([self._tmpl.a_local_m, ca])
        b = np.concatenate([self._tmpl.b_local_m, cb])
        r = self._radii
        for i in range(a.shape[0]):
            ax = b[i] - a[i]
            n = float(np.linalg.norm(ax))
            ax = ax / n if n > 1e-9 else np.array([0.0, 0.0, 1.0])
            e1 = np.cross(ax, [0.0, 0.0, 1.0])
            if np.linalg.norm(e1) < 1e-6:
                e1 = np.cross(ax, [1.0, 0.0, 0.0])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(ax, e1)
            rows = [a[i] - r[i] * ax, b[i] + r[i] * ax]
            for c in (a[i], 0.5 * (a[i] + b[i]), b[i]):
                rows += [c + r[i] * e1, c - r[i] * e1, c + r[i] * e2, c - r[i] * e2]
            pts[i] = rows
        return pts

    def _clapper_local(self) -> tuple[F64, F64]:
        """Arm rods in their arm frames (x along the arm from the hinge, z the arm's normal)."""
        # From 1 cm off the hinge to 3 cm past the marker (the board's end).
        length = self.scenario.clapperboard.arm_length_m + 0.03
        a = np.array([[0.01, 0.0, 0.0], [0.01, 0.0, 0.0]])
        b = np.array([[length, 0.0, 0.0], [length, 0.0, 0.0]])
        return a, b

    def frames(self, t_ns: npt.ArrayLike) -> _Frames:
        """Rigid frames and capsule end points of all parts at session times (1-D int ns)."""
        from mocaprig.process.body.kinematics import forward_kinematics

        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        kin = forward_kinematics(self.scenario.pose(t), self.scenario.shape)
        j = self._tmpl.joint
        rot_b = kin.rotations[:, j]
        org_b = kin.positions_m[:, j]
        cb = self.scenario.clapperboard
        theta = cb.angle_rad(t)
        u = np.array([np.cos(cb.yaw_rad), np.sin(cb.yaw_rad), 0.0])
        z = np.array([0.0, 0.0, 1.0])
        hinge_axis = np.cross(z, u)
        c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
        # Top arm: x = the arm direction rotated up by θ about the hinge, z its upper normal.
        x_top = c * u + s * z
        z_top = -s * u + c * z
        rot_top = np.stack([x_top, np.broadcast_to(hinge_axis, x_top.shape), z_top], axis=-1)
        rot_bot = np.broadcast_to(np.stack([u, hinge_axis, z], axis=-1), rot_top.shape)
        # Arm frames sit half a board thickness above / below the hinge line.
        org_top = cb.hinge_m + 0.5 * cb.arm_thickness_m * z_top
        org_bot = np.broadcast_to(cb.hinge_m - 0.5 * cb.arm_thickness_m * z, org_top.shape)
        rot = np.concatenate([rot_b, rot_top[:, None], rot_bot[:, None]], axis=1)
        org = np.concatenate([org_b, org_top[:, None], org_bot[:, None]], axis=1)
        ca, cb_ = self._clapper_local()
        a_l = np.concatenate([self._tmpl.a_local_m, ca])
        b_l = np.concatenate([self._tmpl.b_local_m, cb_])
        a = org + np.einsum("tpij,pj->tpi", rot, a_l)
        b = org + np.einsum("tpij,pj->tpi", rot, b_l)
        return _Frames(a, b, rot, org)

    def max_motion_px(self, t_ns: npt.ArrayLike) -> F64:
        """Largest image displacement (px) of any probed surface point between consecutive times.

        Args:
            t_ns: Session times (1-D int ns, increasing), ``T >= 2``.

        Returns:
            ``(T - 1,)`` displacements in DAVIS pixels.
        """
        fr = self.frames(t_ns)
        pw = fr.origin_m[:, :, None, :] + np.einsum("tpij,pkj->tpki", fr.rot, self._probe_local)
        uv, z = project(self.camera, pw)
        uv = np.where((z > 0.05)[..., None], uv, 0.0)
        d = np.linalg.norm(np.diff(uv, axis=0), axis=-1)
        out: F64 = np.nan_to_num(d, nan=0.0).reshape(d.shape[0], -1).max(axis=1)
        return out

    # ----------------------------------------------------------------------------------------
    # rendering

    def _flicker(self, t_ns: int) -> float:
        if self.look.flicker_hz <= 0 or self.look.flicker_depth <= 0:
            return 1.0
        ph = 2.0 * np.pi * self.look.flicker_hz * (t_ns * 1e-9)
        return float(1.0 + self.look.flicker_depth * np.sin(ph))

    def render_batch(self, t_ns: npt.ArrayLike) -> F64:
        """Linear irradiance ``(T, H, W)`` (sensor rows, columns) at session times (1-D int ns)."""
        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        fr = self.frames(t)
        out = np.empty((t.shape[0], *self.shape))
        for i in range(t.shape[0]):
            # The room and the camera are static: identical part poses give the identical
            # image, so a still actor (every scenario's static start) costs no ray casting.
            key = fr.rot[i].tobytes() + fr.origin_m[i].tobytes()
            if key != self._cache_key:
                self._cache_img = self._render_one(fr, i)
                self._cache_key = key
                self.renders += 1
            out[i] = self._cache_img * self._flicker(int(t[i]))
        return out

    def render(self, t_ns: int) -> F64:
        """Linear irradiance ``(H, W)`` at one session time (int ns); row 0 = top."""
        out: F64 = self.render_batch(np.array([int(t_ns)]))[0]
        return out

    def _render_one(self, fr: _Frames, i: int) -> F64:
        from mocaprig.process.body.surface import Capsules, render_pinhole

        n_parts = self._radii.shape[0]
        caps = Capsules(
            a_m=fr.a_m[i], b_m=fr.b_m[i], radius_m=self._radii, joint=np.arange(n_parts)
        )
        res = render_pinhole(
            caps, self._canvas_K, self.camera.T_cam_world, self._canvas_w, self._canvas_h
        )
        canvas = self._background.copy()
        hv, hu = np.nonzero(res.segment >= 0)
        if hv.size:
            part = res.segment[hv, hu].astype(np.intp)
            r_wc = self.camera.T_world_cam[:3, :3]
            p_cam = self._rays_cam[hv, hu] * res.depth_m[hv, hu, None]
            p_w = p_cam @ r_wc.T + self.camera.T_world_cam[:3, 3]
            rel = p_w - fr.origin_m[i, part]
            p_loc = np.einsum("nji,nj->ni", fr.rot[i, part], rel)
            alb = _pattern(self._tex, part, p_loc)
            n_w = res.normals_cam[hv, hu] @ r_wc.T
            lam = np.maximum(n_w @ self._light, 0.0)
            canvas[hv, hu] = alb * (self.look.ambient + self.look.diffuse * lam)
        fine = cv2.remap(
            canvas.astype(np.float32),
            self._map_x,
            self._map_y,
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        s = self.look.supersample
        h, w = self.shape
        out: F64 = fine.reshape(h, s, w, s).mean(axis=(1, 3), dtype=np.float64)
        return out

    def edge_map(self, t_ns: int, *, threshold: float = 0.05) -> npt.NDArray[np.bool_]:
        """True intensity edges at a session time: ``|∇ log(eps + I)| > threshold`` per pixel.

        The gradient is the central difference of :func:`log_intensity` of :meth:`render`
        (one-sided at the border), in log units per pixel. The default, 0.05 ln/px, is a
        quarter of the nominal contrast threshold: an edge that moves by ≤ 4 px produces at
        least one event.
        """
        check_positive(float(threshold), name="threshold")
        lg = log_intensity(self.render(int(t_ns)))
        gy, gx = np.gradient(lg)
        out: npt.NDArray[np.bool_] = np.hypot(gx, gy) > threshold
        return out
