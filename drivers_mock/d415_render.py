"""D415 image formation: the simulated world seen by one D415's left imager (IR Y8 + depth Z16).

Everything follows realsense-d415.md ("the note"); model values cite its sections.

Scene
=====

* the actor's 22 body capsules (:func:`mocaprig.process.body.surface.capsules`), rendered with
  :func:`mocaprig.process.body.surface.render_pinhole`;
* the clapperboard's two arms as thin capsules (three side by side per arm, 10 mm thick, 40 mm
  wide) and its two markers;
* a static room, a box ``±room_half_m`` wide and ``room_height_m`` tall (floor, four walls,
  ceiling) with a mildly textured albedo; its depth, incidence and projector pattern are computed
  once per camera (the static background cache);
* the 53 body markers and 2 clapperboard markers, spheres of ``marker_radius_m`` (7 mm).

Depth (Z16, note §1.5, §4.2)
============================

Work in disparity ``d = f·B/Z`` (f in px, B the baseline):

* noise: ``d + σ_d·n``, ``σ_d = subpixel_rms_px`` (0.08 px, §1.5), so ``σ_Z ≈ Z²·σ_d/(f·B)``;
  ``n`` mixes white and spatially correlated (Gaussian-blurred, "blotchy", §4.2) unit noise;
* invalid (0) where ``d`` exceeds the 126 px search range (MinZ = f·B/126, §1.5, shifted by
  ``disparity_shift_px``) or falls below ``min_disparity_px`` (far field); in the left invalid
  band (``u < d``: the right imager does not see that strip, §1.5); in occlusion shadows (seen by
  the left imager, hidden from the right one: computed geometrically per row, the right imager
  sits at +X, so shadows fall on the *left* of foreground edges in the left image); where the
  projected texture is too weak to match (emitter off, low laser power, exposure or gain, dark or
  grazing surfaces, §4.2) — blotchy, through a correlated uniform field; randomly at
  ``hole_rate``; and on most saturated marker blobs (§4.4: per marker and frame, invalid, outlier
  or correct);
* flying pixels: along depth discontinuities a fraction of pixels takes a depth between the two
  sides (§4.2);
* quantised to the depth unit (0.001 m), values above 65535 units are invalid.

Infrared (Y8, note §1.6, §4.3, §4.4)
====================================

``DN = s·(A·ρ + L·(P/150)·ρ·cosθ·(Z₀/Z)²·dots·speckle) + noise``, with ``s`` the
exposure×gain scale relative to 8500 µs and gain 16, ``ρ`` the albedo, ``θ`` the incidence
angle, ``P`` the laser power (mW, 0 when the emitter is off), ``dots`` the projector's fixed
pseudo-random dot field (seeded by the serial, 67°×41°, projected from ``projector_offset_m``
along +X of the left imager so the dots shift with depth), ``speckle`` multiplicative
exponential-like (Gamma) intensity, then shot and read noise, clipped to 0..255. ``A`` is the
ambient room light (the imagers also see visible light, §1.1).

Retro-reflective markers (§4.4) are discs of radius ``f·r/Z`` px at their projected centres,
with a soft edge and a peak far above full scale (``marker_gain`` × full scale at ``Z₀`` and the
default settings, ∝ (laser + a little ambient)·exposure·gain/Z²), so they saturate at 255 until
the exposure gets very short, while the background darkens. Each marker is drawn as the streak
it sweeps during the exposure (motion blur, its light spread along the streak) and z-tested per
pixel against the rendered scene (partial occlusion by the body, the board or another marker).

Rolling shutter (§4.3) is *not* modelled: a frame shows the world at mid-exposure (markers: over
the exposure). Other cameras' projectors are not rendered (the note reports no significant
cross-talk, §4.3).

Quality
=======

``"full"`` draws fresh noise fields every frame; ``"fast"`` draws them once per resolution and
seed (a bank slightly larger than the image) and takes a random crop per frame, so noise is
still different from frame to frame but costs no random generation (≈ 2× faster).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import cv2
import numpy as np
import numpy.typing as npt

from mocaprig.drivers_mock.scenario import stream_rng
from mocaprig.errors import ValidationError
from mocaprig.validation import check_range

if TYPE_CHECKING:
    from mocaprig.drivers_mock.rig import D415Spec
    from mocaprig.drivers_mock.scenario import Scenario
    from mocaprig.process.body.surface import Capsules

__all__ = [
    "CLAPPER_SEGMENT",
    "DepthModel",
    "IrModel",
    "IrSettings",
    "Quality",
    "RenderedFrame",
    "Room",
    "SceneRenderer",
    "mode_intrinsics",
]

_log = logging.getLogger(__name__)

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

Quality = Literal["full", "fast"]

#: Segment label of the clapperboard's arms in the rendered segment image.
CLAPPER_SEGMENT = 100

#: The rig's reference mode: intrinsics are given at 848×480 (realsense-d415.md §1.4).
_REF_WIDTH = 848
_REF_HEIGHT = 480


@dataclass(frozen=True, slots=True)
class DepthModel:
    """The D415 depth error and hole model (realsense-d415.md §1.5, §4.2, §4.4).

    Attributes:
        subpixel_rms_px: Sub-pixel disparity RMS ``s`` (px): 0.08 (§1.5, Grunnet-Jepsen #3904).
        correlated_fraction: Share of the disparity noise variance that is spatially correlated
            (blotchy after the matching window, §4.2).
        correlation_px: Gaussian σ (px) of the correlated component.
        search_range_px: Disparity search range (px): 126, so MinZ = f·B/126 (§1.5).
        disparity_shift_px: Advanced-mode ``disparity_shift`` (px), trades max-Z for min-Z.
        min_disparity_px: Disparities below this (far field) are invalid.
        hole_rate: Fraction of pixels randomly invalid (blotchy).
        texture_min_dn: Projected-texture contrast (DN) below which matching starts failing.
        flying_pixel_fraction: Fraction of depth-edge pixels given a mixed depth.
        edge_disparity_px: Disparity step (px) that counts as a depth edge.
        marker_invalid_prob: Probability a marker's blob is invalid (0) in a frame (§4.4:
            "often invalid").
        marker_outlier_prob: Probability it is an outlier (offset by ``marker_outlier_sigma_m``).
        marker_outlier_sigma_m: σ (m) of an outlier blob's depth offset.
    """

    subpixel_rms_px: float = 0.08
    correlated_fraction: float = 0.5
    correlation_px: float = 2.0
    search_range_px: float = 126.0
    disparity_shift_px: float = 0.0
    min_disparity_px: float = 2.0
    hole_rate: float = 0.003
    texture_min_dn: float = 6.0
    flying_pixel_fraction: float = 0.3
    edge_disparity_px: float = 1.5
    marker_invalid_prob: float = 0.6
    marker_outlier_prob: float = 0.15
    marker_outlier_sigma_m: float = 0.05

    def __post_init__(self) -> None:
        check_range(self.subpixel_rms_px, 0.0, 2.0, name="DepthModel.subpixel_rms_px")
        check_range(self.correlated_fraction, 0.0, 1.0, name="DepthModel.correlated_fraction")
        check_range(self.correlation_px, 0.3, 20.0, name="DepthModel.correlation_px")
        check_range(self.hole_rate, 0.0, 1.0, name="DepthModel.hole_rate")
        check_range(self.flying_pixel_fraction, 0.0, 1.0, name="DepthModel.flying_pixel_fraction")
        check_range(self.marker_invalid_prob, 0.0, 1.0, name="DepthModel.marker_invalid_prob")
        check_range(self.marker_outlier_prob, 0.0, 1.0, name="DepthModel.marker_outlier_prob")
        if self.marker_invalid_prob + self.marker_outlier_prob > 1.0:
            msg = "DepthModel: marker_invalid_prob + marker_outlier_prob must not exceed 1"
            raise ValidationError(msg)

    def sigma_z_m(self, z_m: float, focal_px: float, baseline_m: float) -> float:
        """The model's RMS depth error at ``z_m``: ``Z²·s/(f·B)`` (§1.5)."""
        return z_m * z_m * self.subpixel_rms_px / (focal_px * baseline_m)


