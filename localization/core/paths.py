"""Where the package finds its data and keeps what it derives (no ROS).

- ``package_share_dir()``: the source checkout, or ``share/localization`` when installed
  (``config/``, ``maps/``, ``launch/``, ``rviz/`` live there);
- ``resolve_map_path(name_or_path)``: a YAML path as given, else a bare name (``stata_basement``)
  looked up in the package's ``maps/`` first, then ``$LOCALIZATION_MAPS_DIR``, then the shared
  data directory's ``maps/`` (``map_not_found(name)``: the line naming every folder searched and
  the maps available, when none has it);
- ``parameter_files()``: the parameter files in the package's ``config/``, by name;
- ``shared_dir()``: ``$LOCALIZATION_SHARED_DIR``, else ``../shared`` beside the checkout (the bags);
- ``cache_dir()``: ``$LOCALIZATION_CACHE_DIR``, else ``$XDG_CACHE_HOME/localization``
  (``~/.cache/localization``): range tables, simulated bags;
- ``atomic_write(path)``: write a file so a reader never sees half of it (temporary file in the
  same directory, then rename).
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

PACKAGE = "localization"
_SOURCE_ROOT = Path(__file__).resolve().parents[2]  # the checkout (…/localization/core/paths.py)


def package_share_dir() -> Path:
    """The folder holding ``config/`` and ``maps/``: the checkout, else the installed share dir."""
    if (_SOURCE_ROOT / "config").is_dir():
        return _SOURCE_ROOT
    try:
        from ament_index_python.packages import get_package_share_directory
        return Path(get_package_share_directory(PACKAGE))
    except Exception:  # noqa: BLE001 - no ament index (pip install): the source layout
        return _SOURCE_ROOT


def config_dir() -> Path:
    """The package's ``config/`` (parameter files)."""
    return package_share_dir() / "config"


def package_maps_dir() -> Path:
    """The maps shipped with the package (``maps/``)."""
    return package_share_dir() / "maps"


def shared_dir() -> Path:
    """``$LOCALIZATION_SHARED_DIR``, else ``../shared`` beside the checkout (bags, reference data)."""
    env = os.environ.get("LOCALIZATION_SHARED_DIR")
    return Path(env).expanduser() if env else _SOURCE_ROOT.parent / "shared"


def map_search_dirs() -> list[Path]:
    """Where a bare map name is looked up, in order."""
    dirs = [package_maps_dir()]
    env = os.environ.get("LOCALIZATION_MAPS_DIR")
    if env:
        dirs.append(Path(env).expanduser())
    dirs.append(shared_dir() / "maps")
    return dirs


def is_map_name(name_or_path) -> bool:
    """Whether ``--map`` got a bare map name (``stata_basement``), not a path to a YAML."""
    path = Path(name_or_path).expanduser()
    return not (path.suffix in (".yaml", ".yml") or path.exists() or len(path.parts) > 1)


def find_map(name: str) -> Path | None:
    """``NAME.yaml`` in the first of ``map_search_dirs()`` that has it (None: in none)."""
    for folder in map_search_dirs():
        candidate = folder / f"{name}.yaml"
        if candidate.is_file():
            return candidate
    return None


def available_maps() -> dict[str, Path]:
    """Every map a bare name finds: name -> YAML (the first folder of ``map_search_dirs()`` wins)."""
    found: dict[str, Path] = {}
    for folder in map_search_dirs():
        if folder.is_dir():
            for yaml in sorted(folder.glob("*.yaml")):
                found.setdefault(yaml.stem, yaml)
    return dict(sorted(found.items()))


def map_not_found(name: str) -> str:
    """One line for a bare map name no folder has: every folder searched, and the maps there are."""
    folders = ", ".join(str(d) for d in map_search_dirs())
    maps = ", ".join(available_maps()) or "none"
    return (f"map {name!r} not found: no {name}.yaml in {folders} (set LOCALIZATION_MAPS_DIR for another folder, "
            f"or give the YAML's path); maps available: {maps}")


def resolve_map_path(name_or_path) -> Path:
    """A map YAML path as given, or a bare map name looked up in ``map_search_dirs()`` (the first
    that has ``NAME.yaml``; when none has it, the package's path: ``map_not_found`` says where else
    it was looked for)."""
    if not is_map_name(name_or_path):
        return Path(name_or_path).expanduser()
    return find_map(str(name_or_path)) or package_maps_dir() / f"{name_or_path}.yaml"


def split_ros_args(argv) -> tuple[list[str], list[str]]:
    """Split a command line into (own arguments, the ``--ros-args ... [--]`` blocks for rclpy), each
    in its original order."""
    own: list[str] = []
    ros: list[str] = []
    inside = False
    for arg in argv:
        if arg == "--ros-args":
            inside = True
            ros.append(arg)
        elif inside and arg == "--":
            inside = False
            ros.append(arg)
        elif inside:
            ros.append(arg)
        else:
            own.append(arg)
    return own, ros


def parameter_files() -> list[str]:
    """The names of the node parameter files in the package's ``config/`` (YAML files with a
    ``ros__parameters`` section), sorted: what ``--params NAME`` accepts."""
    folder = config_dir()
    if not folder.is_dir():
        return []
    return sorted(p.stem for p in folder.glob("*.yaml") if "ros__parameters:" in p.read_text(errors="replace"))


def resolve_params_path(name_or_path) -> Path:
    """A parameter file as given when it exists or has a folder, else a bare name (``real_params``
    or ``real_params.yaml``) in the package's ``config/``."""
    path = Path(name_or_path).expanduser()
    if path.exists() or len(path.parts) > 1:
        return path
    return config_dir() / (path.name if path.suffix in (".yaml", ".yml") else f"{path.name}.yaml")


def cache_dir() -> Path:
    """``$LOCALIZATION_CACHE_DIR``, else ``$XDG_CACHE_HOME/localization`` (``~/.cache/localization``)."""
    env = os.environ.get("LOCALIZATION_CACHE_DIR")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / PACKAGE


@contextlib.contextmanager
def atomic_write(path):
    """``with atomic_write(p) as f: f.write(...)``: a binary file that appears whole or not at all."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
