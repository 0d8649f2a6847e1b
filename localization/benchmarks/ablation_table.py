"""The ablation's one table (``python -m localization.benchmarks.ablation``): rows = the baseline and each
mechanism switched off, columns = the figures of the replays, each the mean ± sample standard deviation
over the filter seeds.

A job's figures are one flat dict per bag or run (keys below, by group); a column reduces the figures of
its group's jobs for one row and one seed to one number, and the seeds give the cell.

**The rule.** A figure of a row *moves* when the row's mean over the seeds lies outside the baseline's
range over the same seeds (its min–max), widened by half the last printed digit (so a difference the
table cannot show does not count). Counts (false recoveries, runs converged) are whole numbers and get no
widening. A cell whose jobs all ran with the baseline's very parameters and data (the switch is already
off for that robot, or the data give it nothing to act on) is the baseline's, printed ``=``, and never
moves.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

GROUPS = ("rss", "pioneer", "perturbed", "global", "kidnap")
GLOBAL_WITHIN_S = 5.0  # s of driving: a global start converged in time (robustness.bench_global's target)
KIDNAP_WITHIN_S = 15.0  # s after the teleport: back in time (robustness.KIDNAP_WITHIN_S)


def _values(figures: list, key: str) -> list:
    return [float(f[key]) for f in figures if f.get(key) is not None]


def mean_of(key: str, absolute: bool = False) -> Callable:
    def reduce(figures):
        v = _values(figures, key)
        return float(np.mean(np.abs(v) if absolute else v)) if v else None
    return reduce


def max_of(key: str) -> Callable:
    return lambda figures: max(_values(figures, key), default=None)


def min_of(key: str) -> Callable:
    return lambda figures: min(_values(figures, key), default=None)


def sum_of(key: str) -> Callable:
    return lambda figures: float(sum(_values(figures, key))) if any(f.get(key) is not None for f in figures) \
        else None


def within(key: str, limit: float) -> Callable:
    """How many runs reached it within ``limit`` (a None figure: never)."""
    return lambda figures: float(sum(f.get(key) is not None and f[key] <= limit for f in figures)) \
        if figures else None


def median_time(key: str) -> Callable:
    """The median over the runs (never: +inf)."""
    def reduce(figures):
        v = [math.inf if f.get(key) is None else float(f[key]) for f in figures]
        return float(np.median(v)) if v else None
    return reduce


@dataclass(frozen=True)
class Column:
    key: str
    title: str
    groups: tuple  # the job groups whose figures it reduces
    reduce: Callable  # list of figure dicts (one per bag or run) -> number or None
    better: str  # "lower" or "higher"
    meaning: str
    decimals: int = 3
    count: bool = False  # whole numbers per seed: no widening, means printed with up to 2 decimals

    @property
    def tolerance(self) -> float:
        return 0.0 if self.count else 0.5 * 10.0 ** -self.decimals


COLUMNS = (
    Column("rss_median", "RSS med", ("rss",), mean_of("median"), "lower",
           "RSS held out: median error vs the yardstick (m), mean over the three bags"),
    Column("rss_p95", "RSS p95", ("rss",), mean_of("p95"), "lower",
           "RSS held out: p95 error vs the yardstick (m), mean over the bags"),
    Column("rss_along", "RSS along", ("rss",), mean_of("along", absolute=True), "lower",
           "RSS held out: |mean along-track error| vs the yardstick (m), mean over the bags"),
    Column("pio_agree", "Pio agree", ("pioneer",), mean_of("agree"), "higher",
           "Pioneer held out: median scan-map agreement where the yardstick is confident, mean over the bags"),
    Column("pio_err", "Pio err", ("pioneer",), mean_of("err"), "lower",
           "Pioneer held out: median error vs the yardstick's confident poses (m), mean over the bags"),
    Column("pio_end", "Pio end", ("pioneer",), min_of("end"), "higher",
           "Pioneer held out: median agreement over a bag's last 10 s, the lowest bag"),
    Column("pert_mean", "Pert mean", ("perturbed",), mean_of("mean"), "lower",
           "perturbed-world trials: mean error vs the map-frame truth (m), mean over the runs"),
    Column("pert_p95", "Pert p95", ("perturbed",), mean_of("p95"), "lower",
           "perturbed-world trials: p95 error vs the map-frame truth (m), mean over the runs"),
    Column("glob_ok", "Global ok", ("global",), within("converged_s", GLOBAL_WITHIN_S), "higher",
           f"global starts below 0.3 m for good within {GLOBAL_WITHIN_S:g} s of driving", count=True),
    Column("kid_ok", "Kidnap ok", ("kidnap",), within("back_s", KIDNAP_WITHIN_S), "higher",
           f"kidnapped runs back below 0.3 m for good within {KIDNAP_WITHIN_S:g} s", count=True),
    Column("kid_s", "Kidnap s", ("kidnap",), median_time("back_s"), "lower",
           "kidnapped runs: median seconds until back below 0.3 m for good (never: inf)", decimals=1),
    Column("kid_jump", "Kidnap jump", ("kidnap",), max_of("jump_after"), "lower",
           "kidnapped runs: largest step between consecutive published estimates from the teleport on (m; a switch "
           "published at once is one step of the whole way)", decimals=2),
    Column("false", "false", GROUPS, sum_of("false"), "lower",
           "false recoveries, summed over the runs: RSS and perturbed, runs of estimates > 1 m from the yardstick or "
           "truth (the replay's); Pioneer, the demo's (> 1 m from the yardstick once converged); global starts and "
           "kidnappings, switches of the cloud to a place > 1 m from the truth",
           count=True),
    Column("jump", "jump", ("rss", "pioneer", "perturbed"), max_of("jump"), "lower",
           "largest step between consecutive published estimates once tracking (m), over the RSS, Pioneer "
           "and perturbed runs", decimals=2),
    Column("ms_rss", "ms RSS", ("rss",), mean_of("ms"), "lower",
           "cost: median sensor-update time (ms, wall clock) of the RSS replays, mean over the bags",
           decimals=1),
    Column("ms_sim", "ms sim", ("perturbed",), mean_of("ms"), "lower",
           "cost: median sensor-update time (ms, wall clock) of the perturbed-world replays, mean over the runs",
           decimals=1),
)


# --------------------------------------------------------------------------------------------
# Cells and the rule
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Stat:
    """One figure of one row over the seeds (None: that seed gave none)."""

    values: tuple
    inert: bool = False  # every job behind it ran with the baseline's parameters and data: the baseline's

    @property
    def finite(self) -> list:
        return [v for v in self.values if v is not None]

    @property
    def complete(self) -> bool:
        return bool(self.values) and len(self.finite) == len(self.values)

    @property
    def mean(self) -> float:
        return float(np.mean(self.finite)) if self.finite else math.nan

    @property
    def sd(self) -> float:
        v = self.finite
        if len(v) < 2 or not all(math.isfinite(x) for x in v):
            return 0.0 if len(v) == 1 else math.nan
        return float(np.std(v, ddof=1))

    @property
    def low(self) -> float:
        return min(self.finite) if self.finite else math.nan

    @property
    def high(self) -> float:
        return max(self.finite) if self.finite else math.nan


def moved(base: Stat | None, other: Stat | None, column: Column) -> str | None:
    """"worse" or "better" when ``other``'s mean lies outside ``base``'s min–max widened by the column's
    tolerance (module docstring); None when it does not, when either is incomplete, or ``other`` is inert."""
    if base is None or other is None or other.inert or not base.complete or not other.complete:
        return None
    m, lo, hi = other.mean, base.low - column.tolerance, base.high + column.tolerance
    if math.isnan(m) or lo <= m <= hi:
        return None
    higher = m > hi
    return "worse" if higher == (column.better == "lower") else "better"


def fmt_number(v: float, column: Column) -> str:
    if v is None or math.isnan(v):
        return "n/a"
    if math.isinf(v):
        return "never" if v > 0 else "-inf"
    if column.count:
        return f"{round(v, 2):g}"
    return f"{v:.{column.decimals}f}"


def fmt_cell(s: Stat | None, column: Column) -> str:
    """``mean ± sd``; ``=``: the baseline's (inert); ``n/a``: no figure."""
    if s is None or not s.finite:
        return "n/a"
    if s.inert:
        return "="
    text = f"{fmt_number(s.mean, column)} ± {fmt_number(s.sd, column)}"
    return text if s.complete else f"{text} ({len(s.finite)}/{len(s.values)} seeds)"


