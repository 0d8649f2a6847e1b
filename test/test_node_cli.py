"""The node's command line, process lifetime and launch files: SIGINT/SIGTERM in every lifecycle
state, strict configuration (parameter file sections, unknown parameters, arguments outside
--ros-args, parameter files by bare name), ``--help`` into a closed pipe, the car launch's TF
argument and the RViz frames (checked statically: no ``launch`` package here)."""
from __future__ import annotations

import ast
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

import node_harness as h  # noqa: E402
import rclpy  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SIGNAL_EXIT_S = 5.0  # a signal ends the process within this


def _env() -> dict:
    env = dict(os.environ)  # conftest.py set ROS_DOMAIN_ID and ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
    env["PYTHONUNBUFFERED"] = "1"
    return env


def _node(*args, module="localization.particle_filter", timeout=60.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True, timeout=timeout,
                          cwd=REPO, env=_env())


class _Output:
    """A process's merged output, read on a thread (so a full pipe never blocks it)."""

    def __init__(self, proc):
        self.proc, self.lines, self.lock = proc, [], threading.Lock()
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self):
        for line in self.proc.stdout:
            with self.lock:
                self.lines.append(line)

    def text(self) -> str:
        with self.lock:
            return "".join(self.lines)

    def wait_for(self, needle: str, timeout: float = 60.0) -> bool:
        return h.wait_until(lambda: needle in self.text(), timeout, period=0.05)


