"""Bring-up files (issue 10): launch files, params files, declared dependencies, ``--version``.

launch_ros is not on PyPI, so a launch file is checked the way ``ros2 launch`` would use it: it
compiles, its pure ``node_descriptions`` name executables that setup.py installs, parameter files
that exist and hold only parameters the node declares (with their types), and the command line
launch_ros builds from it (``<exe> --ros-args -r __node:=N -r __ns:=/NS --params-file F ...``, dict
overrides as a params file keyed by the node's full name, as launch_ros writes them) starts the node
with those values.
One short process run per launch file; every wait is a condition with a deadline.
"""

from __future__ import annotations

import ast
import importlib
import importlib.metadata
import importlib.util
import json
import re
import signal
import subprocess
import sys
import tomllib
import types
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
import yaml
from process_harness import ChildProcess

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
LAUNCH_FILES = ("driver.launch.py", "calibration.launch.py", "sim.launch.py")
PARAMS_FILES = ("driver.yaml", "calibration.yaml")
CODE_PACKAGES = ("fbg_accel_driver", "fbg_accel_calibration")

# Third-party modules the code may import: module -> (PyPI distribution, rosdep key in package.xml).
# A module missing here fails test_declared_dependencies_match_imports: declare it, then add it here.
PYPI_MODULES = {
    "numpy": ("numpy", "python3-numpy"),
    "serial": ("pyserial", "python3-serial"),
    "yaml": ("PyYAML", "python3-yaml"),
    "scipy": ("scipy", "python3-scipy"),
    "matplotlib": ("matplotlib", "python3-matplotlib"),
    "mcap": ("mcap", "python3-mcap-pip"),
    "mcap_ros2": ("mcap-ros2-support", "mcap-ros2-support"),
    "zstandard": ("zstandard", "python3-zstandard-pip"),
    "allantools": ("AllanTools", "python3-allantools-pip"),
    "tqdm": ("tqdm", "python3-tqdm"),
}
# ROS 2 packages (from the ROS install or the ros-jazzy-* wheels): module = package.xml exec_depend.
ROS_MODULES = {"rclpy", "rcl_interfaces", "ament_index_python", "sensor_msgs", "diagnostic_msgs", "geometry_msgs",
               "std_msgs", "std_srvs", "launch", "launch_ros"}


# ----------------------------------------------------------------------------- setup.py / package.xml
def _setup_keywords() -> dict[str, ast.expr]:
    tree = ast.parse((REPO / "setup.py").read_text())
    call = next(n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "setup")
    return {k.arg: k.value for k in call.keywords if k.arg}


def console_scripts() -> dict[str, str]:
    """setup.py console_scripts: executable name -> 'module:function'."""
    eps = ast.literal_eval(_setup_keywords()["entry_points"])
    return dict(tuple(part.strip() for part in line.split("=", 1)) for line in eps["console_scripts"])


def install_requires() -> set[str]:
    return {re.split(r"[<>=!~;\[ ]", r, maxsplit=1)[0] for r in ast.literal_eval(_setup_keywords()["install_requires"])}


def package_xml() -> ET.Element:
    return ET.parse(REPO / "package.xml").getroot()


def node_parameters(executable: str) -> dict[str, tuple[str, Any, str]]:
    """The PARAMETERS table (name: (type, default, description)) of a ROS executable's module."""
    module = importlib.import_module(console_scripts()[executable].split(":")[0])
    return module.PARAMETERS


