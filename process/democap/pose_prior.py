"""Pose prior: how real bodies hold their joints, for the skeleton solve.

Where the cloud says little about a limb (half its markers missed, or the hands above every
camera's view), the solve has the network's estimate to go on, and where the network is far
off too the limb ends wherever the steps leave it; a forearm no point pins down may end
anywhere about its elbow (docs/democap.md, "Pose prior"). The prior is a Gaussian mixture over
the 27 joint angles (:data:`.body.skeleton.DOF_NAMES`, rad) of real motion: the corpus's
``train`` split retargeted onto the reference body (:func:`build_pose_prior`: k-means, then a
mean and a covariance per cluster, every variance floored). The solve adds, for the component
that costs least at each step, ``w·((θ − μ_k)ᵀ Λ_k (θ − μ_k) + c_k)`` (``w``:
:attr:`.solve.SolveOptions.pose_prior_weight`): weak beside one seen marker, what decides an
angle that nothing sees.

The committed prior (:data:`DEFAULT_POSE_PRIOR`, 8 components of the train split's 27 clips at
30 Hz) is made by ``mocaprig democap pose-prior``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
from scipy.cluster.vq import kmeans2

from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body import BvhClip
from mocaprig.process.body.skeleton import NUM_DOF, ROOT_DIM
from mocaprig.process.democap.artifact import load_artifact, save_artifact
from mocaprig.process.democap.pose_bank import reference_poses
from mocaprig.validation import check_finite, check_positive, check_shape

__all__ = [
    "DEFAULT_POSE_PRIOR",
    "PosePrior",
    "build_pose_prior",
    "load_pose_prior",
    "save_pose_prior",
]

_log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

#: The committed prior (module doc).
DEFAULT_POSE_PRIOR = Path(__file__).resolve().parent / "data" / "pose_prior.npz"
_FORMAT_VERSION = 1
#: Fewest frames a cluster needs to become a component (a covariance of 27 angles).
_MIN_FRAMES = 2 * NUM_DOF


@dataclass(frozen=True, slots=True)
class PosePrior:
    """A Gaussian mixture over the 27 joint angles (rad), K components.

    Attributes:
        means: (K, 27) each component's mean angles, rad.
        precisions: (K, 27, 27) each component's inverse covariance, rad⁻².
        costs: (K,) each component's ``log det Σ_k − 2 log π_k``, less their least (0 for
            the likeliest): a component is charged this on top of its Mahalanobis distance.
        source: the clips it was made from.
    """

    means: FloatArray
    precisions: FloatArray
    costs: FloatArray
    source: tuple[str, ...]

    def __post_init__(self) -> None:
        check_finite(check_shape(self.means, ["K", NUM_DOF], name="PosePrior.means"))
        k = self.means.shape[0]
        check_finite(
            check_shape(self.precisions, [k, NUM_DOF, NUM_DOF], name="PosePrior.precisions")
        )
        check_finite(check_shape(self.costs, [k], name="PosePrior.costs"))
        if k < 1:
            msg = "PosePrior needs at least one component"
            raise ValidationError(msg)
        if not np.allclose(self.precisions, np.swapaxes(self.precisions, 1, 2), atol=1e-8):
            msg = "PosePrior.precisions must be symmetric"
            raise ValidationError(msg)
        if np.linalg.eigvalsh(self.precisions).min() <= 0.0:
            msg = "PosePrior.precisions must be positive definite"
            raise ValidationError(msg)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def energy(self, angles: npt.ArrayLike) -> FloatArray:
        """The prior's energy of poses' angles (B, 27), rad -> (B,): the least over the
        components of ``(θ − μ_k)ᵀ Λ_k (θ − μ_k) + c_k`` (unweighted)."""
        a = np.asarray(check_finite(check_shape(angles, ["B", NUM_DOF], name="angles")), np.float64)
        d = a[:, None, :] - self.means[None]
        maha = np.einsum("bki,kij,bkj->bk", d, self.precisions, d)
        return np.asarray((maha + self.costs[None]).min(axis=1))


def build_pose_prior(
    clips: Sequence[BvhClip],
    *,
    components: int = 8,
    rate_hz: float = 30.0,
    floor_deg: float = 5.0,
    seed: int = 0,
) -> PosePrior:
    """A prior of ``components`` Gaussians from motion clips: each clip retargeted onto the
    reference body (thinned to about ``rate_hz``; :func:`.pose_bank.reference_poses`), k-means
    (seeded) over the frames' angles, then each cluster's mean and covariance, every variance
    raised by ``floor_deg``² (an angle the clips never move, the forearm's pronation, is not
    held exactly). Clusters of fewer than 54 frames are dropped.

    Raises:
        ValidationError: no clip, ``components`` < 1, a non-positive rate or floor, or too
            few frames for one component.
    """
    if not clips:
        msg = "build_pose_prior needs at least one clip"
        raise ValidationError(msg)
    if components < 1:
        msg = f"components must be >= 1, got {components}"
        raise ValidationError(msg)
    check_positive(rate_hz, name="rate_hz")
    check_positive(floor_deg, name="floor_deg")
    angles = reference_poses(clips, rate_hz=rate_hz)[:, ROOT_DIM:]
    if len(angles) < max(_MIN_FRAMES, components):
        msg = (
            f"the clips give {len(angles)} frames at {rate_hz} Hz, too few for {components} "
            f"component(s) of {_MIN_FRAMES} frames or more"
        )
        raise ValidationError(msg)
    if components == 1:
        label = np.zeros(len(angles), np.int64)
    else:
        _, label = kmeans2(
            angles, components, seed=np.random.default_rng(seed), minit="++", iter=50
        )
    floor = np.deg2rad(floor_deg) ** 2 * np.eye(NUM_DOF)
    means, precisions, costs = [], [], []
    for k in range(components):
        x = angles[label == k]
        if len(x) < _MIN_FRAMES:
            continue
        cov = np.cov(x.T) + floor
        means.append(x.mean(axis=0))
        precisions.append(np.linalg.inv(cov))
        costs.append(np.linalg.slogdet(cov)[1] - 2.0 * np.log(len(x) / len(angles)))
    c = np.array(costs)
    prec = np.array(precisions)
    _log.info("pose prior: %d components from %d frames", len(means), len(angles))
    return PosePrior(
        means=np.array(means),
        precisions=0.5 * (prec + np.swapaxes(prec, 1, 2)),
        costs=c - c.min(),
        source=tuple(clip.name for clip in clips),
    )


def save_pose_prior(prior: PosePrior, path: Path, *, overwrite: bool = False) -> Path:
    """Write ``prior`` to ``path`` (.npz, float64).

    Raises:
        RecordingError: ``path`` exists and ``overwrite`` is False, or cannot be written.
    """
    return save_artifact(
        path,
        "pose prior",
        {"means": prior.means, "precisions": prior.precisions, "costs": prior.costs},
        source=prior.source,
        version=_FORMAT_VERSION,
        overwrite=overwrite,
    )


def load_pose_prior(path: Path | None = None) -> PosePrior:
    """Read a prior written by :func:`save_pose_prior` (default: :data:`DEFAULT_POSE_PRIOR`).

    Raises:
        ProcessingError: the file is missing, not a prior, or of another format version.
    """
    path = DEFAULT_POSE_PRIOR if path is None else Path(path)
    fields, source = load_artifact(
        path,
        "pose prior",
        ("means", "precisions", "costs"),
        version=_FORMAT_VERSION,
        rebuild="mocaprig democap pose-prior",
    )
    try:
        return PosePrior(**fields, source=source)
    except ValidationError as exc:
        msg = f"pose prior {path} is not a pose prior ({exc})"
        raise ProcessingError(msg) from exc
