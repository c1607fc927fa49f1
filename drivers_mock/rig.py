"""The simulated rig: camera models, device specifications and the default layout.

Frames and conventions
======================

World: right-handed, Z up, metres; the actor stands near the origin and faces +Y at zero root
rotation (as :mod:`mocaprig.process.body.skeleton`).

Camera: the OpenCV convention, +Z forward (optical axis), +X right, +Y down in the image.
``T_world_cam`` (4×4) maps camera coordinates to world coordinates::

    X_world = R_world_cam @ X_cam + t_world_cam          (T_world_cam = [[R, t], [0, 1]])
    X_cam   = R_world_cam.T @ (X_world - t_world_cam)

so ``t_world_cam`` is the camera centre in the world. A point ``X_cam = (x, y, z)`` with
``z > 0`` projects as in ``cv2.projectPoints`` (Brown–Conrady, coefficients
``(k1, k2, p1, p2, k3)``)::

    a = x / z, b = y / z, r² = a² + b²
    a' = a (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 a b + p2 (r² + 2 a²)
    b' = b (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2 b²) + 2 p2 a b
    u = fx a' + cx,  v = fy b' + cy

Pixel ``(0, 0)`` is the centre of the top-left pixel (OpenCV). Depth is ``z`` in metres.

Device numbers come from the specifications (``../shared/docs``), never from a driver's
constants: D415 IR/depth at 848×480 (fx ≈ 623 px, 55 mm baseline, depth scale 1 mm, 30 Hz),
DAVIS240C 240×180 with 18.5 µm pixels behind a 4.5 mm lens (≈ 53°×41°), Vicon at 120 Hz.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt

from mocaprig.errors import ValidationError
from mocaprig.validation import check_finite, check_shape

__all__ = [
    "D415Spec",
    "D415Timing",
    "DavisSpec",
    "PinholeCamera",
    "Rig",
    "SyncRole",
    "ViconSpec",
    "default_rig",
    "look_at",
    "project",
]

_log = logging.getLogger(__name__)

SyncRole = Literal["master", "slave"]

PulseAt = Literal["exposure-start", "readout-start"]

F64 = npt.NDArray[np.float64]


def _frozen_array(x: npt.ArrayLike, shape: list[int | str], name: str) -> F64:
    arr = np.array(check_finite(check_shape(x, shape, name=name), name=name), dtype=np.float64)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, slots=True, eq=False)
class PinholeCamera:
    """A calibrated pinhole camera with Brown–Conrady distortion (OpenCV convention).

    Attributes:
        name: Stream or device label, e.g. ``"d415-0/ir1"``.
        width: Image width (px).
        height: Image height (px).
        K: Intrinsic matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (px), shape ``(3, 3)``.
        distortion: ``(k1, k2, p1, p2, k3)``, shape ``(5,)`` (zeros for rectified streams).
        T_world_cam: Camera-to-world rigid transform, shape ``(4, 4)`` (see the module doc).

    Raises:
        ValidationError: wrong shapes, non-finite values or a non-rigid ``T_world_cam``.
    """

    name: str
    width: int
    height: int
    K: F64 = field(repr=False)
    distortion: F64 = field(repr=False)
    T_world_cam: F64 = field(repr=False)

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            msg = (
                f"camera {self.name!r}: image size must be positive, got {self.width}×{self.height}"
            )
            raise ValidationError(msg)
        k = _frozen_array(self.K, [3, 3], f"camera {self.name!r} K")
        if k[0, 0] <= 0 or k[1, 1] <= 0 or not np.allclose(k[2], [0.0, 0.0, 1.0]):
            msg = f"camera {self.name!r}: K must have fx, fy > 0 and last row (0, 0, 1)"
            raise ValidationError(msg)
        dist = _frozen_array(self.distortion, [5], f"camera {self.name!r} distortion")
        t = _frozen_array(self.T_world_cam, [4, 4], f"camera {self.name!r} T_world_cam")
        r = t[:3, :3]
        if not (np.allclose(r.T @ r, np.eye(3), atol=1e-9) and np.linalg.det(r) > 0):
            msg = f"camera {self.name!r}: T_world_cam's rotation block is not a proper rotation"
            raise ValidationError(msg)
        if not np.allclose(t[3], [0.0, 0.0, 0.0, 1.0]):
            msg = f"camera {self.name!r}: T_world_cam's last row must be (0, 0, 0, 1)"
            raise ValidationError(msg)
        object.__setattr__(self, "K", k)
        object.__setattr__(self, "distortion", dist)
        object.__setattr__(self, "T_world_cam", t)

    @property
    def fx(self) -> float:
        """Focal length along x (px)."""
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        """Focal length along y (px)."""
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        """Principal point x (px)."""
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        """Principal point y (px)."""
        return float(self.K[1, 2])

    @property
    def center_m(self) -> F64:
        """Camera centre in the world (m), shape ``(3,)``."""
        return np.array(self.T_world_cam[:3, 3])

    @property
    def T_cam_world(self) -> F64:
        """World-to-camera transform, the inverse of ``T_world_cam``, shape ``(4, 4)``."""
        r = self.T_world_cam[:3, :3]
        out = np.eye(4)
        out[:3, :3] = r.T
        out[:3, 3] = -r.T @ self.T_world_cam[:3, 3]
        return out

    @property
    def fov_deg(self) -> tuple[float, float]:
        """Horizontal and vertical field of view of the pinhole (deg, distortion ignored)."""
        h = 2.0 * np.degrees(np.arctan2(self.width / 2.0, self.fx))
        v = 2.0 * np.degrees(np.arctan2(self.height / 2.0, self.fy))
        return float(h), float(v)

    def with_pose(self, T_world_cam: npt.ArrayLike, *, name: str | None = None) -> PinholeCamera:
        """The same intrinsics at another pose."""
        return PinholeCamera(
            self.name if name is None else name,
            self.width,
            self.height,
            self.K,
            self.distortion,
            np.asarray(T_world_cam, dtype=np.float64),
        )

    def to_dict(self) -> dict[str, object]:
        """A JSON-ready description (lists of floats)."""
        return {
            "name": self.name,
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "distortion": self.distortion.tolist(),
            "T_world_cam": self.T_world_cam.tolist(),
        }


def look_at(eye: npt.ArrayLike, target: npt.ArrayLike, up: npt.ArrayLike = (0.0, 0.0, 1.0)) -> F64:
    """The camera-to-world transform of an OpenCV camera at ``eye`` looking at ``target``.

    The camera's +Z points from ``eye`` to ``target``, +X is ``forward × up`` (to the right in
    the image) and +Y = Z × X points down in the image (along ``-up`` as far as possible).

    Args:
        eye: Camera centre (m), shape ``(3,)``.
        target: A point on the optical axis (m), shape ``(3,)``.
        up: The world's up direction, shape ``(3,)``; must not be parallel to the view.

    Returns:
        ``T_world_cam``, shape ``(4, 4)``.

    Raises:
        ValidationError: ``eye == target`` or ``up`` parallel to the viewing direction.
    """
    e = np.asarray(check_finite(check_shape(eye, [3], name="eye"), name="eye"), dtype=np.float64)
    t = np.asarray(check_finite(check_shape(target, [3], name="target"), name="target"), float)
    u = np.asarray(check_finite(check_shape(up, [3], name="up"), name="up"), dtype=np.float64)
    z = t - e
    nz = np.linalg.norm(z)
    if nz < 1e-12:
        msg = "look_at(): eye and target coincide; give a target away from the camera centre"
        raise ValidationError(msg)
    z = z / nz
    x = np.cross(z, u)
    nx = np.linalg.norm(x)
    if nx < 1e-9:
        msg = "look_at(): 'up' is parallel to the viewing direction; choose another up vector"
        raise ValidationError(msg)
    x = x / nx
    y = np.cross(z, x)
    out = np.eye(4)
    out[:3, 0], out[:3, 1], out[:3, 2], out[:3, 3] = x, y, z, e
    return out


def project(camera: PinholeCamera, points_world: npt.ArrayLike) -> tuple[F64, F64]:
    """Project world points into a camera (the equations of the module doc).

    Args:
        camera: The camera.
        points_world: Points (m), shape ``(..., 3)``.

    Returns:
        ``(pixels, depth)``: pixel coordinates ``(..., 2)`` (NaN for points at or behind the
        camera, ``z <= 1e-9``) and camera-frame depth ``z`` (m), shape ``(...)``.
    """
    p = np.asarray(check_shape(points_world, ["...", 3], name="points_world"), dtype=np.float64)
    t = camera.T_cam_world
    pc = p @ t[:3, :3].T + t[:3, 3]
    z = pc[..., 2]
    ok = z > 1e-9
    safe_z = np.where(ok, z, 1.0)
    a = pc[..., 0] / safe_z
    b = pc[..., 1] / safe_z
    k1, k2, p1, p2, k3 = camera.distortion
    r2 = a * a + b * b
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    ad = a * radial + 2.0 * p1 * a * b + p2 * (r2 + 2.0 * a * a)
    bd = b * radial + p1 * (r2 + 2.0 * b * b) + 2.0 * p2 * a * b
    uv = np.stack([camera.fx * ad + camera.cx, camera.fy * bd + camera.cy], axis=-1)
    uv[~ok] = np.nan
    return uv, z


# --------------------------------------------------------------------------------------------
# Device specifications
# --------------------------------------------------------------------------------------------

#: D415 IR/depth at 848×480: the 1280×720 example unit (fx = 940.92, ppx = 636.45,
#: ppy = 359.39) scaled by 0.6625 (realsense-d415.md §1.4). Streams are rectified: zero distortion.
D415_WIDTH = 848
D415_HEIGHT = 480
D415_FX_PX = 940.92 * 0.6625
D415_CX_PX = 636.45 * 0.6625
D415_CY_PX = 359.39 * 0.6625


@dataclass(frozen=True, slots=True, eq=False)
class D415Spec:
    """One RealSense D415 streaming left IR (Y8) and depth (Z16) at 848×480.

    Depth is computed in the left imager's frame, so ``ir_left`` is also the depth camera
    (same intrinsics and pose). The right imager sits ``baseline_m`` along the left camera's +X.

    Attributes:
        name: Rig label, e.g. ``"d415-0"``.
        serial: The 12-digit serial number string.
        role: ``"master"`` (``inter_cam_sync_mode`` 1) or ``"slave"`` (mode 2).
        ir_left: The left IR / depth camera.
        depth_scale_m: Metres per Z16 unit (0.001).
        baseline_m: Stereo baseline (m), ≈ 0.055.
        rate_hz: Frame rate (30).
        firmware: Firmware version string reported by the device.
    """

    name: str
    serial: str
    role: SyncRole
    ir_left: PinholeCamera
    depth_scale_m: float = 0.001
    baseline_m: float = 0.055
    rate_hz: float = 30.0
    firmware: str = "5.16.0.1"

    def __post_init__(self) -> None:
        if len(self.serial) != 12 or not self.serial.isdigit():
            msg = f"D415 {self.name!r}: serial must be a 12-digit string, got {self.serial!r}"
            raise ValidationError(msg)
        if self.role not in ("master", "slave"):
            msg = f"D415 {self.name!r}: role must be 'master' or 'slave', got {self.role!r}"
            raise ValidationError(msg)

    @property
    def sync_mode(self) -> int:
        """``inter_cam_sync_mode``: 1 for the master, 2 for a slave."""
        return 1 if self.role == "master" else 2

    @property
    def depth(self) -> PinholeCamera:
        """The depth stream's camera (identical to ``ir_left``)."""
        return self.ir_left

    @property
    def ir_right(self) -> PinholeCamera:
        """The right imager: ``ir_left`` shifted by ``baseline_m`` along its own +X."""
        shift = np.eye(4)
        shift[0, 3] = self.baseline_m
        return self.ir_left.with_pose(self.ir_left.T_world_cam @ shift, name=f"{self.name}/ir2")

    def to_dict(self) -> dict[str, object]:
        """A JSON-ready description."""
        return {
            "name": self.name,
            "model": "Intel RealSense D415",
            "serial": self.serial,
            "role": self.role,
            "inter_cam_sync_mode": self.sync_mode,
            "firmware": self.firmware,
            "depth_scale_m": self.depth_scale_m,
            "baseline_m": self.baseline_m,
            "rate_hz": self.rate_hz,
            "ir_left": self.ir_left.to_dict(),
        }


