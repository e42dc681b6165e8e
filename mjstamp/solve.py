"""Solve a task: STAMP on its log posterior, then decode, verify and group the plans.

Which plans are *returned*: the particles whose MJX rollout (the planner's own
model) satisfies the task's success predicate; each is then replayed in MuJoCo
C with the scene's own solver settings, and counts as *verified* when the
predicate holds there too. The task plan of a verified plan is read off its C
replay.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mjstamp import plans as plans_mod
from mjstamp import svgd
from mjstamp.tracecache import cached_jit

STAMP_KEYS = ("svgd_learning_rate", "sgd_learning_rate", "svgd_max_iters", "sgd_max_iters",
              "min_iters", "jacobian")


@dataclasses.dataclass
class SolveResult:
    """Everything a solve produced (see `summary` for the JSON view)."""

    task: Any
    config: dict
    theta: np.ndarray
    svgd_theta: np.ndarray
    initial_theta: np.ndarray
    cost: np.ndarray
    returned: np.ndarray
    predicted: plans_mod.Decoded
    verified: plans_mod.Decoded
    replay: plans_mod.Replay
    diagnostics: svgd.StampDiagnostics
    stamp: svgd.StampResult
    rows: list[dict]
    timings: dict[str, float]

    @property
    def verified_fraction(self) -> float:
        """Share of returned plans whose MuJoCo C replay succeeds."""
        n = int(self.returned.sum())
        return float((self.verified.ok & self.returned).sum() / n) if n else 0.0

    def verified_mask(self) -> np.ndarray:
        """(n,) returned and verified in MuJoCo C."""
        return self.returned & self.verified.ok

    def summary(self, coverage: dict | None = None) -> dict:
        """JSON-ready summary (also the body of plans.json)."""
        ok = self.verified_mask()
        found = sorted({p for p, good in zip(self.verified.plan, ok, strict=True) if good})
        codes = sorted({c for c, good in zip(self.verified.code, ok, strict=True) if good})
        out = {
            "task": self.task.name,
            "particles": int(self.theta.shape[0]),
            "seed": int(self.config.get("seed", 0)),
            "wall_time_s": self.timings["total_s"],
            "timings": self.timings,
            "returned_plans": int(self.returned.sum()),
            "verified_plans": int(ok.sum()),
            "verified_fraction": self.verified_fraction,
            "distinct_verified_task_plans": len(found),
            "distinct_verified_codes": len(codes),
            "verified_codes": codes,
            "task_plans": [
                {k: r[k] for k in ("task_plan", "code", "plans", "verified", "verified_share",
                                   "best_cost")}
                for r in self.rows
            ],
            "plans": [
                {
                    "particle": int(i),
                    "task_plan": self.verified.plan[i],
                    "predicted_task_plan": self.predicted.plan[i],
                    "verified": bool(self.verified.ok[i]),
                    "cost": float(self.cost[i]),
                    "motion_plan": {
                        name: np.asarray(val[i]).tolist()
                        for name, val in self.task.unpack(self.theta).items()
                    },
                }
                for i in np.flatnonzero(self.returned)
            ],
            "iteration_seconds": _iteration_seconds(self.diagnostics),
            "stamp": {
                "svgd_iters": self.stamp.svgd_iters,
                "sgd_iters": self.stamp.sgd_iters,
                "svgd_converged": self.stamp.svgd_converged,
                "sgd_converged": self.stamp.sgd_converged,
            },
            "config": self.config,
            "declaration": self.task.describe(),
        }
        if coverage is not None:
            out["coverage"] = coverage["coverage"]
            out["coverage_detail"] = coverage
        return out

    def arrays(self) -> dict[str, dict[str, np.ndarray]]:
        """Arrays for the result files: particles.npz and trajectories.npz."""
        d = self.diagnostics
        particles = {
            "theta": self.theta, "svgd_theta": self.svgd_theta,
            "initial_theta": self.initial_theta, "cost": self.cost,
            "returned": self.returned, "verified": self.verified.ok,
            # Task plan of every particle's C replay (returned or not), for figures.
            "task_plan": np.asarray(self.verified.plan, dtype=str),
            "predicted_task_plan": np.asarray(self.predicted.plan, dtype=str),
            "logdensity_mean": d.logdensity_mean, "logdensity_max": d.logdensity_max,
            "phase": d.phase, "displacement": d.displacement, "step_seconds": d.step_seconds,
        }
        idx = np.flatnonzero(self.returned)
        qpos0, qvel0, _ = self.task.inputs(self.task.unpack(self.theta[idx]), xp=np)
        trajectories = {
            "particle": idx,
            "qpos0": np.asarray(qpos0, np.float64),
            "qvel0": np.asarray(qvel0, np.float64),
            "qpos": self.replay.qpos[idx],
            "qvel": self.replay.qvel[idx],
            "ctrl": self.replay.ctrl[idx],
            "xpos": self.replay.xpos[idx],
            "timestep": np.float64(self.task.scene.m.opt.timestep),
        }
        return {"particles": particles, "trajectories": trajectories}


def _iteration_seconds(d: svgd.StampDiagnostics) -> dict[str, float | None]:
    """Per phase: the first iteration (compile or cache load included) and the median."""
    out: dict[str, float | None] = {}
    for phase, name in ((svgd.PHASE_SVGD, "svgd"), (svgd.PHASE_SGD, "sgd")):
        t = d.step_seconds[d.phase == phase]
        out[f"{name}_first"] = float(t[0]) if len(t) else None
        out[f"{name}_median"] = float(np.median(t[1:])) if len(t) > 1 else None
    return out


def _jit(fn, task, name: str, *example):
    """jax.jit, through the trace cache when the task has a `cache_key`.

    Only registered tasks have one (their code is mjstamp's, whose source the
    trace cache hashes, and their config is the key); a task declared in a
    user's script may change without its key changing, so it is traced anew.
    """
    key = getattr(task, "cache_key", None)
    if key is None:
        return jax.jit(fn)
    return cached_jit(fn, f"{key} {name}", *example)


def solve(task, config: dict, *, seed: int = 0, progress: bool | None = None) -> SolveResult:
    """Runs STAMP on `task`, then decodes, verifies and groups the plans.

    Args:
      task: a `Task`.
      config: the task's config (particles, learning rates, iteration caps...).
      seed: makes the run reproducible.
      progress: tqdm bar; None shows it on a terminal.

    Returns:
      A `SolveResult`.
    """
    task.check()
    t_start = time.perf_counter()
    n = int(config["particles"])
    key = jax.random.key(seed)
    theta0 = task.initial_particles(key, n)
    stamp_config = svgd.StampConfig(
        seed=seed, **{k: config[k] for k in STAMP_KEYS if k in config}
    )
    discrete = {}
    if task.has_actions:
        # Discrete SVGD (eq. 4): the surrogate ρ relaxes actions with Γ̃, the target
        # p(Γ(θ)) and the SGD refinement take them at Γ. Γ has no gradient, so SGD
        # leaves the logits alone: App. E fixes them during SGD the same way.
        discrete = {
            "log_target_fn": lambda th: task.log_posterior(th, hard=True)[0],
            "sgd_logdensity_fn": task.logdensity(hard=True),
        }
    result = svgd.run_stamp(
        task.logdensity(), theta0, task.kernel(), stamp_config, progress=progress,
        jit=lambda step, state, key, phase: _jit(step, task, f"stamp-{phase}", state, key),
        **discrete,
    )
    jax.block_until_ready(result.particles)
    t_stamp = time.perf_counter()

    theta = np.asarray(result.particles, np.float64)
    theta_j = jnp.asarray(theta, task.scene.dtype)

    def final(th):
        """Cost and MJX trajectory of the final particles, from one rollout."""
        r, values = task.evaluate(th, hard=True)
        return task.cost_total(values), r.traj["qpos"]

    final = _jit(final, task, "final", theta_j)
    cost, qpos = jax.device_get(final(theta_j))
    cost = np.asarray(cost, np.float64)
    predicted_replay = plans_mod.Replay(task, np.asarray(qpos), source="mjx")
    predicted = plans_mod.decode(task, predicted_replay, theta)
    t_decode = time.perf_counter()
    replay = plans_mod.simulate_c(task, theta)
    verified = plans_mod.decode(task, replay, theta)
    t_verify = time.perf_counter()
    returned = predicted.ok & np.isfinite(cost)
    rows = plans_mod.group(cost, returned, predicted, verified)
    timings = {
        "stamp_s": t_stamp - t_start,
        "decode_s": t_decode - t_stamp,
        "verify_s": t_verify - t_decode,
        "total_s": time.perf_counter() - t_start,
    }
    return SolveResult(
        task=task, config={**config, "seed": seed}, theta=theta,
        svgd_theta=np.asarray(result.svgd_particles, np.float64),
        initial_theta=np.asarray(theta0, np.float64), cost=cost, returned=returned,
        predicted=predicted, verified=verified, replay=replay,
        diagnostics=result.diagnostics, stamp=result, rows=rows, timings=timings,
    )
