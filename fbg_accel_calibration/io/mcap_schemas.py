"""The ros2msg schemas of a calibration recording (``mcap_format``): the full definitions written, as rosbag2 writes
them into MCAP (:func:`message_definition`), and, on reading, the decoder of each channel with a one-line error when
its schema is not the type or lacks a field the reader uses (another definition under that name)."""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path
from typing import Any

from mcap.records import Channel, Schema
from mcap_ros2.decoder import DecoderFactory

from fbg_accel_driver.command_line import first_line

from .mcap_format import TOPIC_POSE, TOPIC_RAW, TOPIC_REFERENCE_GRAVITY, TOPIC_TEMPERATURE, TYPE_RAW, McapRecordingError

_PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
               "uint32", "int64", "uint64", "string", "wstring"}
_SEPARATOR = "=" * 80
_CONSTANT = re.compile(r"^\S+\s+[A-Z][A-Z0-9_]*\s*=")


# ---------------------------------------------------------------------------- message definitions
def _find_msg_file(package: str, name: str) -> Path:
    tried = []
    prefixes = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    for prefix in [*prefixes, Path(sys.prefix)]:
        candidate = prefix / "share" / package / "msg" / f"{name}.msg"
        tried.append(str(candidate))
        if candidate.is_file():
            return candidate
    raise McapRecordingError(f"message definition {package}/msg/{name} not found; looked in: {', '.join(tried)}")


def _dependencies(package: str, text: str) -> list[tuple[str, str]]:
    """Non-primitive field types (package, name) referenced by a .msg text, in order of appearance."""
    deps: list[tuple[str, str]] = []
    for raw_line in text.splitlines():
        line = raw_line.split("#", 1)[0].strip()
        if not line or _CONSTANT.match(line):  # a constant definition: "type NAME=value"
            continue
        field_type = line.split()[0]
        base = re.sub(r"\[.*?\]$", "", field_type)
        base = re.sub(r"<=\d+$", "", base)
        if base in _PRIMITIVES:
            continue
        parts = base.split("/")
        dep = (package, parts[0]) if len(parts) == 1 else (parts[0], parts[-1])
        if dep not in deps:
            deps.append(dep)
    return deps


def message_definition(datatype: str) -> str:
    """Full ros2msg schema text of ``datatype`` (``pkg/msg/Name``): its .msg text followed by every
    dependency as ``====...`` / ``MSG: pkg/Name`` / text, the format rosbag2 writes into MCAP."""
    package, _, name = datatype.split("/")
    main_text = _find_msg_file(package, name).read_text(encoding="utf-8")
    out = [main_text.rstrip("\n")]
    seen = {(package, name)}
    queue = _dependencies(package, main_text)
    while queue:
        dep = queue.pop(0)
        if dep in seen:
            continue
        seen.add(dep)
        text = _find_msg_file(*dep).read_text(encoding="utf-8")
        out.append(f"{_SEPARATOR}\nMSG: {dep[0]}/{dep[1]}\n{text.rstrip(chr(10))}")
        queue.extend(d for d in _dependencies(dep[0], text) if d not in seen)
    return "\n".join(out) + "\n"


def _decoder_for(path: Path | str, factory: DecoderFactory, channel: Channel, schemas: dict[int, Schema],
                 is_raw: bool) -> Any:
    """The ``mcap_ros2`` decoder of a channel, or one line saying why there is none: the raw topic of another
    type, a schema that does not parse (instead of an AttributeError or InvalidResourceName traceback)."""
    schema = schemas.get(channel.schema_id)
    if is_raw and (schema is None or schema.name != TYPE_RAW):
        found = schema.name if schema is not None else "no schema"
        raise McapRecordingError(f"{path}: topic '{channel.topic}' has type '{found}', expected '{TYPE_RAW}'")
    try:
        decoder = factory.decoder_for(channel.message_encoding, schema)
    except Exception as exc:  # the ROS 2 msg parser raises many types on a malformed definition
        name = schema.name if schema is not None else "?"
        raise McapRecordingError(f"{path}: schema '{name}' of topic '{channel.topic}' cannot be parsed "
                                 f"({type(exc).__name__}: {first_line(exc)[:200]})") from None
    if decoder is None:
        raise McapRecordingError(f"{path}: no ROS 2 decoder for topic {channel.topic} "
                                 f"(encoding '{channel.message_encoding}')")
    return decoder


_HEADER = ("std_msgs/Header", "stamp"), ("std_msgs/Header", "frame_id")
_ROLE_FIELDS = {  # (type, field) that the reader uses of each role; "" = the channel's own type
    TOPIC_RAW: (("", "header"), ("", "name"), ("", "position"), *_HEADER),
    TOPIC_TEMPERATURE: (("", "header"), ("", "temperature"), *_HEADER),
    TOPIC_REFERENCE_GRAVITY: (("", "header"), ("", "vector"), *_HEADER, *(("geometry_msgs/Vector3", c) for c in "xyz")),
    TOPIC_POSE: (("", "message"), ("", "values"), ("diagnostic_msgs/KeyValue", "key"),
                 ("diagnostic_msgs/KeyValue", "value")),
}


