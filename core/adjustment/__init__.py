"""Weighted least squares with priors, variance components and robust blunder handling
(sensor-agnostic)."""
