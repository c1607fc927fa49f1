"""Inference: a fused marker cloud (world, m) -> 53 labelled markers + 19 joints (world, m).

Every network variant (``DemocapConfig.variant``) decodes the same way: per-view keypoints
(CoM3D of the heat maps, or the regressed coordinates), Eq. 7 fusion, inverse normalisation.
The ``"pose"`` baseline predicts no markers: its marker estimates are NaN.

**Rotation ensemble** (``rotations=K``, a test-time augmentation; the paper is single-shot,
K = 1): the centred cloud is also turned about the vertical axis by ``k·180°/K`` (k = 1 …
K-1), each turned cloud goes through the network as the paper's front/back pair, the
estimates are turned back, and the K estimates are combined per coordinate (median, or mean).
Turns of 180° would add nothing: the back view of a cloud is the front view of the cloud
turned by 180°. The network is trained with ±180° rotation augmentation, so every turn is a
valid input; its errors at different turns are largely independent, so the median removes
much of them (docs/democap.md, "Rotation ensemble"), at K times the network cost.

**Inference copy** (``optimise=True``): the predictor runs a copy of the network with every
convolution's batch norm folded into its weights, in channels-last memory layout: the same
function (outputs within float32 rounding), about a quarter less time on a CPU. The
checkpoint's own model is left as it is (training and resuming use it).

**Compiled network** (``compile=True``; off by default, on in the live predictor): the
network stage (both views, CoM3D decoding and the fusion) runs through ``torch.compile``
(inductor, the weights frozen as constants, a static shape): about a quarter less time a
pass on the 2-core CPU (docs/democap.md, "Speed"), the estimates the same to float
rounding. The first pass compiles it for its batch size, 10-30 s (a C++ compiler is
needed; inductor caches the result on disk, ``TORCHINDUCTOR_CACHE_DIR``); passes of any
other size run uncompiled, so that a live stream never stalls on a second compile (a
sparse cloud's further turns with the solve). Where compiling fails the predictor logs why
and runs the network as it is.

**Skeleton solve** (``solve=True``, the default): the body model is fitted to the cloud
from the ensemble's estimate and from each turn's (:mod:`.solve`); the fit that explains the
cloud best gives the markers and joints, and the solved pose and height come with them. With
``rotations=1`` the single estimate is the one start. Off (``solve=False``) the estimates are
the network's alone (the paper's output; live use at a high frame rate). The ``"pose"``
baseline has no markers to fit: it is never solved.

**Sparse clouds** (``sparse_rotations``, ``sparse_points``): with the solve and an ensemble,
a cloud of fewer than :data:`SPARSE_POINTS` points (half the detections, a limb hidden, few
cameras) is solved from :data:`SPARSE_ROTATIONS` turns: the turns the ensemble lacks go
through the network for those clouds alone, and the solve starts from their median and from
every turn. The network's estimates of a sparse cloud are far off, and more starts find the
body more often (docs/democap.md); a dense cloud costs nothing more.

**Pose bank** (``pose_bank=True``, the default with the solve): a cloud the solve explains
poorly (energy per point above ``BankSearch.energy_per_point``) is solved once more from the
best placements of the committed bank of real poses (:mod:`.pose_bank`), and the solution
that explains the cloud better is kept: where the network is far off every start is, and the
bank's are not.

**Re-solve** (``resolve_rounds``, :data:`RESOLVE_ROUNDS` by default): a cloud still explained
poorly after that is solved again from its own solution, round after round. The solve's
prior terms then pull toward that solution, not toward the network's estimate (which is what
held it in a wrong minimum), and its bent starts, gate schedule and limb search run again
from there; a round's solution is kept only where it explains the cloud better, and a cloud
a round did not improve is left (the next would start where it did). On the
validation frames (none of them test frames) 2 rounds took the bent train-clip frames from
21.6 to 15.7 mm, procedural freestyle from 21.7 to 19.2 and the corpus validation walks from
10.1 to 9.5; with the bank built without the frames' activity, dance 48.0 -> 28.2 and the
playground 108.5 -> 93.5 mm (docs/democap.md, "Re-solve").

**Batched turns** (``workers=1``, the default): the front/back views of every turn (and every
cloud) go through the network as one batch, ``2·K·B`` views: one pass instead of K, which on a
CPU costs about 15 % less than K passes of 2 views (fewer per-operation overheads for the
small ``lite`` network; the estimates are the same, bit for bit on the machine here).
"""

from __future__ import annotations

