"""Argument types and helpers shared by the console scripts (one copy each)."""
from __future__ import annotations

import argparse
import math
import os
import re
import sys
from pathlib import Path

from localization.core.parameters import BY_NAME, ParameterError, Parameters
from localization.core.paths import find_map, is_map_name, map_not_found, parameter_files, resolve_params_path


def floats(text: str, n: int | None = None) -> tuple:
    """``"a,b,c"`` -> (a, b, c), all finite; ``n``: exactly that many."""
    try:
        vals = tuple(float(v) for v in text.replace(" ", "").split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
    if n is not None and len(vals) != n:
        raise argparse.ArgumentTypeError(f"expected {n} comma-separated numbers, got {text!r}")
    if not all(math.isfinite(v) for v in vals):
        raise argparse.ArgumentTypeError(f"expected finite numbers, got {text!r}")
    return vals


def pose(text: str) -> tuple:
    """``X,Y,YAW`` (metres, metres, radians)."""
    try:
        return floats(text, 3)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected X,Y,YAW (three numbers), got {text!r}") from None


#: the argument types whose values may start with '-' (``--initial-pose -1,2,0``)
NUMBER_TYPES = (floats, pose)
#: a value of those types that argparse would take for an option: '-1,2,0', '-6.0,20.0,-2.24', '-1e-3,0,0',
#: '-1,2;3,4' (waypoints)
_NEGATIVE_NUMBERS = re.compile(r"-\.?\d[\d.eE+-]*(\s*[,;]\s*-?\.?\d[\d.eE+-]*)*")


class Parser(argparse.ArgumentParser):
    """The tools' argument parser: a number list starting with '-' is taken as the value of an option of
    ``NUMBER_TYPES`` or added with ``numbers=True`` (``--initial-pose -1,2,0``, not only
    ``--initial-pose=-1,2,0``), where argparse alone would read it as an unknown option. Everything else is
    argparse's own."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._number_options: set = set()

    def add_argument(self, *args, numbers: bool = False, **kwargs):
        action = super().add_argument(*args, **kwargs)
        if (numbers or kwargs.get("type") in NUMBER_TYPES) and action.nargs is None and action.option_strings:
            self._number_options.update(action.option_strings)
        return action

    def parse_known_args(self, args=None, namespace=None):
        argv = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(join_negative_values(argv, self._number_options), namespace)


def join_negative_values(argv: list, options) -> list:
    """``[..., OPTION, "-1,2,0", ...]`` -> ``[..., "OPTION=-1,2,0", ...]`` for each of ``options`` (up to a
    ``--`` that ends the options)."""
    out: list = []
    k = 0
    while k < len(argv):
        arg = argv[k]
        if arg == "--":
            return out + argv[k:]
        if arg in options and k + 1 < len(argv) and _NEGATIVE_NUMBERS.fullmatch(str(argv[k + 1])):
            out.append(f"{arg}={argv[k + 1]}")
            k += 2
            continue
        out.append(arg)
        k += 1
    return out


IMAGE_SUFFIXES = (".png", ".pgm", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def map_name_or_yaml(text: str) -> str:
    """``--map``: a map_server YAML or a map name; the map's image is refused with the YAML to give (a name
    no maps folder has is refused when the map is loaded: ``load_map``)."""
    suffix = Path(text).suffix.lower()
    if suffix in IMAGE_SUFFIXES:
        stem = text[: -len(suffix)]
        raise argparse.ArgumentTypeError(f"{text} is the map's image: give its map_server YAML ({stem}.yaml) or "
                                         f"the map name ({Path(stem).name})")
    return text


def load_map(name_or_path):
    """The map of ``--map`` (``core.occupancy_map.load_map``); a bare name no maps folder has raises
    MapError naming every folder searched and the maps available (``paths.map_not_found``)."""
    from localization.core.occupancy_map import MapError
    from localization.core.occupancy_map import load_map as load_occupancy_map
    if is_map_name(name_or_path) and find_map(str(name_or_path)) is None:
        raise MapError(map_not_found(str(name_or_path)))
    return load_occupancy_map(name_or_path)


def _float_from(text: str, allow_zero: bool) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(value) and (value >= 0 if allow_zero else value > 0)):
        raise argparse.ArgumentTypeError(f"must be a {'non-negative' if allow_zero else 'positive'} number: {text!r}")
    return value


def positive_float(text: str) -> float:
    return _float_from(text, allow_zero=False)


def non_negative_float(text: str) -> float:
    return _float_from(text, allow_zero=True)


_PARAM_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_.]*")


def param_override(text: str) -> tuple:
    """``NAME=VALUE`` or the ROS spelling ``NAME:=VALUE`` with VALUE parsed as YAML
    (``-p num_particles=500``, ``-p recovery:=false``); NAME must be a parameter of the table."""
    import yaml

    sep = min((i for i in (text.find(":="), text.find("=")) if i >= 0), default=-1)
    if sep <= 0:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE or NAME:=VALUE, got {text!r}")
    name = text[:sep].strip()
    value = text[sep + (2 if text.startswith(":=", sep) else 1):]
    if not _PARAM_NAME.fullmatch(name):
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE or NAME:=VALUE, got {text!r}")
    if name not in BY_NAME:
        raise argparse.ArgumentTypeError(f"unknown parameter {name!r} in {text!r}")
    try:
        return name, yaml.safe_load(value)
    except yaml.YAMLError:
        raise argparse.ArgumentTypeError(f"value of {name} is not valid YAML: {value!r}") from None


def topic_list(text: str) -> list:
    """``/scan,/vesc/odom``: one or more topic names, comma-separated (an option taking one value
    cannot swallow a positional argument that follows it)."""
    topics = [t.strip() for t in text.split(",") if t.strip()]
    bad = [t for t in topics if not re.fullmatch(r"/?[A-Za-z_~][A-Za-z0-9_/~]*", t)]
    if not topics or bad:
        raise argparse.ArgumentTypeError(f"expected comma-separated topic names (/scan,/odom), got {text!r}")
    return topics


def output_problem(path, overwrite: bool, kind: str = "folder") -> str | None:
    """Why ``path`` cannot be written, checked before any work is done (None: it can): an existing
    non-empty output without ``overwrite``, a file where a folder is wanted (or the reverse), or a
    parent folder that does not exist (``kind="file"``: the file's own folder is not created)."""
    path = Path(path)
    if path.exists():
        if kind == "file" and path.is_dir():
            return f"{path} is a folder: give a file name"
        if kind == "folder" and not path.is_dir():
            return f"{path} exists and is not a folder"
        non_empty = any(path.iterdir()) if path.is_dir() else path.stat().st_size > 0
        if non_empty and not overwrite:
            return f"{path} exists already: choose another name, or pass --overwrite to replace it"
    if kind == "file":
        parent = path.parent if str(path.parent) else Path(".")
        if not parent.is_dir():
            return f"folder {parent} of {path} does not exist"
        if not os.access(parent, os.W_OK):
            return f"cannot write in {parent}"
    return None


def load_parameters(params_file, overrides: dict) -> Parameters:
    """The parameter file (a path or a name in the package's config/, e.g. ``real_params``) with
    ``overrides``; raises ParameterError (one line) for a missing file or a bad value."""
    if params_file is None:
        return Parameters(overrides)
    path = resolve_params_path(params_file)
    if not Path(path).is_file():
        raise ParameterError(f"parameter file not found: {path}")
    return Parameters.from_yaml(path, **overrides)


#: the car's parameter file in the package's config/ (the RSS 2022 RACECAR bags)
REAL_PARAMS = "real_params"



def params_names() -> str:
    """The parameter files ``--params NAME`` accepts, for a help text: ``params, pioneer_params, ...``."""
    return ", ".join(parameter_files()) or "none found"


PARAMS_HELP = ("ROS 2 parameter file, or a name in the package's config/ (" + params_names() + "); default: the "
               "built-in defaults, or config/real_params.yaml when the bag has the car's odometry topic "
               "(/vesc/odom) and not /odom (said on stderr)")


def _topics_of(bag) -> set | None:
    from localization.bags import BagError, open_bag
    try:
        with open_bag(bag) as b:
            return set(b.topic_infos)
    except BagError:
        return None


def parameters_for_bags(params_file, overrides: dict, bags, odom_topic: str | None = None, prog: str = "",
                        say=None) -> Parameters:
    """The parameters a tool runs with: ``params_file`` (a path or a name in config/) when given;
    else the built-in defaults, unless every bag lacks the defaults' odometry topic (``/odom``, the
    simulator's) and has the car's (``config/real_params.yaml``'s ``/vesc/odom``): then the car's
    parameter file, said in one line on stderr (``say``). A given ``odom_topic`` keeps the
    defaults. Raises ParameterError (one line) for a missing file or a bad value."""
    params = load_parameters(params_file, overrides)
    if params_file is not None or odom_topic:
        return params
    seen = [_topics_of(b) for b in bags if Path(b).exists()]
    if not seen or any(t is None for t in seen):
        return params
    real = load_parameters(REAL_PARAMS, overrides)
    if any(params.odom_topic in t or real.odom_topic not in t for t in seen):
        return params
    (say or (lambda line: print(line, file=sys.stderr)))(
        f"{prog + ': ' if prog else ''}note: no --params given and the bag has {real.odom_topic}, not "
        f"{params.odom_topic}: using the car's parameters (config/{REAL_PARAMS}.yaml); pass --params params "
        "for the simulator's")
    return real
