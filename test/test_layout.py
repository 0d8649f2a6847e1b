"""The package's layers, read from its own source (ast): every import, at module level or inside a
function, goes to the same package or a lower layer, and inside the core to the same folder or a
lower one; there is no import circle; the core talks no ROS; and the linter passes."""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "localization"

# lowest first; a module may import from its own package or from a layer with a lower rank
LAYERS = {"core": 0, "ros": 1, "bags": 1, "sim": 2, "eval": 3, "tools": 4, "benchmarks": 4}
FACADE_RANK = 5  # localization/*.py: the course's module names
# the core's folders by role, lowest first ("base": the modules directly in core/: geometry, scan, maps, ...)
CORE_LAYERS = {"base": 0, "raycast": 1, "matching": 1, "models": 2, "filter": 3, "localizer": 4}
ROS_MODULES = ("rclpy", "tf2_ros", "builtin_interfaces", "rcl_interfaces", "rosidl_runtime_py", "launch")
# the only modules that talk ROS (DDS): the node's package, the DDS player, the node's benchmarks
ROS_ALLOWED = ("localization.ros.", "localization.tools.play", "localization.benchmarks.latency",
               "localization.benchmarks.cold_start", "localization.benchmarks.node_callbacks",
               "localization.particle_filter")


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in PKG.rglob("*.py")}


def imports_of(path: Path, name: str) -> list[str]:
    """Every imported module name (absolute), wherever the import statement stands."""
    tree = ast.parse(path.read_text(), str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            known = modules()
            submodules = [f"{mod}.{a.name}" for a in node.names if f"{mod}.{a.name}" in known]
            out += submodules  # ``from pkg import submodule`` depends on the submodule ...
            if len(submodules) < len(node.names):  # ... names defined in ``pkg`` itself on ``pkg``
                out.append(mod)
    return out


def rank(name: str) -> tuple[str, int]:
    parts = name.split(".")
    if len(parts) >= 2 and parts[1] in LAYERS:
        return parts[1], LAYERS[parts[1]]
    return "top", FACADE_RANK


def graph() -> dict[str, set[str]]:
    mods = modules()
    return {name: {m for m in imports_of(path, name) if m in mods and m != name} for name, path in mods.items()}


def test_every_import_goes_down_the_layers():
    bad = []
    for src, targets in graph().items():
        src_pkg, src_rank = rank(src)
        for dst in targets:
            dst_pkg, dst_rank = rank(dst)
            if dst == "localization" or dst_pkg == src_pkg:
                continue
            if dst_rank >= src_rank:
                bad.append(f"{src} -> {dst}")
    assert not bad, "imports against the layers: " + ", ".join(sorted(bad))


def core_rank(name: str) -> tuple[str, int]:
    parts = name.split(".")
    folder = parts[2] if len(parts) >= 4 or (len(parts) == 3 and parts[2] in CORE_LAYERS) else "base"
    return folder, CORE_LAYERS[folder]


def test_core_folders_import_down_their_roles():
    """Maps and ray casting, then the models, then the filter, then the localizer and its parts."""
    folders = {p.name for p in (PKG / "core").iterdir() if (p / "__init__.py").exists()}
    assert folders == set(CORE_LAYERS) - {"base"}, f"core folders without a role here: {folders}"
    bad = []
    for src, targets in graph().items():
        if not src.startswith("localization.core"):
            continue
        src_folder, src_rank = core_rank(src)
        for dst in targets:
            dst_folder, dst_rank = core_rank(dst)
            if dst.startswith("localization.core") and dst_folder != src_folder and dst_rank >= src_rank:
                bad.append(f"{src} -> {dst}")
    assert not bad, "core imports against its folders: " + ", ".join(sorted(bad))


def test_no_import_circle():
    g = graph()
    state: dict[str, int] = {}
    cycles = []

    def visit(node, stack):
        state[node] = 1
        for nxt in g[node]:
            if state.get(nxt) == 1:
                cycles.append(" -> ".join(stack[stack.index(nxt):] + [nxt]))
            elif nxt not in state:
                visit(nxt, stack + [nxt])
        state[node] = 2

    for node in g:
        if node not in state:
            visit(node, [node])
    assert not cycles, "import circles: " + "; ".join(cycles)


def test_the_core_talks_no_ros_and_only_the_adapters_talk_dds():
    core, dds = [], []
    for name, path in modules().items():
        external = [m for m in imports_of(path, name) if not m.startswith("localization")]
        ros = [m for m in external if m.split(".")[0] in ROS_MODULES or m.split(".")[0].endswith("_msgs")
               or m.split(".")[0] in ("std_srvs", "lifecycle_msgs")]
        if name.startswith("localization.core") and (ros or any(m.startswith("rosbags") for m in external)):
            core.append(f"{name}: {ros or external}")
        if any(m.split(".")[0] == "rclpy" for m in ros) and not name.startswith(ROS_ALLOWED):
            dds.append(name)
    assert not core, f"the core imports ROS or a bag library: {core}"
    assert not dds, f"modules outside the ROS adapters that import rclpy: {dds}"


def test_the_checker_sees_a_circle_and_a_layer_breach(tmp_path, monkeypatch):
    """The walker above must be able to fail: a fake package with a circle and an upward import."""
    pkg = tmp_path / "localization"
    (pkg / "core").mkdir(parents=True)
    (pkg / "eval").mkdir()
    for f in ("__init__.py", "core/__init__.py", "eval/__init__.py"):
        (pkg / f).write_text("")
    (pkg / "core" / "a.py").write_text("def f():\n    from localization.eval import b\n")
    (pkg / "eval" / "b.py").write_text("from localization.core import a\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    monkeypatch.setattr(sys.modules[__name__], "PKG", pkg)
    g = graph()
    assert "localization.eval.b" in g["localization.core.a"] and "localization.core.a" in g["localization.eval.b"]
    try:
        test_every_import_goes_down_the_layers()
    except AssertionError as exc:
        assert "localization.core.a -> localization.eval.b" in str(exc)
    else:
        raise AssertionError("the layer check did not fail")


def test_the_course_module_names_stay_importable_and_the_top_package_is_light():
    code = ("import sys, localization; assert 'numpy' not in sys.modules, 'heavy top-level import'; "
            "from localization.motion_model import MotionModel; from localization.sensor_model import SensorModel; "
            "from localization.occupancy_map import OccupancyMap; from localization.particle_filter import main; "
            "assert SensorModel.__module__ == 'localization.sensor_model'; "
            "print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_ruff_passes():
    """The linter, as ROS 2 packages run flake8 (configuration in pyproject.toml)."""
    out = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", str(ROOT)], capture_output=True,
                         text=True, cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
