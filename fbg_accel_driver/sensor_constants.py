"""Physical constants of the sensor and of the units, defined once (no ROS, no numpy)."""

STANDARD_GRAVITY = 9.80665  # m/s^2 (CGPM 1901); the local g of a calibration site goes in the pose plan
# Local gravity on the Earth's surface: WGS-84 normal gravity 9.780 m/s^2 (equator) .. 9.832 m/s^2 (poles), minus
# 3.1e-6 m/s^2 per metre of altitude; 9.7 .. 9.9 leaves room for local anomalies. A value outside is a typo or a unit.
GRAVITY_RANGE_MPS2 = (9.7, 9.9)
FULL_SCALE_MPS2 = 20.0 * STANDARD_GRAVITY  # the sensor's range, +-20 g (paper section 3.4)
# Reference photodetector counts below this: no source light (SLD off, fiber unplugged), not data. Eq. 24 divides by
# the reference, so Psi = counts / ref of such a sample is tens of times its normal size. ~6 % of the ~870 counts the
# measured board shows at rest. The driver publishes no acceleration for it (its ``min_reference_counts`` default),
# and the offline tools leave it out of every fit and diagnosis (``Recording.low_reference``).
LOW_REFERENCE_COUNTS = 50
AHT10_SIGMA_C = 0.3  # degC: the AHT10's stated accuracy +-0.3 degC (paper 3.5, datasheet), taken as one standard deviation
