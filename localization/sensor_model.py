"""The course's module name: ``from localization.sensor_model import SensorModel``
(the beam model of ``localization.core.sensors.beam``; ``SensorModel()`` uses the lookup-table
ray caster, cached on disk)."""
from localization.core.sensors.beam import BeamModel, BeamModelParams

SensorModel = BeamModel

__all__ = ["BeamModel", "BeamModelParams", "SensorModel"]