def _short_type(name: str) -> str:
    """``pkg/msg/Name`` -> ``pkg/Name`` (the spelling of a schema's ``MSG:`` lines)."""
    parts = name.strip().split("/")
    return f"{parts[0]}/{parts[-1]}" if len(parts) > 1 else name.strip()


def _schema_fields(name: str, text: str) -> dict[str, set[str]]:
    """Field names of each type in a ros2msg schema text (:func:`_schema_layout`'s fields, their names alone)."""
    return {kind: {field for _, field in fields} for kind, fields in _schema_layout(name, text).items()}


def _schema_layout(name: str, text: str) -> dict[str, list[tuple[str, str]]]:
    """The fields ``(type, name)`` in order of each type in a ros2msg schema text (its own type under ``name``, then
    every ``MSG:`` section), constants left out; a type without a package is of its section's package."""
    out: dict[str, list[tuple[str, str]]] = {}
    current = _short_type(name)
    for section in re.split(r"^={3,}\s*$", text, flags=re.MULTILINE):
        lines = section.strip().splitlines()
        if lines and lines[0].startswith("MSG:"):
            current = _short_type(lines[0][4:])
            lines = lines[1:]
        fields = out.setdefault(current, [])
        for raw_line in lines:
            line = raw_line.split("#", 1)[0].strip()
            parts = line.split()
            if len(parts) >= 2 and not _CONSTANT.match(line):
                kind = parts[0]
                if "/" not in kind and re.sub(r"\[.*$", "", kind) not in _PRIMITIVES:
                    kind = f"{current.split('/')[0]}/{kind}"
                fields.append((kind, parts[1]))
    return out


_STAMPED = {"std_msgs/Header": [("builtin_interfaces/Time", "stamp"), ("string", "frame_id")],
            "builtin_interfaces/Time": [("int32", "sec"), ("uint32", "nanosec")]}
_EVENT_LAYOUTS = {  # the standard definitions of the event types: their messages are read by ros2_cdr's layouts
    TOPIC_TEMPERATURE: {"sensor_msgs/Temperature": [("std_msgs/Header", "header"), ("float64", "temperature"),
                                                    ("float64", "variance")], **_STAMPED},
    TOPIC_REFERENCE_GRAVITY: {"geometry_msgs/Vector3Stamped": [("std_msgs/Header", "header"),
                                                               ("geometry_msgs/Vector3", "vector")],
                              "geometry_msgs/Vector3": [("float64", "x"), ("float64", "y"), ("float64", "z")],
                              **_STAMPED},
    TOPIC_POSE: {"diagnostic_msgs/DiagnosticStatus": [("byte", "level"), ("string", "name"), ("string", "message"),
                                                      ("string", "hardware_id"),
                                                      ("diagnostic_msgs/KeyValue[]", "values")],
                 "diagnostic_msgs/KeyValue": [("string", "key"), ("string", "value")]},
}


def standard_event_schema(schema: Schema | None, role: str) -> bool:
    """Whether an event topic's schema is the standard definition of its type, field for field (comments, constants
    and the order of its sections aside): then every message in the layout ``ros2_cdr`` writes decodes as
    ``ros2_cdr`` reads it."""
    want = _EVENT_LAYOUTS.get(role)
    if schema is None or want is None:
        return False
    return _schema_layout(schema.name, schema.data.decode("utf-8", "replace")) == want


def _check_fields(path: Path | str, channel: Channel, schema: Schema | None, role: str) -> None:
    """One line when a role's schema has the type name this reader expects but not the fields it reads (another
    definition under that name, e.g. a renamed field): the messages would decode into objects without them."""
    if schema is None:
        return
    fields = _schema_fields(schema.name, schema.data.decode("utf-8", "replace"))
    own = _short_type(schema.name)
    for type_name, name in _ROLE_FIELDS[role]:
        have = fields.get(type_name or own)
        if have is not None and name not in have:
            where = name if not type_name else f"{type_name}.{name}"
            raise McapRecordingError(f"{path}: topic {channel.topic}'s schema {schema.name} lacks field {where} "
                                     "(a different definition)")


def _decode(path: Path | str, decoder: Any, channel: Channel, data: bytes) -> Any:
    """One message decoded, or one line naming the topic when its bytes do not match its schema."""
    try:
        return decoder(data)
    except Exception as exc:
        raise McapRecordingError(f"{path}: a '{channel.topic}' message does not decode with its schema "
                                 f"({type(exc).__name__}: {first_line(exc)[:200]})") from None
