"""DeMoCap checkpoints: network weights plus what is needed to use or resume them.

A checkpoint is a ``torch.save`` dict holding ``format`` (``"mocaprig-democap"``),
``format_version``, the config (:meth:`DemocapConfig.to_dict`), the marker and joint names in
output order, the model state (of the config's ``variant``; a config without the key is
markers-to-pose) and, for resuming, the optimiser and scheduler state, the
number of finished epochs, the seed and the loss history, and ``train_motions``, the names of
the BVH clips in the training pool (absent in older files: none). Loading checks all of them against
this code and raises :class:`mocaprig.errors.ProcessingError` naming what differs.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from mocaprig.errors import ProcessingError
from mocaprig.process.body import DEMOCAP_JOINTS, MARKER_NAMES
from mocaprig.process.democap.config import DemocapConfig
from mocaprig.process.democap.model import DemocapModel, build_network

__all__ = [
    "DEFAULT_CHECKPOINT",
    "FORMAT",
    "FORMAT_VERSION",
    "Checkpoint",
    "load_checkpoint",
    "save_checkpoint",
]

FORMAT = "mocaprig-democap"
FORMAT_VERSION = 1
#: The committed ``lite`` checkpoint.
DEFAULT_CHECKPOINT = Path(__file__).parent / "weights" / "democap_lite.pt"


@dataclass(slots=True)
class Checkpoint:
    """A loaded checkpoint (mutable: training updates it in place)."""

    config: DemocapConfig
    model: DemocapModel
    epoch: int = 0
    seed: int = 0
    optimizer_state: dict[str, Any] | None = None
    scheduler_state: dict[str, Any] | None = None
    history: list[dict[str, float]] = field(default_factory=list)
    #: names of the BVH clips trained on (an evaluation on one of them is not held out)
    train_motions: list[str] = field(default_factory=list)


def save_checkpoint(ckpt: Checkpoint, path: Path) -> None:
    """Write ``ckpt`` atomically (a temporary file renamed over ``path``)."""
    data = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "config": ckpt.config.to_dict(),
        "marker_names": list(MARKER_NAMES),
        "joint_names": list(DEMOCAP_JOINTS),
        "model": ckpt.model.state_dict(),
        "optimizer": ckpt.optimizer_state,
        "scheduler": ckpt.scheduler_state,
        "epoch": ckpt.epoch,
        "seed": ckpt.seed,
        "history": ckpt.history,
        "train_motions": list(ckpt.train_motions),
    }
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(data, tmp)
    tmp.replace(path)


def load_checkpoint(path: Path) -> Checkpoint:
    """Read and check a checkpoint.

    Raises:
        ProcessingError: the file is missing or unreadable, is not a DeMoCap checkpoint, has
            another format version, or its config, marker set or joint list do not match.
    """
    path = Path(path)
    if not path.is_file():
        msg = f"DeMoCap checkpoint {path} does not exist; train one with `mocaprig democap train`"
        raise ProcessingError(msg)
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        msg = f"DeMoCap checkpoint {path} cannot be read ({exc}); is it a torch file?"
        raise ProcessingError(msg) from exc
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        msg = f"{path} is not a DeMoCap checkpoint (no format {FORMAT!r})"
        raise ProcessingError(msg)
    if data.get("format_version") != FORMAT_VERSION:
        msg = (
            f"{path} has checkpoint format version {data.get('format_version')!r}; this code "
            f"reads version {FORMAT_VERSION}; retrain or use a matching mocaprig"
        )
        raise ProcessingError(msg)
    for key, expected in (("marker_names", MARKER_NAMES), ("joint_names", DEMOCAP_JOINTS)):
        got = tuple(data.get(key, ()))
        if got != tuple(expected):
            msg = (
                f"{path}: its {key.replace('_', ' ')} ({len(got)} names) differ from this "
                f"code's ({len(expected)}); the checkpoint was trained for another "
                "marker set or skeleton and cannot be used"
            )
            raise ProcessingError(msg)
    try:
        cfg = DemocapConfig.from_dict(dict(data["config"]))
        model = build_network(cfg, num_markers=len(MARKER_NAMES), num_joints=len(DEMOCAP_JOINTS))
        model.load_state_dict(data["model"])
    except Exception as exc:
        msg = f"{path}: the weights do not match the stored config ({exc}); the file is damaged"
        raise ProcessingError(msg) from exc
    return Checkpoint(
        config=cfg,
        model=model,
        epoch=int(data.get("epoch", 0)),
        seed=int(data.get("seed", 0)),
        optimizer_state=data.get("optimizer"),
        scheduler_state=data.get("scheduler"),
        history=list(data.get("history", [])),
        train_motions=[str(n) for n in data.get("train_motions", [])],
    )
