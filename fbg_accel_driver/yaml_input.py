"""The one YAML loader of the project for files people write (calibration file, pose and excitation plans,
simulator config, ``--set`` values, rosbag2 metadata). Pure Python (PyYAML), no ROS.

:class:`StrictSafeLoader` is ``yaml.SafeLoader`` (no arbitrary objects) that also

* refuses a key given twice in one mapping, at any level (PyYAML keeps the last one silently: a block pasted at
  the top of a file would replace the one further down), naming the key and both lines;
* refuses aliases (``*name``): a few aliased lines can expand into billions of elements or a structure that
  refers to itself (memory exhaustion in the readers); none of these files needs them;
* reads a number in scientific notation without a dot or exponent sign (``2e-3``, ``3e1``, ``1.0e3``) as a float,
  as YAML 1.2 does, not as the string YAML 1.1 makes of it. Quoted text stays text.
"""

from __future__ import annotations

import re
from typing import Any

import yaml

FLOAT_TAG = "tag:yaml.org,2002:float"
MERGE_TAG = "tag:yaml.org,2002:merge"
# the YAML 1.2 core-schema floats with an exponent that the YAML 1.1 float pattern of PyYAML misses
_EXPONENT_FLOAT = re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$")


class StrictSafeLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` refusing duplicate keys and aliases, with YAML 1.2 floats (module docstring)."""

    document_kind = "this file"  # named in the alias message

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            raise yaml.composer.ComposerError(
                None, None, f"aliases (*name) are not allowed in {self.document_kind}", self.peek_event().start_mark)
        return super().compose_node(parent, index)

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


StrictSafeLoader.add_implicit_resolver(FLOAT_TAG, _EXPONENT_FLOAT, list("-+0123456789."))


def load_yaml(text: str, loader: type[StrictSafeLoader] = StrictSafeLoader) -> Any:
    """The document in ``text`` read with ``loader`` (:class:`StrictSafeLoader`); ``yaml.YAMLError`` when refused."""
    return yaml.load(text, Loader=loader)  # a SafeLoader subclass: no arbitrary objects
