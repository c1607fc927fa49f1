"""Device identity in the recording format: one type builds and parses every name.

A :class:`DeviceId` is a device kind and serial. Every topic (``/d415/<serial>/ir``), device
label (``d415/<serial>``), metadata record name (``device/d415/<serial>``) and ``frame_id``
(``d415_<serial>``) of the format (``docs/recording-format.md``) is made by it, and topics are
parsed back only by :meth:`DeviceId.from_topic`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final, Literal, get_args

from mocaprig.errors import ValidationError

__all__ = ["DeviceId", "DeviceKind"]

DeviceKind = Literal["d415", "davis", "syncbox"]
_KINDS: Final = frozenset(get_args(DeviceKind))


@dataclass(frozen=True, slots=True, order=True)
class DeviceId:
    """One device of a rig: its kind and serial (the sync box has none: one box per rig).

    The format's names all come from here: :attr:`label` ``d415/<serial>``, :meth:`topic`
    ``/d415/<serial>/<stream>`` (``/syncbox/<stream>``), :attr:`metadata_name`
    ``device/d415/<serial>`` and :attr:`settings_name` ``settings/davis/<serial>``.
    """

    kind: DeviceKind
    serial: str = ""

    def __post_init__(self) -> None:
        if self.kind not in _KINDS:
            msg = f"device kind {self.kind!r} is not one of {sorted(_KINDS)}"
            raise ValidationError(msg)
        if self.kind == "syncbox":
            if self.serial:
                msg = f"the sync box has no serial in the format, got {self.serial!r}"
                raise ValidationError(msg)
        elif not self.serial or "/" in self.serial:
            msg = f"{self.kind} serial {self.serial!r} must be non-empty and contain no '/'"
            raise ValidationError(msg)

    @property
    def label(self) -> str:
        """``d415/<serial>``, ``davis/<serial>`` or ``syncbox``."""
        return self.kind if self.kind == "syncbox" else f"{self.kind}/{self.serial}"

    def topic(self, stream: str) -> str:
        """The MCAP topic of one of this device's streams."""
        if not stream or "/" in stream:
            msg = f"stream name {stream!r} must be non-empty and contain no '/'"
            raise ValidationError(msg)
        return f"/{self.label}/{stream}"

    @property
    def metadata_name(self) -> str:
        """Name of the MCAP metadata record that describes the device (``device/<label>``)."""
        return f"device/{self.label}"

    @property
    def settings_name(self) -> str:
        """Name of the MCAP metadata record of its register settings (``settings/<label>``)."""
        return f"settings/{self.label}"

    @property
    def frame_id(self) -> str:
        """The ``frame_id`` its image and calibration messages carry (``d415_<serial>``)."""
        return self.label.replace("/", "_")

    def __str__(self) -> str:
        return self.label

    @classmethod
    def parse(cls, text: str, *, kind: DeviceKind | None = None) -> DeviceId:
        """A device from its label (``d415/123``) or, with ``kind``, a bare serial (``123``).

        Raises:
            ValidationError: neither a label nor (with ``kind``) a serial.
        """
        s = str(text).strip()
        if s == "syncbox":
            return cls("syncbox")
        head, sep, tail = s.partition("/")
        if sep and head in _KINDS and tail and "/" not in tail:
            if kind is not None and head != kind:
                msg = f"{text!r} is a {head}, not a {kind}"
                raise ValidationError(msg)
            return cls(head, tail)  # type: ignore[arg-type]
        if kind is not None and not sep:
            return cls(kind, s)
        want = f"'{kind}/<serial>' or a bare serial" if kind else "'<kind>/<serial>'"
        msg = f"{text!r} is not a device label; expected {want} (kinds: {sorted(_KINDS)})"
        raise ValidationError(msg)

    @classmethod
    def from_topic(cls, topic: str) -> tuple[DeviceId, str] | None:
        """``(device, stream)`` of a device topic, or None for another topic (``/diagnostics``)."""
        parts = topic.split("/")
        if len(parts) == 3 and parts[0] == "" and parts[1] == "syncbox" and parts[2]:
            return cls("syncbox"), parts[2]
        camera = len(parts) == 4 and parts[0] == "" and parts[1] in _KINDS - {"syncbox"}
        if camera and parts[2] and parts[3]:
            return cls(parts[1], parts[2]), parts[3]  # type: ignore[arg-type]
        return None