# ----------------------------------------------------------------------------- launch files
def load_launch(name: str) -> ModuleType:
    """Compile and import a launch file (without launch/launch_ros: they must be imported lazily)."""
    path = REPO / "launch" / name
    compile(path.read_text(), str(path), "exec")  # a SyntaxError names the file and line
    spec = importlib.util.spec_from_file_location(f"launch_file_{name.split('.')[0]}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def descriptions(name: str, **overrides: str) -> list[dict[str, Any]]:
    """node_descriptions of a launch file for its default arguments plus ``overrides`` (the source tree
    stands for the share directory: setup.py installs config/ and launch/ there unchanged)."""
    module = load_launch(name)
    args = {n: default for n, (default, _) in module.launch_arguments(str(REPO)).items()}
    unknown = set(overrides) - set(args)
    assert not unknown, f"{name} has no launch argument(s) {unknown}"
    return module.node_descriptions(str(REPO), args | overrides)


def command_line(desc: dict[str, Any], tmp_path: Path) -> list[str]:
    """The command launch_ros runs for a description (what `ros2 run` runs, plus the node's ROS arguments)."""
    cmd = [str(BIN / desc["executable"]), *desc.get("arguments", [])]
    if not desc.get("ros_node", True):
        return cmd
    ros: list[str] = []
    ns = desc.get("namespace") or ""
    ns = ns if not ns or ns.startswith("/") else "/" + ns
    if desc.get("name"):
        ros += ["-r", f"__node:={desc['name']}"]
    if ns:
        ros += ["-r", f"__ns:={ns}"]
    ros += desc.get("ros_arguments", [])
    # launch_ros (jazzy) writes a dict as a params file keyed by the node's full name, else by /**
    key = f"{ns}/{desc['name']}" if desc.get("name") else "/**"
    for i, p in enumerate(desc.get("parameters", [])):
        if isinstance(p, dict):
            f = tmp_path / f"launch_params_{desc['executable']}_{i}.yaml"
            f.write_text(yaml.safe_dump({key: {"ros__parameters": p}}))
            p = str(f)
        ros += ["--params-file", p]
    return [*cmd, "--ros-args", *ros]


def overrides_of(desc: dict[str, Any]) -> dict[str, Any]:
    """The parameter overrides (dicts) of a description, merged in order."""
    out: dict[str, Any] = {}
    for p in desc.get("parameters", []):
        if isinstance(p, dict):
            out |= p
    return out


def check_values(where: str, values: dict[str, Any], declared: dict[str, tuple[str, Any, str]]) -> None:
    """Every name is a declared parameter and its YAML value has the declared type (rclpy refuses others)."""
    declared = declared | {"use_sim_time": ("bool", False, "rclpy's own")}
    unknown = sorted(set(values) - set(declared))
    assert not unknown, f"{where}: {unknown} are not parameters of the node (silently ignored by ROS)"
    python_types = {"string": (str,), "integer": (int,), "double": (float,), "bool": (bool,)}
    for k, v in values.items():
        typ = declared[k][0]
        ok = isinstance(v, python_types[typ]) and not (typ != "bool" and isinstance(v, bool)) \
            if typ in python_types else isinstance(v, list)
        assert ok, f"{where}: {k}: {v!r} is not of the declared type {typ}"


# ----------------------------------------------------------------------------- pure checks
@pytest.mark.parametrize("params_file", PARAMS_FILES)
def test_params_files_use_the_wildcard_key_and_declared_parameters(params_file: str) -> None:
    data = yaml.safe_load((REPO / "config" / params_file).read_text())
    assert list(data) == ["/**"], \
        f"config/{params_file}: top-level keys {list(data)}; a node-name key is ignored under a namespace"
    executable = {"driver.yaml": "driver", "calibration.yaml": "calibration"}[params_file]
    values = data["/**"]["ros__parameters"]
    check_values(f"config/{params_file}", values, node_parameters(executable))


@pytest.mark.parametrize("launch_file", LAUNCH_FILES)
def test_launch_file_names_installed_executables_existing_params_files_and_parameters(launch_file: str) -> None:
    module = load_launch(launch_file)
    assert callable(module.generate_launch_description)
    scripts = console_scripts()
    descs = descriptions(launch_file)
    assert descs, f"{launch_file} starts nothing"
    for d in descs:
        assert d["executable"] in scripts, f"{launch_file}: executable {d['executable']!r} is not a setup.py console script"
        if not d.get("ros_node", True):
            continue
        declared = node_parameters(d["executable"])
        files = [p for p in d["parameters"] if isinstance(p, str)]
        assert files, f"{launch_file}: {d['executable']} gets no params file"
        for f in files:
            assert Path(f).is_file() and Path(f).parent == REPO / "config", f
            check_values(f, yaml.safe_load(Path(f).read_text())["/**"]["ros__parameters"], declared)
        for p in d["parameters"]:
            if isinstance(p, dict):
                check_values(f"{launch_file} overrides", p, declared)
                for k, v in p.items():  # file-valued overrides name shipped files
                    if k.endswith("_file") and v and v not in ("sim", "none"):  # driver's calibration choices
                        assert Path(v).is_file(), f"{launch_file}: {k} {v} does not exist"


def test_sim_launch_board_sim_arguments_parse_and_point_the_driver_at_its_link(tmp_path: Path) -> None:
    from fbg_accel_sim.board_sim import build_parser

    link = str(tmp_path / "board")
    sim, driver = descriptions("sim.launch.py", link=link)
    args = build_parser().parse_args(sim["arguments"])
    assert Path(args.config).is_file() and args.link == link
    assert overrides_of(driver)["port"] == link
    # the driver starts once board_sim has announced its pty (the link exists then): started together, the
    # driver's first open could come first and log "cannot open ...: No such file" as an ERROR
    assert driver["start_after_output"] == ("board_sim", "PTY ")


def test_two_sim_launches_under_two_namespaces_get_a_board_each() -> None:
    """Two simulated sensors on one vehicle: ``sim.launch.py namespace:=acc_a`` and ``namespace:=acc_b`` with
    their other arguments left at the defaults. Each driver must read its own board. On the unchanged code
    both board_sims were given the one default link (/tmp/fbg_accel_sim_board_<uid>): the second re-pointed
    it, the acc_a driver read board B, the acc_b driver was refused the port for ever and board A had no
    reader (seen with both launches' command lines as processes)."""
    def link_of(sim: dict[str, Any]) -> str:
        return sim["arguments"][sim["arguments"].index("--link") + 1]

    (sim_a, drv_a), (sim_b, drv_b) = (descriptions("sim.launch.py", namespace=ns) for ns in ("acc_a", "acc_b"))
    link_a, link_b = link_of(sim_a), link_of(sim_b)
    assert link_a != link_b, link_a
    assert overrides_of(drv_a)["port"] == link_a and overrides_of(drv_b)["port"] == link_b
    (sim_root, _), (sim_root2, _) = descriptions("sim.launch.py"), descriptions("sim.launch.py", namespace="/")
    assert link_of(sim_root) not in (link_a, link_b)
    assert sim_root2["arguments"] == sim_root["arguments"]  # "/" is the root namespace, as ""
    assert "acc_a" in link_a and "/" not in Path(link_a).name  # says whose board it is, one file name


def test_launch_arguments_refuse_bad_values_with_their_name() -> None:
    with pytest.raises(ValueError, match="start_driver"):
        descriptions("calibration.launch.py", start_driver="maybe")
    with pytest.raises(ValueError, match="temperature_level"):
        descriptions("calibration.launch.py", temperature_level="two")
    with pytest.raises(ValueError, match="log_level"):
        descriptions("driver.launch.py", log_level="loud")
    with pytest.raises(ValueError, match="managed"):
        descriptions("sim.launch.py", managed="perhaps")
    assert [d["executable"] for d in descriptions("calibration.launch.py", start_driver="false")] == ["calibration"]


@pytest.mark.parametrize("launch_file", LAUNCH_FILES)
def test_every_launch_file_takes_managed_use_sim_time_and_log_level(launch_file: str) -> None:
    """``managed:=true`` makes the driver a lifecycle node (``--managed``), ``use_sim_time`` and ``log_level`` reach
    every ROS node; the defaults leave the node as before (plain, wall clock, info)."""
    for managed, sim_time, level in (("false", "false", "info"), ("true", "true", "debug")):
        descs = [d for d in descriptions(launch_file, managed=managed, use_sim_time=sim_time, log_level=level)
                 if d.get("ros_node", True)]
        assert descs
        for d in descs:
            assert overrides_of(d)["use_sim_time"] is (sim_time == "true"), d
            assert d["ros_arguments"][-2:] == ["--log-level", level], d
            assert ("--managed" in d.get("arguments", [])) is (managed == "true" and d["executable"] == "driver"), d


def test_calibration_launch_ends_with_the_recorder_and_only_with_it() -> None:
    descs = descriptions("calibration.launch.py")
    assert [d.get("ends_launch", False) for d in descs] == [False, True], descs
    assert descs[1]["executable"] == "calibration"


def _fake_launch(monkeypatch: pytest.MonkeyPatch) -> None:
    """Stand-ins for launch, launch_ros and ament_index_python with the jazzy signatures (keyword-only
    where the real ones are): a wrong keyword in launch_support.generate raises TypeError here."""
    def module(name: str, **attrs: Any) -> None:
        m = ModuleType(name)
        m.__dict__.update(attrs)
        monkeypatch.setitem(sys.modules, name, m)

    class LaunchConfiguration:
        def __init__(self, variable_name: str, *, default: Any = None) -> None:
            self.variable_name = variable_name

        def perform(self, context: dict[str, str]) -> str:
            return context[self.variable_name]

    def declare(name: str, *, default_value: Any = None, description: Any = None, choices: Any = None) -> tuple:
        return ("argument", name, default_value)

    def execute_process(*, cmd: list, prefix: Any = None, name: Any = None, cwd: Any = None, env: Any = None,
                        additional_env: Any = None, output: str = "log") -> tuple:
        return ("process", cmd, name, output)

    def node(*, executable: str, package: Any = None, name: Any = None, namespace: Any = None, exec_name: Any = None,
             parameters: Any = None, remappings: Any = None, ros_arguments: Any = None, arguments: Any = None,
             output: str = "log") -> tuple:
        return ("node", {"package": package, "executable": executable, "name": name, "namespace": namespace,
                         "parameters": parameters, "arguments": arguments, "ros_arguments": ros_arguments,
                         "output": output})

    def share(package_name: str) -> str:
        assert package_name == "fbg_accel_driver", package_name
        return str(REPO)

    module("launch", LaunchDescription=lambda initial_entities=None: ("description", list(initial_entities or [])))
    module("launch.actions", DeclareLaunchArgument=declare, ExecuteProcess=execute_process,
           OpaqueFunction=lambda *, function, args=None, kwargs=None: ("opaque", function),
           RegisterEventHandler=lambda event_handler, **kwargs: ("handler", event_handler),
           EmitEvent=lambda *, event, **kwargs: ("emit", event))
    module("launch.event_handlers",
           OnProcessExit=lambda *, target_action=None, on_exit, **kwargs: ("on_exit", target_action, on_exit),
           OnProcessIO=lambda *, target_action=None, on_stdin=None, on_stdout=None, on_stderr=None, **kwargs:
           ("on_io", target_action, on_stdout))
    module("launch.events", Shutdown=lambda *, reason="reason not given", due_to_sigint=False: ("shutdown", reason))
    module("launch.substitutions", LaunchConfiguration=LaunchConfiguration)
    module("launch_ros.actions", Node=node)
    module("launch_ros.parameter_descriptions", ParameterValue=lambda value, *, value_type=None: ("value", value, value_type))
    module("launch_ros.substitutions", ExecutableInPackage=lambda executable, package: ("exe", executable, package))
    module("ament_index_python.packages", get_package_share_directory=share)


@pytest.mark.parametrize("launch_file", LAUNCH_FILES)
def test_generate_launch_description_starts_the_described_nodes(launch_file: str, monkeypatch: pytest.MonkeyPatch) -> None:
    module = load_launch(launch_file)
    _fake_launch(monkeypatch)
    kind, entities = module.generate_launch_description()
    assert kind == "description"
    declared = {e[1]: e[2] for e in entities if e[0] == "argument"}
    assert declared == {n: d for n, (d, _) in module.launch_arguments(str(REPO)).items()}
    (opaque,) = [e[1] for e in entities if e[0] == "opaque"]
    given = {"namespace": "veh1"} | ({"sensor_id": "007"} if "sensor_id" in declared else {})
    started = opaque(declared | given)
    descs = module.node_descriptions(str(REPO), declared | given)
    handlers = [a[1] for a in started if a[0] == "handler"]
    started = [a for a in started if a[0] != "handler"]
    # a node that waits for a program's output line starts from that program's output, once
    programs = {a[2]: a for a in started if a[0] == "process"}  # name -> action
    for d in descs:
        if "start_after_output" in d:
            program, text = d["start_after_output"]
            (io,) = [h for h in handlers if h[0] == "on_io" and h[1] is programs[program]]
            handlers.remove(io)
            line = types.SimpleNamespace(text=f"{text}/dev/pts/7\n".encode())
            assert io[2](types.SimpleNamespace(text=b"other output\n")) is None
            (node,) = io[2](line)
            assert io[2](line) is None  # once
            started.append(node)
    assert len(started) == len(descs)
    started.sort(key=lambda a: [d["executable"] for d in descs].index(a[1]["executable"] if a[0] == "node"
                                                                        else a[2]))
    # the end of a process marked ends_launch (the calibration recorder) shuts the launch down
    ending = [a for a, d in zip(started, descs, strict=True) if d.get("ends_launch")]
    assert handlers == [("on_exit", a, [("emit", ("shutdown", f"{a[1]['executable']} ended"))]) for a in ending]
    for action, d in zip(started, descs, strict=True):
        if not d.get("ros_node", True):
            assert action == ("process", [("exe", d["executable"], "fbg_accel_driver"), *d["arguments"]],
                              d["executable"], "screen")
            continue
        kind, kw = action
        params = [p if isinstance(p, str) else {k: ("value", v, str) if isinstance(v, str) else v for k, v in p.items()}
                  for p in d["parameters"]]
        assert (kind, kw) == ("node", {"package": "fbg_accel_driver", "executable": d["executable"], "name": d["name"],
                                       "namespace": "veh1", "parameters": params, "arguments": d.get("arguments", []),
                                       "ros_arguments": d["ros_arguments"], "output": "screen"})


def _third_party_imports(paths: list[Path]) -> dict[str, set[str]]:
    """Top-level module -> files, for absolute imports that are neither stdlib nor the project's own."""
    found: dict[str, set[str]] = {}
    for f in paths:
        for node in ast.walk(ast.parse(f.read_text(), str(f))):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            for n in names:
                top = n.split(".")[0]
                if top not in sys.stdlib_module_names and top not in CODE_PACKAGES:
                    found.setdefault(top, set()).add(str(f.relative_to(REPO)))
    return found


def test_declared_dependencies_match_imports() -> None:
    code = [f for pkg in CODE_PACKAGES for f in (REPO / pkg).rglob("*.py")]
    imports = _third_party_imports([*code, *(REPO / "launch").glob("*.launch.py")])
    unknown = {m: sorted(f) for m, f in imports.items() if m not in PYPI_MODULES and m not in ROS_MODULES}
    assert not unknown, f"imports of undeclared third-party modules {unknown}: declare them in setup.py and package.xml"
    exec_depends = {e.text for e in package_xml().iter("exec_depend")}
    requires = install_requires()
    for m, files in imports.items():
        if m in ROS_MODULES:
            assert m in exec_depends, f"{m} (imported by {sorted(files)}) is not an exec_depend of package.xml"
            continue
        dist, key = PYPI_MODULES[m]
        assert dist in requires, f"{m} (imported by {sorted(files)}) needs {dist} in setup.py install_requires"
        assert key in exec_depends, f"{m} (imported by {sorted(files)}) needs <exec_depend>{key}</exec_depend>"
    # and nothing declared that nothing imports (setuptools: the ament_python convention)
    code_imports = _third_party_imports(code)
    unused = requires - {"setuptools"} - {PYPI_MODULES[m][0] for m in code_imports if m in PYPI_MODULES}
    assert not unused, f"setup.py install_requires {sorted(unused)} are imported nowhere"
    # the pinned venv installs every declared distribution
    pinned = (REPO / "requirements.txt").read_text().lower()
    for dist in requires - {"setuptools"}:
        assert re.search(rf"^{re.escape(dist.lower())}==", pinned, re.M), f"{dist} is not pinned in requirements.txt"
    # keys that rosdistro does not define come with their definition
    local = yaml.safe_load((REPO / "rosdep.yaml").read_text())
    for key in sorted(k for k in exec_depends if k and k.endswith("-pip")):
        dist = next(d for d, k in PYPI_MODULES.values() if k == key)
        assert local[key]["ubuntu"]["pip"]["packages"] == [dist], f"rosdep.yaml: {key} must pip-install {dist}"


# What the tests use beyond the exec_depends: test module -> rosdep key (with its PyPI distribution when rosdistro
# lacks the key), and the tools they run (pytest plugins, colcon, pip/wheel, the C compiler of the firmware tests).
TEST_MODULES = {"pytest": ("python3-pytest", None), "hypothesis": ("python3-hypothesis", None),
                "rosbags": ("python3-rosbags-pip", "rosbags"), "lifecycle_msgs": ("lifecycle_msgs", None),
                "xdist": ("python3-pytest-xdist-pip", "pytest-xdist")}
TEST_TOOLS = {"python3-pytest-timeout", "python3-colcon-common-extensions", "python3-pip", "python3-wheel", "gcc"}


def test_every_test_import_and_tool_is_a_test_depend() -> None:
    """``rosdep install`` of the package gives what its tests import and run (only pytest used to be declared)."""
    tests = [*(REPO / "test").glob("*.py")]
    # the tests' helpers, the bench scripts' modules and the package's own simulator
    local_modules = {f.stem for f in [*tests, *(REPO / "bench").glob("*.py")]} | {"fbg_accel_sim"}
    imports = {m: f for m, f in _third_party_imports(tests).items() if m not in local_modules}
    declared = {m for m in PYPI_MODULES} | ROS_MODULES | set(TEST_MODULES)
    unknown = {m: sorted(f) for m, f in imports.items() if m not in declared}
    assert not unknown, f"tests import modules that no depend of package.xml provides: {unknown}"
    test_depends = {e.text for e in package_xml().iter("test_depend")}
    exec_depends = {e.text for e in package_xml().iter("exec_depend")}
    missing = sorted(k for m, (k, _) in TEST_MODULES.items() if m in imports and k not in test_depends | exec_depends)
    missing += sorted(TEST_TOOLS - test_depends)
    assert not missing, f"package.xml lacks <test_depend> {missing}"
    assert "timeout" in tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]
    local = yaml.safe_load((REPO / "rosdep.yaml").read_text())
    for key, dist in TEST_MODULES.values():
        if dist is not None:
            assert local[key]["ubuntu"]["pip"]["packages"] == [dist], f"rosdep.yaml: {key} must pip-install {dist}"


