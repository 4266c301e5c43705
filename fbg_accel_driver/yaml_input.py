"""The one YAML loader of the project for files people write (calibration file, pose and excitation plans,
simulator config, ``--set`` values, rosbag2 metadata). Pure Python (PyYAML), no ROS.

:class:`StrictSafeLoader` is ``yaml.SafeLoader`` (no arbitrary objects) that also

* refuses a key given twice in one mapping, at any level (PyYAML keeps the last one silently: a block pasted at
  the top of a file would replace the one further down), naming the key and both lines;
* refuses aliases (``*name``): a few aliased lines can expand into billions of elements or a structure that
  refers to itself (memory exhaustion in the readers); none of these files needs them;
* reads a number in scientific notation without a dot or exponent sign (``2e-3``, ``3e1``, ``1.0e3``) as a float,
  as YAML 1.2 does, not as the string YAML 1.1 makes of it. Quoted text stays text;
* reads as numbers only decimal ones: YAML 1.1's sexagesimal (``1:22`` is 82), octal (``012`` is 10), hex (``0x52``)
  and binary forms stay text, so a typo or a time of day never becomes a silently different number (the readers
  then refuse the text where a number belongs);
* reads dates as text (no ``datetime``: none of these files needs one, and ``2026-13-45`` made PyYAML fail with a
  bare ``ValueError``);
* refuses a document nested deeper than :data:`MAX_DEPTH` levels (3000 levels overflowed Python's stack).

:func:`read_yaml_file` is the one way a file is read, with one error contract: :class:`YamlFileError` (a
``ValueError``), one line that starts with the path -- a missing file, a directory, a FIFO or device, a file too
large, one that is not UTF-8 text, and every refusal of the parser.
"""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path
from typing import Any

import yaml

from .command_line import one_line

FLOAT_TAG = "tag:yaml.org,2002:float"
MERGE_TAG = "tag:yaml.org,2002:merge"
# the YAML 1.2 core-schema floats with an exponent that the YAML 1.1 float pattern of PyYAML misses
_EXPONENT_FLOAT = re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$")
INT_TAG = "tag:yaml.org,2002:int"
TIMESTAMP_TAG = "tag:yaml.org,2002:timestamp"
# YAML 1.1 numbers without the sexagesimal forms (1:22, 1:22.5), octal (012), hex (0x52) and binary (0b1)
_DECIMAL_INT = re.compile(r"^[-+]?(?:0|[1-9][0-9_]*)$")
_DECIMAL_FLOAT = re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+][0-9]+)?
                    |\.[0-9][0-9_]*(?:[eE][-+][0-9]+)?
                    |[-+]?\.(?:inf|Inf|INF)
                    |\.(?:nan|NaN|NAN))$""", re.X)
MAX_DEPTH = 64  # nesting levels of a document; the project's files use fewer than 8
MAX_FILE_BYTES = 1 << 20  # default bound of read_yaml_file (the calibration file has its own)


class YamlFileError(ValueError):
    """A YAML file (or text) that cannot be read; the message is one line and starts with the file's path."""


class StrictSafeLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` refusing duplicate keys and aliases, with YAML 1.2 floats (module docstring)."""

    document_kind = "this file"  # named in the alias message
    _depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            raise yaml.composer.ComposerError(
                None, None, f"aliases (*name) are not allowed in {self.document_kind}", self.peek_event().start_mark)
        if self._depth >= MAX_DEPTH:
            raise yaml.composer.ComposerError(
                None, None, f"nested more than {MAX_DEPTH} levels deep", self.peek_event().start_mark)
        self._depth += 1
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        if isinstance(node, yaml.MappingNode):
            first: dict[Any, Any] = {}
            for key_node, _ in node.value:
                if key_node.tag == MERGE_TAG:
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    earlier = first.setdefault(key, key_node)
                except TypeError:
                    continue  # unhashable: SafeConstructor refuses it with its own message
                if earlier is not key_node:
                    raise yaml.constructor.ConstructorError(
                        "while constructing a mapping", node.start_mark,
                        f"found duplicate key {key!r} (first given on line {earlier.start_mark.line + 1}); "
                        "a key may appear once in a mapping", key_node.start_mark)
        return super().construct_mapping(node, deep=deep)


StrictSafeLoader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag not in (INT_TAG, FLOAT_TAG, TIMESTAMP_TAG)]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}
for _tag, _regexp, _first in ((INT_TAG, _DECIMAL_INT, "-+0123456789"), (FLOAT_TAG, _DECIMAL_FLOAT, "-+0123456789."),
                              (FLOAT_TAG, _EXPONENT_FLOAT, "-+0123456789.")):
    StrictSafeLoader.add_implicit_resolver(_tag, _regexp, list(_first))


def load_yaml(text: str, loader: type[StrictSafeLoader] = StrictSafeLoader, source: str | None = None) -> Any:
    """The document in ``text`` read with ``loader`` (:class:`StrictSafeLoader`).

    Without ``source``: ``yaml.YAMLError`` when refused (also for a value its constructor refuses, e.g.
    ``!!int x``). With ``source`` (a path or e.g. ``"--set key"``): :class:`YamlFileError`, one line starting
    with ``source``."""
    try:
        return yaml.load(text, Loader=loader)  # a SafeLoader subclass: no arbitrary objects
    except yaml.YAMLError as exc:
        if source is None:
            raise
        raise YamlFileError(f"{source}: not valid YAML ({one_line(str(exc))})") from None
    except (ValueError, TypeError, OverflowError, RecursionError) as exc:  # a constructor's refusal, e.g. !!int x
        what = "nested too deeply" if isinstance(exc, RecursionError) else one_line(str(exc)) or type(exc).__name__
        if source is None:
            raise yaml.YAMLError(what) from None
        raise YamlFileError(f"{source}: not valid YAML ({what})") from None


def file_kind(path: Path | str) -> str | None:
    """What is at ``path`` when it is not a regular file -- "not found", "a directory", "a FIFO (named pipe)",
    "a character device", "a block device", "a socket" -- or None for a regular file (links followed). Lets a
    reader say what it was given instead of "not found", and never block on a FIFO or read ``/dev/zero``."""
    try:
        mode = os.stat(path).st_mode
    except ValueError:  # a NUL character in the name
        return "not a valid path (it holds a NUL character)"
    except FileNotFoundError:
        return "not found" if not os.path.islink(path) else "a dangling symbolic link"
    except OSError as exc:
        return f"not readable ({exc.strerror or exc})"
    for test, name in ((stat.S_ISREG, None), (stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def read_yaml_file(path: Path | str, what: str = "YAML file", max_bytes: int = MAX_FILE_BYTES,
                   loader: type[StrictSafeLoader] = StrictSafeLoader) -> Any:
    """The document of the YAML file at ``path`` (``what`` names it in messages, e.g. "pose plan").

    Raises :class:`YamlFileError`, one line starting with the path, when it is not a regular file
    (:func:`file_kind`), is larger than ``max_bytes``, cannot be read, is not UTF-8, or is not valid YAML
    for ``loader``."""
    p = Path(path)
    kind = file_kind(p)
    if kind == "not found":
        raise YamlFileError(f"{p}: {what} not found")
    if kind is not None:
        raise YamlFileError(f"{p}: {kind}, not a {what}")
    try:
        with open(p, "rb") as fh:
            raw = fh.read(max_bytes + 1)
    except OSError as exc:
        raise YamlFileError(f"{p}: {what} cannot be read ({exc.strerror or exc})") from None
    if len(raw) > max_bytes:
        raise YamlFileError(f"{p}: larger than {max_bytes} bytes, not a {what}")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise YamlFileError(f"{p}: not UTF-8 text, not a {what} (byte {exc.start})") from None
    return load_yaml(text, loader, source=str(p))
