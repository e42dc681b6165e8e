"""Repair: a local search in MuJoCo C for plans that fail there.

A plan found on the gradient model can miss in the scene's own physics by a
hair (a ball that grazes a pocket's edge). `repair` moves it, by batched C
replays around it, until it succeeds there, keeping its task plan where it can.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from mjstamp.tasks.declaration import Kind
from mjstamp.tasks.problem import as_problem
from mjstamp.verify.replay import cost_c, decode, simulate_c


@dataclasses.dataclass
class Repair:
    """What `repair` did to m plans.

    Attributes:
      theta: (m, d) the plans after repair (unchanged where not repaired).
      repaired: (m,) whether a plan now verifies in MuJoCo C.
      rollouts: MuJoCo C rollouts spent.
      seconds: wall time.
    """

    theta: np.ndarray
    repaired: np.ndarray
    rollouts: int
    seconds: float


def _box(problem) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(low, high, movable, clip) per coordinate of θ; discrete logits are not moved."""
    low, high = problem.low, problem.high
    movable = np.concatenate([np.full(v.size, v.kind is not Kind.DISCRETE)
                              for v in problem.variables])
    clip = np.concatenate([np.full(v.size, v.kind is Kind.BOX) for v in problem.variables])
    return low, high, movable, clip


def repair(
    task,
    theta: np.ndarray,
    target: np.ndarray | None = None,
    *,
    rounds: int = 8,
    samples: int = 32,
    seed: int = 0,
) -> Repair:
    """Refines plans whose MuJoCo C replay fails, by a local search in MuJoCo C.

    Each round draws `samples` candidates per plan around its current centre,
    Gaussian with a scale per candidate spread log-uniformly from 0.1% to 5%
    of each coordinate's box width (discrete logits stay fixed), replays them
    all in one batched C rollout and decodes them like any plan. A plan is
    repaired by its best successful candidate (one with the `target` task plan
    first, then the lowest cost in C); otherwise the centre moves to the
    candidate with the lowest cost in C (the task's own costs on the C
    replay), if lower. The budget is `rounds · samples` rollouts per plan.

    Args:
      task: the `Task`.
      theta: (m, d) plans that fail in MuJoCo C.
      target: (m,) task plans they were meant to have (their MJX decode), or
        None for any.
      rounds: search rounds (0 repairs nothing).
      samples: candidates per plan and round.
      seed: the draws.

    Returns:
      A `Repair`.
    """
    started = time.perf_counter()
    task = as_problem(task)
    theta = np.array(theta, np.float64, copy=True)
    m = len(theta)
    out = Repair(theta.copy(), np.zeros(m, bool), 0, 0.0)
    if m == 0 or rounds < 1:
        return out
    rng = np.random.default_rng(seed)
    low, high, movable, clip = _box(task)
    width = (high - low) * movable
    centre = theta.copy()
    centre_cost = cost_c(task, simulate_c(task, centre), centre)
    out.rollouts += m
    scales = np.exp(rng.uniform(np.log(1e-3), np.log(5e-2), (rounds, samples)))
    for r in range(rounds):
        active = np.flatnonzero(~out.repaired)
        if not len(active):
            break
        eps = rng.normal(size=(len(active), samples, theta.shape[1]))
        cand = centre[active, None] + eps * scales[r][None, :, None] * width
        cand = np.where(clip, np.clip(cand, low, high), cand).reshape(-1, theta.shape[1])
        replay = simulate_c(task, cand)
        decoded = decode(task, replay, cand)
        cost = cost_c(task, replay, cand).reshape(len(active), samples)
        out.rollouts += len(cand)
        ok = decoded.ok.reshape(len(active), samples)
        plan = decoded.plan.reshape(len(active), samples)
        cand = cand.reshape(len(active), samples, -1)
        for row, i in enumerate(active):
            if ok[row].any():
                same = ok[row] & (plan[row] == target[i]) if target is not None else ok[row]
                pool = same if same.any() else ok[row]
                j = int(np.argmin(np.where(pool, cost[row], np.inf)))
                out.theta[i] = cand[row, j]
                out.repaired[i] = True
            elif cost[row].min() < centre_cost[i]:
                j = int(np.argmin(cost[row]))
                centre[i], centre_cost[i] = cand[row, j], cost[row, j]
    out.seconds = time.perf_counter() - started
    return out
