"""What a STAMP run reports: its per-iteration records, its result and the convergence test.

`StampDiagnostics` holds one row per iteration; the loop builds each row from a
step's `StepInfo` (`_fetch`) and stacks them at the end (`_stack_records`).
`has_converged` reads the records of a phase and ends it.

References:
  STAMP Algorithm 1 line 7 (the convergence test).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import jax
import numpy as np

from mjstamp.svgd._host import fetch
from mjstamp.svgd.steps import StepInfo

__all__ = ["StampDiagnostics", "StampResult", "has_converged"]


class StampDiagnostics(NamedTuple):
    """Per-iteration diagnostics of a run, T = SVGD + SGD iterations (numpy).

    Attributes:
      logdensity_mean: (T,) mean log ρ over the particles with a finite value.
      logdensity_max: (T,) max log ρ.
      bandwidth: (T, g) kernel bandwidths (NaN in the SGD phase).
      phase: (T,) PHASE_SVGD (0) or PHASE_SGD (1).
      learning_rate: (T,) step size ε when the optimizer exposes it (the
        default ones do), NaN otherwise.
      displacement: (T,) mean ‖Δθ_i‖ of the iteration: the step actually taken.
      nonfinite_particles: (T,) particles with a NaN/inf log ρ, score or
        features: frozen that iteration and counted for no other particle.
      step_seconds: (T,) wall time of each iteration; the first of each phase
        includes compiling its step (or loading it from the caches).
      driving_norm_mean: (T,) mean over particles of ‖D_i‖, the driving term
        D_i = Σ_j a_j k(θ_j, θ_i) ∇log ρ(θ_j) of the Stein direction (a_j = 1/n,
        or the normalised importance weights of discrete SVGD); NaN in SGD.
      driving_norm_median: (T,) median of ‖D_i‖; NaN in SGD.
      repulsion_norm_mean: (T,) mean of ‖R_i‖, the repulsive term
        R_i = Σ_j a_j ∇_{θ_j} k(θ_j, θ_i); NaN in SGD.
      repulsion_norm_median: (T,) median of ‖R_i‖; NaN in SGD.
      score_norm_median: (T,) median of ‖∇log ρ(θ_i)‖ over finite particles
        (both phases: in SGD the score is the direction).
      direction_norm_mean: (T,) mean ‖φ_i‖ of the direction handed to the
        optimizer (D + R in SVGD, the score in SGD); displacement /
        (learning_rate · direction_norm_mean) is the optimizer's gain (1 for
        plain SGD; Adam's per-coordinate normalisation makes it large where
        gradients are small).
      displacement_per_coordinate: (T, d) mean over particles of |Δθ_ik|.
      near_zero_share: (T,) share of the particles whose score norm is at most
        near_zero_threshold, i.e. that feel almost no gradient.
      near_zero_threshold: (T,) τ = max(1e-3 · m, 1e-12), m the median of the
        nonzero score norms at the first iteration of the phase
        (`mjstamp.svgd.near_zero_threshold`); constant within a phase.
      self_weight_median: (T,) median over particles of a_i k_ii / Σ_j a_j k_ji,
        the share of a particle's own score in its driving term: near 1/n the
        kernel averages every particle's score, so a particle in a narrow valley
        follows the crowd rather than its valley; NaN in SGD.
      rescued: (T,) particles re-drawn after the iteration (`rescue_window`).
      nonfinite_redrawn: (T,) particles re-drawn after the iteration for
        being non-finite `nonfinite_redraw` iterations in a row.
      backtracked: (T,) particles whose previous step lowered their log
        density and was taken back at this iteration (`backtrack`; SVGD only).
      step_scale_median: (T,) median over particles of the step scale
        (`backtrack`; 1 when off).
    """

    logdensity_mean: np.ndarray
    logdensity_max: np.ndarray
    bandwidth: np.ndarray
    phase: np.ndarray
    learning_rate: np.ndarray
    displacement: np.ndarray
    nonfinite_particles: np.ndarray
    step_seconds: np.ndarray
    driving_norm_mean: np.ndarray
    driving_norm_median: np.ndarray
    repulsion_norm_mean: np.ndarray
    repulsion_norm_median: np.ndarray
    score_norm_median: np.ndarray
    direction_norm_mean: np.ndarray
    displacement_per_coordinate: np.ndarray
    near_zero_share: np.ndarray
    near_zero_threshold: np.ndarray
    self_weight_median: np.ndarray
    rescued: np.ndarray
    nonfinite_redrawn: np.ndarray
    backtracked: np.ndarray
    step_scale_median: np.ndarray


class StampResult(NamedTuple):
    """What `run_stamp` returns.

    Attributes:
      particles: (n, d) final particles (after SGD; with `backtrack`, the best
        point each particle visited in SGD).
      svgd_particles: (n, d) particles at the end of the SVGD phase (with
        `backtrack`, the last points it accepted).
      diagnostics: `StampDiagnostics`.
      svgd_iters: SVGD iterations run.
      sgd_iters: SGD iterations run.
      svgd_converged: True if the SVGD phase ended by the convergence test.
      sgd_converged: True if the SGD phase ended by the convergence test.
      rescued: (n,) times each particle was re-drawn (`rescue_window`).
      nonfinite_redrawn: (n,) times each particle was re-drawn for being
        non-finite (`nonfinite_redraw`).
    """

    particles: jax.Array
    svgd_particles: jax.Array
    diagnostics: StampDiagnostics
    svgd_iters: int
    sgd_iters: int
    svgd_converged: bool
    sgd_converged: bool
    rescued: np.ndarray
    nonfinite_redrawn: np.ndarray


def has_converged(
    logdensity_mean: Sequence[float],
    displacement: Sequence[float],
    *,
    window: int,
    rtol: float,
    motion_tol: float,
    min_iters: int = 0,
) -> bool:
    """The convergence test of a phase (Algorithm 1 line 7, and the end of SGD).

    With t iterations done, L̄ the mean log posterior and m the mean particle
    displacement per iteration, the phase has converged when t >= min_iters,
    t > W and both

      |L̄_t − L̄_{t−W}| ≤ rtol · max(|L̄_{t−W}|, 1)  and  (1/W) Σ_{s>t−W} m_s ≤ motion_tol.

    The max(·, 1) compares a mean log posterior near 0 in absolute terms.
    Non-finite values never count as converged.

    Args:
      logdensity_mean: L̄ for the iterations of this phase so far.
      displacement: m for the same iterations.
      window: W >= 1.
      rtol: relative tolerance on the change of L̄.
      motion_tol: tolerance on the mean displacement, in units of θ.
      min_iters: iterations before the test may pass.

    Returns:
      Whether the phase has converged.
    """
    t = len(logdensity_mean)
    if t < max(min_iters, window + 1):
        return False
    now, then = float(logdensity_mean[-1]), float(logdensity_mean[-1 - window])
    motion = float(np.mean(np.asarray(displacement[-window:], dtype=float)))
    if not (math.isfinite(now) and math.isfinite(then) and math.isfinite(motion)):
        return False
    return abs(now - then) <= rtol * max(abs(then), 1.0) and motion <= motion_tol


_FROM_STEP = tuple(f for f in StampDiagnostics._fields if f in StepInfo._fields)


def _fetch(info: StepInfo, phase: int) -> tuple[StampDiagnostics, np.ndarray]:
    """The iteration's record and its (n,) score norms, on the host (waits for the step).

    The record's step_seconds and near-zero fields are left for the loop to fill.
    N.B. everything derived from the (n,) score norms is computed here in numpy: a
    jnp call outside the step would be one more dispatch per iteration.
    """
    # N.B. the fields a StepInfo carries are copied by name; the rest the loop fills.
    copied = {name: getattr(info, name) for name in _FROM_STEP}
    record, score_norm = fetch((
        StampDiagnostics(**{**dict.fromkeys(StampDiagnostics._fields), **copied})._replace(
            phase=phase, rescued=0, nonfinite_redrawn=0, backtracked=0,
            step_scale_median=1.0),
        info.score_norm,
    ))
    finite = score_norm[np.isfinite(score_norm)]
    median = float(np.median(finite)) if finite.size else math.nan
    return record._replace(score_norm_median=median), score_norm


# dtype of each StampDiagnostics column; bandwidth's width g may differ between phases
# (SGD has none): a row of another width is NaN.
_COLUMN_DTYPES = {"phase": np.int8, "nonfinite_particles": int, "rescued": int,
                  "nonfinite_redrawn": int, "backtracked": int}


def _stack_records(rows: Sequence[StampDiagnostics], dim: int) -> StampDiagnostics:
    """The run's `StampDiagnostics`: its per-iteration rows stacked leaf by leaf (T rows).

    Args:
      rows: one `StampDiagnostics` per iteration, each field that iteration's
        value (bandwidth (g,), displacement_per_coordinate (d,), the rest scalars).
      dim: d, the width of displacement_per_coordinate when there are no rows.
    """
    g = max((np.size(r.bandwidth) for r in rows), default=0)

    def bandwidth(b):
        b = np.asarray(b, dtype=float).ravel()
        return b if b.size == g else np.full(g, np.nan)

    if not rows:
        return StampDiagnostics(**{f: np.zeros(0, _COLUMN_DTYPES.get(f, float))
                                   for f in StampDiagnostics._fields})._replace(
            bandwidth=np.zeros((0, 0)), displacement_per_coordinate=np.zeros((0, dim)))
    rows = [r._replace(bandwidth=bandwidth(r.bandwidth)) for r in rows]
    stacked = jax.tree.map(lambda *column: np.array(column), *rows)
    return StampDiagnostics(**{f: np.asarray(v, dtype=_COLUMN_DTYPES.get(f, float))
                               for f, v in stacked._asdict().items()})._replace(
        bandwidth=np.asarray(stacked.bandwidth, dtype=float).reshape(len(rows), g))
