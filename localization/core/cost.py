"""The cost of a sensor update, in counts (not seconds): what the tests budget.

Timings depend on the machine and its load; counts do not. Per scan the core counts

- **beams cast**: rays cast (or looked up in the range table) and beam endpoints scored, by name.
  ``weigh`` is the sensor update itself, N particles × B beams; every other name is an extra on top
  of it: ``range_scale`` (the online range scale's probe, poses × B), ``agreement`` (the scan–map
  agreement of the estimate, B endpoints per pose scored), ``beam_skip`` (beam skipping's second look
  at every particle's beams, N × B), ``tempered`` (the extra stages of a tempered first update),
  ``challenger`` (a recovery's second cloud), ``global_seed`` (the lattice a global spread scores);
- **passes over the cloud**: each full numpy or compiled pass over the N particles (or their N
  weights), by name: ``motion`` (per odometry piece: the noise draw and the move), ``weigh`` (the
  fused sensor kernel), ``normalise``, ``ess``, ``resample``, ``estimate``, ``snapshot`` (the cloud
  copied before an update whose jump is judged), ... A numpy expression over N values is one pass
  per array it makes.

``CostMeter`` collects the counts while a scan goes through the pipeline (the localizer's parts and
models share one meter; not thread safe: used under the localizer's lock); ``take`` freezes them
into an ``UpdateCost`` (on ``ScanResult`` and in replay's metrics) and starts again.
"""
from __future__ import annotations

from dataclasses import dataclass

WEIGH = "weigh"  # the sensor update's own N × B beams


@dataclass(frozen=True)
class UpdateCost:
    """What one scan cost the core, in counts (module docstring)."""

    particles: int = 0  # N: the cloud the sensor update weighed (0: no sensor update)
    beams: int = 0  # B: the beams it offered each particle
    casts: tuple[tuple[str, int], ...] = ()  # (name, beams cast or scored), sorted by name
    passes: tuple[tuple[str, int], ...] = ()  # (name, full passes over a cloud), sorted by name

    @property
    def beams_cast(self) -> int:
        """Every beam cast or scored, the sensor update's N × B and the extras."""
        return sum(n for _, n in self.casts)

    @property
    def extras(self) -> dict[str, int]:
        """The beams cast or scored besides the sensor update's own, by name."""
        return {name: n for name, n in self.casts if name != WEIGH}

    @property
    def total_passes(self) -> int:
        return sum(n for _, n in self.passes)

    def cast(self, name: str) -> int:
        return dict(self.casts).get(name, 0)

    def passes_of(self, name: str) -> int:
        return dict(self.passes).get(name, 0)

    def as_dict(self) -> dict:
        return {"particles": self.particles, "beams": self.beams, "beams_cast": self.beams_cast,
                "casts": dict(self.casts), "passes": self.total_passes, "passes_by_name": dict(self.passes)}


NO_COST = UpdateCost()


class CostMeter:
    """Counts beams cast and passes over the cloud until ``take`` (module docstring)."""

    def __init__(self, prefix: str = "", counts: tuple[dict, dict] | None = None):
        self._prefix = prefix
        self._casts, self._passes = counts if counts is not None else ({}, {})

    def scoped(self, prefix: str) -> "CostMeter":
        """A meter writing to the same counts under ``prefix``: its beams as the one extra ``prefix``, its
        passes as ``prefix name`` (a challenger cloud's)."""
        return CostMeter(f"{self._prefix}{prefix} ", (self._casts, self._passes))

    def cast(self, name: str, beams: int) -> None:
        """``beams`` rays cast (or endpoints scored) for ``name``."""
        key = self._prefix.strip() or name  # a scoped meter's beams count under its scope (one named extra)
        self._casts[key] = self._casts.get(key, 0) + int(beams)

    def sweep(self, name: str, passes: int = 1) -> None:
        """``passes`` full passes over a cloud for ``name``."""
        key = f"{self._prefix}{name}"
        self._passes[key] = self._passes.get(key, 0) + int(passes)

    def take(self, particles: int = 0, beams: int = 0) -> UpdateCost:
        """The counts so far as an ``UpdateCost`` of a sensor update of ``particles`` × ``beams`` (0: none);
        the meter starts again from zero."""
        cost = UpdateCost(int(particles), int(beams), tuple(sorted(self._casts.items())),
                          tuple(sorted(self._passes.items())))
        self._casts.clear()
        self._passes.clear()
        return cost


