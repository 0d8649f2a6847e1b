"""The course's module name: ``from localization.motion_model import MotionModel``
(the implementation lives in ``localization.core.motion``)."""
from localization.core.motion import MotionModel, MotionNoiseParams

__all__ = ["MotionModel", "MotionNoiseParams"]
