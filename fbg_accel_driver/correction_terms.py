"""Declared extra model terms added by ``fbg-accel-calib diagnose`` (registry; pure numpy).

Each term is a class with a ``kind`` string, ``to_dict``/``from_dict`` for the calibration
YAML, ``new_state()`` for streaming state (or ``None``), and
``contribution(cal, inputs, state) -> (N, 3)`` additive m/s^2 on top of eq. 28, where
``inputs`` has ``ref`` (N,), ``xyz`` (N, 3) counts, ``psi`` (N, 3), ``temp_c`` (N,), ``t_s`` (N,).
"""

from __future__ import annotations

from typing import Any

CORRECTION_TYPES: dict[str, type] = {}


def correction_from_dict(d: Any) -> Any:
    """Build a correction term from its YAML mapping; unknown kinds are refused."""
    if not isinstance(d, dict) or "kind" not in d:
        raise ValueError("a correction term must be a mapping with a 'kind'")
    kind = d["kind"]
    if kind not in CORRECTION_TYPES:
        raise ValueError(f"unknown correction kind '{kind}' (known: {sorted(CORRECTION_TYPES)})")
    return CORRECTION_TYPES[kind].from_dict(d)
