"""The static calibration fit: static intervals, eq. 28's sums and solver, the degree by cross-validation, the
coefficients' covariance and the slow error of a pose mean, the noise (correlation, Allan deviation), the
ADC's code table, the field check from gravity, and the one path from files to a fitted calibration
(``fit_pipeline``)."""