@dataclass(frozen=True)
class CostBudget:
    """What one scan may cost (``check``), with N the particles weighed, B the beams offered and k the extra
    stages of a tempered update (its ``tempered`` beams ÷ N·B; 0 for a plain update):

    - the sensor update's own beams (``weigh``): at most ``weigh_factor`` × N × B;
    - each extra: at most a·B + b·N·B + c·W for its (name, a, b, c) in ``extras``, W the beams the filter
      weighed (``weigh`` and ``tempered``: N·B·(1 + k)); an extra not listed: none allowed;
    - passes over the cloud: those of a name in ``pass_caps`` (name, c, d) at most c + d·k; all the others
      together at most ``passes`` + ``passes_per_stage``·k."""

    weigh_factor: float = 1.1
    extras: tuple[tuple[str, float, float, float], ...] = ()  # (name, per B, per N·B, per beam weighed)
    passes: int = 0
    passes_per_stage: int = 0
    pass_caps: tuple[tuple[str, int, int], ...] = ()  # (name, passes, passes per extra stage)

    def check(self, cost: UpdateCost) -> list[str]:
        """What in ``cost`` exceeds the budget, one line each (empty: within it)."""
        n, b = cost.particles, cost.beams
        nb = n * b
        stages = cost.cast("tempered") / nb if nb else 0.0
        out = []
        if cost.cast(WEIGH) > self.weigh_factor * nb:
            out.append(f"weigh: {cost.cast(WEIGH)} beams cast > {self.weigh_factor} x {n} x {b}")
        weighed = cost.cast(WEIGH) + cost.cast("tempered")
        caps = {name: a * b + per_nb * nb + per_weighed * weighed for name, a, per_nb, per_weighed in self.extras}
        for name, beams in cost.extras.items():
            if beams > caps.get(name, 0):
                out.append(f"{name}: {beams} beams > its cap {caps.get(name, 0):.0f} (N = {n}, B = {b})")
        own = {name: base + per_stage * stages for name, base, per_stage in self.pass_caps}
        for name, cap in own.items():
            if cost.passes_of(name) > cap:
                out.append(f"{name}: {cost.passes_of(name)} passes over the cloud > its cap {cap:.0f}")
        rest = sum(k for name, k in cost.passes if name not in own)
        if rest > self.passes + self.passes_per_stage * stages:
            out.append(f"{rest} passes over the cloud > {self.passes + self.passes_per_stage * stages:.0f} "
                       f"({dict(cost.passes)})")
        return out


#: The budget ``test/test_cost_budget.py`` holds the shipped configurations to (real bags, docs/performance.md):
#: agreement: the estimate, the published pose of a judged jump, a challenger's estimate; range_scale: 7 poses
#: (the estimate and its ± steps in x, y, θ) per Gauss–Newton step, 2 steps; beam_skip: its two compiled looks
#: (the votes, the sum over the used beams) at the columns of every particle the filter weighed; tempered: at
#: most initial_update_stages − 1 extra stages. Passes: a plain update makes 13 (the RSS bags: a draw per
#: odometry piece and one move, the weighing's 3, the resampling's 3, the estimate's 3; beam skipping's check
#: adds 6); each extra stage of a tempered update weighs and normalises again; its numpy bisection
#: (``tempered``) and a move back in time (``shift``, numpy) have their own caps.
BUDGET = CostBudget(
    extras=(("agreement", 3, 0, 0), ("range_scale", 14, 0, 0), ("beam_skip", 0, 0, 2), ("tempered", 0, 7, 0)),
    passes=24, passes_per_stage=10, pass_caps=(("tempered", 180, 180), ("shift", 14, 0)))


def cost_summary(costs) -> dict:
    """Replay's figures of a run's costs (``UpdateCost`` per scan): per sensor update the beams cast ÷ N·B
    (median, max), each extra's beams ÷ B (median, max over the updates that had it), the passes over the
    cloud (median, max, and per name the max); per scan without a sensor update the passes (max)."""
    costs = list(costs)
    updates = [c for c in costs if c.particles > 0 and c.beams > 0]
    others = [c for c in costs if not (c.particles > 0 and c.beams > 0)]
    out = {"scans": len(costs), "sensor_updates": len(updates),
           "passes_without_update_max": max((c.total_passes for c in others), default=0)}
    if not updates:
        return out

    def med_max(values) -> dict:
        values = sorted(values)
        return {"median": values[len(values) // 2], "max": values[-1]}
    extras: dict[str, list] = {}
    by_name: dict[str, int] = {}
    for c in updates:
        for name, beams in c.extras.items():
            extras.setdefault(name, []).append(beams / c.beams)
        for name, k in c.passes:
            by_name[name] = max(by_name.get(name, 0), k)
    out.update(beams_cast_per_nb=med_max([c.beams_cast / (c.particles * c.beams) for c in updates]),
               extra_beams_per_b={name: med_max(v) for name, v in sorted(extras.items())},
               passes=med_max([c.total_passes for c in updates]), passes_max_by_name=dict(sorted(by_name.items())))
    return out
