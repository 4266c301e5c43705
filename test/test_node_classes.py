"""The node classes in-process (issue 12): imported directly, built in a private rclpy context with
parameter overrides, checked through rclpy's own view of them (declared parameters and descriptors,
publishers, subscriptions, services, lifecycle transitions) and destroyed. No process, no board: the
driver's port is a path where nothing answers (its reader thread retries with back-off until closed).
The process tests (test_driver_process, test_calibration_node_process, ...) cover the running data path."""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rcl_interfaces.msg import ParameterType
from rclpy.context import Context
from rclpy.lifecycle import LifecyclePublisher, TransitionCallbackReturn
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy

from fbg_accel_calibration.recorder import calibration_node, calibration_parameters
from fbg_accel_calibration.recorder.calibration_node import CalibrationNode
from fbg_accel_driver import driver_node, driver_parameters
from fbg_accel_driver.command_line import StartupError
from fbg_accel_driver.driver_node import DriverNode, ManagedDriverNode

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)

REPO = Path(__file__).resolve().parents[1]
DATA_TOPICS = {"/imu/data_raw", "/imu/temperature", "/imu/raw"}
PLAN = REPO / "config" / "pose_plan_six_position.yaml"
TYPE_CODES = {"string": ParameterType.PARAMETER_STRING, "integer": ParameterType.PARAMETER_INTEGER,
              "double": ParameterType.PARAMETER_DOUBLE, "bool": ParameterType.PARAMETER_BOOL,
              "string_array": ParameterType.PARAMETER_STRING_ARRAY, "double_array": ParameterType.PARAMETER_DOUBLE_ARRAY}


def overrides(**values: Any) -> list[Parameter]:
    return [Parameter(name, value=value) for name, value in values.items()]


@pytest.fixture
def port(tmp_path: Path) -> str:
    return str(tmp_path / "no_board_here")


def built_or_refused(make: Callable[[], Node], built: list[Any], ros: Context, name: str) -> Any:
    """``make()``'s node, kept in ``built`` for the fixture to end. A node whose constructor raised (a refused
    parameter) must already have left ``ros``'s graph when the refusal reaches the caller, while the exception (whose
    frames hold the half-built node) is still held: rclpy made it (parameter services, a rosout publisher, perhaps a
    reader thread) before the refusal. Left to the garbage collector, it was destroyed whenever the exception went,
    in a process after its context had shut down, where Fast DDS could hang (a refused ``calibration`` process that
    printed its error and never exited)."""
    before = len(nodes_left(ros, name))  # the nodes of this name built earlier in the test and still alive
    try:
        node = make()
    except Exception:
        assert len(nodes_left(ros, name)) == before, f"a refused {name} node is still in the graph"
        raise
    built.append(node)
    return node


def nodes_left(ros: Context, name: str) -> list[str]:
    """The nodes ``/name`` (the root namespace, where these tests build them) still in ``ros``'s graph: this
    process's own nodes are in it at once; the run's DDS domain is its own (scripts/test.sh, conftest.py)."""
    probe = Node("nodes_left_probe", context=ros)
    try:
        return [f"{ns}{n}" for n, ns in probe.get_node_names_and_namespaces() if (n, ns) == (name, "/")]
    finally:
        probe.destroy_node()


@pytest.fixture
def make_driver(ros: Context, port: str) -> Iterator[Any]:
    """Build a driver node class with overrides (port: nowhere); every node built, also one whose constructor
    raised, is closed and destroyed: none is left logging or answering after its test."""
    built: list[DriverNode] = []

    def make(cls: type[DriverNode] = DriverNode, **values: Any) -> DriverNode:
        return built_or_refused(lambda: cls(context=ros, parameter_overrides=overrides(**({"port": port} | values))),
                                built, ros, driver_node.NODE_NAME)

    yield make
    for node in built:
        if getattr(node, "link", None) is not None:
            node.close()
        node.destroy_node()
    assert not nodes_left(ros, driver_node.NODE_NAME)


def publishers(node: Node) -> dict[str, Any]:
    return {p.topic_name: p for p in node.publishers}


