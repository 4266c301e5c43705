"""The diagnosis, room by room: ``design`` (data and model), ``cv`` (cross-validation by visit), ``floor``
(the noise a residual is judged against), ``search`` (a candidate on top of a model, and its checks), ``structure``
(what remains). ``fbg_accel_calibration.diagnosis.diagnose`` runs them in order."""
