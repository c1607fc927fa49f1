"""The real motion corpus: CMU clips split by performer, with an activity per clip.

The corpus (``../shared/data/motion/corpus``: 44 BVH clips of 8 CMU performers, described in
``../shared/data/README.md``) is never copied into the repository. Its split is: the committed
table ``data/corpus_split.toml`` lists the clips of each split (``train``, ``validation``,
``test``) with an activity tag per clip. The split is **by subject** (the number after
``cmu_``): :func:`load_split` refuses a table in which one performer appears in two splits, so
the test clips are motion of people whose clips never reached training or validation.

``democap train --corpus DIR`` adds the train split to the training pool (each clip retargeted
onto training bodies, :func:`corpus_pool`); the validation split guides the run; the test split
is the headline *unseen real motion, unseen subjects* protocol of ``democap eval``
(:mod:`.evaluate`), and the activity tags drive its *leave-one-activity-out* protocol.
"""

from __future__ import annotations

import logging
import re
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal, get_args

from mocaprig.errors import ValidationError
from mocaprig.process.body import BvhClip, read_bvh
from mocaprig.process.democap.dataset import NOMINAL_SUBJECTS, SubjectModel, pool_from_bvh
from mocaprig.process.democap.simdata import PoseFrames

__all__ = [
    "ACTIVITIES",
    "CORPUS_SPLITS",
    "SPLIT_TABLE",
    "CorpusClip",
    "CorpusSplit",
    "CorpusSplitName",
    "corpus_pool",
    "default_corpus_dir",
    "load_split",
    "read_corpus_clips",
    "subject_of",
]

_log = logging.getLogger(__name__)

CorpusSplitName = Literal["train", "validation", "test"]
#: The splits, in the table's order.
CORPUS_SPLITS: tuple[CorpusSplitName, ...] = get_args(CorpusSplitName)
#: Activity tags a table may use.
ACTIVITIES: tuple[str, ...] = (
    "walk",
    "run",
    "jump",
    "strike",
    "everyday",
    "playground",
    "dance",
    "basketball",
)
#: The committed split table.
SPLIT_TABLE = Path(__file__).parent / "data" / "corpus_split.toml"
_FORMAT_VERSION = 1
_NAME = re.compile(r"^cmu_(\d+)_(\d+)$")


def subject_of(name: str) -> int:
    """The CMU subject of a clip name (``cmu_05_02`` -> 5).

    Raises:
        ValidationError: the name is not ``cmu_<subject>_<trial>``.
    """
    m = _NAME.match(name)
    if m is None:
        msg = f"corpus clip name {name!r} is not cmu_<subject>_<trial> (e.g. cmu_05_02)"
        raise ValidationError(msg)
    return int(m.group(1))


@dataclass(frozen=True, slots=True)
class CorpusClip:
    """One clip of the split table.

    Attributes:
        name: the file stem (``cmu_05_02``), also the clip name a checkpoint records.
        subject: the CMU performer.
        split: ``train``, ``validation`` or ``test``.
        activity: the activity tag (:data:`ACTIVITIES`).
    """

    name: str
    subject: int
    split: CorpusSplitName
    activity: str

    def path(self, corpus_dir: Path) -> Path:
        """The clip's BVH file in ``corpus_dir``."""
        return Path(corpus_dir) / f"{self.name}.bvh"


@dataclass(frozen=True, slots=True)
class CorpusSplit:
    """The split table: every clip with its split and activity."""

    clips: tuple[CorpusClip, ...]

    def in_split(self, split: CorpusSplitName) -> tuple[CorpusClip, ...]:
        """The clips of one split, in table order."""
        return tuple(c for c in self.clips if c.split == split)

    def subjects(self, split: CorpusSplitName) -> tuple[int, ...]:
        """The performers of one split, sorted."""
        return tuple(sorted({c.subject for c in self.in_split(split)}))

    def activities(self) -> tuple[str, ...]:
        """The activities present, in :data:`ACTIVITIES` order."""
        present = {c.activity for c in self.clips}
        return tuple(a for a in ACTIVITIES if a in present)

    def by_name(self, name: str) -> CorpusClip | None:
        """The clip called ``name``, or None."""
        return next((c for c in self.clips if c.name == name), None)


