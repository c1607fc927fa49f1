"""Foxglove ``SceneUpdate`` builders: the one way results are drawn (DeMoCap and EventCap).

Points are world metres; ``frame_id`` names the frame the points are in; ``t_ns`` stamps the
entity. Colours are RGBA in [0, 1].
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Final

import numpy as np
import numpy.typing as npt

from mocaprig.acquire.recording_format import SceneUpdateMsg

__all__ = ["BONE_RGBA", "CAPSULE_RGBA", "capsule_scene", "points_scene"]

F64 = npt.NDArray[np.float64]

#: Colour of bone lines.
BONE_RGBA: Final = (0.9, 0.9, 0.9, 1.0)
#: Colour of a capsule template.
CAPSULE_RGBA: Final = (0.95, 0.75, 0.55, 0.6)


def points_scene(
    entity_id: str,
    frame_id: str,
    t_ns: int,
    points_m: F64,
    size_m: float,
    rgba: tuple[float, float, float, float],
    metadata: Mapping[str, str],
    *,
    names: Sequence[str] = (),
    bones: Sequence[tuple[int, int]] = (),
) -> SceneUpdateMsg:
    """One entity of spheres ``points_m`` (N, 3) of diameter ``size_m`` (and a text label per
    point from ``names``, and ``bones`` as one line list) as a ``foxglove.SceneUpdate``."""
    from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    upd = SceneUpdate()
    ent = upd.entities.add()
    ent.timestamp.FromNanoseconds(int(t_ns))
    ent.frame_id = frame_id
    ent.id = entity_id
    for k, v in metadata.items():
        kv = ent.metadata.add()
        kv.key, kv.value = k, v
    for p in points_m:
        s = ent.spheres.add()
        s.pose.position.x, s.pose.position.y, s.pose.position.z = (float(v) for v in p)
        s.pose.orientation.w = 1.0
        s.size.x = s.size.y = s.size.z = size_m
        s.color.r, s.color.g, s.color.b, s.color.a = rgba
    for name, p in zip(names, points_m, strict=False):
        tx = ent.texts.add()
        tx.pose.position.x, tx.pose.position.y, tx.pose.position.z = (float(v) for v in p)
        tx.pose.orientation.w = 1.0
        tx.billboard = True
        tx.font_size = 12.0
        tx.scale_invariant = True
        tx.color.r = tx.color.g = tx.color.b = tx.color.a = 1.0
        tx.text = name
    if bones:
        ln = ent.lines.add()
        ln.type = LinePrimitive.Type.LINE_LIST
        ln.pose.orientation.w = 1.0
        ln.thickness = 3.0
        ln.scale_invariant = True
        ln.color.r, ln.color.g, ln.color.b, ln.color.a = BONE_RGBA
        for a, b in bones:
            for q in (points_m[a], points_m[b]):
                pt = ln.points.add()
                pt.x, pt.y, pt.z = (float(v) for v in q)
    return SceneUpdateMsg(upd)


def _quat_z_to(d: F64) -> F64:
    """Unit quaternions (x, y, z, w) turning +Z onto the unit directions ``d`` (N, 3)."""
    q = np.zeros((d.shape[0], 4))
    q[:, 0], q[:, 1] = -d[:, 1], d[:, 0]  # cross(z, d)
    q[:, 3] = 1.0 + d[:, 2]
    flip = q[:, 3] < 1e-9  # d = -Z: any half turn about a horizontal axis
    q[flip] = (1.0, 0.0, 0.0, 0.0)
    out: F64 = q / np.linalg.norm(q, axis=1, keepdims=True)
    return out


def capsule_scene(
    entity_id: str, frame_id: str, t_ns: int, a_m: F64, b_m: F64, radius_m: F64
) -> SceneUpdateMsg:
    """The posed capsule template as a scene update: per capsule (end points ``a_m``, ``b_m``
    (C, 3) world m, radii (C,) m) a cylinder between the ends and a sphere at each end."""
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    upd = SceneUpdate()
    ent = upd.entities.add()
    ent.timestamp.FromNanoseconds(int(t_ns))
    ent.frame_id, ent.id = frame_id, entity_id
    axis = b_m - a_m
    length = np.linalg.norm(axis, axis=1)
    quat = _quat_z_to(axis / np.maximum(length, 1e-12)[:, None])
    mid = 0.5 * (a_m + b_m)
    for c in range(a_m.shape[0]):
        d = 2.0 * float(radius_m[c])
        if length[c] > 1e-9:
            cy = ent.cylinders.add()
            cy.pose.position.x, cy.pose.position.y, cy.pose.position.z = (float(v) for v in mid[c])
            o = cy.pose.orientation
            o.x, o.y, o.z, o.w = (float(v) for v in quat[c])
            cy.size.x = cy.size.y = d
            cy.size.z = float(length[c])
            cy.bottom_scale = cy.top_scale = 1.0
            cy.color.r, cy.color.g, cy.color.b, cy.color.a = CAPSULE_RGBA
        for p in (a_m[c], b_m[c]):
            s = ent.spheres.add()
            s.pose.position.x, s.pose.position.y, s.pose.position.z = (float(v) for v in p)
            s.pose.orientation.w = 1.0
            s.size.x = s.size.y = s.size.z = d
            s.color.r, s.color.g, s.color.b, s.color.a = CAPSULE_RGBA
    return SceneUpdateMsg(upd)
