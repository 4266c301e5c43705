"""Calibration toolchain, one room (subpackage) per job: io, fit, dynamic, diagnosis, reports, recorder, commands
(docs/architecture.md, "Package graph")."""