def load_split(path: Path | None = None) -> CorpusSplit:
    """Read and check a split table (default: the committed :data:`SPLIT_TABLE`).

    Raises:
        ValidationError: the file is missing or not TOML, has another ``format_version``, lacks
            a split, names a clip twice or badly, uses an unknown activity, or puts one
            subject in two splits.
    """
    path = SPLIT_TABLE if path is None else Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as exc:
        msg = f"corpus split table {path} cannot be read ({exc})"
        raise ValidationError(msg) from exc
    if data.get("format_version") != _FORMAT_VERSION:
        msg = (
            f"corpus split table {path}: format_version {data.get('format_version')!r}, "
            f"this code reads {_FORMAT_VERSION}"
        )
        raise ValidationError(msg)
    clips: list[CorpusClip] = []
    owner: dict[int, str] = {}
    for split in CORPUS_SPLITS:
        table = data.get(split)
        if not isinstance(table, dict) or not table:
            msg = f"corpus split table {path}: no [{split}] table of clip = activity"
            raise ValidationError(msg)
        for name, activity in table.items():
            if activity not in ACTIVITIES:
                msg = (
                    f"corpus split table {path}: clip {name} has activity {activity!r}; "
                    f"known: {', '.join(ACTIVITIES)}"
                )
                raise ValidationError(msg)
            subject = subject_of(name)
            if owner.setdefault(subject, split) != split:
                msg = (
                    f"corpus split table {path}: subject {subject} is in both "
                    f"{owner[subject]!r} and {split!r} ({name}); the split is by subject"
                )
                raise ValidationError(msg)
            clips.append(CorpusClip(name, subject, split, str(activity)))
    names = [c.name for c in clips]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        msg = f"corpus split table {path}: clip(s) {dup} listed more than once"
        raise ValidationError(msg)
    return CorpusSplit(tuple(clips))


def default_corpus_dir() -> Path | None:
    """``../shared/data/motion/corpus`` beside the repository, when it is there (None on a clone
    without the shared data)."""
    root = Path(__file__).resolve().parents[2]
    path = root.parent / "shared" / "data" / "motion" / "corpus"
    return path if path.is_dir() else None


def read_corpus_clips(corpus_dir: Path, clips: Sequence[CorpusClip]) -> list[BvhClip]:
    """The BVH files of ``clips`` from ``corpus_dir``, each named after its table entry.

    Raises:
        ValidationError: ``corpus_dir`` is not a folder, or a clip's file is missing (named,
            with the folder).
    """
    corpus_dir = Path(corpus_dir)
    if not corpus_dir.is_dir():
        msg = f"motion corpus folder {corpus_dir} does not exist (pass --corpus DIR)"
        raise ValidationError(msg)
    missing = [c.name for c in clips if not c.path(corpus_dir).is_file()]
    if missing:
        msg = f"motion corpus {corpus_dir} lacks {', '.join(f'{n}.bvh' for n in missing)}"
        raise ValidationError(msg)
    out = []
    for c in clips:
        bvh = read_bvh(c.path(corpus_dir))
        out.append(bvh if bvh.name == c.name else replace(bvh, name=c.name))
    _log.info("read %d corpus clip(s) from %s", len(out), corpus_dir)
    return out


def corpus_pool(
    clips: Sequence[BvhClip],
    seed: int,
    *,
    split: CorpusSplitName,
    subjects: int,
    subject_model: SubjectModel = NOMINAL_SUBJECTS,
) -> list[PoseFrames]:
    """Takes of corpus clips on ``subjects`` bodies each, from ``split``'s body seed stream
    (clip *i* gets bodies ``i·subjects`` ... ``i·subjects + subjects - 1``, so no two clips share
    a body), each clip centred on the rig (:func:`dataset.pool_from_bvh` with ``centre=True``);
    ``subject_model`` draws the bodies (default: the nominal ones).

    Raises:
        ValidationError: ``subjects`` < 1.
    """
    pool: list[PoseFrames] = []
    for i, clip in enumerate(clips):
        pool += pool_from_bvh(
            clip,
            seed,
            subjects=subjects,
            split=split,
            centre=True,
            first_body=i * subjects,
            subject_model=subject_model,
        )
    return pool
