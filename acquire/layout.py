"""Foxglove layouts for mocaprig files: one per use, chosen and filled in from a file's channels.

The four layouts ship as package data, ``acquire/data/layouts/<use>.json``, each a Foxglove
layout as the app exports it (``configById`` keyed by ``<PanelType>!<id>``, the ``layout``
mosaic tree of ``{first, second, direction, splitPercentage}`` splits, ``globalVariables``,
``userNodes``, ``playbackConfig``), written for the simulated rig's devices so that it opens on
a ``mocaprig simulate`` recording as it is. :func:`layout_for` fills one in for a file: a panel
(Image, RawMessages) or a Plot series naming a device topic is repeated for each device of that
kind in the file (one IR panel per D415 serial), panels and series whose topics the file lacks
are left out, and a 3D panel follows the frame its scene topics are drawn in.
:func:`layout_problems` checks a layout against a file's channels: every topic a panel names
exists with the schema the panel draws, and every plotted message path is a numeric field of
that schema. :func:`write_layout` is ``mocaprig info FILE --layout``.
"""

from __future__ import annotations

import copy
import json
import logging
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Final, Literal, get_args

from google.protobuf import descriptor_pb2, descriptor_pool  # type: ignore[import-untyped]
from google.protobuf.descriptor import FieldDescriptor  # type: ignore[import-untyped]

from mocaprig.acquire.device_id import DeviceId, DeviceKind
from mocaprig.acquire.recording_format import MESSAGE_TYPES
from mocaprig.errors import RecordingError, ValidationError

__all__ = [
    "LAYOUT_USES",
    "LayoutUse",
    "WrittenLayout",
    "choose_use",
    "default_layout_path",
    "layout_for",
    "layout_problems",
    "layout_template",
    "write_layout",
]

_log = logging.getLogger(__name__)

LayoutUse = Literal["recording", "calibration", "democap", "eventcap"]
"""What a file is for: a recording check, a calibrated recording's review, a DeMoCap replay's
results, an EventCap run's results."""
LAYOUT_USES: Final[tuple[LayoutUse, ...]] = get_args(LayoutUse)

#: The calibration attachment of a calibrated recording (docs/recording-format.md §4); the
#: same name as ``calib.calibration_attachment.ATTACHMENT_NAME``, which acquire cannot import.
_CALIBRATION_ATTACHMENT: Final = "calibration.toml"

_IMAGE_SCHEMAS: Final = frozenset({"foxglove.RawImage", "foxglove.CompressedImage"})
_SCENE_SCHEMA: Final = "foxglove.SceneUpdate"
_NUMERIC_TYPES: Final = frozenset(
    {
        FieldDescriptor.TYPE_DOUBLE,
        FieldDescriptor.TYPE_FLOAT,
        FieldDescriptor.TYPE_INT64,
        FieldDescriptor.TYPE_UINT64,
        FieldDescriptor.TYPE_INT32,
        FieldDescriptor.TYPE_UINT32,
        FieldDescriptor.TYPE_SINT32,
        FieldDescriptor.TYPE_SINT64,
        FieldDescriptor.TYPE_FIXED32,
        FieldDescriptor.TYPE_FIXED64,
        FieldDescriptor.TYPE_SFIXED32,
        FieldDescriptor.TYPE_SFIXED64,
        FieldDescriptor.TYPE_BOOL,
        FieldDescriptor.TYPE_ENUM,
    }
)
_LAYOUT_KEYS: Final = ("configById", "layout", "globalVariables", "userNodes", "playbackConfig")
# One path segment: a field name, then optional [slice] and {filter} (Foxglove message paths).
_SEGMENT: Final = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)(\[[^\]]*\])?(\{[^}]*\})?$")

Role = Literal["image", "calibration", "scene", "plot", "raw", "log"]


@dataclass(frozen=True, slots=True)
class _Ref:
    """A topic or message path a panel names, and what the panel does with it."""

    role: Role
    path: str


@dataclass(frozen=True, slots=True)
class WrittenLayout:
    """What :func:`write_layout` wrote: the file, the use chosen and its panel count."""

    path: Path
    use: LayoutUse
    panels: int


