"""Pose plan loader: valid plans give the right reference vectors, every bad input one clear error."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from fbg_accel_calibration.io.table_geometry import STANDARD_GRAVITY, table_specific_force
from fbg_accel_calibration.recorder.pose_plan import PosePlan, PosePlanError
from fbg_accel_calibration.recorder.pose_recorder import DetectorSettings

CONFIG = Path(__file__).resolve().parents[1] / "config"


def _plan(**over) -> dict:
    d = {"name": "t", "dwell_s": 2.0, "samples_per_pose": 10,
         "poses": [{"name": "a", "psi_deg": 0, "theta_deg": 0}, {"name": "b", "psi_deg": 90, "theta_deg": 90}]}
    d.update(over)
    return d


def test_six_position_plan_is_the_papers_six_axis_poses():
    plan = PosePlan.load(CONFIG / "pose_plan_six_position.yaml")
    g = plan.local_g_mps2
    expected = {"z_down": (0, 0, -g), "z_up": (0, 0, g), "x_down": (-g, 0, 0), "x_up": (g, 0, 0),
                "y_down": (0, -g, 0), "y_up": (0, g, 0)}
    assert [p.name for p in plan.poses] == list(expected)
    for p in plan.poses:
        np.testing.assert_allclose(p.gref_mps2, expected[p.name], atol=1e-9)
        assert p.samples == 100
    assert plan.chamber is not None and plan.chamber.levels_c == (16.0, 24.0, 45.0)
    assert plan.level_setpoint_c(2) == 45.0 and plan.level_setpoint_c(-1) is None


def test_sim_e2e_plan_loads_and_spans_all_directions():
    plan = PosePlan.load(Path(__file__).resolve().parent / "fixtures" / "pose_plan_sim_e2e.yaml")
    assert len(plan) == 6
    assert plan.chamber is not None and len(plan.chamber.levels_c) == 3
    # the first dwell covers the node's start-up (learning + window + hold + samples), the others window + hold +
    # 200 samples at the test's 100 Hz
    d = DetectorSettings()
    assert plan.poses[0].dwell_s >= d.learn_s + d.window_s + d.hold_s + 2.0
    assert min(p.dwell_s for p in plan.poses) >= d.window_s + d.hold_s + 2.0
    # every axis sees both signs of gravity, so M and b are identified
    g = plan.gref_mps2
    assert np.all(g.max(axis=0) > 0.9 * plan.local_g_mps2) and np.all(g.min(axis=0) < -0.9 * plan.local_g_mps2)


def test_angles_follow_the_table_convention_and_gref_is_taken_as_given():
    d = _plan(local_g_mps2=9.79, poses=[{"psi_deg": 30, "theta_deg": 60}, {"gref_mps2": [0.0, 0.0, -9.79], "dwell_s": 5,
                                                                              "samples": 3}])
    plan = PosePlan.from_dict(d)
    np.testing.assert_allclose(plan.poses[0].gref_mps2, table_specific_force([30], [60], 9.79)[0])
    np.testing.assert_allclose(plan.poses[1].gref_mps2, [0, 0, -9.79])
    assert plan.poses[0].name == "pose_0" and plan.poses[0].dwell_s == 2.0 and plan.poses[0].samples == 10
    assert plan.poses[1].dwell_s == 5.0 and plan.poses[1].samples == 3
    assert plan.total_samples == 13
    # metadata form round-trips to the same plan
    again = PosePlan.from_dict(yaml.safe_load(plan.to_yaml()))
    np.testing.assert_allclose(again.gref_mps2, plan.gref_mps2)


def test_defaults():
    plan = PosePlan.from_dict({"dwell_s": 1, "poses": [{"psi_deg": 0, "theta_deg": 0}]})
    assert plan.local_g_mps2 == STANDARD_GRAVITY and plan.poses[0].samples == 100 and plan.chamber is None


@pytest.mark.parametrize(
    ("change", "fragment"),
    [
        ({"poses": []}, "'poses' must be a non-empty list"),
        ({"poses": "z"}, "'poses' must be a non-empty list"),
        ({"dwell_s": -1}, "dwell_s must be > 0"),
        ({"dwell_s": None}, "dwell_s must be a number"),
        ({"samples_per_pose": 0}, "samples_per_pose must be a positive integer"),
        ({"samples_per_pose": 2.5}, "samples_per_pose must be a positive integer"),
        ({"local_g_mps2": 1.0}, "is it in m/s^2"),
        ({"local_g_mps2": float("nan")}, "local_g_mps2 must be finite"),
        ({"dwel_s": 3}, "unknown key(s) ['dwel_s']"),
        ({"format": "other"}, "format is 'other'"),
        ({"format_version": 9}, "format_version 9 is not supported"),
        ({"poses": [{"psi_deg": 0}]}, "need both psi_deg and theta_deg"),
        ({"poses": [{"name": "p"}]}, "needs table angles psi_deg/theta_deg or a reference gref_mps2"),
        ({"poses": [{"psi_deg": 0, "theta_deg": 0, "gref_mps2": [0, 0, 9.8]}]}, "either psi_deg/theta_deg or gref_mps2"),
        ({"poses": [{"gref_mps2": [0, 0, 1]}]}, "values must be in m/s^2"),
        ({"poses": [{"gref_mps2": [0, 9.8]}]}, "list of 3 numbers"),
        ({"poses": [{"gref_mps2": [0, "a", 9.8]}]}, "gref_mps2[1] must be a number"),
        ({"poses": [{"psi_deg": "x", "theta_deg": 0}]}, "psi_deg must be a number"),
        ({"poses": [{"name": "a", "psi_deg": 0, "theta_deg": 0}, {"name": "a", "psi_deg": 0, "theta_deg": 180}]},
         "duplicate pose name 'a'"),
        ({"poses": [{"psi_deg": 0, "theta_deg": 0, "samples": -3}]}, "samples must be a positive integer"),
        ({"poses": [{"psi_deg": 0, "theta_deg": 0, "colour": 1}]}, "unknown key(s) ['colour']"),
        ({"poses": [7]}, "poses[0] is not a mapping"),
        ({"chamber": {"levels_c": []}}, "levels_c must be a non-empty list"),
        ({"chamber": {"levels_c": [300]}}, "is it in degC"),
        ({"chamber": {"levels_c": [20], "soak_s": -1}}, "soak_s must be >= 0"),
        ({"chamber": {"levels_c": [20], "setpoint": 1}}, "unknown key(s) ['setpoint']"),
        ({"chamber": [20]}, "chamber is not a mapping"),
    ],
)
def test_bad_plans_are_refused_with_a_message_naming_the_problem(change, fragment):
    with pytest.raises(PosePlanError) as err:
        PosePlan.from_dict(_plan(**change), source="plan.yaml")
    assert fragment in str(err.value)
    assert str(err.value).startswith("plan.yaml")


def test_missing_dwell_and_top_level_type():
    d = _plan()
    del d["dwell_s"]
    with pytest.raises(PosePlanError, match="no dwell time"):
        PosePlan.from_dict(d)
    with pytest.raises(PosePlanError, match="top level is not a mapping"):
        PosePlan.from_dict([1, 2])


def test_file_errors(tmp_path):
    with pytest.raises(PosePlanError, match="pose plan file not found"):
        PosePlan.load(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("poses: [unclosed\n")
    with pytest.raises(PosePlanError, match="not valid YAML"):
        PosePlan.load(bad)


def test_temperature_level_out_of_range():
    plan = PosePlan.from_dict(_plan(chamber={"levels_c": [10, 20]}), source="p")
    with pytest.raises(PosePlanError, match="has 2 levels"):
        plan.level_setpoint_c(2)
    with pytest.raises(PosePlanError, match="no 'chamber' section"):
        PosePlan.from_dict(_plan()).level_setpoint_c(0)


def test_plans_and_the_simulator_config_share_the_calibration_files_yaml_loader(tmp_path):
    """Duplicate keys were last-wins, 2e-3 a string and format_version: true version 1 in every file people write."""
    from fbg_accel_calibration.dynamic.excitation_plan import ExcitationPlan, ExcitationPlanError
    from fbg_accel_sim.sim_config import SimConfig, SimConfigError, parse_set_argument

    plan = tmp_path / "plan.yaml"
    plan.write_text("name: t\ndwell_s: 2.0\nsamples_per_pose: 10\nmove_s: 1e0\nposes:\n"
                    "- {name: a, psi_deg: 0, theta_deg: 0}\n- {name: b, psi_deg: 90, theta_deg: 90}\n", encoding="utf-8")
    assert PosePlan.load(plan).move_s == 1.0
    plan.write_text(plan.read_text(encoding="utf-8") + "dwell_s: 20.0\n", encoding="utf-8")
    with pytest.raises(PosePlanError, match=r"found duplicate key 'dwell_s' \(first given on line 2\)"):
        PosePlan.load(plan)
    with pytest.raises(PosePlanError, match=r"format_version True is not supported \(this tool reads 1\)"):
        PosePlan.from_dict(_plan(format_version=True), source="plan.yaml")
    excitation = yaml.safe_load((CONFIG / "excitation_plan_stepped_sine.yaml").read_text(encoding="utf-8"))
    with pytest.raises(ExcitationPlanError, match=r"format_version 1.0 is not supported \(this tool reads 1\)"):
        ExcitationPlan.from_dict({**excitation, "format_version": 1.0})
    assert parse_set_argument("noise.x=2e-3") == ("noise.x", 2e-3)
    sim = tmp_path / "sim.yaml"
    sim.write_text("seed: 1\nseed: 2\n", encoding="utf-8")
    with pytest.raises(SimConfigError, match="found duplicate key 'seed'"):
        SimConfig.load(sim)


def test_table_angles_in_radians_are_refused_like_a_gref_in_g():
    """A gref_mps2 in g is refused as a unit slip; angles in radians (pi, pi/2 written into *_deg) were taken as
    degrees: every pose within 0.06 g of z_up, and the run "calibrated" against wrong references."""
    with pytest.raises(PosePlanError, match="radian"):
        PosePlan.from_dict({"dwell_s": 5.0, "poses": [
            {"name": "z_up", "psi_deg": 0, "theta_deg": 0},
            {"name": "z_down", "psi_deg": 0, "theta_deg": 3.14159},
            {"name": "x_up", "psi_deg": 1.5708, "theta_deg": 1.5708},
            {"name": "y_down", "psi_deg": 0, "theta_deg": 4.71239}]})
    # small tilts in degrees that are no multiple of pi/2 stay accepted (e.g. a plan of near-level poses)
    PosePlan.from_dict({"dwell_s": 5.0, "poses": [{"psi_deg": 0, "theta_deg": 0}, {"psi_deg": 0, "theta_deg": 2.5},
                                                  {"psi_deg": 90, "theta_deg": 2.5}]})
