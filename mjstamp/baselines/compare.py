"""STAMP against the baselines on one task: Table I's layout (paper Q2).

For each seed, STAMP's default solve sets N, the distinct verified task plans
it found, and its wall time; each baseline then runs until it has verified N
distinct task plans or its cap is spent. A method's runtime is the mean over
seeds of its time to N (the cap where it did not get there, marked '>');
its factor is its runtime over STAMP's, with the standard deviation
propagated from both.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence

import numpy as np

from mjstamp.baselines import METHODS, run
from mjstamp.config import SolveConfig
from mjstamp.errors import MjstampError, valid_list
from mjstamp.progress import Progress

__all__ = ["ALL", "compare", "format_table", "parse_methods"]

ALL = ("stamp", *METHODS)


def parse_methods(text: str | Sequence[str]) -> list[str]:
    """["stamp", ...] from "stamp,enumerate"; one line naming the valid ones otherwise."""
    names = [m.strip() for m in (text.split(",") if isinstance(text, str) else text)]
    bad = [m for m in names if m not in ALL]
    if bad or not names or "" in names:
        raise MjstampError(f"unknown method {(bad or [''])[0]!r}; valid: {valid_list(ALL)}")
    return list(dict.fromkeys(names))


def _check(seeds, cap_s) -> None:
    if isinstance(seeds, bool) or not isinstance(seeds, int) or seeds < 1:
        raise MjstampError(f"seeds={seeds!r} must be an integer >= 1")
    if isinstance(cap_s, bool) or not isinstance(cap_s, (int, float)) or not cap_s > 0:
        raise MjstampError(f"cap={cap_s!r} must be a number of seconds > 0")


def compare(task_factory: Callable, *, methods: Sequence[str] = ALL, seeds: int = 3,
            cap_s: float = 600.0, solve_config=None, progress=False,
            warm_up: bool = True) -> dict:
    """Times every method to STAMP's distinct verified task plans, over `seeds` seeds.

    Args:
      task_factory: () -> (Task, solve config): a registered task's
        `registry.load`, or a user's own function.
      methods: of `ALL`; "stamp" is always run (it sets the target).
      seeds: seeds 0..seeds-1.
      cap_s: each baseline's wall-time cap per seed.
      solve_config: overrides of the solve settings (None: the task's own).
      progress: status lines (`mjstamp.progress`: a callable, a `Progress`, True;
        False: none).
      warm_up: run each method once briefly first, so that no method's
        first seed pays its compiles (STAMP's included).

    Returns:
      {method: {"runtime_mean_s", "runtime_std_s", "factor", "factor_std",
      "distinct_verified" (per seed), "reached" (per seed), "runtime_s" (per
      seed), "target" (per seed)}}.
    """
    from mjstamp.solver import solve  # noqa: PLC0415

    methods = parse_methods(methods)
    _check(seeds, cap_s)
    say = Progress.of(progress or False, "compare")  # N.B. None: silent, as before
    task, config = task_factory()
    if solve_config:
        base = config if isinstance(config, SolveConfig) else SolveConfig.from_dict(config)
        config = SolveConfig.from_dict(solve_config, base=base)
    baselines = [m for m in methods if m != "stamp"]
    if baselines and "enumerate" in baselines:
        from mjstamp.baselines.common import candidates  # noqa: PLC0415
        from mjstamp.solver import as_problem  # noqa: PLC0415

        candidates(as_problem(task))  # N.B. a task enumerate cannot apply to fails before any work
    if warm_up:
        say("warming up: STAMP and each method once, untimed (compiles, caches)")
        solve(task, config, seed=0, progress=False)
        for m in baselines:
            run(m, task, target=1, cap_s=min(cap_s, 60.0), seed=0, config=config)
    rows: dict[str, dict] = {m: {"runtime_s": [], "distinct_verified": [], "reached": [],
                                 "target": []} for m in ["stamp", *baselines]}
    for seed in range(seeds):
        started = time.perf_counter()
        summary = solve(task, config, seed=seed, progress=False).summary()
        stamp_s = time.perf_counter() - started
        target = summary["distinct_verified_task_plans"]
        say(f"seed {seed}: stamp {target} task plans in {stamp_s:.1f} s")
        _add(rows["stamp"], stamp_s, target, True, target)
        for m in baselines:
            if target == 0:
                _add(rows[m], 0.0, 0, True, 0)
                continue
            r = run(m, task, target=target, cap_s=cap_s, seed=seed, config=config)
            runtime = r.time_to(target)
            say(f"seed {seed}: {m} {len(r.found)}/{target} task plans in "
                f"{(runtime if runtime is not None else r.wall_s):.1f} s"
                f"{'' if r.reached else f' (cap {cap_s:g} s)'}")
            _add(rows[m], runtime if runtime is not None else cap_s, len(r.found), r.reached,
                 target)
    base = np.asarray(rows["stamp"]["runtime_s"])
    for m, row in rows.items():
        t = np.asarray(row["runtime_s"])
        row["runtime_mean_s"], row["runtime_std_s"] = float(t.mean()), float(t.std())
        # N.B. STAMP against itself is 1 exactly: its spread is in the others' factors.
        row["factor"], row["factor_std"] = (1.0, 0.0) if m == "stamp" else _ratio(t, base)
        row["reached_all"] = all(row["reached"])
    return rows


def _add(row: dict, runtime: float, found: int, reached: bool, target: int) -> None:
    row["runtime_s"].append(float(runtime))
    row["distinct_verified"].append(int(found))
    row["reached"].append(bool(reached))
    row["target"].append(int(target))


def _ratio(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """mean(a) / mean(b) and its standard deviation, propagated from both spreads."""
    ma, mb = float(a.mean()), float(b.mean())
    if mb <= 0:
        return math.nan, math.nan
    f = ma / mb
    rel = math.hypot(float(a.std()) / ma if ma > 0 else 0.0, float(b.std()) / mb)
    return f, f * rel


def format_table(task: str, rows: dict) -> str:
    """Table I's layout: method, runtime mean ± std, factor ± std, task plans found."""
    lines = [f"task {task}: time to STAMP's distinct verified task plans "
             f"(targets {rows['stamp']['target']})",
             f"{'method':<10}  {'runtime (s)':>17}  {'factor':>15}  found / target per seed",
             "-" * 72]
    for m, r in rows.items():
        mark = "" if r["reached_all"] else ">"
        runtime = f"{mark}{r['runtime_mean_s']:.1f} ± {r['runtime_std_s']:.1f}"
        factor = f"{mark}{r['factor']:.1f} ± {r['factor_std']:.1f}"
        found = ", ".join(f"{f}/{t}" for f, t in zip(r["distinct_verified"], r["target"],
                                                     strict=True))
        lines.append(f"{m:<10}  {runtime:>17}  {factor:>15}  {found}")
    if not all(r["reached_all"] for r in rows.values()):
        lines.append("> : did not reach the target within the cap on every seed (cap counted)")
    return "\n".join(lines)
