"""The calibration node: its pure core (pose plan, pose sequencer, the static and the dynamic recorder,
the stream's bookkeeping and watch, the progress display, the end-of-run refit) and its ROS shell
(``calibration_node``, entry point ``calibration_main``, parameters ``calibration_parameters``)."""
