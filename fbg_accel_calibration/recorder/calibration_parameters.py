"""The calibration node's parameters and exit statuses (ROS-free): its parameter table
(``command_line.ParameterTable``) and what each exit status means. Read by the node (``calibration_node``) and by its
entry point (``calibration_main``), whose ``--help`` answers without rclpy.
"""

from __future__ import annotations

from fbg_accel_driver.command_line import ParameterTable
from fbg_accel_driver.stillness_monitor import DEFAULT_FALSE_ALARM_PER_RUN, DEFAULT_NOISE_CORR_S

EXIT_OK, EXIT_FIT_FAILED, EXIT_STARTUP, EXIT_INTERRUPTED, EXIT_RECORDING_FAILED = 0, 1, 2, 3, 4
# name: (type, default, description), ROS-free so that --help needs no ROS (command_line.ParameterTable;
# a default of None declares the parameter by type only, unset unless given)
PARAMETERS: ParameterTable = {
    "plan_file": ("string", "", "pose plan YAML (required), e.g. config/pose_plan_six_position.yaml, or an excitation "
                  "plan (dynamic run: records imu/raw with aux_counts and the reference for the plan's duration)"),
    "output_dir": ("string", ".", "directory of the run's MCAP file and calibration YAML (created if missing)"),
    "run_label": ("string", "", "file stem of this run (empty: <sensor_id>[_L<level>]_<YYYYmmddTHHMMSSZ>)"),
    "sensor_id": ("string", "unknown", "sensor identifier written into the MCAP metadata and the calibration"),
    "operator_notes": ("string", "", "free text stored in the MCAP metadata"),
    "mode": ("string", "service", "pose advance: service (operator calls calibration/next_pose) or auto (table motion/dwell)"),
    "temperature_level": ("integer", -1, "index of the plan's chamber level of this run (-1: none)"),
    "fit": ("bool", True, "refit at the end of a complete run and write the calibration YAML"),
    "fit_degree": ("integer", -1, "temperature degree n of eq. 28, 0..6 (-1: chosen by held-out cross-validation)"),
    "fit_with": ("string_array", None, "earlier runs' MCAP files or glob patterns fitted together with this run"),
    "calibration_file": ("string", "", "output calibration YAML (empty: <output_dir>/<run_label>_calibration.yaml); "
                         "never one of the fitted recordings"),
    "run_to_run_from": ("string", "", "earlier calibration YAML of this sensor whose run-to-run component R the "
                        "end-of-run fit carries when its runs do not identify R (one run per level; empty: none)"),
    "force": ("bool", False, "replace an existing calibration_file (default: refuse it at start-up)"),
    "still_window_s": ("double", 0.25, "static detector moving window (s)"),
    "still_hold_s": ("double", 1.0, "continuous stillness (s) required before a pose is recorded (covers TIA settling)"),
    "still_noise_std": ("double_array", None, "Psi noise floor per axis x,y,z (unset: learnt at the start of the run)"),
    "still_noise_corr_s": ("double", DEFAULT_NOISE_CORR_S, "correlation time (s) of a configured still_noise_std (TIA low-pass)"),
    "noise_learn_s": ("double", 5.0, "seconds at the start of the run used to learn the noise floor (table still)"),
    "still_false_alarm_per_run": ("double", DEFAULT_FALSE_ALARM_PER_RUN,
                                  "expected false still->moving transitions per run of a still sensor, (0, 1)"),
    "motion_expect_g": ("double", 0.1, "pose changes above this (g) must show motion before the next pose is recorded"),
    "stream_timeout_s": ("double", 0.0, "end the run (file closed, status 3) after this many seconds without an imu/raw "
                         "sample once samples have come; 0: wait for them to come back (a stall is reported after 5 s)"),
    "exit_when_done": ("bool", True, "exit once the run is complete (and fitted)"),
    "progress": ("bool", True, "print the progress line (pose k of N, stillness, samples, temperature) on stdout"),
}
