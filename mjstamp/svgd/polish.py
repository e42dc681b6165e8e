"""Precision polish: batched, box-bounded Levenberg–Marquardt on each particle's residuals.

Adam at a fixed step circles an optimum at about its step's scale; a goal
whose success region is small (a point goal within r: a share of the box that
shrinks as r^k) needs a descent that converges into it. Where the cost is a
sum of squares C = Σ r(θ)² (plus terms that hold still), Gauss–Newton's model
r(θ + δ) ≈ r + Jδ is exact to first order, and a damped step
(JᵀJ + μ·s·I) δ = −Jᵀr lands a particle inside a contact mode in a handful of
steps.

Each particle runs its own Levenberg–Marquardt, all in one batch: one
evaluation of the residuals and their Jacobians per iteration (forward mode
with d tangents or reverse mode with m pullbacks, `value_and_batched_jacobian`),
at the trial point; a trial is kept only where P = Σ r² falls by at least a
share of what the model predicts (Armijo's rule as
`mujoco.minimize.least_squares` applies it). Only the residuals count: a
task's other costs (an aim, an effort) shape the landscape STAMP explores, but
their minimum is not the goal, and a polish that held them would stop short
of it;
μ falls after a good prediction and rises after a poor one or a rejection
(Fletcher's rule, as MuJoCo's). Coordinates work in units of their box width,
so μ weighs every coordinate alike (MuJoCo's `x_scale`); the box is respected
by freezing coordinates at a bound whose gradient points out (MuJoCo's clamped
set) and clipping the step. A particle stops when its residuals are within
`depth` of their goals' tolerances (landed), when an accepted step no longer
lowers P by a relative `stall`, when μ passes `mu_max`, or at `max_iters`.

Pure JAX on any particle-separable residual function: nothing here knows of
MuJoCo (`mjstamp.solve` hands it the task's residuals on its MJX rollouts).

References:
  K. Madsen, H. B. Nielsen, O. Tingleff, "Methods for non-linear least squares
  problems" (2004), §3.2; MuJoCo's `mujoco.minimize.least_squares`.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from mjstamp.errors import MjstampError
from mjstamp.progress import Progress, ProgressLike
from mjstamp.svgd._jacobian import value_and_batched_jacobian

__all__ = ["PolishConfig", "PolishResult", "PolishState", "build_polish_step", "run_polish"]

#: Armijo's constant: a trial must lower P by this share of the model's predicted reduction.
ARMIJO = 1e-2

#: With `PolishConfig.patience`, the batch stops while fewer than this share still descend.
STRAGGLERS = 0.1


@dataclasses.dataclass(frozen=True)
class PolishConfig:
    """Settings of the precision polish; validated on construction.

    Attributes:
      max_iters: most iterations (each one evaluation of the residuals and
        their Jacobians); 0 turns the polish off; None: the caller decides
        (`mjstamp.solve`: by the device, `polish_iterations`), and
        `run_polish` takes 20.
      patience: the batch stops once this many iterations landed no particle
        while fewer than a tenth of the particles still descend (each step
        costs the whole batch); 0: it runs while any descends.
      depth: a particle has landed when every residual term with a tolerance
        is within `depth` × its tolerance (0.25: inside the goal, not at its
        edge, so a plan survives small differences of the physics).
      stall: a particle stops when an accepted step lowers its objective by
        less than this share of it.
      mu0: initial damping μ, relative to the mean of diag(JᵀJ).
      mu_max: a particle whose μ passes this stops: 100 × the mean curvature
        leaves steps of about 1% of Gauss–Newton's, which means the model
        predicts nothing at any useful scale (a landscape rough at fine
        scales: `mjstamp.verify.land` takes over there).
    """

    max_iters: int | None = None
    patience: int = 3
    depth: float = 0.25
    stall: float = 1e-4
    mu0: float = 1e-3
    mu_max: float = 1e2

    def __post_init__(self):
        if self.max_iters is not None and (
                isinstance(self.max_iters, bool) or not isinstance(self.max_iters, int)
                or self.max_iters < 0):
            raise MjstampError(f"polish.max_iters={self.max_iters!r} must be an integer >= 0 "
                               "or None")
        if (isinstance(self.patience, bool) or not isinstance(self.patience, int)
                or self.patience < 0):
            raise MjstampError(f"polish.patience={self.patience!r} must be an integer >= 0")
        for name, low, high in (("depth", 0.0, 1.0), ("stall", 0.0, 1.0),
                                ("mu0", 0.0, np.inf), ("mu_max", 0.0, np.inf)):
            value = getattr(self, name)
            if (isinstance(value, bool) or not isinstance(value, (int, float))
                    or not (low < value <= high) or not np.isfinite(value)):
                bounds = f"({low:g}, {high:g}]" if np.isfinite(high) else f"({low:g}, inf)"
                raise MjstampError(f"polish.{name}={value!r} must be a finite number in {bounds}")
        if self.mu0 >= self.mu_max:
            raise MjstampError(f"polish.mu0={self.mu0!r} must be below polish.mu_max="
                               f"{self.mu_max!r}")


class PolishState(NamedTuple):
    """The batch's Levenberg–Marquardt state (n particles, d coordinates, m residuals).

    Attributes:
      theta: (n, d) current points.
      residual: (n, m) residuals at `theta`.
      objective: (n,) P = Σ r² at `theta`.
      jac: (n, m, d) Jacobians of the residuals at `theta`.
      mu: (n,) damping.
      done: (n,) stopped.
      landed: (n,) within the goals' tolerances (`PolishConfig.depth`).
      iterations: (n,) iterations each particle ran.
      fresh: (n,) not evaluated yet: the next step evaluates `theta` itself.
    """

    theta: jax.Array
    residual: jax.Array
    objective: jax.Array
    jac: jax.Array
    mu: jax.Array
    done: jax.Array
    landed: jax.Array
    iterations: jax.Array
    fresh: jax.Array


def _landed(residual, sizes, tolerances, depth):
    """(n,) every term with a tolerance within depth × it (False where none has one)."""
    out, any_goal = jnp.ones(residual.shape[0], bool), False
    bounds = np.cumsum([0, *sizes])
    for start, stop, tol in zip(bounds[:-1], bounds[1:], tolerances, strict=True):
        if tol is None:
            continue
        any_goal = True
        norm = jnp.linalg.norm(residual[:, start:stop], axis=1)
        out &= norm <= depth * tol
    return out if any_goal else jnp.zeros(residual.shape[0], bool)


def build_polish_step(
    fn: Callable[[jax.Array], Sequence[jax.Array]],
    low: np.ndarray,
    high: np.ndarray,
    config: PolishConfig,
    *,
    tolerances: Sequence[float | None] = (),
    mode: str = "auto",
):
    """(init, step) of the batched Levenberg–Marquardt polish.

    Args:
      fn: θ (n, d) -> [r_k (n, m_k)], the residuals of each term,
        particle-separable; the objective is P = Σ_k ‖r_k‖².
      low: (d,) the box's lower bounds.
      high: (d,) its upper bounds.
      config: `PolishConfig`.
      tolerances: per term, the norm ‖r_k‖ within which its goal is met, or None.
      mode: how the Jacobian is taken: 'fwd' (d tangents), 'rev' (m pullbacks)
        or 'auto' (whichever is fewer).

    Returns:
      init(θ, m) -> PolishState (m: the residuals' count; nothing is evaluated);
      step(state) -> (state, info {"accepted": (n,)}): the first step evaluates
      θ, every later one a trial per particle.
    """
    low_np, high_np = np.asarray(low, np.float64), np.asarray(high, np.float64)
    width_np = np.where(high_np > low_np, high_np - low_np, 1.0)
    sizes: list[int] = []  # m_k, read off the first trace of fn

    def flat(theta):
        parts = fn(theta)
        if len(parts) != len(tolerances):
            raise ValueError(f"{len(parts)} residual terms, {len(tolerances)} tolerances")
        sizes[:] = [x.shape[1] for x in parts]
        r = jnp.concatenate(parts, axis=1)
        return r, jnp.sum(r**2, axis=1)

    def evaluate(theta):
        how = mode
        if how == "auto":
            m = sum(sizes) if sizes else jax.eval_shape(flat, theta)[0].shape[1]
            how = "rev" if m < theta.shape[1] else "fwd"
        (r, p), jac = value_and_batched_jacobian(flat, theta, how, has_aux=True)
        return r, p, jac

    def init(theta, m: int):
        """The state before any evaluation: the first `step` evaluates θ and keeps it."""
        n, d = theta.shape
        dtype = theta.dtype
        return PolishState(theta, jnp.zeros((n, m), dtype), jnp.full(n, jnp.inf, dtype),
                           jnp.zeros((n, m, d), dtype), jnp.full(n, config.mu0, dtype),
                           jnp.zeros(n, bool), jnp.zeros(n, bool), jnp.zeros(n, jnp.int32),
                           jnp.ones(n, bool))

    def step(state: PolishState):
        dtype = state.theta.dtype
        low_, high_ = jnp.asarray(low_np, dtype), jnp.asarray(high_np, dtype)
        width = jnp.asarray(width_np, dtype)
        theta, r, jac = state.theta, state.residual, state.jac
        jz = jac * width  # (n, m, d): columns in box widths
        grad = jnp.einsum("nmd,nm->nd", jz, r)
        # N.B. MuJoCo's clamped set: a coordinate at a bound whose descent points out stays.
        clamped = ((theta <= low_) & (grad > 0)) | ((theta >= high_) & (grad < 0))
        jf = jz * ~clamped[:, None, :]
        hess = jnp.einsum("nmd,nme->nde", jf, jf)
        d = theta.shape[1]
        scale = jnp.trace(hess, axis1=1, axis2=2) / d + jnp.finfo(dtype).tiny
        damped = hess + (state.mu * scale)[:, None, None] * jnp.eye(d, dtype=dtype)
        dz = -jnp.linalg.solve(damped, (grad * ~clamped)[..., None])[..., 0]
        trial = jnp.clip(theta + dz * width, low_, high_)
        # N.B. a fresh row evaluates its own θ: one compiled program serves start and steps.
        trial = jnp.where((state.done | state.fresh)[:, None], theta, trial)
        r_new, p_new, jac_new = evaluate(trial)
        dtheta = trial - theta
        model = r + jnp.einsum("nmd,nd->nm", jac, dtheta)
        predicted = jnp.sum(r**2, axis=1) - jnp.sum(model**2, axis=1)
        actual = state.objective - p_new
        finite = jnp.isfinite(p_new) & jnp.all(jnp.isfinite(jac_new), axis=(1, 2))
        active = ~state.done & ~state.fresh
        ok = (active & finite & (predicted > 0) & (actual >= ARMIJO * predicted))
        ok |= state.fresh & finite
        ratio = jnp.where(predicted > 0, actual / jnp.where(predicted > 0, predicted, 1), 0)
        # Fletcher's rule (as MuJoCo's least_squares), μ floored at 1e-12 of the scale.
        mu = jnp.where(ok & (ratio > 0.75), jnp.maximum(state.mu / 3, 1e-12), state.mu)
        mu = jnp.where(ok & (ratio < 0.25), mu * 2, mu)
        mu = jnp.where(active & ~ok, mu * 10, mu)
        mu = jnp.where(state.fresh, state.mu, mu)
        keep = ok[:, None]
        theta = jnp.where(keep, trial, theta)
        r = jnp.where(keep, r_new, r)
        p = jnp.where(ok, p_new, state.objective)
        jac = jnp.where(ok[:, None, None], jac_new, jac)
        landed = _landed(r, sizes, tolerances, config.depth)
        stalled = ok & active & (actual <= config.stall * jnp.abs(state.objective))
        done = state.done | landed | stalled | (mu > config.mu_max) | (state.fresh & ~finite)
        iterations = state.iterations + active.astype(jnp.int32)
        return (PolishState(theta, r, p, jac, mu, done, landed, iterations,
                            jnp.zeros_like(state.fresh)), {"accepted": ok & active})

    return init, step


@dataclasses.dataclass(frozen=True)
class PolishResult:
    """What a polish did.

    Attributes:
      particles: (n, d) polished points.
      iterations: (n,) iterations each particle ran.
      landed: (n,) within its goals' tolerances.
      objective_before, objective_after: (n,) P at the start and the end.
      steps: iterations the batch ran.
      seconds: wall time (compiles included).
    """

    particles: np.ndarray
    iterations: np.ndarray
    landed: np.ndarray
    objective_before: np.ndarray
    objective_after: np.ndarray
    steps: int
    seconds: float

    def as_dict(self) -> dict:
        """JSON-ready summary (no per-particle arrays)."""
        it = self.iterations
        better = self.objective_after < self.objective_before
        return {"particles": int(len(it)), "steps": self.steps,
                "iterations_median": float(np.median(it)) if len(it) else 0.0,
                "iterations_max": int(it.max()) if len(it) else 0,
                "landed": int(self.landed.sum()), "improved": int(better.sum()),
                "seconds": round(self.seconds, 3)}


def run_polish(
    fn: Callable[[jax.Array], Sequence[jax.Array]],
    theta0,
    low: np.ndarray,
    high: np.ndarray,
    config: PolishConfig = PolishConfig(),
    *,
    tolerances: Sequence[float | None] = (),
    mode: str = "auto",
    jit: Callable | None = None,
    progress: ProgressLike = False,
) -> PolishResult:
    """Polishes particles θ0 (n, d) on residuals `fn` (see `build_polish_step`).

    Args:
      fn: θ (n, d) -> [r_k (n, m_k)] (`build_polish_step`).
      theta0: (n, d) the particles.
      low: (d,) the box's lower bounds.
      high: (d,) its upper bounds.
      config: `PolishConfig` (max_iters None: 20).
      tolerances: per term, its goal's radius in the units of r_k, or None.
      mode: the Jacobian's mode ('fwd', 'rev', 'auto').
      jit: `jit(fn, name, *example) -> compiled fn` (the solve's trace cache);
        None: `jax.jit`.
      progress: hears a line per few iterations (`mjstamp.progress`).

    Returns:
      A `PolishResult`.
    """
    started = time.perf_counter()
    if config.max_iters is None:
        config = dataclasses.replace(config, max_iters=20)
    say = Progress.of(progress, "polish")
    theta0 = jnp.asarray(theta0)
    init, step = build_polish_step(fn, low, high, config, tolerances=tolerances, mode=mode)
    compile_ = (lambda f, name, *example: jax.jit(f)) if jit is None else jit
    m = sum(x.shape[1] for x in jax.eval_shape(fn, theta0))
    state = init(theta0, m)
    stepper = compile_(step, "polish-step", state)
    state, _ = stepper(state)  # evaluates θ0
    before = np.asarray(state.objective, np.float64)
    steps, history = 0, [int(jnp.sum(state.landed))]
    while steps < config.max_iters and not bool(jnp.all(state.done)):
        state, _ = stepper(state)
        steps += 1
        history.append(int(jnp.sum(state.landed)))
        # N.B. a few stragglers would hold the whole batch: each step costs all of it.
        if (config.patience and len(history) > config.patience
                and history[-1] == history[-1 - config.patience]
                and int(jnp.sum(~state.done)) < STRAGGLERS * len(before)):
            break
        if steps == 1 or steps % 5 == 0:
            say(f"polish {steps}/{config.max_iters}: {int(jnp.sum(state.landed))} of "
                f"{len(before)} landed, {int(jnp.sum(~state.done))} still descending")
    out = jax.device_get(state)
    return PolishResult(np.asarray(out.theta, np.float64), np.asarray(out.iterations),
                        np.asarray(out.landed), before, np.asarray(out.objective, np.float64),
                        steps, time.perf_counter() - started)
