"""Training: simulated batches, Adam with ×0.95 decay every 4 epochs, a checkpoint per epoch.

Deterministic for a seed: the network starts from ``torch.manual_seed(seed)``; step ``s`` of
epoch ``e`` draws its batch from ``numpy.random.default_rng([seed, e, s])`` and torch is
re-seeded at each epoch start, so a run resumed from an epoch checkpoint continues exactly as
an uninterrupted one would (on the same machine and torch build).

The pool: the procedural takes, BVH clips (``motions``) and the motion corpus's train split
(``corpus``, :mod:`.corpus`), all on bodies of the training seed streams. After each epoch the
run is validated on a fixed set of its own: 48 samples of the ``validation`` seed stream
(procedural takes; ``val_mpjpe_mm``), disjoint from every test set, and, when given, 48 of the
corpus's validation split (``validation_motions``; ``val_corpus_mpjpe_mm``). The validation
samples draw no random numbers of the training batches, so they do not change the weights.
"""

from __future__ import annotations

import collections
import itertools
import logging
import multiprocessing
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, Literal

import numpy as np
import torch

from mocaprig.errors import ValidationError
from mocaprig.process.body import BvhClip
from mocaprig.process.democap.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from mocaprig.process.democap.config import DemocapConfig
from mocaprig.process.democap.corpus import corpus_pool
from mocaprig.process.democap.dataset import (
    Batch,
    check_observation_jitter,
    make_batch,
    make_pool,
    pool_from_bvh,
    simulate_sample,
)
from mocaprig.process.democap.model import DemocapModel, build_network, democap_loss
from mocaprig.process.democap.simdata import PoseFrames

__all__ = ["Device", "TrainOptions", "resolve_device", "train"]

_log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class TrainOptions:
    """What :func:`train` does.

    Attributes:
        epochs: train until this many epochs are finished (in total, counting resumed ones).
        seed: the run's seed (a resumed run keeps the checkpoint's seed).
        takes: training takes in the pool (each a new subject and take, 6 s at 30 Hz).
        samples_per_epoch: overrides the config's value when set.
        batch_size: overrides the config's value when set.
        threads: torch CPU threads.
        max_seconds: stop after the epoch that passes this wall time (None: no limit).
        motions: BVH clips added to the training pool (each on ``motion_subjects`` bodies of
            the training stream); their names are stored in the checkpoint. A resumed run
            must be given the same clips as before, or more.
        motion_subjects: bodies per BVH clip.
        corpus: clips of the motion corpus's train split (:mod:`.corpus`), each centred on
            the rig and retargeted onto ``corpus_subjects`` training bodies of its own; their
            names are stored in the checkpoint beside ``motions``' (and follow the same resume
            rule).
        corpus_subjects: bodies per corpus clip.
        validation_motions: clips of the corpus's validation split: a second validation set
            (one validation body per clip), reported as ``val_corpus_mpjpe_mm``. Never
            trained on.
        device: ``"cuda"`` (a GPU; mixed precision), ``"cpu"``, or ``"auto"`` (CUDA when
            torch sees one).
        data_workers: processes simulating the training batches ahead of the network (0: in
            the training process). Each step's batch comes from its own seeded generator, so
            the batches, and on the CPU the trained weights, do not depend on this number.
        observation_jitter: each training sample sees the D415 model with its scales
            (detection, noise, strays, occlusion) drawn from ``[1 - j, 1 + j]``
            (:func:`.dataset.jittered_observation`); 0: the nominal model. Stored in each
            epoch's history record, so the ``perturbed`` protocol can say how far its scales
            lie from what training saw.
        lr: the learning rate from this run's first epoch on (None: the config's for a new run,
            the stored schedule's for a resumed one). On a resumed run it is a warm restart, e.g.
            to fine-tune on new motions; the step decay continues from it.
    """

    epochs: int
    seed: int = 0
    takes: int = 96
    samples_per_epoch: int | None = None
    batch_size: int | None = None
    threads: int = 2
    max_seconds: float | None = None
    motions: tuple[BvhClip, ...] = ()
    motion_subjects: int = 4
    corpus: tuple[BvhClip, ...] = ()
    corpus_subjects: int = 2
    validation_motions: tuple[BvhClip, ...] = ()
    device: Device = "auto"
    data_workers: int = 0
    lr: float | None = None
    observation_jitter: float = 0.0


