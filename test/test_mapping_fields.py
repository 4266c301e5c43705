"""The one check of a YAML mapping's fields (fbg_accel_driver.mapping_fields, issue 12)."""

import math

import numpy as np
import pytest

from fbg_accel_driver.mapping_fields import number, refuse_unknown


def fail(msg: str) -> KeyError:  # any exception type the caller chooses
    return KeyError(f"f.yaml: {msg}")


def test_numbers_are_read_as_floats() -> None:
    got = [number(3, "x", fail), number(np.int64(4), "x", fail, positive=True), number(0.0, "x", fail, minimum=0.0),
           number("1e-3", "x", fail, text=True), number("inf", "x", fail, text=True, finite=False)]
    assert got == [3.0, 4.0, 0.0, 1e-3, math.inf] and all(type(v) is float for v in got)


@pytest.mark.parametrize(("value", "checks", "message"), [
    (True, {}, "x must be a number, got bool True"), (None, {}, "x must be a number, got NoneType None"),
    ("1e-3", {}, "x must be a number, got str '1e-3'"), ("warm", {"text": True}, "x must be a number, got str 'warm'"),
    (10**400, {}, "x is too large for a float"), (math.nan, {}, "x must be finite, got nan"),
    (math.inf, {"minimum": 0.0}, "x must be a finite number >= 0, got inf"), (0, {"positive": True}, "x must be > 0, got 0"),
    (-1, {"minimum": 1e-3}, "x must be >= 0.001, got -1"), (math.nan, {"finite": False, "minimum": 0}, "x must be >= 0, got nan"),
])
def test_a_bad_number_raises_the_callers_error_naming_the_field(value, checks, message) -> None:
    with pytest.raises(KeyError) as err:
        number(value, "x", fail, **checks)
    assert err.value.args[0] == f"f.yaml: {message}"


def test_an_unknown_key_names_the_nearest_known_one_or_lists_them() -> None:
    refuse_unknown({"gain": 1}, ("gain", "delay_s"), "", fail)
    with pytest.raises(KeyError, match=r"unknown key 'dynamic\.dely_s' \(did you mean 'dynamic\.delay_s'\?\)"):
        refuse_unknown({"gain": 1, "dely_s": 0}, ("gain", "delay_s"), "dynamic.", fail)
    with pytest.raises(KeyError, match=r"unknown key '7' \(known: gain, delay_s\)"):
        refuse_unknown({7: 1}, ("gain", "delay_s"), "", fail)
