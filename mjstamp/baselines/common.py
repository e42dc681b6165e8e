"""What the baselines share: the found-plan tracker, candidate task plans, the constrained loss.

Every baseline ends the way `solve` does: a plan counts when its MuJoCo C
replay with the scene's own solver succeeds (`verify.simulate_c`, then the
task's own `decode`), and its task plan is read off that replay. The tracker
times the first verification of each distinct task plan, so a method's time to
N task plans includes everything it did to get there (rollouts, gradients,
replays), compiles excepted when the caller warms up first.
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mjstamp import verify
from mjstamp.errors import MjstampError
from mjstamp.tasks.declaration import Kind
from mjstamp.tasks.problem import Problem

__all__ = ["BaselineResult", "Candidate", "Tracker", "candidates", "constrained_logdensity"]


@dataclasses.dataclass
class BaselineResult:
    """What a baseline found.

    Attributes:
      method: "enumerate", "blocking", "cem" or "cmaes".
      task: the task's name.
      seed: the seed.
      target: the distinct verified task plans asked for (None: until the cap).
      cap_s: the wall-time cap.
      found: one dict per distinct verified task plan, in the order found:
        {"task_plan", "code", "found_at_s", "theta" (list), "cost_c"}.
      wall_s: seconds used (until the target was reached, or the cap).
      reached: whether `target` distinct task plans were verified within the cap.
      runs: optimisation runs (enumerate, blocking) or generations (cem, cmaes).
      rollouts: particle rollouts done (MJX or MuJoCo C), verification included.
      settings: the method's own settings.
    """

    method: str
    task: str
    seed: int
    target: int | None
    cap_s: float
    found: list[dict]
    wall_s: float
    reached: bool
    runs: int
    rollouts: int
    settings: dict

    @property
    def task_plans(self) -> list[str]:
        """The distinct verified task plans, in the order found."""
        return [f["task_plan"] for f in self.found]

    def time_to(self, n: int) -> float | None:
        """Seconds until n distinct task plans were verified, or None if fewer were."""
        return self.found[n - 1]["found_at_s"] if len(self.found) >= n else None

    def summary(self) -> dict[str, Any]:
        """JSON-ready: the fields of `solve`'s summary that apply, and the method's own."""
        return {
            "method": self.method, "task": self.task, "seed": self.seed, "target": self.target,
            "cap_s": self.cap_s, "wall_time_s": self.wall_s, "reached": self.reached,
            "distinct_verified_task_plans": len(self.found),
            "distinct_verified_codes": len({f["code"] for f in self.found}),
            "verified_task_plans": self.task_plans, "runs": self.runs,
            "rollouts": self.rollouts, "settings": self.settings, "plans": self.found,
        }


class Tracker:
    """Distinct task plans verified in MuJoCo C, timed from the tracker's start."""

    def __init__(self, problem: Problem, target: int | None, cap_s: float, *,
                 start: float | None = None):
        if target is not None and (isinstance(target, bool) or not isinstance(target, int)
                                   or target < 1):
            raise MjstampError(f"target={target!r} must be an integer >= 1 (task plans) or None")
        if isinstance(cap_s, bool) or not isinstance(cap_s, (int, float)) or not cap_s > 0:
            raise MjstampError(f"cap_s={cap_s!r} must be a number of seconds > 0")
        self.problem, self.target, self.cap_s = problem, target, float(cap_s)
        self.found: dict[str, dict] = {}
        self.rollouts = 0
        # N.B. `start`: when the method began (its calibration and compiles count,
        # as STAMP's screen and calibration do in its wall time).
        self.start = time.perf_counter() if start is None else start
        self.finished_at: float | None = None

    def elapsed(self) -> float:
        """Seconds since the tracker started."""
        return time.perf_counter() - self.start

    @property
    def done(self) -> bool:
        """The target is reached, or the cap spent."""
        return self.finished_at is not None or self.elapsed() >= self.cap_s

    def verify(self, theta: np.ndarray) -> verify.Decoded:
        """Replays θ (n, d) in MuJoCo C, records new verified task plans; returns the decode."""
        theta = np.asarray(theta, np.float64)
        replay = verify.simulate_c(self.problem, theta)
        decoded = verify.decode(self.problem, replay, theta)
        self.rollouts += len(theta)
        self.record(decoded, theta, replay)
        return decoded

    def record(self, decoded: verify.Decoded, theta: np.ndarray, replay) -> list[str]:
        """Adds the successful, not yet found task plans of a decoded C replay."""
        now = self.elapsed()
        if self.finished_at is not None or now > self.cap_s:
            return []  # N.B. what comes after the cap does not count
        new = []
        for i in np.flatnonzero(decoded.ok):
            plan = str(decoded.plan[i])
            if plan in self.found:
                continue
            cost = float(verify.cost_c(self.problem, replay.rows([i]), theta[[i]])[0])
            code, actions = str(decoded.code[i]), list(decoded.actions[i])
            self.found[plan] = {
                "task_plan": plan, "code": code, "symbolic": symbolic(code, actions),
                "action_ids": chosen(self.problem, theta[i]), "found_at_s": now,
                "theta": theta[i].tolist(), "cost_c": cost}
            new.append(plan)
            if self.target is not None and len(self.found) >= self.target:
                self.finished_at = now
                break
        return new

    def result(self, method: str, seed: int, runs: int, settings: dict) -> BaselineResult:
        """The `BaselineResult` of what was found."""
        # N.B. a method stopped by its cap is reported at the cap: what it did after
        # (the rest of a run, at most `check_every` iterations) is not counted.
        wall = self.finished_at if self.finished_at is not None else min(self.elapsed(),
                                                                          self.cap_s)
        return BaselineResult(
            method=method, task=self.problem.name, seed=seed, target=self.target,
            cap_s=self.cap_s, found=list(self.found.values()), wall_s=float(wall),
            reached=self.target is not None and len(self.found) >= self.target, runs=runs,
            rollouts=self.rollouts, settings=settings)