@dataclass(frozen=True, slots=True)
class D415Timing:
    """D415 sync timing the specifications leave open: parameters of the world, not facts.

    Nothing here is documented for the D415 itself (realsense-d415.md §2.2, §6;
    docs/d415-timing.md). Two published readings exist; both are available as presets:

    * :meth:`exposure_start` (the default, what the calibration assumes today): the master's
      pin-5 pulse marks its exposure start and a slave starts exposing 100 µs after the edge;
    * :meth:`readout_start` (Intel's answers for the D4xx family, librealsense #8470, #3570,
      #10998, #9220): the frame timestamp is taken at readout start and the pulse follows it,
      i.e. the edge comes at the end of the master's exposure, and trigger-to-exposure is
      ≈ 0.77 ms.

    The estimators (sync check, calibration) are never told these values.

    Attributes:
        pulse_at: Where the master's pulse falls: its ``"exposure-start"`` or its
            ``"readout-start"`` (= end of its exposure).
        trigger_to_exposure_us: A slave's exposure starts this long after the trigger edge.
        free_run_period_ppm: A self-timed camera (master, mode 0, a slave without trigger)
            captures every ``(1 + ppm·1e-6)/fps`` seconds **of its own clock**; 0 is the premise
            of Intel's "unsynced timestamps keep a constant difference".
        free_run_period_spread_ppm: Unit-to-unit spread (σ) of that period error.
        global_time_ready_s: ``global_time_enabled``: frames switch from ``hardware_clock`` to
            ``global_time`` this long after the stream starts (the keeper's 15 samples at
            100 ms, realsense-d415.md §2.7).
        global_time_offset_us: σ of each camera's constant global-time offset error (the
            keeper's half round-trip estimate).
        global_time_rate_ppm: σ of each camera's residual global-time rate error.
        global_time_jitter_us: σ of the per-frame global-time jitter.
    """

    pulse_at: PulseAt = "exposure-start"
    trigger_to_exposure_us: float = 100.0
    free_run_period_ppm: float = 0.0
    free_run_period_spread_ppm: float = 0.0
    global_time_ready_s: float = 1.5
    global_time_offset_us: float = 150.0
    global_time_rate_ppm: float = 0.1
    global_time_jitter_us: float = 10.0

    def __post_init__(self) -> None:
        if self.pulse_at not in ("exposure-start", "readout-start"):
            msg = (
                f"D415Timing.pulse_at must be 'exposure-start' or 'readout-start', "
                f"got {self.pulse_at!r}"
            )
            raise ValidationError(msg)
        values = (
            self.trigger_to_exposure_us,
            self.free_run_period_spread_ppm,
            self.global_time_ready_s,
            self.global_time_offset_us,
            self.global_time_rate_ppm,
            self.global_time_jitter_us,
        )
        if not all(np.isfinite(v) and v >= 0 for v in values):
            msg = "D415Timing: delays, spreads and the global-time ready time must be >= 0"
            raise ValidationError(msg)
        if not (np.isfinite(self.free_run_period_ppm) and abs(self.free_run_period_ppm) < 1e3):
            msg = "D415Timing.free_run_period_ppm must be finite and below 1000 in magnitude"
            raise ValidationError(msg)

    @classmethod
    def exposure_start(cls) -> D415Timing:
        """Pulse at the master's exposure start, slaves 0.1 ms after the edge (the default)."""
        return cls()

    @classmethod
    def readout_start(cls) -> D415Timing:
        """Pulse at the master's readout start (end of exposure), trigger-to-exposure 0.77 ms."""
        return cls(pulse_at="readout-start", trigger_to_exposure_us=770.0)

    def to_dict(self) -> dict[str, object]:
        """A JSON-ready description."""
        return {
            "pulse_at": self.pulse_at,
            "trigger_to_exposure_us": self.trigger_to_exposure_us,
            "free_run_period_ppm": self.free_run_period_ppm,
            "free_run_period_spread_ppm": self.free_run_period_spread_ppm,
            "global_time_ready_s": self.global_time_ready_s,
            "global_time_offset_us": self.global_time_offset_us,
            "global_time_rate_ppm": self.global_time_rate_ppm,
            "global_time_jitter_us": self.global_time_jitter_us,
        }