def fmt_range(s: Stat | None, column: Column) -> str:
    if s is None or not s.finite:
        return "n/a"
    return f"{fmt_number(s.low, column)}–{fmt_number(s.high, column)}"


# --------------------------------------------------------------------------------------------
# From job results to rows
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Outcome:
    """One job's figures: ``figures`` one dict per bag or run; ``inert``: not run, the baseline's copied."""

    group: str
    mechanism: str
    seed: int
    figures: tuple = ()
    inert: bool = False
    error: str | None = None


@dataclass
class Row:
    key: str  # "baseline" or a mechanism's name
    title: str
    switch: str  # the parameter override, as text
    cells: dict = field(default_factory=dict)  # column key -> Stat
    moves: dict = field(default_factory=dict)  # column key -> "worse" / "better"


def build_rows(outcomes: list, rows: list, seeds: list, columns=COLUMNS) -> list:
    """``rows``: (key, title, switch) in order, the baseline first; one ``Row`` each with a ``Stat`` per
    column whose groups ran (a seed with a failed job of the column's groups gives None)."""
    by = {}
    for o in outcomes:
        by.setdefault((o.mechanism, o.seed), []).append(o)
    ran = {o.group for o in outcomes}
    out = []
    for key, title, switch in rows:
        row = Row(key, title, switch)
        for c in columns:
            if not ran & set(c.groups):
                continue
            values, inert = [], True
            for seed in seeds:
                jobs = [o for o in by.get((key, seed), []) if o.group in c.groups]
                if not jobs or any(o.error is not None for o in jobs):
                    values.append(None)
                    continue
                inert &= all(o.inert for o in jobs)
                values.append(c.reduce([f for o in jobs for f in o.figures]))
            row.cells[c.key] = Stat(tuple(values), inert=inert and key != rows[0][0] and any(
                v is not None for v in values))
        out.append(row)
    base = out[0]
    for row in out[1:]:
        for k, s in row.cells.items():
            verdict = moved(base.cells.get(k), s, next(c for c in columns if c.key == k))
            if verdict is not None:
                row.moves[k] = verdict
    return out


