"""The simulated world: one seeded, immutable :class:`Scenario` every mock renders from.

A scenario holds the actor (body shape, marker set with placement jitter, motion), the rig
(camera poses and intrinsics, Vicon), the device clocks, the clapperboard and the noise
settings. It is built from ``(name, seed, seconds[, motion_path])`` by :func:`build_scenario`
and is fully determined by them: every random draw comes from a generator derived from the seed
and a stream name (:meth:`Scenario.rng`), so adding a stream never changes another's draws.

Sampling is lazy and vectorised: :meth:`Scenario.sample` (or :meth:`pose`, :meth:`joints_m`,
:meth:`markers_m`, :meth:`clapper_markers_m`) evaluates the world at any array of session times
(int ns); nothing is precomputed. Session time 0 is the start of the simulated session; the
motion clip's time 0 is at session time 0.
"""

from __future__ import annotations

import logging
import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from mocaprig.drivers_mock.clapperboard import Clapperboard, make_clapperboard
from mocaprig.drivers_mock.clock import DeviceClock, d415_clock, davis_clock, vicon_clock
from mocaprig.drivers_mock.noise import NoiseSettings
from mocaprig.drivers_mock.rig import D415Timing, PinholeCamera, PulseAt, Rig, default_rig
from mocaprig.drivers_mock.world import WORLD_KINDS, WorldKind, WorldParams
from mocaprig.errors import ValidationError
from mocaprig.validation import check_positive

if TYPE_CHECKING:
    from mocaprig.process.body.markers import MarkerSet
    from mocaprig.process.body.motion import Motion
    from mocaprig.process.body.shape import BodyShape