# ----------------------------------------------------------------------------- driver
def test_driver_declares_every_parameter_with_its_default_and_descriptor(make_driver: Any, port: str) -> None:
    node = make_driver(calibration_file="sim")
    for name, (typ, default, desc) in driver_parameters.PARAMETERS.items():
        expected = {"port": port, "calibration_file": "sim"}.get(name, default)
        assert node.get_parameter(name).value == expected, name
        d = node.describe_parameter(name)
        assert (d.description, d.type) == (desc, TYPE_CODES[typ]), name
        assert d.read_only is (name not in driver_parameters.RUNTIME_PARAMETERS), name
    decimation = node.describe_parameter("decimation").integer_range[0]
    assert (decimation.from_value, decimation.to_value, decimation.step) == (1, 10000, 1)
    assert node.describe_parameter("covariance_source").additional_constraints == "one of calibration, parameter, unknown"
    # the values reached the core and the link
    assert node.core is not None and node.core.config.decimation == 1
    assert node.link is not None and node.cal_info["calibration_file"] == str(driver_parameters.default_calibration_path())


def test_driver_publishes_the_data_topics_with_the_system_default_reliable_qos(make_driver: Any) -> None:
    pubs = publishers(make_driver(calibration_file="sim"))
    assert DATA_TOPICS | {"/diagnostics"} <= set(pubs)
    for topic in DATA_TOPICS:
        qos = pubs[topic].qos_profile
        assert (qos.reliability, qos.durability, qos.history, qos.depth) == (
            ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE, HistoryPolicy.KEEP_LAST, 100), topic
    # per-topic QoS overrides are declared for the data topics, not for /diagnostics
    names = {n for n in make_driver(calibration_file="none")._parameters if n.startswith("qos_overrides.")}
    assert "qos_overrides./imu/raw.publisher.reliability" in names
    assert not any(n.startswith("qos_overrides./diagnostics.") for n in names)


@pytest.mark.parametrize("cls", [DriverNode, ManagedDriverNode])
def test_a_qos_override_applies_to_its_own_topic_only(make_driver: Any, cls: type[DriverNode]) -> None:
    """docs/topics.md's own example: ``qos_overrides./imu/data_raw.publisher: {reliability: best_effort, depth: 5}``
    changes imu/data_raw, not imu/temperature nor imu/raw (what a loss-free calibration recorder needs reliable), nor
    the next driver built in the process, nor the same node's next configure. Before, rclpy applied the override to
    the one profile object every data publisher was given: imu/temperature and imu/raw, created after imu/data_raw,
    were best effort with depth 5 too, and so was every driver created later in the process."""
    given = {"qos_overrides./imu/data_raw.publisher.reliability": "best_effort",
             "qos_overrides./imu/data_raw.publisher.depth": 5}
    node = make_driver(cls, calibration_file="sim", **given)
    if cls is ManagedDriverNode:
        assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    for _ in range(2):  # managed: also after cleanup and a new configure
        pubs = publishers(node)
        assert (pubs["/imu/data_raw"].qos_profile.reliability, pubs["/imu/data_raw"].qos_profile.depth) == (
            ReliabilityPolicy.BEST_EFFORT, 5)
        for topic in ("/imu/temperature", "/imu/raw"):
            qos = pubs[topic].qos_profile
            assert (qos.reliability, qos.depth) == (ReliabilityPolicy.RELIABLE, 100), topic
        if cls is DriverNode:
            break
        assert node.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
        assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    later = make_driver(calibration_file="sim")  # another driver in the same process, without overrides
    for topic in DATA_TOPICS:
        qos = publishers(later)[topic].qos_profile
        assert (qos.reliability, qos.depth) == (ReliabilityPolicy.RELIABLE, 100), topic


def test_driver_without_calibration_publishes_raw_and_temperature_only(make_driver: Any) -> None:
    node = make_driver(calibration_file="none")
    assert DATA_TOPICS - set(publishers(node)) == {"/imu/data_raw"}
    assert node.calibration is None and node.cal_info["sensor_id"] == "uncalibrated"