def moves_text(row: Row, columns=COLUMNS) -> str:
    if not row.moves:
        return "none"
    titles = {c.key: c.title for c in columns}
    return ", ".join(f"{titles[k]} ({v})" for k, v in row.moves.items())


def _shown(rows: list, columns) -> list:
    return [c for c in columns if c.key in rows[0].cells]


def render_text(rows: list, columns=COLUMNS) -> str:
    """The table as fixed-width text: a baseline range line under the baseline, a ``*`` on a moved cell."""
    cols = _shown(rows, columns)
    body = [[r.title] + [fmt_cell(r.cells[c.key], c) + ("*" if c.key in r.moves else "") for c in cols]
            + ["" if i == 0 else moves_text(r, cols)] for i, r in enumerate(rows)]
    body.insert(1, ["  baseline min–max"] + [fmt_range(rows[0].cells[c.key], c) for c in cols] + [""])
    header = ["row"] + [c.title for c in cols] + ["moves beyond the baseline's spread"]
    widths = [max(len(line[k]) for line in [header] + body) for k in range(len(header))]
    return "\n".join("  ".join(cell.ljust(w) for cell, w in zip(line, widths)).rstrip()
                     for line in [header] + body)


def render_markdown(rows: list, columns=COLUMNS) -> str:
    """The table as markdown: moved cells in bold, the baseline's min–max in the second row."""
    cols = _shown(rows, columns)
    lines = ["| row | switched off by | " + " | ".join(c.title for c in cols) + " | moves beyond the baseline's "
             "spread |", "| --- | --- | " + " | ".join("---" for _ in cols) + " | --- |"]
    for i, r in enumerate(rows):
        cells = [f"**{fmt_cell(r.cells[c.key], c)}**" if c.key in r.moves else fmt_cell(r.cells[c.key], c)
                 for c in cols]
        moves = "" if i == 0 else moves_text(r, cols)
        lines.append(f"| {r.title} | {r.switch} | " + " | ".join(cells) + f" | {moves} |")
        if i == 0:
            lines.append("| *baseline min–max* | | " + " | ".join(fmt_range(r.cells[c.key], c) for c in cols)
                         + " | |")
    return "\n".join(lines)


def column_notes(rows: list, columns=COLUMNS) -> str:
    """One markdown bullet per column shown: its title and what it measures."""
    return "\n".join(f"- *{c.title}*: {c.meaning} ({'higher' if c.better == 'higher' else 'lower'} is better)"
                     for c in _shown(rows, columns))
