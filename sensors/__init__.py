"""Sensor models: the interface, the registry and the built-in models."""
from swathflow.sensors.base import Parameter, ParameterSet, RayMissWarning, SensorModel
from swathflow.sensors.registry import get_sensor, list_sensors

__all__ = ["Parameter", "ParameterSet", "RayMissWarning", "SensorModel", "get_sensor",
           "list_sensors"]
