"""BVH (Biovision hierarchy) motion files: reader, native forward kinematics, retargeting.

Reading (:func:`read_bvh`, :func:`parse_bvh`) accepts any joint hierarchy, any number of joints,
``End Site`` leaves, and per-joint channel lists of any order (e.g. ``Zrotation Xrotation
Yrotation``, 3 or 6 channels). Conventions:

* Rotation channels are Euler angles in degrees, applied in the listed order as *intrinsic*
  rotations: ``CHANNELS 3 Zrotation Yrotation Xrotation`` gives the local rotation
  ``R = Rz(z) @ Ry(y) @ Rx(x)`` (the Biovision convention; scipy ``Rotation.from_euler("ZYX",
  [z, y, x], degrees=True)``).
* A joint's global transform is ``T_parent @ Translate(t) @ R``, where ``t`` is the joint's
  ``OFFSET`` or, for a joint with position channels, the channel values themselves (exporters
  that put position channels on every joint write the offset there; for the usual root with a
  zero offset both readings agree).
* ``End Site`` leaves become joints named ``<parent>_End`` with no channels, so their positions
  come out of the forward kinematics like any other joint's.
* Units: lengths are scaled to metres at read time. ``unit_scale`` (metres per file unit) may be
  given; by default it is detected from the rest skeleton's largest extent (m, cm, mm, inches,
  or the CMU cgspeed unit of 0.056444 m) and the choice is logged.

Retargeting (:func:`retarget_bvh`) fits our 33-parameter pose (:mod:`process.body.skeleton`) to
each BVH frame; see its docstring. Which BVH joint stands for each of ours comes from the naming
tables of the common exporters and the skeleton's structure (:mod:`process.body.bvh_names`), or
from a user's joint map (a TOML file of ``our joint = "its joint"`` lines, :func:`load_joint_map`;
``--joint-map FILE.toml`` on the command line).
"""

from __future__ import annotations

import logging
import math
import re
import time
import tomllib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
import numpy.typing as npt

from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body.bvh_names import (
    DEFAULT_JOINT_CANDIDATES,
    JointMapping,
    check_joint_map,
    map_joints,
)
from mocaprig.validation import check_positive

if TYPE_CHECKING:
    from mocaprig.process.body.motion import Motion
    from mocaprig.process.body.shape import BodyShape

__all__ = [
    "DEFAULT_JOINT_CANDIDATES",
    "BvhClip",
    "RetargetReport",
    "UpAxis",
    "bvh_forward_kinematics",
    "bvh_global_positions",
    "bvh_rest_positions",
    "bvh_to_body_frame",
    "load_joint_map",
    "map_bvh_joints",
    "parse_bvh",
    "read_bvh",
    "resolve_joint_map",
    "retarget_bvh",
    "retarget_errors",
]

_log = logging.getLogger(__name__)

_CHANNEL_NAMES = {
    "xposition": "Xposition",
    "yposition": "Yposition",
    "zposition": "Zposition",
    "xrotation": "Xrotation",
    "yrotation": "Yrotation",
    "zrotation": "Zrotation",
}

#: Known length units: (name, metres per unit, plausible range of the skeleton's largest extent).
_UNITS: tuple[tuple[str, float, float, float], ...] = (
    ("metres", 1.0, 0.4, 3.0),
    ("CMU cgspeed units (0.056444 m)", 0.056444, 12.0, 45.0),
    ("inches", 0.0254, 45.0, 120.0),
    ("centimetres", 0.01, 120.0, 300.0),
    ("millimetres", 0.001, 400.0, 3000.0),
)


