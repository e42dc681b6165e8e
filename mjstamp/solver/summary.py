"""What a solve writes: the plans.json summary, the .npz arrays and the table's rows.

`summarize` and `to_arrays` read a `SolveResult`; `group` makes the rows of
the table of task plans. The folder's schema, writing and reading it are
`mjstamp.results`'.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mjstamp.results import ROW_KEYS
from mjstamp.svgd import PHASE_SGD, PHASE_SVGD, StampDiagnostics, StampResult
from mjstamp.tasks.problem import Decoded


def summarize(result, coverage: dict | None = None) -> dict:
    """The JSON view of a solve: the body of plans.json (`SolveResult.summary`).

    Args:
      result: the solve.
      coverage: `modes.coverage` of its verified task plans against a sweep, or None.
    """
    ok = result.verified_mask()
    found = sorted({p for p, good in zip(result.verified.plan, ok, strict=True) if good})
    codes = sorted({c for c, good in zip(result.verified.code, ok, strict=True) if good})
    out = {
        "task": result.problem.name,
        "particles": int(result.theta.shape[0]),
        "devices": result.devices,
        "seed": int(result.config["seed"]),
        "wall_time_s": result.timings["total_s"],
        "timings": result.timings,
        "compiles": result.compiles,
        "returned_plans": int(result.returned.sum()),
        "verified_plans": int(ok.sum()),
        "repaired_plans": int((result.repaired & ok).sum()),
        "verified_fraction": result.verified_fraction,
        "verified_particle_share": float(ok.sum() / len(ok)),
        "distinct_verified_task_plans": len(found),
        "distinct_verified_codes": len(codes),
        "verified_codes": codes,
        # Returned plans the JAX signed distances decode otherwise than MuJoCo C (which decides).
        "symbol_disagreements": result.symbol_disagreements,
        "fidelity": result.fidelity,
        "screen": result.screen,
        "rescue": result.rescue,
        "loss": result.loss,
        "kept_from_earlier": {
            name: int(((result.source == name) & ok).sum())
            for name in ("landed", "unpolished", "svgd", "initial", "screen")
        },
        "polish": result.polish,
        "found": {plan: {k: v for k, v in f.items() if k != "theta"}
                  for plan, f in (result.found or {}).items()},
        "first_plan_s": min((f["seconds"] for f in (result.found or {}).values()),
                            default=None),
        "task_plans": [{k: r[k] for k in ROW_KEYS if k in r} for r in result.rows],
        "robustness": _robustness_summary(result.robustness),
        "cost_scale": result.problem.cost_scale,
        "robust_planning": None if result.problem.robust is None
        else result.problem.robust.describe(),
        "plans": _plans(result),
        "iteration_seconds": _iteration_seconds(result.diagnostics),
        "stamp": {
            "svgd_iters": result.stamp.svgd_iters,
            "sgd_iters": result.stamp.sgd_iters,
            "svgd_converged": result.stamp.svgd_converged,
            "sgd_converged": result.stamp.sgd_converged,
            "nonfinite_particles": _nonfinite_report(result.stamp),
        },
        "config": result.config,
        "declaration": result.problem.describe(),
    }
    if coverage is not None:
        out["coverage"] = coverage["coverage"]
        out["coverage_detail"] = coverage
    return out


def _robustness_summary(rob: dict | None) -> dict | None:
    """The robustness scoring's settings and the median score, or None (not scored)."""
    if rob is None:
        return None
    scored = rob["success"][np.isfinite(rob["success"])]
    return {k: rob[k] for k in ("samples", "seed", "seconds", "rollouts", "uncertain",
                                "declared")} | {
        "scored_plans": len(scored),
        "median": float(np.median(scored)) if len(scored) else None,
    }


def _plan_robustness(rob: dict | None, i: int) -> dict:
    """A verified plan's scores ({} when not scored)."""
    if rob is None or not np.isfinite(rob["success"][i]):
        return {}
    spread = rob["cost_std"][i]
    return {"robustness": float(rob["success"][i]),
            "robust_same_plan": float(rob["same_plan"][i]),
            "robust_cost_median": float(rob["cost_median"][i]),
            "robust_cost_std": float(spread) if np.isfinite(spread) else None}


def _plans(result) -> list[dict]:
    """plans.json's "plans": one entry per returned plan."""
    params = result.problem.unpack(result.theta)
    return [
        {
            "particle": int(i),
            "task_plan": result.verified.plan[i],
            "predicted_task_plan": result.predicted.plan[i],
            "verified": bool(result.verified.ok[i]),
            "repaired": bool(result.repaired[i]),
            "source": str(result.source[i]),
            "cost": float(result.cost[i]),
            "motion_plan": {name: np.asarray(val[i]).tolist() for name, val in params.items()},
            **_plan_robustness(result.robustness, i),
        }
        for i in np.flatnonzero(result.returned)
    ]


