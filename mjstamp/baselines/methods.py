"""The baselines: enumerate (PDDLStream's reduction), blocking (Diverse LGP), cem (sampling).

Each takes any `Task` (or its `Problem`), runs until it has verified `target`
distinct task plans in MuJoCo C or its cap is spent, and returns a
`BaselineResult`. The gradient methods (enumerate, blocking) calibrate the
gradient model as `solve` does, and differentiate the same MJX rollouts at the
hard decode Γ(θ) with the same optimizer as STAMP's SGD phase (Adam, steps in
box widths; forward-mode scores for d <= 2, a pullback otherwise), batched
over `starts` random starts. Their settings and why:

- starts = 32: a batch large enough that a run's random starts cover the box
  of a 2-4-dimensional task, small enough that one run costs a quarter of
  STAMP's 128-particle SGD phase (more starts did not find plans sooner on
  billiards: the run ends when its candidate is verified).
- iterations = the task's `stamp.sgd_max_iters` (what STAMP's SGD phase gets), with
  a C verification of every start each `check_every` = 20 iterations, and the
  run ended as soon as its candidate (enumerate) is verified.
- symbol_weight = 10, block_weight = 10: on the scale of the tasks' costs
  (billiards' best plans cost 6-8); the squared symbol error is at most S.

cem scores its populations with the same MJX rollouts, forward only, at Γ(θ)
(`rollouts="mjx"`, the default), and replays each population in MuJoCo C to
verify it (counted in its time). With `rollouts="c"` it scores the C replays
themselves (the task's costs on them, `verify.cost_c`): on a CPU the C forward
is several times cheaper than MJX's, so this is what a user without a GPU
would do. Population 128
(STAMP's particles), elites 10%, at most 20 generations per restart, restart
when the elites' spread is below 1% of every box width; each restart starts
from a uniform mean and half-width spreads.
"""

from __future__ import annotations

import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from mjstamp import parallel, verify
from mjstamp.baselines.common import (
    BaselineResult,
    Tracker,
    candidates,
    constrained_logdensity,
    empty_spec,
    onehots,
)
from mjstamp.config import SolveConfig
from mjstamp.errors import MjstampError
from mjstamp.svgd._jacobian import value_and_batched_jacobian
from mjstamp.tasks.problem import Problem

__all__ = ["run_blocking", "run_cem", "run_enumerate"]

MAX_BLOCKED = 64  # task plans the blocking penalty holds (one compiled shape)