@dataclass(frozen=True, slots=True)
class BvhClip:
    """A parsed BVH file, lengths in metres.

    Attributes:
        name: Label (the file stem, or what the caller gave).
        joint_names: Names of the ``J`` joints in file order; End Sites are ``<parent>_End``.
        parents: Parent index of each joint (-1 for roots), parents before children.
        offsets_m: ``OFFSET`` of each joint in its parent's frame (m), shape ``(J, 3)``.
        channels: Channel names of each joint in file order (``()`` for End Sites), spelled
            ``Xposition`` ... ``Zrotation``.
        frames: Motion data, shape ``(F, C)`` with ``C = sum(len(c) for c in channels)``;
            position channels in metres, rotation channels in degrees. Read-only.
        frame_time_s: Frame period (s).
        unit_scale: Metres per file length unit that was applied.
        source: Where the text came from (path or ``"<string>"``), for messages.
        joint_map: The user's (our joint, BVH joint) pairs that retargeting applies before the
            naming tables (:func:`map_bvh_joints`); ``()`` for none.
    """

    name: str
    joint_names: tuple[str, ...]
    parents: tuple[int, ...]
    offsets_m: npt.NDArray[np.float64] = field(repr=False)
    channels: tuple[tuple[str, ...], ...] = field(repr=False)
    frames: npt.NDArray[np.float64] = field(repr=False)
    frame_time_s: float
    unit_scale: float = 1.0
    source: str = "<string>"
    joint_map: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        j = len(self.joint_names)
        if len(self.parents) != j or len(self.channels) != j:
            msg = (
                f"BvhClip {self.name!r}: {j} joint names, {len(self.parents)} parents and "
                f"{len(self.channels)} channel lists; they must agree"
            )
            raise ValidationError(msg)
        for i, p in enumerate(self.parents):
            if not -1 <= p < i:
                msg = f"BvhClip {self.name!r}: joint {i} has parent {p}; parents must come first"
                raise ValidationError(msg)
        offsets = np.array(self.offsets_m, dtype=np.float64)
        frames = np.array(self.frames, dtype=np.float64)
        if offsets.shape != (j, 3):
            msg = f"BvhClip {self.name!r}: offsets_m has shape {offsets.shape}, expected ({j}, 3)"
            raise ValidationError(msg)
        c = sum(len(ch) for ch in self.channels)
        if frames.ndim != 2 or frames.shape[1] != c:
            msg = f"BvhClip {self.name!r}: frames has shape {frames.shape}, expected (F, {c})"
            raise ValidationError(msg)
        check_positive(float(self.frame_time_s), name="BvhClip.frame_time_s")
        check_joint_map(dict(self.joint_map), self.joint_names, source=self.source)
        offsets.setflags(write=False)
        frames.setflags(write=False)
        object.__setattr__(self, "offsets_m", offsets)
        object.__setattr__(self, "frames", frames)

    @property
    def num_joints(self) -> int:
        """Number of joints ``J`` (End Sites included)."""
        return len(self.joint_names)

    @property
    def num_frames(self) -> int:
        """Number of frames ``F``."""
        return int(self.frames.shape[0])

    @property
    def rate_hz(self) -> float:
        """Frame rate (Hz)."""
        return 1.0 / self.frame_time_s

    @property
    def channel_start(self) -> tuple[int, ...]:
        """Column of each joint's first channel in :attr:`frames`."""
        starts: list[int] = []
        col = 0
        for ch in self.channels:
            starts.append(col)
            col += len(ch)
        return tuple(starts)

    def joint_index(self, name: str) -> int:
        """Index of a joint by exact name.

        Raises:
            ValidationError: no such joint.
        """
        try:
            return self.joint_names.index(name)
        except ValueError:
            msg = f"BVH {self.source} has no joint {name!r}; joints: {', '.join(self.joint_names)}"
            raise ValidationError(msg) from None


# --------------------------------------------------------------------------------------------
# Parsing


class _Tokens:
    """Whitespace tokens of the HIERARCHY section, with 1-based line numbers."""

    def __init__(self, lines: Sequence[str], source: str) -> None:
        self.items: list[tuple[str, int]] = []
        self.source = source
        self.pos = 0
        self.motion_line = -1
        for k, line in enumerate(lines):
            parts = line.split()
            if parts and parts[0].upper() == "MOTION":
                self.motion_line = k
                break
            self.items.extend((p, k + 1) for p in parts)
        self.end_line = len(lines)

    def error(self, what: str, line: int | None = None) -> ProcessingError:
        if line is None:
            line = self.items[self.pos][1] if self.pos < len(self.items) else self.end_line
        return ProcessingError(f"BVH {self.source}, line {line}: {what}")

    def peek(self) -> str | None:
        return self.items[self.pos][0] if self.pos < len(self.items) else None

    def next(self, expecting: str) -> tuple[str, int]:
        if self.pos >= len(self.items):
            where = "the MOTION section" if self.motion_line >= 0 else "the end of the file"
            msg = f"expected {expecting} but reached {where}"
            raise self.error(msg, self.end_line if self.motion_line < 0 else self.motion_line + 1)
        tok = self.items[self.pos]
        self.pos += 1
        return tok

    def expect(self, word: str) -> int:
        tok, line = self.next(repr(word))
        if tok.upper() != word.upper():
            msg = f"expected {word!r}, found {tok!r}"
            raise self.error(msg, line)
        return line

    def number(self, what: str) -> float:
        tok, line = self.next(what)
        try:
            value = float(tok)
        except ValueError:
            msg = f"expected a number for {what}, found {tok!r}"
            raise self.error(msg, line) from None
        if not math.isfinite(value):
            msg = f"{what} is {tok!r}; it must be finite"
            raise self.error(msg, line)
        return value