#: DAVIS240C: 240×180 pixels of 18.5 µm (eventcap-method.md §4.3).
DAVIS_WIDTH = 240
DAVIS_HEIGHT = 180
DAVIS_PIXEL_PITCH_UM = 18.5


@dataclass(frozen=True, slots=True, eq=False)
class DavisSpec:
    """The DAVIS240C event camera and its lens.

    Attributes:
        name: Rig label (``"davis"``).
        serial: The 8-character serial string (as libcaer reports it).
        camera: Its pinhole model (240×180, fx = focal_length_mm / pixel pitch).
        focal_length_mm: Lens focal length (mm); 4.5 mm gives ≈ 52.5°×40.6°.
        pixel_pitch_um: 18.5 µm.
    """

    name: str
    serial: str
    camera: PinholeCamera
    focal_length_mm: float
    pixel_pitch_um: float = DAVIS_PIXEL_PITCH_UM

    def to_dict(self) -> dict[str, object]:
        """A JSON-ready description."""
        return {
            "name": self.name,
            "model": "DAVIS240C",
            "serial": self.serial,
            "focal_length_mm": self.focal_length_mm,
            "pixel_pitch_um": self.pixel_pitch_um,
            "camera": self.camera.to_dict(),
        }


@dataclass(frozen=True, slots=True, eq=False)
class ViconSpec:
    """The Vicon reference system.

    Attributes:
        rate_hz: Frame rate (120 Hz).
        volume_min_m: Lower corner of the calibrated capture volume (m), shape ``(3,)``.
        volume_max_m: Upper corner (m), shape ``(3,)``.
        noise_sigma_m: Per-axis Gaussian noise of a reconstructed marker (m), 0.5 mm.
        residual_mean_mm: Mean reconstruction residual written to the C3D (mm).
        residual_sd_mm: Its spread (mm).
        camera_positions_m: The Vicon cameras' centres (m), shape ``(C, 3)``; used only by
            the occlusion heuristic (a marker facing few cameras drops out more often).
        subject: Subject name, the C3D label prefix (``"<subject>:<MARKER>"``).
    """

    rate_hz: float = 120.0
    volume_min_m: F64 = field(default_factory=lambda: np.array([-3.0, -3.0, 0.0]), repr=False)
    volume_max_m: F64 = field(default_factory=lambda: np.array([3.0, 3.0, 2.5]), repr=False)
    noise_sigma_m: float = 0.0005
    residual_mean_mm: float = 0.8
    residual_sd_mm: float = 0.3
    camera_positions_m: F64 = field(default_factory=lambda: _vicon_ring(10), repr=False)
    subject: str = "actor"

    def __post_init__(self) -> None:
        lo = _frozen_array(self.volume_min_m, [3], "ViconSpec.volume_min_m")
        hi = _frozen_array(self.volume_max_m, [3], "ViconSpec.volume_max_m")
        if not np.all(hi > lo):
            msg = "ViconSpec: volume_max_m must exceed volume_min_m on every axis"
            raise ValidationError(msg)
        cams = _frozen_array(self.camera_positions_m, ["C", 3], "ViconSpec.camera_positions_m")
        if self.rate_hz <= 0 or self.noise_sigma_m < 0:
            msg = "ViconSpec: rate_hz must be > 0 and noise_sigma_m >= 0"
            raise ValidationError(msg)
        object.__setattr__(self, "volume_min_m", lo)
        object.__setattr__(self, "volume_max_m", hi)
        object.__setattr__(self, "camera_positions_m", cams)

    def to_dict(self) -> dict[str, object]:
        """A JSON-ready description."""
        return {
            "rate_hz": self.rate_hz,
            "volume_min_m": np.asarray(self.volume_min_m).tolist(),
            "volume_max_m": np.asarray(self.volume_max_m).tolist(),
            "noise_sigma_m": self.noise_sigma_m,
            "residual_mean_mm": self.residual_mean_mm,
            "residual_sd_mm": self.residual_sd_mm,
            "camera_positions_m": np.asarray(self.camera_positions_m).tolist(),
            "subject": self.subject,
        }


