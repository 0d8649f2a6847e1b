"""Argument types and helpers shared by the console scripts (one copy each)."""
from __future__ import annotations

import argparse
import math
from pathlib import Path

from localization.core.parameters import ParameterError, Parameters
from localization.core.paths import resolve_params_path


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


IMAGE_SUFFIXES = (".png", ".pgm", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def map_name_or_yaml(text: str) -> str:
    """``--map``: a map_server YAML or a map name; the map's image is refused with the YAML to give."""
    suffix = Path(text).suffix.lower()
    if suffix in IMAGE_SUFFIXES:
        stem = text[: -len(suffix)]
        raise argparse.ArgumentTypeError(f"{text} is the map's image: give its map_server YAML ({stem}.yaml) or "
                                         f"the map name ({Path(stem).name})")
    return text


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


def param_override(text: str) -> tuple:
    """``NAME=VALUE`` with VALUE parsed as YAML (``-p num_particles=500``)."""
    import yaml
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
    name, value = text.split("=", 1)
    return name.strip(), yaml.safe_load(value)


def load_parameters(params_file, overrides: dict) -> Parameters:
    """The parameter file (a path or a name in the package's config/, e.g. ``real_params``) with
    ``overrides``; raises ParameterError (one line) for a missing file or a bad value."""
    if params_file is None:
        return Parameters(overrides)
    path = resolve_params_path(params_file)
    if not Path(path).is_file():
        raise ParameterError(f"parameter file not found: {path}")
    return Parameters.from_yaml(path, **overrides)


