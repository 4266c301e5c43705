"""Refit at the end of a calibration run: MCAP files to a calibration YAML and a fit report (pure, no ROS).

Used by the ``calibration`` node once its run is complete; the same fit as ``fbg-accel-calib fit``
(``fit_pipeline.fit_files``): the run's MCAP together with earlier runs (other chamber temperatures),
streamed, the temperature degree by held-out cross-validation unless a degree is given, eq. 28, the slow
error (with the run-to-run component of an earlier calibration when one is given, as ``fit --run-to-run-from``),
and the result saved in the driver's calibration file format (``ThermalCalibration.save``).
"""

from __future__ import annotations

import glob
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fbg_accel_driver.sensor_constants import FULL_SCALE_MPS2
from fbg_accel_driver.thermal_model import ThermalCalibration

from ..fit.fit_pipeline import DEFAULT_MAX_DEGREE, FitOptions, fit_files
from ..fit.model_selection import SelectionResult
from ..fit.slow_error import CarriedRunToRun
from ..fit.slow_error import summary_line as slow_error_line
from ..fit.thermal_fit import reference_reach_warnings
from ..io.atomic_output import atomic_path, check_outputs


class RefitError(ValueError):
    """The run's data cannot give a calibration (with the reason)."""


@dataclass
class RefitResult:
    calibration: ThermalCalibration
    selection: SelectionResult
    sources: list[str]
    output: Path

    def report(self) -> str:
        """Human-readable fit report (degree table like paper Table 4, RMSE, noise, range)."""
        cal, fit = self.calibration, self.calibration.fit
        lines = [f"calibration fit of {len(self.sources)} file(s): " + ", ".join(self.sources)]
        lines += ["degree selection (" + self.selection.criterion + "):", self.selection.table_markdown()]
        lines += [f"note: {n}" for n in self.selection.notes]
        rmse = np.asarray(fit.get("rmse_mps2", [np.nan] * 3))
        noise = np.asarray(cal.noise_sigma_mps2)
        lines += [
            f"degree n = {cal.degree}; {fit.get('samples_used')} static samples used of {fit.get('samples_total')} "
            f"({fit.get('samples_excluded_in_motion')} excluded as in motion), {fit.get('poses')} poses, "
            f"temperature levels {fit.get('temperature_levels_c')} degC",
            "in-sample RMSE x/y/z: " + " / ".join(f"{v:.4f}" for v in rmse) + " m/s^2 = "
            + " / ".join(f"{v / FULL_SCALE_MPS2:.2e}" for v in rmse) + " of the 20 g full scale",
            "within-pose noise floor x/y/z: " + " / ".join(f"{v:.4f}" for v in noise) + " m/s^2",
            f"temperature range covered: {cal.temperature_range_c[0]:.2f} .. {cal.temperature_range_c[1]:.2f} degC",
        ]
        slow = slow_error_line(fit.get("slow_error", {}))  # where the run-to-run part came from, or why it is not one
        lines += ([slow] if slow is not None else []) + [f"calibration written to {self.output}"]
        lines += [f"warning: {w}" for w in reference_reach_warnings(fit.get("reference_range_mps2", [[-np.inf, np.inf]] * 3))]
        return "\n".join(lines)


def expand_sources(run_file: str | Path, extra: list[str]) -> list[str]:
    """The run's file plus ``extra`` paths or glob patterns (sorted, without duplicates)."""
    out = [str(Path(run_file))]
    for pattern in extra:
        if not pattern:
            continue
        matches = sorted(glob.glob(pattern)) if any(c in pattern for c in "*?[") else [pattern]
        if not matches:
            raise RefitError(f"fit_with: {pattern!r} matches no file")
        for m in matches:
            if not Path(m).is_file():
                raise RefitError(f"fit_with: {m} is not a file")
            if all(Path(m).resolve() != Path(o).resolve() for o in out):
                out.append(m)
    return out


def refit(sources: list[str], output: str | Path, degree: int | None = None, sensor_id: str | None = None,
          force: bool = False, run_to_run_from: CarriedRunToRun | None = None) -> RefitResult:
    """Fit ``sources`` (MCAP files) at ``degree`` (None: chosen by cross-validation) and save to ``output``:
    the same fit as ``fbg-accel-calib fit`` with its default options (``fit_pipeline.fit_files``);
    ``run_to_run_from`` the run-to-run component of an earlier calibration of the sensor
    (``slow_error.carried_run_to_run``, read when the run starts), as ``fit --run-to-run-from``. ``output``
    is refused (``OutputError``, before the fit) if it is one of the sources, or exists and not ``force``."""
    check_outputs([Path(output)], sources, force)
    try:
        out = fit_files([Path(s) for s in sources], degree=degree, max_degree=DEFAULT_MAX_DEGREE, sensor_id=sensor_id,
                        options=FitOptions(run_to_run_from=run_to_run_from))
    except ValueError as exc:  # NotIdentifiedError included
        raise RefitError(str(exc)) from None
    cal = out.calibration
    cal.fit["sources"] = list(sources)  # as given (fit_files stores str(Path(s)): "./a.mcap" would become "a.mcap")
    path = Path(output)
    with atomic_path(path) as tmp:  # never a half-written YAML next to the recording (SIGKILL, full disk)
        cal.save(tmp)
    return RefitResult(cal, out.selection, list(sources), path)