def test_calibration_node_recording_failure_ends_with_status_recording_failed(make_calibration: Any,
                                                                             tmp_path: Path) -> None:
    """The output directory removed during the run: the node said "fit failed ...; the recording is kept"
    (status 1) or "done"; a failed recording is status 4, whatever the sequencer reached."""
    node = make_calibration(output_dir=str(tmp_path / "out"))
    assert node.mcap_path.is_file()
    shutil.rmtree(tmp_path / "out")
    assert node.finish() == calibration_parameters.EXIT_RECORDING_FAILED
    assert "ENOENT" in node.recorder.write_error and not node.yaml_path.exists()


@pytest.mark.parametrize(("values", "message"), [
    ({"calibration_file": ""}, "parameter 'calibration_file' is required: the sensor's calibration YAML, 'sim'"),
    ({"calibration_file": "  "}, "parameter 'calibration_file' is required"),
    ({"calibration_file": "sim", "decimation": 0}, "invalid parameter 'decimation': "),
    ({"calibration_file": "sim", "baud": "fast"}, "invalid parameter 'baud': "),
    ({"calibration_file": "sim", "frame_id": "/base"}, "invalid parameter 'frame_id': '/base' (non-empty, no leading '/'"),
    ({"calibration_file": "sim", "port": ""}, "invalid parameter 'port': empty"),
    ({"calibration_file": "sim", "chain_compensation": "magic"}, "invalid parameter 'chain_compensation': 'magic'"),
    ({"calibration_file": "sim", "calibraton_file": "x"},
     "unknown parameter 'calibraton_file' (did you mean 'calibration_file'?) (driver --help lists the parameters)"),
])
def test_driver_refuses_a_bad_parameter_with_one_clear_message(make_driver: Any, values: dict[str, Any],
                                                              message: str) -> None:
    with pytest.raises(StartupError) as err:
        make_driver(**values)
    assert message in str(err.value)


@pytest.mark.parametrize("values", [
    {"calibraton_file": "sim"},  # docs/topics.md's own example: the required parameter given under a misspelt name
    {"calibraton_file": "sim", "calibration_file": "nowhere.yaml"},
])
def test_driver_names_a_misspelt_parameter_before_the_errors_it_causes(make_driver: Any, values: dict[str, Any]) -> None:
    """A misspelt name is what the user must fix; the errors it causes (the parameter it was meant to set is then
    missing or keeps its default) must not hide it. Before: ``-p calibraton_file:=sim`` alone was refused with
    "parameter 'calibration_file' is required", which the user had just given (docs/topics.md promises the nearest
    valid name); given beside a calibration_file that does not load, the load's error came instead. The unknown-name
    check ran only after the calibration was loaded and the publishers created."""
    with pytest.raises(StartupError) as err:
        make_driver(**values)
    assert str(err.value).startswith("unknown parameter 'calibraton_file' (did you mean 'calibration_file'?)"), err.value


def test_driver_refuses_a_missing_calibration_file(make_driver: Any, tmp_path: Path) -> None:
    missing = tmp_path / "nowhere.yaml"
    with pytest.raises(StartupError, match="calibration file rejected: ") as err:
        make_driver(calibration_file=str(missing))
    assert str(missing) in str(err.value)


def test_driver_runtime_parameters_reach_the_core_and_read_only_ones_are_refused(make_driver: Any) -> None:
    node = make_driver(calibration_file="sim")
    assert node.set_parameters(overrides(decimation=10))[0].successful
    assert node.core.config.decimation == 10
    assert not node.set_parameters(overrides(port="/dev/null"))[0].successful
    refused = node.set_parameters(overrides(out_of_range_variance_factor=0.5))[0]
    assert not refused.successful and node.core.config.out_of_range_variance_factor == 10.0


