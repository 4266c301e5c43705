"""Driver records -> ROS messages (sensor_msgs, builtin_interfaces; no rclpy).

``DriverMessages`` keeps one message object per topic and refills it for every record: the
constant fields (frame_id, the JointState names, the REP 145 "not provided" markers) are set once,
so a sample costs only the fields that change. Each ``*_msg`` method returns the same object every
time: publish it before asking for the next one (rclpy serialises a message inside ``publish``).
"""

from __future__ import annotations

from sensor_msgs.msg import Imu, JointState, Temperature

from .driver_core import RAW_AUX_NAME, RAW_NAMES, ImuRecord, RawRecord, TemperatureRecord


class DriverMessages:
    """Reusable ``imu/raw`` (JointState), ``imu/data_raw`` (Imu) and ``imu/temperature`` messages."""

    def __init__(self, frame_id: str) -> None:
        self._raw = JointState()
        self._raw.header.frame_id = frame_id
        self._raw.name = list(RAW_NAMES)
        self._names_v1 = list(RAW_NAMES)
        self._names_aux = [*RAW_NAMES, RAW_AUX_NAME]  # version-2 frames: the reference transducer's counts
        self._imu = Imu()
        self._imu.header.frame_id = frame_id
        self._imu.orientation_covariance[0] = -1.0  # REP 145: orientation not provided
        self._imu.angular_velocity_covariance[0] = -1.0  # REP 145: angular velocity not provided
        self._temp = Temperature()
        self._temp.header.frame_id = frame_id

    def raw_msg(self, r: RawRecord) -> JointState:
        """Counts, temperature (degC), validity, status, seq, board time (s), stamped with ROS time."""
        m = self._raw
        _set_stamp(m.header.stamp, r.stamp_ns)
        f = r.frame
        m.position = [float(f.ref), float(f.x), float(f.y), float(f.z), float(r.temperature_c),
                      1.0 if r.temperature_valid else 0.0, float(f.status), float(f.seq), f.t_us * 1e-6]
        if f.aux is None:
            m.name = self._names_v1
        else:
            m.name = self._names_aux
            m.position.append(float(f.aux))
        return m

    def imu_msg(self, s: ImuRecord) -> Imu:
        """Specific force in m/s^2 in the sensor frame, with its covariance in (m/s^2)^2."""
        m = self._imu
        _set_stamp(m.header.stamp, s.stamp_ns)
        acc = m.linear_acceleration
        acc.x, acc.y, acc.z = s.accel_mps2
        m.linear_acceleration_covariance = s.covariance
        return m

    def temperature_msg(self, t: TemperatureRecord) -> Temperature:
        """AHT10 temperature in degC and its variance in degC^2."""
        m = self._temp
        _set_stamp(m.header.stamp, t.stamp_ns)
        m.temperature = t.temperature_c
        m.variance = t.variance
        return m


def _set_stamp(stamp: object, ns: int) -> None:
    stamp.sec, stamp.nanosec = divmod(ns, 1_000_000_000)