def _iteration_seconds(d: StampDiagnostics) -> dict[str, float | None]:
    """Per phase: the first iteration (compile or cache load included) and the median."""
    out: dict[str, float | None] = {}
    for phase, name in ((PHASE_SVGD, "svgd"), (PHASE_SGD, "sgd")):
        t = d.step_seconds[d.phase == phase]
        out[f"{name}_first"] = float(t[0]) if len(t) else None
        out[f"{name}_median"] = float(np.median(t[1:])) if len(t) > 1 else None
    return out


def _nonfinite_report(stamp: StampResult) -> dict[str, int]:
    """How many particles went non-finite: per iteration at most, iterations hit, re-draws."""
    counts = stamp.diagnostics.nonfinite_particles
    return {"max_per_iteration": int(counts.max(initial=0)),
            "iterations_with_any": int((counts > 0).sum()),
            "redrawn": int(stamp.nonfinite_redrawn.sum())}


def to_arrays(result) -> dict[str, dict[str, np.ndarray]]:
    """Arrays for the result files: particles.npz and trajectories.npz (`SolveResult.arrays`)."""
    d = result.diagnostics
    particles = {
        "theta": result.theta, "svgd_theta": result.svgd_theta,
        "initial_theta": result.initial_theta, "cost": result.cost,
        "returned": result.returned, "verified": result.verified.ok,
        "repaired": result.repaired, "source": np.asarray(result.source, dtype=str),
        # Task plan of every particle's C replay (returned or not), for figures.
        "task_plan": np.asarray(result.verified.plan, dtype=str),
        "predicted_task_plan": np.asarray(result.predicted.plan, dtype=str),
        "logdensity_mean": d.logdensity_mean, "logdensity_max": d.logdensity_max,
        "phase": d.phase, "displacement": d.displacement, "step_seconds": d.step_seconds,
    }
    if result.robustness is not None:
        particles["robustness"] = result.robustness["success"]
    idx = np.flatnonzero(result.returned)
    qpos0, qvel0, _ = result.problem.inputs(result.theta[idx], xp=np)
    replay = result.replay
    trajectories = {
        "particle": idx,
        "qpos0": np.asarray(qpos0, np.float64),
        "qvel0": np.asarray(qvel0, np.float64),
        "qpos": replay.qpos[idx],
        "qvel": replay.qvel[idx],
        "ctrl": replay.ctrl[idx],
        "xpos": replay.xpos[idx],
        "timestep": np.float64(result.problem.scene.m.opt.timestep),
    }
    return {"particles": particles, "trajectories": trajectories}


def group(cost: np.ndarray, returned: np.ndarray, predicted: Decoded, verified: Decoded,
          repaired: np.ndarray | None = None, robustness: np.ndarray | None = None):
    """Rows of the result table: one per task plan found among returned plans.

    Plans are grouped by the task plan of their MuJoCo C replay (what actually
    happens); a row counts the returned plans with that task plan, how many of
    them succeeded in C (verified), how many of those only after repair, and
    the best MJX cost among the verified; with `robustness` ((n,) success
    shares under uncertain physics, NaN where not scored), the best and the
    median score of its verified plans.
    """
    repaired = np.zeros(len(cost), bool) if repaired is None else repaired
    rows: dict[str, dict[str, Any]] = {}
    for i in np.flatnonzero(returned):
        key = verified.plan[i] if verified.ok[i] else f"{predicted.plan[i]} (failed)"
        row = rows.setdefault(key, {
            "task_plan": key, "code": verified.code[i], "plans": 0, "verified": 0,
            "repaired": 0, "best_cost": None, "particles": [],
        })
        row["plans"] += 1
        row["particles"].append(int(i))
        if verified.ok[i]:
            row["verified"] += 1
            row["repaired"] += int(repaired[i])
            c = float(cost[i])
            row["best_cost"] = c if row["best_cost"] is None else min(row["best_cost"], c)
    out = sorted(rows.values(), key=lambda r: (-r["verified"], r["task_plan"]))
    for r in out:
        r["verified_share"] = r["verified"] / r["plans"]
        if robustness is not None:
            scores = [float(robustness[i]) for i in r["particles"]
                      if verified.ok[i] and np.isfinite(robustness[i])]
            r["robustness_best"] = max(scores) if scores else None
            r["robustness_median"] = float(np.median(scores)) if scores else None
    return out


__all__ = ["group", "summarize", "to_arrays"]
