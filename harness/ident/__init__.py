"""Identification, as the labs did it: sensor calibration, preprocessing, ARMAX order grid and selection, the
models exported as FMUs, the cross-fit matrix and the acceptance gate."""
