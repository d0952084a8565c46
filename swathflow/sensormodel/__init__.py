"""The sensor-model interface and the registry of sensor plugins."""
from swathflow.sensormodel.base import Parameter, ParameterSet, RayMissWarning, SensorModel
from swathflow.sensormodel.registry import get_sensor, list_sensors

__all__ = ["Parameter", "ParameterSet", "RayMissWarning", "SensorModel", "get_sensor",
           "list_sensors"]