import copy
import functools
import logging
import threading
import time
import weakref
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt
import torch
from scipy.spatial.transform import Rotation
from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from mocaprig.errors import ValidationError
from mocaprig.process.body import DEMOCAP_JOINT_INDEX, NUM_MARKERS, POSE_DIM
from mocaprig.process.democap.checkpoint import DEFAULT_CHECKPOINT, Checkpoint, load_checkpoint
from mocaprig.process.democap.dataset import prepare_cloud
from mocaprig.process.democap.geometry import Normalisation, to_world_frame
from mocaprig.process.democap.model import (
    DemocapModel,
    DemocapOutput,
    fuse_views_torch,
    view_keypoints,
)
from mocaprig.process.democap.pose_bank import BankSearch, PoseBank, bank_starts, load_pose_bank
from mocaprig.process.democap.pose_prior import PosePrior, load_pose_prior
from mocaprig.process.democap.simdata import Box, Camera
from mocaprig.process.democap.solve import (
    SHAPE_DIM,
    SolveOptions,
    SolveResult,
    SubjectCalibration,
    calibrate_subject,
    solve_skeleton,
)
from mocaprig.validation import check_finite, check_shape

__all__ = [
    "DEFAULT_ROTATIONS",
    "RESOLVE_ROUNDS",
    "SPARSE_POINTS",
    "SPARSE_ROTATIONS",
    "Combine",
    "DemocapPredictor",
    "Prediction",
    "SubjectPredictions",
    "decode",
    "ensemble_rotations",
]

_log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
#: The default size of the rotation ensemble: three turns (0°, 60°, 120°) meet the accuracy
#: targets on held-out data at three times the single shot's network cost (docs/democap.md).
DEFAULT_ROTATIONS = 3
#: A cloud with fewer points than this is *sparse* (a nominal 4-camera cloud of the 53
#: markers has 110-145 after the merge; half the detections leave 60-90): its solve starts
#: from :data:`SPARSE_ROTATIONS` turns (docs/democap.md, "Skeleton solve").
SPARSE_POINTS = 100
#: The ensemble a sparse cloud's solve starts from (the turns of the default's among them).
SPARSE_ROTATIONS = 6
#: Default rounds of the re-solve (module doc).
RESOLVE_ROUNDS = 2
#: How the rotation ensemble's estimates are combined, per coordinate.
Combine = Literal["median", "mean"]


@dataclass(frozen=True, slots=True)
class Prediction:
    """One frame's estimate, world frame, metres: markers (53, 3) and joints (19, 3).

    The markers are all NaN for a network that does not estimate them (the ``"pose"``
    baseline; :attr:`DemocapPredictor.predicts_markers`).
    """

    markers_m: FloatArray
    joints_m: FloatArray
    #: the solved body's pose vector (33,) (:mod:`process.body.skeleton`), None unsolved
    pose: FloatArray | None = None
    #: the solved body's standing height, m; None unsolved
    height_m: float | None = None


@dataclass(frozen=True, slots=True)
class SubjectPredictions:
    """:meth:`DemocapPredictor.predict_subject`'s result, one entry per cloud in order.

    Attributes:
        predictions: solved with the subject's calibration.
        calibration: the subject (:class:`solve.SubjectCalibration`).
        frame_by_frame: each cloud solved on its own (what :meth:`predict_many` gives).
    """

    predictions: list[Prediction]
    calibration: SubjectCalibration
    frame_by_frame: list[Prediction]


