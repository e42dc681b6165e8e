"""Baselines to compare STAMP with, on any task: enumerate, blocking, cem, cmaes.

    from mjstamp import baselines
    result = baselines.run("blocking", task, target=10, cap_s=300, seed=0)
    result.summary()["distinct_verified_task_plans"]

`mjstamp compare TASK` (and `benchmarks/paper/table1.py`) time each method to the
number of distinct verified task plans STAMP's default run finds.
"""

from __future__ import annotations

from mjstamp.baselines.common import BaselineResult, Tracker, candidates
from mjstamp.baselines.evolution import run_cmaes
from mjstamp.baselines.methods import run_blocking, run_cem, run_enumerate
from mjstamp.errors import MjstampError, valid_list

__all__ = ["METHODS", "BaselineResult", "Tracker", "candidates", "run"]

METHODS = {"enumerate": run_enumerate, "blocking": run_blocking, "cem": run_cem,
           "cmaes": run_cmaes}


def run(method: str, task, **kwargs) -> BaselineResult:
    """Runs baseline `method` on a task (settings: `baselines.methods`, `baselines.evolution`)."""
    if method not in METHODS:
        raise MjstampError(f"unknown method {method!r}; valid: {valid_list(METHODS)}")
    return METHODS[method](task, **kwargs)
