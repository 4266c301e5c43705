"""Physical constants of the sensor and of the units, defined once (no ROS, no numpy)."""

STANDARD_GRAVITY = 9.80665  # m/s^2 (CGPM 1901); the local g of a calibration site goes in the pose plan
FULL_SCALE_MPS2 = 20.0 * STANDARD_GRAVITY  # the sensor's range, +-20 g (paper section 3.4)
