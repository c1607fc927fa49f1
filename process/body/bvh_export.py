"""Writing our skeleton's poses as a BVH (Biovision hierarchy) file.

The hierarchy is :data:`~process.body.skeleton.JOINTS` / :data:`~process.body.skeleton.PARENTS`
with the body's rest offsets (:func:`~process.body.shape.rest_offsets`). Joints with children
get ``JOINT`` blocks; the childless ends (``HeadEnd``, ``RightHandEnd``, ``RightToeEnd`` …) are
written as ``End Site`` of their parent, which BVH readers (ours included,
:func:`~process.body.bvh.parse_bvh`) name ``<parent>_End`` (so ``HeadEnd`` reads back as
``Head_End``). Channels: the root has ``Xposition Yposition Zposition Zrotation Yrotation
Xrotation``, every other joint ``Zrotation Yrotation Xrotation`` (intrinsic, ``R = Rz Ry Rx``,
degrees, the Biovision convention). Each joint's local rotation is ``R_parent⁻¹ R_joint`` from
:func:`~process.body.kinematics.forward_kinematics`'s world rotations, so the BVH's forward
kinematics reproduce our joint positions exactly (to float printing).

Frames: our world is Z up; BVH viewers expect Y up, so by default (``up="y"``) the root is
turned by the fixed rotation ``(x, y, z) -> (x, z, -y)``; ``up="z"`` keeps our world axes.
Lengths are written in centimetres (the common BVH unit), ``unit_scale=0.01`` on reading.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
from pathlib import Path
from typing import Final, Literal

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from mocaprig.errors import ProcessingError, ValidationError
from mocaprig.process.body.kinematics import forward_kinematics
from mocaprig.process.body.shape import BodyShape, rest_offsets
from mocaprig.process.body.skeleton import JOINTS, PARENTS, POSE_DIM
from mocaprig.validation import check_finite, check_positive, check_shape

__all__ = [
    "BVH_CM_PER_M",
    "Y_UP_FROM_Z_UP",
    "BvhWriter",
    "bvh_joint_name",
    "bvh_text",
    "write_bvh",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]

#: File length unit: centimetres per metre.
BVH_CM_PER_M: Final = 100.0
#: Rotation from our Z-up world to the Y-up BVH world: ``(x, y, z) -> (x, z, -y)``.
Y_UP_FROM_Z_UP: Final = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
Y_UP_FROM_Z_UP.setflags(write=False)

_CHILDREN: Final = tuple(tuple(c for c, p in enumerate(PARENTS) if p == j) for j in range(26))


def bvh_joint_name(joint: int) -> str:
    """The name joint ``joint`` of :data:`JOINTS` has in the written file, as read back
    (childless ends are ``End Site`` leaves: ``<parent>_End``)."""
    if _CHILDREN[joint]:
        return JOINTS[joint]
    return f"{JOINTS[PARENTS[joint]]}_End"


def _hierarchy(offsets_cm: F64) -> list[str]:
    lines = ["HIERARCHY"]

    def joint(j: int, depth: int) -> None:
        pad = "  " * depth
        x, y, z = offsets_cm[j]
        if not _CHILDREN[j]:
            lines.extend(
                [f"{pad}End Site", f"{pad}{{", f"{pad}  OFFSET {x:.6f} {y:.6f} {z:.6f}", f"{pad}}}"]
            )
            return
        head = "ROOT" if PARENTS[j] < 0 else "JOINT"
        lines.extend([f"{pad}{head} {JOINTS[j]}", f"{pad}{{"])
        lines.append(f"{pad}  OFFSET {x:.6f} {y:.6f} {z:.6f}")
        if PARENTS[j] < 0:
            lines.append(
                f"{pad}  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation"
            )
        else:
            lines.append(f"{pad}  CHANNELS 3 Zrotation Yrotation Xrotation")
        for c in _CHILDREN[j]:
            joint(c, depth + 1)
        lines.append(f"{pad}}}")

    joint(0, 0)
    return lines


def _motion(poses: F64, shape: BodyShape, up: Literal["y", "z"]) -> F64:
    """Channel values (F, 6 + 3·J_inner): root position cm, then ZYX Euler degrees."""
    kin = forward_kinematics(poses, shape)
    rots = kin.rotations
    inner = [j for j in range(len(JOINTS)) if _CHILDREN[j]]
    local = np.empty((poses.shape[0], len(inner), 3, 3))
    for k, j in enumerate(inner):
        p = PARENTS[j]
        local[:, k] = rots[:, j] if p < 0 else np.swapaxes(rots[:, p], -1, -2) @ rots[:, j]
    root_pos = kin.positions_m[:, 0]
    if up == "y":
        local[:, 0] = Y_UP_FROM_Z_UP @ local[:, 0]
        root_pos = root_pos @ Y_UP_FROM_Z_UP.T
    euler = Rotation.from_matrix(local.reshape(-1, 3, 3)).as_euler("ZYX", degrees=True)
    return np.concatenate([root_pos * BVH_CM_PER_M, euler.reshape(poses.shape[0], -1)], axis=1)


def _check_options(rate_hz: float, up: str, who: str) -> None:
    check_positive(rate_hz, name="rate_hz")
    if up not in ("y", "z"):
        msg = f"{who}: up must be 'y' or 'z', got {up!r}"
        raise ValidationError(msg)


def _check_poses(poses: npt.ArrayLike, who: str) -> F64:
    q = np.asarray(check_finite(check_shape(poses, ["F", POSE_DIM], name="poses")), np.float64)
    if q.shape[0] == 0:
        msg = f"{who}: no poses to write; give at least one (F, 33) pose"
        raise ValidationError(msg)
    return q


def _header(shape: BodyShape, frames: int, rate_hz: float) -> list[str]:
    lines = _hierarchy(rest_offsets(shape) * BVH_CM_PER_M)
    lines.extend(["MOTION", f"Frames: {frames}", f"Frame Time: {1.0 / rate_hz:.9f}"])
    return lines


def _motion_lines(poses: F64, shape: BodyShape, up: Literal["y", "z"]) -> str:
    values = _motion(poses, shape, up)
    return "".join(" ".join(f"{v:.6f}" for v in row) + "\n" for row in values)


def bvh_text(
    poses: npt.ArrayLike,
    shape: BodyShape,
    *,
    rate_hz: float,
    up: Literal["y", "z"] = "y",
) -> str:
    """The BVH text of poses (F, 33) (:mod:`process.body.skeleton` layout) at ``rate_hz``.

    Raises:
        ValidationError: wrong pose shape, non-finite values, no frames or a bad rate.
    """
    q = _check_poses(poses, "bvh_text")
    _check_options(rate_hz, up, "bvh_text")
    return "\n".join(_header(shape, q.shape[0], rate_hz)) + "\n" + _motion_lines(q, shape, up)


class BvhWriter:
    """Write poses as a BVH file block by block (memory bounded by a block; module doc).

    The motion lines go to a file beside ``path`` as they come; :meth:`close` writes the
    hierarchy and the frame count, copies the motion after them and moves the file into place,
    so a long take's poses are never all held. Leaving the ``with`` block on an exception removes
    the partial files.

    Raises:
        ValidationError: bad options. ProcessingError: ``path`` exists and ``overwrite`` is
            False, or a write failed.
    """

    def __init__(
        self,
        path: str | Path,
        shape: BodyShape,
        *,
        rate_hz: float,
        up: Literal["y", "z"] = "y",
        overwrite: bool = False,
    ) -> None:
        _check_options(rate_hz, up, "BvhWriter")
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            msg = f"{self.path} exists; pass --overwrite (overwrite=True) to replace it"
            raise ProcessingError(msg)
        self._shape, self._rate_hz, self._up = shape, rate_hz, up
        self._frames = 0
        self._closed = False
        self._body = self.path.with_name(f".{self.path.name}.{os.getpid()}.motion.tmp")
        self._tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        try:
            self._fh = self._body.open("w", encoding="utf-8", newline="\n")
        except OSError as err:
            msg = f"cannot write BVH file {self.path}: {err}; check the folder and free space"
            raise ProcessingError(msg) from err

    def __enter__(self) -> BvhWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.discard()

    @property
    def frames(self) -> int:
        """Frames written so far."""
        return self._frames

    def write(self, poses: npt.ArrayLike) -> None:
        """Append poses (F, 33) (:mod:`process.body.skeleton` layout)."""
        q = _check_poses(poses, f"BVH {self.path}")
        try:
            self._fh.write(_motion_lines(q, self._shape, self._up))
        except OSError as err:
            self.discard()
            msg = f"cannot write BVH file {self.path}: {err}; check the folder and free space"
            raise ProcessingError(msg) from err
        self._frames += q.shape[0]

    def close(self) -> Path:
        """Write the hierarchy and frame count, then the motion; move the file into place."""
        if self._closed:
            return self.path
        if self._frames == 0:
            self.discard()
            msg = f"BVH {self.path}: no poses were written; give at least one (F, 33) pose"
            raise ValidationError(msg)
        try:
            self._fh.close()
            with self._tmp.open("w", encoding="utf-8", newline="\n") as out:
                out.write("\n".join(_header(self._shape, self._frames, self._rate_hz)) + "\n")
                with self._body.open("r", encoding="utf-8", newline="\n") as body:
                    shutil.copyfileobj(body, out, 1 << 20)
            self._tmp.replace(self.path)
        except OSError as err:
            self.discard()
            msg = f"cannot write BVH file {self.path}: {err}; check the folder and free space"
            raise ProcessingError(msg) from err
        finally:
            self._body.unlink(missing_ok=True)
        self._closed = True
        _log.info("wrote %s (%d frames at %g Hz)", self.path, self._frames, self._rate_hz)
        return self.path

    def discard(self) -> None:
        """Stop and remove the partial files (nothing is left at ``path``)."""
        self._closed = True
        with contextlib.suppress(OSError):
            self._fh.close()
        self._body.unlink(missing_ok=True)
        self._tmp.unlink(missing_ok=True)


def write_bvh(
    path: str | Path,
    poses: npt.ArrayLike,
    shape: BodyShape,
    *,
    rate_hz: float,
    up: Literal["y", "z"] = "y",
    overwrite: bool = False,
) -> Path:
    """Write poses (F, 33) as a BVH file (module doc); returns the path.

    Raises:
        ValidationError: bad poses or options (:func:`bvh_text`).
        ProcessingError: ``path`` exists and ``overwrite`` is False, or the write failed.
    """
    q = _check_poses(poses, "write_bvh")
    with BvhWriter(path, shape, rate_hz=rate_hz, up=up, overwrite=overwrite) as w:
        w.write(q)
    return w.path