def test_managed_driver_publishes_only_after_configure_and_activate(make_driver: Any) -> None:
    node = make_driver(ManagedDriverNode, calibration_file="sim")
    assert isinstance(node, ManagedDriverNode) and node.link is None
    assert not DATA_TOPICS & set(publishers(node))
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    pubs = publishers(node)
    assert all(isinstance(pubs[t], LifecyclePublisher) and not pubs[t].is_activated for t in DATA_TOPICS)
    assert node.link is not None and node._publishing is False  # frames decoded and diagnosed, not published
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    assert node._publishing is True and all(pubs[t].is_activated for t in DATA_TOPICS)
    assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    assert node._publishing is False and not any(pubs[t].is_activated for t in DATA_TOPICS)
    assert node.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
    assert node.link is None and not DATA_TOPICS & set(publishers(node))


def test_managed_driver_configure_fails_cleanly_on_a_bad_parameter(make_driver: Any) -> None:
    node = make_driver(ManagedDriverNode, calibration_file="")  # construction succeeds: configure reads it
    assert node.trigger_configure() == TransitionCallbackReturn.FAILURE
    assert node.link is None and not DATA_TOPICS & set(publishers(node))
    # back in unconfigured (configure is only a transition from there): it fails again, for the same reason
    assert node.trigger_configure() == TransitionCallbackReturn.FAILURE


@pytest.mark.parametrize(("name", "value"), [
    ("qos_overrides./imu/raw.publisher.reliability", "bogus"),
    ("qos_overrides./imu/data_raw.publisher.depth", -1),
    ("qos_overrides./imu/temperature.publisher.history", "keep_everything"),
])
def test_driver_refuses_a_bad_qos_override_with_one_clear_message(make_driver: Any, name: str, value: Any) -> None:
    """docs/topics.md: the data topics' QoS is overridden by the ``qos_overrides`` parameters, and an invalid
    parameter stops start-up with one line naming it (exit status 2). Before, a value rclpy cannot apply ended the
    plain driver with a traceback and exit status 1 (``RuntimeError: Unexpected QoS override ...``; for a negative
    depth ``RCLError: ... failed setting topic QoS``, naming neither the parameter nor the topic)."""
    with pytest.raises(StartupError) as err:
        make_driver(calibration_file="sim", **{name: value})
    topic = name.split(".")[1]
    assert f"invalid QoS override for {topic}" in str(err.value) and "qos_overrides" in str(err.value), err.value


@pytest.mark.parametrize("values", [
    # a misspelt qos_overrides name is refused after the publishers are created (they declare those parameters;
    # a misspelt plain name, the case here before, is now refused before anything is created)
    {"qos_overrides./imu/raw.publisher.reliablity": "best_effort"},
    {"qos_overrides./imu/raw.publisher.reliability": "bogus"},  # refused while creating them
])
def test_managed_driver_configure_that_fails_late_leaves_nothing_behind(make_driver: Any, values: dict[str, Any]) -> None:
    """A configure refused after the first publishers exist returns FAILURE and leaves the node as unconfigured as
    before: no publisher, no reader. Before, a misspelt parameter left the four publishers in place (unactivated, but
    advertised: subscribers matched a node that would never publish) and each retry added four more; a bad QoS
    override returned ERROR with the publishers created before it left in place."""
    node = make_driver(ManagedDriverNode, calibration_file="sim", **values)
    for _ in range(2):  # configure may be retried from unconfigured: it fails again, leaving nothing either
        assert node.trigger_configure() == TransitionCallbackReturn.FAILURE
        assert node.link is None and node.core is None
        assert not (DATA_TOPICS | {"/diagnostics"}) & set(publishers(node)), set(publishers(node))


# ----------------------------------------------------------------------------- calibration
@pytest.fixture
def make_calibration(ros: Context, tmp_path: Path) -> Iterator[Any]:
    built: list[CalibrationNode] = []

    def make(remaps: tuple[str, ...] = (), **values: Any) -> CalibrationNode:
        """The node with parameter ``values`` and the command line's topic ``remaps`` (``-r from:=to``)."""
        base = {"plan_file": str(PLAN), "output_dir": str(tmp_path), "run_label": "inproc", "progress": False}
        args = {"cli_args": ["--ros-args", *[a for r in remaps for a in ("-r", r)]]} if remaps else {}
        return built_or_refused(lambda: CalibrationNode(context=ros, parameter_overrides=overrides(**(base | values)),
                                                        **args), built, ros, calibration_node.NODE_NAME)

    yield make
    for node in built:
        recorder = getattr(node, "recorder", None)
        if recorder is not None and not recorder.finished:
            recorder.abort("test over")
            node.finish()
        node.destroy_node()
    assert not nodes_left(ros, calibration_node.NODE_NAME)


