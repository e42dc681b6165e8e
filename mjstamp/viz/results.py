"""The choice of which plans of a results directory (`mjstamp.results.Results`) to play."""

from __future__ import annotations

import numpy as np

from mjstamp.errors import MjstampError, valid_list
from mjstamp.results import Results


def select_plans(
    results: Results,
    *,
    plan: int | list[int] | None = None,
    task_plan: str | None = None,
) -> list[dict]:
    """Plans to play, as entries of plans.json's "plans" (particle, task_plan, ...).

    By default one plan per mode: for every task plan with verified plans, in
    the order of the result table, its verified plan of least cost.

    Args:
      results: the opened directory.
      plan: particle index (or indices) of returned plans to play, in order.
      task_plan: play every verified plan of this task plan (failed ones for a
        "... (failed)" row), least cost first.

    Raises:
      MjstampError: both or an unknown `plan` / `task_plan` given, or nothing to play.
    """
    entries = list(results.summary.get("plans", []))
    by_particle = {int(e["particle"]): e for e in entries}
    if plan is not None and task_plan is not None:
        raise MjstampError("give a plan or a task plan to play, not both")
    if plan is not None:
        wanted = [plan] if isinstance(plan, int | np.integer) else list(plan)
        out = []
        for p in wanted:
            if int(p) not in by_particle:
                raise MjstampError(
                    f"plan {p} is not among the returned plans of {str(results.path)!r}; "
                    f"valid: {valid_list(sorted(by_particle))}"
                )
            out.append(by_particle[int(p)])
        return out
    rows = [r["task_plan"] for r in results.summary.get("task_plans", [])]
    if task_plan is not None:
        failed = task_plan.endswith(" (failed)")
        name = task_plan.removesuffix(" (failed)")
        out = [
            e for e in entries
            if (not failed and e["verified"] and e["task_plan"] == name)
            or (failed and not e["verified"] and e.get("predicted_task_plan") == name)
        ]
        if not out:
            raise MjstampError(
                f"task plan {task_plan!r} has no plans in {str(results.path)!r}; valid: "
                f"{valid_list(rows)}"
            )
        return sorted(out, key=lambda e: e["cost"])
    best: dict[str, dict] = {}
    for e in entries:
        if e["verified"] and (e["task_plan"] not in best
                              or e["cost"] < best[e["task_plan"]]["cost"]):
            best[e["task_plan"]] = e
    order = [r for r in rows if r in best] + sorted(set(best) - set(rows))
    if not order:
        raise MjstampError(
            f"{str(results.path)!r} holds no verified plans; choose returned ones with "
            f"--plan (valid: {valid_list(sorted(by_particle))})"
        )
    return [best[r] for r in order]