@dataclasses.dataclass(frozen=True)
class Candidate:
    """A task plan to ask for: symbol bits and, per discrete variable, an option per phase."""

    bits: tuple[int, ...]
    actions: tuple[tuple[int, ...], ...]

    def name(self, problem: Problem) -> str:
        """The task plan's symbolic part, as `Problem.decode` spells it (less the label)."""
        acts = [v.options[o] for v, opts in zip(_discrete(problem), self.actions, strict=True)
                for o in opts]
        return symbolic("".join(map(str, self.bits)), acts)


def symbolic(code: str, actions: list[str]) -> str:
    """A task plan without its success label: "0110", "push-a,push-b", "01-push-a"."""
    return "-".join(p for p in (code, ",".join(actions)) if p) or "-"


def chosen(problem: Problem, theta: np.ndarray) -> tuple[tuple[int, ...], ...]:
    """Per discrete variable, the option Γ(θ) takes in each phase (argmax of its logits)."""
    out = []
    for v in _discrete(problem):
        logits = np.asarray(theta)[problem.slices()[v.name]].reshape(v.phases, len(v.options))
        out.append(tuple(int(o) for o in logits.argmax(axis=1)))
    return tuple(out)


def _discrete(problem: Problem):
    return [v for v in problem.variables if v.kind is Kind.DISCRETE]


def candidates(problem: Problem, *, limit: int = 4096) -> list[Candidate]:
    """Every combination of symbol bits and discrete options (the symbolic plans to try).

    Raises:
      MjstampError: the task has neither symbols nor discrete variables (there
        is nothing to enumerate), or more than `limit` combinations.
    """
    discrete = _discrete(problem)
    if not problem.contacts and not discrete:
        raise MjstampError(f"task {problem.name!r} declares no contact symbols and no discrete "
                           "actions: there are no task plans to enumerate (use cem)")
    count = 2 ** len(problem.contacts)
    for v in discrete:
        count *= len(v.options) ** v.phases
    if count > limit:
        raise MjstampError(f"task {problem.name!r} has {count} symbolic plans to enumerate, "
                           f"more than {limit}")
    bit_sets = list(itertools.product((0, 1), repeat=len(problem.contacts)))
    action_sets = [list(itertools.product(range(len(v.options)), repeat=v.phases))
                   for v in discrete]
    return [Candidate(tuple(b), tuple(a))
            for b in bit_sets for a in itertools.product(*action_sets)]


