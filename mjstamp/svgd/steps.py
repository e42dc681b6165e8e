"""SVGD, discrete SVGD and SGD steps: state plus pure functions, optax for updates.

Every step has the signature `step(state, key) -> (state, info)` and is jit-able;
the optimizer is any optax `GradientTransformation`, so Adam, clipping and
schedules come free. SVGD *ascends* log ρ, optax *minimises*: the steps feed
−φ to the optimizer as the "gradient" (blackjax does the same), so with
`optax.sgd(ε)` one step is exactly θ_i ← θ_i + ε φ_i.

How a task plugs in
-------------------
The log density is *batched*, and has one signature, in the way
`jax.value_and_grad(..., has_aux=True)` reads it:
`logdensity_fn(particles (n, d)) -> (logp (n,), aux (n, f))`, with the rollouts
vmapped inside, and *particle-separable* (row i depends on particle i only);
aux are the kernel features of the same rollout, or an (n, 0) array where the
kernel needs none. Per step the engine calls it once on the whole batch and
takes the n scores ∇ log ρ(θ_i) from one reverse pass; the kernel then costs one
n×n matrix and its gradient. So a step is n rollouts, never n².

A task whose kernel needs features of the same rollout (billiards: the soft
wall-hit indicators w(θ) of App. B-B) returns them as aux and uses
`feature_kernel()` (no feature_fn). The step then gets log ρ, the features and
all per-particle Jacobians ∂[log ρ, φ]/∂θ from one batched forward pass plus
either 1+f batched pullbacks or d batched pushforwards (`jacobian=`), still n
rollouts per step.

Each step is `update(state, evaluate(state.particles), key)`, and carries both
halves as `step.evaluate` (the batched log density and its derivatives: the
rollouts, which dominate compile time) and `step.update` (kernel, direction,
optimizer: cheap). A loop may compile them apart, so that two steps built on
the same `evaluate` (`build_sgd_step(evaluate=...)`) share one compiled
rollout.

References:
  STAMP eq. (1) (SVGD), eq. (4) (discrete SVGD with importance weights),
  Algorithm 1 (lines 6 and 10).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from mjstamp.svgd._checks import check_particles
from mjstamp.svgd._jacobian import JacobianMode, check_mode, value_and_batched_jacobian
from mjstamp.svgd.kernels import Kernel, flat_bandwidths, rbf

__all__ = [
    "SVGDState",
    "StepInfo",
    "init",
    "build_svgd_step",
    "build_dsvgd_step",
    "build_sgd_step",
    "Evaluation",
    "build_evaluate",
    "stein_direction",
    "importance_log_weights",
    "NEAR_ZERO_RTOL",
    "NEAR_ZERO_ATOL",
    "near_zero_threshold",
    "near_zero_share",
]

# (n, d) -> (logp (n,), aux (n, f)), aux an (n, 0) array where there is none
LogDensityFn = Callable[[jax.Array], tuple[jax.Array, jax.Array]]

# "Near zero" for a score: relative to the typical score of the particles that do feel a
# gradient, so that it is free of the scale of θ and of log ρ; the absolute floor only
# decides when no particle feels one (it is ~0 in any units a task would use).
NEAR_ZERO_RTOL = 1e-3
NEAR_ZERO_ATOL = 1e-12


class SVGDState(NamedTuple):
    """State of the SVGD, discrete SVGD and SGD steps.

    Attributes:
      particles: (n, d) array θ_{1:n}.
      opt_state: the optax optimizer state.
    """

    particles: jax.Array
    opt_state: optax.OptState


class StepInfo(NamedTuple):
    """Diagnostics of one step, all evaluated at the particles *before* it.

    Attributes:
      logdensity: (n,) log ρ(θ_i).
      logdensity_mean: () mean of log ρ over particles where it is finite.
      logdensity_max: () max of log ρ over particles where it is finite.
      bandwidth: (g,) kernel bandwidths used (empty for SGD).
      weights: (n,) normalised weights a_j of the Stein sum (1/n for SVGD,
        w_j / Σw for discrete SVGD, 1/n for SGD).
      learning_rate: () ε read from an `optax.inject_hyperparams` optimizer
        state, NaN when the optimizer does not expose it.
      displacement: () mean over particles of ‖θ_i(new) − θ_i‖.
      nonfinite_particles: () number of particles whose log ρ, score or features
        were NaN/inf: they are frozen this step (no update, optimizer state
        kept), get zero weight, and count for no other particle's kernel terms.
      score_norm: (n,) ‖∇log ρ(θ_i)‖ per particle, NaN where it is not finite.
      driving_norm_mean: () mean over particles of ‖D_i‖, the driving term
        D_i = Σ_j a_j k(θ_j, θ_i) ∇log ρ(θ_j) (a_j = 1/n for SVGD, the
        normalised importance weights for discrete SVGD); NaN for SGD.
      driving_norm_median: () median of ‖D_i‖; NaN for SGD.
      repulsion_norm_mean: () mean over particles of ‖R_i‖, the repulsive term
        R_i = Σ_j a_j ∇_{θ_j} k(θ_j, θ_i) (in θ-space for a feature kernel);
        NaN for SGD.
      repulsion_norm_median: () median of ‖R_i‖; NaN for SGD.
      direction_norm_mean: () mean ‖φ_i‖ of the direction handed to the
        optimizer (φ = D + R for SVGD, the score for SGD); the optimizer's gain
        is displacement / (learning_rate · direction_norm_mean).
      displacement_per_coordinate: (d,) mean over particles of |Δθ_ik|, the
        step actually taken along each coordinate k.
      self_weight_median: () median over particles of a_i k_ii / Σ_j a_j k_ji,
        the share of a particle's own score in its driving term (1/n when the
        kernel is flat over all particles, 1 when no other particle is within
        reach); NaN for SGD, which follows each particle's own score alone.
      guard_logdensity: (n,) the log density a step must not lower
        (`StampConfig.backtrack`): log p(Γ(θ_i)), the plan as decoded, in
        discrete SVGD; log ρ(θ_i) otherwise.
    """

    logdensity: jax.Array
    logdensity_mean: jax.Array
    logdensity_max: jax.Array
    bandwidth: jax.Array
    weights: jax.Array
    learning_rate: jax.Array
    displacement: jax.Array
    nonfinite_particles: jax.Array
    score_norm: jax.Array
    driving_norm_mean: jax.Array
    driving_norm_median: jax.Array
    repulsion_norm_mean: jax.Array
    repulsion_norm_median: jax.Array
    direction_norm_mean: jax.Array
    displacement_per_coordinate: jax.Array
    self_weight_median: jax.Array
    guard_logdensity: jax.Array


class Evaluation(NamedTuple):
    """The log density and its derivatives at a step's particles, from one batched call.

    Attributes:
      logp: (n,) log ρ(θ_i).
      score: (n, d) ∇ log ρ(θ_i).
      features: (n, f) the kernel features ψ(θ_i) of the same rollout, or None.
      features_jac: (n, f, d) their Jacobians ∂ψ/∂θ_i, or None.
      log_target: (n,) log p(Γ(θ_i)), the discrete target at the hard decode
        (no gradient taken), or None.
    """

    logp: jax.Array
    score: jax.Array
    features: jax.Array | None = None
    features_jac: jax.Array | None = None
    log_target: jax.Array | None = None


def init(particles: jax.Array, optimizer: optax.GradientTransformation) -> SVGDState:
    """Initial state for any of the steps.

    Args:
      particles: (n, d) floating array, n >= 1 (SVGD steps need n >= 2).
      optimizer: the optax transformation the step will use.

    Returns:
      SVGDState(particles, optimizer.init(particles)).
    """
    particles = jnp.asarray(particles)
    check_particles(particles, min_particles=1)
    return SVGDState(particles, optimizer.init(particles))


# ----------------------------------------------------------------------------
# Evaluating the batched log density


def _split_output(out: Any, n: int, name: str = "logdensity_fn") -> tuple[jax.Array, jax.Array]:
    """(logp (n,), aux (n, f)) from what a log density returned, its shapes checked."""
    if not isinstance(out, tuple) or len(out) != 2:
        got = f"a tuple of {len(out)}" if isinstance(out, tuple) else type(out).__name__
        raise ValueError(
            f"{name} must return (logp (n,), aux (n, f)), aux the kernel features of the "
            f"same rollout or an (n, 0) array; got {got}"
        )
    logp, aux = out
    if aux.ndim != 2 or aux.shape[0] != n:
        raise ValueError(f"{name} aux (features) must have shape (n, f) with n={n}; "
                         f"got {aux.shape}")
    if logp.shape != (n,):
        raise ValueError(
            f"{name} must return log-densities of shape (n,) = ({n},) for "
            f"particles of shape (n, d); got {logp.shape}"
        )
    return logp, aux


def _logp_and_score(logdensity_fn: LogDensityFn, x: jax.Array):
    """Log ρ (n,) and its n gradients (n, d) from one batched call and one pullback."""
    n = x.shape[0]
    logp, pullback = jax.vjp(lambda p: _split_output(logdensity_fn(p), n)[0], x)
    (score,) = pullback(jnp.ones_like(logp))
    return logp, score


def _logp_score_features(logdensity_fn: LogDensityFn, x: jax.Array, mode: JacobianMode):
    """Log ρ, scores, features and their Jacobians from one batched call."""
    n = x.shape[0]

    def stacked(p):
        logp, feats = _split_output(logdensity_fn(p), n)
        if feats.shape[1] == 0:
            raise ValueError(
                "the kernel reads features from the log density (feature_kernel "
                "without feature_fn): logdensity_fn must return "
                "(logp (n,), features (n, f)) with f >= 1"
            )
        return jnp.concatenate([logp[:, None], feats.astype(logp.dtype)], axis=1)

    out, jac = value_and_batched_jacobian(stacked, x, mode)
    return out[:, 0], jac[:, 0, :], (out[:, 1:], jac[:, 1:, :])


def _logp_and_score_fwd(logdensity_fn: LogDensityFn, x: jax.Array):
    """Log ρ (n,) and its n gradients (n, d) from one pass carrying d tangents."""
    n = x.shape[0]
    out, jac = value_and_batched_jacobian(
        lambda p: _split_output(logdensity_fn(p), n)[0][:, None], x, "fwd"
    )
    return out[:, 0], jac[:, 0, :]


def sgd_mode(jacobian: JacobianMode, dim: int) -> str:
    """How the SGD step differentiates: 'fwd' or 'rev' ('auto': 'fwd' when d <= 2)."""
    check_mode(jacobian)
    return jacobian if jacobian != "auto" else ("fwd" if dim <= 2 else "rev")


def build_evaluate(
    logdensity_fn: LogDensityFn,
    *,
    features: bool = False,
    jacobian: JacobianMode = "auto",
    log_target_fn: Callable[[jax.Array], jax.Array] | None = None,
) -> Callable[[jax.Array], Evaluation]:
    """Builds `evaluate(particles (n, d)) -> Evaluation`: what a step reads of log ρ.

    Args:
      logdensity_fn: batched log ρ, (n, d) -> (logp (n,), aux (n, f)).
      features: also return the features of the same rollout and their
        Jacobians (for a kernel that reads them), differentiated as
        `jacobian` says ('auto': whichever of 1+f and d is smaller); without
        features, 'rev' takes the scores from one pullback, 'fwd' from d
        tangents, 'auto' the latter when d <= 2.
      jacobian: 'auto', 'fwd' or 'rev'.
      log_target_fn: batched (n, d) -> (log p(Γ(θ)) (n,), aux) for discrete SVGD.

    Returns:
      A jit-able function of the particles.
    """
    check_mode(jacobian)

    def evaluate(x: jax.Array) -> Evaluation:
        n = x.shape[0]
        feats = feats_jac = log_target = None
        if features:
            logp, score, (feats, feats_jac) = _logp_score_features(logdensity_fn, x, jacobian)
        elif sgd_mode(jacobian, x.shape[1]) == "fwd":
            logp, score = _logp_and_score_fwd(logdensity_fn, x)
        else:
            logp, score = _logp_and_score(logdensity_fn, x)
        if log_target_fn is not None:
            log_target = jax.lax.stop_gradient(
                _split_output(log_target_fn(x), n, "log_target_fn")[0])
        return Evaluation(logp, score, feats, feats_jac, log_target)

    return evaluate


def _finite_rows(*arrays: jax.Array) -> jax.Array:
    ok = None
    for a in arrays:
        a_ok = jnp.all(jnp.isfinite(a.reshape(a.shape[0], -1)), axis=1)
        ok = a_ok if ok is None else ok & a_ok
    return ok


def _zero_rows(a: jax.Array, ok: jax.Array) -> jax.Array:
    return jnp.where(ok.reshape((-1,) + (1,) * (a.ndim - 1)), a, 0.0)


def importance_log_weights(
    log_surrogate: jax.Array, log_target: jax.Array
) -> jax.Array:
    """Normalised log weights log(w_j / Σ w) with w_j = ρ(x_j) / p(Γ(x_j)).

    Computed in log space (a log-softmax), so weights of 1e±300 neither overflow
    nor underflow. Entries where either input is not finite get weight 0; if no
    entry is finite, all weights are 0 (log weight −inf).

    Args:
      log_surrogate: (n,) log ρ(x_j) = log p̃(Γ̃(x_j)) + const.
      log_target: (n,) log p(Γ(x_j)) + const.

    Returns:
      (n,) log weights; exp of them sums to 1 (or 0 when nothing is finite).

    References:
      STAMP eq. (4).
    """
    log_w = log_surrogate - log_target
    ok = jnp.isfinite(log_w)
    log_w = jnp.where(ok, log_w, -jnp.inf)
    safe = jnp.where(jnp.any(ok), log_w, 0.0)
    return jnp.where(ok, jax.nn.log_softmax(safe), -jnp.inf)


def near_zero_threshold(score_norm: jax.Array, *, xp: Any = jnp) -> jax.Array:
    """The score norm below which a particle counts as feeling no gradient.

    τ = max(NEAR_ZERO_RTOL · m, NEAR_ZERO_ATOL), with m the median of the finite
    score norms above NEAR_ZERO_ATOL: 1e-3 of the typical particle that feels a
    gradient. The median leaves out the particles with a zero score so that a
    landscape where most particles sit on a plateau still gets a reference
    from those that do not; τ = NEAR_ZERO_ATOL when none does. `run_stamp` takes
    τ from the first iteration of each phase and keeps it for the phase.

    Args:
      score_norm: (n,) ‖∇log ρ(θ_i)‖, NaN where not finite (`StepInfo.score_norm`).
      xp: `jax.numpy` (jit-able) or `numpy` (on the host, no device dispatch).

    Returns:
      () threshold τ.
    """
    s = xp.asarray(score_norm)
    felt = xp.isfinite(s) & (s > NEAR_ZERO_ATOL)
    if xp is jnp:
        median = jnp.nanmedian(jnp.where(felt, s, jnp.nan))
    else:  # numpy warns on an all-NaN nanmedian
        median = xp.median(s[felt]) if felt.any() else xp.nan
    return xp.where(
        xp.isnan(median), NEAR_ZERO_ATOL, xp.maximum(NEAR_ZERO_RTOL * median, NEAR_ZERO_ATOL)
    )


def near_zero_share(score_norm: jax.Array, threshold: Any, *, xp: Any = jnp) -> jax.Array:
    """Share of the n particles whose score norm is at most `threshold`.

    Particles with a non-finite score are not counted as near zero (they are
    `nonfinite_particles`).

    Args:
      score_norm: (n,) ‖∇log ρ(θ_i)‖, NaN where not finite.
      threshold: () τ, e.g. from `near_zero_threshold`.
      xp: `jax.numpy` or `numpy`.

    Returns:
      () share in [0, 1].
    """
    return xp.mean(xp.asarray(score_norm) <= threshold)


def stein_direction(
    logdensity_fn: LogDensityFn,
    kernel: Kernel,
    particles: jax.Array,
    *,
    log_target_fn: Callable[[jax.Array], jax.Array] | None = None,
    jacobian: JacobianMode = "auto",
) -> tuple[jax.Array, StepInfo]:
    """The Stein direction φ_i = Σ_j a_j [k_ji ∇log ρ(θ_j) + ∇_{θ_j} k_ji].

    Here k_ji = k(θ_j, θ_i), and a_j = 1/n (SVGD, eq. (1)), or, when
    log_target_fn is given, a_j = w_j / Σw with w_j = ρ(θ_j) / p(Γ(θ_j))
    (discrete SVGD, eq. (4)). Particles whose log ρ, score or features are not
    finite get zero score and zero weight.

    Args:
      logdensity_fn: batched (n, d) -> (log ρ (n,), aux (n, f)), aux the features
        when the kernel reads features from it.
      kernel: a `Kernel`.
      particles: (n, d), n >= 2.
      log_target_fn: batched (n, d) -> (log p(Γ(θ)) (n,), aux), the discrete
        target at the hard decode; no gradient is taken through it.
      jacobian: 'auto', 'fwd' or 'rev': how to differentiate log ρ and the
        features when the kernel reads features from the log density.

    Returns:
      (phi (n, d), info) with info.learning_rate, info.displacement and
      info.displacement_per_coordinate NaN (the optimizer sets them).

    References:
      STAMP eq. (1), eq. (4), Algorithm 1 line 6.
    """
    check_particles(particles)
    evaluate = _stein_evaluate(logdensity_fn, kernel, jacobian, log_target_fn)
    return _direction(evaluate(particles), kernel, particles,
                      weighted=log_target_fn is not None)


def _stein_evaluate(logdensity_fn, kernel: Kernel, jacobian, log_target_fn):
    """The evaluation a Stein step reads: with the features a kernel reads, else one pullback."""
    features = kernel.uses_density_features
    return build_evaluate(logdensity_fn, features=features,
                          jacobian=jacobian if features else "rev", log_target_fn=log_target_fn)


def _direction(ev: Evaluation, kernel: Kernel, x: jax.Array, *, weighted: bool):
    """(φ (n, d), info) of `stein_direction` from an evaluation at the particles x."""
    if kernel.uses_density_features:
        if ev.features is None:
            raise ValueError("the kernel reads features from the log density: the "
                             "evaluation must carry them (build_evaluate(features=True))")
        ok = _finite_rows(ev.logp, ev.score, ev.features, ev.features_jac)
        features = (_zero_rows(ev.features, ok), _zero_rows(ev.features_jac, ok))
    else:
        ok = _finite_rows(ev.logp, ev.score)
        features = None
    logp = ev.logp
    score = _zero_rows(ev.score, ok)
    log_target = None
    if not weighted:
        a = ok / jnp.maximum(jnp.sum(ok), 1)
    else:
        log_target = ev.log_target
        log_w = importance_log_weights(jnp.where(ok, logp, jnp.nan), log_target)
        a = jnp.exp(jax.lax.stop_gradient(log_w))
    a = a.astype(x.dtype)
    # N.B. a particle that is not finite counts for no other one: weight 0, and
    # left out of the median heuristic (`valid`); its θ is zeroed so a NaN in it
    # cannot reach the n×n products (0 · NaN is NaN).
    terms = kernel.evaluate(_zero_rows(x, ok), a, features=features, valid=ok)
    # φ_i = Σ_j a_j k_ji s_j + Σ_j a_j ∇_{x_j} k_ji: one n×n product per term. The two
    # terms are kept apart only for their norms (O(n d) on top of the O(n² d) kernel).
    kw = a[:, None] * terms.gram  # kw[j, i] = a_j k_ji
    driving = kw.T @ score
    phi = driving + terms.repulsion
    # Share of particle i's own score in its driving term's kernel weights.
    total = jnp.sum(kw, axis=0)
    own = jnp.where(total > 0, jnp.diagonal(kw) / jnp.where(total > 0, total, 1.0), jnp.nan)
    info = _info(
        logp, ok, score, flat_bandwidths(terms.params), a, phi,
        driving=driving, repulsion=terms.repulsion, self_weight=own, guard=log_target,
    )  # fmt: skip
    return phi, info


def _info(
    logp, ok, score, bandwidth, weights, direction, *, driving=None, repulsion=None,
    self_weight=None, guard=None,
):
    """StepInfo of a step at the particles it starts from (optimizer fields NaN)."""
    count = jnp.sum(ok)
    mean = jnp.sum(jnp.where(ok, logp, 0.0)) / jnp.maximum(count, 1)
    nan = jnp.asarray(jnp.nan, logp.dtype)

    def norms(v):  # (mean, median) over particles of ‖v_i‖; NaN for a term SGD lacks
        if v is None:
            return nan, nan
        r = jnp.linalg.norm(v, axis=1)
        return jnp.mean(r), jnp.median(r)

    d_mean, d_median = norms(driving)
    r_mean, r_median = norms(repulsion)
    return StepInfo(
        logdensity=logp,
        logdensity_mean=jnp.where(count > 0, mean, jnp.nan),
        logdensity_max=jnp.max(jnp.where(ok, logp, -jnp.inf)),
        bandwidth=bandwidth,
        weights=weights,
        learning_rate=nan,
        displacement=nan,
        nonfinite_particles=logp.shape[0] - count,
        score_norm=jnp.where(ok, jnp.linalg.norm(score, axis=1), jnp.nan),
        driving_norm_mean=d_mean,
        driving_norm_median=d_median,
        repulsion_norm_mean=r_mean,
        repulsion_norm_median=r_median,
        direction_norm_mean=jnp.mean(jnp.linalg.norm(direction, axis=1)),
        displacement_per_coordinate=jnp.full(direction.shape[1:], jnp.nan, logp.dtype),
        self_weight_median=nan if self_weight is None else jnp.nanmedian(self_weight),
        guard_logdensity=jnp.where(ok, logp if guard is None else guard, jnp.nan),
    )


def _learning_rate(opt_state: Any) -> jax.Array:
    try:
        # N.B. with a schedule, inject_hyperparams also keeps a schedule *state*
        # under "learning_rate"; only the array is the rate.
        lr = optax.tree_utils.tree_get(
            opt_state,
            "learning_rate",
            default=None,
            filtering=lambda _, value: hasattr(value, "dtype"),
        )
    except KeyError:  # several learning rates in one chain: no single ε
        lr = None
    return jnp.asarray(jnp.nan if lr is None else lr, jnp.float32)


def _apply(optimizer, state: SVGDState, direction: jax.Array, info: StepInfo, ok: jax.Array):
    """Ascends along `direction` with optax (which minimises −direction).

    Particles not `ok` ((n,) bool: a non-finite log density, score or
    features) are frozen for the step: a zero direction into the optimizer, no
    update, and their (n, d) rows of the optimizer state (Adam's moments) kept
    as they were; state shared by all particles (Adam's step count) advances.
    """
    # N.B. a frozen particle's direction is zeroed before the optimizer too: one that
    # reads all rows at once (a global-norm clip, a trust ratio) must not see it.
    updates, opt_state = optimizer.update(-_zero_rows(direction, ok), state.opt_state,
                                          state.particles)
    updates = _zero_rows(updates, ok)
    shape = state.particles.shape

    def keep_frozen(new, old):  # per-particle state rows (n, d) of frozen particles
        if getattr(new, "shape", None) == shape and getattr(old, "shape", None) == shape:
            return jnp.where(ok[:, None], new, old)
        return new

    opt_state = jax.tree.map(keep_frozen, opt_state, state.opt_state)
    particles = optax.apply_updates(state.particles, updates)
    info = info._replace(
        learning_rate=_learning_rate(opt_state),
        displacement=jnp.mean(jnp.linalg.norm(updates, axis=1)),
        displacement_per_coordinate=jnp.mean(jnp.abs(updates), axis=0),
    )
    return SVGDState(particles, opt_state), info


def build_svgd_step(
    logdensity_fn: LogDensityFn,
    kernel: Kernel | None,
    optimizer: optax.GradientTransformation,
    *,
    jacobian: JacobianMode = "auto",
) -> Callable[[SVGDState, jax.Array], tuple[SVGDState, StepInfo]]:
    """Builds the SVGD step θ_i ← θ_i + ε φ_i (through `optimizer`).

    Args:
      logdensity_fn: batched log ρ, (n, d) -> (logp (n,), aux (n, f)), aux
        the features for a `feature_kernel()` that reads them from it.
      kernel: a `Kernel`; None for `rbf()` with the median heuristic.
      optimizer: optax transformation; `optax.sgd(ε)` gives eq. (1) exactly.
      jacobian: 'auto', 'fwd' or 'rev' (see `stein_direction`).

    Returns:
      A jit-able `step(state, key) -> (state, StepInfo)`; key is unused (the
      update is deterministic) and kept for a uniform step signature.

    References:
      STAMP eq. (1); Algorithm 1 lines 5-6 with w_j = 1.
    """
    return _build_stein_step(logdensity_fn, kernel, optimizer, jacobian)


def build_dsvgd_step(
    logdensity_fn: LogDensityFn,
    log_target_fn: Callable[[jax.Array], jax.Array],
    kernel: Kernel | None,
    optimizer: optax.GradientTransformation,
    *,
    jacobian: JacobianMode = "auto",
) -> Callable[[SVGDState, jax.Array], tuple[SVGDState, StepInfo]]:
    """Builds the weighted discrete-SVGD step of eq. (4).

    φ_i = (1/w) Σ_j w_j [∇log ρ(θ_j) k_ji + ∇_{θ_j} k_ji], w_j = ρ(θ_j) / p(Γ(θ_j)),
    where ρ ∝ p₀ p̃(Γ̃(θ)) is the smooth surrogate (logdensity_fn) and p(Γ(θ)) the
    target at the hard decode (log_target_fn). With the uniform base p₀ the
    ratio is p̃(Γ̃(θ_j)) / p(Γ(θ_j)) up to a constant, which the normalisation
    removes.

    Args:
      logdensity_fn: batched log ρ (see `build_svgd_step`).
      log_target_fn: batched (n, d) -> (log p(Γ(θ)) (n,), aux); no gradient is taken.
      kernel: a `Kernel`; None for `rbf()`.
      optimizer: optax transformation.
      jacobian: 'auto', 'fwd' or 'rev'.

    Returns:
      A jit-able `step(state, key) -> (state, StepInfo)`.

    References:
      STAMP eq. (3), (4); Algorithm 1 line 6.
    """
    return _build_stein_step(
        logdensity_fn, kernel, optimizer, jacobian, log_target_fn=log_target_fn, weighted=True
    )


def _build_stein_step(
    logdensity_fn, kernel, optimizer, jacobian, *, log_target_fn=None, weighted=False
):
    """The step of SVGD (uniform weights) and discrete SVGD (`weighted`): φ, then optax."""
    kernel = rbf() if kernel is None else kernel
    _check_builder(logdensity_fn, kernel, optimizer, jacobian)
    if weighted and not callable(log_target_fn):
        raise ValueError(f"log_target_fn must be callable; got {log_target_fn!r}")
    evaluate = _stein_evaluate(logdensity_fn, kernel, jacobian,
                               log_target_fn if weighted else None)

    def update(state: SVGDState, ev: Evaluation, key: jax.Array) -> tuple[SVGDState, StepInfo]:
        del key  # deterministic; kept for the uniform step(state, key) signature
        check_particles(state.particles)
        phi, info = _direction(ev, kernel, state.particles, weighted=weighted)
        return _apply(optimizer, state, phi, info, ~jnp.isnan(info.score_norm))  # NaN: not ok

    return _composed(evaluate, update, min_particles=2)


def _composed(evaluate, update, *, min_particles: int):
    """step(state, key) = update(state, evaluate(state.particles), key), both halves kept."""

    def step(state: SVGDState, key: jax.Array) -> tuple[SVGDState, StepInfo]:
        check_particles(state.particles, min_particles=min_particles)  # before tracing
        return update(state, evaluate(state.particles), key)

    step.evaluate = evaluate
    step.update = update
    return step


def build_sgd_step(
    logdensity_fn: LogDensityFn,
    optimizer: optax.GradientTransformation,
    *,
    jacobian: JacobianMode = "auto",
    evaluate: Callable[[jax.Array], Evaluation] | None = None,
) -> Callable[[SVGDState, jax.Array], tuple[SVGDState, StepInfo]]:
    """Builds the SGD refinement step θ_i ← θ_i + ε ∇log ρ(θ_i) (through `optimizer`).

    Particles no longer interact; features returned by logdensity_fn are
    ignored (and pruned from the computation).

    Args:
      logdensity_fn: batched log ρ, (n, d) -> (logp (n,), aux (n, f)).
      optimizer: optax transformation.
      jacobian: how the scores are computed: 'rev' (one pullback; any d),
        'fwd' (d batched tangents) or 'auto': 'fwd' when d <= 2, else 'rev'.
        N.B. a pullback through a rollout costs several forward passes, a
        tangent about one: billiards' d = 2 reverse-mode value and score of
        128 particles take 0.45 s against 0.37 s forward-mode, and compile in
        26 s against 13 s (2-core CPU).
      evaluate: an evaluation of this same log density to read log ρ and the
        scores from (another step's `step.evaluate`, so that both share one
        compiled rollout; its features are not used); default: one built
        here as `jacobian` says.

    Returns:
      A jit-able `step(state, key) -> (state, StepInfo)`.

    References:
      STAMP §IV-B; Algorithm 1 line 10.
    """
    _check_builder(logdensity_fn, None, optimizer, jacobian)
    if evaluate is None:
        evaluate = build_evaluate(logdensity_fn, jacobian=jacobian)
    elif not callable(evaluate):
        raise ValueError(f"evaluate must be callable; got {evaluate!r}")

    def update(state: SVGDState, ev: Evaluation, key: jax.Array) -> tuple[SVGDState, StepInfo]:
        del key
        check_particles(state.particles, min_particles=1)
        logp, score = ev.logp, ev.score
        ok = _finite_rows(logp, score)
        n = logp.shape[0]
        score = _zero_rows(score, ok)
        info = _info(
            logp, ok, score, jnp.zeros((0,), logp.dtype), jnp.full((n,), 1.0 / n), score
        )
        return _apply(optimizer, state, score, info, ok)

    return _composed(evaluate, update, min_particles=1)


def _check_builder(logdensity_fn, kernel, optimizer, jacobian) -> None:
    if not callable(logdensity_fn):
        raise ValueError(f"logdensity_fn must be callable; got {logdensity_fn!r}")
    if kernel is not None and not isinstance(kernel, Kernel):
        raise ValueError(
            f"kernel must be a mjstamp.svgd Kernel or None; got {kernel!r}"
        )
    if not isinstance(optimizer, optax.GradientTransformation):
        raise ValueError(
            f"optimizer must be an optax.GradientTransformation; got {optimizer!r}"
        )
    check_mode(jacobian)
