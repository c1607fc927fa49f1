"""A recording copy with its calibration attached (``mocaprig calibrate vicon --attach-to``).

MCAP files are append-only once finished, so :func:`attach_calibration` rewrites the recording
with the calibration as the :data:`ATTACHMENT_NAME` attachment.
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path
from typing import Final

from mocaprig.calib.calibration import Calibration, calibration_bytes
from mocaprig.errors import CalibrationError

__all__ = ["ATTACHMENT_NAME", "attach_calibration"]

#: Name of the calibration attachment written into a recording copy.
ATTACHMENT_NAME: Final = "calibration.toml"


def attach_calibration(
    source: str | Path, output: str | Path, cal: Calibration, *, overwrite: bool = False
) -> Path:
    """Write a copy of a recording with the calibration attached as :data:`ATTACHMENT_NAME`.

    MCAP files are append-only once finished, so the recording is rewritten: every schema,
    channel, message (chunked, lz4), metadata record and attachment is copied, an older
    ``calibration.toml`` attachment is replaced, and the new one added.

    Raises:
        CalibrationError: ``output`` exists and ``overwrite`` is False, ``output`` is the
            source, or the source cannot be read.
    """
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    src, dst = Path(source), Path(output)
    if dst.exists() and dst.resolve() == src.resolve():
        msg = f"{dst}: --attach-to must name a new file, not the recording itself"
        raise CalibrationError(msg)
    if dst.exists() and not overwrite:
        msg = f"{dst} exists; pass --overwrite to replace it"
        raise CalibrationError(msg)
    part = dst.with_name(dst.name + ".part")
    try:
        with src.open("rb") as fin, part.open("wb") as fout:
            reader = make_reader(fin)
            summary = reader.get_summary()
            header = reader.get_header()
            w = Writer(fout, compression=CompressionType.LZ4)
            w.start(profile=header.profile, library=header.library)
            schema_ids: dict[int, int] = {}
            channel_ids: dict[int, int] = {}
            if summary is not None:
                for sid, sch in summary.schemas.items():
                    schema_ids[sid] = w.register_schema(sch.name, sch.encoding, sch.data)
                for ch_id, ch in summary.channels.items():
                    channel_ids[ch_id] = w.register_channel(
                        ch.topic,
                        ch.message_encoding,
                        schema_ids.get(ch.schema_id, 0),
                        dict(ch.metadata),
                    )
            for meta in reader.iter_metadata():
                w.add_metadata(meta.name, dict(meta.metadata))
            for att in reader.iter_attachments():
                if att.name == ATTACHMENT_NAME:
                    continue
                w.add_attachment(
                    create_time=att.create_time,
                    log_time=att.log_time,
                    name=att.name,
                    media_type=att.media_type,
                    data=att.data,
                )
            now = _dt.datetime.now(_dt.UTC)
            t_ns = int(now.timestamp() * 1e9)
            w.add_attachment(
                create_time=t_ns,
                log_time=t_ns,
                name=ATTACHMENT_NAME,
                media_type="application/toml",
                data=calibration_bytes(cal),
            )
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                cid = channel_ids.get(channel.id)
                if cid is None:
                    sid = 0
                    if schema is not None:
                        if schema.id not in schema_ids:
                            schema_ids[schema.id] = w.register_schema(
                                schema.name, schema.encoding, schema.data
                            )
                        sid = schema_ids[schema.id]
                    cid = w.register_channel(
                        channel.topic, channel.message_encoding, sid, dict(channel.metadata)
                    )
                    channel_ids[channel.id] = cid
                w.add_message(
                    channel_id=cid,
                    log_time=message.log_time,
                    publish_time=message.publish_time,
                    data=message.data,
                    sequence=message.sequence,
                )
            w.finish()  # type: ignore[no-untyped-call]
    except Exception as err:
        part.unlink(missing_ok=True)
        if isinstance(err, CalibrationError):
            raise
        msg = f"cannot attach the calibration: copying {src} to {dst} failed: {err}"
        raise CalibrationError(msg) from err
    part.replace(dst)
    return dst