def _vicon_ring(n: int, *, radius_m: float = 4.0, height_m: float = 2.6) -> F64:
    az = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False) + np.pi / n
    return np.stack([radius_m * np.cos(az), radius_m * np.sin(az), np.full(n, height_m)], axis=1)


@dataclass(frozen=True, slots=True, eq=False)
class Rig:
    """Every device of the simulated rig.

    Attributes:
        d415: The depth cameras, master first.
        davis: The event camera.
        vicon: The reference system.
        d415_timing: The D415s' undocumented sync timing (:class:`D415Timing`).
    """

    d415: tuple[D415Spec, ...]
    davis: DavisSpec
    vicon: ViconSpec
    d415_timing: D415Timing = D415Timing()

    @property
    def cameras(self) -> dict[str, PinholeCamera]:
        """Every imaging camera by name: ``"<d415 name>"`` (left IR = depth) and ``"davis"``."""
        out = {d.name: d.ir_left for d in self.d415}
        out[self.davis.name] = self.davis.camera
        return out

    def camera(self, name: str) -> PinholeCamera:
        """One camera by name.

        Raises:
            ValidationError: no camera of that name (the message lists the names).
        """
        cams = self.cameras
        if name not in cams:
            msg = f"the rig has no camera {name!r}; it has {sorted(cams)}"
            raise ValidationError(msg)
        return cams[name]

    def to_dict(self) -> dict[str, object]:
        """A JSON-ready description."""
        return {
            "d415": [d.to_dict() for d in self.d415],
            "davis": self.davis.to_dict(),
            "vicon": self.vicon.to_dict(),
            "d415_timing": self.d415_timing.to_dict(),
        }