def _parse_joint(
    tok: _Tokens,
    parent: int,
    name: str,
    names: list[str],
    parents: list[int],
    offsets: list[tuple[float, float, float]],
    channels: list[tuple[str, ...]],
    *,
    end_site: bool,
) -> None:
    index = len(names)
    names.append(name)
    parents.append(parent)
    tok.expect("{")
    tok.expect("OFFSET")
    offsets.append(
        (
            tok.number(f"{name} OFFSET x"),
            tok.number(f"{name} OFFSET y"),
            tok.number(f"{name} OFFSET z"),
        )
    )
    chans: tuple[str, ...] = ()
    if not end_site:
        tok.expect("CHANNELS")
        count_tok, count_line = tok.next(f"the channel count of {name}")
        if not count_tok.isdigit() or not 0 <= int(count_tok) <= 6:
            msg = f"joint {name!r}: channel count must be an integer 0..6, found {count_tok!r}"
            raise tok.error(msg, count_line)
        got: list[str] = []
        for _ in range(int(count_tok)):
            ch, ch_line = tok.next(f"a channel name of {name}")
            canon = _CHANNEL_NAMES.get(ch.lower())
            if canon is None:
                msg = (
                    f"joint {name!r}: unknown channel {ch!r} (expected one of "
                    f"{', '.join(sorted(_CHANNEL_NAMES.values()))}); CHANNELS says {count_tok}"
                )
                raise tok.error(msg, ch_line)
            if canon in got:
                msg = f"joint {name!r}: channel {canon} listed twice"
                raise tok.error(msg, ch_line)
            got.append(canon)
        chans = tuple(got)
    channels.append(chans)
    while True:
        word = tok.peek()
        if word is None:
            tok.next(f"'}}' closing joint {name!r}")
        upper = (word or "").upper()
        if upper == "}":
            tok.next("'}'")
            return
        if end_site:
            bad, bad_line = tok.next("'}'")
            msg = f"End Site of {names[parent]!r} must only hold an OFFSET, found {bad!r}"
            raise tok.error(msg, bad_line)
        if upper == "JOINT":
            tok.next("JOINT")
            child, _ = tok.next("a joint name after JOINT")
            _parse_joint(tok, index, child, names, parents, offsets, channels, end_site=False)
        elif upper == "END":
            tok.next("End")
            tok.expect("Site")
            _parse_joint(
                tok, index, f"{name}_End", names, parents, offsets, channels, end_site=True
            )
        else:
            bad, bad_line = tok.next("JOINT, End Site or '}'")
            msg = f"inside joint {name!r}: expected JOINT, End Site or '}}', found {bad!r}"
            raise tok.error(msg, bad_line)


def _detect_unit(rest_extent: float, source: str) -> float:
    for unit_name, scale, low, high in _UNITS:
        if low <= rest_extent < high:
            _log.info(
                "BVH %s: rest skeleton spans %.4g file units; reading lengths as %s "
                "(pass unit_scale= to override)",
                source,
                rest_extent,
                unit_name,
            )
            return scale
    msg = (
        f"BVH {source}: cannot tell the length unit from the rest skeleton's extent "
        f"{rest_extent:.4g}; pass unit_scale= (metres per file unit)"
    )
    raise ProcessingError(msg)


def parse_bvh(
    text: str,
    *,
    unit_scale: float | None = None,
    source: str = "<string>",
    name: str | None = None,
    joint_map: Mapping[str, str] | None = None,
) -> BvhClip:
    """Parse BVH text.

    Args:
        text: The whole file content.
        unit_scale: Metres per file length unit; ``None`` detects it from the skeleton size
            (logged at INFO).
        source: What to call the text in error messages (a path).
        name: Clip name (default: the stem of ``source``).
        joint_map: Our joint name -> BVH joint name, kept on the clip for retargeting
            (:attr:`BvhClip.joint_map`; e.g. from :func:`load_joint_map`).

    Returns:
        The clip, lengths in metres.

    Raises:
        ProcessingError: malformed text; the message names ``source``, the line and the problem.
        ValidationError: ``unit_scale`` is not a finite number > 0, or ``joint_map`` names a
            joint that is not ours or not in the file.
    """
    if unit_scale is not None:
        check_positive(float(unit_scale), name="unit_scale")
    lines = text.splitlines()
    tok = _Tokens(lines, source)
    tok.expect("HIERARCHY")
    names: list[str] = []
    parents: list[int] = []
    offsets: list[tuple[float, float, float]] = []
    channels: list[tuple[str, ...]] = []
    while tok.peek() is not None:
        tok.expect("ROOT")
        root, _ = tok.next("a joint name after ROOT")
        _parse_joint(tok, -1, root, names, parents, offsets, channels, end_site=False)
    if not names:
        msg = "no ROOT joint in the HIERARCHY section"
        raise tok.error(msg)
    if tok.motion_line < 0:
        msg = "no MOTION section"
        raise tok.error(msg, len(lines))
    k = tok.motion_line + 1
    frames_count, k = _header_value(lines, k, "Frames", source)
    frame_time, k = _header_value(lines, k, "Frame Time", source)
    if not (math.isfinite(frames_count) and frames_count >= 1 and frames_count.is_integer()):
        msg = f"BVH {source}, line {k}: Frames must be a positive integer, found {frames_count!r}"
        raise ProcessingError(msg)
    n_frames = int(frames_count)
    if not (math.isfinite(frame_time) and frame_time > 0):
        msg = f"BVH {source}, line {k}: Frame Time must be > 0 s and finite, found {frame_time!r}"
        raise ProcessingError(msg)
    # The frame count is the file's word: never allocate more rows than it holds lines.
    frame_lines = sum(1 for line in lines[k:] if line.strip())
    if n_frames > frame_lines:
        msg = (
            f"BVH {source}, line {k}: the header declares {n_frames} frames, found "
            f"{frame_lines} frame lines (a truncated file, or a wrong Frames count)"
        )
        raise ProcessingError(msg)
    n_channels = sum(len(c) for c in channels)
    data = np.empty((n_frames, n_channels), dtype=np.float64)
    row = 0
    for j in range(k, len(lines)):
        parts = lines[j].split()
        if not parts:
            continue
        if row >= n_frames:
            msg = (
                f"BVH {source}, line {j + 1}: more frame lines than the {n_frames} the header "
                "declares"
            )
            raise ProcessingError(msg)
        if len(parts) != n_channels:
            msg = (
                f"BVH {source}, line {j + 1}: frame {row} has {len(parts)} values, the hierarchy "
                f"declares {n_channels} channels"
            )
            raise ProcessingError(msg)
        try:
            data[row] = [float(p) for p in parts]
        except ValueError as err:
            msg = f"BVH {source}, line {j + 1}: frame {row} holds a non-number ({err})"
            raise ProcessingError(msg) from None
        row += 1
    if row != n_frames:
        msg = f"BVH {source}, line {len(lines)}: the header declares {n_frames} frames, found {row}"
        raise ProcessingError(msg)
    if not np.all(np.isfinite(data)):
        bad = int(np.argwhere(~np.isfinite(data))[0, 0])
        msg = f"BVH {source}: frame {bad} holds a non-finite value (nan or inf)"
        raise ProcessingError(msg)
    off = np.array(offsets, dtype=np.float64)
    if unit_scale is None:
        rest = _forward(off, tuple(parents), channels, np.zeros((1, n_channels)), rest=True)[0][0]
        extent = float(np.max(rest.max(axis=0) - rest.min(axis=0)))
        unit_scale = _detect_unit(extent, source)
    scale = float(unit_scale)
    pos_cols = [
        start + i
        for start, ch in zip(_starts(channels), channels, strict=True)
        for i, c in enumerate(ch)
        if c.endswith("position")
    ]
    data[:, pos_cols] *= scale
    label = name if name is not None else Path(source).stem
    return BvhClip(
        name=label,
        joint_names=tuple(names),
        parents=tuple(parents),
        offsets_m=off * scale,
        channels=tuple(channels),
        frames=data,
        frame_time_s=float(frame_time),
        unit_scale=scale,
        source=source,
        joint_map=tuple((joint_map or {}).items()),
    )


