"""Sensor models: the interface, the registry and the built-in models."""
from .base import Parameter, ParameterSet, RayMissWarning, SensorModel
from .registry import get_sensor, list_sensors

__all__ = ["Parameter", "ParameterSet", "RayMissWarning", "SensorModel", "get_sensor",
           "list_sensors"]
