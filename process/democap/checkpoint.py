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

import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
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

    Nothing the file says is trusted before it is checked: the network is built without memory
    (torch's ``meta`` device) and its weight shapes compared to the stored ones before it gets
    any, so a damaged config cannot make this allocate more than the file holds.

    Raises:
        ProcessingError: the file is missing or unreadable, is not a DeMoCap checkpoint, has
            another format version, or its config, marker set, joint list or weights do not
            match (or hold NaN/inf).
    """
    path = Path(path)
    if not path.is_file():
        msg = f"DeMoCap checkpoint {path} does not exist; train one with `mocaprig democap train`"
        raise ProcessingError(msg)
    try:
        is_zip = zipfile.is_zipfile(path)
    except zipfile.BadZipFile as exc:  # an end record naming other disks, a bad offset...
        msg = f"DeMoCap checkpoint {path} cannot be read: its zip structure is damaged ({exc})"
        raise ProcessingError(msg) from exc
    if not is_zip:
        # torch.load would read anything else as a legacy pickle stream, whose length words it
        # trusts: 64 random bytes made it allocate 1.8 GB (fuzz campaign, 2026-11-27).
        msg = (
            f"DeMoCap checkpoint {path} cannot be read: it is not a torch zip archive (what "
            "torch.save writes); "
            "the file is damaged or not a checkpoint"
        )
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
        names = data.get(key, ())
        got = tuple(names) if isinstance(names, list | tuple) else (names,)
        if got != tuple(expected):
            msg = (
                f"{path}: its {key.replace('_', ' ')} ({len(got)} names) differ from this "
                f"code's ({len(expected)}); the checkpoint was trained for another "
                "marker set or skeleton and cannot be used"
            )
            raise ProcessingError(msg)
    state = _checked_state(path, data.get("model"))
    try:
        cfg = DemocapConfig.from_dict(dict(data["config"]))
    except Exception as exc:
        msg = f"{path}: the stored config is invalid ({exc}); the file is damaged"
        raise ProcessingError(msg) from exc
    probe = _meta_network(path, cfg, state)
    try:
        # Every parameter and buffer is in the state (strict load), so none stays uninitialised.
        model = probe.to_empty(device="cpu")
        model.load_state_dict(state)
    except Exception as exc:
        msg = f"{path}: the weights do not match the stored config ({exc}); the file is damaged"
        raise ProcessingError(msg) from exc
    try:
        opt, sched = data.get("optimizer"), data.get("scheduler")
        if not (opt is None or isinstance(opt, dict)) or not (
            sched is None or isinstance(sched, dict)
        ):
            bad = "the optimiser or scheduler state is not a table"
            raise TypeError(bad)
        return Checkpoint(
            config=cfg,
            model=model,
            epoch=int(data.get("epoch", 0)),
            seed=int(data.get("seed", 0)),
            optimizer_state=opt,
            scheduler_state=sched,
            history=[dict(h) for h in data.get("history", [])],
            train_motions=[str(n) for n in data.get("train_motions", [])],
        )
    except (TypeError, ValueError, OverflowError) as exc:
        msg = f"{path}: the training state is damaged ({exc}); retrain or use another file"
        raise ProcessingError(msg) from exc


def _checked_state(path: Path, state: object) -> dict[str, torch.Tensor]:
    """The stored weights, if every tensor holds its elements (a view claiming more than its
    storage would make loading allocate beyond the file) and all of them are finite."""
    if not isinstance(state, dict) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()
    ):
        msg = f"{path}: the model weights are not a table of tensors; the file is damaged"
        raise ProcessingError(msg)
    for key, t in state.items():
        if t.numel() * t.element_size() > t.untyped_storage().nbytes():
            msg = (
                f"{path}: weight {key} of shape {tuple(t.shape)} claims more values than the "
                "file stores; the file is damaged"
            )
            raise ProcessingError(msg)
    for key, t in state.items():
        if t.is_floating_point() and not _finite(t):
            msg = (
                f"{path}: weight {key} holds NaN or infinite values; the file is damaged (or "
                "the training diverged): use another checkpoint"
            )
            raise ProcessingError(msg)
    return state


def _finite(t: torch.Tensor) -> bool:
    """All values finite; numpy where it can (torch's kernels wait for its thread pool, tens of
    ms for this on a busy 2-core machine)."""
    if t.dtype in (torch.float16, torch.float32, torch.float64):
        return bool(np.isfinite(t.detach().numpy()).all())
    return bool(torch.isfinite(t).all())


def _meta_network(path: Path, cfg: DemocapConfig, state: dict[str, torch.Tensor]) -> DemocapModel:
    """The network of ``cfg`` on the ``meta`` device (no memory), if its weights have the stored
    shapes; a config whose network is not the stored one is refused.

    Every unit of the network has at least one weight tensor, so a config with more units than
    the file has tensors is damaged (and building its modules, even without memory, could take
    forever); within that bound the network is built on the ``meta`` device and its weight
    shapes compared with the stored ones.
    """
    sizes = (cfg.input_px, cfg.stem_channels, cfg.feature_channels, cfg.stem_units, cfg.width,
             *cfg.stage_branches, *cfg.stage_modules, *cfg.stage_units)  # fmt: skip
    if not all(type(v) is int and v >= 0 for v in sizes):
        msg = f"{path}: the stored network sizes {sizes} are not all counts; the file is damaged"
        raise ProcessingError(msg)
    units = cfg.stem_units + sum(
        m * u * b
        for m, u, b in zip(cfg.stage_modules, cfg.stage_units, cfg.stage_branches, strict=False)
    )
    if not 0 <= units <= len(state):
        msg = (
            f"{path}: the stored config asks for {units} network units but the file holds "
            f"{len(state)} weight tensors; the file is damaged"
        )
        raise ProcessingError(msg)
    try:
        with torch.device("meta"):
            probe = build_network(
                cfg, num_markers=len(MARKER_NAMES), num_joints=len(DEMOCAP_JOINTS)
            )
        want = {k: tuple(v.shape) for k, v in probe.state_dict().items()}
    except Exception as exc:
        msg = f"{path}: the stored config does not build a network ({exc}); the file is damaged"
        raise ProcessingError(msg) from exc
    have = {k: tuple(v.shape) for k, v in state.items()}
    if want != have:
        diff = sorted(set(want) ^ set(have)) or [k for k in want if want[k] != have[k]]
        msg = (
            f"{path}: the weights do not match the stored config (first difference: "
            f"{diff[0]}); the file is damaged"
        )
        raise ProcessingError(msg)
    return probe
