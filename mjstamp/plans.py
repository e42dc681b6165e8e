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


def _chaos_note(verdict: dict) -> str:
    """', within the scene's own chaos (...)' when MJX was judged by C's spread."""
    if verdict.get("judged_by") != "chaos":
        return ""
    return (f", over it but within the scene's own chaos: C against itself nudged by 1e-9 m "
            f"p95 {verdict['chaos_p95_m']:.2g} m")


def _parting_note(verdict: dict | None) -> str:
    """', parting at box-box contacts ('crate'/'ledge')' from a verdict's JSON view."""
    pairs = ((verdict or {}).get("parting") or {}).get("pairs") or []
    if not pairs:
        return ""
    def named(p):
        geoms = (repr(g) if g else f"#{i}" for g, i in zip(p["geoms"], p["ids"], strict=True))
        return f"{'-'.join(p['types'])} {'/'.join(geoms)}"

    return f", parting at contacts of {', '.join(named(p) for p in pairs[:3])}"


def _particles_line(summary: dict) -> str:
    """A line 'particles: ...' (verified share, the mean cost per phase, re-draws), or ''."""
    loss = summary.get("loss")
    if not loss or loss["mean"]["initial"] is None or "verified_particle_share" not in summary:
        return ""
    m = loss["mean"]
    line = (f"\nparticles: {summary['verified_particle_share']:.0%} end as verified plans; mean "
            f"cost {m['initial']:.3g} at the start, {m['svgd']:.3g} after SVGD, "
            f"{m['final']:.3g} at the end")
    if loss.get("svgd_share") is not None:
        line += f" (SVGD: {loss['svgd_share']:.0%} of the decrease)"
    rescue = summary.get("rescue")
    if rescue:
        line += f"; {rescue['redraws']} stalled particles re-drawn"
    return line


def _robustness_line(robust: dict | None) -> str:
    """A line 'robustness: ...' (what was perturbed, how many replays), or ''."""
    if not robust:
        return ""
    parts = []
    for u in robust["uncertain"]:
        what = (f"{u['spread'] * 1000:.3g} mm" if u["kind"] == "position"
                else f"±{u['spread']:.0%}")
        if u["distribution"] == "normal":
            what = "σ " + what.lstrip("±")
        count = len(u["names"])
        parts.append(f"{u['kind']} {what} ({count} {'element' if count == 1 else 'elements'})")
    source = "declared" if robust["declared"] else "the default uncertainty"
    median = robust.get("median")
    return (f"\nrobustness: success share of {robust['samples']} perturbed MuJoCo C replays per "
            f"verified plan, {source}: {', '.join(parts) or 'nothing'}"
            + ("" if median is None else f"; median {median:.0%}")
            + f" ({robust['seconds']:.1f} s)")