def test_version_matches_between_setup_py_and_package_xml() -> None:
    assert ast.literal_eval(_setup_keywords()["version"]) == package_xml().findtext("version")


# ----------------------------------------------------------------------------- --version
def test_every_executable_prints_its_version_from_the_metadata() -> None:
    version = importlib.metadata.version("fbg_accel_driver")
    assert version == ast.literal_eval(_setup_keywords()["version"])
    for name in console_scripts():
        res = subprocess.run([str(BIN / name), "--version"], capture_output=True, text=True, timeout=60)
        assert (res.returncode, res.stdout, res.stderr) == (0, f"{name} {version}\n", ""), name
    # ... without starting ROS: no rclpy import behind --version
    probe = (
        "import contextlib, importlib, io, json, sys\n"
        "out = {}\n"
        "for name, target in json.loads(sys.argv[1]).items():\n"
        "    mod, func = target.split(':')\n"
        "    buf = io.StringIO()\n"
        "    with contextlib.redirect_stdout(buf):\n"
        "        try:\n"
        "            rc = getattr(importlib.import_module(mod), func)(['--version'])\n"
        "        except SystemExit as e:\n"
        "            rc = e.code\n"
        "    out[name] = [rc, buf.getvalue()]\n"
        "out['rclpy imported'] = 'rclpy' in sys.modules\n"
        "print(json.dumps(out))\n"
    )
    res = subprocess.run([sys.executable, "-c", probe, json.dumps(console_scripts())], capture_output=True, text=True,
                         timeout=120, cwd=REPO)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    assert out.pop("rclpy imported") is False
    assert out == {name: [0, f"{name} {version}\n"] for name in console_scripts()}


