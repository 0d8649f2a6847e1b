"""The course's module name: ``from localization.sensor_model import SensorModel``
(the beam model of ``localization.core.sensors.beam``; ``SensorModel()`` uses the lookup-table
ray caster, cached on disk). Its ``sigma_hit`` is in metres (the course's 8 cells of 0.05 m =
0.4 m) and its table cells are ``table_resolution`` = 0.05 m, whatever the map's resolution."""
from localization.core.sensors.beam import BeamModel, BeamModelParams

SensorModel = BeamModel

__all__ = ["BeamModel", "BeamModelParams", "SensorModel"]