# --------------------------------------------------------------------------------- templates


def layout_template(use: LayoutUse) -> dict[str, Any]:
    """The stored layout of ``use`` (``acquire/data/layouts/<use>.json``), parsed.

    Raises:
        ValidationError: ``use`` is not one of :data:`LAYOUT_USES`.
    """
    if use not in LAYOUT_USES:
        msg = f"layout use {use!r} is not one of {list(LAYOUT_USES)}"
        raise ValidationError(msg)
    text = resources.files("mocaprig.acquire").joinpath(f"data/layouts/{use}.json").read_text()
    data: dict[str, Any] = json.loads(text)
    return data


def _panel_type(panel_id: str) -> str:
    return panel_id.split("!", 1)[0]


def _refs(panel_id: str, config: Mapping[str, Any]) -> list[_Ref]:
    """The topics and message paths a panel's config names (the keys Foxglove reads)."""
    kind = _panel_type(panel_id)
    refs: list[_Ref] = []
    if kind == "Image":
        mode = config.get("imageMode", {})
        if mode.get("imageTopic"):
            refs.append(_Ref("image", mode["imageTopic"]))
        if mode.get("calibrationTopic"):
            refs.append(_Ref("calibration", mode["calibrationTopic"]))
    elif kind == "3D":
        refs.extend(_Ref("scene", t) for t, s in config.get("topics", {}).items() if s)
    elif kind == "Plot":
        refs.extend(_Ref("plot", p["value"]) for p in config.get("paths", []))
    elif kind == "RawMessages":
        refs.append(_Ref("raw", config.get("topicPath", "")))
    elif kind == "RosOut":
        refs.append(_Ref("log", config.get("topicToRender", "")))
    return refs


def _split_path(path: str, topics: Sequence[str]) -> tuple[str, list[str]] | None:
    """``(topic, field segments)`` of a message path, the topic being the longest of
    ``topics`` it starts with; None when it names none of them."""
    best = None
    for t in topics:
        if (path == t or path.startswith(t + ".")) and (best is None or len(t) > len(best)):
            best = t
    if best is None:
        return None
    rest = path[len(best) + 1 :]
    return best, (rest.split(".") if rest else [])


def _device_of(path: str) -> tuple[DeviceId, str] | None:
    """The device a topic or message path belongs to (the topic ends at the first '.' after
    its last '/'; serials of the stored layouts have no '.')."""
    head, _, tail = path.rpartition("/")
    return DeviceId.from_topic(f"{head}/{tail.split('.', 1)[0]}") if head else None


# --------------------------------------------------------------------------------- choosing


def _template_scene_topics(use: LayoutUse) -> set[str]:
    cfgs = layout_template(use)["configById"]
    return {r.path for pid, cfg in cfgs.items() for r in _refs(pid, cfg) if r.role == "scene"}


def choose_use(schemas: Mapping[str, str], attachments: Sequence[str]) -> LayoutUse:
    """The layout for a file with channels ``schemas`` (topic -> schema name) and
    ``attachments`` (names): results files by the scene topics their layout draws, then a
    calibrated recording (a ``calibration.toml`` attachment), then a recording.

    Raises:
        ValidationError: the file has neither scene results nor device streams.
    """
    scenes = {t for t, s in schemas.items() if s == _SCENE_SCHEMA}
    for use in ("eventcap", "democap"):
        if scenes & _template_scene_topics(use):
            return use
    if any(DeviceId.from_topic(t) is not None for t in schemas):
        return "calibration" if _CALIBRATION_ATTACHMENT in attachments else "recording"
    msg = (
        f"no layout fits a file with topics {sorted(schemas)}: expected device streams "
        "(a recording) or DeMoCap/EventCap results"
    )
    raise ValidationError(msg)


# --------------------------------------------------------------------------------- filling in


