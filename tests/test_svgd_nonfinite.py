"""Non-finite particles are contained: frozen, left out of the kernel, re-drawn after M."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from mjstamp.svgd import (
    StampConfig,
    build_dsvgd_step,
    build_sgd_step,
    build_svgd_step,
    feature_kernel,
    init,
    rbf,
    run_stamp,
    sum_kernels,
)

KEY = jax.random.key(0)
BAD = 1.5  # the log density is NaN where θ_0 > BAD: part of the box


def _no_aux(x):
    return jnp.zeros((x.shape[0], 0), x.dtype)


def _logp(x):
    value = -0.5 * jnp.sum((x - 0.3) ** 2, axis=1)
    return jnp.where(x[:, 0] > BAD, jnp.nan, value), _no_aux(x)


def _logp_features(x):
    traj = jnp.cumsum(jnp.tanh(x[:, None, :] * jnp.linspace(0.1, 1.0, 6)[None, :, None]), 1)
    feats = jax.nn.sigmoid(jnp.stack([traj[:, :, 0].max(1), -traj[:, :, 1].min(1)], 1))
    feats = jnp.where(x[:, :1] > BAD, jnp.inf, feats)  # the features go bad too
    return _logp(x)[0], feats


def _particles():
    good = jnp.clip(jax.random.normal(jax.random.key(3), (9, 2)), -1.2, 1.2)
    bad = jnp.array([[2.0, 0.1], [3.0, -1.0], [BAD + 0.01, 0.5]])
    x = jnp.concatenate([good[:4], bad[:1], good[4:], bad[1:]])
    return x, np.asarray(x[:, 0] <= BAD)


STEPS = {
    "svgd-rbf": lambda opt: build_svgd_step(_logp, rbf(), opt),
    "svgd-sum": lambda opt: build_svgd_step(
        _logp, sum_kernels([(1.0, rbf(), [0]), (0.5, rbf(), [1])]), opt
    ),
    "svgd-features": lambda opt: build_svgd_step(_logp_features, feature_kernel(), opt),
    "dsvgd": lambda opt: build_dsvgd_step(
        _logp, lambda x: (-0.25 * jnp.sum(x**2, axis=1), _no_aux(x)), rbf(), opt
    ),
    "sgd": lambda opt: build_sgd_step(_logp, opt),
}


@pytest.mark.parametrize("name", sorted(STEPS))
def test_a_nonfinite_particle_changes_no_other_particles_update(name):
    """Three particles in the NaN region change no other particle's step.

    Steps on all n move the others exactly as steps on the finite ones alone;
    the three stay put with their Adam moments.
    """
    x, ok = _particles()
    optimizer = optax.adam(0.05)
    step = jax.jit(STEPS[name](optimizer))
    full, alone = init(x, optimizer), init(x[ok], optimizer)
    for _ in range(3):  # Adam's moments are nonzero after the first step
        full, info = step(full, KEY)
        alone, _ = step(alone, KEY)
    assert int(info.nonfinite_particles) == int((~ok).sum()) == 3
    np.testing.assert_allclose(full.particles[ok], alone.particles, rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(full.particles[~ok], x[~ok])
    moments = [leaf for leaf in jax.tree.leaves(full.opt_state) if leaf.shape == x.shape]
    assert moments and all(np.all(np.asarray(m)[~ok] == 0) for m in moments)


def test_a_nan_theta_does_not_reach_the_kernel():
    """Even a particle whose θ itself is NaN leaves the others finite and unchanged."""
    x, ok = _particles()
    x = x.at[np.flatnonzero(~ok)[0]].set(jnp.nan)
    optimizer = optax.sgd(0.1)
    step = jax.jit(build_svgd_step(_logp, rbf(), optimizer))
    full, _ = step(init(x, optimizer), KEY)
    alone, _ = step(init(x[ok], optimizer), KEY)
    np.testing.assert_allclose(full.particles[ok], alone.particles, rtol=1e-12, atol=1e-14)


def test_particles_nonfinite_m_iterations_in_a_row_are_redrawn():
    """With nonfinite_redraw=M the loop re-draws them after M iterations, from `redraw`."""
    x, ok = _particles()
    calls = []

    def redraw(key, k):
        calls.append(k)
        return jax.random.uniform(key, (k, 2), minval=-1.0, maxval=1.0)

    config = StampConfig(svgd_max_iters=6, sgd_max_iters=4, min_iters=100, seed=1,
                         nonfinite_redraw=2)
    result = run_stamp(_logp, x, rbf(), config, redraw=redraw, progress=False)
    d = result.diagnostics
    assert d.nonfinite_particles.tolist()[:3] == [3, 3, 0]
    assert d.nonfinite_redrawn.tolist() == [0, 3, 0, 0, 0, 0, 0, 0, 0, 0]
    assert calls == [3]
    assert result.nonfinite_redrawn.tolist() == (~ok).astype(int).tolist()
    assert np.all(np.isfinite(_logp(result.particles)[0]))


def test_without_redraw_a_nonfinite_particle_stays_frozen():
    x, ok = _particles()
    config = StampConfig(svgd_max_iters=3, sgd_max_iters=2, min_iters=100)
    result = run_stamp(_logp, x, rbf(), config, progress=False)
    assert result.diagnostics.nonfinite_particles.tolist() == [3] * 5
    assert result.nonfinite_redrawn.sum() == 0
    np.testing.assert_array_equal(result.particles[~ok], x[~ok])


def test_nonfinite_redraw_is_validated():
    with pytest.raises(ValueError, match="nonfinite_redraw"):
        StampConfig(nonfinite_redraw=-1)


def test_a_particle_that_goes_bad_mid_run_keeps_its_moments():
    """Frozen when it enters the NaN region: θ and its (nonzero) Adam moments stay put."""
    target = jnp.array([3.0, 0.0])  # the mode lies inside the NaN region θ_0 > BAD

    def logp(x):
        value = -0.5 * jnp.sum((x - target) ** 2, axis=1)
        return jnp.where(x[:, 0] > BAD, jnp.nan, value), _no_aux(x)

    optimizer = optax.adam(0.2)
    step = jax.jit(build_svgd_step(logp, rbf(), optimizer))
    state = init(jnp.stack([jnp.linspace(-1.0, 1.4, 6), jnp.zeros(6)], axis=1), optimizer)
    frozen_seen = 0
    for _ in range(40):
        before = state
        state, info = step(state, KEY)
        bad = np.isnan(np.asarray(info.score_norm))
        if not bad.any():
            continue
        frozen_seen += 1
        np.testing.assert_array_equal(state.particles[bad], before.particles[bad])
        for new, old in zip(jax.tree.leaves(state.opt_state), jax.tree.leaves(before.opt_state),
                            strict=True):
            if new.shape == before.particles.shape:
                np.testing.assert_array_equal(np.asarray(new)[bad], np.asarray(old)[bad])
                assert np.all(np.asarray(old)[bad][:, 0] != 0)  # built up before freezing
    assert frozen_seen > 0


@pytest.mark.parametrize("valid", [[False] * 5, [True] + [False] * 4])
def test_median_bandwidth_of_fewer_than_two_valid_particles_is_one(valid):
    x = jax.random.normal(KEY, (5, 2))
    terms = rbf().evaluate(x, jnp.full(5, 0.2), valid=jnp.array(valid))
    np.testing.assert_array_equal(terms.params, [1.0])