@dataclass(frozen=True, slots=True)
class IrModel:
    """Radiometry of the left imager's Y8 image (realsense-d415.md §1.6, §4.3, §4.4).

    Values are DN (0..255) at the reference settings: exposure 8500 µs, gain 16, laser 150 mW
    (the defaults of §1.6).

    Attributes:
        ambient_dn: Room light on an albedo-1 surface.
        laser_dn: Projector dot peak on an albedo-1 surface facing the camera at
            ``reference_distance_m`` (falls off as 1/Z²).
        reference_distance_m: ``Z₀`` of the laser and marker terms.
        speckle_shape: Gamma shape of the laser speckle (1 = exponential, §4.3).
        shot_noise_dn: Shot noise: σ² grows by this many DN² per DN of signal.
        read_noise_dn: Read noise σ (DN).
        dot_count: Dots of the projector pattern over its 67°×41° field (§1.1).
        dot_sigma_rad: Angular σ of one dot (rad).
        projector_offset_m: Projector centre along +X of the left imager (m); not in the note
            (the datasheet drawings were not read), so an assumed value inside the 55 mm baseline.
        projector_fov_deg: Projector field of view (H, V), 67°×41° (§1.1).
        marker_gain: A marker's peak at ``reference_distance_m`` and the reference settings,
            in multiples of full scale (retro-reflection, §4.4).
        marker_ambient: Marker brightness without the emitter, as a fraction of the
            emitter-on return at the reference laser power.
        marker_edge_px: Width (px) of a marker blob's soft edge.
        body_albedo: Mean albedo of the actor's clothing.
        floor_albedo: Floor albedo.
        wall_albedo: Wall and ceiling albedo.
        board_albedo: Clapperboard albedo.
    """

    ambient_dn: float = 40.0
    laser_dn: float = 260.0
    reference_distance_m: float = 2.5
    speckle_shape: float = 1.5
    shot_noise_dn: float = 0.3
    read_noise_dn: float = 1.0
    dot_count: int = 12000
    dot_sigma_rad: float = 0.0012
    projector_offset_m: float = 0.0275
    projector_fov_deg: tuple[float, float] = (67.0, 41.0)
    marker_gain: float = 40.0
    marker_ambient: float = 0.03
    marker_edge_px: float = 1.2
    body_albedo: float = 0.45
    floor_albedo: float = 0.3
    wall_albedo: float = 0.6
    board_albedo: float = 0.25

    def __post_init__(self) -> None:
        if self.dot_count < 0 or min(self.ambient_dn, self.laser_dn, self.marker_gain) < 0:
            msg = "IrModel: dot_count, ambient_dn, laser_dn and marker_gain must be >= 0"
            raise ValidationError(msg)
        check_range(self.speckle_shape, 0.2, 1e3, name="IrModel.speckle_shape")
        check_range(self.marker_edge_px, 0.1, 10.0, name="IrModel.marker_edge_px")


@dataclass(frozen=True, slots=True)
class IrSettings:
    """Exposure, gain and projector state used to form an image (realsense-d415.md §1.6).

    Attributes:
        exposure_us: Exposure (µs).
        gain: Analogue gain (16..248).
        laser_power_mw: Projector power (≈ mW, 0..360).
        emitter_enabled: Projector on.
    """

    exposure_us: int = 8500
    gain: int = 16
    laser_power_mw: int = 150
    emitter_enabled: bool = True

    @property
    def scale(self) -> float:
        """Exposure × gain relative to the reference (8500 µs, gain 16)."""
        return (self.exposure_us / 8500.0) * (self.gain / 16.0)

    @property
    def laser(self) -> float:
        """Projector output relative to 150 mW (0 when off)."""
        return self.laser_power_mw / 150.0 if self.emitter_enabled else 0.0


@dataclass(frozen=True, slots=True)
class Room:
    """The static room around the rig (a textured box).

    Attributes:
        half_width_m: The walls stand at x, y = ±half_width_m (m); the Vicon ring is at 4 m.
        height_m: Ceiling height (m).
    """

    half_width_m: float = 4.5
    height_m: float = 3.2


