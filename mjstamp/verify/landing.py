"""Landing: Gauss–Newton in MuJoCo C, on central differences at the step's own scale.

The polish in the gradient model (`mjstamp.svgd.polish`) trusts the Jacobian
at a point. Where a scene's outcome is rough at fine scales that trust fails:
on billiards' 10 ms steps the target ball's resting place, as a function of
the cue's velocity, is smooth at 0.01 m/s and ripples by centimetres at
0.001 m/s (contacts begin on a step grid), so its exact derivative (AD agrees
with central differences at 1e-5) predicts nothing at the scale of a step, and
damped Gauss–Newton crawls. `land` takes the model from the scene's own
physics at the scale it steps at instead, as derivative-free least squares
does (`mujoco.minimize.least_squares` on finite differences): each iteration
replays, per particle, the 2k points θ ± ρ·w_j e_j of its k movable
coordinates (ρ its trust radius in box widths w) and the Gauss–Newton step
from their central differences, truncated to ρ, all in batched MuJoCo C. The
centre moves to the best of the step and the stencil; ρ doubles after a
well-predicted step and quarters after a poor one. Every point replayed is
decoded: a particle keeps its best success (lowest Σ r²; in its own task plan
where it held one already, so landing deepens a plan and never swaps it for
another particle's) and stops once one is within `depth` of its goals'
tolerances (landed), when ρ falls below `min_radius`, or after `iterations`.

Cheap where it matters: a C rollout costs a small fraction of an MJX value and
gradient, so 20 iterations of a 2-D plan (5 rollouts each) cost less than one
STAMP iteration's gradient.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from mjstamp.tasks.problem import as_problem
from mjstamp.verify.repairs import _box
from mjstamp.verify.replay import Replay, decode, residuals_c, simulate_c


@dataclasses.dataclass
class Landing:
    """What `land` did to n particles.

    Attributes:
      theta: (n, d) each particle's best success in C (lowest Σ r²), or its
        final centre where it found none.
      ok: (n,) `theta` succeeds in MuJoCo C.
      landed: (n,) ... and within `depth` of its goals' tolerances (where the
        task declares none: succeeds).
      objective: (n,) Σ r² of `theta` in C.
      iterations: (n,) iterations each particle ran.
      rollouts: MuJoCo C rollouts spent.
      seconds: wall time.
      plan: (n,) the task plan `theta` verifies in C ("" where not `ok`).
    """

    theta: np.ndarray
    ok: np.ndarray
    landed: np.ndarray
    objective: np.ndarray
    iterations: np.ndarray
    rollouts: int
    seconds: float
    plan: np.ndarray | None = None


def _evaluate(problem, theta, tolerances, depth, replay: Replay | None = None):
    """(Σ r² (m,), residual (m, M), ok (m,), landed (m,), plan (m,)) of points θ (m, d) in C."""
    m = len(theta)
    if replay is None:
        # N.B. batches padded to a power of two rows (copies of the last): a task's controls
        # (pushing's skills) and the poses are compiled per batch shape, and the active
        # particles change in number every iteration.
        theta = np.concatenate([theta, np.repeat(theta[-1:], (1 << (m - 1).bit_length()) - m,
                                                 axis=0)])
        replay = simulate_c(problem, theta)
    parts = [part[:m] for part in residuals_c(problem, replay, theta)]
    decoded = decode(problem, replay, theta)
    ok = np.asarray(decoded.ok, bool)[:m]
    landed = ok.copy()
    for part, tol in zip(parts, tolerances, strict=True):
        if tol is not None:
            landed &= np.linalg.norm(part, axis=1) <= depth * tol
    r = np.concatenate(parts, axis=1)
    return np.sum(r**2, axis=1), r, ok, landed, np.asarray(decoded.plan, dtype=object)[:m]


class _Best:
    """Each particle's best success so far, in the task plan it started with (if any).

    N.B. a particle that already holds a task plan keeps it: landing deepens, never swaps.
    """

    def __init__(self, theta: np.ndarray, p, ok, landed, plan):
        self.target = np.where(ok, plan, None)
        self.theta, self.p = theta.copy(), np.where(ok, p, np.inf)
        self.ok, self.landed = ok.copy(), landed.copy()
        self.plan = np.where(ok, plan, "").astype(object)

    @staticmethod
    def rank(p, ok, landed):
        """Lower is better: landed (by Σ r²) < success (by Σ r²) < anything else (inf)."""
        return np.where(landed, -1.0 / (1.0 + p), np.where(ok, p, np.inf))

    def keep(self, rows, pts, p, ok, landed, plan) -> None:
        """Each row's best success among its points pts (len(rows), s, d), in its task plan."""
        mine = self.target[rows][:, None]
        ok = ok & ((mine == None) | (plan == mine))  # noqa: E711 - elementwise on objects
        landed = landed & ok
        score = self.rank(p, ok, landed)
        j = np.argmin(score, axis=1)
        take = np.arange(len(rows))
        better = score[take, j] < self.rank(self.p[rows], self.ok[rows], self.landed[rows])
        idx = rows[better]
        self.theta[idx], self.p[idx] = pts[take, j][better], p[take, j][better]
        self.ok[idx], self.landed[idx] = True, landed[take, j][better]
        self.plan[idx] = plan[take, j][better]


