"""An evolutionary sampler in MuJoCo C: CMA-ES with restarts, every verified task plan kept.

What a user who doubts gradients would run first: no MJX, no gradient model,
no calibration. Each population is replayed in MuJoCo C with the scene's own
solver (`verify.simulate_c`), ranked by the task's own cost on those replays
(`verify.cost_c`), and decoded as solved plans are (`verify.decode`); every
successful sample's task plan goes to the `Tracker`, so a restart that
converges on a mode already found still counts whatever else it met on the
way. One MuJoCo C step costs a small fraction of one MJX value-and-gradient
per particle-step, so the sampler may spend many samples for each gradient
STAMP takes (benchmarks/results/README.md has the measures).

Settings and why (`run_cmaes`):

- search space: θ's box scaled to the unit cube; a sample outside it is
  mirrored back in (u ↦ the reflection of u in [0, 1], periodically), so the
  sampler searches the same box uniform sampling draws from, and the mirrored
  cost is a continuous function on all of R^d (no penalty to scale against
  the task's costs);
- population = 32 at the first start (more than CMA-ES's default
  4 + ⌊3 ln d⌋, 13-14 for d = 8-35: one C replay batch of 32 keeps a small
  machine's cores busy), multiplied by
  `population_growth` = 2 at each restart up to `max_population` = 256
  (IPOP-CMA-ES, Auger and Hansen 2005: larger populations see the global
  structure of multimodal costs);
- sigma0 = 0.3 of the box width, from a uniform mean (Hansen's advice: a
  quarter to a third of the search range);
- restart rule: σ · √max diag(C) < `tol_x` = 1e-3 of the box width (the run
  has converged); the best cost of the last 10 + ⌈30 d / λ⌉ generations
  moved less than 1e-12 of its size (flat); the condition number of C
  passed 1e14; 100 + 50 (d + 3)² / √λ generations (CMA-ES's usual
  limits); or the run has met a success and then found no new task plan
  for `stall_generations` = 10 generations: refining a mode already found
  adds no task plan, a fresh start may;
- weights, learning rates and damping: Hansen's defaults ("The CMA
  Evolution Strategy: A Tutorial", 2016, Table 1), μ = λ/2.

References:
  N. Hansen, "The CMA Evolution Strategy: A Tutorial", arXiv:1604.00772;
  A. Auger and N. Hansen, "A Restart CMA Evolution Strategy With Increasing
  Population Size", CEC 2005.
"""

from __future__ import annotations

import math

import numpy as np

from mjstamp import verify
from mjstamp.baselines.common import BaselineResult, Tracker
from mjstamp.errors import MjstampError
from mjstamp.tasks.problem import as_problem

__all__ = ["CMAES", "mirror", "run_cmaes"]


def mirror(u: np.ndarray) -> np.ndarray:
    """Reflects unit-cube coordinates into [0, 1], periodically (…, −0.2 ↦ 0.2, 1.3 ↦ 0.7)."""
    u = np.mod(u, 2.0)
    return np.where(u > 1.0, 2.0 - u, u)