@dataclass(frozen=True, slots=True, eq=False)
class RenderedFrame:
    """One simulated capture of one camera, with the truth that produced it.

    Attributes:
        depth_z16: Depth image (H, W) uint16 in depth units, 0 = invalid.
        ir_y8: Left IR image (H, W) uint8.
        marker_uv: Projected centres of the 53 body + 2 clapperboard markers at mid-exposure
            (55, 2) px (NaN behind the camera).
        marker_z_m: Their camera-frame depth (55,) m.
        marker_visible: Whether any part of each marker's blob is visible (55,).
        marker_depth_kind: Per marker, 0 = correct, 1 = invalid, 2 = outlier depth (55,).
    """

    depth_z16: npt.NDArray[np.uint16] = field(repr=False)
    ir_y8: npt.NDArray[np.uint8] = field(repr=False)
    marker_uv: F64 = field(repr=False)
    marker_z_m: F64 = field(repr=False)
    marker_visible: npt.NDArray[np.bool_] = field(repr=False)
    marker_depth_kind: npt.NDArray[np.int8] = field(repr=False)


def mode_intrinsics(k_ref: npt.ArrayLike, width: int, height: int) -> F64:
    """Intrinsics of a D415 mode from the 848×480 reference K (realsense-d415.md §1.2, §1.4).

    16:9 modes are the same field of view scaled (848×480 is 1280×720 × 0.6625); 4:3 modes
    (640×480) are a centre crop of the 16:9 image at the same height.
    """
    k = np.array(k_ref, dtype=np.float64)
    if width <= 0 or height <= 0:
        msg = f"image size must be positive, got {width}x{height}"
        raise ValidationError(msg)
    if width / height > 1.7:
        s = width / _REF_WIDTH
        out = k.copy()
        out[:2, :] *= s
        out[2] = (0.0, 0.0, 1.0)
        out[1, 2] = k[1, 2] * height / _REF_HEIGHT
        return out
    s = height / _REF_HEIGHT
    out = k.copy()
    out[:2, :] *= s
    out[2] = (0.0, 0.0, 1.0)
    out[0, 2] -= (_REF_WIDTH * s - width) / 2.0
    return out


class _NoiseBank:
    """Noise fields of one image size: fresh per frame (``full``) or crops of a bank (``fast``)."""

    _PAD = 48

    def __init__(self, height: int, width: int, *, seed: int, corr_px: float, quality: Quality):
        self.h, self.w = height, width
        self.corr_px = corr_px
        self.quality = quality
        ks = int(2 * np.ceil(3 * corr_px) + 1)
        k1 = cv2.getGaussianKernel(ks, corr_px).ravel()
        self._ksize = ks
        self._corr_gain = float(1.0 / np.sqrt(np.sum(k1 * k1) ** 2))
        self._bank: dict[str, F32] = {}
        if quality == "fast":
            rng = stream_rng(seed, f"d415-noise-bank-{width}x{height}")
            hh, ww = height + self._PAD, width + self._PAD
            self._bank["normal"] = rng.standard_normal((2, hh, ww), dtype=np.float32)
            self._bank["corr"] = np.stack(
                [self._correlated(rng.standard_normal((hh, ww), dtype=np.float32)) for _ in "ab"]
            )
            self._bank["uniform_corr"] = np.stack(
                [self._uniformise(self._bank["corr"][i]) for i in range(2)]
            )
            self._bank["uniform"] = rng.random((2, hh, ww), dtype=np.float32)

    def _correlated(self, white: F32) -> F32:
        out = cv2.GaussianBlur(white, (self._ksize, self._ksize), self.corr_px)
        return np.asarray(out * np.float32(self._corr_gain), dtype=np.float32)

    @staticmethod
    def _uniformise(gauss: F32) -> F32:
        # Φ(x) by the logistic approximation (|err| < 0.01): a correlated uniform field.
        return np.asarray(1.0 / (1.0 + np.exp(np.float32(-1.702) * gauss)), dtype=np.float32)

    def _crop(self, name: str, rng: np.random.Generator) -> F32:
        bank = self._bank[name]
        bank.setflags(write=False)  # shared by every camera of this size: never written
        i = int(rng.integers(0, bank.shape[0]))
        dy, dx = (int(x) for x in rng.integers(0, self._PAD + 1, size=2))
        return bank[i, dy : dy + self.h, dx : dx + self.w]

    def normal(self, rng: np.random.Generator) -> F32:
        if self.quality == "fast":
            return self._crop("normal", rng)
        return rng.standard_normal((self.h, self.w), dtype=np.float32)

    def correlated(self, rng: np.random.Generator) -> F32:
        """Unit-variance Gaussian field, spatially correlated over ``corr_px``."""
        if self.quality == "fast":
            return self._crop("corr", rng)
        return self._correlated(rng.standard_normal((self.h, self.w), dtype=np.float32))

    def uniform(self, rng: np.random.Generator) -> F32:
        if self.quality == "fast":
            return self._crop("uniform", rng)
        return rng.random((self.h, self.w), dtype=np.float32)

    def gamma(self, rng: np.random.Generator, shape: float) -> F32:
        """Gamma(shape)/shape variates (mean 1): laser speckle intensity."""
        if self.quality == "fast":
            key = f"gamma-{shape:g}"
            if key not in self._bank:
                grng = stream_rng(0, f"d415-speckle-{shape:g}")
                hh, ww = self._bank["normal"].shape[1:]
                self._bank[key] = (grng.gamma(shape, 1.0 / shape, (2, hh, ww))).astype(np.float32)
            return self._crop(key, rng)
        return rng.gamma(shape, 1.0 / shape, (self.h, self.w)).astype(np.float32)

    def uniform_correlated(self, rng: np.random.Generator) -> F32:
        """A blotchy field with roughly uniform marginals on [0, 1]."""
        if self.quality == "fast":
            return self._crop("uniform_corr", rng)
        return self._uniformise(self.correlated(rng))


_BANKS: dict[tuple[int, int, int, float, str], _NoiseBank] = {}


def _noise_bank(
    height: int, width: int, *, seed: int, corr_px: float, quality: Quality
) -> _NoiseBank:
    key = (height, width, seed, corr_px, quality)
    if key not in _BANKS:
        if len(_BANKS) > 8:
            _BANKS.clear()
        _BANKS[key] = _NoiseBank(height, width, seed=seed, corr_px=corr_px, quality=quality)
    return _BANKS[key]


