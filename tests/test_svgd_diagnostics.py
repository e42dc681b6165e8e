"""Per-iteration diagnostics of the Stein steps: driving and repulsive terms, step, plateaus."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from mjstamp.svgd import (
    NEAR_ZERO_ATOL,
    NEAR_ZERO_RTOL,
    PHASE_SGD,
    PHASE_SVGD,
    StampConfig,
    build_dsvgd_step,
    build_svgd_step,
    init,
    near_zero_share,
    near_zero_threshold,
    rbf,
    run_stamp,
)

MU = np.array([0.5, -1.0])
PRECISION = np.array([[2.0, 0.6], [0.6, 1.0]])  # Σ⁻¹ of a correlated 2-D Gaussian
BANDWIDTH = 1.3
STEP = 0.1
X0 = np.array([[0.0, 0.0], [1.0, -0.5], [-0.7, 0.4], [2.0, 1.5], [0.3, -2.2]])


def gaussian(x):
    """Batched log N(x; μ, Σ) + const, (n, 2) -> ((n,), (n, 0) aux)."""
    r = x - jnp.asarray(MU)
    return -0.5 * jnp.einsum("ni,ij,nj->n", r, jnp.asarray(PRECISION), r), jnp.zeros((len(x), 0))


def _hand_terms(x, a):
    """D_i = Σ_j a_j k_ji s_j and R_i = Σ_j a_j ∇_{x_j} k_ji in numpy, pair by pair."""
    n = len(x)
    score = -(x - MU) @ PRECISION.T
    driving, repulsion = np.zeros_like(x), np.zeros_like(x)
    for i in range(n):
        for j in range(n):
            k = np.exp(-np.sum((x[j] - x[i]) ** 2) / BANDWIDTH**2)
            driving[i] += a[j] * k * score[j]
            repulsion[i] += a[j] * (-2.0 * (x[j] - x[i]) / BANDWIDTH**2) * k
    return score, driving, repulsion


def _norm_stats(v):
    r = np.linalg.norm(v, axis=1)
    return r.mean(), np.median(r)


@pytest.mark.parametrize("weighted", [False, True])
def test_diagnostics_match_a_hand_computation_on_a_2d_gaussian(weighted):
    """Driving and repulsive norms, score norms and the step equal numpy's, pair by pair."""
    with jax.enable_x64(True):
        x = jnp.asarray(X0)
        kernel = rbf(bandwidth=BANDWIDTH)
        optimizer = optax.sgd(STEP)
        if weighted:  # discrete SVGD: a_j ∝ ρ(x_j) / p(Γ(x_j)), here a tilted target
            tilt = np.array([0.3, -0.2])
            def tilted(t):
                return gaussian(t)[0] + t @ tilt, jnp.zeros((len(t), 0))

            step = build_dsvgd_step(gaussian, tilted, kernel, optimizer)
            log_w = -X0 @ tilt
            a = np.exp(log_w - log_w.max())
            a /= a.sum()
        else:
            step = build_svgd_step(gaussian, kernel, optimizer)
            a = np.full(len(X0), 1 / len(X0))
        state, info = jax.jit(step)(init(x, optimizer), jax.random.key(0))

        score, driving, repulsion = _hand_terms(X0, a)
        phi = driving + repulsion
        np.testing.assert_allclose(info.weights, a, rtol=1e-12)
        np.testing.assert_allclose(info.score_norm, np.linalg.norm(score, axis=1), rtol=1e-12)
        np.testing.assert_allclose(
            [info.driving_norm_mean, info.driving_norm_median], _norm_stats(driving), rtol=1e-12
        )
        np.testing.assert_allclose(
            [info.repulsion_norm_mean, info.repulsion_norm_median],
            _norm_stats(repulsion),
            rtol=1e-12,
        )
        np.testing.assert_allclose(info.direction_norm_mean, _norm_stats(phi)[0], rtol=1e-12)
        gram = np.exp(-np.sum((X0[:, None] - X0[None]) ** 2, -1) / BANDWIDTH**2)
        np.testing.assert_allclose(info.self_weight_median, np.median(a / (a @ gram)), rtol=1e-12)
        np.testing.assert_allclose(info.bandwidth, [BANDWIDTH])
        # optax.sgd(ε): the step is ε φ, per coordinate and in norm.
        np.testing.assert_allclose(
            info.displacement_per_coordinate, np.mean(np.abs(STEP * phi), axis=0), rtol=1e-12
        )
        np.testing.assert_allclose(info.displacement, STEP * _norm_stats(phi)[0], rtol=1e-12)
        np.testing.assert_allclose(state.particles, X0 + STEP * phi, rtol=1e-12)


