"""Stage 3, calibration: the generic control-point adjustment of a sensor plugin's
parameters (the default calibration strategy), its result file and report."""