# ------------------------------------------------------------------ signals in every lifecycle state
def _change_state(context, transitions) -> None:
    """Drive /particle_filter through ``transitions`` (lifecycle_msgs Transition ids) from a client node."""
    from lifecycle_msgs.srv import ChangeState
    client_node = rclpy.create_node("pf_cli_lifecycle_client", context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    try:
        client = client_node.create_client(ChangeState, "/particle_filter/change_state")
        assert client.wait_for_service(timeout_sec=30.0), "no /particle_filter/change_state service"
        for tid in transitions:
            req = ChangeState.Request()
            req.transition.id = tid
            future = client.call_async(req)
            rclpy.spin_until_future_complete(client_node, future, executor=executor, timeout_sec=30.0)
            assert future.done() and future.result().success, f"transition {tid} failed"
    finally:
        executor.shutdown(timeout_sec=2.0)
        client_node.destroy_node()


@pytest.mark.parametrize("state", ["unconfigured", "inactive", "active", "finalized"])
def test_lifecycle_node_stops_on_sigint_and_sigterm_in_every_state(context, state):
    from lifecycle_msgs.msg import Transition
    path = {"unconfigured": [], "inactive": [Transition.TRANSITION_CONFIGURE],
            "active": [Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE],
            "finalized": [Transition.TRANSITION_UNCONFIGURED_SHUTDOWN]}[state]
    for sig in (signal.SIGINT, signal.SIGTERM):
        proc = subprocess.Popen([sys.executable, "-m", "localization.ros.lifecycle_node", "--ros-args", "-p",
                                 "ray_caster:=distance_transform"], stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, cwd=REPO, env=_env())
        out = _Output(proc)
        try:
            # unconfigured, it says what it waits for (one line)
            assert out.wait_for("unconfigured: waiting for the configure transition"), out.text()
            _change_state(context, path)
            if state == "active":
                assert out.wait_for("particle filter ready for input", 30.0), out.text()
            if state == "finalized":
                assert out.wait_for("finalized", 30.0), out.text()
            time.sleep(0.5)  # idle in that state: no timer, no input wakes it
            t0 = time.monotonic()
            proc.send_signal(sig)
            code = proc.wait(SIGNAL_EXIT_S + 5.0)
            took = time.monotonic() - t0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        out.thread.join(timeout=5.0)
        text = out.text()
        assert code == 0 and took < SIGNAL_EXIT_S, (state, sig, code, took, text)
        assert text.count("unconfigured: waiting for") == 1 and "Traceback" not in text, text


def test_lifecycle_cleanup_resets_the_statistics(context, drive, capfd):
    """After cleanup the next run's statistics start from zero (the shutdown line is not stale)."""
    scans = [msg for _, kind, msg in drive.until(0.3) if kind == "scan"]
    with h.lifecycle_running(context, "pf_stats_probe") as (node, probe):
        node.trigger_configure()
        node.trigger_activate()
        assert h.wait_until(lambda: probe.scan_pub.get_subscription_count() > 0, 10.0)
        for k, msg in enumerate(scans):  # lock-step: the scan subscription's queue is short
            probe.scan_pub.publish(msg)
            assert h.wait_until(lambda k=k: node.counts["scan"] == k + 1, 10.0), (node.counts, k)
        node.trigger_deactivate()
        node.trigger_cleanup()
        node.trigger_configure()
        assert node.counts["scan"] == 0 and node.watchdog.scans_received == 0
        node.trigger_activate()
        node.trigger_deactivate()
        node.trigger_cleanup()
    stats = [line for line in capfd.readouterr().err.splitlines() if "scans: " in line and "received" in line]
    assert len(stats) == 2, stats
    n = len(scans)
    assert f"scans: {n} received, {n} processed, {n} not used" in stats[0]  # no map: none usable
    assert "scans: 0 received, 0 processed, 0 not used" in stats[1]


# ------------------------------------------------------------------ strict configuration
def test_arguments_outside_ros_args_are_an_error_with_a_hint():
    for args in (["--params-file", "real_params"], ["-p", "num_particles:=10"], ["--bogus"]):
        proc = _node(*args)
        assert proc.returncode == 2, (args, proc.stderr)
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and "unrecognized arguments" in lines[0] and args[0] in lines[0], proc.stderr
        assert "after --ros-args" in lines[0]


def test_parameter_file_without_a_section_for_the_node_is_an_error(tmp_path):
    bad = tmp_path / "typo.yaml"
    bad.write_text("particle_filtr:\n  ros__parameters:\n    num_particles: 10\n")
    proc = _node("--ros-args", "--params-file", str(bad))
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "no section for the node 'particle_filter'" in lines[0], proc.stderr
    assert "'particle_filtr'" in lines[0]  # the keys found
    # replay reads parameter files the same way
    from localization.core.parameters import ParameterError, Parameters
    with pytest.raises(ParameterError, match="particle_filtr"):
        Parameters.from_yaml(bad)
    # wildcards and namespaces apply as in rcl
    for text in ("/**:\n  ros__parameters:\n    num_particles: 10\n",
                 "/particle_filter:\n  ros__parameters:\n    num_particles: 10\n"):
        bad.write_text(text)
        assert Parameters.from_yaml(bad).num_particles == 10


def test_unknown_parameter_is_an_error_in_the_node_and_in_replay(tmp_path):
    typo = tmp_path / "unknown.yaml"
    typo.write_text("particle_filter:\n  ros__parameters:\n    num_particle: 10\n")
    proc = _node("--ros-args", "--params-file", str(typo))
    assert proc.returncode == 1 and "unknown parameter num_particle" in proc.stdout + proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
    from localization.core.parameters import ParameterError, Parameters
    with pytest.raises(ParameterError, match="num_particle"):
        Parameters.from_yaml(typo)


def test_a_yaml_syntax_error_in_the_parameter_file_names_its_line_and_column(tmp_path):
    bad = tmp_path / "broken.yaml"
    bad.write_text("particle_filter:\n  ros__parameters:\n    num_particles: 300\n    odom_topic: /odom: x\n")
    proc = _node("--ros-args", "--params-file", str(bad))
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and f"{bad}:4:22: mapping values are not allowed here" in lines[0], proc.stderr
    # an indentation error: the line of the problem, and the context it was in
    from localization.ros.cli import check_params_file
    bad.write_text("particle_filter:\n  ros__parameters:\n    num_particles: 300\n   odom_topic: /odom\n")
    problem = check_params_file(bad, [])
    assert problem.startswith(f"parameter file is not valid YAML: {bad}:4:4: expected <block end>"), problem
    assert "(while parsing a block mapping from line 2)" in problem


def test_parameter_file_by_bare_name_and_the_hint_for_a_missing_one():
    from localization.core.paths import config_dir, resolve_params_path
    assert resolve_params_path("real_params.yaml") == config_dir() / "real_params.yaml"
    assert resolve_params_path("real_params") == config_dir() / "real_params.yaml"
    proc = _node("--ros-args", "--params-file", "real_paramz.yaml")
    assert proc.returncode == 1
    line = proc.stderr.strip()
    assert "parameter file not found: real_paramz.yaml" in line and str(config_dir()) in line
    assert "real_params" in line  # the names that are there


def test_help_into_a_closed_pipe_is_no_error():
    proc = subprocess.run(f"{sys.executable} -m localization.particle_filter -h | head -1", shell=True,
                          capture_output=True, text=True, timeout=60, cwd=REPO, env=_env())
    assert proc.stdout.startswith("usage:") and len(proc.stdout.splitlines()) == 1
    assert "Traceback" not in proc.stderr and "BrokenPipe" not in proc.stderr, proc.stderr


# ------------------------------------------------------------------ launch file and RViz (static)
def _launch_tree():
    source = (REPO / "launch" / "localization_car.launch.py").read_text()
    return source, ast.parse(source)


def test_car_launch_makes_map_to_odom_the_default_and_passes_publish_tf_to_the_node():
    from localization.core.parameters import BY_NAME
    source, tree = _launch_tree()
    declared = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "DeclareLaunchArgument":
            default = next((k.value for k in node.keywords if k.arg == "default_value"), None)
            declared[node.args[0].value] = default.value if isinstance(default, ast.Constant) else None
    assert declared["publish_tf"] == "map_to_odom"
    rule = BY_NAME["publish_tf"].rule
    assert declared["publish_tf"] in rule  # a value the node accepts
    # the node's parameters: the params file, then a dict that carries publish_tf from the argument
    nodes = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "Node"
             and any(k.arg == "package" and isinstance(k.value, ast.Name) and k.value.id == "PACKAGE"
                     for k in n.keywords)]
    assert len(nodes) == 1
    params = next(k.value for k in nodes[0].keywords if k.arg == "parameters")
    assert isinstance(params, ast.List) and isinstance(params.elts[-1], ast.Name)
    dict_name = params.elts[-1].id
    assigned = next(n.value for n in ast.walk(tree) if isinstance(n, ast.Assign)
                    and getattr(n.targets[0], "id", "") == dict_name)
    keys = {k.value: ast.unparse(v) for k, v in zip(assigned.keys, assigned.values)}
    assert keys["publish_tf"] == "get('publish_tf')", keys  # the launch argument, not a constant


def test_rviz_frames_exist_in_the_car_launch_tf_tree():
    """Fixed frame map and view target: frames of the tree the car launch gives (map -> odom by the node,
    odom -> base_link by the odometry driver); the scan is drawn in its own frame (no frame forced)."""
    import yaml

    from localization.core.parameters import Parameters
    params = Parameters.from_yaml(REPO / "config" / "real_params.yaml", publish_tf="map_to_odom")
    tree = {params.map_frame, params.odom_frame, params.base_frame}  # map -> odom (node), odom -> base_link
    doc = yaml.safe_load((REPO / "rviz" / "localization.rviz").read_text())
    manager = doc["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == params.map_frame
    assert manager["Views"]["Current"]["Target Frame"] in {params.odom_frame, params.base_frame}
    assert manager["Views"]["Current"]["Target Frame"] in tree
    for display in manager["Displays"]:
        if "Reference Frame" in display:
            assert display["Reference Frame"] in tree, display
        if display["Class"].endswith("LaserScan"):
            assert "Frame" not in " ".join(display), display  # the scan's header frame