# ----------------------------------------------------------------------------- processes
def _start_all(descs: list[dict[str, Any]], tmp_path: Path) -> list[ChildProcess]:
    """The processes of a launch file, each started as launch starts it (after the output it waits for)."""
    procs: dict[str, ChildProcess] = {}
    for d in descs:
        if "start_after_output" in d:
            program, text = d["start_after_output"]
            procs[program].wait_line(re.escape(text), timeout=60)
        procs[d["executable"]] = ChildProcess(d["executable"], command_line(d, tmp_path))
    return list(procs.values())


def _stop_all(procs: list[ChildProcess]) -> list[int]:
    return [p.stop() for p in reversed(procs)][::-1]


@pytest.fixture(scope="module")
def driver_launch_run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str, int]]:
    """driver.launch.py's command line with a port override, start-up imports logged (-X importtime)."""
    tmp = tmp_path_factory.mktemp("driver_launch")
    port = str(tmp / "no_board_here")
    (desc,) = descriptions("driver.launch.py", port=port, calibration_file="sim")
    with pytest.MonkeyPatch.context() as env:
        env.setenv("PYTHONPROFILEIMPORTTIME", "1")  # the child logs every import to stderr
        proc = ChildProcess("driver", command_line(desc, tmp))
    try:
        proc.wait_line(r"reading \S*no_board_here at", timeout=60)
    finally:
        rc = proc.stop()
    yield port, proc.output(), rc