def format_table(summary: dict, *, markdown: bool = False) -> str:
    """The table of task plans `mjstamp solve` prints, from a solve's summary.

    Args:
      summary: `SolveResult.summary()` or the contents of plans.json.
      markdown: a Markdown table (for notebooks) instead of aligned text.

    Returns:
      The table, a header line above it and a line of totals below it.
    """
    header = ("task plan", "plans found", "verified", "repaired", "best cost", "verified share")
    body = [
        (r["task_plan"], str(r["plans"]), str(r["verified"]), str(r.get("repaired", 0)),
         "-" if r["best_cost"] is None else f"{r['best_cost']:.3g}",
         f"{r['verified_share']:.0%}")
        for r in summary["task_plans"]
    ]
    robust = summary.get("robustness")
    if robust:  # N.B. results written before robustness scores have none
        header += ("robust best/median",)
        body = [b + ("-" if r.get("robustness_best") is None else
                     f"{r['robustness_best']:.0%}/{r['robustness_median']:.0%}",)
                for b, r in zip(body, summary["task_plans"], strict=True)]
    title = (f"task {summary['task']}: {summary['particles']} particles, "
             f"{summary['wall_time_s']:.1f} s; {summary['returned_plans']} plans returned, "
             f"{summary['verified_fraction']:.0%} verified in MuJoCo C")
    codes = (f" (symbol codes: {summary['distinct_verified_codes']})"
             if summary["declaration"]["symbols"] else "")
    footer = f"distinct verified task plans: {summary['distinct_verified_task_plans']}{codes}"
    if summary.get("repaired_plans"):
        footer += f"; {summary['repaired_plans']} plans verified only after repair in MuJoCo C"
    fid = summary.get("fidelity") or {}
    if "iterations" in fid and "mjx_divergence_p95_m" in fid:
        tol = fid.get("tolerance_m")
        footer += (
            f"\ngradient model: {describe(fid.get('gradient', 'unrolled'), fid['iterations'])}; "
            "MJX vs MuJoCo C "
            f"divergence p95 {fid['mjx_divergence_p95_m']:.2g} m"
            + (f" (tolerance {tol:.2g} m" + ("" if fid.get("faithful", True) else
                                             ", NOT faithful: allow_unfaithful")
               + _chaos_note(fid.get("mjx_final") or {})
               + ("" if fid.get("faithful_at_end", True) else
                  ", over it at the final particles" + _parting_note(fid.get("mjx_final"))
                  + ": their plans are verified in C") + ")"
               if tol is not None else "")
        )
    footer += _particles_line(summary) + _robustness_line(robust)
    if markdown:
        lines = ["| " + " | ".join(header) + " |", "| --- |" + " ---: |" * (len(header) - 1)]
        lines += ["| `" + b[0] + "` | " + " | ".join(b[1:]) + " |" for b in body]
        return "\n\n".join([title, "\n".join(lines), footer])
    widths = [max(len(h), *(len(b[i]) for b in body)) if body else len(h)
              for i, h in enumerate(header)]
    line = "  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True))
    rows = ["  ".join(c.ljust(w) for c, w in zip(b, widths, strict=True)).rstrip()
            for b in body]
    return "\n".join([title, line, "-" * len(line), *rows, footer])


# ----------------------------------------------------------------------------
# Saving and loading.


def check_writable(out: str | os.PathLike) -> Path:
    """Creates `out` if needed and checks a file can be written there, up front."""
    path = Path(out)
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path, prefix=".write-test-")
        os.close(fd)
        os.unlink(tmp)
    except OSError as e:
        raise MjstampError(
            f"results directory {str(path)!r} is not writable: {e.strerror or e}"
        ) from None
    return path


def save(
    out: Path, summary: dict, arrays: dict[str, dict[str, np.ndarray]], *, model=None
) -> list[Path]:
    """Writes plans.json, one .npz per entry of `arrays` and scene.mjb, each atomically.

    scene.mjb is the task's compiled MjModel (meshes and textures included), so
    a results directory plays back without the task's code or MJCF files.
    plans.json is written last: a directory with a plans.json is complete.
    """
    written = []
    if model is not None:
        target = out / "scene.mjb"
        size = mujoco.mj_sizeModel(model)
        buffer = np.empty(size, np.uint8)
        mujoco.mj_saveModel(model, None, buffer)
        write_atomic(target, lambda f: f.write(buffer.tobytes()))
        written.append(target)
    for name, data in arrays.items():
        target = out / f"{name}.npz"
        write_atomic(target, lambda f, d=data: np.savez_compressed(f, **d))
        written.append(target)
    target = out / "plans.json"
    payload = json.dumps({"schema_version": SCHEMA_VERSION, **summary}, indent=2).encode()
    write_atomic(target, lambda f: f.write(payload))
    written.append(target)
    return written


# What readers of a results directory rely on (playback, `select_plans`,
# `mjstamp.load`), checked once by `load` and `load_model`; `SolveResult.summary()`
# and `arrays()` write all of it and more. {key: type}, optional keys checked when
# present.
_SUMMARY = {"task": str, "plans": list, "task_plans": list}
_SUMMARY_OPTIONAL = {"particles": int, "config": dict, "declaration": dict}
_PLAN = {"particle": int, "task_plan": str, "verified": bool, "cost": float}
_PLAN_OPTIONAL = {"predicted_task_plan": str, "repaired": bool, "motion_plan": dict}
_ROW = {"task_plan": str}
# trajectories.npz: required arrays, and the shape of each (symbols bind on first use).
_TRAJECTORIES = ("particle", "qpos0", "qpos")
_TRAJECTORY_SHAPES = {
    "particle": ("rows",), "qpos": ("rows", "T", "nq"), "qpos0": ("rows", "nq"),
    "qvel0": ("rows", "nv"), "qvel": ("rows", "T", "nv"), "ctrl": ("rows", "T", "nu"),
    "xpos": ("rows", "T", "nbody", 3), "timestep": (),
}
# particles.npz: the arrays with one row per particle (the rest are per iteration).
_PER_PARTICLE = ("theta", "svgd_theta", "initial_theta", "cost", "returned", "verified",
                 "repaired", "source", "task_plan", "predicted_task_plan")
