"""The one check of a YAML mapping's fields (fbg_accel_driver.mapping_fields, issue 12)."""

import math

import numpy as np
import pytest

from fbg_accel_driver.mapping_fields import format_version, number, number_array, refuse_unknown


def fail(msg: str) -> KeyError:  # any exception type the caller chooses
    return KeyError(f"f.yaml: {msg}")


def test_numbers_are_read_as_floats() -> None:
    got = [number(3, "x", fail), number(np.int64(4), "x", fail, positive=True), number(0.0, "x", fail, minimum=0.0),
           number(1e-3, "x", fail), number(math.inf, "x", fail, finite=False)]
    assert got == [3.0, 4.0, 0.0, 1e-3, math.inf] and all(type(v) is float for v in got)


@pytest.mark.parametrize(("value", "checks", "message"), [
    (True, {}, "x must be a number, got bool True"), (None, {}, "x must be a number, got NoneType None"),
    ("1e-3", {}, "x must be a number, got str '1e-3'"), ("warm", {}, "x must be a number, got str 'warm'"),
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


def test_an_array_applies_the_number_rules_to_every_entry() -> None:
    """``np.asarray(dtype=float)`` read ``yes``/``true`` as 1.0 and numeric text as a number; each entry is a number()."""
    np.testing.assert_array_equal(number_array([[1, 2.5], [3, 4]], "M", fail), [[1.0, 2.5], [3.0, 4.0]])
    for value, message in (([1.0, True], "M[1] must be a number, got bool True"),
                           ([[0.0], ["1e-3"]], "M[1][0] must be a number, got str '1e-3'"),
                           ([1.0, math.nan], "M[1] must be finite, got nan")):
        with pytest.raises(KeyError) as err:
            number_array(value, "M", fail)
        assert err.value.args[0] == f"f.yaml: {message}"
    with pytest.raises(KeyError, match=r"M is not a numeric array"):
        number_array([[1.0], [1.0, 2.0]], "M", fail)


@pytest.mark.parametrize("value", [True, 1.0, "1", 2, None])
def test_a_format_version_is_the_integer_the_reader_reads(value) -> None:
    assert format_version(1, "v", fail, reads=1) == 1
    with pytest.raises(KeyError, match=r"v .* is not supported \(this driver reads 1\)"):
        format_version(value, "v", fail, reads=1)