class CMAES:
    """One run of CMA-ES with a full covariance: `ask` a population, `tell` its costs.

    Minimises over R^d. State: the mean m, the step size σ, the covariance
    C = B D² Bᵀ and the evolution paths p_σ, p_c.

    References:
      Hansen (2016), Table 1 and Fig. 7 (the algorithm and its defaults).
    """

    def __init__(self, mean: np.ndarray, sigma: float, population: int,
                 rng: np.random.Generator):
        n = len(mean)
        self.n, self.lam, self.rng = n, population, rng
        self.mean, self.sigma = np.asarray(mean, np.float64).copy(), float(sigma)
        mu = population // 2
        w = math.log(mu + 0.5) - np.log(np.arange(1, mu + 1))
        self.weights = w / w.sum()
        self.mu_eff = 1.0 / float(np.sum(self.weights ** 2))
        me = self.mu_eff
        self.c_c = (4 + me / n) / (n + 4 + 2 * me / n)
        self.c_s = (me + 2) / (n + me + 5)
        self.c_1 = 2 / ((n + 1.3) ** 2 + me)
        self.c_mu = min(1 - self.c_1, 2 * (me - 2 + 1 / me) / ((n + 2) ** 2 + me))
        self.d_s = 1 + 2 * max(0.0, math.sqrt((me - 1) / (n + 1)) - 1) + self.c_s
        self.chi_n = math.sqrt(n) * (1 - 1 / (4 * n) + 1 / (21 * n ** 2))
        self.p_s, self.p_c = np.zeros(n), np.zeros(n)
        self.C, self.B, self.D = np.eye(n), np.eye(n), np.ones(n)
        self.generation = 0
        self._y: np.ndarray | None = None

    def ask(self) -> np.ndarray:
        """(λ, d) samples x = m + σ B D z, z ~ N(0, I)."""
        z = self.rng.standard_normal((self.lam, self.n))
        self._y = (z * self.D) @ self.B.T
        return self.mean + self.sigma * self._y

    def tell(self, cost: np.ndarray) -> None:
        """Updates m, σ, C and the paths from the costs (λ,) of the last `ask` (inf: worst)."""
        y = self._y[np.argsort(cost, kind="stable")[: len(self.weights)]]
        y_w = self.weights @ y
        self.mean = self.mean + self.sigma * y_w
        inv_sqrt = self.B @ np.diag(1 / self.D) @ self.B.T  # C^(-1/2)
        self.p_s = ((1 - self.c_s) * self.p_s
                    + math.sqrt(self.c_s * (2 - self.c_s) * self.mu_eff) * inv_sqrt @ y_w)
        self.generation += 1
        norm = np.linalg.norm(self.p_s)
        h_s = norm / math.sqrt(1 - (1 - self.c_s) ** (2 * self.generation)) < (
            (1.4 + 2 / (self.n + 1)) * self.chi_n)
        self.p_c = ((1 - self.c_c) * self.p_c
                    + h_s * math.sqrt(self.c_c * (2 - self.c_c) * self.mu_eff) * y_w)
        rank_mu = (y.T * self.weights) @ y
        delta = (1 - h_s) * self.c_c * (2 - self.c_c)
        self.C = ((1 - self.c_1 - self.c_mu) * self.C
                  + self.c_1 * (np.outer(self.p_c, self.p_c) + delta * self.C)
                  + self.c_mu * rank_mu)
        self.sigma *= math.exp(self.c_s / self.d_s * (norm / self.chi_n - 1))
        self.C = (self.C + self.C.T) / 2
        eig, self.B = np.linalg.eigh(self.C)
        self.D = np.sqrt(np.maximum(eig, 1e-300))

    @property
    def spread(self) -> float:
        """σ · √max diag(C): the largest standard deviation of a coordinate."""
        return self.sigma * math.sqrt(float(np.max(np.diag(self.C))))

    @property
    def condition(self) -> float:
        """The condition number of C."""
        return float((self.D.max() / self.D.min()) ** 2)


def _check(name: str, value, low, *, integer: bool) -> None:
    kind = int if integer else (int, float)
    if isinstance(value, bool) or not isinstance(value, kind) or not value >= low:
        raise MjstampError(f"{name}={value!r} must be {'an integer' if integer else 'a number'}"
                           f" >= {low}")


def run_cmaes(task, *, target: int | None = None, cap_s: float = 600.0, seed: int = 0,
              config=None, population: int = 32, population_growth: int = 2,
              max_population: int = 256, sigma0: float = 0.3, tol_x: float = 1e-3,
              stall_generations: int = 10) -> BaselineResult:
    """IPOP-CMA-ES over θ's box in MuJoCo C, keeping every verified distinct task plan.

    Runs until `target` distinct task plans are verified or `cap_s` is spent
    (the module docstring gives the settings and why). One population of each
    size the restarts will use is replayed, decoded and costed first, untimed
    and discarded, as `baselines.sampling.random_search` replays one chunk: the JIT
    compiles of the poses, decoder and cost (once per batch size) are not the
    sampler's work; everything after them counts.

    Args:
      task: a `Task` or its `Problem`.
      target: distinct verified task plans to stop at (None: run to the cap).
      cap_s: wall-time cap in seconds.
      seed: seeds the means and the samples.
      config: ignored (the solve settings: C replays use the scene's own
        solver, no gradient model), accepted as the other baselines' is.
      population: λ at the first start (>= 4).
      population_growth: λ's factor at each restart (1: a fixed population).
      max_population: the largest λ.
      sigma0: the first step size of each start, in box widths.
      tol_x: restart when every coordinate's spread is below this (box widths).
      stall_generations: restart when, after a success, this many generations
        found no new task plan.

    Returns:
      a `BaselineResult` ("cmaes"; `runs` counts generations).
    """
    del config
    _check_settings(population, population_growth, max_population, stall_generations, seed,
                    sigma0, tol_x)
    problem = as_problem(task)
    Tracker(problem, target, cap_s)  # N.B. checks target and cap_s before any work
    theta_of, d = _unit_box(problem)
    rng = np.random.default_rng(seed)
    _warm_up(problem, theta_of, d, seed,
             _population_sizes(population, population_growth, max_population))
    tracker = Tracker(problem, target, cap_s)
    lam, generations, restarts = population, 0, 0
    while not tracker.done:
        es = CMAES(rng.uniform(size=d), sigma0, lam, rng)
        generations += _run_start(problem, tracker, es, theta_of, d, tol_x=tol_x,
                                  stall_generations=stall_generations)
        restarts += 1
        lam = min(lam * population_growth, max_population)
    return tracker.result("cmaes", seed, generations, {
        "population": population, "population_growth": population_growth,
        "max_population": max_population, "sigma0": sigma0, "tol_x": tol_x,
        "stall_generations": stall_generations, "starts": restarts, "warm_up": "untimed"})


