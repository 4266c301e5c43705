"""FBG triaxial accelerometer: board protocol, calibration model, driver and simulator."""
