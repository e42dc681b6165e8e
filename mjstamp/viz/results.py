"""A results directory, opened for playback, and the choice of which plans to play."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import mujoco
import numpy as np

from mjstamp import plans as plans_io
from mjstamp.errors import MjstampError, valid_list
from mjstamp.fileio import probe


@dataclasses.dataclass(frozen=True)
class Results:
    """What `mjstamp solve --out DIR` wrote, as playback needs it.

    Attributes:
      path: the directory.
      summary: contents of plans.json.
      model: the compiled scene (scene.mjb).
      trajectories: arrays of trajectories.npz: particle (r,), qpos0 (r, nq),
        qvel0 (r, nv), qpos (r, T, nq), qvel (r, T, nv), ctrl (r, T, nu), ...
    """

    path: Path
    summary: dict
    model: mujoco.MjModel
    trajectories: dict[str, np.ndarray]

    @property
    def task(self) -> str:
        """Name of the task that wrote the directory."""
        return str(self.summary.get("task", "?"))

    @property
    def display(self) -> dict:
        """Drawing hints of the task: {"trace": [body], "force": [[geom_a, geom_b]]}."""
        hints = self.summary.get("declaration", {}).get("display") or {}
        return {"trace": list(hints.get("trace", [])), "force": list(hints.get("force", []))}

    @property
    def timestep(self) -> float:
        """Seconds between two saved states."""
        if "timestep" in self.trajectories:
            return float(self.trajectories["timestep"])
        return float(self.model.opt.timestep)

    def row(self, particle: int) -> int:
        """Index in trajectories.npz of a returned particle's plan."""
        rows = np.flatnonzero(self.trajectories["particle"] == particle)
        if len(rows) == 0:
            raise MjstampError(
                f"{str(self.path)!r}: particle {particle} has no saved trajectory; valid: "
                + valid_list(self.trajectories["particle"].tolist())
            )
        return int(rows[0])


def load_results(path: str | os.PathLike, *, task: str | None = None) -> Results:
    """Opens a results directory for playback, checking it is complete and current.

    Args:
      path: directory written by `mjstamp solve TASK --out DIR`.
      task: if given, the task the directory must belong to.

    Raises:
      MjstampError: the directory does not exist or belongs to another task;
        any damage to its files (`plans.load`, `plans.load_model`: one line
        naming the file, what is wrong and what to do).
    """
    path = Path(path)
    if not probe(path.exists, path, "results directory "):
        raise MjstampError(f"results directory {str(path)!r} does not exist")
    if not path.is_dir():
        raise MjstampError(f"{str(path)!r} is not a directory (expected a results directory)")
    summary, arrays = plans_io.load(path)
    if task is not None and summary["task"] != task:
        raise MjstampError(
            f"{str(path)!r} holds plans of task {summary['task']!r}, not {task!r}"
        )
    traj = arrays["trajectories"]
    m = plans_io.load_model(path, trajectories=traj, task=summary["task"])
    return Results(path=path, summary=summary, model=m, trajectories=traj)


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