def test_run_stamp_records_the_terms_and_nan_where_sgd_has_none():
    """run_stamp's rows carry the step's diagnostics; SGD has no driving/repulsive term."""
    with jax.enable_x64(True):
        config = StampConfig(svgd_max_iters=3, sgd_max_iters=2, rtol=0.0, motion_tol=0.0)
        res = run_stamp(
            gaussian, jnp.asarray(X0), rbf(bandwidth=BANDWIDTH), config,
            svgd_optimizer=optax.sgd(STEP), sgd_optimizer=optax.sgd(STEP), progress=False,
        )  # fmt: skip
        d = res.diagnostics
        np.testing.assert_array_equal(d.phase, [PHASE_SVGD] * 3 + [PHASE_SGD] * 2)
        score, driving, repulsion = _hand_terms(X0, np.full(len(X0), 1 / len(X0)))
        np.testing.assert_allclose(
            [d.driving_norm_mean[0], d.driving_norm_median[0]], _norm_stats(driving), rtol=1e-12
        )
        np.testing.assert_allclose(
            [d.repulsion_norm_mean[0], d.repulsion_norm_median[0]],
            _norm_stats(repulsion),
            rtol=1e-12,
        )
        np.testing.assert_allclose(
            d.score_norm_median[0], np.median(np.linalg.norm(score, axis=1)), rtol=1e-12
        )
        assert d.displacement_per_coordinate.shape == (5, 2)
        assert np.all(d.displacement_per_coordinate > 0)
        for name in ("driving_norm_mean", "driving_norm_median", "repulsion_norm_mean",
                     "repulsion_norm_median", "self_weight_median"):
            column = getattr(d, name)
            assert np.all(np.isfinite(column[:3])) and np.all(np.isnan(column[3:])), name
        # In SGD the direction is the score: displacement = ε · mean ‖score‖.
        np.testing.assert_allclose(d.displacement[3:], STEP * d.direction_norm_mean[3:])
        # A Gaussian has no plateau: no particle's score is near zero.
        np.testing.assert_array_equal(d.near_zero_share, 0.0)


def plateau(x):
    """Flat (zero score) inside the unit disc, a bowl −(‖x‖² − 1)² outside."""
    return -jax.nn.relu(jnp.sum(x**2, axis=1) - 1.0) ** 2, jnp.zeros((len(x), 0))


def test_near_zero_share_counts_the_particles_on_a_plateau():
    """Particles inside the flat disc feel no gradient; the others set the reference."""
    x = np.array([[0.1, 0.2], [-0.5, 0.3], [0.0, -0.6], [1.5, 0.0], [0.0, 2.0], [-2.5, 1.0]])
    config = StampConfig(svgd_max_iters=1, sgd_max_iters=0)
    res = run_stamp(plateau, jnp.asarray(x), rbf(), config, progress=False)
    r2 = np.sum(x**2, axis=1)
    outside = 4.0 * np.maximum(r2 - 1.0, 0.0) * np.sqrt(r2)  # ‖∇‖ = 4 (r² − 1) r
    tau = NEAR_ZERO_RTOL * np.median(outside[3:])
    np.testing.assert_allclose(res.diagnostics.near_zero_threshold, [tau], rtol=1e-5)
    np.testing.assert_allclose(res.diagnostics.near_zero_share, [0.5])
    # The same rule in jnp (jit-able, for a step) and numpy (the loop's host side).
    for xp in (jnp, np):
        np.testing.assert_allclose(near_zero_threshold(outside, xp=xp), tau, rtol=1e-6)
        np.testing.assert_allclose(near_zero_share(outside, tau, xp=xp), 0.5)
    # Nobody feels a gradient: the absolute floor decides; NaN scores are not near zero.
    flat = np.array([0.0, 0.0, np.nan, 5e-13])
    for xp in (jnp, np):
        assert float(near_zero_threshold(flat, xp=xp)) == NEAR_ZERO_ATOL
        np.testing.assert_allclose(near_zero_share(flat, NEAR_ZERO_ATOL, xp=xp), 0.75)
    jitted = jax.jit(lambda s: near_zero_share(s, near_zero_threshold(s)))
    np.testing.assert_allclose(jitted(jnp.asarray(outside)), 0.5)
