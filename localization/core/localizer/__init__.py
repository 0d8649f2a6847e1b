"""The localizer and its parts (docs/core.md): ``localizer`` (the object the node and the tools hold),
``pipeline`` (one scan, top to bottom), ``recovery`` (the one decision after an update), ``health``,
``policies``, ``timeline``, ``seeder``, ``initial_pose``, ``range_scale``."""
from localization.core.localizer.localizer import (
    Ignored,
    Localizer,
    PoseEstimate,
    ScanResult,
    build_filter,
    build_sensor_model,
)

__all__ = ["Ignored", "Localizer", "PoseEstimate", "ScanResult", "build_filter", "build_sensor_model"]
