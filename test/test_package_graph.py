"""The three top-level packages import each other in one direction only:
fbg_accel_driver <- fbg_accel_calibration <- fbg_accel_sim (docs/architecture.md, issue 12).

Every import is checked, including function-local ones, relative ones and module paths named in strings
(the demo starts the simulator and the driver by a ``python -c`` command)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ORDER = ("fbg_accel_driver", "fbg_accel_calibration", "fbg_accel_sim")  # each may import only those before it
_NAMED_IN_STRING = re.compile(r"\b(fbg_accel_(?:driver|calibration|sim))\b")


def imported_packages(path: Path, package: str) -> set[str]:
    """Top-level project packages that the module at ``path`` (inside ``package``) imports or names in code."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            found.add(package if node.level else (node.module or "").split(".")[0])
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and "import" in node.value:
            found.update(_NAMED_IN_STRING.findall(node.value))
    return found & set(ORDER)


def _modules() -> list[tuple[str, Path]]:
    return [(pkg, p) for pkg in ORDER for p in sorted((ROOT / pkg).rglob("*.py"))]


def test_every_package_has_modules() -> None:
    counts = {pkg: sum(1 for q, _ in _modules() if q == pkg) for pkg in ORDER}
    assert all(n >= 3 for n in counts.values()), counts


@pytest.mark.parametrize(("package", "path"), _modules(), ids=lambda v: v if isinstance(v, str) else v.name)
def test_imports_point_down_the_graph_only(package: str, path: Path) -> None:
    allowed = set(ORDER[: ORDER.index(package) + 1])
    assert imported_packages(path, package) <= allowed, (
        f"{path.relative_to(ROOT)} imports {sorted(imported_packages(path, package) - allowed)}; "
        f"{package} may import only {sorted(allowed)}")


def test_the_checker_sees_local_relative_and_string_imports(tmp_path: Path) -> None:
    """The scan is able to fail: each kind of import it must catch is caught."""
    src = tmp_path / "m.py"
    src.write_text("def f():\n    from fbg_accel_sim.board_sim import main\n"
                   "from . import sibling\n"
                   "CMD = 'import sys; from fbg_accel_calibration.cli import main'\n"
                   "DOC = 'fbg_accel_sim is the simulator'\n", encoding="utf-8")
    assert imported_packages(src, "fbg_accel_driver") == {"fbg_accel_sim", "fbg_accel_driver", "fbg_accel_calibration"}
