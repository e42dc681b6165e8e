"""Robustness: plans replayed in MuJoCo C under the task's uncertain physics.

`robustness` scores plans by the share of M perturbed replays (models and
initial states drawn from `Task.uncertain`) in which they still succeed;
`perturbed_replays` replays a saved plan in the same draws, for playback.
"""

from __future__ import annotations

import dataclasses
import time
import warnings

import mujoco
import numpy as np

from mjstamp.errors import MjstampError
from mjstamp.scenes import uncertainty
from mjstamp.scenes.rollout import replay as replay_c
from mjstamp.scenes.rollout import replay_model
from mjstamp.tasks.problem import as_problem
from mjstamp.verify.replay import Replay, cost_c


@dataclasses.dataclass
class Robustness:
    """How m plans fare under the task's uncertain physics (`robustness`).

    Attributes:
      success: (m,) share of the M perturbed MuJoCo C replays whose success
        predicate holds.
      same_plan: (m,) share that succeed with the plan's own task plan.
      cost_median, cost_std: (m,) median and standard deviation of the task's
        cost C over the M replays (failed replays included; a replay that
        blew up counts as +inf in the median and is left out of the spread).
      samples: M.
      seed: the draws' seed.
      rollouts: MuJoCo C rollouts spent (m · M).
      seconds: wall time.
      uncertain: the uncertainty scored under (`Uncertain.describe` each).
      declared: whether the task declared it (else the defaults).
    """

    success: np.ndarray
    same_plan: np.ndarray
    cost_median: np.ndarray
    cost_std: np.ndarray
    samples: int
    seed: int
    rollouts: int
    seconds: float
    uncertain: list
    declared: bool


def robustness(task, theta: np.ndarray, plan: np.ndarray | None = None, *, samples: int = 32,
               seed: int = 0, max_steps: int = 1 << 19,
               stream: int = uncertainty.SCORE_STREAM) -> Robustness:
    """Replays plans under M perturbed models and initial states in MuJoCo C.

    Every plan meets the same M draws of the task's uncertainty (`Task.uncertain`,
    the defaults when it declared none; `scenes.uncertainty.sample`): M models
    with perturbed friction, mass, ... and M offsets of the initial positions,
    all replayed in one batched `mujoco.rollout` per chunk of plans.

    Args:
      task: the `Task` or `Problem`.
      theta: (m, d) plans.
      plan: (m,) their task plans (nominal replay), for `same_plan`; None:
        `same_plan` is `success`.
      samples: M >= 1 perturbed replays per plan.
      seed: seeds the draws (the same seed, the same scores).
      max_steps: rollout steps held in memory at once (chunks of plans).
      stream: the draws' random stream; `uncertainty.PLAN_STREAM` with samples = K
        replays a robust solve's own K planning draws (in MuJoCo C, the scene's
        solver), to tell overfitting to them from not reaching them.

    Returns:
      A `Robustness`.
    """
    started = time.perf_counter()
    problem = as_problem(task)
    samples = int(samples)
    if samples < 1:
        raise MjstampError(f"robustness samples={samples} must be >= 1")
    theta = np.asarray(theta, np.float64).reshape(-1, problem.dim)
    m = len(theta)
    out = Robustness(np.zeros(m), np.zeros(m), np.full(m, np.inf), np.full(m, np.nan),
                     samples, int(seed), m * samples, 0.0,
                     [u.describe() for u in problem.uncertain], problem.uncertain_declared)
    if m == 0:
        return out
    draws = uncertainty.sample(problem.scene.m, problem.uncertain, samples, seed, stream=stream)
    zero = uncertainty.is_zero(problem.uncertain)
    per_chunk = max(1, max_steps // (samples * problem.horizon))
    for start in range(0, m, per_chunk):
        rows = np.arange(start, min(start + per_chunk, m))
        th = np.repeat(theta[rows], samples, axis=0)
        qpos0, qvel0, ctrl = problem.inputs(th, xp=np)
        qpos0 = np.asarray(qpos0, np.float64) + np.tile(draws.qpos_noise, (len(rows), 1))
        ctrl = np.asarray(ctrl, np.float64)
        states = replay_c(problem.scene, qpos0, qvel0, ctrl, fields=("qpos", "qvel"),
                          solver="scene", models=None if zero else draws.models * len(rows))
        replay = Replay(problem, states["qpos"], source="mujoco", qvel=states["qvel"], ctrl=ctrl)
        decoded = problem.decode(replay, th)
        cost = cost_c(problem, replay, th).reshape(len(rows), samples)
        ok = decoded.ok.reshape(len(rows), samples)
        out.success[rows] = ok.mean(axis=1)
        if plan is None:
            out.same_plan[rows] = out.success[rows]
        else:
            same = decoded.plan.reshape(len(rows), samples) == np.asarray(plan)[rows, None]
            out.same_plan[rows] = (ok & same).mean(axis=1)
        out.cost_median[rows] = np.median(cost, axis=1)
        finite = np.where(np.isfinite(cost), cost, np.nan)
        with warnings.catch_warnings():  # a row that blew up in every replay: NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            out.cost_std[rows] = np.nanstd(finite, axis=1)
    out.seconds = time.perf_counter() - started
    return out


def perturbed_replays(m: mujoco.MjModel, scored: dict | None, qpos0: np.ndarray,
                      qvel0: np.ndarray, ctrl: np.ndarray | None, count: int, *,
                      horizon: int, where: str) -> dict[str, np.ndarray]:
    """A saved plan replayed in the first `count` perturbed models its score used.

    The draws are those of `robustness` (the same seed, `samples` and
    uncertainty, resolved again against the saved scene), so replay j is the
    j-th of the M replays behind the plan's score.

    Args:
      m: the saved scene (scene.mjb, the scene's own solver settings).
      scored: plans.json's "robustness" (None: the solve scored nothing).
      qpos0: (nq,) the plan's initial positions.
      qvel0: (nv,) its initial velocities.
      ctrl: (T, nu) its controls (None or empty for a scene without actuators).
      count: 1 <= count <= M replays.
      horizon: T, the plan's steps.
      where: the results directory (named in errors).

    Returns:
      {"qpos0": (count, nq) perturbed initial positions, "qpos", "qvel": (count, T, ...)}.

    Raises:
      MjstampError: nothing scored, or `count` out of 1..M (one line each).
    """
    if not scored:
        raise MjstampError(f"{where} holds no robustness scores (solved with "
                           "verify.robustness_samples=0): there are no perturbed replays to play")
    samples = int(scored["samples"])
    if not 1 <= count <= samples:
        raise MjstampError(f"perturbed replays={count} is not valid for {where}: its plans "
                           f"were scored on {samples}; valid: 1..{samples}")
    uncertain = uncertainty.from_describe(m, scored["uncertain"], f"{where}/plans.json")
    draws = uncertainty.sample(m, uncertain, samples, int(scored["seed"]))
    qpos0 = np.asarray(qpos0, np.float64)[None] + draws.qpos_noise[:count]
    qvel0 = np.repeat(np.asarray(qvel0, np.float64)[None], count, axis=0)
    ctrl = (np.zeros((count, int(horizon), m.nu)) if ctrl is None or np.size(ctrl) == 0
            else np.repeat(np.asarray(ctrl, np.float64)[None], count, axis=0))
    zero = uncertainty.is_zero(uncertain)
    states = replay_model(m, qpos0, qvel0, ctrl, fields=("qpos", "qvel"),
                          models=None if zero else draws.models[:count])
    return {"qpos0": qpos0, **states}
