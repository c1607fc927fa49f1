"""DeMoCap: fused D415 marker clouds -> 53 labelled markers + 19 joints (docs/democap.md).

Pipeline: normalisation into the [0.1, 0.9] cuboid (:mod:`.geometry`), front/back orthographic
renders, the staged markers-to-pose network and CoM3D decoding (:mod:`.model`), dual-view
fusion, inverse normalisation (:mod:`.infer`); the baselines of paper Table 2 and a
direct-regression network are ``DemocapConfig.variant`` values (:func:`build_network`).
Training data is simulated at the marker level (:mod:`.simdata`, :mod:`.dataset`);
:mod:`.train` trains, :mod:`.evaluate` measures, :mod:`.replay` runs the network on a
calibrated recording and :mod:`.live` on live D415 frame sets. Inference can average a
rotation ensemble (:mod:`.infer`) and, by default offline, fits the body model to the cloud
from the network's estimates (:mod:`.solve`, the skeleton solve).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from mocaprig.lazy_exports import lazy_getattr

if TYPE_CHECKING:
    from collections.abc import Callable

    from mocaprig.process.democap.checkpoint import (
        DEFAULT_CHECKPOINT,
        Checkpoint,
        load_checkpoint,
        save_checkpoint,
    )
    from mocaprig.process.democap.config import (
        CONFIGS,
        VARIANTS,
        DemocapConfig,
        config_by_name,
    )
    from mocaprig.process.democap.evaluate import EvalReport
    from mocaprig.process.democap.infer import (
        DEFAULT_ROTATIONS,
        DemocapPredictor,
        Prediction,
        SubjectPredictions,
    )
    from mocaprig.process.democap.live import (
        LIVE_ROTATIONS,
        LiveCamera,
        LivePipeline,
        LiveResult,
        cameras_from_calibration,
        live_predictor,
    )
    from mocaprig.process.democap.model import DemocapNet, build_network
    from mocaprig.process.democap.replay import ReplayResult, run_replay, score_replay
    from mocaprig.process.democap.solve import (
        SolveOptions,
        SolveResult,
        SubjectCalibration,
        calibrate_subject,
        solve_skeleton,
    )
    from mocaprig.process.democap.train import TrainOptions

#: The public names by submodule, imported on first use (:mod:`mocaprig.lazy_exports`): most
#: need torch, which the commands that only register their options here should not import.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "checkpoint": ("DEFAULT_CHECKPOINT", "Checkpoint", "load_checkpoint", "save_checkpoint"),
    "config": ("CONFIGS", "VARIANTS", "DemocapConfig", "config_by_name"),
    "evaluate": ("EvalReport",),
    "infer": ("DEFAULT_ROTATIONS", "DemocapPredictor", "Prediction", "SubjectPredictions"),
    "live": (
        "LIVE_ROTATIONS",
        "LiveCamera",
        "LivePipeline",
        "LiveResult",
        "cameras_from_calibration",
        "live_predictor",
    ),
    "model": ("DemocapNet", "build_network"),
    "replay": ("ReplayResult", "run_replay", "score_replay"),
    "solve": (
        "SolveOptions",
        "SolveResult",
        "SubjectCalibration",
        "calibrate_subject",
        "solve_skeleton",
    ),
    "train": ("TrainOptions",),
}
__getattr__ = lazy_getattr(__name__, _EXPORTS)


__all__ = [
    "CONFIGS",
    "DEFAULT_CHECKPOINT",
    "DEFAULT_ROTATIONS",
    "LIVE_ROTATIONS",
    "VARIANTS",
    "Checkpoint",
    "DemocapConfig",
    "DemocapNet",
    "DemocapPredictor",
    "EvalReport",
    "LiveCamera",
    "LivePipeline",
    "LiveResult",
    "Prediction",
    "ReplayResult",
    "SolveOptions",
    "SolveResult",
    "SubjectCalibration",
    "SubjectPredictions",
    "TrainOptions",
    "build_network",
    "calibrate_subject",
    "cameras_from_calibration",
    "config_by_name",
    "demo_figures",
    "live_predictor",
    "load_checkpoint",
    "run_replay",
    "save_checkpoint",
    "score_replay",
    "solve_skeleton",
]


def demo_figures(
    *,
    seed: int = 0,
    frames_per_take: int = 10,
    progress: Callable[[str, int, int], None] | None = None,
) -> dict[str, Any]:
    """Quick figures for ``mocaprig demo`` (a few seconds): the committed ``lite`` checkpoint
    on a small held-out simulated test set (6 takes, 4 cameras), with the default inference
    (rotation ensemble and skeleton solve), the network's own ensemble estimate (no solve)
    and its single shot (the paper's inference). ``progress`` is told ``(inference, frames
    estimated, frames)``: ``"solve"``, ``"network"``, ``"single shot"``.

    Returns:
        ``{"mpjpe_mm", "mpmpe_mm", "pck50", "mpjae_deg", "frames", "config", "epochs",
        "rotations", "solve", "network_mpjpe_mm", "network_pck50", "single_shot_mpjpe_mm",
        "single_shot_pck50"}``.

    Raises:
        ProcessingError: the committed checkpoint is missing or does not match.
    """
    from mocaprig.process.democap.evaluate import evaluate, held_out_pool
    from mocaprig.process.democap.infer import DemocapPredictor
    from mocaprig.progress import bind_stage

    predictor = DemocapPredictor()
    pool = held_out_pool(seed)  # one test set for both inferences

    m = evaluate(
        predictor,
        seed=seed,
        num_cameras=4,
        frames_per_take=frames_per_take,
        pool=pool,
        progress=bind_stage(progress, "solve"),
    ).metrics
    network, single = (
        evaluate(
            DemocapPredictor(predictor.checkpoint, rotations=k, solve=False),
            seed=seed,
            num_cameras=4,
            frames_per_take=frames_per_take,
            pool=pool,
            progress=bind_stage(progress, name),
        ).metrics
        for k, name in ((predictor.rotations, "network"), (1, "single shot"))
    )
    return {
        "mpjpe_mm": m.mpjpe_mm,
        "mpmpe_mm": m.mpmpe_mm,
        "pck50": m.pck50,
        "mpjae_deg": m.mpjae_deg,
        "frames": m.frames,
        "config": predictor.checkpoint.config.name,
        "epochs": predictor.checkpoint.epoch,
        "rotations": predictor.rotations,
        "solve": predictor.solves,
        "network_mpjpe_mm": network.mpjpe_mm,
        "network_pck50": network.pck50,
        "single_shot_mpjpe_mm": single.mpjpe_mm,
        "single_shot_pck50": single.pck50,
    }