def _integer(name: str, value, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise MjstampError(f"{name}={value!r} must be an integer >= {low}")


def _weight(name: str, value) -> None:
    if (isinstance(value, bool) or not isinstance(value, (int, float))
            or not 0 <= value < math.inf):
        raise MjstampError(f"{name}={value!r} must be a finite number >= 0")


def _setup(task, config, seed: int, starts: int, *,
           soft_symbols: bool = False) -> tuple[Problem, SolveConfig]:
    """The problem on its calibrated gradient model, and the solve settings it uses.

    `soft_symbols`: the method reads every symbol's soft indicator, so a task
    with a symbol the gradient model cannot relax is refused at once
    (`Problem.check_relaxed`), before calibrating.
    """
    from mjstamp.solver import pipeline as solve_mod  # noqa: PLC0415 - solve imports much

    _integer("seed", seed, 0)
    _integer("starts", starts, 1)
    problem = solve_mod.as_problem(task)
    if soft_symbols:
        problem.check_relaxed()
    cfg = config if isinstance(config, SolveConfig) else SolveConfig.from_dict(config)
    if cfg.calibration.enabled:
        theta = np.asarray(problem.init(jax.random.key(seed), max(starts, 8)), np.float64)
        problem, _ = solve_mod.calibrate(problem, theta, cfg)
    return problem, cfg


class _SGD:
    """Batched SGD on the constrained log density, compiled once per (problem, starts)."""

    def __init__(self, problem: Problem, cfg: SolveConfig, starts: int, *, symbol_weight: float,
                 block_weight: float):
        from mjstamp.solver import pipeline as solve_mod  # noqa: PLC0415

        self.problem, self.starts = problem, starts
        devices = _devices(cfg)
        logp = parallel.shard_particles(
            constrained_logdensity(problem, symbol_weight=symbol_weight,
                                   block_weight=block_weight), devices)
        widths = (problem.high - problem.low).astype(np.float64)
        self.optimizer = solve_mod.box_optimizer(cfg.stamp.sgd_learning_rate, cfg.stamp.sgd_step,
                                              widths)
        # N.B. as `build_sgd_step` resolves the solve's `jacobian` setting.
        mode = cfg.stamp.jacobian
        if mode == "auto":
            mode = "fwd" if problem.dim <= 2 else "rev"
        optimizer = self.optimizer

        def step(theta, opt_state, spec):
            out, jac = value_and_batched_jacobian(lambda p: logp(p, spec)[:, None], theta, mode)
            value, score = out[:, 0], jac[:, 0, :]
            ok = jnp.isfinite(value) & jnp.all(jnp.isfinite(score), axis=1)
            score = jnp.where(ok[:, None], score, 0.0)
            updates, opt_state = optimizer.update(-score, opt_state, theta)
            return theta + jnp.where(ok[:, None], updates, 0.0), opt_state, value

        dtype = problem.scene.dtype
        theta = jnp.zeros((starts, problem.dim), dtype)
        spec = {k: jnp.asarray(v) for k, v in empty_spec(problem, MAX_BLOCKED, dtype).items()}
        name = (f"baseline-sgd starts={starts} sym={symbol_weight} block={block_weight} "
                f"{cfg.stamp.sgd_learning_rate} {cfg.stamp.sgd_step} on {devices}")
        self.step = solve_mod.problem_jit(problem)(step, name, theta, optimizer.init(theta),
                                                   spec)

    def run(self, key, spec: dict, iters: int, check_every: int, tracker: Tracker,
            stop=lambda: False) -> None:
        """One run from `starts` uniform starts; verifies in C every `check_every` iterations."""
        dtype = self.problem.scene.dtype
        theta = jnp.asarray(self.problem.init(key, self.starts), dtype)
        opt_state = self.optimizer.init(theta)
        spec = {k: jnp.asarray(v, dtype) for k, v in spec.items()}
        for t in range(1, iters + 1):
            theta, opt_state, _ = self.step(theta, opt_state, spec)
            if t % check_every == 0 or t == iters:
                tracker.verify(np.asarray(jax.device_get(theta)))
                if tracker.done or stop():
                    return


def _devices(cfg: SolveConfig) -> int:
    """The devices the batched rollouts are sharded over: those `solve` would use."""
    devices = cfg.devices or jax.device_count()
    parallel.check_devices(devices)
    return devices


def _iters(cfg: SolveConfig, iters: int | None, check_every: int) -> int:
    iters = cfg.stamp.sgd_max_iters if iters is None else iters
    _integer("iters", iters, 1)
    _integer("check_every", check_every, 1)
    return iters


def run_enumerate(task, *, target: int | None = None, cap_s: float = 600.0, seed: int = 0,
                  config=None, starts: int = 32, iters: int | None = None,
                  check_every: int = 20, symbol_weight: float = 10.0) -> BaselineResult:
    """PDDLStream's reduction (STAMP App. E): one symbolic plan at a time.

    The candidates are every combination of symbol bits and discrete options;
    each round takes them in a random order (seeded), skipping those already
    verified, and optimises one: SGD from `starts` random starts on the cost
    plus a loss requiring its symbols, its options fixed. Verified plans of
    any task plan count (a run aimed at one may verify another). Once every
    candidate has been verified, rounds go over all of them again, each run
    ending at its first new task plan (one whose success label differs).

    Raises:
      MjstampError: a task without symbols or discrete actions (nothing to
        enumerate), or a bad setting.
    """
    started = time.perf_counter()
    _weight("symbol_weight", symbol_weight)
    problem, cfg = _setup(task, config, seed, starts, soft_symbols=True)
    cands = candidates(problem)
    iters = _iters(cfg, iters, check_every)
    sgd = _SGD(problem, cfg, starts, symbol_weight=symbol_weight, block_weight=0.0)
    tracker = Tracker(problem, target, cap_s, start=started)
    rng = np.random.default_rng(seed)
    key = jax.random.key(seed)
    dtype = problem.scene.dtype
    runs = 0
    while not tracker.done:
        # N.B. once every candidate is verified, passes go on over all of them (new
        # random starts): task plans that differ only in their success label remain.
        found = {f["symbolic"] for f in tracker.found.values()}
        left = [c for c in cands if c.name(problem) not in found] or cands
        for i in rng.permutation(len(left)):
            c = left[i]
            symbolic = c.name(problem)
            if left is not cands and any(f["symbolic"] == symbolic
                                         for f in tracker.found.values()):
                continue
            spec = empty_spec(problem, MAX_BLOCKED, dtype)
            spec.update(want=np.asarray(c.bits, dtype), want_on=np.ones((), dtype),
                        fix=onehots(problem, c.actions, dtype),
                        fix_on=np.ones((), dtype) if c.actions else np.zeros((), dtype))
            key, sub = jax.random.split(key)
            before = len(tracker.found)

            def stop(s=symbolic, aimed=left is not cands, before=before):
                """Aimed at a candidate: it is verified; a later round: any new task plan."""
                if aimed:
                    return any(f["symbolic"] == s for f in tracker.found.values())
                return len(tracker.found) > before

            sgd.run(sub, spec, iters, check_every, tracker, stop=stop)
            runs += 1
            if tracker.done:
                break
    return tracker.result("enumerate", seed, runs, {
        "starts": starts, "iters": iters, "check_every": check_every,
        "symbol_weight": symbol_weight, "candidates": len(cands)})


def run_blocking(task, *, target: int | None = None, cap_s: float = 600.0, seed: int = 0,
                 config=None, starts: int = 32, iters: int | None = None,
                 check_every: int = 20, block_weight: float = 10.0) -> BaselineResult:
    """Diverse LGP's recipe (STAMP App. E): a single-plan optimisation, repeated, blocking.

    Each run is SGD from `starts` random starts on the cost plus a penalty on
    the soft probability of every task plan found so far (its symbols and
    options); each distinct task plan it verifies is kept and blocked in the
    runs after it. N.B. the penalty acts on symbols and options, as Diverse
    LGP blocks symbolic plans: task plans that differ only in their success
    label (billiards' pocket) are blocked together once one is found.
    """
    started = time.perf_counter()
    _weight("block_weight", block_weight)
    problem, cfg = _setup(task, config, seed, starts, soft_symbols=True)
    iters = _iters(cfg, iters, check_every)
    sgd = _SGD(problem, cfg, starts, symbol_weight=0.0, block_weight=block_weight)
    tracker = Tracker(problem, target, cap_s, start=started)
    key = jax.random.key(seed)
    dtype = problem.scene.dtype
    blocks = Blocks(problem, dtype)
    runs = 0
    while not tracker.done:
        spec = empty_spec(problem, MAX_BLOCKED, dtype)
        spec.update(blocks.spec(list(tracker.found.values())))
        key, sub = jax.random.split(key)
        sgd.run(sub, spec, iters, check_every, tracker)
        runs += 1
    return tracker.result("blocking", seed, runs, {
        "starts": starts, "iters": iters, "check_every": check_every,
        "block_weight": block_weight, "max_blocked": MAX_BLOCKED})


class Blocks:
    """The blocking penalty's arrays for the task plans found so far (the latest MAX_BLOCKED)."""

    def __init__(self, problem: Problem, dtype):
        self.problem, self.dtype = problem, dtype

    def spec(self, found: list[dict]) -> dict[str, np.ndarray]:
        """The arrays blocking the task plans `found` (entries of `Tracker.found`)."""
        found = found[-MAX_BLOCKED:]
        spec = empty_spec(self.problem, MAX_BLOCKED, self.dtype)
        for j, f in enumerate(found):
            spec["blocked"][j] = [int(b) for b in f["code"]]
            spec["blocked_actions"][j] = onehots(self.problem, f["action_ids"], self.dtype)
            spec["blocked_on"][j] = 1.0
        return {k: spec[k] for k in ("blocked", "blocked_actions", "blocked_on")}


def run_cem(task, *, target: int | None = None, cap_s: float = 600.0, seed: int = 0,
            config=None, population: int = 128, elite_frac: float = 0.1,
            generations: int = 20, min_spread: float = 0.01,
            rollouts: str = "mjx") -> BaselineResult:
    """Cross-entropy method with restarts over θ, forward only, every sample verified.

    What a user of MJX sampling planners (hydrax's CEM) would try: a diagonal
    Gaussian over θ, refit to the best `elite_frac` of each population by the
    task's own cost (of its MJX rollouts, or of its C replays); every sample
    is replayed in MuJoCo C and each successful one's task plan is kept. A
    restart draws a new uniform mean when the elites' spread falls below
    `min_spread` of every box width, or after `generations`.
    `rollouts`: "mjx" (the planner's forward rollouts score, C verifies) or
    "c" (C replays score and verify).
    """
    started = time.perf_counter()
    _integer("population", population, 2)
    _integer("generations", generations, 1)
    for name, value in (("elite_frac", elite_frac), ("min_spread", min_spread)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < 1:
            raise MjstampError(f"{name}={value!r} must be a number in (0, 1)")
    if rollouts not in ("mjx", "c"):
        raise MjstampError(f"rollouts={rollouts!r} is not valid; valid: mjx, c")
    problem, cfg = _setup(task, config, seed, population)
    score = _mjx_cost(problem, population, _devices(cfg)) if rollouts == "mjx" else None
    low, high = problem.low.astype(np.float64), problem.high.astype(np.float64)
    width = high - low
    elites = max(2, math.ceil(elite_frac * population))
    tracker = Tracker(problem, target, cap_s, start=started)
    rng = np.random.default_rng(seed)
    runs = 0
    while not tracker.done:
        mean, spread = rng.uniform(low, high), width / 2
        for _ in range(generations):
            x = np.clip(mean + spread * rng.standard_normal((population, len(low))), low, high)
            replay = verify.simulate_c(problem, x)
            decoded = verify.decode(problem, replay, x)
            if score is None:
                cost = verify.cost_c(problem, replay, x)
            else:
                cost = score(x)
                tracker.rollouts += population
            tracker.rollouts += population
            tracker.record(decoded, x, replay)
            runs += 1
            if tracker.done:
                break
            best = x[np.argsort(cost, kind="stable")[:elites]]
            mean, spread = best.mean(axis=0), best.std(axis=0)
            if np.all(spread < min_spread * width):
                break
    return tracker.result("cem", seed, runs, {
        "population": population, "elite_frac": elite_frac, "generations": generations,
        "min_spread": min_spread, "rollouts": rollouts})


def _mjx_cost(problem: Problem, population: int, devices: int):
    """θ (P, d) numpy -> (P,) the task's cost of its MJX rollouts at Γ(θ) (non-finite: inf)."""
    from mjstamp.solver import pipeline as solve_mod  # noqa: PLC0415

    dtype = problem.scene.dtype

    def cost(theta):
        return problem.cost_total(problem.evaluate(theta, hard=True)[1])

    fn = solve_mod.problem_jit(problem)(parallel.shard_particles(cost, devices),
                                        f"baseline-cem-cost on {devices}",
                                        jnp.zeros((population, problem.dim), dtype))

    def score(x):
        value = np.asarray(jax.device_get(fn(jnp.asarray(x, dtype))), np.float64)
        return np.where(np.isfinite(value), value, np.inf)

    return score
