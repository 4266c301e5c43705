"""Calibration toolchain: recording, fitting, degree selection, noise and diagnosis."""
