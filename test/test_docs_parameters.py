"""The parameter tables of the docs and the shipped params files say what the nodes declare.

docs/topics.md (driver) and docs/calibration_node.md (calibration node) each have a parameter table
(name, type, default); config/driver.yaml and config/calibration.yaml are the example params files the launch
files use. A parameter added, renamed or given a new default in ``PARAMETERS`` without its doc row (or the other
way round) fails here, naming the row. Pure: no ROS, no process.
"""

from __future__ import annotations

import re
from decimal import Decimal
from pathlib import Path
from typing import Any

import pytest
import yaml

from fbg_accel_calibration.recorder.calibration_parameters import PARAMETERS as CALIBRATION_PARAMETERS
from fbg_accel_driver.driver_parameters import PARAMETERS as DRIVER_PARAMETERS

REPO = Path(__file__).resolve().parents[1]
DOC_TYPES = {"string": "string", "int": "integer", "integer": "integer", "double": "double", "bool": "bool",
             "string[]": "string_array", "double[3]": "double_array", "double[]": "double_array"}
CASES = {"driver": ("docs/topics.md", DRIVER_PARAMETERS), "calibration": ("docs/calibration_node.md", CALIBRATION_PARAMETERS)}


def doc_table(doc: str) -> dict[str, tuple[str, str]]:
    """name -> (type cell, default cell) of the table in the doc's ``## Parameters`` section."""
    text = (REPO / doc).read_text(encoding="utf-8")
    section = re.search(r"^## Parameters.*?$(.*?)(?=^## |\Z)", text, flags=re.M | re.S)
    assert section, f"{doc}: no '## Parameters' section"
    rows = {}
    for line in section.group(1).splitlines():
        m = re.match(r"^\| `([a-z_0-9]+)` \| ([^|]+) \| ([^|]+) \|", line)
        if m:
            rows[m.group(1)] = (m.group(2).strip(), m.group(3).strip())
    assert rows, f"{doc}: the parameter table has no rows"
    return rows


def default_matches(typ: str, declared: Any, cell: str) -> bool:
    """Whether a doc's default cell states the declared default (numbers to the digits the cell shows)."""
    cell = cell.strip("`")
    if declared is None:
        return cell == "unset"
    if typ == "bool":
        return cell == str(declared).lower()
    if typ == "string":
        if declared == "":  # an empty default is documented as "" or by what it stands for: (required), <...>
            return cell == '""' or cell.startswith("(") or "<" in cell
        return cell == declared
    try:
        shown = Decimal(cell)
    except ArithmeticError:
        return False
    exponent = shown.as_tuple().exponent
    assert isinstance(exponent, int)
    return abs(float(shown) - float(declared)) <= 0.5 * 10.0 ** exponent


@pytest.mark.parametrize("node", sorted(CASES))
def test_the_doc_table_lists_every_declared_parameter_with_its_type_and_default(node: str) -> None:
    doc, declared = CASES[node]
    rows = doc_table(doc)
    assert sorted(rows) == sorted(declared), (
        f"{doc}: documented but not declared {sorted(set(rows) - set(declared))}, "
        f"declared but not documented {sorted(set(declared) - set(rows))}")
    for name, (typ_cell, default_cell) in rows.items():
        typ, default, _ = declared[name]
        assert DOC_TYPES.get(typ_cell) == typ, f"{doc}: {name}: type {typ_cell!r}, declared {typ}"
        assert default_matches(typ, default, default_cell), f"{doc}: {name}: default {default_cell!r}, declared {default!r}"


# values of the shipped params files that deliberately differ from the node's default (the file says why)
PARAMS_FILE_CHOICES = {"calibration.yaml": {"output_dir": "calibration_runs"}}


@pytest.mark.parametrize(("params_file", "node"), [("driver.yaml", "driver"), ("calibration.yaml", "calibration")])
def test_the_params_file_sets_every_scalar_parameter_to_its_default(params_file: str, node: str) -> None:
    """The example params files are the table in YAML: every parameter with a scalar default, at that default
    (array parameters are unset by default and a params file cannot state 'unset'), apart from the choices above.
    Before: config/calibration.yaml lacked stream_timeout_s, although its header names only fit_with and
    still_noise_std as left out."""
    values = yaml.safe_load((REPO / "config" / params_file).read_text())["/**"]["ros__parameters"]
    declared = CASES[node][1]
    scalar = {n for n, (_, default, _) in declared.items() if default is not None}
    assert sorted(values) == sorted(scalar), (
        f"config/{params_file}: missing {sorted(scalar - set(values))}, not scalar parameters {sorted(set(values) - scalar)}")
    expected = {n: declared[n][1] for n in scalar} | PARAMS_FILE_CHOICES.get(params_file, {})
    for name in sorted(scalar):
        assert values[name] == expected[name], f"config/{params_file}: {name}: {values[name]!r}, default {expected[name]!r}"


@pytest.mark.parametrize("node", sorted(CASES))
def test_help_lists_every_parameter_in_aligned_columns(node: str) -> None:
    """``driver --help`` and ``calibration --help`` list each parameter as ``name type default ...``, the types in
    one column. Before: ``still_false_alarm_per_run``'s 25 characters overran the calibration node's 20-character
    name column, so its type and default stood 6 columns right of every other row's."""
    from fbg_accel_calibration.recorder.calibration_main import _usage as calibration_usage
    from fbg_accel_driver.driver_main import USAGE

    text = USAGE if node == "driver" else calibration_usage()
    declared = CASES[node][1]
    type_columns = set()
    for name, (typ, _, _) in declared.items():
        line = next(line for line in text.splitlines() if line.startswith(f"  {name} "))
        type_columns.add(line.index(f" {typ} ", len(name) + 2) + 1)
    assert len(type_columns) == 1, f"{node} --help: the type column starts at {sorted(type_columns)}"
