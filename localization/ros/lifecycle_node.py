"""The lifecycle (managed) variant of the node: ``particle_filter_lifecycle``.

    ros2 run localization particle_filter_lifecycle --ros-args --params-file real_params
    ros2 lifecycle set /particle_filter configure   # localizer, publishers, services, threads
    ros2 lifecycle set /particle_filter activate    # subscriptions and timers: it localizes
    ros2 lifecycle set /particle_filter deactivate  # inputs unsubscribed (state kept)
    ros2 lifecycle set /particle_filter cleanup     # everything but the parameters released

The same wiring as ``ParticleFilterNode`` (``node.LocalizationMixin``), mapped onto the
transitions, so nav2's lifecycle_manager can start it beside map_server. Parameters are declared
at construction (read-only, as in the plain node). Unconfigured it logs one line saying what it
waits for; in every state (unconfigured, inactive, active, finalized) SIGINT and SIGTERM end it
cleanly with exit code 0 (``cli.spin_node``). Cleanup logs the run's statistics, and the next
configure starts them again from zero.
"""
from __future__ import annotations

import sys

from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn

from localization.ros.cli import spin_node
from localization.ros.node import LocalizationMixin


class LifecycleParticleFilterNode(LocalizationMixin, LifecycleNode):
    def __init__(self, **node_kwargs):
        super().__init__(**node_kwargs)  # LocalizationMixin: every field, the parameters declared
        self.get_logger().info(f"unconfigured: waiting for the configure transition (a lifecycle manager, or "
                               f"'ros2 lifecycle set {self.get_fully_qualified_name()} configure')")

    def on_configure(self, state) -> TransitionCallbackReturn:
        try:
            self._configure()
        except Exception as exc:  # noqa: BLE001 - a failed transition, not a crash
            self.get_logger().error(f"configure failed: {exc!r}")
            return TransitionCallbackReturn.FAILURE
        self.get_logger().info("configured")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state) -> TransitionCallbackReturn:
        self._activate()
        return super().on_activate(state)

    def on_deactivate(self, state) -> TransitionCallbackReturn:
        self._deactivate()
        self.get_logger().info("deactivated: inputs unsubscribed")
        return super().on_deactivate(state)

    def on_cleanup(self, state) -> TransitionCallbackReturn:
        self._cleanup()
        self.get_logger().info("cleaned up")
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state) -> TransitionCallbackReturn:
        self._shutdown_wiring()
        self.get_logger().info("finalized: nothing more to do; Ctrl-C or SIGTERM ends the process")
        return TransitionCallbackReturn.SUCCESS

    def destroy_node(self):
        self._shutdown_wiring()
        return super().destroy_node()


def main(args=None) -> int:
    return spin_node(LifecycleParticleFilterNode, args)


if __name__ == "__main__":
    sys.exit(main())
