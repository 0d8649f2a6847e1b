"""The search space: a YAML file naming parameters of the table, each with a range or a list of choices
(``config/tune_space.yaml``), and how a trial draws one value per entry."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from localization.core.parameters import BY_NAME
from localization.core.paths import config_dir, resolve_params_path
from localization.eval.tuning.errors import SpaceError


@dataclass(frozen=True)
class SpaceEntry:
    """One tuned parameter: a range [low, high] (``log``: sampled uniformly in log; ``step``: on a
    grid) or a list of ``choices``. Integer parameters of the table sample integers."""

    name: str
    low: float | int | None = None
    high: float | int | None = None
    log: bool = False
    step: float | int | None = None
    choices: tuple | None = None

    @property
    def is_int(self) -> bool:
        d = BY_NAME[self.name].default
        return isinstance(d, int) and not isinstance(d, bool)

    def suggest(self, trial):
        if self.choices is not None:
            return trial.suggest_categorical(self.name, list(self.choices))
        if self.is_int:
            return trial.suggest_int(self.name, int(self.low), int(self.high), step=int(self.step or 1), log=self.log)
        return trial.suggest_float(self.name, float(self.low), float(self.high), step=self.step, log=self.log)


def default_space_path() -> Path:
    return config_dir() / "tune_space.yaml"


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _entry(name: str, spec, where: str) -> SpaceEntry:
    if name not in BY_NAME:
        raise SpaceError(f"{where}: unknown parameter {name!r} (not in the parameter table, "
                         "localization/core/parameters.py)")
    p = BY_NAME[name]

    def ok(value) -> bool:
        if isinstance(p.default, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if type(value) is not type(p.default):
            return False
        return p.check is None or p.check(value)

    if isinstance(spec, list):
        spec = {"choices": spec}
    if not isinstance(spec, dict):
        raise SpaceError(f"{where}: {name}: expected {{low: A, high: B}} or {{choices: [...]}}, got {spec!r}")
    unknown = set(spec) - {"low", "high", "log", "step", "choices"}
    if unknown:
        raise SpaceError(f"{where}: {name}: unknown key(s) {', '.join(sorted(map(str, unknown)))} "
                         "(use low, high, log, step or choices)")
    if "choices" in spec:
        choices = spec["choices"]
        if set(spec) != {"choices"} or not isinstance(choices, list) or not choices:
            raise SpaceError(f"{where}: {name}: choices must be a non-empty list, alone")
        bad = [c for c in choices if not ok(c)]
        if bad:
            raise SpaceError(f"{where}: {name}: choice {bad[0]!r} is not valid ({name} must be {p.rule or 'valid'})")
        return SpaceEntry(name, choices=tuple(choices))
    if isinstance(p.default, (bool, str)):
        raise SpaceError(f"{where}: {name} is not numeric: give it {{choices: [...]}}")
    if "low" not in spec or "high" not in spec:
        raise SpaceError(f"{where}: {name}: needs both low and high")
    low, high, log, step = spec["low"], spec["high"], spec.get("log", False), spec.get("step")
    if not (_number(low) and _number(high)):
        raise SpaceError(f"{where}: {name}: low and high must be finite numbers, got {low!r}, {high!r}")
    if not low < high:
        raise SpaceError(f"{where}: {name}: low ({low}) must be below high ({high})")
    if not isinstance(log, bool):
        raise SpaceError(f"{where}: {name}: log must be true or false, got {log!r}")
    if log and low <= 0:
        raise SpaceError(f"{where}: {name}: a log range needs low > 0, got {low}")
    if step is not None and not (_number(step) and step > 0):
        raise SpaceError(f"{where}: {name}: step must be a positive number, got {step!r}")
    if log and step is not None and not isinstance(p.default, int):
        raise SpaceError(f"{where}: {name}: give log or step, not both")
    is_int = isinstance(p.default, int)
    if is_int and not all(float(v).is_integer() for v in (low, high, step or 1)):
        raise SpaceError(f"{where}: {name} is an integer parameter: low, high and step must be integers")
    if is_int and log and step not in (None, 1):
        raise SpaceError(f"{where}: {name}: give log or step, not both")
    for v in (low, high):
        if not ok(int(v) if is_int else v):
            raise SpaceError(f"{where}: {name}: {v} is out of the parameter's range ({name} must be {p.rule})")
    return SpaceEntry(name, int(low) if is_int else float(low), int(high) if is_int else float(high), log,
                      (int(step) if is_int else float(step)) if step is not None else None)


def load_space(path=None) -> list[SpaceEntry]:
    """The search space of a YAML file (default ``config/tune_space.yaml``; a bare name is looked up
    in the package's config/): ``name: {low: A, high: B[, log: true][, step: S]}`` or
    ``name: {choices: [...]}`` per parameter. Raises SpaceError (one line)."""
    import yaml

    path = default_space_path() if path is None else resolve_params_path(path)
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except FileNotFoundError:
        raise SpaceError(f"search space file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SpaceError(f"cannot read search space file {path}: {exc}") from None
    except yaml.YAMLError as exc:
        first = " ".join(str(exc).split())
        raise SpaceError(f"search space file {path} is not valid YAML: {first}") from None
    if not isinstance(doc, dict) or not doc:
        raise SpaceError(f"search space file {path}: expected a mapping of parameter names to ranges")
    return [_entry(str(name), spec, str(path)) for name, spec in doc.items()]


def space_from_dict(doc: dict, where: str = "search space") -> list[SpaceEntry]:
    return [_entry(str(name), spec, where) for name, spec in doc.items()]
