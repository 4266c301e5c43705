"""The rooms of fbg_accel_calibration (its subpackages by job) import each other in one direction only
(docs/architecture.md, "Package graph"), and every module lives in a room."""

from __future__ import annotations

from pathlib import Path

from test_package_graph import ROOT, module_imports

PKG = "fbg_accel_calibration"
# each room may import only those before it (and itself)
ORDER = ('io', 'fit', 'dynamic', 'diagnosis', 'reports', 'recorder', 'commands')
# imports that go up the order, each with why (a function-local import of one function)
UPWARD = {
    ("io.input_files", "fit.thermal_fit"),  # sensor_id_of: the recording's sensor id, kept beside the fit that checks it
}


def room_imports(root: Path = ROOT) -> dict[tuple[str, str], tuple[str, str]]:
    """(module, imported module) -> (its room, the imported module's room), for every import across rooms."""
    edges = {}
    for mod, imported in module_imports(root, (PKG,)).items():
        here = mod.split(".")
        for other in imported:
            there = other.split(".")
            if len(here) > 2 and len(there) > 2 and here[1] != there[1]:
                edges[(".".join(here[1:]), ".".join(there[1:]))] = (here[1], there[1])
    return edges


def upward(edges: dict[tuple[str, str], tuple[str, str]]) -> dict[tuple[str, str], tuple[str, str]]:
    """The imports of a room's module from a room later in ORDER (a room not in ORDER counts as last)."""
    rank = {room: i for i, room in enumerate(ORDER)}
    return {e: r for e, r in edges.items() if rank.get(r[1], len(ORDER)) > rank.get(r[0], len(ORDER))}


def test_every_module_is_in_a_room() -> None:
    loose = sorted(p.name for p in (ROOT / PKG).glob("*.py") if p.name != "__init__.py")
    assert loose == [], f"modules outside a room: {loose}"
    rooms = sorted(p.name for p in (ROOT / PKG).iterdir() if (p / "__init__.py").is_file())
    assert rooms == sorted(ORDER), rooms


def test_rooms_import_down_the_order_only() -> None:
    edges = room_imports()
    assert set(upward(edges)) - set(UPWARD) == set(), sorted(set(upward(edges)) - set(UPWARD))
    assert set(UPWARD) <= set(edges), f"allowed upward imports that are gone: {sorted(set(UPWARD) - set(edges))}"


def test_the_room_check_sees_an_upward_import(tmp_path: Path) -> None:
    """The check is able to fail: a function-local relative import of a later room's module is found, and a
    downward one is not reported."""
    for f, text in {"__init__.py": "", "io/__init__.py": "", "io/a.py": "def f():\n    from ..fit import b\n",
                    "fit/__init__.py": "", "fit/b.py": "from ..io.a import f\n"}.items():
        (tmp_path / PKG / f).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / PKG / f).write_text(text, encoding="utf-8")
    assert upward(room_imports(tmp_path)) == {("io.a", "fit.b"): ("io", "fit")}