def test_driver_launch_starts_the_driver_with_its_params_file(driver_launch_run: tuple[str, str, int]) -> None:
    port, output, rc = driver_launch_run
    line = next(ln for ln in output.splitlines() if "reading " in ln)
    # the params file's values (= the node's defaults) and the launch argument's port
    assert f"reading {port} at 921600 baud, calibration {REPO / 'config' / 'calibration_sim.yaml'}" in line, line
    assert line.rstrip().endswith("decimation 1"), line
    errors = [ln for ln in output.splitlines() if ln.startswith("[ERROR]") and "serial link down" not in ln]
    assert rc == 0 and not errors and "Traceback" not in output, output[-3000:]


def test_driver_startup_imports_neither_matplotlib_nor_scipy(driver_launch_run: tuple[str, str, int]) -> None:
    _, output, _ = driver_launch_run
    imported = {m.group(1).split(".")[0] for m in re.finditer(r"^import time:.*\|\s*(\S+)\s*$", output, re.M)}
    assert {"rclpy", "numpy", "serial", "yaml"} <= imported, "the import log did not capture the start-up"
    assert not imported & {"matplotlib", "scipy"}, sorted(imported & {"matplotlib", "scipy"})


def test_driver_under_a_namespace_takes_its_params_file(tmp_path: Path) -> None:
    # config/driver.yaml as shipped, with two values changed: keys and structure are the file's own.
    data = yaml.safe_load((REPO / "config" / "driver.yaml").read_text())
    port = str(tmp_path / "ns_port")
    for section in data.values():
        section["ros__parameters"].update(port=port, decimation=7, calibration_file="sim")
    params = tmp_path / "driver.yaml"
    params.write_text(yaml.safe_dump(data))
    proc = ChildProcess("driver", [BIN / "driver", "--ros-args", "-r", "__ns:=/veh1", "--params-file", params])
    try:
        line = proc.wait_line(r"reading \S+ at \d+ baud", timeout=60)
    finally:
        rc = proc.stop()
    assert line.startswith("[INFO]") and "[veh1.fbg_accel_driver]" in line, line
    assert f"reading {port} at" in line and line.rstrip().endswith("decimation 7"), line
    assert rc == 0


