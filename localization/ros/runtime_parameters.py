"""Parameters set while the node runs (``ros2 param set``, rqt_reconfigure, Foxglove's parameter panel).

    on-set callback    each value of the parameter table is checked (``core.runtime_parameters.check_change``)
                       against the values set so far: a parameter that cannot change at runtime, or a value
                       against the table's rules, is refused with the reason, and nothing changes
    post-set callback  on the node's executor, between updates: a change applied at once
                       (``Localizer.reconfigure``, under the localizer's lock); a change that needs seconds of
                       preparation (a range table, filter kernels to compile), and every change after it
                       until it is done, goes to the parameter-change thread, which prepares it off the hot
                       path while the node keeps localizing and then swaps it in between two updates

Changes are applied in the order they were set. One log line and /diagnostics ("parameters changed") say
what changed and when it took effect. Before the lifecycle node is configured a change only updates the
values the next configuration uses.
"""
from __future__ import annotations

import time

from rcl_interfaces.msg import SetParametersResult

from localization.core.parameters import BY_NAME, ParameterError, Parameters
from localization.core.runtime_parameters import Change, How, check_change
from localization.ros.scan_worker import ScanQueueWorker

QUEUE_DEPTH = 1024  # changes waiting behind one being prepared (a stream of sets from a script)


class RuntimeParameters:
    """The node's parameter callbacks (module docstring); ``stop`` ends the parameter-change thread."""

    def __init__(self, node):
        self.node = node
        self.log = node.get_logger()
        self.target = Parameters(dict(node.params))  # the values as set: a new change is checked against these
        self.last = "none since the start"  # the last change applied (/diagnostics)
        self.applied = 0  # changes applied
        self.worker = ScanQueueWorker(self._apply, self.log.error, name="parameter_change", depth=QUEUE_DEPTH)
        node.add_on_set_parameters_callback(self.validate)
        node.add_post_set_parameters_callback(self.on_set)

    @staticmethod
    def _values(parameters) -> dict:
        return {p.name: p.value for p in parameters if p.name in BY_NAME}  # others (use_sim_time) are rclpy's

    def validate(self, parameters) -> SetParametersResult:
        values = self._values(parameters)
        if values:
            try:
                check_change(self.target, values)
            except ParameterError as exc:
                self.log.warning(f"parameter change refused: {exc}")
                return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def on_set(self, parameters) -> None:
        values = self._values(parameters)
        if not values:
            return
        change = check_change(self.target, values)
        self.target = change.params
        if not change.changed:
            return
        if change.needs_preparation or not self.worker.idle:
            self.log.info(f"parameter change {change.describe()}: " + (
                "prepared off the hot path, then applied" if change.needs_preparation else
                "applied after the change being prepared"))
            self.worker.put(change)
        else:
            self._apply(change, time.monotonic())

    def _apply(self, change: Change, t_set: float) -> None:
        """Prepare (this thread) and apply (under the localizer's lock) one change."""
        node, loc = self.node, self.node.localizer
        t0 = time.monotonic()
        if loc is None:  # not configured: the next configuration uses the values
            dict.update(node.params, {name: change.params[name] for name in change.changed})
            prepared = None
        else:
            prepared = loc.prepare_change(change)
            loc.reconfigure(change, prepared)
        watchdog = node.watchdog
        if watchdog is not None and How.NODE in change.hows:
            for name in change.changed:
                if hasattr(watchdog, name):
                    setattr(watchdog, name, change.params[name])
        how = f"prepared in {time.monotonic() - t0:.2f} s off the hot path, " if change.needs_preparation else ""
        self.last = f"{change.describe()} ({how}applied {time.monotonic() - t_set:.3f} s after it was set)"
        self.applied += 1
        self.log.info(f"parameters changed: {self.last}")

    def stop(self) -> None:
        self.worker.stop()
