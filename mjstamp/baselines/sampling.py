"""Uniform random search in MuJoCo C: the baseline a planner should beat at equal wall time.

Shots uniform over θ's box (`modes.uniform_theta`, the range particles start
in) are replayed in MuJoCo C with the scene's own solver settings and decoded
as solved plans are; the distinct successful task plans are what it finds.
"""

from __future__ import annotations

import time

import numpy as np

from mjstamp import verify
from mjstamp.errors import MjstampError
from mjstamp.modes import uniform_theta


def random_search(task, wall_s: float, *, seed: int = 0, chunk: int = 256,
                  keep_best: int = 0) -> dict:
    """Uniform random shots in MuJoCo C for `wall_s` seconds: the planner's baseline.

    Shots are drawn uniform over θ's bounds, replayed in MuJoCo C with the
    scene's own solver settings and decoded as solved plans are. One chunk is
    replayed first, untimed and discarded, so that the decoder's JIT compile
    (which a C sampler would not need) does not count; then chunks run until
    the wall time is spent. A chunk that finishes after `wall_s` is not
    counted, so the search never gets more time than it was given.

    Args:
      task: a `Task`.
      wall_s: wall-clock budget in seconds (> 0).
      seed: seeds the draws.
      chunk: shots per batch; smaller wastes less of the budget at the end.
      keep_best: keep the this many successes of each task plan with the
        lowest cost C on their C replay (`verify.cost_c`, costed in the search's
        time); 0: none.

    Returns:
      {"task_plans": sorted distinct successful task plans, "shots": shots
      counted, "successes", "wall_s": time used, "found_at_s": {task plan:
      seconds into the search when it was first found}, "best": {task plan:
      (m, d) its kept successes, lowest cost first} (empty without keep_best)}.
    """
    if not wall_s > 0:
        raise MjstampError(f"random_search(wall_s={wall_s}) must be > 0")
    rng = np.random.default_rng(seed)
    warm = uniform_theta(task, chunk, np.random.default_rng([seed, 1]))
    replay = verify.simulate_c(task, warm)
    verify.decode(task, replay, warm)
    if keep_best:
        verify.cost_c(task, replay, warm[:1])  # N.B. its compile, untimed as the decoder's
    found_at: dict[str, float] = {}
    best: dict[str, list[tuple[float, np.ndarray]]] = {}
    shots = successes = 0
    t0 = time.perf_counter()
    elapsed = 0.0
    while True:
        theta = uniform_theta(task, chunk, rng)
        replay = verify.simulate_c(task, theta)
        decoded = verify.decode(task, replay, theta)
        ok = np.flatnonzero(decoded.ok)
        if keep_best and ok.size:
            cost = verify.cost_c(task, replay.rows(ok), theta[ok])
        now = time.perf_counter() - t0
        if now > wall_s:  # N.B. before keeping: an uncounted chunk's plans are not found
            break
        if keep_best and ok.size:
            for j, c in zip(ok, cost, strict=True):
                kept = best.setdefault(str(decoded.plan[j]), [])
                kept.append((float(c), theta[j]))
                kept.sort(key=lambda e: e[0])
                del kept[keep_best:]
        elapsed = now
        shots += len(theta)
        successes += int(decoded.ok.sum())
        for plan in decoded.plan[decoded.ok]:
            found_at.setdefault(str(plan), now)
    return {
        "task_plans": sorted(found_at),
        "shots": shots,
        "successes": successes,
        "wall_s": elapsed,
        "found_at_s": found_at,
        "best": {plan: np.stack([t for _, t in kept]) for plan, kept in sorted(best.items())},
    }


__all__ = ["random_search"]