def test_calibration_launch_starts_driver_and_recorder_under_a_namespace(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)  # launched from tmp_path: the relative output_dir lands there
    port = str(tmp_path / "no_board_here")
    descs = descriptions("calibration.launch.py", namespace="veh1", port=port, sensor_id="acc4")
    assert [d["executable"] for d in descs] == ["driver", "calibration"]
    procs = _start_all(descs, tmp_path)
    try:
        driver_line = procs[0].wait_line(r"reading \S+ at", timeout=60)
        calib_line = procs[1].wait_line(r"recording to", timeout=60)
    finally:
        rcs = _stop_all(procs)
    assert "[veh1.fbg_accel_driver]" in driver_line and f"reading {port} at" in driver_line, driver_line
    # output_dir from config/calibration.yaml (not the node's default "."), sensor_id from the launch argument
    assert "[veh1.calibration]" in calib_line, calib_line
    assert re.search(r"recording to calibration_runs/acc4_\d{8}T\d{6}Z\.mcap$", calib_line.rstrip()), calib_line
    assert "plan 'six_position'" in calib_line, calib_line  # the launch argument's default plan
    # the recorder interrupted: MCAP closed cleanly, and exit 0 (--stopped-ok), where it exits 3 on its own, so
    # that Ctrl-C of the launch file shows no "process has died" ERROR
    assert descs[1]["arguments"] == ["--stopped-ok"]
    assert rcs == [0, 0], (rcs, procs[1].output())
    assert "run SIGINT" in procs[1].output() and "closed" in procs[1].output(), procs[1].output()