def test_calibration_node_declares_its_parameters_and_subscribes_best_effort(make_calibration: Any,
                                                                            tmp_path: Path) -> None:
    node = make_calibration(temperature_level=0)
    given = {"plan_file": str(PLAN), "output_dir": str(tmp_path), "run_label": "inproc", "progress": False,
             "temperature_level": 0}
    for name, (typ, default, _desc) in calibration_parameters.PARAMETERS.items():
        assert node.p[name] == given.get(name, default), name  # None: declared by type only, unset
        d = node.describe_parameter(name)
        assert d.read_only and d.type == TYPE_CODES[typ], name
    subs = {s.topic_name: s.qos_profile for s in node.subscriptions}
    for topic in ("/imu/raw", "/imu/temperature"):
        assert (subs[topic].reliability, subs[topic].depth) == (ReliabilityPolicy.BEST_EFFORT, 2000), topic
    assert {"/calibration/next_pose", "/calibration/abort"} <= {s.service_name for s in node.services}
    assert node.mcap_path == tmp_path / "inproc.mcap" and node.mcap_path.is_file()
    assert node.yaml_path == tmp_path / "inproc_calibration.yaml"
    assert node.setpoint_c == node.plan.level_setpoint_c(0) and not node.dynamic


def test_calibration_node_aborted_run_closes_its_recording_with_status_interrupted(make_calibration: Any) -> None:
    node = make_calibration()
    node.recorder.abort("in-process test")
    assert node.finish() == calibration_parameters.EXIT_INTERRUPTED
    assert node.mcap_path.read_bytes()[-8:] == b"\x89MCAP0\r\n"  # footer magic: a complete file
    assert not node.yaml_path.exists()


@pytest.mark.parametrize(("values", "message"), [
    ({"plan_file": ""}, "parameter 'plan_file' is required"),
    ({"fit_degree": 9}, "invalid parameter 'fit_degree': 9 (-1 for auto, or 0..6)"),
    ({"mode": "manual"}, "invalid parameter 'mode': 'manual' (auto or service)"),
    ({"still_hold_s": 0.0}, "invalid parameter 'still_hold_s': 0.0 (must be > 0)"),
    ({"fit": "yes"}, "invalid parameter 'fit': "),
    ({"run_label": "a/b"}, "invalid parameter 'run_label': 'a/b'"),
    ({"plan_file": "/etc/hostname"}, "pose plan rejected"),
    ({"still_window_s": -1.0}, "invalid parameter 'still_window_s'"),
    ({"fit_degre": 2}, "unknown parameter 'fit_degre' (did you mean 'fit_degree'?)"),
    ({"run_to_run_from": "/nonexistent/r2r.yaml"},
     "invalid parameter 'run_to_run_from': run_to_run_from: /nonexistent/r2r.yaml: calibration file not found"),
    ({"sensor_id": "acc\x1b[31m4\nforged"}, "invalid parameter 'sensor_id': sensor id 'acc\\x1b[31m4\\nforged' holds "
                                              "control characters"),
])
def test_calibration_node_refuses_a_bad_parameter_with_one_clear_message(make_calibration: Any, values: dict[str, Any],
                                                                        message: str, tmp_path: Path) -> None:
    with pytest.raises(StartupError) as err:
        make_calibration(**values)
    assert message in str(err.value)
    if "run_label" not in values:  # refused before the recording is created
        assert not any(tmp_path.glob("*.mcap"))