_FILES = ("particles.npz", "trajectories.npz", "scene.mjb")
_NAME = re.compile(r"[A-Za-z0-9_.-]+")


def _task_word(task: object) -> str:
    """A task name fit for a suggested command line, else the placeholder TASK."""
    return task if isinstance(task, str) and _NAME.fullmatch(task) else "TASK"


def _rerun(path: Path, task: object) -> str:
    return f"re-run `mjstamp solve {_task_word(task)} --out {shlex.quote(str(path))}`"


def _damaged(file: Path, what: str, task: object) -> MjstampError:
    """One line: the file, what is wrong with it, and the solve that writes it anew."""
    what = " ".join(what.split())  # exception texts may span lines
    return MjstampError(f"{str(file)!r} {what}; {_rerun(file.parent, task)}")


_KINDS = {dict: "an object", list: "a list", str: "a string", bool: "true/false",
          int: "an integer", float: "a number", type(None): "null"}


def _is(value: object, kind: type) -> bool:
    """Whether a JSON value is of `kind` (a bool is no number; an integer is a float)."""
    if isinstance(value, bool) and kind is not bool:
        return False
    return isinstance(value, int | float) if kind is float else isinstance(value, kind)


def _check_fields(obj: dict, where: str, required: dict, optional: dict, bad) -> None:
    for key in required:
        if key not in obj:
            bad(f"has no {key!r} in {where}" if where else f"lacks {key!r}")
    for key, kind in {**required, **optional}.items():
        if key in obj and not _is(obj[key], kind):
            label = f"{where}.{key}" if where else repr(key)
            bad(f"has {label} {_KINDS[type(obj[key])]}, not {_KINDS[kind]}")


def _check_summary(plans: Path, summary: dict) -> None:
    """The shape of plans.json that readers rely on (`_SUMMARY` and below)."""
    task = summary.get("task")

    def bad(what: str):
        raise _damaged(plans, what, task)

    _check_fields(summary, "", _SUMMARY, _SUMMARY_OPTIONAL, bad)
    seen = set()
    for i, entry in enumerate(summary["plans"]):
        if not isinstance(entry, dict):
            bad(f"has plans[{i}] {_KINDS[type(entry)]}, not an object")
        _check_fields(entry, f"plans[{i}]", _PLAN, _PLAN_OPTIONAL, bad)
        if entry["particle"] < 0 or entry["particle"] in seen:
            bad(f"has plans[{i}].particle {entry['particle']} "
                + ("twice" if entry["particle"] in seen else "< 0"))
        seen.add(entry["particle"])
    for i, row in enumerate(summary["task_plans"]):
        if not isinstance(row, dict):
            bad(f"has task_plans[{i}] {_KINDS[type(row)]}, not an object")
        _check_fields(row, f"task_plans[{i}]", _ROW, {}, bad)
    display = summary.get("declaration", {}).get("display") or {}
    if not isinstance(display, dict):
        bad(f"has declaration.display {_KINDS[type(display)]}, not an object")
    trace, force = display.get("trace", []), display.get("force", [])
    if not (isinstance(trace, list) and all(isinstance(b, str) for b in trace)):
        bad("has declaration.display.trace that is not a list of body names")
    if not (isinstance(force, list) and all(
            isinstance(p, list) and len(p) == 2 and all(isinstance(g, str) for g in p)
            for p in force)):
        bad("has declaration.display.force that is not a list of [geom, geom] pairs")


