"""Seeding: choose STAMP's initial particles from a forward-only screen in MuJoCo C.

Many TAMP landscapes are a plateau with narrow valleys (billiards: 16 task
plans in 1% of the velocity box, each 0.03-0.2% of it). Particles drawn
uniformly mostly start on the plateau, where the score is near zero and they
stay. A screen costs no gradients: `screen` times more candidates than
particles are drawn from the prior, replayed in batched MuJoCo C on all cores
with the scene's own solver, decoded into task plans and scored with the
task's own costs on the C replay. The particles are then taken from the screen
spread over its task plans, not only its best costs: candidates are grouped by
task plan (the successful ones by their full task plan, the others by their
symbol code and discrete actions), groups are visited in order of their best
cost, successful groups first, and each visit takes the group's next-best
candidate, round-robin, until n particles are chosen.

References:
  cuTAMP seeds its particles from a sampled, filtered batch in the same spirit.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import defaultdict

import jax
import numpy as np

from mjstamp import verify
from mjstamp.tasks import Problem, as_problem


@dataclasses.dataclass(frozen=True)
class Screen:
    """What a screen found (JSON view: `as_dict`).

    Attributes:
      candidates: how many were replayed.
      successes: how many succeeded in MuJoCo C.
      task_plans: {task plan: count} among the successes.
      groups: groups the particles were drawn from.
      seconds: wall time.
      cost_min, cost_median: of the candidates' finite costs C (None if none).
      first_seen_s: {task plan: seconds from the screen's start to the end of
        the chunk that first verified it} (plans stream at these times).
    """

    candidates: int
    successes: int
    task_plans: dict[str, int]
    groups: int
    seconds: float
    cost_min: float | None = None
    cost_median: float | None = None
    first_seen_s: dict[str, float] = dataclasses.field(default_factory=dict)

    def as_dict(self) -> dict:
        """JSON-ready view."""
        return dataclasses.asdict(self)


def _group_keys(decoded: verify.Decoded) -> list[str]:
    keys = []
    for i in range(len(decoded.ok)):
        if decoded.ok[i]:
            keys.append(f"ok:{decoded.plan[i]}")
        else:
            keys.append(f"no:{decoded.code[i]}:{','.join(decoded.actions[i])}")
    return keys


def seed_particles(
    problem, key: jax.Array, n: int, *, screen: int = 64, chunk: int = 256
) -> tuple[np.ndarray, Screen]:
    """Initial particles (n, d) chosen from `screen · n` candidates screened in MuJoCo C.

    Args:
      problem: the `Problem` (or a `Task`, built here).
      key: PRNG key of the candidates (`Problem.init`).
      n: particles to choose.
      screen: candidates per particle (>= 1; 1 returns the prior draw).
      chunk: candidates per batched C replay (bounds memory).

    Returns:
      (particles (n, d) float64, `Screen`).
    """
    seeded = screen_particles(problem, key, n, screen=screen, chunk=chunk)
    return seeded.particles, seeded.screen


@dataclasses.dataclass(frozen=True)
class Seeded:
    """A screen's outcome: the chosen particles, its report, and its successes by task plan.

    Attributes:
      particles: (n, d) initial particles.
      screen: the `Screen` report.
      successes: {task plan: (m, d) candidates that reached it in MuJoCo C},
        best cost first, at most max(`POOL`, n); the stall rescue re-draws near them
        (`Redraw`) and the solve returns the best of those no particle holds.
      replay: the particles' MuJoCo C replay, from the screen's own (None
        without a screen: nothing was replayed).
    """

    particles: np.ndarray
    screen: Screen
    successes: dict[str, np.ndarray]
    replay: verify.Replay | None = None


POOL = 256
"""Most candidates a group keeps beyond the n particles (a task plan's pool of successes)."""


def _draws(problem, key: jax.Array, total: int, chunk: int, seconds: float, started: float):
    """(first index, (m, d) candidates): `total` prior draws, then chunks until `seconds`."""
    first = np.asarray(problem.init(key, total), np.float64)
    for start in range(0, total, chunk):
        yield start, first[start : start + chunk]
    more = 0
    while time.perf_counter() - started < seconds:
        more += 1
        yield total + (more - 1) * chunk, np.asarray(
            problem.init(jax.random.fold_in(key, more), chunk), np.float64)


def screen_particles(
    problem, key: jax.Array, n: int, *, screen: int = 64, chunk: int = 256,
    seconds: float = 0.0, until_dry: int = 0,
) -> Seeded:
    """`seed_particles`, also handing back its successes and the particles' C replay (`Seeded`).

    `seconds` > 0 screens on past the `screen · n` candidates, a chunk at a
    time (fresh keys folded from `key`), until that much wall time has passed:
    the chunks it gets depend on the machine's speed, so the count is in the
    report (`Screen.candidates`). `until_dry` > 0 stops it sooner, once that
    many chunks in a row past the first `screen · n` found no new task plan
    (the screen's yield has dried up).
    """
    started = time.perf_counter()
    problem = as_problem(problem)
    total = n * max(1, int(screen))
    if screen <= 1 and not seconds > 0:
        candidates = np.asarray(problem.init(key, total), np.float64)
        return Seeded(candidates, Screen(total, 0, {}, 0, time.perf_counter() - started), {})
    groups: dict[str, list[tuple[float, int]]] = defaultdict(list)
    successes: dict[str, int] = defaultdict(int)
    first_seen: dict[str, float] = {}
    states: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    kept: dict[int, np.ndarray] = {}
    costs: list[np.ndarray] = []
    screened, cap, dry = 0, max(POOL, n), 0
    for start, part in _draws(problem, key, total, chunk, seconds, started):
        if until_dry and dry >= until_dry:
            break
        plans_before = len(successes)
        screened = start + len(part)
        replay = verify.simulate_c(problem, part)
        decoded = problem.decode(replay, part)
        cost = verify.cost_c(problem, replay, part)
        costs.append(cost[np.isfinite(cost)])
        for j, k in enumerate(_group_keys(decoded)):
            groups[k].append((float(cost[j]), start + j))
            states[start + j] = (replay.qpos[j], replay.qvel[j], replay.ctrl[j])
            kept[start + j] = part[j]
            if decoded.ok[j]:
                successes[str(decoded.plan[j])] += 1
        chunk_s = round(time.perf_counter() - started, 3)
        for plan in successes:
            first_seen.setdefault(plan, chunk_s)
        for members in groups.values():
            members.sort()
            for _, i in members[cap:]:
                kept.pop(i, None)
            del members[cap:]
        depth = _unreachable_depth([len(members) for members in groups.values()], n)
        for members in groups.values():
            for _, i in members[depth:]:
                states.pop(i, None)
        if screened > total:
            dry = 0 if len(successes) > plans_before else dry + 1
    costs = np.concatenate(costs)
    order = sorted(groups, key=lambda k: (not k.startswith("ok:"), groups[k][0][0]))
    chosen: list[int] = []
    depth = 0
    while len(chosen) < n:
        for k in order:
            if depth < len(groups[k]) and len(chosen) < n:
                chosen.append(groups[k][depth][1])
        depth += 1
    report = Screen(
        candidates=screened, successes=int(sum(successes.values())),
        task_plans=dict(sorted(successes.items(), key=lambda kv: -kv[1])),
        groups=len(groups), seconds=time.perf_counter() - started,
        cost_min=float(costs.min()) if costs.size else None,
        cost_median=float(np.median(costs)) if costs.size else None,
        first_seen_s=first_seen,
    )
    found = {k[len("ok:"):]: np.stack([kept[i] for _, i in groups[k]])
             for k in order if k.startswith("ok:")}
    qpos, qvel, ctrl = (np.stack(a) for a in zip(*(states[i] for i in chosen), strict=True))
    # N.B. the screen's own C states of the chosen candidates: the solve replays them no more.
    replay = verify.Replay(problem, qpos, source="mujoco", qvel=qvel, ctrl=ctrl)
    return Seeded(np.stack([kept[i] for i in chosen]), report, found, replay)


def _unreachable_depth(sizes: list[int], n: int) -> int:
    """The least rank r no candidate of that rank in its group is chosen at: Σ min(size, r) >= n.

    The round-robin takes every group's candidates of rank < r before any of
    rank r, so one of rank >= r comes after at least n others and is never
    chosen. More candidates only raise every rank and size: what is
    unreachable now stays so, and the screen drops its states.
    """
    for r in range(1, max(sizes, default=0) + 1):
        if sum(min(s, r) for s in sizes) >= n:
            return r
    return max(sizes, default=0)


def auto_cost_scale(screen: Screen | None) -> float:
    """β of `screen.cost_scale` "auto": max(1, ln M / (median − min)) of the screen's costs.

    With β the best of M candidates stands at least ln M nats above the
    typical one in the log posterior −β·C: the odds a region of 1/M of the
    box needs to outweigh the rest. 1 without a screen or a spread of costs.
    """
    if screen is None or screen.cost_min is None or screen.cost_median is None:
        return 1.0
    spread = screen.cost_median - screen.cost_min
    if not spread > 0:
        return 1.0
    return max(1.0, math.log(screen.candidates) / spread)


class Redraw:
    """Fresh particles for the stall rescue: from the prior, or near a screen's successes.

    Each fresh particle is, with probability `near`, a success of the screen
    plus Gaussian noise of `jitter` times each coordinate's box width (clipped
    to the box), its task plan chosen uniformly among the screen's task plans,
    so a rare task plan is as likely as a common one and none is crowded out;
    otherwise a draw from the prior. With no successes it always draws from the
    prior. A pure function of the key (a resumed solve re-draws the same).

    Args:
      problem: the `Problem` (its prior `init` and box `low`/`high`).
      successes: {task plan: (m, d) candidates} (`Seeded.successes`).
      near: share of the re-draws taken near a success.
      jitter: noise scale in box widths.
    """

    def __init__(self, problem: Problem, successes: dict[str, np.ndarray], *,
                 near: float = 0.5, jitter: float = 0.01):
        self.problem = problem
        self.pools = [np.asarray(v, np.float64) for _, v in sorted(successes.items()) if len(v)]
        self.near = float(near) if self.pools else 0.0
        self.jitter = float(jitter)
        self.low = np.asarray(problem.low, np.float64)
        self.high = np.asarray(problem.high, np.float64)

    def __call__(self, key: jax.Array, k: int) -> np.ndarray:
        """(k, d) fresh particles."""
        prior_key, key = jax.random.split(key)
        fresh = np.array(self.problem.init(prior_key, k), np.float64)
        if not self.near:
            return fresh
        rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).ravel().tolist())
        take = rng.random(k) < self.near
        for i in np.flatnonzero(take):
            pool = self.pools[rng.integers(len(self.pools))]
            centre = pool[rng.integers(len(pool))]
            noise = rng.normal(size=centre.shape) * self.jitter * (self.high - self.low)
            fresh[i] = np.clip(centre + noise, self.low, self.high)
        return fresh
