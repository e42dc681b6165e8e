"""The guards of the STAMP loop around a step: backtracking, stall rescue, non-finite re-draw.

Each guard is a `NamedTuple` state and pure functions in the optax style,
`*_init(n) -> state` and `*_update(..., state) -> (decision, state)`, on host
(numpy) arrays: the loop fetches a step's diagnostics once and every guard
reads them there (a jnp call per guard would be one more dispatch per
iteration). No function here writes into an array it is given; the loop
applies the decisions to the particles and the optimizer state once per
iteration (`edits.py`).

References:
  STAMP Algorithm 1 (the steps these guard); `StampConfig.backtrack`,
  `rescue_window` and `nonfinite_redraw` for what each guard is for.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

__all__ = [
    "BacktrackState",
    "Backtracked",
    "RescueState",
    "backtrack_apply",
    "backtrack_best",
    "backtrack_forget",
    "backtrack_init",
    "backtrack_update",
    "nonfinite_update",
    "rescue_init",
    "stall_update",
]

PHASE_SVGD = 0  # the phase codes of the loop and of `StampDiagnostics.phase`
PHASE_SGD = 1

MIN_SCALE = 2.0 ** -10
GROW = 1.25
_NONE = np.zeros(0, dtype=int)


# ----------------------------------------------------------------------------
# Backtracking (StampConfig.backtrack)


class BacktrackState(NamedTuple):
    """What backtracking remembers of each particle in a phase (host arrays).

    The log density guarded is the step's `guard_logdensity`: in discrete SVGD
    the target at the decoded plan, log p(Γ(θ)), so a step of the relaxed
    surrogate that makes the plan itself worse is taken back.

    Attributes:
      theta: (n, d) SVGD: each particle's last accepted point; SGD: the best
        point it visited; None before the phase's first iteration.
      logp: (n,) the log density at theta (NaN: none yet).
      peak: (n,) SVGD: the highest log density the particle has held in the phase.
      scale: (n,) the scale of the particle's next optimizer update, in
        [MIN_SCALE, 1].
    """

    theta: np.ndarray | None
    logp: np.ndarray
    peak: np.ndarray
    scale: np.ndarray


class Backtracked(NamedTuple):
    """What a backtracking update decided about the update just computed from θ_t.

    Attributes:
      back: indices of the particles taken back to their last accepted point
        (their update dropped, their optimizer's first moment zeroed).
      scaled: indices of the accepted particles whose update is scaled.
      used: (len(scaled),) the scales of those updates.
    """

    back: np.ndarray
    scaled: np.ndarray
    used: np.ndarray

    @property
    def edits(self) -> bool:
        """Whether the particles after the step change (else the step stands as it is)."""
        return bool(self.back.size or self.scaled.size)


def backtrack_init(n: int) -> BacktrackState:
    """No accepted point, scales 1: the state at the start of a phase."""
    return BacktrackState(theta=None, logp=np.full(n, np.nan), peak=np.full(n, np.nan),
                          scale=np.ones(n))


def backtrack_update(
    theta_t: np.ndarray, logp: np.ndarray, phase: int, state: BacktrackState
) -> tuple[Backtracked, BacktrackState]:
    """(decision, state) once a step from θ_t has reported log ρ(θ_t).

    The step reports log ρ at the particles it started from, so a step's
    outcome is known one iteration later: log ρ(θ_t) is compared with the
    highest log ρ the particle has held in the phase (its peak; comparing with
    the last accepted point would let small falls add up without bound). In
    SVGD a fall counts beyond max(1, d/2) nats below the peak, the depth of a
    d-dimensional Gaussian's typical set below its mode, so the repulsion may
    still spread particles over a mode but not throw them out of it: the
    particle goes back to its last accepted point and its scale halves (down
    to MIN_SCALE); where it did not fall θ_t is accepted and its scale grows
    by GROW, up to 1. In SGD nothing is taken back; the best point each
    particle visits is kept (`backtrack_best`). Particles whose log density is
    not finite are left to the non-finite handling.

    Args:
      theta_t: (n, d) float64 particles the step started from.
      logp: (n,) float64 `guard_logdensity` of the step, at θ_t.
      phase: PHASE_SVGD or PHASE_SGD.
      state: `BacktrackState`.
    """
    theta = theta_t if state.theta is None else state.theta
    finite = np.isfinite(logp)
    if phase == PHASE_SGD:  # the best point each particle has visited; Adam runs free
        better = finite & ~(logp <= state.logp)  # NaN: none yet
        return Backtracked(_NONE, _NONE, np.zeros(0)), state._replace(
            theta=np.where(better[:, None], theta_t, theta),
            logp=np.where(better, logp, state.logp))
    margin = max(1.0, theta_t.shape[1] / 2)
    # N.B. a step into a region where log ρ is not finite is a fall too: the
    # particle goes back to its last accepted point instead of freezing there.
    # N.B. in SVGD peak >= logp wherever logp is finite: every accept raises
    # it, and both are reset and forgotten together (SGD leaves peak alone).
    fell = np.isfinite(state.logp) & (~finite | (logp < state.peak - margin))
    accept = finite & ~fell
    scaled = np.flatnonzero(accept & (state.scale < 1))
    decision = Backtracked(np.flatnonzero(fell), scaled, state.scale[scaled])
    scale = np.where(fell, np.maximum(state.scale / 2, MIN_SCALE),
                     np.where(accept, np.minimum(state.scale * GROW, 1.0), state.scale))
    return decision, BacktrackState(
        theta=np.where(accept[:, None], theta_t, theta),
        logp=np.where(accept, logp, state.logp),
        peak=np.where(accept, np.fmax(state.peak, logp), state.peak),
        scale=scale)


def backtrack_apply(after: np.ndarray, theta_t: np.ndarray, decision: Backtracked,
                    state: BacktrackState) -> np.ndarray:
    """The particles after the guard: `after` (the step's) with its decision applied (a copy).

    An accepted particle with a scale below 1 moves that share of its step from
    θ_t; one taken back returns to its last accepted point (`state`, updated).
    """
    host = np.array(after)
    if decision.scaled.size:
        start = theta_t[decision.scaled].astype(host.dtype)
        used = decision.used.astype(host.dtype)[:, None]
        host[decision.scaled] = start + used * (host[decision.scaled] - start)
    if decision.back.size:
        host[decision.back] = state.theta[decision.back]
    return host


def backtrack_forget(idx: np.ndarray, state: BacktrackState) -> BacktrackState:
    """Particles `idx` re-drawn: no accepted point, scale 1."""
    gone = np.isin(np.arange(state.scale.size), idx)
    return state._replace(logp=np.where(gone, np.nan, state.logp),
                          peak=np.where(gone, np.nan, state.peak),
                          scale=np.where(gone, 1.0, state.scale))


def backtrack_best(state: BacktrackState) -> tuple[np.ndarray, np.ndarray]:
    """(rows, their points): each particle that has a scored point and that point.

    In SGD the best point each particle visited; in SVGD its last accepted one.
    """
    rows = np.flatnonzero(np.isfinite(state.logp))
    if state.theta is None or rows.size == 0:
        return _NONE, np.zeros((0, 0))
    return rows, state.theta[rows]


# ----------------------------------------------------------------------------
# Re-draws: stalled particles (rescue_window), non-finite ones (nonfinite_redraw)


class RescueState(NamedTuple):
    """Per-particle counters of the re-draws, (n,) ints each (host arrays).

    Attributes:
      stalled: consecutive SVGD iterations the particle has stalled.
      rescued: times it was re-drawn for stalling.
      failing: consecutive iterations its log density, score or features were
        not finite.
      nonfinite_redrawn: times it was re-drawn for that.
      fresh: indices re-drawn by the last re-draw and not yet counted
        (N.B. as the loop has always done: the non-finite count of a particle
        re-drawn for being non-finite also starts from zero at the iteration
        after its re-draw).
    """

    stalled: np.ndarray
    rescued: np.ndarray
    failing: np.ndarray
    nonfinite_redrawn: np.ndarray
    fresh: np.ndarray = _NONE


def rescue_init(n: int) -> RescueState:
    """Every counter at zero."""
    zeros = np.zeros(n, dtype=int)
    return RescueState(zeros, zeros, zeros, zeros, _NONE)


def stall_update(logp: np.ndarray, score_norm: np.ndarray, threshold: float, window: int,
                 state: RescueState) -> tuple[np.ndarray, RescueState]:
    """(indices to re-draw, state): the particles stalled `window` iterations in a row.

    Stalled: the score norm is at most `threshold` (the particle feels no
    gradient; NaN counts as none) and log ρ is at most the population's median
    (it is not resting in a good mode), or log ρ is not finite.

    Args:
      logp: (n,) float64 log ρ of the iteration.
      score_norm: (n,) ‖∇log ρ(θ_i)‖, NaN where it is not finite.
      threshold: the phase's near-zero score norm (`near_zero_threshold`).
      window: R >= 1 of `StampConfig.rescue_window`.
      state: `RescueState`.
    """
    finite = np.isfinite(logp)
    median = float(np.median(logp[finite])) if finite.any() else math.inf
    flat = ~(score_norm > threshold)  # NaN counts as no gradient
    low = ~(logp > median)
    state = state._replace(stalled=np.where(flat & low, state.stalled + 1, 0))
    idx = np.flatnonzero(state.stalled >= window)
    if idx.size == 0:
        return idx, state
    return idx, _redrawn(idx, "rescued", state)


def nonfinite_update(score_norm: np.ndarray, window: int,
                     state: RescueState) -> tuple[np.ndarray, RescueState]:
    """(indices to re-draw, state): the particles non-finite `window` iterations in a row.

    Args:
      score_norm: (n,) ‖∇log ρ(θ_i)‖, NaN where log ρ, the score or the
        features are not finite.
      window: M >= 1 of `StampConfig.nonfinite_redraw`.
      state: `RescueState`; its `fresh` particles (re-drawn, not yet scored)
        count from zero.
    """
    failing = np.where(np.isnan(score_norm), state.failing + 1, 0)
    failing[state.fresh] = 0  # N.B. `failing` is this function's own new array
    state = state._replace(failing=failing, fresh=_NONE)
    idx = np.flatnonzero(state.failing >= window)
    if idx.size == 0:
        return idx, state
    return idx, _redrawn(idx, "nonfinite_redrawn", state)


def _redrawn(idx: np.ndarray, counter: str, state: RescueState) -> RescueState:
    """The counters once particles `idx` are re-drawn: streaks reset, `counter` + 1."""
    hit = np.isin(np.arange(state.stalled.size), idx)
    return state._replace(
        stalled=np.where(hit, 0, state.stalled), failing=np.where(hit, 0, state.failing),
        fresh=idx, **{counter: getattr(state, counter) + hit})