def _checkpoint_task(checkpoint: Path) -> object:
    """The task named in a checkpoint's `meta` (a JSON string), or None if unreadable."""
    try:
        with np.load(checkpoint, allow_pickle=False) as f:
            meta = f["meta"].item()
        meta = meta.decode() if isinstance(meta, bytes) else meta
        return json.loads(meta).get("task")
    except Exception:  # noqa: BLE001 - a damaged checkpoint only costs us the task's name
        return None


def _read_summary(path: Path) -> dict:
    """plans.json, parsed and checked: one MjstampError line for any damage."""
    plans = path / "plans.json"
    if not probe(plans.is_file, path, "results directory "):
        checkpoint = path / "checkpoint.npz"
        if checkpoint.is_file():
            task = _task_word(_checkpoint_task(checkpoint))
            raise MjstampError(
                f"{str(path)!r} holds a checkpoint.npz but no plans.json: the solve did not "
                f"finish; `mjstamp solve {task} --resume {shlex.quote(str(path))}` continues it"
            )
        raise MjstampError(f"{str(path)!r} holds no plans.json (not a results directory; "
                           "`mjstamp solve TASK --out DIR` writes one)")
    try:
        raw = plans.read_bytes()
    except OSError as e:
        raise _damaged(plans, f"cannot be read ({e.strerror or e})", None) from None
    text = raw.decode(errors="replace")
    found = re.search(r'"task":\s*"([^"\\]*)"', text)  # the task, even if JSON fails
    try:
        summary = json.loads(raw.decode())
    except (ValueError, RecursionError) as e:  # JSONDecodeError, UnicodeDecodeError
        raise _damaged(plans, f"is not valid JSON (truncated or overwritten?): {e}",
                       found and found.group(1)) from None
    if not isinstance(summary, dict):
        raise _damaged(plans, f"holds {_KINDS[type(summary)]}, not an object with "
                       "schema_version, task and plans", None)
    version = summary.get("schema_version")
    if version != SCHEMA_VERSION:
        raise MjstampError(
            f"{str(plans)!r} has schema_version {version!r}; this mjstamp reads "
            f"{SCHEMA_VERSION} ({_rerun(path, summary.get('task'))})"
        )
    _check_summary(plans, summary)
    return summary


def _read_npz(file: Path, task: str) -> dict[str, np.ndarray]:
    try:
        f = np.load(file, allow_pickle=False)
    except Exception as e:  # noqa: BLE001 - BadZipFile, EOFError, ValueError, OSError...
        raise _damaged(file, f"is truncated or not an .npz archive ({type(e).__name__}: {e})",
                       task) from None
    if not isinstance(f, np.lib.npyio.NpzFile):
        raise _damaged(file, "holds one .npy array, not an .npz archive", task)
    try:
        with f:
            return {k: f[k] for k in f.files}
    except Exception as e:  # noqa: BLE001 - a corrupt member: zlib.error, BadZipFile (CRC)...
        raise _damaged(file, f"is corrupt ({type(e).__name__}: {e})", task) from None


def _shape_error(arrays: dict, dims: dict, bound: set[str]) -> str | None:
    """What is wrong with the shapes of trajectories.npz's arrays, or None.

    Args:
      arrays: the arrays.
      dims: sizes of the symbols in `_TRAJECTORY_SHAPES` known so far; filled
        in by the first array that has each.
      bound: the symbols whose sizes come from scene.mjb (named in the error).
    """
    for key, spec in _TRAJECTORY_SHAPES.items():
        if key not in arrays:
            continue
        a = arrays[key]
        numeric = "iu" if key == "particle" else "fiu"
        if a.dtype.kind not in numeric:
            return f"has {key} of dtype {a.dtype}, not numbers"
        expected = f"has {key} of shape {a.shape}, not ({', '.join(map(str, spec))})"
        if a.ndim != len(spec):
            return expected
        for size, sym in zip(a.shape, spec, strict=True):
            want = sym if isinstance(sym, int) else dims.setdefault(sym, size)
            if size != want and isinstance(sym, int):
                return expected
            if size != want:
                if sym in bound:
                    return (f"has {key} of shape {a.shape} but scene.mjb has {sym}={want} "
                            "(files from different runs?)")
                return (f"has {key} of shape {a.shape}, where {sym}={want} "
                        "(files from different runs?)")
    if dims.get("T") == 0:
        return "has trajectories of no steps"
    if "timestep" in arrays and not float(arrays["timestep"]) > 0:
        return f"has timestep {float(arrays['timestep'])}, not > 0"
    return None