def _header_value(lines: Sequence[str], k: int, key: str, source: str) -> tuple[float, int]:
    while k < len(lines) and not lines[k].strip():
        k += 1
    if k >= len(lines):
        msg = f"BVH {source}, line {len(lines)}: missing '{key}:' after MOTION"
        raise ProcessingError(msg)
    m = re.match(rf"\s*{key}\s*:\s*(\S+)\s*$", lines[k], flags=re.IGNORECASE)
    if m is None:
        msg = f"BVH {source}, line {k + 1}: expected '{key}: <number>', found {lines[k].strip()!r}"
        raise ProcessingError(msg)
    try:
        value = float(m.group(1))
    except ValueError:
        msg = f"BVH {source}, line {k + 1}: '{key}' value {m.group(1)!r} is not a number"
        raise ProcessingError(msg) from None
    return value, k + 1


def read_bvh(
    path: str | Path,
    *,
    unit_scale: float | None = None,
    name: str | None = None,
    joint_map: Mapping[str, str] | None = None,
) -> BvhClip:
    """Read a BVH file (see :func:`parse_bvh` for the conventions and options).

    Raises:
        ProcessingError: the file cannot be read or is malformed (the message names the file
            and line).
        ValidationError: ``joint_map`` names a joint that is not ours or not in the file.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8", errors="replace")
    except OSError as err:
        msg = f"cannot read BVH file {p}: {err.strerror or err}"
        raise ProcessingError(msg) from err
    return parse_bvh(text, unit_scale=unit_scale, source=str(p), name=name, joint_map=joint_map)


def load_joint_map(path: str | Path) -> dict[str, str]:
    """Read a joint map: a TOML file of ``our joint = "its joint"`` lines, e.g.
    ``LeftUpLeg = "Bip01_L_Thigh"`` (our names: :data:`~process.body.skeleton.JOINTS`).

    Raises:
        ProcessingError: the file cannot be read, is not TOML, or holds something other than
            our joint names set to strings (the message names the file and the entry).
    """
    from mocaprig.process.body.skeleton import JOINT_INDEX, JOINTS

    p = Path(path)
    try:
        table = tomllib.loads(p.read_text(encoding="utf-8"))
    except OSError as err:
        msg = f"cannot read joint map {p}: {err.strerror or err}"
        raise ProcessingError(msg) from err
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        msg = f'joint map {p} is not TOML ({err}); write lines like LeftUpLeg = "Thigh_L"'
        raise ProcessingError(msg) from err
    out: dict[str, str] = {}
    for ours, theirs in table.items():
        if ours not in JOINT_INDEX:
            msg = f"joint map {p}: {ours!r} is not one of our joints ({', '.join(JOINTS)})"
            raise ProcessingError(msg)
        if not isinstance(theirs, str) or not theirs:
            msg = (
                f"joint map {p}: {ours} = {theirs!r}; the value must be the BVH joint's name "
                f'as a string, e.g. {ours} = "Bip01_L_Thigh"'
            )
            raise ProcessingError(msg)
        out[ours] = theirs
    return out


# --------------------------------------------------------------------------------------------
# Forward kinematics in the BVH's own frame


def _starts(channels: Sequence[tuple[str, ...]]) -> list[int]:
    out: list[int] = []
    col = 0
    for ch in channels:
        out.append(col)
        col += len(ch)
    return out


def _axis_rotation(axis: str, angle_rad: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Elementary rotation matrices about x, y or z, shape ``angle.shape + (3, 3)``."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    o, z = np.ones_like(c), np.zeros_like(c)
    if axis == "X":
        rows = ((o, z, z), (z, c, -s), (z, s, c))
    elif axis == "Y":
        rows = ((c, z, s), (z, o, z), (-s, z, c))
    else:
        rows = ((c, -s, z), (s, c, z), (z, z, o))
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def _forward(
    offsets: npt.NDArray[np.float64],
    parents: Sequence[int],
    channels: Sequence[tuple[str, ...]],
    frames: npt.NDArray[np.float64],
    *,
    rest: bool = False,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    n = frames.shape[0]
    j_count = len(parents)
    pos = np.zeros((n, j_count, 3))
    rot = np.zeros((n, j_count, 3, 3))
    eye = np.broadcast_to(np.eye(3), (n, 3, 3))
    for j, (p, start) in enumerate(zip(parents, _starts(channels), strict=True)):
        local_r = np.array(eye)
        trans = np.broadcast_to(offsets[j], (n, 3)).copy()
        for i, ch in enumerate(channels[j]):
            if rest:
                continue
            values = frames[:, start + i]
            if ch.endswith("position"):
                trans[:, "XYZ".index(ch[0])] = values
            else:
                local_r = local_r @ _axis_rotation(ch[0], np.deg2rad(values))
        if p < 0:
            pos[:, j] = trans
            rot[:, j] = local_r
        else:
            pos[:, j] = pos[:, p] + np.einsum("fij,fj->fi", rot[:, p], trans)
            rot[:, j] = rot[:, p] @ local_r
    return pos, rot


def bvh_forward_kinematics(
    clip: BvhClip, *, frames: slice | npt.ArrayLike | None = None
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Global joint positions and rotations in the BVH's native frame and metres.

    Args:
        clip: The clip.
        frames: Which frames (a slice or index array; default all).

    Returns:
        ``(positions (F, J, 3) m, rotations (F, J, 3, 3))``; a rotation maps the joint's local
        frame to the BVH world frame.
    """
    if frames is None:
        data = clip.frames
    elif isinstance(frames, slice):
        data = clip.frames[frames]
    else:
        data = clip.frames[np.asarray(frames, dtype=np.intp)]
    data = np.atleast_2d(data)
    return _forward(clip.offsets_m, clip.parents, clip.channels, data)


