"""Inference: a fused marker cloud (world, m) -> 53 labelled markers + 19 joints (world, m).

Every network variant (``DemocapConfig.variant``) decodes the same way: per-view keypoints
(CoM3D of the heat maps, or the regressed coordinates), Eq. 7 fusion, inverse normalisation.
The ``"pose"`` baseline predicts no markers: its marker estimates are NaN.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import torch

from acquire.check import check_finite, check_shape
from process.democap.checkpoint import DEFAULT_CHECKPOINT, Checkpoint, load_checkpoint
from process.democap.dataset import prepare_cloud
from process.democap.geometry import Normalisation, to_world_frame
from process.democap.model import DemocapModel, DemocapOutput, fuse_views_torch, view_keypoints

__all__ = ["DemocapPredictor", "Prediction", "decode"]

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class Prediction:
    """One frame's estimate, world frame, metres: markers (53, 3) and joints (19, 3).

    The markers are all NaN for a network that does not estimate them (the ``"pose"``
    baseline; :attr:`DemocapPredictor.predicts_markers`).
    """

    markers_m: FloatArray
    joints_m: FloatArray


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


def _to_world(n: FloatArray, norm: Normalisation, centre: FloatArray) -> FloatArray:
    return to_world_frame(norm.invert(n) + centre)


class DemocapPredictor:
    """A loaded network ready for inference (eval mode, no gradients).

    Args:
        checkpoint: a :class:`Checkpoint`, a path, or ``None`` for the committed ``lite`` one.

    Raises:
        ProcessingError: the checkpoint is missing or does not match (see
            :func:`load_checkpoint`).
    """

    def __init__(self, checkpoint: Checkpoint | Path | None = None) -> None:
        ckpt = (
            checkpoint
            if isinstance(checkpoint, Checkpoint)
            else load_checkpoint(DEFAULT_CHECKPOINT if checkpoint is None else Path(checkpoint))
        )
        self.checkpoint = ckpt
        self.net = ckpt.model.eval()
        self.size_px = ckpt.config.input_px
        #: whether the network estimates the markers (not the ``"pose"`` baseline)
        self.predicts_markers = ckpt.config.predicts_markers
        #: seconds spent per stage by the last :meth:`predict_many` call
        self.last_timings_s: dict[str, float] = {}

    def predict(self, raw_m: npt.ArrayLike) -> Prediction:
        """One fused cloud (N, 3), world, m -> :class:`Prediction`.

        Raises:
            ValidationError: wrong shape, non-finite values or fewer than 2 points.
        """
        return self.predict_many([raw_m])[0]

    def predict_many(
        self, clouds: Sequence[npt.ArrayLike], *, rotations: Sequence[FloatArray] | None = None
    ) -> list[Prediction]:
        """Several clouds in one network batch. ``rotations`` (evaluation only) rotates each
        centred cloud before normalisation; the outputs are rotated back."""
        t0 = time.perf_counter()
        fronts, backs, norms, centres = [], [], [], []
        for i, c in enumerate(clouds):
            p = np.asarray(check_finite(check_shape(c, ["N", 3], name="cloud")), np.float64)
            rot = None if rotations is None else rotations[i]
            f, b, norm, centre = prepare_cloud(p, rot, size_px=self.size_px)
            fronts.append(f)
            backs.append(b)
            norms.append(norm)
            centres.append(centre)
        t1 = time.perf_counter()
        with torch.inference_mode():
            front = torch.from_numpy(np.stack(fronts))[:, None]
            back = torch.from_numpy(np.stack(backs))[:, None]
            m, j = decode(self.net, front, back)
        t2 = time.perf_counter()
        mk, jt = m.double().numpy(), j.double().numpy()
        out = []
        for i in range(len(norms)):
            mi, ji = norms[i].invert(mk[i]), norms[i].invert(jt[i])
            if rotations is not None:
                mi, ji = mi @ rotations[i], ji @ rotations[i]
            out.append(
                Prediction(
                    markers_m=to_world_frame(mi + centres[i]),
                    joints_m=to_world_frame(ji + centres[i]),
                )
            )
        t3 = time.perf_counter()
        self.last_timings_s = {"render_s": t1 - t0, "network_s": t2 - t1, "decode_s": t3 - t2}
        return out