def _projector_pattern(serial: str, k: F64, width: int, height: int, model: IrModel) -> F32:
    """The projector's dot field in its own image plane (same K as the left imager).

    Dots are uniform in the tangent plane over the projector's 67°×41° field (§1.1), seeded by
    the serial (§4.3), so every mode of one device shows the same physical pattern.
    """
    rng = stream_rng(int(serial), "d415-projector")
    th = np.tan(np.radians(model.projector_fov_deg[0]) / 2.0)
    tv = np.tan(np.radians(model.projector_fov_deg[1]) / 2.0)
    x = rng.uniform(-th, th, model.dot_count)
    y = rng.uniform(-tv, tv, model.dot_count)
    amp = rng.uniform(0.6, 1.0, model.dot_count)
    u = k[0, 0] * x + k[0, 2]
    v = k[1, 1] * y + k[1, 2]
    img = np.zeros((height, width), np.float32)
    ui, vi = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    fu, fv = u - ui, v - vi
    for du, dv, w in (
        (0, 0, (1 - fu) * (1 - fv)),
        (1, 0, fu * (1 - fv)),
        (0, 1, (1 - fu) * fv),
        (1, 1, fu * fv),
    ):
        uu, vv = ui + du, vi + dv
        ok = (uu >= 0) & (uu < width) & (vv >= 0) & (vv < height)
        np.add.at(img, (vv[ok], uu[ok]), (amp * w)[ok].astype(np.float32))
    sigma_px = max(model.dot_sigma_rad * k[0, 0], 0.45)
    ks = int(2 * np.ceil(3 * sigma_px) + 1)
    img = np.asarray(cv2.GaussianBlur(img, (ks, ks), sigma_px), np.float32)
    # Normalise so an isolated full-amplitude dot peaks at 1.
    peak = 1.0 / (2.0 * np.pi * sigma_px * sigma_px)
    return np.asarray(np.minimum(img / np.float32(min(peak, 1.0)), 2.0), dtype=np.float32)


