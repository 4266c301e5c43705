"""The README cannot rot: its quick shell blocks run on a fresh clone, and every other command it shows names
launch files, launch arguments, executables, parameters, options and files that exist.

A fenced ``bash`` block preceded by the line ``<!-- readme-test -->`` is run as it stands (``bash -euo pipefail``)
in a ``git clone`` of this repository, with the team's ``../shared`` beside the clone as the project expects and
this test run's virtual environment as the clone's ``.venv`` (the clone's own code first on PYTHONPATH). Only
quick blocks carry the marker: the demo, the test suite, launch files (launch is not on PyPI) and the two-minute
dynamic calibration cannot run inside the suite, so their commands are checked against the code instead.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
MARK = "<!-- readme-test -->"
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.M | re.S)


def blocks(text: str) -> list[tuple[int, str, str, bool]]:
    """(line, language, body, marked) of each fenced block."""
    out = []
    for m in FENCE.finditer(text):
        before = text[: m.start()].rstrip("\n").rsplit("\n", 1)[-1].strip()
        out.append((text.count("\n", 0, m.start()) + 1, m.group(1), m.group(2), before == MARK))
    return out


def commands(text: str) -> list[tuple[int, list[str]]]:
    """Shell commands of the README's bash blocks and inline code spans, as tokens (comments, continuations and
    ``&&`` / ``|`` / ``&`` joins resolved)."""
    found: list[tuple[int, str]] = []
    for line, lang, body, _ in blocks(text):
        if lang == "bash":
            for i, ln in enumerate(body.replace("\\\n", " ").splitlines()):
                found.append((line + 1 + i, ln))
    prose = FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), text)
    for m in re.finditer(r"`((?:ros2|fbg-accel-calib|\.venv/bin/|driver|board_sim|calibration) [^`]*)`", prose):
        found.append((prose.count("\n", 0, m.start()) + 1, m.group(1)))
    out = []
    for line, src in found:
        for part in re.split(r"&&|\|\||[|;&]", src):
            try:
                tokens = shlex.split(part, comments=True)
            except ValueError:
                continue
            if tokens:
                out.append((line, tokens))
    return out


def _launch_arguments(name: str) -> set[str]:
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"readme_launch_{name.split('.')[0]}", REPO / "launch" / name)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return set(module.launch_arguments(str(REPO)))


def _node_parameters(exe: str) -> set[str]:
    if exe == "driver":
        from fbg_accel_driver.driver_parameters import PARAMETERS
    else:
        from fbg_accel_calibration.recorder.calibration_parameters import PARAMETERS
    return set(PARAMETERS) | {"use_sim_time"}


def _check_command(tokens: list[str]) -> list[str]:
    from fbg_accel_calibration.commands.cli import build_parser

    problems = []
    for t in tokens:  # repository files named as arguments
        if re.fullmatch(r"(config|launch|scripts|bench)/[\w./-]+\.\w+", t) and not (REPO / t).exists():
            problems.append(f"no file {t}")
    if tokens[:3] == ["ros2", "launch", "fbg_accel_driver"] and len(tokens) > 3:
        if not (REPO / "launch" / tokens[3]).is_file():
            return [*problems, f"no launch file {tokens[3]}"]
        known = _launch_arguments(tokens[3])
        problems += [f"{tokens[3]} has no argument {t.split(':=')[0]}" for t in tokens[4:]
                     if ":=" in t and t.split(":=")[0] not in known]
        return problems
    exe = None
    if tokens[:3] == ["ros2", "run", "fbg_accel_driver"] and len(tokens) > 3:
        exe, args = tokens[3], tokens[4:]
    elif tokens[0].startswith(".venv/bin/"):
        exe, args = tokens[0].removeprefix(".venv/bin/"), tokens[1:]
    elif tokens[0] in ("fbg-accel-calib", "driver", "calibration", "board_sim"):
        exe, args = tokens[0], tokens[1:]
    if exe is None:
        return problems
    if exe in ("driver", "calibration"):
        declared = _node_parameters(exe)
        for i, t in enumerate(args):
            if t == "-p" and i + 1 < len(args):
                name = args[i + 1].split(":=")[0]
                if name not in declared and not name.startswith("qos_overrides."):
                    problems.append(f"{exe} has no parameter {name}")
    elif exe == "fbg-accel-calib":
        parser = build_parser()
        sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
        if args and not args[0].startswith("-"):
            if args[0] not in sub.choices:
                return [*problems, f"fbg-accel-calib has no command {args[0]}"]
            options = {o for a in sub.choices[args[0]]._actions for o in a.option_strings}
            problems += [f"fbg-accel-calib {args[0]} has no option {t}" for t in args[1:]
                         if t.startswith("--") and t.split("=")[0] not in options]
    elif exe == "board_sim":
        from fbg_accel_sim.board_sim import build_parser as sim_parser

        options = {o for a in sim_parser()._actions for o in a.option_strings}
        problems += [f"board_sim has no option {t}" for t in args if t.startswith("--") and t not in options]
    else:
        problems.append(f"{exe} is not an executable of the package")
    return problems


def test_every_command_in_the_readme_names_what_exists() -> None:
    text = (REPO / "README.md").read_text(encoding="utf-8")
    cmds = commands(text)
    assert len(cmds) >= 15, "the README's commands were not found"
    problems = [f"README.md:{line}: {' '.join(tokens)}: {p}" for line, tokens in cmds for p in _check_command(tokens)]
    assert not problems, "\n".join(problems)


def test_the_readme_marks_its_quick_blocks() -> None:
    marked = [b for b in blocks((REPO / "README.md").read_text(encoding="utf-8")) if b[3]]
    assert len(marked) >= 2 and all(lang == "bash" for _, lang, _, _ in marked), marked


def test_marked_readme_blocks_run_on_a_fresh_clone(tmp_path: Path) -> None:
    if not SHARED.is_dir():
        pytest.fail(f"the team's shared directory is missing: {SHARED} (the README's measured-data block needs it)")
    ws = tmp_path / "ws"
    clone = ws / REPO.name
    ws.mkdir()
    res = subprocess.run(["git", "clone", "--quiet", str(REPO), str(clone)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    (ws / "shared").symlink_to(SHARED)
    (clone / ".venv").symlink_to(Path(sys.prefix))
    env = {**os.environ, "PYTHONPATH": str(clone)}
    failures = []
    marked = [(line, body) for line, _, body, is_marked in blocks((clone / "README.md").read_text(encoding="utf-8"))
              if is_marked]
    assert marked, "the clone's README has no marked block"
    for line, body in marked:
        run = subprocess.run(["bash", "-euo", "pipefail", "-c", body], cwd=clone, env=env, capture_output=True,
                             text=True, timeout=180)
        if run.returncode != 0:
            failures.append(f"README.md:{line} exited {run.returncode}:\n{body}\n--- stdout\n{run.stdout[-2000:]}"
                            f"\n--- stderr\n{run.stderr[-2000:]}")
    assert not failures, "\n".join(failures)
