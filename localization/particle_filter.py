"""The course's entry point: ``ros2 run localization particle_filter`` and
``python -m localization.particle_filter`` start the node of ``localization.ros.node``."""
import sys

from localization.ros.node import ParticleFilterNode, main

__all__ = ["ParticleFilterNode", "main"]

if __name__ == "__main__":
    sys.exit(main())
