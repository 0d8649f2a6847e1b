"""What a calibration returns (``localization.eval.calibration``): the values under their metrics keys,
the node parameters they set, their uncertainty and the figures beside them."""
from __future__ import annotations

from dataclasses import dataclass, field

KEYS = ("odom_time_offset_s", "odom_speed_scale", "odom_yaw_rate_scale", "odom_yaw_rate_bias", "laser_offset_x",
        "laser_offset_y", "laser_offset_yaw", "lidar_scale_to_map_scale", "map_wall_depth")
#: metrics key -> node parameter name
PARAM_NAMES = {"odom_time_offset_s": "odom_time_offset", "odom_speed_scale": "odom_speed_scale",
               "odom_yaw_rate_scale": "odom_yaw_rate_scale", "odom_yaw_rate_bias": "odom_yaw_rate_bias",
               "laser_offset_x": "laser_offset_x", "laser_offset_y": "laser_offset_y",
               "laser_offset_yaw": "laser_offset_yaw", "lidar_scale_to_map_scale": "lidar_scale_to_map_scale",
               "map_wall_depth": "map_wall_depth"}


class CalibrationError(RuntimeError):
    """Not enough data to calibrate (one line saying why)."""


@dataclass
class CalibrationResult:
    values: dict  # KEYS -> float
    uncertainty: dict  # KEYS -> float (1 σ)
    scans: int = 0
    good_scans: int = 0
    pairs: int = 0
    residual_rms: dict = field(default_factory=dict)
    rejected: dict = field(default_factory=dict)  # slips and skids left out (package doc, step 3)
    channel_offsets: dict = field(default_factory=dict)  # δ_v, δ_ω (s) with their σ
    wall_surface: dict = field(default_factory=dict)  # o (m): where beams end behind the free-space edge
    yardstick: dict = field(default_factory=dict)  # the reference track's own figures

    def as_dict(self) -> dict:
        return {**{k: float(self.values[k]) for k in KEYS},
                "uncertainty": {k: float(self.uncertainty[k]) for k in KEYS},
                "scans": self.scans, "good_scans": self.good_scans, "pairs": self.pairs,
                "residual_rms": self.residual_rms, "rejected": self.rejected,
                "channel_offsets": self.channel_offsets, "wall_surface": self.wall_surface,
                "yardstick": self.yardstick}

    def parameter_yaml(self, node: str = "particle_filter") -> str:
        r = self.rejected
        lines = [f"# localization-calibrate: {self.good_scans} of {self.scans} scans matched, {self.pairs} pairs "
                 f"({r.get('pairs', 0)} rejected as slip or skid, {r.get('seconds', 0.0):.1f} s)",
                 f"{node}:", "  ros__parameters:"]
        for k in KEYS:
            lines.append(f"    {PARAM_NAMES[k]}: {self.values[k]:.6g}  # ± {self.uncertainty[k]:.2g}")
        return "\n".join(lines) + "\n"
