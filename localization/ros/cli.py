"""The node's command line and process: ``--help``, strict arguments, spin until a signal.

``prepare_args``: arguments outside ``--ros-args`` are an error (exit 2, with a hint); every
``--params-file`` must exist (a bare name is looked up in the package's config/) and have a section
for this node (exit 1); unknown parameters are refused later, when the node declares them
(``ros.parameters``). ``spin_node`` runs a node until SIGINT or SIGTERM, which end it within
SPIN_WAKE_S in every lifecycle state, with exit code 0.
"""
from __future__ import annotations

import os
import sys
import threading
from pathlib import Path

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

from localization.core.parameters import NODE_NAME, ParameterError, help_text

GIL_SWITCH_INTERVAL_S = 0.0005  # see spin_node
SPIN_WAKE_S = 0.2  # s: the executor's longest wait, so SIGINT/SIGTERM are acted on within it

USAGE = """usage: {prog} [-h] [--ros-args --params-file FILE -p NAME:=VALUE ...]

The particle filter localizer node (Monte Carlo localization in a known map).

Inputs: /map (nav_msgs/OccupancyGrid), /scan (sensor_msgs/LaserScan), /odom (nav_msgs/Odometry),
/initialpose (geometry_msgs/PoseWithCovarianceStamped). Outputs: /pf/pose
(PoseWithCovarianceStamped), /pf/pose/odom (Odometry), /pf/particles, /pf/health, /diagnostics, TF.
Services: ~/reinitialize_global_localization, request_nomotion_update (std_srvs/Empty).

--params-file accepts a path or the name of a file in the package's config/ (params, real_params).
Examples:
  {prog} --ros-args --params-file real_params -p odom_topic:=/vesc/odom
  {prog} --ros-args -p set_initial_pose:=true -p initial_pose.x:=1.0 -p initial_pose.y:=2.0

Parameters by group (name = default  [rule], then what it does):

{params}

Documentation: docs/node.md in the package.
"""


def usage(prog: str = NODE_NAME) -> str:
    return USAGE.format(prog=prog, params=help_text())


def _print_help(text: str) -> None:
    """Print the usage; a reader that stops early (``particle_filter -h | head``) is no error."""
    try:
        print(text, flush=True)
    except BrokenPipeError:
        devnull = os.open(os.devnull, os.O_WRONLY)  # Python flushes stdout again at exit: not into the pipe
        os.dup2(devnull, sys.stdout.fileno())


def _node_identity(ros: list[str]) -> tuple[str, str]:
    """(namespace, node name) after the ``-r __node:=`` / ``-r __ns:=`` remappings of the ROS arguments."""
    name, namespace = NODE_NAME, "/"
    for i, arg in enumerate(ros[:-1]):
        if arg in ("-r", "--remap"):
            key, _, value = ros[i + 1].partition(":=")
            if key in ("__node", "__name") and value:
                name = value
            elif key == "__ns" and value:
                namespace = value
    return namespace, name


def yaml_error(path, exc) -> str:
    """A YAML error as ``file:line:column: problem (context)``, as compilers write it (line and column from 1)."""
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    where = f"{path}:{mark.line + 1}:{mark.column + 1}" if mark is not None else str(path)
    context, context_mark = getattr(exc, "context", None), getattr(exc, "context_mark", None)
    if context and context_mark is not None:
        context += f" from line {context_mark.line + 1}"
    return f"{where}: {problem}" + (f" ({context})" if context else "")


def check_params_file(path, ros: list[str]) -> str:
    """Why a parameter file cannot configure this node ("" when it can): unreadable, or no section
    that applies to the node (a misspelt node name would leave every parameter at its default)."""
    import yaml

    from localization.core.parameters import node_sections, section_error
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except yaml.YAMLError as exc:
        return f"parameter file is not valid YAML: {yaml_error(path, exc)}"
    except OSError as exc:
        return f"cannot read parameter file {path}: {exc}".splitlines()[0]
    keys = list(doc) if isinstance(doc, dict) else []
    namespace, name = _node_identity(ros)
    return "" if node_sections(keys, name, namespace) else section_error(path, keys, name)