def bvh_global_positions(
    clip: BvhClip, *, frames: slice | npt.ArrayLike | None = None
) -> npt.NDArray[np.float64]:
    """Global joint positions (m) in the BVH's native frame, shape ``(F, J, 3)``."""
    return bvh_forward_kinematics(clip, frames=frames)[0]


def bvh_rest_positions(clip: BvhClip) -> npt.NDArray[np.float64]:
    """Joint positions (m) of the rest pose (all channels zero, offsets only), shape ``(J, 3)``."""
    zero = np.zeros((1, clip.frames.shape[1]))
    pos, _ = _forward(clip.offsets_m, clip.parents, clip.channels, zero, rest=True)
    return np.asarray(pos[0], dtype=np.float64)


# --------------------------------------------------------------------------------------------
# Retargeting onto our skeleton

#: Direction cues (our joint a -> our joint b, weight) fitted by :func:`retarget_bvh`.
_CUES: tuple[tuple[str, str, float], ...] = (
    ("Hips", "Spine1", 1.0),
    ("Spine1", "Spine2", 1.0),
    ("Spine2", "Neck", 1.0),
    ("Neck", "Head", 0.5),
    ("Head", "HeadEnd", 0.5),
    ("LeftUpLeg", "RightUpLeg", 2.0),
    ("LeftArm", "RightArm", 1.0),
    *(
        cue
        for s in ("Right", "Left")
        for cue in (
            ("Spine2", f"{s}Arm", 0.5),
            (f"{s}Arm", f"{s}ForeArm", 1.0),
            (f"{s}ForeArm", f"{s}Hand", 1.0),
            (f"{s}Hand", f"{s}HandEnd", 0.3),
            (f"{s}UpLeg", f"{s}Leg", 1.0),
            (f"{s}Leg", f"{s}Foot", 1.0),
            (f"{s}Foot", f"{s}ToeBase", 1.0),
            (f"{s}Foot", f"{s}ToeEnd", 0.3),
        )
    ),
)

UpAxis = Literal["auto", "x", "y", "z"]


@dataclass(frozen=True, slots=True)
class RetargetReport:
    """How well a retargeted motion follows its BVH clip.

    Attributes:
        bone_angle_error_deg: Mean angle (deg) between our and the BVH's direction for every
            direction cue used by the fit, over frames and cues.
        bone_angle_error_deg_p95: 95th percentile of the same angles (deg).
        mpjpe_m: Mean per-joint position error (m) over the mapped joints, both skeletons
            root-centred and the BVH scaled by the one least-squares factor ``scale``. This
            mixes pose error with the two skeletons' different proportions.
        mpjpe_bone_normalised_m: Mean per-joint position error (m) against a reference built
            by chaining our bone lengths along the BVH's bone directions from the root (bones
            without a BVH counterpart copy ours): pose error alone, in our body's scale.
        scale: The global factor of ``mpjpe_m`` (our size / BVH size).
        joints: Our joints that were compared.
        num_frames: Frames compared.
    """

    bone_angle_error_deg: float
    bone_angle_error_deg_p95: float
    mpjpe_m: float
    mpjpe_bone_normalised_m: float
    scale: float
    joints: tuple[str, ...]
    num_frames: int


