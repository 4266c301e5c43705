"""Where the paper's measured series is read from and where its results pages are written (relative to the
working directory): the defaults of ``report-measured`` and ``uncertainty-measured``, without their numerical
modules (the argument parser shows them in ``--help``)."""

from __future__ import annotations

from pathlib import Path

MEASURED_CSV = Path("../shared/data/measured/fig13_multiposition_23C.csv")
FIT_MD = Path("docs/results/measured_fit.md")
FIT_PNG = Path("docs/img/measured_fit.png")
UNCERTAINTY_MD = Path("docs/results/calibration_uncertainty.md")
