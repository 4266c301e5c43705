"""Checks of the fields of a parsed YAML mapping, shared by the file readers. Pure Python, no ROS.

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

import numpy as np

MAX_ARRAY_ENTRIES = 1 << 16  # entries (lists and numbers) a numeric array of a file may have

Fail = Callable[[str], Exception]


def number(value: Any, where: str, fail: Fail, *, minimum: float | None = None, positive: bool = False,
           finite: bool = True) -> float:
    """``value`` as a float, else ``fail("<where> must be ...")`` raised; a bool or a string is not a number.

    ``positive``: must be > 0; ``minimum``: must be >= it; ``finite=False`` lets NaN and infinity through
    (for a caller whose own check names them better). A hand-written ``1e-3`` is a float already: the project's
    YAML loader (``fbg_accel_driver.yaml_input``) resolves floats as YAML 1.2 does."""
    try:
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
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


def number_array(value: Any, where: str, fail: Fail, *, finite: bool = True) -> np.ndarray:
    """``value`` (nested lists of numbers) as a float array; every entry read by the rules of :func:`number`
    (a bool or a string is not a number), so ``fail("<where>[i][j] must be a number, got ...")`` names the entry.
    A ragged nesting gives ``fail("<where> is not a numeric array (<numpy message>)")``; the shape is the caller's
    to check. A numpy array of numbers (not of bools) is taken as it is."""
    if isinstance(value, np.ndarray) and value.dtype.kind in "iuf":
        out = np.asarray(value, dtype=float)
    else:
        stack: list[tuple[str, Any]] = [(where, value)]
        seen = 0
        while stack:
            at, v = stack.pop()
            seen += 1
            if seen > MAX_ARRAY_ENTRIES:
                raise fail(f"{where} has more than {MAX_ARRAY_ENTRIES} entries")
            if isinstance(v, list | tuple):
                stack.extend((f"{at}[{i}]", x) for i, x in enumerate(v))
            else:
                number(v, at, fail, finite=finite)
        try:
            out = np.asarray(value, dtype=float)
        except (TypeError, ValueError, OverflowError) as exc:
            raise fail(f"{where} is not a numeric array ({exc})") from None
    if finite and not np.all(np.isfinite(out)):
        raise fail(f"{where} contains NaN or infinite values")
    return out


def format_version(value: Any, where: str, fail: Fail, *, reads: int, reader: str = "this driver",
                   exact: bool = True) -> int:
    """A ``format_version``: an integer, not a bool, ``1.0`` or ``"1"``, else ``fail("<where> <value!r> is not
    supported (<reader> reads <reads>)")``; ``exact``: also that message for an integer other than ``reads`` (the
    calibration file's top level passes ``exact=False``: it migrates older versions and words a newer one itself)."""
    if isinstance(value, bool) or not isinstance(value, int) or (exact and value != reads):
        raise fail(f"{where} {value!r} is not supported ({reader} reads {reads})")
    return int(value)


def same_values(a: Any, b: Any) -> bool:
    """``a == b`` for nested mappings, lists, tuples (a list equals a tuple), numbers and numpy values, with NaN equal
    to NaN: what a file's ``save`` then ``load`` gives back equals what was saved (``__eq__`` of the file objects)."""
    if isinstance(a, np.ndarray | np.generic):
        a = a.tolist()
    if isinstance(b, np.ndarray | np.generic):
        b = b.tolist()
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        return a.keys() == b.keys() and all(same_values(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(same_values(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return bool(a == b)