def _check_settings(population, population_growth, max_population, stall_generations, seed,
                    sigma0, tol_x) -> None:
    """Raises MjstampError on a setting of `run_cmaes` out of its range (named in the line)."""
    _check("population", population, 4, integer=True)
    _check("population_growth", population_growth, 1, integer=True)
    _check("max_population", max_population, population, integer=True)
    _check("stall_generations", stall_generations, 1, integer=True)
    _check("seed", seed, 0, integer=True)
    for name, value in (("sigma0", sigma0), ("tol_x", tol_x)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < 1:
            raise MjstampError(f"{name}={value!r} must be a number in (0, 1) (box widths)")


def _unit_box(problem):
    """(theta_of, d): θ of unit-cube coordinates (n, d) -> (n, d), mirrored into θ's box."""
    low, high = problem.low.astype(np.float64), problem.high.astype(np.float64)
    width = high - low

    def theta_of(x):
        return low + width * mirror(x)

    return theta_of, len(low)


def _population_sizes(population: int, growth: int, largest: int) -> list[int]:
    """Every λ the restarts will use: `population`, times `growth` each restart, up to `largest`."""
    sizes = [population]
    while sizes[-1] < largest and growth > 1:
        sizes.append(min(sizes[-1] * growth, largest))
    return sizes


def _warm_up(problem, theta_of, d: int, seed: int, sizes: list[int]) -> None:
    """Replays, decodes and costs one population of each size, untimed and discarded.

    N.B. the replay's poses compile once per batch size: warm every population
    size of the schedule, and the one-plan replay `Tracker.record` costs.
    """
    for size in sizes:
        warm = theta_of(np.random.default_rng([seed, 1]).uniform(size=(size, d)))
        replay = verify.simulate_c(problem, warm)
        verify.decode(problem, replay, warm)
        verify.cost_c(problem, replay, warm)
    verify.cost_c(problem, replay.rows([0]), warm[:1])


def _run_start(problem, tracker: Tracker, es: CMAES, theta_of, d: int, *, tol_x: float,
               stall_generations: int) -> int:
    """Generations of one start, run until its restart rule fires or `tracker` is done.

    Every generation's samples are replayed in C, decoded, recorded in
    `tracker` and costed; the costs are told to `es`.
    """
    lam = es.lam
    flat = 10 + math.ceil(30 * d / lam)
    limit = 100 + math.ceil(50 * (d + 3) ** 2 / math.sqrt(lam))
    best: list[float] = []
    met_success, since_new, generations = False, 0, 0
    while not tracker.done:
        theta = theta_of(es.ask())
        replay = verify.simulate_c(problem, theta)
        decoded = verify.decode(problem, replay, theta)
        cost = verify.cost_c(problem, replay, theta)
        tracker.rollouts += len(theta)
        new = tracker.record(decoded, theta, replay)
        generations += 1
        es.tell(cost)
        met_success |= bool(decoded.ok.any())
        since_new = 0 if new else since_new + 1
        best.append(float(cost.min()))
        recent = best[-flat:]
        if (es.spread < tol_x or es.condition > 1e14 or es.generation >= limit
                or (met_success and since_new >= stall_generations)
                or (len(best) >= flat and np.isfinite(recent).all()
                    and max(recent) - min(recent) <= 1e-12 * (1 + abs(min(recent))))):
            break
    return generations