def _d415_serial(rng: np.random.Generator) -> str:
    # Observed D415 serials are 12 digits and start with 8 (e.g. 819312070311).
    return "8" + "".join(str(d) for d in rng.integers(0, 10, size=11))


def default_rig(
    rng: np.random.Generator,
    *,
    num_d415: int = 4,
    radius_m: float = 2.5,
    d415_height_m: float = 1.4,
) -> Rig:
    """The default rig with small seeded perturbations.

    * ``num_d415`` D415 on a circle of ``radius_m`` around the origin at chest height, at
      azimuths 45° + k·360°/n (a cross, as in DeMoCap; none sits in front of the actor, where the
      DAVIS is), each aimed at (0, 0, 0.9 m) — slightly down. 2.5 m rather than 2 m because the
      D415's 42° vertical FOV needs ≈ 2.4 m to frame a 1.8 m actor head to toe; the capture area
      inside the circle is still ≈ 4 m across. The first D415 is the sync master.
    * The DAVIS240C 3 m in front of the actor (+Y) at 1.2 m, aimed at (0, 0, 0.95 m), 4.5 mm lens.
    * Per seed: each camera's position jitters by ≈ 5 cm, its aim by ≈ 5 cm, roll by ≈ 1°,
      D415 focal lengths by ≈ 0.5 % and principal points by ≈ 2 px; the DAVIS has a mild
      barrel distortion (k1 ≈ −0.25).

    Args:
        rng: The seeded generator (consumed).
        num_d415: Number of D415 (≥ 1).
        radius_m: Circle radius (m).
        d415_height_m: Camera height (m).

    Raises:
        ValidationError: ``num_d415 < 1`` or a non-positive radius/height.
    """
    if num_d415 < 1:
        msg = f"default_rig(): num_d415 must be >= 1, got {num_d415}"
        raise ValidationError(msg)
    if not (radius_m > 0 and d415_height_m > 0):
        msg = "default_rig(): radius_m and d415_height_m must be > 0"
        raise ValidationError(msg)
    d415s: list[D415Spec] = []
    serials: set[str] = set()
    for i in range(num_d415):
        az = np.radians(45.0 + 360.0 * i / num_d415 + rng.normal(0.0, 3.0))
        r = radius_m + rng.normal(0.0, 0.05)
        eye = np.array([r * np.cos(az), r * np.sin(az), d415_height_m + rng.normal(0.0, 0.03)])
        target = np.array([0.0, 0.0, 0.9]) + rng.normal(0.0, 0.05, size=3)
        pose = _with_roll(look_at(eye, target), np.radians(rng.normal(0.0, 1.0)))
        f = D415_FX_PX * (1.0 + rng.normal(0.0, 0.005))
        k = np.array(
            [
                [f, 0.0, D415_CX_PX + rng.normal(0.0, 2.0)],
                [0.0, f, D415_CY_PX + rng.normal(0.0, 2.0)],
                [0.0, 0.0, 1.0],
            ]
        )
        serial = _d415_serial(rng)
        while serial in serials:
            serial = _d415_serial(rng)
        serials.add(serial)
        name = f"d415-{i}"
        cam = PinholeCamera(f"{name}/ir1", D415_WIDTH, D415_HEIGHT, k, np.zeros(5), pose)
        baseline = 0.055 + rng.normal(0.0, 0.0002)
        d415s.append(
            D415Spec(name, serial, "master" if i == 0 else "slave", cam, baseline_m=baseline)
        )
    focal_mm = 4.5
    f_px = focal_mm * 1000.0 / DAVIS_PIXEL_PITCH_UM * (1.0 + rng.normal(0.0, 0.01))
    k_davis = np.array(
        [
            [f_px, 0.0, DAVIS_WIDTH / 2.0 + rng.normal(0.0, 2.0)],
            [0.0, f_px, DAVIS_HEIGHT / 2.0 + rng.normal(0.0, 2.0)],
            [0.0, 0.0, 1.0],
        ]
    )
    dist = np.array(
        [
            -0.25 + rng.normal(0.0, 0.02),
            0.08 + rng.normal(0.0, 0.01),
            rng.normal(0.0, 3e-4),
            rng.normal(0.0, 3e-4),
            0.0,
        ]
    )
    eye = np.array([0.0, 3.0, 1.2]) + rng.normal(0.0, 0.05, size=3)
    target = np.array([0.0, 0.0, 0.95]) + rng.normal(0.0, 0.03, size=3)
    pose = _with_roll(look_at(eye, target), np.radians(rng.normal(0.0, 1.0)))
    davis_serial = f"0246{int(rng.integers(0, 10_000)):04d}"
    davis = DavisSpec(
        "davis",
        davis_serial,
        PinholeCamera("davis", DAVIS_WIDTH, DAVIS_HEIGHT, k_davis, dist, pose),
        focal_mm,
    )
    _log.debug("default rig: %d D415, DAVIS serial %s", num_d415, davis_serial)
    return Rig(tuple(d415s), davis, ViconSpec())


def _with_roll(T_world_cam: F64, roll_rad: float) -> F64:
    c, s = np.cos(roll_rad), np.sin(roll_rad)
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out = np.array(T_world_cam)
    out[:3, :3] = T_world_cam[:3, :3] @ rz
    return out
