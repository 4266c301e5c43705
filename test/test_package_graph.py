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
                   "CMD = 'import sys; from fbg_accel_calibration.commands.cli import main'\n"
                   "DOC = 'fbg_accel_sim is the simulator'\n", encoding="utf-8")
    assert imported_packages(src, "fbg_accel_driver") == {"fbg_accel_sim", "fbg_accel_driver", "fbg_accel_calibration"}



def _module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def module_imports(root: Path, packages: tuple[str, ...]) -> dict[str, set[str]]:
    """Every module of ``packages`` under ``root`` -> the modules of those packages it imports anywhere in its code
    (at the top, in a function, under ``TYPE_CHECKING``; relative or absolute; ``from package import module`` as that
    module)."""
    files = {_module_name(p, root): p for pkg in packages for p in sorted((root / pkg).rglob("*.py"))}
    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        is_pkg = path.name == "__init__.py"
        here = name.split(".") if is_pkg else name.split(".")[:-1]
        out: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = ".".join(here[: len(here) - node.level + 1] + ([node.module] if node.module else [])) \
                    if node.level else (node.module or "")
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in files else base for a in node.names]
            else:
                continue
            for t in targets:
                while t and t not in files:  # a name inside a module: the module
                    t = t.rpartition(".")[0]
                if t and t != name:
                    out.add(t)
        graph[name] = out
    return graph


def import_circles(graph: dict[str, set[str]]) -> set[frozenset[str]]:
    """The sets of modules that import each other, directly or around a circle (strongly connected components of more
    than one module, Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: set[frozenset[str]] = set()

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.add(frozenset(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_module_imports_itself_round_a_circle() -> None:
    circles = import_circles(module_imports(ROOT, ORDER))
    assert circles == set(), sorted(sorted(c) for c in circles)


def test_the_circle_check_sees_local_relative_and_type_checking_imports(tmp_path: Path) -> None:
    """The check is able to fail: a circle closed by a function-local import, a relative one, one under TYPE_CHECKING
    and a ``from package import module`` are each found; a one-way chain is not a circle."""
    pkg = tmp_path / "p"
    (pkg / "sub").mkdir(parents=True)
    for f, text in {"__init__.py": "", "sub/__init__.py": "",
                    "a.py": "from .b import X\n",
                    "b.py": "def f():\n    from p.a import Y\n",
                    "c.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .sub import d\n",
                    "sub/d.py": "from .. import c\n",
                    "e.py": "from .a import X\n"}.items():
        (pkg / f).write_text(text, encoding="utf-8")
    circles = import_circles(module_imports(tmp_path, ("p",)))
    assert circles == {frozenset({"p.a", "p.b"}), frozenset({"p.c", "p.sub.d"})}


MODULE_LINES = 820  # about 800 lines: one job per module, in every package (issue 41)


@pytest.mark.parametrize("package", ORDER)
def test_no_module_is_over_about_800_lines(package: str) -> None:
    long = {str(p.relative_to(ROOT)): n for pkg, p in _modules() if pkg == package
            and (n := len(p.read_text(encoding="utf-8").splitlines())) > MODULE_LINES}
    assert long == {}, long