@pytest.mark.parametrize(("remaps", "message"), [
    (("imu/raw:=/acc_b/imu/raw",), "imu/temperature resolves to /imu/temperature"),
    (("imu/raw:=/acc_b/raw_counts", "imu/temperature:=/acc_b/temperature"), "imu/raw resolves to /acc_b/raw_counts"),
], ids=["one-topic-moved", "raw-renamed"])
def test_calibration_node_refuses_remaps_the_recording_cannot_name(make_calibration: Any, remaps: tuple[str, ...],
                                                                  message: str, tmp_path: Path) -> None:
    """A recording names its topics ``<namespace>/imu/raw``, ``<namespace>/imu/temperature``, ... (the fit finds a
    run's topics by that namespace). A node whose two subscriptions resolve into different namespaces, or to a raw
    topic not named ``imu/raw``, cannot write what it records under the names it recorded: on the unchanged code it
    started and wrote /acc_b's messages as /imu/raw (the names of its own namespace: test_two_sensors_process.py)."""
    with pytest.raises(StartupError) as err:
        make_calibration(remaps=remaps)
    assert message in str(err.value)
    assert not any(tmp_path.glob("*.mcap")), "no recording may be started on bad input"


def test_calibration_node_never_overwrites_a_recording(make_calibration: Any, tmp_path: Path) -> None:
    (tmp_path / "taken.mcap").write_bytes(b"earlier run")
    with pytest.raises(StartupError, match=r"taken\.mcap exists; choose another run_label"):
        make_calibration(run_label="taken")
    assert (tmp_path / "taken.mcap").read_bytes() == b"earlier run"


def test_calibration_node_never_records_through_a_dangling_link(make_calibration: Any, tmp_path: Path) -> None:
    """A dangling link at the recording's name is a name taken: the never-overwrite check followed it and the recording
    was written outside output_dir. Refused by that check, before any file is opened (the exclusive open behind it,
    which refuses a link too, is test_output_safety.py's)."""
    outside = tmp_path / "outside"
    outside.mkdir()
    (tmp_path / "keep.mcap").symlink_to(outside / "victim.mcap")
    with pytest.raises(StartupError, match=r"keep\.mcap exists; choose another run_label"):
        make_calibration(run_label="keep")
    assert not (outside / "victim.mcap").exists() and (tmp_path / "keep.mcap").is_symlink()


def test_calibration_node_never_writes_its_calibration_over_a_recording_or_an_existing_file(
        make_calibration: Any, tmp_path: Path) -> None:
    """Issue 42, item 1: ``-p fit_with:=[prev.mcap] -p calibration_file:=prev.mcap`` ended with "calibration
    written to prev.mcap" (a 1.5 MB recording became a 5 KB YAML); so did calibration_file naming the run's own
    MCAP, and an existing file was replaced without asking. All three are refused before anything is recorded."""
    prev = tmp_path / "prev.mcap"
    prev.write_bytes(b"an earlier level's recording")
    old = tmp_path / "old.yaml"
    old.write_text("an earlier calibration")
    cases = [({"fit_with": [str(prev)], "calibration_file": str(prev)}, "output is the input file"),
             ({"fit_with": [str(tmp_path / "p*.mcap")], "calibration_file": str(tmp_path / "." / "prev.mcap")},
              "output is the input file"),
             ({"calibration_file": str(tmp_path / "inproc.mcap")}, "output is the input file"),
             ({"calibration_file": str(old)}, "exists; set force:=true to replace it"),
             ({"calibration_file": str(tmp_path / "nodir" / "c.yaml")}, "does not exist")]
    for values, message in cases:
        with pytest.raises(StartupError) as err:
            make_calibration(**values)
        assert "invalid parameter 'calibration_file'" in str(err.value) and message in str(err.value), str(err.value)
        assert not (tmp_path / "inproc.mcap").exists()
    assert prev.read_bytes() == b"an earlier level's recording" and old.read_text() == "an earlier calibration"
    with pytest.raises(StartupError, match=r"invalid parameter 'fit_with': .*matches no file"):
        make_calibration(fit_with=[str(tmp_path / "none*.mcap")])  # found at start-up, not after the run
    node = make_calibration(calibration_file=str(old), force=True)  # accepted with force
    assert node.yaml_path == old
    dynamic = make_calibration(plan_file=str(REPO / "config" / "excitation_plan_stepped_sine.yaml"), run_label="dyn",
                               calibration_file=str(prev))  # a dynamic run writes no calibration: nothing to refuse
    assert dynamic.dynamic