def _replace_strings(value: Any, old: str, new: str) -> Any:
    if isinstance(value, str):
        return value.replace(old, new)
    if isinstance(value, dict):
        return {
            _replace_strings(k, old, new): _replace_strings(v, old, new) for k, v in value.items()
        }
    if isinstance(value, list):
        return [_replace_strings(v, old, new) for v in value]
    return value


def _serials(schemas: Mapping[str, str]) -> dict[DeviceKind, list[str]]:
    found: dict[DeviceKind, set[str]] = {}
    for t in schemas:
        parsed = DeviceId.from_topic(t)
        if parsed is not None:
            found.setdefault(parsed[0].kind, set()).add(parsed[0].serial)
    return {k: sorted(v) for k, v in found.items()}


def _has(path: str, schemas: Mapping[str, str]) -> bool:
    return _split_path(path, list(schemas)) is not None


def _fill_plot(
    config: dict[str, Any], schemas: Mapping[str, str], serials: Mapping[DeviceKind, list[str]]
) -> dict[str, Any] | None:
    paths = []
    for p in config.get("paths", []):
        dev = _device_of(p["value"])
        if dev is None:
            paths.append(p)
            continue
        template = dev[0]
        for serial in serials.get(template.kind, []):
            paths.append(_replace_strings(p, template.serial, serial) if template.serial else p)
    kept = [p for p in paths if _has(p["value"], schemas)]
    return {**config, "paths": kept} if kept else None


def _fill_panel(
    panel_id: str,
    config: dict[str, Any],
    schemas: Mapping[str, str],
    frames: Mapping[str, str],
    serials: Mapping[DeviceKind, list[str]],
) -> list[tuple[str, dict[str, Any]]]:
    """The panels one stored panel becomes in the file (none, one, or one per device)."""
    kind = _panel_type(panel_id)
    if kind == "Plot":
        plot = _fill_plot(config, schemas, serials)
        return [] if plot is None else [(panel_id, plot)]
    if kind == "3D":
        topics = {t: s for t, s in config.get("topics", {}).items() if t in schemas}
        if not topics:
            return []
        drawn_in = {frames[t] for t in topics if t in frames}
        stored = str(config.get("followTf", ""))
        follow = drawn_in.pop() if len(drawn_in) == 1 else stored
        # The stored grid layer is pinned to the stored frame: move it with the view.
        layers = _replace_strings(config.get("layers", {}), stored, follow)
        return [(panel_id, {**config, "topics": topics, "followTf": follow, "layers": layers})]
    devices = {dev[0] for r in _refs(panel_id, config) if (dev := _device_of(r.path)) is not None}
    if len(devices) > 1:
        msg = f"stored layout panel {panel_id} names several devices {sorted(map(str, devices))}"
        raise ValidationError(msg)
    clones: list[tuple[str, dict[str, Any]]] = [(panel_id, config)]
    template = devices.pop() if devices else None
    if template is not None and template.serial:  # the sync box has no serial: one per rig
        clones = [
            (f"{panel_id}-{i}", _replace_strings(config, template.serial, serial))
            for i, serial in enumerate(serials.get(template.kind, []))
        ]
    out = []
    for pid, cfg in clones:
        mode = cfg.get("imageMode", {})
        if kind == "Image" and mode.get("calibrationTopic") not in (None, *schemas):
            # An image without its intrinsics still shows; only the 3D overlays need them.
            cfg = {**cfg, "imageMode": {k: v for k, v in mode.items() if k != "calibrationTopic"}}
        if all(_has(r.path, schemas) for r in _refs(pid, cfg)):
            out.append((pid, cfg))
    return out


def _side_by_side(ids: Sequence[str], direction: str) -> Any:
    """A mosaic tree giving ``ids`` equal shares along ``direction``; None for no ids."""
    if not ids:
        return None
    if len(ids) == 1:
        return ids[0]
    rest = _side_by_side(ids[1:], direction)
    return {
        "first": ids[0],
        "second": rest,
        "direction": direction,
        "splitPercentage": round(100.0 / len(ids), 3),
    }