def spec_size(problem: Problem) -> tuple[int, int]:
    """(symbols S, one-hot width A of all discrete variables' phases)."""
    width = sum(v.phases * len(v.options) for v in _discrete(problem))
    return len(problem.contacts), width


def empty_spec(problem: Problem, blocked: int, dtype) -> dict[str, np.ndarray]:
    """A spec asking for nothing: no symbols wanted, no actions fixed, nothing blocked."""
    s, a = spec_size(problem)
    return {"want": np.zeros(s, dtype), "want_on": np.zeros((), dtype),
            "fix": np.zeros(a, dtype), "fix_on": np.zeros((), dtype),
            "blocked": np.zeros((blocked, s), dtype),
            "blocked_actions": np.zeros((blocked, a), dtype),
            "blocked_on": np.zeros(blocked, dtype)}


def onehots(problem: Problem, actions: tuple[tuple[int, ...], ...], dtype) -> np.ndarray:
    """(A,) the one-hots of a candidate's options, in θ's logit layout."""
    parts = []
    for v, opts in zip(_discrete(problem), actions, strict=True):
        block = np.zeros((v.phases, len(v.options)), dtype)
        block[np.arange(v.phases), list(opts)] = 1.0
        parts.append(block.ravel())
    return np.concatenate(parts) if parts else np.zeros(0, dtype)


def constrained_logdensity(problem: Problem, *, symbol_weight: float, block_weight: float):
    """Log density (n,): −C(θ) at Γ(θ), plus the loss that asks for or blocks task plans.

    spec (arrays, so that one compile serves every candidate):
      want (S,) bits and want_on: add symbol_weight · Σ_k (s_k − want_k)², s the
        soft contact indicators (App. E's loss that requires the chosen symbols);
      fix (A,) one-hots and fix_on: the discrete options are fixed to these
        (their logits replaced), as App. E fixes them;
      blocked (M, S), blocked_actions (M, A), blocked_on (M,): add
        block_weight · Σ_j P(plan j), P the soft probability of repeating a
        blocked task plan (Π_k s_k or 1 − s_k, times the Γ̃ probabilities of its
        options): Diverse LGP's penalty on the plans already found.
    """
    discrete = _discrete(problem)
    blocks = [(problem.slices()[v.name], v.phases, len(v.options)) for v in discrete]

    def logp(theta, spec):
        n = theta.shape[0]
        probs = []
        for sl, phases, m in blocks:
            logits = theta[:, sl]
            probs.append(jax.nn.softmax(logits.reshape(n, phases, m), axis=-1).reshape(n, -1))
        if blocks:
            fixed = 8.0 * (2.0 * spec["fix"] - 1.0)
            start = 0
            for sl, phases, m in blocks:
                width = phases * m
                part = jnp.broadcast_to(fixed[start:start + width], (n, width))
                theta = theta.at[:, sl].set(jnp.where(spec["fix_on"] > 0, part, theta[:, sl]))
                start += width
        r, values = problem.evaluate(theta, hard=True)
        cost = problem.cost_total(values)
        if problem.contacts:
            s = jnp.stack([r.symbols[c.name] for c in problem.contacts], axis=1)  # (n, S)
            cost = cost + spec["want_on"] * symbol_weight * jnp.sum((s - spec["want"]) ** 2, 1)
            match = jnp.where(spec["blocked"][None] > 0, s[:, None], 1.0 - s[:, None]).prod(-1)
        else:
            match = jnp.ones((n, spec["blocked"].shape[0]), theta.dtype)
        if blocks:
            p = jnp.concatenate(probs, axis=1)  # (n, A)
            logq = jnp.log(jnp.clip(p, 1e-12))[:, None, :] * spec["blocked_actions"][None]
            match = match * jnp.exp(logq.sum(-1))
        cost = cost + block_weight * jnp.sum(spec["blocked_on"][None] * match, axis=1)
        return -cost

    return logp