def _stencil(centre: np.ndarray, rho: np.ndarray, axes: np.ndarray, width: np.ndarray,
             box) -> np.ndarray:
    """θ ± ρ w_j e_j per movable coordinate j: (m, 2k, d) points, clipped to the box."""
    low, high, clip = box
    m, d = centre.shape
    k = len(axes)
    step = np.zeros((m, 2 * k, d))
    for i, j in enumerate(axes):
        step[:, 2 * i, j] = rho * width[j]
        step[:, 2 * i + 1, j] = -rho * width[j]
    pts = centre[:, None] + step
    return np.where(clip, np.clip(pts, low, high), pts)


def _jacobian(pts: np.ndarray, sr: np.ndarray, axes: np.ndarray, width: np.ndarray):
    """(m, M, k) central differences of the residuals, in box units (the offsets taken)."""
    dz = (pts[:, 0::2, axes] - pts[:, 1::2, axes]).diagonal(axis1=1, axis2=2)  # (m, k)
    dz = dz / width[axes]
    jac = (sr[:, 0::2] - sr[:, 1::2]).transpose(0, 2, 1)  # (m, M, k)
    return jac / np.where(dz > 0, dz, 1.0)[:, None, :]


def _gauss_newton(jac: np.ndarray, r: np.ndarray, rho: np.ndarray):
    """The damped Gauss–Newton step (m, k) cut to the trust radius, and its uncut size (m,)."""
    k = jac.shape[2]
    g = np.einsum("mrk,mr->mk", jac, r)
    h = np.einsum("mrk,mrl->mkl", jac, jac)
    damping = 1e-9 * (np.trace(h, axis1=1, axis2=2) / k + 1e-300)
    finite = np.isfinite(h).all(axis=(1, 2)) & np.isfinite(g).all(axis=1)
    h = np.where(finite[:, None, None], h, np.eye(k))
    g = np.where(finite[:, None], g, 0.0)
    delta = -np.linalg.solve(h + damping[:, None, None] * np.eye(k), g[..., None])[..., 0]
    size = np.linalg.norm(delta, axis=1)
    delta *= np.minimum(1.0, rho / np.maximum(size, 1e-300))[:, None]
    return delta, size


def _new_radius(rho: np.ndarray, ratio: np.ndarray, full: np.ndarray) -> np.ndarray:
    """Trust radius after a step: doubled (a full step that did well), quartered, or kept.

    N.B. at most a whole box width: a step past that leaves every box anyway.
    """
    return np.where(ratio > 0.75, np.where(full, np.minimum(2 * rho, 1.0), rho),
                    np.where(ratio < 0.25, rho / 4, rho))


