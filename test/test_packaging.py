"""Packaging as pip and rosdep expect it: setup.py declares every third-party package the code
imports (extras for the optional tools), requirements.txt pins exactly those (in the declared
ranges) and constraints.txt pins the rest; package.xml is well-formed, names a rosdep key for
every ROS package the code imports and keeps the bringup pieces out."""
from __future__ import annotations

import ast
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]

#: import name -> distribution name, where they differ
DISTRIBUTION = {"PIL": "pillow", "yaml": "pyyaml", "foxglove": "foxglove-sdk"}
#: ROS packages: from a ROS install (package.xml) or the ROS 2 wheels of requirements.txt, not setup.py
ROS = {"rclpy", "ament_index_python", "builtin_interfaces", "rcl_interfaces", "std_msgs", "std_srvs", "sensor_msgs",
       "nav_msgs", "geometry_msgs", "diagnostic_msgs", "lifecycle_msgs", "tf2_ros", "tf2_msgs", "launch", "launch_ros"}
#: optional tools: the only modules allowed to import an extra's package
TUNING = "localization/eval/tuning/"
EXTRA_USERS = {"optuna": (f"{TUNING}objective.py", f"{TUNING}storage.py", f"{TUNING}study.py", f"{TUNING}workers.py",
                          "localization/tools/tune.py"),
               "sqlalchemy": (f"{TUNING}storage.py",),
               "foxglove-sdk": ("localization/ros/live_view.py",)}
BRINGUP = {"nav2_map_server", "nav2_lifecycle_manager", "rviz2", "rviz_default_plugins"}
#: keys rosdep has no Ubuntu 24.04 (noble) rule for: pip installs these
NO_NOBLE_KEY = {"python3-numba", "python3-rosbags", "python3-optuna", "python3-foxglove-sdk"}


def _setup_call() -> dict:
    tree = ast.parse((ROOT / "setup.py").read_text())
    call = next(n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "setup")
    return {k.arg: k.value for k in call.keywords}


def _declared() -> tuple[dict, dict]:
    kw = _setup_call()
    base = [Requirement(r) for r in ast.literal_eval(kw["install_requires"])]
    extras = {name: [Requirement(r) for r in reqs] for name, reqs in ast.literal_eval(kw["extras_require"]).items()}
    return {r.name.lower(): r for r in base}, extras


def _imports() -> dict:
    """Top-level third-party modules imported anywhere in localization/ -> the files importing them."""
    found: dict = {}
    for path in sorted((ROOT / "localization").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top not in sys.stdlib_module_names and top != "localization":
                    found.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    return found


def _pins(path: Path) -> dict:
    pins = {}
    for line in path.read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, _, version = line.partition("==")
            pins[name.strip().lower().replace("_", "-")] = version.strip()
    return pins


def test_setup_declares_every_third_party_import():
    base, extras = _declared()
    extra_names = {r.name.lower(): name for name, reqs in extras.items() for r in reqs}
    imports = _imports()
    assert {"numpy", "scipy", "rosbags", "yaml", "matplotlib", "tqdm", "optuna", "foxglove"} <= set(imports)
    missing = []
    for module, files in imports.items():
        if module in ROS:
            continue
        dist = DISTRIBUTION.get(module, module).lower()
        if dist in base:
            continue
        if dist in extra_names:  # an extra: only the optional tool may import it
            allowed = EXTRA_USERS.get(dist, ())
            assert files <= set(allowed), f"{dist} ([{extra_names[dist]}]) imported by {sorted(files - set(allowed))}"
            continue
        missing.append(f"{module} ({', '.join(sorted(files))})")
    assert not missing, "imported but not declared in setup.py: " + "; ".join(missing)
    assert {"numpy", "scipy", "numba", "rosbags", "pyyaml", "matplotlib", "tqdm"} <= set(base)
    assert all(r.specifier for r in base.values()), "runtime dependencies are declared with version ranges"
    assert {"tune", "live", "dev"} <= set(extras)
    assert {"optuna"} == {r.name for r in extras["tune"]} and {"foxglove-sdk"} == {r.name for r in extras["live"]}
    assert {"pytest", "hypothesis", "ruff"} <= {r.name for r in extras["dev"]}


def test_requirements_pin_the_declared_packages_within_their_ranges():
    base, extras = _declared()
    pins = _pins(ROOT / "requirements.txt")
    declared = list(base.values()) + [r for reqs in extras.values() for r in reqs]
    for req in declared:
        name = req.name.lower()
        assert name in pins, f"{name} is declared in setup.py but not pinned in requirements.txt"
        assert req.specifier.contains(pins[name], prereleases=True), f"{name}=={pins[name]} is outside {req}"
    assert all(v for v in pins.values()), "requirements.txt pins every line (NAME==VERSION)"
    # only direct dependencies: the ROS wheels, and what setup.py declares
    extra = set(pins) - {r.name.lower() for r in declared}
    assert extra <= {"ros-jazzy-rclpy", "ros-jazzy-common-interfaces", "ros-jazzy-rmw-fastrtps-cpp"}, extra


def test_constraints_pin_the_resolved_set():
    pins, lock = _pins(ROOT / "requirements.txt"), _pins(ROOT / "constraints.txt")
    for name, version in pins.items():
        assert lock.get(name) == version, f"constraints.txt pins {name}=={lock.get(name)}, requirements {version}"
    assert len(lock) > 2 * len(pins)  # the transitive packages too (llvmlite, alembic, ...)
    assert {"llvmlite", "sqlalchemy", "alembic"} <= set(lock)
    lines = [ln for ln in (ROOT / "constraints.txt").read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    assert all(re.fullmatch(r"[A-Za-z0-9_.\-]+==[^\s@]+", ln) for ln in lines)  # NAME==VERSION, no local or editable
    assert "localization" not in lock
    boot = (ROOT / "scripts" / "bootstrap.sh").read_text()
    assert re.search(r"pip install .*-r requirements\.txt -c constraints\.txt", boot)
    assert "constraints.txt" in boot.split("want=")[1].splitlines()[0]  # a changed lock re-installs


def test_package_xml_is_well_formed_with_rosdep_keys_and_no_bringup():
    root = ET.parse(ROOT / "package.xml").getroot()
    assert root.tag == "package" and root.get("format") == "3"
    assert root.findtext("name") == "localization"
    assert root.find("export").findtext("build_type") == "ament_python"
    run = {e.text.strip() for e in root.iter() if e.tag in ("exec_depend", "depend")}
    assert not run & BRINGUP, f"bringup pieces are not the library's dependencies: {run & BRINGUP}"
    assert not run & NO_NOBLE_KEY, f"no rosdep rule on Ubuntu 24.04 for {run & NO_NOBLE_KEY}"
    ros_imports = set(_imports()) & ROS
    assert ros_imports <= run, f"imported ROS packages without an exec_depend: {ros_imports - run}"
    for key in ("python3-numpy", "python3-scipy", "python3-yaml", "python3-matplotlib", "python3-tqdm"):
        assert key in run, key
    tests = {e.text.strip() for e in root.iter("test_depend")}
    assert "python3-pytest" in tests


@pytest.mark.parametrize("launch", sorted((ROOT / "launch").glob("*.py")), ids=lambda p: p.name)
def test_launch_files_import_only_declared_ros_packages(launch):
    run = {e.text.strip() for e in ET.parse(ROOT / "package.xml").getroot().iter("exec_depend")}
    for node in ast.walk(ast.parse(launch.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            top = node.module.split(".")[0]
            if top not in sys.stdlib_module_names:
                assert top in run, f"{launch.name} imports {top}, which package.xml does not declare"