def decode(
    net: DemocapModel, front: torch.Tensor, back: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Both views through ``net`` in one batch, per-view keypoints (CoM3D, or the regressed
    coordinates), Eq. 7 fusion -> normalised front-frame markers (B, 53, 3) and joints
    (B, 19, 3). The markers are NaN for a network without them (``"pose"``)."""
    b = front.shape[0]
    out: DemocapOutput = net(torch.cat([front, back], dim=0))
    m, j = view_keypoints(out)
    joints = fuse_views_torch(j[:b], j[b:])
    if m is None:
        nan = torch.full((b, net.num_markers, 3), float("nan"), dtype=j.dtype, device=j.device)
        return nan, joints
    return fuse_views_torch(m[:b], m[b:]), joints


def ensemble_rotations(k: int) -> list[FloatArray]:
    """The ``k`` turns (3, 3) of the rotation ensemble: ``i·180°/k`` about the image frame's
    vertical axis (y), i = 0 … k-1; the first is the identity.

    Raises:
        ValidationError: ``k`` < 1.
    """
    if k < 1:
        msg = f"rotations must be >= 1 (1: the paper's single shot), got {k}"
        raise ValidationError(msg)
    return [
        np.asarray(Rotation.from_euler("y", 180.0 * i / k, degrees=True).as_matrix())
        for i in range(k)
    ]


def _checked(clouds: Sequence[npt.ArrayLike]) -> list[FloatArray]:
    """Clouds (N, 3) as float64 arrays.

    Raises:
        ValidationError: a cloud of the wrong shape or with non-finite values.
    """
    return [
        np.asarray(check_finite(check_shape(c, ["N", 3], name="cloud")), np.float64) for c in clouds
    ]


_Decode = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]


class _CompiledDecode:
    """:func:`decode` of one network through ``torch.compile`` for the first batch shape it
    is called with (module doc, "Compiled network"); any other shape runs uncompiled (a
    second compile would stall a live stream for seconds), as does everything once
    compiling has failed."""

    def __init__(self, net: DemocapModel) -> None:
        self._eager: _Decode = functools.partial(decode, net)
        # freezing: the weights become constants (folded, pre-packed for the CPU); one
        # compile thread: no worker processes spawned behind the caller's back
        self._compiled: _Decode = torch.compile(
            self._eager, dynamic=False, options={"freezing": True, "compile_threads": 1}
        )
        self._lock = threading.Lock()
        #: the batch shape compiled for (front and back views); None until the first call
        self.shape: tuple[int, ...] | None = None
        #: why compiling failed (the network then runs as it is); None while it works
        self.failure: str | None = None

    def __call__(
        self, front: torch.Tensor, back: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        key = (*front.shape, *back.shape)
        if self.shape is None and self.failure is None:
            with self._lock:  # one thread compiles; a second one waits for it
                if self.shape is None and self.failure is None:
                    return self._first(key, front, back)
        if key == self.shape and self.failure is None:
            return self._compiled(front, back)
        return self._eager(front, back)

    def _first(
        self, key: tuple[int, ...], front: torch.Tensor, back: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        t0 = time.perf_counter()
        _log.info("compiling the DeMoCap network for batches of %d views (once)", key[0] * 2)
        try:
            out = self._compiled(front, back)
        # Any failure of the compiler stack (no C++ compiler, an unsupported CPU or
        # platform) leaves the network itself working: run it as it is.
        except Exception as err:
            self.failure = f"{type(err).__name__}: {err}".splitlines()[0]
            _log.warning(
                "torch.compile of the DeMoCap network failed (%s); it runs uncompiled "
                "(slower: see docs/democap.md, 'Speed')",
                self.failure,
            )
            return self._eager(front, back)
        self.shape = key
        _log.info("compiled in %.1f s", time.perf_counter() - t0)
        return out


def _inference_copy(net: DemocapModel) -> DemocapModel:
    """A copy of ``net`` (eval mode) with each Conv2d -> BatchNorm2d pair of a Sequential
    folded into one convolution (the batch norm removed), in channels-last layout."""
    out = copy.deepcopy(net).eval()
    for mod in out.modules():
        if isinstance(mod, nn.Sequential):
            i = 0
            while i < len(mod) - 1:
                conv, bn = mod[i], mod[i + 1]
                if isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d):
                    mod[i] = fuse_conv_bn_eval(conv, bn)
                    del mod[i + 1]  # no Identity left behind: one module call less
                i += 1
    out.to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # in place
    return out


class DemocapPredictor:
    """A loaded network ready for inference (eval mode, no gradients).

    Args:
        checkpoint: a :class:`Checkpoint`, a path, or ``None`` for the committed ``lite`` one.
        rotations: size K of the rotation ensemble (module doc); 1 is the paper's single shot
            (the fastest: live use at a high frame rate).
        combine: how the K estimates are combined per coordinate.
        optimise: run the folded, channels-last inference copy of the network (module doc).
        compile: run the network stage through ``torch.compile`` (module doc, "Compiled
            network"): a quarter faster after 10-30 s of compiling, for passes of the first
            pass's batch size; for a process that runs many passes of one size (live use).
        solve: fit the body model to the cloud from the network's estimates (module doc);
            ignored for a network without markers (the ``"pose"`` baseline).
        solve_options: the solve's weights and schedule (default :class:`SolveOptions`).
        sparse_rotations: with the solve and an ensemble (``rotations`` > 1), a cloud of
            fewer than ``sparse_points`` points is solved from an ensemble of this many
            turns instead (the turns not already run go through the network for it alone):
            where the cloud is sparse the network's estimates are far off and more starts
            find the body more often; ``None`` (or no more than ``rotations``) for never.
        pose_bank: with the solve, a cloud the solve explains poorly (``bank_search``'s
            ``energy_per_point``) is solved once more from the best placements of a bank of
            real poses (:mod:`.pose_bank`), and whichever solution explains it better is
            kept: where every network start is far off (a body bent double, a pose of an
            activity never trained on) a bank pose is often near. True: the committed bank;
            False: none; or a :class:`PoseBank`.
        bank_search: how the bank is searched (default :class:`BankSearch`).
        pose_prior: with the solve, a prior over the joint angles of real motion
            (:mod:`.pose_prior`) in every solve, at the solve options'
            ``pose_prior_weight``: what holds a limb the cloud says little about (half its
            markers missed, a hand above every view). True: the committed prior; False:
            none; or a :class:`PosePrior`.
        resolve_rounds: with the solve, how many times a cloud still explained poorly
            (``bank_search``'s ``energy_per_point``) is solved again from its own solution
            (module doc); 0 for never.
        workers: how many network passes the K turns are split into, run at once: 1 (the
            default) puts the front/back views of all turns in one batch on the calling
            thread (the least work); ``W`` > 1 makes ``min(W, K)`` batches of consecutive
            turns, the first on the calling thread and the others on threads the predictor
            keeps (made on first use). Each pass uses torch's own thread setting, which the
            caller owns. The estimates do not depend on it (the same to float rounding).
        subject_calibration: with the solve, callers that know which frames show one
            subject (:func:`evaluate.evaluate`: a take) estimate them with
            :meth:`predict_subject` (calibrated, then solved again); this many rounds of
            calibration, 0 for none (the default: every frame on its own).
        subject: with the solve, a calibrated subject (:mod:`.subject`, a subject file) every
            cloud is solved as: its lengths and marker placement held, not sampled frame by
            frame (None: every frame on its own). Given to every solve: for clouds of
            someone else it is wrong.

    Raises:
        ProcessingError: the checkpoint is missing or does not match (see
            :func:`load_checkpoint`).
        ValidationError: ``rotations`` or ``workers`` < 1, ``resolve_rounds`` or
            ``subject_calibration`` < 0, or an unknown ``combine``.
    """

    def __init__(
        self,
        checkpoint: Checkpoint | Path | None = None,
        *,
        rotations: int = DEFAULT_ROTATIONS,
        combine: Combine = "median",
        optimise: bool = True,
        compile: bool = False,
        solve: bool = True,
        solve_options: SolveOptions | None = None,
        sparse_rotations: int | None = SPARSE_ROTATIONS,
        sparse_points: int = SPARSE_POINTS,
        pose_bank: PoseBank | bool = True,
        bank_search: BankSearch | None = None,
        pose_prior: PosePrior | bool = True,
        resolve_rounds: int = RESOLVE_ROUNDS,
        workers: int = 1,
        subject_calibration: int = 0,
        subject: SubjectCalibration | None = None,
    ) -> None:
        self._turns = ensemble_rotations(int(rotations))
        # the sparse ensemble's turns that the ensemble does not run already
        self._sparse_turns: list[FloatArray] = []
        if sparse_rotations is not None and len(self._turns) > 1:
            self._sparse_turns = [
                r
                for r in ensemble_rotations(int(sparse_rotations))
                if not any(np.allclose(r, t, atol=1e-9) for t in self._turns)
            ]
        #: the cloud size below which the solve starts from the larger ensemble, and its size
        #: (None: never)
        self.sparse_points = int(sparse_points)
        self.sparse_rotations = (
            len(self._turns) + len(self._sparse_turns) if self._sparse_turns else None
        )
        if combine not in ("median", "mean"):
            msg = f"combine must be 'median' or 'mean', got {combine!r}"
            raise ValidationError(msg)
        if workers < 1:
            msg = f"workers must be >= 1, got {workers}"
            raise ValidationError(msg)
        if resolve_rounds < 0 or subject_calibration < 0:
            msg = (
                "resolve_rounds and subject_calibration must be >= 0, got "
                f"{resolve_rounds} and {subject_calibration}"
            )
            raise ValidationError(msg)
        ckpt = (
            checkpoint
            if isinstance(checkpoint, Checkpoint)
            else load_checkpoint(DEFAULT_CHECKPOINT if checkpoint is None else Path(checkpoint))
        )
        self.checkpoint = ckpt
        self.net = ckpt.model.eval()
        self._run_net: DemocapModel = _inference_copy(self.net) if optimise else self.net
        self._channels_last = optimise
        self._decode: _Decode = (
            _CompiledDecode(self._run_net) if compile else functools.partial(decode, self._run_net)
        )
        self.size_px = ckpt.config.input_px
        #: size of the rotation ensemble (1: single shot)
        self.rotations = len(self._turns)
        self.combine: Combine = combine
        self.workers = int(workers)
        self._pool: ThreadPoolExecutor | None = None
        self._pool_lock = threading.Lock()
        #: whether the network estimates the markers (not the ``"pose"`` baseline)
        self.predicts_markers = ckpt.config.predicts_markers
        #: whether the estimates are solved skeletons (module doc)
        self.solves = bool(solve) and self.predicts_markers
        self.solve_options = solve_options or SolveOptions()
        #: the bank of real poses the solve also starts from (None: the network's starts only)
        self.pose_bank: PoseBank | None = None
        if self.solves and pose_bank is not False:
            self.pose_bank = load_pose_bank() if pose_bank is True else pose_bank
        self.bank_search = bank_search or BankSearch()
        #: the prior over joint angles every solve holds (None: none)
        self.pose_prior: PosePrior | None = None
        if self.solves and pose_prior is not False:
            self.pose_prior = load_pose_prior() if pose_prior is True else pose_prior
        #: rounds of the re-solve (module doc)
        self.resolve_rounds = int(resolve_rounds)
        #: rounds of subject calibration for frames known to show one subject (0: none)
        self.subject_calibration = int(subject_calibration) if self.solves else 0
        if subject is not None and not isinstance(subject, SubjectCalibration):
            msg = f"subject must be a SubjectCalibration (load_subject), got {type(subject)}"  # type: ignore[unreachable]
            raise ValidationError(msg)
        #: the subject every cloud is solved as (None: every frame on its own)
        self.subject = subject if self.solves else None
        #: seconds spent per stage by the last :meth:`predict_many` call
        self.last_timings_s: dict[str, float] = {}

    @property
    def compiled(self) -> bool:
        """Whether the network stage runs compiled: ``compile=True`` and no compiling has
        failed so far (module doc, "Compiled network")."""
        return isinstance(self._decode, _CompiledDecode) and self._decode.failure is None

    def warm_up(self) -> float:
        """One network pass over a made-up cloud (a 1.75 m column of points): a compiled
        network compiles now, for the one-cloud batches of a live stream, not on the first
        real cloud (live capture calls it before it starts the cameras). Returns the seconds
        it took."""
        t0 = time.perf_counter()
        z = np.linspace(0.05, 1.75, 60)
        cloud = np.stack([0.15 * np.cos(7.0 * z), 0.15 * np.sin(7.0 * z), z], axis=1)
        self._hypotheses([cloud])
        return time.perf_counter() - t0

    def predict(self, raw_m: npt.ArrayLike) -> Prediction:
        """One fused cloud (N, 3), world, m -> :class:`Prediction`.

        Raises:
            ValidationError: wrong shape, non-finite values or fewer than 2 points.
        """
        return self.predict_many([raw_m])[0]

    def _pass(self, front: torch.Tensor, back: torch.Tensor) -> tuple[FloatArray, FloatArray]:
        """One network pass: front/back views (N, 1, S, S) -> fused markers and joints."""
        if self._channels_last:
            front = front.contiguous(memory_format=torch.channels_last)
            back = back.contiguous(memory_format=torch.channels_last)
        with torch.inference_mode():
            m, j = self._decode(front, back)
        return m.double().numpy(), j.double().numpy()

    def _network(self, fronts: torch.Tensor, backs: torch.Tensor) -> tuple[FloatArray, FloatArray]:
        """The network stage: views (K, B, 1, S, S) of the K turns -> fused markers
        (K, B, 53, 3) and joints (K, B, 19, 3), normalised. The turns are split into
        ``min(workers, K)`` groups of consecutive turns, each group one batched pass; the
        first runs on the calling thread, the others on the predictor's own threads."""
        k, b = fronts.shape[:2]
        groups = np.array_split(np.arange(k), min(self.workers, k))

        def run(g: npt.NDArray[np.intp]) -> tuple[FloatArray, FloatArray]:
            lo, hi = int(g[0]), int(g[-1]) + 1
            return self._pass(fronts[lo:hi].flatten(0, 1), backs[lo:hi].flatten(0, 1))

        futures = [self._executor().submit(run, g) for g in groups[1:]]
        outs = [run(groups[0])] + [f.result() for f in futures]
        m = np.concatenate([o[0] for o in outs]).reshape(k, b, -1, 3)
        j = np.concatenate([o[1] for o in outs]).reshape(k, b, -1, 3)
        return m, j

    def _executor(self) -> ThreadPoolExecutor:
        """The predictor's threads for the groups of turns beyond the first (made once, on
        first use; shut down when the predictor is collected)."""
        with self._pool_lock:
            if self._pool is None:
                pool = ThreadPoolExecutor(self.workers - 1, thread_name_prefix="democap-turns")
                weakref.finalize(self, pool.shutdown, wait=False)
                self._pool = pool
            return self._pool

    def hypotheses(
        self, clouds: Sequence[npt.ArrayLike]
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """The network's estimates of several clouds, before any solve: the combined
        ensemble's markers (B, 53, 3) and joints (B, 19, 3), then each turn's markers
        (K, B, 53, 3) and joints (K, B, 19, 3), world frame, m. All turns of all clouds go
        through one network batch per worker (module doc); ``last_timings_s`` has the stages.

        Raises:
            ValidationError: a cloud of the wrong shape, with non-finite values or with fewer
                than 2 points.
        """
        return self._hypotheses(_checked(clouds))

    def _hypotheses(
        self, points: list[FloatArray]
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """:meth:`hypotheses` of clouds already checked."""
        mk, jt = self._turn_estimates(points, self._turns)
        t0 = time.perf_counter()
        markers, joints = self._combine(mk), self._combine(jt)
        self.last_timings_s["decode_s"] += time.perf_counter() - t0
        return markers, joints, mk, jt

    def _combine(self, estimates: FloatArray) -> FloatArray:
        """The turns' estimates (K, B, ...) combined per coordinate -> (B, ...)."""
        reduce = np.median if self.combine == "median" else np.mean
        return np.asarray(reduce(estimates, axis=0))

    def _turn_estimates(
        self, points: list[FloatArray], turns: list[FloatArray]
    ) -> tuple[FloatArray, FloatArray]:
        """Each turn's estimates of each cloud, world frame, m: markers (K, B, 53, 3) and
        joints (K, B, 19, 3); the stages' times in :attr:`last_timings_s`."""
        t0 = time.perf_counter()
        k, n, s = len(turns), len(points), self.size_px
        nm, nj = self.net.num_markers, self.net.num_joints
        if not points:
            self.last_timings_s = {"render_s": 0.0, "network_s": 0.0, "decode_s": 0.0}
            return np.zeros((k, 0, nm, 3)), np.zeros((k, 0, nj, 3))
        fronts, backs = [], []
        boxes: list[list[tuple[Normalisation, FloatArray]]] = []
        for rot in turns:
            box = []
            for p in points:
                f, b, norm, centre = prepare_cloud(p, rot, size_px=self.size_px)
                fronts.append(f)
                backs.append(b)
                box.append((norm, centre))
            boxes.append(box)
        front_t = torch.from_numpy(np.stack(fronts)).reshape(k, n, 1, s, s)
        back_t = torch.from_numpy(np.stack(backs)).reshape(k, n, 1, s, s)
        t1 = time.perf_counter()
        m, j = self._network(front_t, back_t)
        t2 = time.perf_counter()
        # estimates in the world frame, each turned back
        mk = np.empty((k, n, nm, 3))
        jt = np.empty((k, n, nj, 3))
        for t, (rot, box) in enumerate(zip(turns, boxes, strict=True)):
            for i, (norm, centre) in enumerate(box):
                mk[t, i] = to_world_frame(norm.invert(m[t, i]) @ rot + centre)
                jt[t, i] = to_world_frame(norm.invert(j[t, i]) @ rot + centre)
        t3 = time.perf_counter()
        self.last_timings_s = {"render_s": t1 - t0, "network_s": t2 - t1, "decode_s": t3 - t2}
        return mk, jt

    def _solve(
        self,
        points: list[FloatArray],
        mk: FloatArray,
        jt: FloatArray,
        views: Sequence[Sequence[Camera]] | None,
        crop_box_m: Box | None = None,
        subjects: Sequence[SubjectCalibration | None] | None = None,
    ) -> SolveResult:
        """The solve of ``points`` (``views``: their cameras, ``crop_box_m``: their crop) from
        the turns' estimates (K, B, ...): their combination, then each turn's (a single turn
        is the one start)."""
        markers, joints = self._combine(mk), self._combine(jt)
        hyp_m = markers[None] if len(mk) == 1 else np.concatenate([markers[None], mk])
        hyp_j = joints[None] if len(jt) == 1 else np.concatenate([joints[None], jt])
        return solve_skeleton(
            points,
            hyp_m,
            hyp_j,
            options=self.solve_options,
            views=views,
            crop_box_m=crop_box_m,
            subjects=subjects,
            pose_prior=self.pose_prior,
        )

    def predict_many(
        self,
        clouds: Sequence[npt.ArrayLike],
        *,
        views: Sequence[Sequence[Camera]] | None = None,
        crop_box_m: Box | None = None,
    ) -> list[Prediction]:
        """Several clouds: the network's estimates (:meth:`hypotheses`), then the skeleton
        solve from them when :attr:`solves`. ``views``: per cloud, the calibrated cameras
        that made it; the solve then does not charge a body part for being absent where no
        camera looks (:func:`solve.solve_skeleton`); the network does not use them.
        ``crop_box_m`` (with ``views``): the world box the clouds were cropped to; a body part
        outside it is not charged either.

        Raises:
            ValidationError: a cloud of the wrong shape, with non-finite values or with fewer
                than 2 points; ``views`` not one camera list per cloud; when it solves, a bad
                ``crop_box_m`` or one without ``views`` (:func:`solve.solve_skeleton` checks it).
        """
        _check_views(views, len(clouds))
        points = _checked(clouds)
        if not points:
            return []
        if not self.solves:
            markers, joints, _, _ = self._hypotheses(points)
            return [
                Prediction(markers_m=m, joints_m=j) for m, j in zip(markers, joints, strict=True)
            ]
        _, _, mk, jt = self._hypotheses(points)
        subjects = None if self.subject is None else [self.subject] * len(points)
        return self._solved(points, mk, jt, views, crop_box_m, subjects).predictions()

    def predict_subject(
        self,
        clouds: Sequence[npt.ArrayLike],
        *,
        views: Sequence[Sequence[Camera]] | None = None,
        crop_box_m: Box | None = None,
        rounds: int = 1,
    ) -> SubjectPredictions:
        """Frames of one subject (a take, or a range-of-motion take): solved one by one
        (:meth:`predict_many`), the subject calibrated from them (:func:`calibrate_subject`:
        their segment lengths and where their markers sit), then solved again with the
        calibration, ``rounds`` times. Costs ``1 + rounds`` solves; the network runs once.
        The first, frame-by-frame solutions come with the result. It calibrates anew: the
        predictor's :attr:`subject`, if any, is not used.

        Raises:
            ValidationError: what :meth:`predict_many` raises; a predictor that does not
                solve; fewer than 3 clouds; ``rounds`` < 1.
        """
        if not self.solves:
            msg = "predict_subject needs the skeleton solve (DemocapPredictor(solve=True))"
            raise ValidationError(msg)
        if rounds < 1:
            msg = f"rounds must be >= 1, got {rounds}"
            raise ValidationError(msg)
        _check_views(views, len(clouds))
        points = _checked(clouds)
        if len(points) < 3:
            msg = f"a subject calibration needs at least 3 clouds, got {len(points)}"
            raise ValidationError(msg)
        _, _, mk, jt = self._hypotheses(points)
        sol = self._solved(points, mk, jt, views, crop_box_m, None)
        alone = sol.predictions()
        cal = calibrate_subject(points, sol.result(), views=views, crop_box_m=crop_box_m)
        for k in range(rounds):
            if k:
                cal = calibrate_subject(
                    points, sol.result(), views=views, crop_box_m=crop_box_m, previous=cal
                )
            sol = self._solved(points, mk, jt, views, crop_box_m, [cal] * len(points))
        _log.info(
            "subject calibrated from %d frames (%d round(s)): height %.3f m",
            len(points),
            rounds,
            float(np.median(sol.height_m)),
        )
        return SubjectPredictions(sol.predictions(), cal, alone)

    def _solved(
        self,
        points: list[FloatArray],
        mk: FloatArray,
        jt: FloatArray,
        views: Sequence[Sequence[Camera]] | None,
        crop_box_m: Box | None,
        subjects: Sequence[SubjectCalibration | None] | None,
    ) -> _Solved:
        """The solve of ``points`` from the turns' estimates ``mk, jt`` (K, B, ...) of
        :meth:`_hypotheses`, the pose bank and the re-solves."""
        n = len(points)
        timings = dict(self.last_timings_s)
        sparse = np.array([len(p) < self.sparse_points for p in points]) & bool(self._sparse_turns)
        t3 = time.perf_counter()
        sol = _Solved.empty(n)
        dense = np.flatnonzero(~sparse)
        if len(dense):
            sub, sub_views = _rows(points, views, dense)
            sol.put(
                dense,
                self._solve(
                    sub, mk[:, dense], jt[:, dense], sub_views, crop_box_m, _pick(subjects, dense)
                ),
            )
        few = np.flatnonzero(sparse)
        if len(few):
            sub, sub_views = _rows(points, views, few)
            t_net = time.perf_counter()
            xm, xj = self._turn_estimates(sub, self._sparse_turns)
            for key, v in self.last_timings_s.items():
                timings[key] += v
            t3 += time.perf_counter() - t_net  # the network's time is not the solve's
            all_m, all_j = np.concatenate([mk[:, few], xm]), np.concatenate([jt[:, few], xj])
            sol.put(
                few, self._solve(sub, all_m, all_j, sub_views, crop_box_m, _pick(subjects, few))
            )
        sizes = np.array([len(p) for p in points])
        poor = np.flatnonzero(sol.energy / sizes > self.bank_search.energy_per_point)
        if self.pose_bank is not None and len(poor):
            sub, sub_views = _rows(points, views, poor)
            t_bank = time.perf_counter()
            bm, bj = bank_starts(sub, sol.height_m[poor], self.pose_bank, search=self.bank_search)
            timings["bank_search_s"] = time.perf_counter() - t_bank
            # the bank already holds bent bodies: no bent copies of its starts
            opt = replace(self.solve_options, bend_starts_rad=())
            banked = solve_skeleton(
                sub,
                bm,
                bj,
                options=opt,
                views=sub_views,
                crop_box_m=crop_box_m,
                subjects=_pick(subjects, poor),
                pose_prior=self.pose_prior,
            )
            better = np.flatnonzero(banked.energy < sol.energy[poor])
            sol.put(poor[better], banked, better)
        t_again = time.perf_counter()
        todo = np.flatnonzero(sol.energy / sizes > self.bank_search.energy_per_point)
        for _ in range(self.resolve_rounds):
            if not len(todo):
                break
            sub, sub_views = _rows(points, views, todo)
            # the solution is the start and the prior: the network's estimate held it there
            again = solve_skeleton(
                sub,
                sol.markers_m[todo][None],
                sol.joints_m[todo][None],
                options=self.solve_options,
                views=sub_views,
                crop_box_m=crop_box_m,
                subjects=_pick(subjects, todo),
                pose_prior=self.pose_prior,
            )
            better = np.flatnonzero(again.energy < sol.energy[todo])
            sol.put(todo[better], again, better)
            # a cloud no round improved would start the next from the same solution again
            todo = todo[better]
            todo = todo[sol.energy[todo] / sizes[todo] > self.bank_search.energy_per_point]
        if self.resolve_rounds:
            timings["resolve_s"] = time.perf_counter() - t_again
        timings["solve_s"] = time.perf_counter() - t3
        self.last_timings_s = timings
        return sol


def _check_views(views: Sequence[Sequence[Camera]] | None, n: int) -> None:
    if views is not None and len(views) != n:
        msg = f"views has {len(views)} entries for {n} clouds; give one camera list per cloud"
        raise ValidationError(msg)


def _pick(
    subjects: Sequence[SubjectCalibration | None] | None, rows: npt.NDArray[np.intp]
) -> list[SubjectCalibration | None] | None:
    """The calibrations of ``rows`` (None: no calibrations)."""
    return None if subjects is None else [subjects[int(i)] for i in rows]


def _rows(
    points: list[FloatArray],
    views: Sequence[Sequence[Camera]] | None,
    rows: npt.NDArray[np.intp],
) -> tuple[list[FloatArray], list[Sequence[Camera]] | None]:
    """The clouds ``rows`` and their cameras."""
    picked = [points[int(i)] for i in rows]
    return picked, None if views is None else [views[int(i)] for i in rows]


@dataclass(frozen=True, slots=True)
class _Solved:
    """The solve's outputs of B clouds, filled in by groups of clouds."""

    markers_m: FloatArray
    joints_m: FloatArray
    poses: FloatArray
    height_m: FloatArray
    energy: FloatArray
    shape_z: FloatArray

    @staticmethod
    def empty(n: int) -> _Solved:
        return _Solved(
            np.full((n, NUM_MARKERS, 3), np.nan),
            np.full((n, len(DEMOCAP_JOINT_INDEX), 3), np.nan),
            np.full((n, POSE_DIM), np.nan),
            np.full((n,), np.nan),
            np.full((n,), np.inf),
            np.full((n, SHAPE_DIM), np.nan),
        )

    def predictions(self) -> list[Prediction]:
        return [
            Prediction(
                markers_m=self.markers_m[i],
                joints_m=self.joints_m[i],
                pose=self.poses[i],
                height_m=float(self.height_m[i]),
            )
            for i in range(len(self.energy))
        ]

    def result(self) -> SolveResult:
        """As a :class:`SolveResult` (the hypotheses are not kept: all 0)."""
        return SolveResult(
            markers_m=self.markers_m,
            joints_m=self.joints_m,
            poses=self.poses,
            height_m=self.height_m,
            energy=self.energy,
            hypothesis=np.zeros(len(self.energy), np.int64),
            shape_z=self.shape_z,
        )

    def put(
        self,
        rows: npt.NDArray[np.intp],
        sol: SolveResult,
        src: npt.NDArray[np.intp] | None = None,
    ) -> None:
        """Fill ``rows`` from the solve's frames ``src`` (default: all of them, in order)."""
        pick = slice(None) if src is None else src
        self.markers_m[rows] = sol.markers_m[pick]
        self.joints_m[rows] = sol.joints_m[pick]
        self.poses[rows] = sol.poses[pick]
        self.height_m[rows] = sol.height_m[pick]
        self.energy[rows] = sol.energy[pick]
        self.shape_z[rows] = sol.shape_z[pick]