def layout_for(
    schemas: Mapping[str, str],
    *,
    use: LayoutUse,
    frames: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """The stored layout of ``use`` filled in for a file with channels ``schemas`` (topic ->
    schema name) and ``frames`` (topic -> its ``frame_id`` channel metadata).

    Device panels are repeated per device of their kind (side by side within their split),
    Plot series per device, panels and series whose topics the file lacks are left out.

    Raises:
        ValidationError: nothing of the layout fits the file.
    """
    stored = layout_template(use)
    configs: dict[str, Any] = stored["configById"]
    serials = _serials(schemas)
    kept: dict[str, Any] = {}

    def fill(node: Any, direction: str) -> Any:
        if isinstance(node, str):
            panels = _fill_panel(node, configs[node], schemas, frames or {}, serials)
            kept.update(panels)
            return _side_by_side(
                [p for p, _ in panels], "row" if direction == "column" else "column"
            )
        first = fill(node["first"], node["direction"])
        second = fill(node["second"], node["direction"])
        if first is None or second is None:
            return second if first is None else first
        return {**node, "first": first, "second": second}

    tree = fill(stored["layout"], "row")
    if tree is None:
        msg = f"none of the {use} layout's panels fits a file with topics {sorted(schemas)}"
        raise ValidationError(msg)
    return {**copy.deepcopy(stored), "configById": kept, "layout": tree}


# --------------------------------------------------------------------------------- checking


def _leaves(node: Any) -> Iterator[str]:
    if isinstance(node, str):
        yield node
    elif isinstance(node, dict):
        yield from _leaves(node.get("first"))
        yield from _leaves(node.get("second"))


_DESCRIPTORS: dict[str, Any] = {}


def _descriptor(schema_name: str) -> Any:
    """The protobuf descriptor of a schema the recorder writes (built from the very bytes it
    stores in the file), or None for a schema mocaprig does not write."""
    if schema_name not in _DESCRIPTORS:
        cls = MESSAGE_TYPES.get(schema_name)
        if cls is None:
            return None
        pool = descriptor_pool.DescriptorPool()
        for fdp in descriptor_pb2.FileDescriptorSet.FromString(cls.SCHEMA.data).file:
            pool.Add(fdp)
        _DESCRIPTORS[schema_name] = pool.FindMessageTypeByName(schema_name)
    return _DESCRIPTORS[schema_name]


def _field_problem(schema_name: str, fields: Sequence[str], *, numeric: bool) -> str | None:
    """What is wrong with the field path ``fields`` in ``schema_name``; None when it resolves
    (to a numeric scalar when ``numeric``)."""
    desc = _descriptor(schema_name)
    if desc is None:
        return f"schema {schema_name} is not one mocaprig writes"
    field = None
    for seg in fields:
        m = _SEGMENT.match(seg)
        if desc is None or m is None or m.group(1) not in desc.fields_by_name:
            return f"{schema_name} has no field path {'.'.join(fields)!r}"
        field = desc.fields_by_name[m.group(1)]
        repeated = bool(field.is_repeated)
        if repeated != (m.group(2) is not None):
            return f"{'.'.join(fields)!r}: {field.name} needs [index] exactly when repeated"
        desc = field.message_type
    if numeric and (field is None or field.type not in _NUMERIC_TYPES):
        return f"{schema_name} {'.'.join(fields)!r} is not a numeric field"
    return None


def _ref_problem(ref: _Ref, schemas: Mapping[str, str]) -> str | None:
    split = _split_path(ref.path, list(schemas))
    if split is None:
        return f"{ref.path!r} is not a topic of the file"
    topic, fields = split
    schema = schemas[topic]
    want = {
        "image": _IMAGE_SCHEMAS,
        "calibration": {"foxglove.CameraCalibration"},
        "scene": {_SCENE_SCHEMA},
        "log": {"foxglove.Log"},
    }.get(ref.role)
    if want is not None and (schema not in want or fields):
        return f"{ref.path!r} is {schema}; the panel draws {sorted(want)}"
    if ref.role in ("plot", "raw") and (fields or ref.role == "plot"):
        return _field_problem(schema, fields, numeric=ref.role == "plot")
    return None


def layout_problems(
    layout: Mapping[str, Any],
    schemas: Mapping[str, str],
    *,
    frames: Mapping[str, str] | None = None,
) -> list[str]:
    """What keeps ``layout`` from opening its panels on a file with channels ``schemas``
    (topic -> schema name) and ``frames`` (topic -> ``frame_id``); empty when nothing does.

    Checked: the keys of a Foxglove layout, that the mosaic's panels and ``configById`` are the
    same set, and per panel that every topic it names exists with a schema it draws (Image:
    raw/compressed image and camera calibration; 3D: scene updates in the frame it follows;
    Log: ``foxglove.Log``), and every Plot path is a numeric field of its topic's schema.
    """
    problems = [f"missing key {k!r}" for k in _LAYOUT_KEYS if k not in layout]
    if problems:
        return problems
    configs: Mapping[str, Any] = layout["configById"]
    leaves = list(_leaves(layout["layout"]))
    if sorted(leaves) != sorted(configs):
        problems.append(f"mosaic panels {sorted(leaves)} differ from configById {sorted(configs)}")
    for pid in leaves:
        cfg = configs.get(pid, {})
        if _panel_type(pid) not in ("Image", "3D", "Plot", "RawMessages", "RosOut"):
            problems.append(f"{pid}: panel type not checked by mocaprig")
            continue
        refs = _refs(pid, cfg)
        if not refs:
            problems.append(f"{pid}: names no topic")
        for ref in refs:
            what = _ref_problem(ref, schemas)
            if what is not None:
                problems.append(f"{pid}: {what}")
        if _panel_type(pid) == "3D" and frames is not None:
            drawn_in = {frames[r.path] for r in refs if r.path in frames}
            if drawn_in and cfg.get("followTf") not in drawn_in:
                problems.append(f"{pid}: follows {cfg.get('followTf')!r}, drawn in {drawn_in}")
    return problems


# --------------------------------------------------------------------------------- writing


def default_layout_path(recording: Path) -> Path:
    """``<name>.layout.json`` next to the file (``session.mcap`` -> ``session.layout.json``)."""
    return recording.with_name(f"{recording.stem}.layout.json")


def write_layout(
    recording: str | Path,
    out: str | Path | None = None,
    *,
    overwrite: bool = False,
    use: LayoutUse | None = None,
) -> WrittenLayout:
    """Write the layout for ``recording`` (chosen by :func:`choose_use` unless ``use`` is
    given, filled in by :func:`layout_for`) to ``out`` (default :func:`default_layout_path`).

    Raises:
        RecordingError: ``out`` exists and ``overwrite`` is False, the file cannot be read, or
            the layout could not be written.
        ValidationError: no layout fits the file.
    """
    from mocaprig.acquire.recording import Recording

    src = Path(recording)
    dst = default_layout_path(src) if out is None else Path(out)
    if dst.exists() and not overwrite:
        msg = f"{dst} exists; pass --overwrite to replace it"
        raise RecordingError(msg)
    with Recording(src) as rec:
        channels = rec.channels
        attachments = [a.name for a in rec.attachments()]
    schemas = {t: c.schema_name for t, c in channels.items()}
    frames = {t: c.metadata["frame_id"] for t, c in channels.items() if "frame_id" in c.metadata}
    chosen = use or choose_use(schemas, attachments)
    layout = layout_for(schemas, use=chosen, frames=frames)
    problems = layout_problems(layout, schemas, frames=frames)
    if problems:
        msg = f"{src}: the {chosen} layout does not fit the file: {'; '.join(problems)}"
        raise ValidationError(msg)
    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.part")
    try:
        tmp.write_text(json.dumps(layout, indent=2) + "\n", encoding="utf-8")
        tmp.replace(dst)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        msg = f"{dst}: writing the layout failed ({err}); check the folder"
        raise RecordingError(msg) from err
    _log.debug("wrote %s layout %s (%d panels)", chosen, dst, len(layout["configById"]))
    return WrittenLayout(dst, chosen, len(layout["configById"]))