def map_bvh_joints(clip: BvhClip, joint_map: Mapping[str, str] | None = None) -> JointMapping:
    """Our joints on the clip's skeleton (:func:`~process.body.bvh_names.map_joints`): the
    clip's own joint map (:attr:`BvhClip.joint_map`) updated with ``joint_map``, then the naming
    tables of the detected exporter family and the skeleton's structure.

    Raises:
        ValidationError: a joint map names a joint that is not ours or not in the BVH.
        ProcessingError: the hips, both hip joints or the chest cannot be matched; the message
            lists both skeletons' joints and the ``--joint-map`` file to write.
    """
    user = {**dict(clip.joint_map), **(joint_map or {})}
    return map_joints(clip.joint_names, clip.parents, joint_map=user, source=clip.source)


def resolve_joint_map(clip: BvhClip, joint_map: Mapping[str, str] | None = None) -> dict[str, int]:
    """Our joint name -> BVH joint index, for our joints that are BVH joints themselves (a
    joint derived on a bone, see :func:`map_bvh_joints`, is left out).

    Args:
        clip: The BVH clip.
        joint_map: Our joint name -> BVH joint name, overriding the defaults (exact names).

    Raises:
        ValidationError: ``joint_map`` names an unknown joint of ours or of the BVH.
        ProcessingError: the hips, both hips joints or the spine cannot be mapped.
    """
    return map_bvh_joints(clip, joint_map).indices()


