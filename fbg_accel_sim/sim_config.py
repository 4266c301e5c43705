"""Configuration of the board simulator: a nested mapping loaded from YAML (pure Python, no ROS).

``config/sim_default.yaml`` holds every parameter with its source. Any other file is merged on
top of it and may only set keys that exist there, so a typo is an error instead of a silently
ignored setting. ``with_overrides`` applies dotted keys (``"effects.tia_lowpass.scale"``).
"""

from __future__ import annotations

import copy
import difflib
import os
import sys
from pathlib import Path
from typing import Any

import yaml

from fbg_accel_driver.yaml_input import YamlFileError, load_yaml, read_yaml_file

DEFAULT_FILE_NAME = "sim_default.yaml"
CONFIG_DIR_ENV = "FBG_ACCEL_CONFIG_DIR"
# Sub-trees whose content is free-form (lists of events, segments, poses): merged by replacement.
_FREE_FORM = ("scenario.poses.list", "scenario.temperature.profile", "scenario.vibration.sines",
              "scenario.slide.segments", "scenario.slide.direction")


class SimConfigError(ValueError):
    """A simulator configuration is missing, malformed or names an unknown key."""


def config_dir() -> Path:
    """The package's ``config/`` directory: source checkout, colcon/pip install share dir, or $FBG_ACCEL_CONFIG_DIR."""
    candidates: list[Path] = []
    if os.environ.get(CONFIG_DIR_ENV):
        candidates.append(Path(os.environ[CONFIG_DIR_ENV]))
    here = Path(__file__).resolve()
    candidates.append(here.parents[1] / "config")  # source checkout / editable install
    for base in (Path(sys.prefix), *here.parents):
        candidates.append(base / "share" / "fbg_accel_driver" / "config")
    for c in candidates:
        if (c / DEFAULT_FILE_NAME).is_file():
            return c
    raise SimConfigError(f"cannot find {DEFAULT_FILE_NAME}; looked in {[str(c) for c in candidates[:3]]} ... "
                         f"(set {CONFIG_DIR_ENV})")


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        data = read_yaml_file(path, "simulator config")
    except YamlFileError as exc:
        raise SimConfigError(str(exc)) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise SimConfigError(f"{path}: top level is not a mapping")
    return data


def _merge(base: dict[str, Any], over: dict[str, Any], prefix: str, source: str) -> None:
    for key, value in over.items():
        dotted = f"{prefix}{key}"
        if key not in base:
            close = difflib.get_close_matches(str(key), [str(k) for k in base], n=1)
            hint = f" (did you mean '{prefix}{close[0]}'?)" if close else ""
            raise SimConfigError(f"{source}: unknown simulator key '{dotted}'{hint}")
        free_form = any(dotted == f or dotted.startswith(f + ".") for f in _FREE_FORM)
        if isinstance(base[key], dict) and not free_form:
            if not isinstance(value, dict):
                raise SimConfigError(f"{source}: '{dotted}' must be a mapping")
            _merge(base[key], value, dotted + ".", source)
        else:
            base[key] = copy.deepcopy(value)


class SimConfig:
    """Simulator parameters (``data`` is the merged nested dict). Use ``get("a.b.c")`` to read."""

    def __init__(self, data: dict[str, Any], source: str = "<dict>") -> None:
        self.data = data
        self.source = source

    @classmethod
    def default(cls) -> SimConfig:
        """The nominal physical sensor (``config/sim_default.yaml``)."""
        path = config_dir() / DEFAULT_FILE_NAME
        return cls(_read_yaml(path), str(path))

    @classmethod
    def load(cls, path: str | Path) -> SimConfig:
        """A config file merged on top of the defaults (unknown keys are refused)."""
        p = Path(path)
        if not p.is_absolute() and not p.is_file():
            alt = config_dir() / p.name
            if alt.is_file():
                p = alt
        over = _read_yaml(p)
        cfg = cls.default()
        data = copy.deepcopy(cfg.data)
        _merge(data, over, "", str(p))
        return cls(data, str(p))

    def with_overrides(self, overrides: dict[str, Any]) -> SimConfig:
        """A copy with dotted keys replaced, e.g. ``{"effects.tia_lowpass.scale": 0.0}``."""
        data = copy.deepcopy(self.data)
        for dotted, value in overrides.items():
            nested = value
            for p in reversed(str(dotted).split(".")):
                nested = {p: nested}
            _merge(data, nested, "", f"override '{dotted}'")
        return SimConfig(data, self.source + " + overrides")

    def get(self, dotted: str) -> Any:
        cur: Any = self.data
        for p in dotted.split("."):
            if not isinstance(cur, dict) or p not in cur:
                raise SimConfigError(f"simulator config has no key '{dotted}'")
            cur = cur[p]
        return cur

    def scale(self, effect: str) -> float:
        """``effects.<effect>.scale`` as float."""
        return float(self.get(f"effects.{effect}.scale"))

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.data, sort_keys=False, default_flow_style=None, width=110)


def parse_set_argument(text: str) -> tuple[str, Any]:
    """``key=value`` of the CLI ``--set`` option; the value is parsed as YAML (numbers, lists, null)."""
    if "=" not in text:
        raise SimConfigError(f"--set expects key=value, got '{text}'")
    key, raw = text.split("=", 1)
    try:
        value = load_yaml(raw, source=f"--set {key}")
    except YamlFileError as exc:
        raise SimConfigError(str(exc)) from None
    return key.strip(), value
