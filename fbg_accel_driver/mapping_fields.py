"""Checks of the fields of a parsed YAML mapping, shared by the file readers (issue 12). Pure Python, no ROS.

``fail(message)`` builds the caller's own exception (usually with the file name in front), so a bad number
reads the same in a calibration file, a pose plan or an excitation plan. Unknown keys: the calibration file
and the excitation plan use :func:`refuse_unknown`; the pose plan keeps its own check, which lists every
unknown key at once."""

from __future__ import annotations

import difflib
import math
import numbers
from collections.abc import Callable, Collection, Mapping
from typing import Any

Fail = Callable[[str], Exception]


def number(value: Any, where: str, fail: Fail, *, minimum: float | None = None, positive: bool = False,
           finite: bool = True, text: bool = False) -> float:
    """``value`` as a float, else ``fail("<where> must be ...")`` raised; a bool is not a number.

    ``positive``: must be > 0; ``minimum``: must be >= it; ``finite=False`` lets NaN and infinity through
    (for a caller whose own check names them better); ``text=True`` reads numeric text such as ``'1e-3'``
    (PyYAML, YAML 1.1, loads a hand-written 1e-3 as a string)."""
    try:
        if isinstance(value, bool) or not isinstance(value, (numbers.Real, str) if text else numbers.Real):
            raise ValueError  # the same message as text that is not a number
        v = float(value)
    except OverflowError:
        raise fail(f"{where} is too large for a float") from None
    except ValueError:
        raise fail(f"{where} must be a number, got {type(value).__name__} {value!r:.40}") from None
    bound = " > 0" if positive else "" if minimum is None else f" >= {minimum:g}"
    if finite and not math.isfinite(v):
        raise fail(f"{where} must be {'a finite number' + bound if bound else 'finite'}, got {value!r}")
    if positive and not v > 0:
        raise fail(f"{where} must be > 0, got {value!r}")
    if minimum is not None and not v >= minimum:
        raise fail(f"{where} must be >= {minimum:g}, got {value!r}")
    return v


def refuse_unknown(d: Mapping[Any, Any], allowed: Collection[str], where: str, fail: Fail) -> None:
    """``fail("unknown key '<where><key>' (did you mean '<where><nearest>'?)")`` raised for the first key of ``d``
    not in ``allowed`` (the known names listed when none is near); ``where`` is the mapping's dotted prefix."""
    for key in d:
        if key not in allowed:
            near = difflib.get_close_matches(str(key), list(allowed), n=1)
            hint = f" (did you mean '{where}{near[0]}'?)" if near else f" (known: {', '.join(allowed)})"
            raise fail(f"unknown key '{where}{key}'{hint}")