def land(task, theta: np.ndarray, *, iterations: int = 20, depth: float = 0.25,
         radius: float = 0.01, min_radius: float = 1e-5,
         replay: Replay | None = None, until: str = "landed") -> Landing:
    """Lands particles θ (n, d) on the task's residual goals by Gauss–Newton in MuJoCo C.

    Args:
      task: a `Task` or `Problem` with residual costs (`Problem.residual_terms`).
      theta: (n, d) particles (discrete logits are not moved).
      iterations: most iterations per particle (0 only evaluates θ).
      depth: landed within this share of each goal's tolerance.
      radius: initial trust radius ρ, in box widths.
      min_radius: a particle whose ρ falls below this stops.
      replay: θ's C replay where the caller has it.
      until: "landed" (a particle stops once landed) or "success" (once it
        has any success in C: a task plan verified, not yet deep in its goal).

    Returns:
      A `Landing`.
    """
    started = time.perf_counter()
    if until not in ("landed", "success"):
        raise ValueError(f"land(until={until!r}); valid: landed, success")
    problem = as_problem(task)
    tolerances = problem.residual_tolerances()
    theta = np.array(theta, np.float64, copy=True)
    n, d = theta.shape
    low, high, movable, clip = _box(problem)
    width = np.where(movable, high - low, 0.0)
    axes = np.flatnonzero(movable)
    p, r, ok, landed, plan = _evaluate(problem, theta, tolerances, depth, replay)
    best = _Best(theta, p, ok, landed, plan)
    rollouts = 0 if replay is not None else n
    centre, rho = theta.copy(), np.full(n, float(radius))
    enough = best.landed if until == "landed" else best.ok
    done = enough | ~np.isfinite(p)
    its = np.zeros(n, int)
    for _ in range(iterations):
        rows = np.flatnonzero(~done)
        if not len(rows) or not len(axes):
            break
        its[rows] += 1
        k, m = len(axes), len(rows)
        pts = _stencil(centre[rows], rho[rows], axes, width, (low, high, clip))
        flat = pts.reshape(-1, d)
        sp, sr, sok, sland, splan = _evaluate(problem, flat, tolerances, depth)
        rollouts += len(flat)
        sp, sok, sland, splan = (a.reshape(m, 2 * k) for a in (sp, sok, sland, splan))
        sr = sr.reshape(m, 2 * k, -1)
        best.keep(rows, pts, sp, sok, sland, splan)
        jac = _jacobian(pts, sr, axes, width)
        delta, size = _gauss_newton(jac, r[rows], rho[rows])
        trial = centre[rows].copy()
        trial[:, axes] += delta * width[axes]
        trial = np.where(clip, np.clip(trial, low, high), trial)
        tp, tr, tok, tland, tplan = _evaluate(problem, trial, tolerances, depth)
        rollouts += m
        best.keep(rows, trial[:, None], tp[:, None], tok[:, None], tland[:, None],
                  tplan[:, None])
        model = r[rows] + np.einsum("mrk,mk->mr", jac, (trial - centre[rows])[:, axes]
                                    / width[axes])
        predicted = p[rows] - np.sum(model**2, axis=1)
        actual = p[rows] - tp
        ratio = np.where(predicted > 0, actual / np.where(predicted > 0, predicted, 1.0), -1.0)
        rho[rows] = _new_radius(rho[rows], ratio, size >= 0.9 * rho[rows])
        # The centre moves to the best of itself, its stencil and the trial.
        pool_p = np.concatenate([p[rows, None], sp, tp[:, None]], axis=1)
        pool_p = np.where(np.isfinite(pool_p), pool_p, np.inf)
        j = np.argmin(pool_p, axis=1)
        pool = np.concatenate([centre[rows, None], pts, trial[:, None]], axis=1)
        pool_r = np.concatenate([r[rows, None], sr, tr[:, None]], axis=1)
        take = np.arange(m)
        centre[rows], p[rows], r[rows] = pool[take, j], pool_p[take, j], pool_r[take, j]
        done[rows] = enough[rows] | (rho[rows] < min_radius)
    out = np.where(best.ok[:, None], best.theta, centre)
    return Landing(out, best.ok, best.landed, np.where(best.ok, best.p, p), its, rollouts,
                   time.perf_counter() - started, best.plan)