Device = Literal["auto", "cpu", "cuda"]
#: Batches simulated ahead per data worker.
_PREFETCH_PER_WORKER: Final = 2


def resolve_device(device: Device) -> torch.device:
    """The torch device of a ``TrainOptions.device`` choice.

    Raises:
        ValidationError: an unknown choice, or ``"cuda"`` without a CUDA device.
    """
    if device not in ("auto", "cpu", "cuda"):
        msg = f"device must be 'auto', 'cpu' or 'cuda', got {device!r}"
        raise ValidationError(msg)
    if device == "cuda" and not torch.cuda.is_available():
        msg = "device 'cuda' was asked for but torch sees no CUDA device; use --device cpu"
        raise ValidationError(msg)
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


_WORKER_POOL: list[PoseFrames] = []


def _init_worker(pool: list[PoseFrames]) -> None:
    # The training pool is sent once per worker process, not with every batch.
    global _WORKER_POOL
    _WORKER_POOL = pool
    torch.set_num_threads(1)  # in the worker process only: simulation is numpy work


def _keyed_batch(
    pool: list[PoseFrames], key: tuple[int, int, int], size: int, size_px: int, jitter: float
) -> Batch:
    """The batch of step ``key`` (seed, epoch, step): its own generator, wherever it is made."""
    rng = np.random.default_rng(list(key))
    return make_batch(pool, rng, size, size_px=size_px, observation_jitter=jitter)


def _worker_batch(key: tuple[int, int, int], size: int, size_px: int, jitter: float) -> Batch:
    return _keyed_batch(_WORKER_POOL, key, size, size_px, jitter)


def _batches(
    pool: list[PoseFrames],
    keys: Sequence[tuple[int, int, int]],
    size: int,
    size_px: int,
    workers: int,
    jitter: float = 0.0,
) -> Iterator[Batch]:
    """The batches of ``keys`` (seed, epoch, step) in order; simulated ``workers`` processes
    ahead when ``workers`` > 0."""
    if workers <= 0:
        for key in keys:
            yield _keyed_batch(pool, key, size, size_px, jitter)
        return
    ctx = multiprocessing.get_context("spawn")  # no fork of a process holding torch threads
    with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker,
                             initargs=(pool,)) as ex:  # fmt: skip
        ahead: collections.deque[Future[Batch]] = collections.deque()
        todo = iter(keys)
        for key in itertools.islice(todo, workers * _PREFETCH_PER_WORKER):
            ahead.append(ex.submit(_worker_batch, key, size, size_px, jitter))
        while ahead:
            batch = ahead.popleft().result()
            nxt = next(todo, None)
            if nxt is not None:
                ahead.append(ex.submit(_worker_batch, nxt, size, size_px, jitter))
            yield batch


def _optimizer(
    model: DemocapModel, cfg: DemocapConfig
) -> tuple[torch.optim.Adam, torch.optim.lr_scheduler.StepLR]:
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=cfg.lr_decay_epochs, gamma=cfg.lr_decay)
    return opt, sched


