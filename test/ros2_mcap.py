"""An MCAP file's messages read by the mcap library's stream reader and decoded by the ROS 2 decoder: a reader
independent of the project's, for the tests that check what a writer put on disk."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def ros2_messages(path: Path, complete: bool = True) -> list[tuple[str, int, str, Any]]:
    """(topic, log time ns, schema name, decoded message) of every message, in file order. ``complete``: the file
    must have its summary (a writer that closed it); otherwise it is read record by record up to where it is cut
    (the chunk a SIGKILLed writer was filling)."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader
    from mcap_ros2.decoder import DecoderFactory

    schemas, channels, out, factory = {}, {}, [], DecoderFactory()
    with open(path, "rb") as fh:
        if complete:
            assert make_reader(fh).get_summary() is not None, f"no summary: {path} was not closed"
            fh.seek(0)
        try:
            for rec in StreamReader(fh).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    ch = channels[rec.channel_id]
                    schema = schemas[ch.schema_id]
                    out.append((ch.topic, rec.log_time, schema.name,
                                factory.decoder_for(ch.message_encoding, schema)(rec.data)))
        except McapError:
            if complete:
                raise
    return out


def frames_by_topic(path: Path) -> dict[str, set[str]]:
    """The header frame_id of every message with a header, per topic, of a closed file."""
    frames: dict[str, set[str]] = {}
    for topic, _, _, msg in ros2_messages(path):
        if hasattr(msg, "header"):
            frames.setdefault(topic, set()).add(msg.header.frame_id)
    return frames