def prepare_args(argv: list[str]) -> tuple[list[str] | None, int | None]:
    """(arguments for rclpy, None) or (None, exit code) after ``--help`` or a bad command line: an
    argument outside ``--ros-args`` (exit 2, with a hint), a missing parameter file, or one without
    a section for this node (exit 1). A ``--params-file`` given by name (``real_params`` or
    ``real_params.yaml``) is looked up in the package's config/ when it is not a file here."""
    from localization.core.paths import config_dir, resolve_params_path, split_ros_args
    prog = os.path.basename(argv[0]) if argv else NODE_NAME
    own, ros = split_ros_args(argv[1:])
    if any(arg in ("-h", "--help") for arg in own):
        _print_help(usage(prog))
        return None, 0
    if own:
        print(f"{prog}: error: unrecognized arguments: {' '.join(own)} (ROS arguments go after --ros-args, e.g. "
              f"{prog} --ros-args --params-file real_params -p num_particles:=1000; {prog} --help lists the "
              "parameters)", file=sys.stderr)
        return None, 2
    out = list(argv[:1])
    i = 0
    while i < len(ros):
        if ros[i] != "--params-file":
            out.append(ros[i])
            i += 1
            continue
        if i + 1 >= len(ros):
            print(f"{prog}: error: --params-file needs a file", file=sys.stderr)
            return None, 2
        path = resolve_params_path(ros[i + 1])
        if not path.is_file():
            names = ", ".join(sorted(f.stem for f in config_dir().glob("*.yaml"))) or "none"
            print(f"{prog}: error: parameter file not found: {ros[i + 1]} (a path, or a name in {config_dir()}: "
                  f"{names})", file=sys.stderr)
            return None, 1
        problem = check_params_file(path, ros)
        if problem:
            print(f"{prog}: error: {problem}", file=sys.stderr)
            return None, 1
        out += ["--params-file", str(path)]
        i += 2
    return out, None


def make_executor():
    """rclpy's EventsExecutor where this rclpy has it (its wait and dispatch are C++: a fraction of
    the Python executor's CPU per callback, docs/performance.md), else the SingleThreadedExecutor.
    Both run one callback at a time, in arrival order."""
    try:
        from rclpy.experimental import EventsExecutor
    except ImportError:
        return SingleThreadedExecutor()
    return EventsExecutor()


def spin_node(node_factory, args=None) -> int:
    """Init rclpy (with our own SIGINT/SIGTERM handling, so the context is still valid while the node
    shuts down and logs), spin ``node_factory()`` until SIGINT or SIGTERM, shut down cleanly (exit
    code 0). The executor waits at most SPIN_WAKE_S at a time, so a signal is acted on within that
    even when nothing else wakes it (a lifecycle node unconfigured, inactive or finalized has no
    timer and no subscription)."""
    import signal

    from rclpy.signals import SignalHandlerOptions

    argv = list(sys.argv if args is None else args)
    argv, code = prepare_args(argv)
    if argv is None:
        return code
    # The executor thread and the sensor-update thread share the GIL: a thread waiting for it gets it
    # after at most the switch interval (5 ms by default), a direct addition to the scan -> pose latency.
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # noqa: BLE001 - e.g. a malformed --ros-args: one line, no traceback
        print(f"{NODE_NAME}: error: {exc}".splitlines()[0], file=sys.stderr)
        return 1
    executor = make_executor()
    stop = threading.Event()

    def on_signal(signum, frame):  # noqa: ARG001 - the loop below ends after the current callback
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    node = None
    try:
        try:
            node = node_factory()
        except ParameterError:
            return 1
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=SPIN_WAKE_S)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