def load(out: str | os.PathLike) -> tuple[dict, dict[str, dict[str, np.ndarray]]]:
    """Loads what `save` wrote: (plans.json contents, {npz name: arrays}).

    The one check of a results directory's files (playback and `mjstamp.load`
    go through here and `load_model`): every damage is one `MjstampError`
    line naming the file, what is wrong and what to do.

    Returns:
      The summary and {"particles": ..., "trajectories": ...}.

    Raises:
      MjstampError: no plans.json (with a checkpoint.npz: an unfinished
        solve), plans.json not JSON, of another schema version or of the wrong
        shape; a file missing, truncated, not an .npz, missing arrays or with
        arrays of the wrong shape (fewer rows than plans.json's plans).
    """
    path = Path(out)
    summary = _read_summary(path)
    task = summary["task"]
    missing = [name for name in _FILES if not (path / name).is_file()]
    if missing:
        raise MjstampError(f"{str(path)!r} lacks {valid_list(missing)} (an incomplete copy?); "
                           f"{_rerun(path, task)}")
    listed = sorted(e["particle"] for e in summary["plans"])

    file = path / "particles.npz"
    particles = _read_npz(file, task)
    count = summary.get("particles")
    for key in _PER_PARTICLE:
        if key not in particles:
            continue
        a = particles[key]
        if a.ndim == 0:
            raise _damaged(file, f"has {key} of shape (), not one row per particle", task)
        n = a.shape[0]
        count = n if count is None else count  # no count in plans.json: the first sets it
        if n != count or (listed and n <= listed[-1]):
            raise _damaged(file, f"has {key} of {n} rows, but plans.json has " + (
                f"{count} particles" if n != count else f"a plan of particle {listed[-1]}"),
                task)

    file = path / "trajectories.npz"
    traj = _read_npz(file, task)
    absent = [k for k in _TRAJECTORIES if k not in traj]
    if absent:
        raise _damaged(file, f"lacks {valid_list(absent)}", task)
    error = _shape_error(traj, {}, set())
    if error:
        raise _damaged(file, error, task)
    unsaved = sorted(set(listed) - set(traj["particle"].tolist()))
    if unsaved:
        raise _damaged(file, f"has no trajectory of particle {valid_list(unsaved)}, which "
                       "plans.json lists (fewer rows than plans?)", task)
    return summary, {"particles": particles, "trajectories": traj}


def load_model(out: str | os.PathLike, *, trajectories: dict[str, np.ndarray] | None = None,
               task: str | None = None) -> mujoco.MjModel:
    """The compiled scene saved with a results directory (scene.mjb).

    Args:
      out: the results directory.
      trajectories: its trajectories.npz arrays (from `load`), whose sizes
        (nq, nv, nu, nbody) must be the scene's.
      task: its task, for the advice in errors.

    Raises:
      MjstampError: no scene.mjb, not a MuJoCo model, or another scene's.
    """
    path = Path(out) / "scene.mjb"
    if not path.is_file():
        raise MjstampError(f"{str(path.parent)!r} holds no scene.mjb (not a results directory; "
                           f"{_rerun(path.parent, task)})")
    # N.B. MuJoCo prints why a model file is unreadable on stderr (a second line
    # and a blank one); the warning handler puts it into our one line instead.
    warnings: list[str] = []
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(warnings.append)
    try:
        m = mujoco.MjModel.from_binary_path(str(path))
    except Exception as e:  # noqa: BLE001 - MuJoCo raises a bare Exception/ValueError
        why = "; ".join(warnings) or str(e)
        raise _damaged(path, f"is not a readable MuJoCo model ({why})", task) from None
    finally:
        mujoco.set_mju_user_warning(previous)
    if trajectories is not None:
        sizes = {"nq": m.nq, "nv": m.nv, "nu": m.nu, "nbody": m.nbody}
        error = _shape_error(trajectories, dict(sizes), set(sizes))
        if error:
            raise _damaged(path.parent / "trajectories.npz", error, task)
    return m