def _axis_vector(v: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    out = np.zeros(3)
    k = int(np.argmax(np.abs(v)))
    out[k] = np.sign(v[k]) or 1.0
    return out


def bvh_to_body_frame(
    clip: BvhClip, *, up_axis: UpAxis = "auto", joint_map: Mapping[str, str] | None = None
) -> npt.NDArray[np.float64]:
    """The rotation (3, 3) taking BVH world coordinates to ours (Z up, subject facing +Y).

    The BVH's up axis is ``up_axis`` or, with ``"auto"``, the rest skeleton's hips-to-chest
    axis; its lateral axis is the rest hips line (left hip -> right hip, our +X). Both are
    snapped to the nearest coordinate axis, so the result is a signed permutation: e.g. CMU
    (Y up, +Z forward, +X the subject's left) gives ``ours = (-x, z, y)``.

    Raises:
        ProcessingError: the up and lateral axes coincide.
    """
    m = map_bvh_joints(clip, joint_map)
    rest = m.points(bvh_rest_positions(clip))
    col = m.column
    lateral = _axis_vector(rest[col("RightUpLeg")] - rest[col("LeftUpLeg")])
    if up_axis == "auto":
        up = _axis_vector(rest[col("Spine2")] - rest[col("Hips")])
    else:
        up = np.zeros(3)
        up["xyz".index(up_axis)] = 1.0
    if abs(float(lateral @ up)) > 0.5:
        msg = (
            f"BVH {clip.source}: the up axis {up} and the hips line {lateral} coincide; "
            "pass up_axis= explicitly"
        )
        raise ProcessingError(msg)
    forward = np.cross(up, lateral)
    return np.stack([lateral, forward, up])


def _how_summary(mapping: JointMapping) -> str:
    """``"; by structure: Spine2, Spine1; derived: ..."`` for the joints not matched by name."""
    parts = []
    for how in ("joint map", "structure", "derived"):
        names = [n for n, m in mapping.joints.items() if m.how == how]
        if names:
            parts.append(
                f"{'from the joint map' if how == 'joint map' else how}: {', '.join(names)}"
            )
    return "".join(f"; {p}" for p in parts)


def _unit(v: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.asarray(v / np.maximum(n, 1e-12))


def _usable_cues(clip: BvhClip, jmap: JointMapping) -> list[tuple[int, int, int, int, float]]:
    """(our joint a, our joint b, column of a, column of b in ``jmap.points``, weight)."""
    from mocaprig.process.body.skeleton import JOINT_INDEX

    rest = jmap.points(bvh_rest_positions(clip))
    cues = []
    for a, b, w in _CUES:
        if a in jmap.joints and b in jmap.joints:
            ia, ib = jmap.column(a), jmap.column(b)
            if np.linalg.norm(rest[ib] - rest[ia]) > 0.01:
                cues.append((JOINT_INDEX[a], JOINT_INDEX[b], ia, ib, w))
    return cues


def retarget_bvh(
    clip: BvhClip,
    shape: BodyShape,
    *,
    joint_map: Mapping[str, str] | None = None,
    up_axis: UpAxis = "auto",
    iterations: int = 60,
    smoothness: float = 0.05,
    ground: bool = True,
    progress: Callable[[int, int], None] | None = None,
) -> Motion:
    """Retarget a BVH clip onto our skeleton: one 33-parameter pose per BVH frame.

    Method (independent of either skeleton's local axis conventions):

    1. BVH global joint positions (:func:`bvh_global_positions`) are rotated into our frame
       (:func:`bvh_to_body_frame`: Z up, facing +Y) and BVH joints are matched to ours by the
       joint map, the exporter's naming table and the skeleton's structure
       (:func:`map_bvh_joints`; the family found is logged).
    2. For every frame at once, our root rotation and 27 angles are fitted with L-BFGS through
       the differentiable forward kinematics so that each direction cue (bones such as
       thigh, shank, upper arm, forearm, foot, spine segments, plus the hip and shoulder lines
       for the root and spine twist) points the same way as in the BVH (loss ``w (1 - cos)``).
       Angles are kept inside the limits by a stiff quadratic penalty and clamped at the end;
       a small smoothness term couples neighbouring frames (the batched equivalent of a
       frame-to-frame warm start) and a tiny pull to neutral settles unobservable twists
       (forearm pronation). The root rotation starts from the hips line and the spine.
    3. The root translation is the BVH hips position times the leg-length ratio (ours / BVH);
       with ``ground`` the whole clip is then shifted vertically so that the lowest sole
       point touches the floor in the median frame, and frames that would still put a sole
       point below the floor have their root raised until it touches.

    Args:
        clip: The BVH clip.
        shape: Our subject's body shape.
        joint_map: Our joint name -> BVH joint name, on top of the clip's own
            (:attr:`BvhClip.joint_map`) and before the naming tables.
        up_axis: The BVH's up axis, or ``"auto"`` to detect it.
        iterations: L-BFGS iterations.
        smoothness: Weight of the frame-to-frame smoothness term.
        ground: Put the feet on the floor (see 3).
        progress: Called as ``progress(done, total)`` during the fit.

    Returns:
        The motion, at the clip's frame rate, named after the clip.

    Raises:
        ProcessingError: the joints cannot be mapped (see :func:`resolve_joint_map`).
    """
    import torch
    from scipy.spatial.transform import Rotation

    from mocaprig.process.body.kinematics import clamp_to_limits, forward_kinematics_torch
    from mocaprig.process.body.motion import Motion
    from mocaprig.process.body.shape import rest_offsets
    from mocaprig.process.body.skeleton import DOF_LIMITS_RAD, JOINTS, POSE_DIM

    started = time.perf_counter()
    mapping = map_bvh_joints(clip, joint_map)
    jmap = {name: mapping.column(name) for name in mapping.names}
    by_name = any(m.how == "name" for m in mapping.joints.values())
    _log.info(
        "BVH %s: %s; %d of our %d joints matched%s",
        clip.source,
        f"{mapping.family.name} joint names ({mapping.family.description})"
        if by_name
        else "joints named by the joint map",
        len(jmap),
        len(JOINTS),
        _how_summary(mapping),
    )
    conv = bvh_to_body_frame(clip, up_axis=up_axis, joint_map=joint_map)
    # (F, M, 3): our mapped joints, our axes, BVH scale
    pos = mapping.points(bvh_global_positions(clip)) @ conv.T
    n = pos.shape[0]
    cues = _usable_cues(clip, mapping)
    target = _unit(pos[:, [c[3] for c in cues]] - pos[:, [c[2] for c in cues]])

    # Initial root rotation from the hips line and the hips -> chest direction.
    x_axis = _unit(pos[:, jmap["RightUpLeg"]] - pos[:, jmap["LeftUpLeg"]])
    up = pos[:, jmap["Spine2"]] - pos[:, jmap["Hips"]]
    z_axis = _unit(up - np.sum(up * x_axis, axis=-1, keepdims=True) * x_axis)
    y_axis = np.cross(z_axis, x_axis)
    root_rot = Rotation.from_matrix(np.stack([x_axis, y_axis, z_axis], axis=-1)).as_rotvec()

    # Root translation from the hips, scaled by the leg-length ratio.
    rest = mapping.points(bvh_rest_positions(clip))
    leg_bvh = [
        np.linalg.norm(rest[jmap[f"{s}Leg"]] - rest[jmap[f"{s}UpLeg"]])
        + np.linalg.norm(rest[jmap[f"{s}Foot"]] - rest[jmap[f"{s}Leg"]])
        for s in ("Left", "Right")
        if f"{s}Leg" in jmap and f"{s}Foot" in jmap
    ]
    leg_ours = shape.thigh_length_m + shape.shank_length_m
    ratio = leg_ours / float(np.mean(leg_bvh)) if leg_bvh else 1.0
    root_pos = pos[:, jmap["Hips"]] * ratio

    dt = torch.float64
    offsets = torch.as_tensor(rest_offsets(shape), dtype=dt)
    lo = torch.tensor(DOF_LIMITS_RAD[:, 0], dtype=dt)
    hi = torch.tensor(DOF_LIMITS_RAD[:, 1], dtype=dt)
    tgt = torch.as_tensor(target, dtype=dt)
    weights = torch.as_tensor([c[4] for c in cues], dtype=dt)
    ia = [c[0] for c in cues]
    ib = [c[1] for c in cues]
    trans = torch.zeros((n, 3), dtype=dt)
    params = torch.zeros((n, 30), dtype=dt)
    params[:, :3] = torch.as_tensor(root_rot, dtype=dt)
    params.requires_grad_(True)
    opt = torch.optim.LBFGS(
        [params], lr=1.0, max_iter=iterations, history_size=20, line_search_fn="strong_wolfe"
    )
    evals = [0]

    def closure() -> torch.Tensor:
        opt.zero_grad()
        angles = params[:, 3:]
        pose = torch.cat([params[:, :3], trans, angles], dim=1)
        joints, _ = forward_kinematics_torch(pose, offsets)
        d = joints[:, ib] - joints[:, ia]
        d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        loss: torch.Tensor = ((1.0 - (d * tgt).sum(-1)) * weights).sum() / n
        over = torch.relu(angles - hi) + torch.relu(lo - angles)
        loss = loss + 100.0 * (over * over).sum() / n + 1e-4 * (angles * angles).sum() / n
        if n > 1:
            step = params[1:] - params[:-1]
            loss = loss + smoothness * (step * step).sum() / n
        loss.backward()  # type: ignore[no-untyped-call]
        evals[0] += 1
        if progress is not None:
            progress(min(evals[0], iterations), iterations)
        return loss

    opt.step(closure)  # type: ignore[no-untyped-call]
    fitted = params.detach().numpy()
    poses = np.zeros((n, POSE_DIM))
    poses[:, :3] = fitted[:, :3]
    poses[:, 3:6] = root_pos
    poses[:, 6:] = fitted[:, 3:]
    poses = clamp_to_limits(poses)
    if ground:
        from mocaprig.process.body.kinematics import forward_kinematics
        from mocaprig.process.body.procedural import floor_clearance_m

        clearance = floor_clearance_m(forward_kinematics(poses, shape), shape)
        poses[:, 5] -= float(np.median(clearance))
        # Our legs cannot always fold like the source's (ankle dorsiflexion stops at 20 deg,
        # toes are rigid), so in deep crouches the scaled source root would sink a foot into
        # the floor; raise the root in just those frames so the sole only touches it.
        below = clearance - float(np.median(clearance))
        poses[:, 5] += np.maximum(-below, 0.0)
    _log.info(
        "retargeted %s: %d frames, %d direction cues, leg ratio %.3f, %d L-BFGS evaluations "
        "in %.2f s",
        clip.source,
        n,
        len(cues),
        ratio,
        evals[0],
        time.perf_counter() - started,
    )
    return Motion(clip.name, clip.rate_hz, poses)


def retarget_errors(
    clip: BvhClip,
    motion: Motion,
    shape: BodyShape,
    *,
    joint_map: Mapping[str, str] | None = None,
    up_axis: UpAxis = "auto",
) -> RetargetReport:
    """Compare a retargeted motion with its BVH clip (see :class:`RetargetReport`).

    Raises:
        ValidationError: the motion and the clip have different frame counts.
    """
    from mocaprig.process.body.kinematics import forward_kinematics
    from mocaprig.process.body.skeleton import JOINT_INDEX, JOINTS, PARENTS

    if motion.num_frames != clip.num_frames:
        msg = f"motion has {motion.num_frames} frames, the BVH clip {clip.num_frames}"
        raise ValidationError(msg)
    mapping = map_bvh_joints(clip, joint_map)
    jmap = {name: mapping.column(name) for name in mapping.names}
    conv = bvh_to_body_frame(clip, up_axis=up_axis, joint_map=joint_map)
    theirs = mapping.points(bvh_global_positions(clip)) @ conv.T
    ours = forward_kinematics(motion.poses, shape).positions_m
    cues = _usable_cues(clip, mapping)
    d_ours = _unit(ours[:, [c[1] for c in cues]] - ours[:, [c[0] for c in cues]])
    d_theirs = _unit(theirs[:, [c[3] for c in cues]] - theirs[:, [c[2] for c in cues]])
    ang = np.degrees(np.arccos(np.clip(np.sum(d_ours * d_theirs, axis=-1), -1.0, 1.0)))
    names = tuple(n for n in jmap if n != "Hips")
    a = ours[:, [JOINT_INDEX[n] for n in names]] - ours[:, [JOINT_INDEX["Hips"]]]
    b = theirs[:, [jmap[n] for n in names]] - theirs[:, [jmap["Hips"]]]
    scale = float(np.sum(a * b) / np.sum(b * b))
    mpjpe = float(np.mean(np.linalg.norm(a - scale * b, axis=-1)))
    rest = mapping.points(bvh_rest_positions(clip))
    ref = np.array(ours)
    for j in range(1, len(PARENTS)):
        p = PARENTS[j]
        bone = ours[:, j] - ours[:, p]
        ours_name, parent_name = JOINTS[j], JOINTS[p]
        if ours_name in jmap and parent_name in jmap:
            ia, ib = jmap[parent_name], jmap[ours_name]
            if np.linalg.norm(rest[ib] - rest[ia]) > 0.01:
                length = np.linalg.norm(bone, axis=-1, keepdims=True)
                bone = length * _unit(theirs[:, ib] - theirs[:, ia])
        ref[:, j] = ref[:, p] + bone
    idx = [JOINT_INDEX[n] for n in names]
    mpjpe_norm = float(np.mean(np.linalg.norm(ours[:, idx] - ref[:, idx], axis=-1)))
    return RetargetReport(
        bone_angle_error_deg=float(ang.mean()),
        bone_angle_error_deg_p95=float(np.percentile(ang, 95)),
        mpjpe_m=mpjpe,
        mpjpe_bone_normalised_m=mpjpe_norm,
        scale=scale,
        joints=names,
        num_frames=int(ours.shape[0]),
    )