class SceneRenderer:
    """Renders the simulated world for one D415 at one mode (module doc for the model).

    Args:
        scenario: The world.
        spec: The camera (pose, intrinsics at 848×480, baseline, serial).
        width, height: The mode's image size.
        depth_scale_m: Metres per Z16 unit.
        depth_model, ir_model, room: Model parameters.
        quality: ``"full"`` or ``"fast"`` noise (module doc).
    """

    def __init__(
        self,
        scenario: Scenario,
        spec: D415Spec,
        *,
        width: int = 848,
        height: int = 480,
        depth_scale_m: float = 0.001,
        depth_model: DepthModel | None = None,
        ir_model: IrModel | None = None,
        room: Room | None = None,
        quality: Quality = "fast",
    ) -> None:
        if quality not in ("full", "fast"):
            msg = f"quality must be 'full' or 'fast', got {quality!r}"
            raise ValidationError(msg)
        self.scenario = scenario
        self.spec = spec
        self.width, self.height = int(width), int(height)
        self.depth_scale_m = float(depth_scale_m)
        self.depth_model = depth_model or DepthModel()
        self.ir_model = ir_model or IrModel()
        self.room = room or Room()
        self.quality: Quality = quality
        self.K = mode_intrinsics(spec.ir_left.K, self.width, self.height)
        self.T_world_cam = np.array(spec.ir_left.T_world_cam)
        self.T_cam_world = np.array(spec.ir_left.T_cam_world)
        self.fx = float(self.K[0, 0])
        self.fb = float(self.K[0, 0] * spec.baseline_m)
        h, w = self.height, self.width
        self._u = np.arange(w, dtype=np.float32)
        self._a = ((self._u - self.K[0, 2]) / self.K[0, 0]).astype(np.float32)
        self._b = ((np.arange(h, dtype=np.float32) - self.K[1, 2]) / self.K[1, 1]).astype(
            np.float32
        )
        # |ray| for unit-z rays, to turn normals into incidence cosines.
        self._ray_norm = np.sqrt(self._a[None, :] ** 2 + self._b[:, None] ** 2 + 1.0).astype(
            np.float32
        )
        self._pattern = _projector_pattern(spec.serial, self.K, w, h, self.ir_model)
        self._bank = _noise_bank(
            h,
            w,
            seed=scenario.seed,
            corr_px=self.depth_model.correlation_px * w / _REF_WIDTH,
            quality=quality,
        )
        self._marker_radius_m = float(scenario.markers.marker_radius_m)
        self._clapper_radius_m = float(scenario.clapperboard.marker_radius_m)
        self._segment_albedo = self._albedo_table()
        self._background()

    # -- static background -------------------------------------------------------------------

    def _albedo_table(self) -> F32:
        rng = stream_rng(self.scenario.seed, "d415-albedo")
        table = np.full(CLAPPER_SEGMENT + 1, self.ir_model.body_albedo, np.float32)
        table[:CLAPPER_SEGMENT] *= rng.uniform(0.8, 1.2, CLAPPER_SEGMENT).astype(np.float32)
        table[CLAPPER_SEGMENT] = self.ir_model.board_albedo
        return table

    def _background(self) -> None:
        """Depth, albedo, incidence and dot pattern of the static room (computed once)."""
        h, w = self.height, self.width
        r = self.T_world_cam[:3, :3]
        c = self.T_world_cam[:3, 3]
        dirs_cam = np.stack(
            np.broadcast_arrays(self._a[None, :], self._b[:, None], np.ones((1, 1))), axis=-1
        ).astype(np.float64)
        dirs = dirs_cam @ r.T  # world directions of unit-z rays: t is the z-depth
        best = np.full((h, w), np.inf)
        normal_w = np.zeros((h, w, 3))
        hw, ht = self.room.half_width_m, self.room.height_m
        planes = (
            (2, 0.0, (0.0, 0.0, 1.0)),
            (2, ht, (0.0, 0.0, -1.0)),
            (0, hw, (-1.0, 0.0, 0.0)),
            (0, -hw, (1.0, 0.0, 0.0)),
            (1, hw, (0.0, -1.0, 0.0)),
            (1, -hw, (0.0, 1.0, 0.0)),
        )
        for axis, value, n in planes:
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (value - c[axis]) / dirs[..., axis]
            ok = np.isfinite(t) & (t > 0) & (t < best)
            best[ok] = t[ok]
            normal_w[ok] = n
        best = np.where(np.isfinite(best), best, 0.0)
        hit = c + dirs * best[..., None]
        floor = normal_w[..., 2] > 0.5
        base = np.where(floor, self.ir_model.floor_albedo, self.ir_model.wall_albedo)
        # Mild texture: 0.5 m tiles on the floor, low-frequency blotches on the walls.
        tiles = np.sign(np.sin(np.pi * hit[..., 0] / 0.5) * np.sin(np.pi * hit[..., 1] / 0.5))
        blotch = np.sin(3.1 * hit[..., 0] + 1.7 * hit[..., 1]) * np.sin(2.3 * hit[..., 2] + 0.4)
        albedo = base * (1.0 + np.where(floor, 0.12 * tiles, 0.1 * blotch))
        cos = np.abs(np.sum(normal_w * dirs, axis=-1)) / np.linalg.norm(dirs, axis=-1)
        self._bg_z = best.astype(np.float32)
        self._bg_albedo = albedo.astype(np.float32)
        self._bg_cos = cos.astype(np.float32)
        self._bg_dots = self._dots(
            np.arange(h)[:, None].repeat(w, 1), np.arange(w)[None, :].repeat(h, 0), self._bg_z
        )

    def _dots(
        self, v: npt.NDArray[np.int64], u: npt.NDArray[np.int64], z: npt.NDArray[np.float32]
    ) -> F32:
        """Projector pattern seen at pixels (v, u) of depth z: parallax ``f·p/Z`` along u."""
        shift = self.fx * self.ir_model.projector_offset_m / np.maximum(z, np.float32(0.05))
        up = np.rint(u - shift).astype(np.int64)
        ok = (up >= 0) & (up < self.width)
        out = np.zeros(u.shape, np.float32)
        out[ok] = self._pattern[v[ok], up[ok]]
        return out

    # -- scene ---------------------------------------------------------------------------------

    def _clapper_capsules(self, t_ns: int) -> tuple[F64, F64]:
        cb = self.scenario.clapperboard
        theta = float(cb.angle_rad(np.array([t_ns], np.int64))[0])
        u = np.array([np.cos(cb.yaw_rad), np.sin(cb.yaw_rad), 0.0])
        z = np.array([0.0, 0.0, 1.0])
        wdir = np.cross(z, u)
        h = cb.arm_thickness_m
        top_dir = np.cos(theta) * u + np.sin(theta) * z
        top_n = -np.sin(theta) * u + np.cos(theta) * z
        a_list, b_list = [], []
        for off in (-0.015, 0.0, 0.015):
            base = cb.hinge_m + off * wdir
            a_list += [base - 0.5 * h * z, base + 0.5 * h * top_n]
            b_list += [
                base + cb.arm_length_m * u - 0.5 * h * z,
                base + cb.arm_length_m * top_dir + 0.5 * h * top_n,
            ]
        return np.array(a_list), np.array(b_list)

    def render(
        self,
        t_start_ns: int,
        settings: IrSettings,
        rng: np.random.Generator,
    ) -> RenderedFrame:
        """Render the capture whose exposure starts at session time ``t_start_ns``.

        Args:
            t_start_ns: Exposure start (session ns).
            settings: Exposure, gain and projector state.
            rng: The frame's generator (noise, marker depth variants).
        """
        from mocaprig.process.body.kinematics import forward_kinematics
        from mocaprig.process.body.surface import Capsules, capsules

        exp_ns = int(settings.exposure_us) * 1000
        t_mid = int(t_start_ns) + exp_ns // 2
        times = np.array([t_start_ns, t_mid, t_start_ns + exp_ns], np.int64)
        world = self.scenario.sample(times)
        kin = forward_kinematics(world.pose[1], self.scenario.shape)
        body = capsules(kin, self.scenario.shape)
        ca, cb = self._clapper_capsules(t_mid)
        n_clap = ca.shape[0]
        caps = Capsules(
            a_m=np.concatenate([body.a_m, ca]),
            b_m=np.concatenate([body.b_m, cb]),
            radius_m=np.concatenate(
                [body.radius_m, np.full(n_clap, 0.5 * self.scenario.clapperboard.arm_thickness_m)]
            ),
            joint=np.concatenate([body.joint, np.full(n_clap, CLAPPER_SEGMENT, np.int64)]),
        )
        z = self._bg_z.copy()
        albedo = self._bg_albedo.copy()
        cos = self._bg_cos.copy()
        dots = self._bg_dots.copy()
        hv, hu, zf, seg, n = self._foreground(caps)
        if hv.size:
            front = zf < z[hv, hu]
            hv, hu, zf, seg, n = hv[front], hu[front], zf[front], seg[front], n[front]
            z[hv, hu] = zf
            albedo[hv, hu] = self._segment_albedo[seg]
            ray = np.stack([self._a[hu], self._b[hv], np.ones_like(zf)], axis=-1)
            cos[hv, hu] = np.clip(-np.sum(n * ray, axis=-1) / self._ray_norm[hv, hu], 0.0, 1.0)
            dots[hv, hu] = self._dots(hv, hu, zf)

        markers_w = np.concatenate([world.markers_m, world.clapper_m], axis=1)  # (3, 55, 3)
        radii = np.concatenate(
            [
                np.full(world.markers_m.shape[1], self._marker_radius_m),
                np.full(world.clapper_m.shape[1], self._clapper_radius_m),
            ]
        )
        blobs = self._marker_blobs(markers_w, radii, z, settings)

        ir_model = self.ir_model
        falloff = (np.float32(ir_model.reference_distance_m) / np.maximum(z, np.float32(0.05))) ** 2
        laser = np.float32(ir_model.laser_dn * settings.laser) * albedo * cos * falloff
        # The texture the matcher sees: DN of the dot peaks (§4.2 low-texture holes).
        texture_dn = np.float32(settings.scale) * laser
        depth = self._depth(z, blobs, texture_dn, rng)
        ir = self._infrared(albedo, laser, dots, blobs, settings, rng)
        return RenderedFrame(
            depth_z16=depth,
            ir_y8=ir,
            marker_uv=blobs.uv_mid,
            marker_z_m=blobs.z_mid,
            marker_visible=blobs.visible,
            marker_depth_kind=blobs.kind,
        )

    def _roi(self, caps: Capsules) -> tuple[int, int, int, int] | None:
        """Pixel box [u0, u1) × [v0, v1) holding every capsule's image, or ``None``."""
        r = self.T_cam_world[:3, :3]
        t = self.T_cam_world[:3, 3]
        a = np.asarray(caps.a_m) @ r.T + t
        b = np.asarray(caps.b_m) @ r.T + t
        rad = np.asarray(caps.radius_m)[:, None]
        lo = np.minimum(a, b) - rad
        hi = np.maximum(a, b) + rad
        keep = hi[:, 2] > 1e-3
        if not np.any(keep):
            return None
        if np.any(lo[keep, 2] <= 1e-3):
            return 0, self.width, 0, self.height
        lo, hi = lo[keep], hi[keep]
        corners = np.stack(
            [
                np.stack([x, y, z], axis=-1)
                for x in (lo[:, 0], hi[:, 0])
                for y in (lo[:, 1], hi[:, 1])
                for z in (lo[:, 2], hi[:, 2])
            ],
            axis=1,
        ).reshape(-1, 3)
        u = self.K[0, 0] * corners[:, 0] / corners[:, 2] + self.K[0, 2]
        v = self.K[1, 1] * corners[:, 1] / corners[:, 2] + self.K[1, 2]
        u0 = max(int(np.floor(u.min())) - 1, 0)
        u1 = min(int(np.ceil(u.max())) + 2, self.width)
        v0 = max(int(np.floor(v.min())) - 1, 0)
        v1 = min(int(np.ceil(v.max())) + 2, self.height)
        if u0 >= u1 or v0 >= v1:
            return None
        return u0, u1, v0, v1

    def _foreground(
        self, caps: Capsules
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], F32, npt.NDArray[np.int64], F32]:
        """Hit pixels of the capsules: (v, u, z-depth, segment, camera-frame normals).

        Only the capsules' pixel box is ray-cast. ``"fast"`` casts every second pixel in each
        direction and fills each 2×2 block from the hit's tangent plane (exact for planes).
        """
        from mocaprig.process.body.surface import render_pinhole

        empty_i = np.zeros(0, np.int64)
        empty = (empty_i, empty_i, np.zeros(0, np.float32), empty_i, np.zeros((0, 3), np.float32))
        box = self._roi(caps)
        self._last_box = box
        if box is None:
            return empty
        u0, u1, v0, v1 = box
        k = self.K.copy()
        k[0, 2] -= u0
        k[1, 2] -= v0
        w, h = u1 - u0, v1 - v0
        step = 2 if self.quality == "fast" else 1
        if step == 2:
            k[0, 0] /= 2.0
            k[1, 1] /= 2.0
            k[0, 2] = (k[0, 2] + 0.5) / 2.0 - 0.5
            k[1, 2] = (k[1, 2] + 0.5) / 2.0 - 0.5
        res = render_pinhole(caps, k, self.T_cam_world, -(-w // step), -(-h // step))
        hv, hu = np.nonzero(res.segment >= 0)
        if hv.size == 0:
            return empty
        z = res.depth_m[hv, hu]
        seg = res.segment[hv, hu].astype(np.int64)
        n = res.normals_cam[hv, hu]
        if step == 2:
            dv = np.array([0, 0, 1, 1])
            du = np.array([0, 1, 0, 1])
            vv = (2 * hv[:, None] + dv).ravel()
            uu = (2 * hu[:, None] + du).ravel()
            rep = np.repeat(np.arange(hv.size), 4)
            ok = (vv < h) & (uu < w)
            vv, uu, rep = vv[ok], uu[ok], rep[ok]
            # Tangent plane of the cast ray's hit: z = (n·P) / (n·ray) for each filled pixel.
            cu = (2 * hu + 0.5) + u0  # full-frame centre of the cast (coarse) pixel
            cv = (2 * hv + 0.5) + v0
            p = np.stack(
                [(cu - self.K[0, 2]) / self.K[0, 0] * z, (cv - self.K[1, 2]) / self.K[1, 1] * z, z],
                axis=-1,
            )
            npd = np.sum(n * p, axis=-1)
            uf, vf = uu + u0, vv + v0
            ray = np.stack(
                [
                    (uf - self.K[0, 2]) / self.K[0, 0],
                    (vf - self.K[1, 2]) / self.K[1, 1],
                    np.ones(uf.size),
                ],
                axis=-1,
            )
            denom = np.sum(n[rep] * ray, axis=-1)
            zr = z[rep]
            zp = np.where(denom < -1e-3, npd[rep] / np.where(denom < -1e-3, denom, -1.0), zr)
            z = np.clip(zp, 0.8 * zr, 1.25 * zr)
            return vf, uf, z.astype(np.float32), seg[rep], n[rep].astype(np.float32)
        return hv + v0, hu + u0, z.astype(np.float32), seg, n.astype(np.float32)

    _last_box: tuple[int, int, int, int] | None = None

    def _fg_box(self, blobs: _Blobs) -> tuple[int, int, int, int] | None:
        """The last foreground box grown by 4 px and by the marker blobs."""
        boxes = []
        if self._last_box is not None:
            u0, u1, v0, v1 = self._last_box
            boxes.append((u0 - 4, u1 + 4, v0 - 4, v1 + 4))
        if blobs.pix_v.size:
            boxes.append(
                (
                    int(blobs.pix_u.min()) - 4,
                    int(blobs.pix_u.max()) + 5,
                    int(blobs.pix_v.min()) - 4,
                    int(blobs.pix_v.max()) + 5,
                )
            )
        if not boxes:
            return None
        b = np.array(boxes)
        u0, v0 = max(0, int(b[:, 0].min())), max(0, int(b[:, 2].min()))
        u1, v1 = min(self.width, int(b[:, 1].max())), min(self.height, int(b[:, 3].max()))
        if u0 >= u1 or v0 >= v1:
            return None
        return u0, u1, v0, v1

    # -- markers ---------------------------------------------------------------------------------

    def _project(self, p_world: F64) -> tuple[F64, F64]:
        pc = p_world @ self.T_cam_world[:3, :3].T + self.T_cam_world[:3, 3]
        zc = pc[..., 2]
        safe = np.where(zc > 1e-6, zc, np.nan)
        u = self.K[0, 0] * pc[..., 0] / safe + self.K[0, 2]
        v = self.K[1, 1] * pc[..., 1] / safe + self.K[1, 2]
        return np.stack([u, v], axis=-1), zc

    def _marker_blobs(
        self, markers_w: F64, radii: F64, z_scene: F32, settings: IrSettings
    ) -> _Blobs:
        """Marker streaks over the exposure, z-tested; paints the spheres into ``z_scene``."""
        m = markers_w.shape[1]
        uv, zc = self._project(markers_w)  # (3, M, 2), (3, M)
        uv_mid, z_mid = uv[1], zc[1]
        ir = self.ir_model
        edge = ir.marker_edge_px
        ok = np.all(np.isfinite(uv), axis=(0, 2)) & np.all(zc > 0.05, axis=0)
        rho = np.where(ok, self.fx * radii / np.where(ok, z_mid, 1.0), 0.0)
        # Polyline start -> mid -> end (pixels) for each marker.
        p0, p1, p2 = uv[0], uv[1], uv[2]
        uv_ok = np.where(np.isfinite(uv), uv, 0.0)
        lo = np.min(uv_ok, axis=0) - (rho + edge + 1.0)[:, None]
        hi = np.max(uv_ok, axis=0) + (rho + edge + 1.0)[:, None]
        lo = np.where(ok[:, None], lo, 0.0)
        hi = np.where(ok[:, None], hi, 0.0)
        half = np.ceil(np.max(hi - lo, axis=1) / 2.0) if m else np.zeros(0)
        ok &= half < 60  # absurd streaks (a marker crossing the near plane) are skipped
        ok &= (hi[:, 0] >= 0) & (lo[:, 0] < self.width) & (hi[:, 1] >= 0) & (lo[:, 1] < self.height)
        blobs = _Blobs(
            uv_mid=uv_mid,
            z_mid=z_mid,
            visible=np.zeros(m, bool),
            kind=np.zeros(m, np.int8),
            pix_v=np.zeros(0, np.int64),
            pix_u=np.zeros(0, np.int64),
            pix_val=np.zeros(0, np.float32),
            pix_marker=np.zeros(0, np.int64),
            pix_core=np.zeros(0, bool),
        )
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            return blobs
        r_st = int(np.max(half[idx]))
        off = np.arange(-r_st, r_st + 1)
        oy, ox = np.meshgrid(off, off, indexing="ij")
        centre = np.rint(0.5 * (lo[idx] + hi[idx])).astype(np.int64)  # (K, 2)
        pu = centre[:, 0, None] + ox.ravel()[None, :]  # (K, S)
        pv = centre[:, 1, None] + oy.ravel()[None, :]
        inside = (pu >= 0) & (pu < self.width) & (pv >= 0) & (pv < self.height)
        puf, pvf = pu.astype(np.float64), pv.astype(np.float64)
        d_streak = np.minimum(
            _seg_dist(puf, pvf, p0[idx], p1[idx]), _seg_dist(puf, pvf, p1[idx], p2[idx])
        )
        d_mid = np.hypot(puf - p1[idx, 0, None], pvf - p1[idx, 1, None])
        rk = rho[idx, None]
        zk = z_mid[idx, None]
        # Front surface of the sphere along each pixel ray (mid-exposure position).
        lat_m = d_streak * zk / self.fx
        r_m = radii[idx, None]
        z_front = zk - np.sqrt(np.maximum(r_m * r_m - lat_m * lat_m, 0.0))
        pvc = np.clip(pv, 0, self.height - 1)
        puc = np.clip(pu, 0, self.width - 1)
        z_behind = z_scene[pvc, puc].astype(np.float64)
        in_sphere = inside & (d_mid < rk)
        # Paint the spheres (mid-exposure) into the scene depth, nearest first.
        z_sph = zk - np.sqrt(np.maximum(r_m * r_m - (d_mid * zk / self.fx) ** 2, 0.0))
        paint = in_sphere & (z_sph < z_behind)
        np.minimum.at(z_scene, (pv[paint], pu[paint]), z_sph[paint].astype(np.float32))
        visible = inside & (z_front <= z_behind + 0.002)
        # Brightness (§4.4): retro-reflection of the camera's own projector (plus a little
        # ambient), ∝ exposure·gain/Z², spread along the streak when the marker moves.
        streak_px = np.hypot(*(p1[idx] - p0[idx]).T) + np.hypot(*(p2[idx] - p1[idx]).T)
        retro = settings.laser + ir.marker_ambient
        peak = (
            255.0
            * ir.marker_gain
            * settings.scale
            * retro
            * (ir.reference_distance_m / z_mid[idx]) ** 2
            * (2.0 * rho[idx] + 1.0)
            / (2.0 * rho[idx] + 1.0 + streak_px)
        )
        cover = np.clip((rk + 0.5 * edge - d_streak) / edge, 0.0, 1.0)
        val = peak[:, None] * cover
        keep = visible & (val > 0.5)
        blobs.pix_v = pv[keep]
        blobs.pix_u = pu[keep]
        blobs.pix_val = val[keep].astype(np.float32)
        blobs.pix_marker = np.broadcast_to(idx[:, None], keep.shape)[keep]
        blobs.pix_core = (cover >= 0.5)[keep]
        blobs.visible[idx] = np.any(keep, axis=1)
        return blobs

    # -- depth -----------------------------------------------------------------------------------

    def _depth(
        self, z: F32, blobs: _Blobs, texture_dn: F32, rng: np.random.Generator
    ) -> npt.NDArray[np.uint16]:
        dm = self.depth_model
        h, w = self.height, self.width
        fb = np.float32(self.fb)
        valid_z = z > 0
        disp = np.where(valid_z, fb / np.where(valid_z, z, 1.0), 0.0).astype(np.float32)
        # The static room is convex (no occlusion, no depth edges): shadows and flying pixels
        # only arise around the foreground, so they are computed in its box.
        shadow = np.zeros(z.shape, bool)
        box = self._fg_box(blobs)
        if box is not None:
            u0, u1, v0, v1 = box
            # A shadow reaches at most the search range left of its occluder.
            ua = max(0, u0 - int(dm.search_range_px) - 2)
            sub = disp[v0:v1, ua:u1]
            # Occlusion shadow: pixel u is hidden from the right imager when some pixel to its
            # right lands at or left of its right-image column u - d (right imager at +X).
            xr = self._u[None, ua:u1] - sub
            suffix = np.minimum.accumulate(xr[:, ::-1], axis=1)[:, ::-1]
            right_min = np.concatenate(
                [suffix[:, 1:], np.full((v1 - v0, 1), np.inf, np.float32)], axis=1
            )
            shadow[v0:v1, ua:u1] = xr > right_min + np.float32(0.5)
            # Flying pixels: mixed depths along discontinuities (§4.2).
            fv0, fv1, fu0, fu1 = max(0, v0 - 1), min(h, v1 + 1), max(0, u0 - 1), min(w, u1 + 1)
            blk = disp[fv0:fv1, fu0:fu1]
            kernel = np.ones((3, 3), np.uint8)
            dmax = cv2.dilate(blk, kernel)
            dmin = cv2.erode(blk, kernel)
            edge = (dmax - dmin) > np.float32(dm.edge_disparity_px)
            u01 = self._bank.uniform(rng)[fv0:fv1, fu0:fu1]
            flying = edge & (u01 < np.float32(dm.flying_pixel_fraction))
            if np.any(flying):
                mix = u01[flying] / np.float32(max(dm.flying_pixel_fraction, 1e-6))
                blk[flying] = dmin[flying] + mix * (dmax[flying] - dmin[flying])
        # Left invalid band: the right imager does not see u - d < 0 (§1.5).
        nb = min(w, int(dm.search_range_px) + 2)
        band = np.zeros(z.shape, bool)
        band[:, :nb] = self._u[None, :nb] < disp[:, :nb]
        # Noise (§1.5, §4.2): white + correlated, σ_d = s.
        a = dm.correlated_fraction
        noise = np.float32(np.sqrt(1.0 - a)) * self._bank.normal(rng)
        if a > 0:
            noise = noise + np.float32(np.sqrt(a)) * self._bank.correlated(rng)
        disp_n = disp + np.float32(dm.subpixel_rms_px) * noise
        invalid = ~valid_z | shadow | band
        invalid |= disp_n > np.float32(dm.search_range_px + dm.disparity_shift_px)
        invalid |= disp_n < np.float32(max(dm.min_disparity_px + dm.disparity_shift_px, 1e-3))
        # Texture too weak to match (§4.2): blotchy holes where the dot contrast is low.
        p_fail = np.clip(1.0 - texture_dn / np.float32(dm.texture_min_dn), 0.0, 1.0)
        invalid |= self._bank.uniform_correlated(rng) < p_fail
        if dm.hole_rate > 0:
            invalid |= self._bank.uniform_correlated(rng) < np.float32(dm.hole_rate * 0.5)
            invalid |= self._bank.uniform(rng)[::-1, ::-1] < np.float32(dm.hole_rate * 0.5)
        z_n = np.where(invalid, 0.0, fb / np.where(invalid, 1.0, disp_n))
        # Markers (§4.4): per marker, invalid, outlier or correct.
        if blobs.pix_v.size:
            m = blobs.uv_mid.shape[0]
            draw = rng.random(m)
            kind = np.where(
                draw < dm.marker_invalid_prob,
                1,
                np.where(draw < dm.marker_invalid_prob + dm.marker_outlier_prob, 2, 0),
            ).astype(np.int8)
            blobs.kind[:] = kind
            offset = np.asarray(rng.normal(0.0, dm.marker_outlier_sigma_m, m), np.float64)
            core = blobs.pix_core
            pv, pu, pm = blobs.pix_v[core], blobs.pix_u[core], blobs.pix_marker[core]
            k = kind[pm]
            z_n[pv[k == 1], pu[k == 1]] = 0.0
            out = k == 2
            sel = (pv[out], pu[out])
            z_n[sel] = np.where(z_n[sel] > 0, z_n[sel] + offset[pm[out]], 0.0)
        units = np.rint(z_n / self.depth_scale_m)
        units = np.where((units > 0) & (units <= 65535), units, 0)
        out_img: npt.NDArray[np.uint16] = units.astype(np.uint16)
        return out_img

    # -- infrared ----------------------------------------------------------------------------------

    def _infrared(
        self,
        albedo: F32,
        laser: F32,
        dots: F32,
        blobs: _Blobs,
        settings: IrSettings,
        rng: np.random.Generator,
    ) -> npt.NDArray[np.uint8]:
        ir = self.ir_model
        s = np.float32(settings.scale)
        speckle = self._speckle(rng)
        signal = s * (np.float32(ir.ambient_dn) * albedo + laser * dots * speckle)
        sigma = np.sqrt(
            np.float32(ir.shot_noise_dn) * signal + np.float32(ir.read_noise_dn**2)
        ).astype(np.float32)
        img = signal + sigma * self._bank.normal(rng)[::-1]
        if blobs.pix_v.size:
            np.maximum.at(img, (blobs.pix_v, blobs.pix_u), blobs.pix_val)
        out: npt.NDArray[np.uint8] = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        return out

    def _speckle(self, rng: np.random.Generator) -> F32:
        """Multiplicative laser speckle, mean 1, Gamma(k) intensity statistics (§4.3)."""
        return self._bank.gamma(rng, self.ir_model.speckle_shape)


@dataclass(slots=True, eq=False)
class _Blobs:
    uv_mid: F64
    z_mid: F64
    visible: npt.NDArray[np.bool_]
    kind: npt.NDArray[np.int8]
    pix_v: npt.NDArray[np.int64]
    pix_u: npt.NDArray[np.int64]
    pix_val: F32
    pix_marker: npt.NDArray[np.int64]
    pix_core: npt.NDArray[np.bool_]


def _seg_dist(pu: F64, pv: F64, a: F64, b: F64) -> F64:
    """Distance from pixels (K, S) to segments a–b (K, 2)."""
    ab = b - a
    l2 = np.sum(ab * ab, axis=-1)[:, None]
    t = ((pu - a[:, 0, None]) * ab[:, 0, None] + (pv - a[:, 1, None]) * ab[:, 1, None]) / np.where(
        l2 > 1e-12, l2, 1.0
    )
    t = np.clip(t, 0.0, 1.0)
    du = pu - (a[:, 0, None] + t * ab[:, 0, None])
    dv = pv - (a[:, 1, None] + t * ab[:, 1, None])
    return np.asarray(np.hypot(du, dv))