__all__ = [
    "DEFAULT_ACTIONS",
    "SCENARIOS",
    "Scenario",
    "ScenarioRecipe",
    "WorldSample",
    "build_scenario",
    "d415_timing_preset",
    "stream_rng",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: Upper bound on a session's length (s); the 1 kHz truth of an hour is already ~1 GB.
MAX_SECONDS = 3600.0


def stream_rng(seed: int, stream: str) -> np.random.Generator:
    """An independent generator for one named random stream of a seeded scenario."""
    return np.random.default_rng(
        [int(seed) & 0xFFFFFFFF, int(seed) >> 32, zlib.crc32(stream.encode())]
    )


@dataclass(frozen=True, slots=True, eq=False)
class WorldSample:
    """The world at a set of session times.

    Attributes:
        t_ns: Session times (int64 ns), shape ``(T,)``.
        pose: Pose vectors ``(T, 33)`` (:mod:`mocaprig.process.body.skeleton` layout).
        joints_m: Joint positions ``(T, 26, 3)`` (m, world).
        markers_m: Body marker centres ``(T, M, 3)`` (m, world), the marker set's order.
        marker_normals: Unit outward skin normal under each body marker ``(T, M, 3)`` (world).
        clapper_m: Clapperboard markers ``(T, 2, 3)`` (m, world), TOP then BOTTOM.
    """

    t_ns: I64 = field(repr=False)
    pose: F64 = field(repr=False)
    joints_m: F64 = field(repr=False)
    markers_m: F64 = field(repr=False)
    marker_normals: F64 = field(repr=False)
    clapper_m: F64 = field(repr=False)


@dataclass(frozen=True, slots=True)
class ScenarioRecipe:
    """How a named scenario builds its motion.

    Attributes:
        name: The scenario name.
        description: One line for ``--help``.
        static_start_s: Length of the static T-pose at the start (s), capped at 20 % of the
            session.
        build_motion: ``(shape, rng, seconds, static_start_s) -> Motion``.
    """

    name: str
    description: str
    static_start_s: float
    build_motion: Callable[[BodyShape, np.random.Generator, float, float], Motion] = field(
        repr=False
    )


#: The everyday actions of the ``default`` scenario, in order (cycled for long sessions).
DEFAULT_ACTIONS: tuple[str, ...] = ("wave", "squat", "clap", "jumping_jacks", "punch_kick")

#: Each action gets at least this long (s); shorter sessions use fewer actions.
_ACTION_S = 3.0


def _actions(names: tuple[str, ...], seconds: float, static_start_s: float) -> tuple[str, ...]:
    n = max(1, int((seconds - static_start_s) // _ACTION_S))
    return tuple(names[i % len(names)] for i in range(n))


def _default_motion(
    shape: BodyShape, rng: np.random.Generator, seconds: float, static_start_s: float
) -> Motion:
    from mocaprig.process.body.procedural import session_motion

    names = _actions(DEFAULT_ACTIONS, seconds, static_start_s)
    return session_motion(
        names, seconds=seconds, rng=rng, static_start_s=static_start_s, shape=shape
    )


def _karate_motion(
    shape: BodyShape, rng: np.random.Generator, seconds: float, static_start_s: float
) -> Motion:
    from mocaprig.process.body.procedural import session_motion

    return session_motion(
        ("karate",), seconds=seconds, rng=rng, static_start_s=static_start_s, shape=shape
    )


def _tpose_motion(
    shape: BodyShape, rng: np.random.Generator, seconds: float, static_start_s: float
) -> Motion:
    from mocaprig.process.body.procedural import make_motion

    return make_motion("t_pose", seconds=seconds, rng=rng, shape=shape)


#: The named scenarios.
SCENARIOS: Mapping[str, ScenarioRecipe] = MappingProxyType(
    {
        r.name: r
        for r in (
            ScenarioRecipe(
                "default",
                "T-pose static start, then wave, squat, clap, jumping jacks, punch and kick",
                1.0,
                _default_motion,
            ),
            ScenarioRecipe(
                "karate",
                "T-pose static start, then fast karate punches and kicks",
                1.0,
                _karate_motion,
            ),
            ScenarioRecipe(
                "tpose", "a static T-pose (tiny sway) for the whole session", 1.0, _tpose_motion
            ),
        )
    }
)


@dataclass(frozen=True, slots=True, eq=False)
class Scenario:
    """A seeded simulated world (see the module doc).

    Attributes:
        name: Scenario name (a key of :data:`SCENARIOS`, or ``"bvh"``).
        seed: The seed everything derives from.
        duration_ns: Session length (ns).
        static_start_s: Length of the static start (s).
        shape: The actor's body.
        markers: The actor's marker set, placement jitter applied.
        motion: The actor's motion; clip time 0 is session time 0 (clamped after its end).
        motion_source: ``"procedural:<scenario>"`` or the BVH path.
        rig: Cameras and the Vicon system.
        clocks: Device clocks by device name (``"davis"``, ``"d415-0"``…, ``"vicon"``).
        clapperboard: The clapperboard.
        noise: Noise settings.
        vicon_start_ns: Session time the Vicon capture starts.
        vicon_end_ns: Session time the Vicon capture stops.
        world_params: The hidden world parameters (:class:`WorldParams`; nominal by default),
            ground truth the calibration is never told.
    """

    name: str
    seed: int
    duration_ns: int
    static_start_s: float
    shape: BodyShape = field(repr=False)
    markers: MarkerSet = field(repr=False)
    motion: Motion = field(repr=False)
    motion_source: str
    rig: Rig = field(repr=False)
    clocks: Mapping[str, DeviceClock] = field(repr=False)
    clapperboard: Clapperboard = field(repr=False)
    noise: NoiseSettings = field(repr=False)
    vicon_start_ns: int = 0
    vicon_end_ns: int = 0
    world_params: WorldParams = field(default_factory=WorldParams.nominal, repr=False)

    @property
    def seconds(self) -> float:
        """Session length (s)."""
        return self.duration_ns * 1e-9

    @property
    def marker_names(self) -> tuple[str, ...]:
        """Body marker names, in the order of the marker axis."""
        return tuple(self.markers.names)

    @property
    def clap_times_ns(self) -> tuple[int, ...]:
        """Clapperboard contact instants (session ns)."""
        return self.clapperboard.clap_times_ns

    def rng(self, stream: str) -> np.random.Generator:
        """A fresh generator for a named random stream (same draws for the same seed)."""
        return stream_rng(self.seed, stream)

    def pose(self, t_ns: npt.ArrayLike) -> F64:
        """Pose vectors at session times (int ns), shape ``t_ns.shape + (33,)``."""
        t = _times(t_ns)
        return self.motion.sample(t.astype(np.float64) * 1e-9)

    def sample(self, t_ns: npt.ArrayLike) -> WorldSample:
        """Everything at once for 1-D session times (int ns): one forward-kinematics pass."""
        from mocaprig.process.body.kinematics import forward_kinematics
        from mocaprig.process.body.markers import marker_positions

        t = _times(t_ns).reshape(-1)
        pose = self.motion.sample(t.astype(np.float64) * 1e-9)
        kin = forward_kinematics(pose, self.shape)
        markers = marker_positions(kin, self.shape, self.markers)
        rot = kin.rotations[:, self.markers.joint_index]
        normals = (rot @ self.markers.normals[..., None])[..., 0]
        return WorldSample(
            t, pose, kin.positions_m, markers, normals, self.clapperboard.markers_m(t)
        )

    def joints_m(self, t_ns: npt.ArrayLike) -> F64:
        """Joint positions (m) at session times, shape ``t_ns.shape + (26, 3)``."""
        from mocaprig.process.body.kinematics import forward_kinematics

        t = _times(t_ns)
        return forward_kinematics(self.pose(t), self.shape).positions_m

    def markers_m(self, t_ns: npt.ArrayLike) -> F64:
        """Body marker centres (m) at session times, shape ``t_ns.shape + (M, 3)``."""
        from mocaprig.process.body.kinematics import forward_kinematics
        from mocaprig.process.body.markers import marker_positions

        t = _times(t_ns)
        kin = forward_kinematics(self.pose(t), self.shape)
        return marker_positions(kin, self.shape, self.markers)

    def clapper_markers_m(self, t_ns: npt.ArrayLike) -> F64:
        """Clapperboard marker centres (m), shape ``t_ns.shape + (2, 3)``, TOP then BOTTOM."""
        return self.clapperboard.markers_m(_times(t_ns))

    def camera(self, name: str) -> PinholeCamera:
        """A rig camera by name (``"d415-0"``…, ``"davis"``)."""
        return self.rig.camera(name)

    def camera_pose(self, name: str) -> F64:
        """``T_world_cam`` (4×4) of a rig camera; cameras are static for the session."""
        return np.array(self.rig.camera(name).T_world_cam)


def _times(t_ns: npt.ArrayLike) -> I64:
    arr = np.asarray(t_ns)
    if arr.dtype.kind not in "iu":
        msg = f"session times must be integer nanoseconds, got dtype {arr.dtype}"
        raise ValidationError(msg)
    return arr.astype(np.int64)


def _bvh_motion(
    path: Path,
    shape: BodyShape,
    seconds: float,
    progress: Callable[[int, int], None] | None,
    joint_map: Mapping[str, str] | None = None,
) -> Motion:
    from mocaprig.process.body.bvh import read_bvh, retarget_bvh
    from mocaprig.process.body.motion import Motion

    clip = read_bvh(path, joint_map=joint_map)
    # Only the frames the session uses are retargeted (the fit costs ~30 ms per frame).
    needed = int(np.ceil(seconds / clip.frame_time_s)) + 2
    if clip.frames.shape[0] > needed:
        clip = replace(clip, frames=clip.frames[:needed])
    motion = retarget_bvh(clip, shape, progress=progress)
    poses = np.array(motion.poses)
    # Centre the clip horizontally so the actor starts at the middle of the rig.
    poses[:, 3:5] -= poses[0, 3:5]
    return Motion(motion.name, motion.rate_hz, poses)


def d415_timing_preset(timing: D415Timing | PulseAt) -> D415Timing:
    """A :class:`~mocaprig.drivers_mock.rig.D415Timing` as given, or the preset named by its
    ``pulse_at`` (``"exposure-start"`` or ``"readout-start"``).

    Raises:
        ValidationError: another name.
    """
    if isinstance(timing, D415Timing):
        return timing
    presets: dict[str, Callable[[], D415Timing]] = {
        "exposure-start": D415Timing.exposure_start,
        "readout-start": D415Timing.readout_start,
    }
    make = presets.get(timing)
    if make is not None:
        return make()
    msg = (
        f"d415_timing must be a D415Timing or one of 'exposure-start', 'readout-start', got "
        f"{timing!r}"
    )
    raise ValidationError(msg)


def build_scenario(
    name: str = "default",
    *,
    seed: int,
    seconds: float,
    motion_path: str | Path | None = None,
    noise: NoiseSettings | None = None,
    progress: Callable[[int, int], None] | None = None,
    d415_timing: D415Timing | PulseAt | None = None,
    joint_map: Mapping[str, str] | None = None,
    world: WorldKind | WorldParams = "nominal",
) -> Scenario:
    """Build a seeded scenario.

    Args:
        name: A key of :data:`SCENARIOS` (ignored for the motion when ``motion_path`` is given).
        seed: Any non-negative integer; the same seed gives the same world.
        seconds: Session length (s), at least 3 s (two claps must fit).
        motion_path: A BVH file to retarget onto the actor instead of the procedural motion
            (no static start; the clip holds its last pose if it is shorter than the session).
        noise: Noise settings (default :class:`NoiseSettings`).
        progress: Optional ``(done, total)`` callback of the BVH retargeting (the slow part).
        d415_timing: The rig's undocumented D415 sync timing (``Rig.d415_timing``, which the
            mock D415s, hence the DAVIS trigger input, the sync box and the Vicon sync channel,
            follow): a :class:`~mocaprig.drivers_mock.rig.D415Timing`, or a preset's name,
            ``"exposure-start"`` (:meth:`D415Timing.exposure_start`, the default) or
            ``"readout-start"`` (:meth:`D415Timing.readout_start`). It draws nothing: the
            same seed gives the same actor, rig poses and clocks under either timing.
        joint_map: Our joint name -> BVH joint name for ``motion_path``'s skeleton
            (:func:`~mocaprig.process.body.bvh.load_joint_map`; ``--joint-map``).
        world: The hidden world parameters (:mod:`~mocaprig.drivers_mock.world`):
            ``"nominal"`` (the default: the simulator's long-standing values, the same
            sessions as before), ``"random"`` (drawn from the scenario's ``"world"`` stream,
            the ranges a real rig can have) or a :class:`WorldParams`. They set the D415
            pulse phase and slave delay (an explicit ``d415_timing`` wins), the clocks'
            drifts, the Vicon occlusion gaps and the clapperboard's closing law here; the
            mocks read the rest from :attr:`Scenario.world_params`.

    Raises:
        ValidationError: unknown scenario, bad seed or length, unknown timing preset or world.
        ProcessingError: the BVH file cannot be read or retargeted.
    """
    from mocaprig.process.body.markers import MarkerSet
    from mocaprig.process.body.shape import BodyShape

    if name not in SCENARIOS:
        msg = f"unknown scenario {name!r}; choose one of {sorted(SCENARIOS)}"
        raise ValidationError(msg)
    if not isinstance(seed, int | np.integer) or seed < 0:
        msg = f"seed must be a non-negative integer, got {seed!r}"
        raise ValidationError(msg)
    seed = int(seed)
    check_positive(float(seconds), name="seconds")
    if seconds > MAX_SECONDS:
        msg = f"seconds must be at most {MAX_SECONDS:g} s, got {seconds:g}; split the session"
        raise ValidationError(msg)
    noise = NoiseSettings() if noise is None else noise
    recipe = SCENARIOS[name]
    params = _world_params(world, seed)
    if params.vicon_gap_fraction is not None or params.vicon_facing_weight is not None:
        noise = replace(
            noise,
            vicon_gap_fraction=_or(params.vicon_gap_fraction, noise.vicon_gap_fraction),
            vicon_facing_weight=_or(params.vicon_facing_weight, noise.vicon_facing_weight),
        )
    duration_ns = round(seconds * 1e9)

    shape = BodyShape.sample(stream_rng(seed, "shape"))
    markers = MarkerSet.for_shape(shape)
    if noise.marker_placement_sigma_m > 0:
        markers = markers.jittered(
            stream_rng(seed, "marker-placement"), sigma_m=noise.marker_placement_sigma_m
        )
    if motion_path is not None:
        path = Path(motion_path)
        static_start_s = 0.0
        motion = _bvh_motion(path, shape, seconds, progress, joint_map)
        source = str(path)
        scenario_name = "bvh"
        if motion.duration_s < seconds:
            _log.warning(
                "BVH motion %s lasts %.2f s, less than the %.2f s session; it holds its last pose",
                path,
                motion.duration_s,
                seconds,
            )
    else:
        static_start_s = min(recipe.static_start_s, 0.2 * seconds)
        motion = recipe.build_motion(shape, stream_rng(seed, "motion"), seconds, static_start_s)
        source = f"procedural:{name}"
        scenario_name = name

    rig = default_rig(stream_rng(seed, "rig"))
    if d415_timing is not None:
        rig = replace(rig, d415_timing=d415_timing_preset(d415_timing))
    elif params.pulse_at is not None or params.slave_trigger_delay_us is not None:
        timing = replace(rig.d415_timing, pulse_at=params.pulse_at or rig.d415_timing.pulse_at)
        if params.slave_trigger_delay_us is not None:
            timing = replace(timing, trigger_to_exposure_us=params.slave_trigger_delay_us)
        rig = replace(rig, d415_timing=timing)
    clock_rng = stream_rng(seed, "clocks")
    clocks: dict[str, DeviceClock] = {"davis": davis_clock(clock_rng)}
    for d in rig.d415:
        clocks[d.name] = d415_clock(clock_rng, name=d.name)
    clocks["vicon"] = vicon_clock(clock_rng, rate_hz=rig.vicon.rate_hz)
    clocks = _with_drifts(clocks, params, [d.name for d in rig.d415])
    if not noise.clock_jitter:
        clocks = {
            k: DeviceClock(c.name, c.offset_ns, c.drift_ppm, 0.0, c.unit_ns, c.seed)
            for k, c in clocks.items()
        }
    clapper = make_clapperboard(
        stream_rng(seed, "clapperboard"),
        seconds=seconds,
        static_start_s=static_start_s,
        closing_s=params.clap_closing_s,
        closing_power=params.clap_power,
        bounce_rad=params.clap_bounce_rad,
        bounce_s=params.clap_bounce_s,
    )
    vrng = stream_rng(seed, "vicon-window")
    vicon_start_ns = round(vrng.uniform(0.05, 0.25) * 1e9)
    vicon_end_ns = duration_ns - round(vrng.uniform(0.05, 0.2) * 1e9)
    scenario = Scenario(
        name=scenario_name,
        seed=seed,
        duration_ns=duration_ns,
        static_start_s=static_start_s,
        shape=shape,
        markers=markers,
        motion=motion,
        motion_source=source,
        rig=rig,
        clocks=MappingProxyType(clocks),
        clapperboard=clapper,
        noise=noise,
        vicon_start_ns=vicon_start_ns,
        vicon_end_ns=vicon_end_ns,
        world_params=params,
    )
    _log.debug("built scenario %s seed %d (%.2f s)", scenario_name, seed, seconds)
    return scenario


def _or(value: float | None, default: float) -> float:
    return default if value is None else value


def _world_params(world: WorldKind | WorldParams, seed: int) -> WorldParams:
    """The hidden parameters: given, nominal, or drawn from the seed's ``"world"`` stream."""
    if isinstance(world, WorldParams):
        return world
    kind = str(world)  # callers outside the type checker may pass anything
    if kind == "nominal":
        return WorldParams.nominal()
    if kind == "random":
        return WorldParams.draw(stream_rng(seed, "world"))
    msg = f"world must be a WorldParams or one of {list(WORLD_KINDS)}, got {world!r}"
    raise ValidationError(msg)


def _with_drifts(
    clocks: dict[str, DeviceClock], params: WorldParams, d415_names: list[str]
) -> dict[str, DeviceClock]:
    """The clocks with the world's drifts where it sets them (offsets and seeds kept)."""
    drifts: dict[str, float] = {}
    if params.d415_drift_ppm is not None:
        drifts.update(zip(d415_names, params.d415_drift_ppm, strict=False))
    if params.davis_drift_ppm is not None:
        drifts["davis"] = params.davis_drift_ppm
    if params.vicon_drift_ppm is not None:
        drifts["vicon"] = params.vicon_drift_ppm
    return {k: replace(c, drift_ppm=drifts[k]) if k in drifts else c for k, c in clocks.items()}
