"""Plans: simulate particles (MJX or MuJoCo C), decode task plans, verify, group, save.

A particle θ decodes into a motion plan (its continuous variables) and a task
plan: the bits of its contact symbols (did geom1 touch geom2 before the first
contact of the `before` pair?), its discrete actions (Γ: the max per phase),
and the label of its success predicate (e.g. the pocket). Verification replays
the plan in MuJoCo C with the scene's *own* solver settings (not the
gradient-safe ones) and reads contacts and success from that replay.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shlex
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mjstamp.errors import MjstampError, valid_list
from mjstamp.fileio import probe, write_atomic
from mjstamp.parallel import local_device
from mjstamp.scenes import mjx, uncertainty
from mjstamp.scenes.fidelity import describe
from mjstamp.scenes.rollout import replay as replay_c
from mjstamp.scenes.rollout import replay_model
from mjstamp.tasks.declaration import Kind
from mjstamp.tasks.problem import FIELDS, Decoded, Problem

__all__ = ["Decoded", "Replay", "Robustness", "cost_c", "decode", "format_table", "group",
           "load", "perturbed_replays", "repair", "robustness", "save", "simulate_c",
           "simulate_mjx"]

# 2: scene.mjb, qpos0/qvel0/qvel/ctrl in trajectories.npz; 3: config split into task
# and solve settings, fidelity, screen, repaired and source per plan.
SCHEMA_VERSION = 3


class Replay:
    """States of n plans over T steps and their poses (numpy, float64).

    Attributes:
      qpos: (n, T, nq) positions after steps 1..T.
      qvel: (n, T, nv) velocities after steps 1..T (C replays only, else None).
      ctrl: (n, T, nu) controls applied at steps 1..T (C replays only, else None).
      xpos: (n, T, nbody, 3) body positions.
      site_xpos: (n, T, nsite, 3) site positions.
      contacts: {(g1, g2): (n, T) bool}, signed distance < 0 (MuJoCo makes a
        contact exactly then for geoms without margin).
    """

    def __init__(self, problem, qpos: np.ndarray, source: str, *, qvel=None, ctrl=None):
        problem = _problem(problem)
        self.problem = problem
        self.scene = problem.scene
        self.source = source
        self.qpos = np.asarray(qpos, np.float64)
        self.qvel = None if qvel is None else np.asarray(qvel, np.float64)
        self.ctrl = None if ctrl is None else np.asarray(ctrl, np.float64)
        self.xpos, self.site_xpos, self.contacts = _poses_and_contacts(problem, self.qpos)

    def body_pos(self, body: str | int) -> np.ndarray:
        """(n, T, 3) body position."""
        return self.xpos[:, :, self.scene.body(body)]

    def site_pos(self, site: str | int) -> np.ndarray:
        """(n, T, 3) site position."""
        return self.site_xpos[:, :, self.scene.site(site)]

    def contact(self, geom1: str | int, geom2: str | int) -> np.ndarray:
        """(n, T) whether the two geoms touch at each step."""
        g1, g2 = self.scene.geom(geom1), self.scene.geom(geom2)
        return self.contacts[(min(g1, g2), max(g1, g2))]


def _problem(task):
    """The `Problem` of a Task (built), or the Problem itself."""
    return task if isinstance(task, Problem) else task.build()


# Compiled per declaration and precision: kinematics and distances do not depend on
# the gradient model's solver options, so a calibrated problem reuses them.
_KINEMATICS: dict[tuple[str, Any], Any] = {}
_STATE_COSTS: dict[tuple[str, Any], Any] = {}


def _kinematics_fn(problem):
    """jit(vmap): qpos (B, nq) -> body, site positions and pair distances."""
    key = (problem.fingerprint, problem.scene.dtype)
    if key not in _KINEMATICS:
        scene = problem.scene
        d0 = mjx.make_data(scene.mx, device=local_device())
        pairs = problem.contact_pairs()
        fns = [problem.distance_fn(*p) for p in pairs]

        def one(qpos):
            d = mjx.kinematics(scene.mx, d0.replace(qpos=qpos))
            dist = jnp.stack([f(d.geom_xpos, d.geom_xmat) for f in fns]) if fns else jnp.zeros(0)
            return d.xpos, d.site_xpos, dist

        _KINEMATICS[key] = (jax.jit(jax.vmap(one)), pairs)
    return _KINEMATICS[key]


def _poses_and_contacts(problem, qpos: np.ndarray, chunk: int = 65536):
    n, T, nq = qpos.shape
    fn, pairs = _kinematics_fn(problem)
    flat = qpos.reshape(-1, nq)
    outs = []
    for start in range(0, len(flat), chunk):
        part = flat[start : start + chunk]
        pad = chunk - len(part) if len(flat) > chunk else 0
        if pad:  # one compiled shape for every chunk
            part = np.concatenate([part, np.repeat(part[-1:], pad, axis=0)])
        out = jax.device_get(fn(jnp.asarray(part, problem.scene.dtype)))
        outs.append([np.asarray(o[: len(part) - pad], np.float64) for o in out])
    xpos, site_xpos, dist = (np.concatenate(parts) for parts in zip(*outs, strict=True))
    xpos = xpos.reshape(n, T, -1, 3)
    site_xpos = site_xpos.reshape(n, T, -1, 3)
    dist = dist.reshape(n, T, len(pairs))
    contacts = {p: dist[:, :, i] < 0.0 for i, p in enumerate(pairs)}
    return xpos, site_xpos, contacts


def simulate_c(task, theta: np.ndarray) -> Replay:
    """Replays particles θ (n, d) of a Task or Problem in MuJoCo C (the scene's own solver).

    Discrete actions are taken at Γ(θ): the plan as decoded, not its relaxation.
    """
    problem = _problem(task)
    theta = np.asarray(theta, np.float64)
    qpos0, qvel0, ctrl = problem.inputs(theta, xp=np)
    ctrl = np.asarray(ctrl, np.float64)
    states = replay_c(problem.scene, qpos0, qvel0, ctrl, fields=("qpos", "qvel"),
                      solver="scene")
    return Replay(problem, states["qpos"], source="mujoco", qvel=states["qvel"], ctrl=ctrl)


def simulate_mjx(task, theta) -> Replay:
    """Rolls particles θ (n, d) out in MJX (the planner's own gradient model)."""
    problem = _problem(task)
    theta = jnp.asarray(theta, problem.scene.dtype)
    rollout = problem.scene.rollout_fn(problem.horizon, fields=("qpos",))
    qpos = rollout(*problem.inputs(theta, hard=True))["qpos"]
    return Replay(problem, np.asarray(qpos), source="mjx")


def _state_cost_fn(problem):
    """jit: states (B, T, nq), (B, T, nv) and θ (B, d) -> the task's cost C (B,).

    The task's own costs on a trajectory it did not roll out itself (a MuJoCo
    C replay): MJX kinematics give the poses, `Problem.score` the terms.
    """
    key = (problem.fingerprint, problem.scene.dtype)
    if key not in _STATE_COSTS:
        scene = problem.scene
        d0 = mjx.make_data(scene.mx, device=local_device())

        def poses(qpos):
            d = mjx.kinematics(scene.mx, d0.replace(qpos=qpos))
            return {f: getattr(d, f) for f in FIELDS if f not in ("qpos", "qvel")}

        def cost(qpos, qvel, theta):
            traj = jax.vmap(jax.vmap(poses))(qpos)
            traj.update(qpos=qpos, qvel=qvel)
            _, values = problem.score(traj, problem.unpack(theta))
            return problem.cost_total(values)

        _STATE_COSTS[key] = jax.jit(cost)
    return _STATE_COSTS[key]


def cost_c(task, replay: Replay, theta: np.ndarray, *, chunk: int = 32) -> np.ndarray:
    """(n,) the task's cost C(θ) on a MuJoCo C replay of θ (n, d), in chunks.

    Non-finite costs (a state that blew up) are +inf.
    """
    problem = _problem(task)
    fn = _state_cost_fn(problem)
    n = len(theta)
    out = np.empty(n)
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        idx = np.arange(start, start + chunk).clip(max=n - 1)  # one compiled shape
        dtype = problem.scene.dtype
        value = fn(jnp.asarray(replay.qpos[idx], dtype), jnp.asarray(replay.qvel[idx], dtype),
                   jnp.asarray(theta[idx], dtype))
        out[start:stop] = np.asarray(value, np.float64)[: stop - start]
    return np.where(np.isfinite(out), out, np.inf)


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
    task = _problem(task)
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
    problem = _problem(task)
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
                           "robustness_samples=0): there are no perturbed replays to play")
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


def decode(task, replay: Replay, theta: np.ndarray) -> Decoded:
    """Task plans of a Task's or Problem's particles θ read off a replay (`Problem.decode`)."""
    return _problem(task).decode(replay, theta)


# The results table and save/load moved to mjstamp.results; these names stay here
# until the merge removes this module.
# ruff: noqa: F401, F811
from mjstamp.results import (  # noqa: E402 - moved; removed at merge
    SCHEMA_VERSION,
    check_writable,
    format_table,
    group,
    load,
    load_model,
    save,
)