def test_calibration_node_reads_run_to_run_from_at_start_up_and_refuses_a_file_that_cannot_give_r(
        make_calibration: Any, tmp_path: Path) -> None:
    """``run_to_run_from`` is read when the node starts, not by the end-of-run fit after the recording: a file without
    R, that is no calibration, or of another sensor stops start-up in one line before the recording is created; a
    good one is kept (its R, name and hash) for the end-of-run fit."""
    from test_driver_core import make_cal

    from fbg_accel_driver.slow_error import SlowErrorSection

    R = np.diag([1e-3, 2e-3, 3e-3])
    make_cal(sensor_id="SN-A", slow_error=SlowErrorSection(2 * R, "test", 30, R)).save(tmp_path / "with_r.yaml")
    make_cal(sensor_id="SN-A", slow_error=SlowErrorSection(2 * R, "test", 30)).save(tmp_path / "no_r.yaml")
    make_cal(sensor_id="SN-A").save(tmp_path / "no_section.yaml")
    cases = [({"run_to_run_from": str(tmp_path / "no_r.yaml")}, "no run-to-run component in its slow_error"),
             ({"run_to_run_from": str(tmp_path / "no_section.yaml")}, "no slow_error section"),
             ({"run_to_run_from": str(tmp_path)}, "a directory, not a calibration file"),
             ({"run_to_run_from": str(tmp_path / "with_r.yaml"), "sensor_id": "SN-B"},
              "is a calibration of sensor 'SN-A', this campaign is of sensor 'SN-B'")]
    for values, message in cases:
        with pytest.raises(StartupError) as err:
            make_calibration(**values)
        msg = str(err.value)
        assert msg.startswith("invalid parameter 'run_to_run_from': ") and message in msg and "\n" not in msg, msg
        assert not (tmp_path / "inproc.mcap").exists()
    for sensor in ("SN-A", "unknown"):  # unknown: the match cannot be checked, R is used (with a warning)
        node = make_calibration(run_to_run_from=str(tmp_path / "with_r.yaml"), sensor_id=sensor, run_label=sensor)
        assert node.run_to_run.matrix.tolist() == R.tolist() and node.run_to_run.source.startswith("with_r.yaml (")
    assert make_calibration(run_label="off").run_to_run is None  # default: none


def test_calibration_node_end_of_run_fit_carries_the_run_to_run_component(make_calibration: Any,
                                                                           tmp_path: Path) -> None:
    """A complete run with ``fit_with`` an earlier level (one run per level, degree 1: b(T) takes up each run's
    constant and R is not identified) and
    ``run_to_run_from``: the node's own fit writes the carried R and names its file. Before, the node had no such
    parameter and its fit wrote "not identified" (and a slow error without R)."""
    import yaml
    from test_driver_core import make_cal
    from test_run_recorder import _recorded_run, _samples

    from fbg_accel_calibration.recorder.pose_plan import PosePlan
    from fbg_accel_driver.slow_error import SlowErrorSection
    from fbg_accel_driver.thermal_model import ThermalCalibration

    R = np.diag([1e-3, 2e-3, 3e-3])
    make_cal(sensor_id="t", slow_error=SlowErrorSection(2 * R, "test", 30, R)).save(tmp_path / "earlier.yaml")
    earlier_level = _recorded_run(tmp_path, "L1", 30.0, 2)  # five of the poses at another temperature
    plan = {"format": "fbg_accel_pose_plan", "format_version": 1, "name": "r2r", "dwell_s": 1.5, "move_s": 0.6,
            "samples_per_pose": 40,
            "poses": [{"name": "z_up", "psi_deg": 0, "theta_deg": 0, "dwell_s": 2.5},
                      {"name": "z_down", "psi_deg": 0, "theta_deg": 180},
                      {"name": "x_up", "psi_deg": 90, "theta_deg": 90}, {"name": "y_up", "psi_deg": 0, "theta_deg": 90},
                      {"name": "x_down", "psi_deg": 270, "theta_deg": 90},
                      {"name": "y_down", "psi_deg": 180, "theta_deg": 90}]}
    (tmp_path / "plan.yaml").write_text(yaml.safe_dump(plan))
    node = make_calibration(plan_file=str(tmp_path / "plan.yaml"), mode="auto", sensor_id="t", fit_degree=1,
                            noise_learn_s=1.0, still_hold_s=0.5, fit_with=[str(earlier_level)],
                            run_to_run_from=str(tmp_path / "earlier.yaml"))
    for sample, _ in _samples(PosePlan.load(tmp_path / "plan.yaml"), seed=1, temp_c=20.0):
        node.recorder.on_raw(sample)
    assert node.recorder.done
    assert node.finish() == calibration_parameters.EXIT_OK
    slow = ThermalCalibration.load(node.yaml_path).slow_error
    assert slow.run_to_run.tolist() == R.tolist()
    assert "plus the run-to-run component carried from earlier.yaml (created " in slow.method