def train(
    out: Path,
    options: TrainOptions,
    *,
    config: DemocapConfig | None = None,
    resume: bool = False,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> Checkpoint:
    """Train (or resume) and write a checkpoint to ``out`` after every epoch.

    Args:
        out: checkpoint path.
        options: see :class:`TrainOptions`.
        config: the network config for a new run, its ``variant`` included (ignored when
            resuming: the checkpoint's config is used).
        resume: continue from ``out``.
        overwrite: allow replacing an existing ``out`` with a new run.
        progress: ``(done_steps, total_steps)`` callback for this call.

    Raises:
        ValidationError: ``out`` exists without ``resume``/``overwrite``, ``resume`` without
            ``out``, no config for a new run, or a non-positive epoch count.
        ProcessingError: the checkpoint to resume does not match this code.
    """
    if options.epochs < 1:
        msg = f"epochs must be >= 1, got {options.epochs}"
        raise ValidationError(msg)
    if options.lr is not None and not options.lr > 0.0:
        msg = f"lr must be > 0, got {options.lr}"
        raise ValidationError(msg)
    out = Path(out)
    if resume:
        ckpt = load_checkpoint(out)
    else:
        if out.exists() and not overwrite:
            msg = f"{out} exists; pass resume to continue it or overwrite to start again"
            raise ValidationError(msg)
        if config is None:
            msg = "a new training run needs a config (e.g. config_by_name('lite'))"
            raise ValidationError(msg)
        torch.manual_seed(options.seed)
        ckpt = Checkpoint(config=config, model=build_network(config), seed=options.seed)
    cfg = ckpt.config
    check_observation_jitter(options.observation_jitter, name="observation_jitter")
    if options.data_workers < 0:
        msg = f"data_workers must be >= 0, got {options.data_workers}"
        raise ValidationError(msg)
    device = resolve_device(options.device)
    amp = device.type == "cuda"
    torch.set_num_threads(max(1, options.threads))
    ckpt.model.to(device)
    batch = options.batch_size or cfg.batch_size
    steps = max(1, (options.samples_per_epoch or cfg.samples_per_epoch) // batch)
    opt, sched = _optimizer(ckpt.model, cfg)
    scaler = torch.amp.GradScaler("cuda", enabled=amp)
    if ckpt.optimizer_state is not None:
        opt.load_state_dict(ckpt.optimizer_state)
    if ckpt.scheduler_state is not None:
        sched.load_state_dict(ckpt.scheduler_state)
    if options.lr is not None:
        # StepLR scales the groups' current rate, so the decay carries on from the new one.
        for group in opt.param_groups:
            group["lr"] = options.lr
        _log.info("learning rate set to %.3g from epoch %d", options.lr, ckpt.epoch + 1)
    pool = make_pool(ckpt.seed, "train", takes=options.takes)
    names = [c.name for c in (*options.motions, *options.corpus)]
    if len(set(names)) != len(names):
        msg = f"BVH and corpus clips must have distinct names, got {names}"
        raise ValidationError(msg)
    overlap = sorted(set(names) & {c.name for c in options.validation_motions})
    if overlap:
        msg = f"clip(s) {overlap} are both trained on and in the validation set"
        raise ValidationError(msg)
    dropped = sorted(set(ckpt.train_motions) - set(names))
    if dropped:
        msg = (
            f"the checkpoint {out} was trained with BVH clip(s) {dropped}; pass them again "
            "to resume (the training pool must not lose motions mid-run)"
        )
        raise ValidationError(msg)
    for clip in options.motions:
        pool += pool_from_bvh(clip, ckpt.seed, subjects=options.motion_subjects, split="train")
    if options.corpus:
        pool += corpus_pool(
            options.corpus, ckpt.seed, split="train", subjects=options.corpus_subjects
        )
        _log.info("%d corpus clip(s) in the training pool", len(options.corpus))
    ckpt.train_motions = sorted(set(ckpt.train_motions) | set(names))
    val = _validation_set(
        make_pool(ckpt.seed, "validation", takes=6, seconds=3.0), ckpt.seed, cfg.input_px
    )
    val_corpus = (
        _validation_set(
            corpus_pool(options.validation_motions, ckpt.seed, split="validation", subjects=1),
            ckpt.seed,
            cfg.input_px,
        )
        if options.validation_motions
        else None
    )
    todo = max(0, options.epochs - ckpt.epoch)
    total = todo * steps
    t_start = time.monotonic()
    done = 0
    _log.info(
        "training on %s%s, batches simulated %s",
        device,
        " with mixed precision" if amp else "",
        f"by {options.data_workers} worker process(es)" if options.data_workers else "in-process",
    )
    for epoch in range(ckpt.epoch, options.epochs):
        torch.manual_seed(ckpt.seed * 100_003 + epoch)
        ckpt.model.train()
        sums: dict[str, float] = {}
        keys = [(ckpt.seed, epoch, step) for step in range(steps)]
        for b in _batches(
            pool, keys, batch, cfg.input_px, options.data_workers, options.observation_jitter
        ):
            with torch.autocast(device.type, dtype=torch.float16, enabled=amp):
                front = ckpt.model(b.front.to(device, non_blocking=True))
                back = ckpt.model(b.back.to(device, non_blocking=True))
            # The loss in float32: heat-map soft-argmax and sums are precision-sensitive.
            loss, parts = democap_loss(
                _float(front), _float(back), b.markers.to(device), b.joints.to(device), cfg
            )
            opt.zero_grad(set_to_none=True)
            scaler.scale(loss).backward()  # type: ignore[no-untyped-call]
            scaler.step(opt)
            scaler.update()
            parts["loss"] = float(loss.detach())
            for k, v in parts.items():
                sums[k] = sums.get(k, 0.0) + v
            done += 1
            if progress is not None:
                progress(done, total)
        sched.step()
        ckpt.epoch = epoch + 1
        record = {k: v / steps for k, v in sums.items()}
        record["epoch"] = float(ckpt.epoch)
        record["lr"] = float(opt.param_groups[0]["lr"])
        record["observation_jitter"] = float(options.observation_jitter)
        record["wall_s"] = time.monotonic() - t_start
        record["val_mpjpe_mm"] = _validate(ckpt.model, val, device)
        if val_corpus is not None:
            record["val_corpus_mpjpe_mm"] = _validate(ckpt.model, val_corpus, device)
        ckpt.history.append(record)
        ckpt.optimizer_state = opt.state_dict()
        ckpt.scheduler_state = sched.state_dict()
        save_checkpoint(ckpt, out)
        _log.info(
            "epoch %d: loss %.4f, held-out MPJPE %.1f mm",
            ckpt.epoch,
            record["loss"],
            record["val_mpjpe_mm"],
        )
        if options.max_seconds is not None and time.monotonic() - t_start > options.max_seconds:
            _log.info("time budget reached after epoch %d", ckpt.epoch)
            break
    ckpt.model.to("cpu").eval()
    return ckpt


def _float(x: Any) -> Any:
    """Model outputs (tensors, lists of them, the output records) as float32: under mixed
    precision the network runs in float16, the loss in float32."""
    if isinstance(x, torch.Tensor):
        return x.float()
    if isinstance(x, (tuple, list)):
        return type(x)(_float(v) for v in x)
    slots = getattr(type(x), "__slots__", ())
    if slots:
        out = object.__new__(type(x))
        for name in slots:
            object.__setattr__(out, name, _float(getattr(x, name)))
        return out
    return x


_Val = list[tuple[torch.Tensor, torch.Tensor, np.ndarray, np.ndarray]]


def _validation_set(pool: list[PoseFrames], seed: int, size_px: int, n: int = 48) -> _Val:
    """``n`` fixed samples of ``pool`` (validation seed streams, no rotation augmentation);
    frames without a usable cloud are replaced by the next draw."""
    rng = np.random.default_rng([seed, 99])
    out: _Val = []
    tries = 0
    while len(out) < n and tries < 20 * n:
        take = pool[tries % len(pool)]
        tries += 1
        s = simulate_sample(
            take, int(rng.integers(take.num_frames)), rng, augment=False, size_px=size_px
        )
        if s is None:
            continue
        out.append(
            (
                torch.from_numpy(s.front)[None, None],
                torch.from_numpy(s.back)[None, None],
                s.norm.scale_m,
                s.joints_n,
            )
        )
    if not out:
        msg = "no validation frame gave a usable cloud; the validation takes are out of view"
        raise ValidationError(msg)
    return out


def _validate(model: DemocapModel, val: _Val, device: torch.device | None = None) -> float:
    """Mean joint error (mm, 17 joints without the toes) on the fixed held-out samples."""
    from mocaprig.process.democap.infer import decode  # local: infer imports this module's siblings

    model.eval()
    keep = [k for k in range(19) if k not in (14, 18)]
    errs = []
    with torch.inference_mode():
        front = torch.cat([v[0] for v in val]).to(device or "cpu")
        back = torch.cat([v[1] for v in val]).to(device or "cpu")
        _, j = decode(model, front, back)
        j = j.float().cpu()
    for i, (_, _, scale, truth) in enumerate(val):
        d = (j[i].double().numpy() - truth) * scale
        errs.append(np.linalg.norm(d[keep], axis=-1).mean())
    return float(np.mean(errs) * 1000.0)