def test_managed_launch_starts_a_lifecycle_driver_at_the_given_log_level(tmp_path: Path) -> None:
    (desc,) = descriptions("driver.launch.py", port=str(tmp_path / "no_board_here"), calibration_file="sim",
                           managed="true", log_level="debug", use_sim_time="true")
    proc = ChildProcess("driver", command_line(desc, tmp_path))
    try:
        # a lifecycle node's own service, seen in the middleware's DEBUG log: both arguments took effect
        line = proc.wait_line(r"fbg_accel_driver/get_state", timeout=60)
    finally:
        rc = proc.stop()
    assert line.startswith("[DEBUG]"), line
    assert proc.find(r"reading \S+ at") is None, "an unconfigured managed driver opened the port"
    assert rc == 0 and "Traceback" not in proc.output(), proc.output()[-3000:]


def test_sim_launch_driver_reads_the_simulated_board(tmp_path: Path) -> None:
    link = str(tmp_path / "board")
    procs = _start_all(descriptions("sim.launch.py", link=link), tmp_path)
    try:
        line = procs[1].wait_line(r"serial link up", timeout=60)
    finally:
        rcs = _stop_all(procs)
    assert f"serial link up: {link}" in line, line
    assert rcs == [0, 0], (rcs, procs[0].output(), procs[1].output())


def test_sim_launch_ctrl_c_ends_without_an_error(tmp_path: Path) -> None:
    """Ctrl-C of ``ros2 launch ... sim.launch.py`` signals board_sim and the driver together, and board_sim's pty
    closes before the driver has acted on its signal. Here in the latest order that can happen: the driver is
    signalled only once board_sim has exited. The driver says the link closed at shutdown (INFO), not that it
    was lost (ERROR)."""
    link = str(tmp_path / "board")
    procs = _start_all(descriptions("sim.launch.py", link=link), tmp_path)
    try:
        procs[1].wait_line(r"serial link up", timeout=60)
        procs[0].proc.send_signal(signal.SIGINT)
        board_rc = procs[0].wait_exit(timeout=30)
    finally:
        rcs = _stop_all(procs)
    out = procs[1].output()
    assert board_rc == 0 and rcs == [0, 0], (rcs, procs[0].output(), out)
    assert not [ln for ln in out.splitlines() if ln.startswith("[ERROR]")], out
    assert "Traceback" not in out and "serial link closed at shutdown" in out, out