def test_refit_refuses_an_input_or_an_existing_output_at_the_end_of_the_run(tmp_path: Path) -> None:
    """The end-of-run fit checks again (a file may have appeared during the run)."""
    from fbg_accel_calibration.io.atomic_output import OutputError
    from fbg_accel_calibration.recorder.run_refit import refit

    run = tmp_path / "run.mcap"
    run.write_bytes(b"recording")
    late = tmp_path / "late.yaml"
    late.write_text("appeared during the run")
    for out, message in ((run, "output is the input file"), (late, "exists")):
        with pytest.raises(OutputError, match=message):
            refit([str(run)], out)
    assert run.read_bytes() == b"recording" and late.read_text() == "appeared during the run"


HOSTILE_BY_TYPE: dict[str, list[Any]] = {
    "string": ["", "acc\x1b[31m4", "a\nb", "x" * 5000, "/dev/zero", "{dir}", "../../x", "\x00"],
    "integer": [-1, -(2**62), 2**62, 7],
    "double": [float("nan"), float("inf"), -1.0, 0.0, 1e300, 5e-324],
    "bool": ["yes", 1],
    "string_array": [["", "/dev/zero"], ["{dir}"], ["x" * 5000], ["*"]],
    "double_array": [[float("nan")] * 3, [1.0], [-1.0, 0.0, 1e300], []],
}


def test_calibration_node_parameters_hostile_values_start_or_refuse_in_one_line(monkeypatch: pytest.MonkeyPatch,
                                                                               make_calibration: Any,
                                                                               tmp_path: Path) -> None:
    """Issue 42: the hostile-input property of the tools, for the node's parameters: every value of every parameter
    either starts the node or is a StartupError of one line that shows no control character raw."""
    work = tmp_path / "w1" / "w2"  # relative names (output_dir "a\nb", "../../x") land under tmp_path
    work.mkdir(parents=True)
    monkeypatch.chdir(work)
    n = 0
    for name, (typ, _default, _desc) in calibration_parameters.PARAMETERS.items():
        for value in HOSTILE_BY_TYPE[typ]:
            n += 1
            if isinstance(value, str):
                value = value.replace("{dir}", str(tmp_path))
            elif isinstance(value, list):
                value = [v.replace("{dir}", str(tmp_path)) if isinstance(v, str) else v for v in value]
            if typ == "double_array" and not value:
                continue  # rclpy cannot type an empty list
            values = {"run_label": f"h{n}", name: value} if name != "run_label" else {name: value}
            try:
                node = make_calibration(**values)
            except StartupError as exc:
                msg = str(exc)
                assert "\n" not in msg and not any(c in msg for c in "\x1b\x00"), (name, value, msg)
                continue
            assert node.recorder is not None, (name, value)
