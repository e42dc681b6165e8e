"""Tests of the SVGD, discrete SVGD and SGD steps (mjstamp.svgd.steps)."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from blackjax.vi import svgd as blackjax_svgd

from mjstamp.svgd import (
    build_dsvgd_step,
    build_sgd_step,
    build_svgd_step,
    feature_kernel,
    importance_log_weights,
    init,
    rbf,
    stein_direction,
)

KEY = jax.random.key(0)


def with_no_aux(logp):
    """A batched (n, d) -> (n,) log density in the engine's signature, (logp, (n, 0) aux)."""
    return lambda x: (logp(x), jnp.zeros((x.shape[0], 0), x.dtype))


def _random_target(d, seed):
    """A random tilted Gaussian log density for one particle, (d,) -> ()."""
    k1, k2 = jax.random.split(jax.random.key(seed))
    a = jax.random.normal(k1, (d, d)) / jnp.sqrt(d) + jnp.eye(d)
    mu = jax.random.normal(k2, (d,))

    def logp(x):
        r = a @ (x - mu)
        return -0.5 * jnp.dot(r, r) + 0.1 * jnp.sum(jnp.log1p(x**2))

    return logp


@pytest.mark.parametrize("n, d, seed", [(20, 2, 0), (50, 7, 1), (64, 16, 2)])
@pytest.mark.parametrize("bandwidth", ["fixed", "median"])
def test_one_step_equals_blackjax(n, d, seed, bandwidth):
    """Same RBF kernel and optax.sgd: one mjstamp step == one blackjax step."""
    logp = _random_target(d, seed)
    x0 = 2.0 * jax.random.normal(jax.random.key(seed + 100), (n, d))
    optimizer = optax.sgd(0.1)
    if bandwidth == "fixed":
        length_scale, kernel = 0.8 * d, rbf(bandwidth=(0.8 * d) ** 0.5)
    else:  # blackjax's median heuristic sets length_scale = s² of ours.
        length_scale, kernel = None, rbf()

    @jax.jit
    def blackjax_step(x):
        ell = length_scale
        if ell is None:
            ell = blackjax_svgd.median_heuristic({"length_scale": 1.0}, x)[
                "length_scale"
            ]
        state = blackjax_svgd.init(x, {"length_scale": ell}, optimizer)
        kernel_step = blackjax_svgd.build_kernel(optimizer)
        return kernel_step(state, jax.grad(logp), blackjax_svgd.rbf_kernel), ell

    expected, length_scale = blackjax_step(x0)
    step = jax.jit(build_svgd_step(with_no_aux(jax.vmap(logp)), kernel, optimizer))
    state, info = step(init(x0, optimizer), KEY)
    np.testing.assert_allclose(
        state.particles, expected.particles, rtol=1e-5, atol=1e-5
    )
    assert float(jnp.max(jnp.abs(state.particles - x0))) > 1e-3  # the step did move
    np.testing.assert_allclose(info.bandwidth, [length_scale**0.5], rtol=1e-5)


def _brute_force_direction(logp1, kernel, x, a):
    """φ_i = Σ_j a_j [k(x_j, x_i) ∇log p(x_j) + ∇_{x_j} k(x_j, x_i)], pair by pair."""
    params = kernel.evaluate(x).params
    k = lambda u, v: kernel.pairwise(params, u, v)  # noqa: E731
    score = jax.vmap(jax.grad(logp1))(x)

    def phi_i(xi):
        kij = jax.vmap(lambda xj: k(xj, xi))(x)
        gk = jax.vmap(lambda xj: jax.grad(k)(xj, xi))(x)
        return jnp.sum(a[:, None] * (kij[:, None] * score + gk), axis=0)

    return jax.vmap(phi_i)(x)


def test_dsvgd_direction_is_importance_weighted_eq4():
    """Discrete SVGD matches eq. (4) computed pair by pair."""
    with jax.enable_x64(True):
        d, n = 4, 12
        logp1 = _random_target(d, 3)
        log_target1 = lambda x: logp1(x) + jnp.sin(3 * x[0]) * 2.0  # noqa: E731
        x = jax.random.normal(jax.random.key(4), (n, d))
        kernel = rbf(groups=[[0, 1], [2, 3]])
        phi, info = jax.jit(
            lambda p: stein_direction(
                with_no_aux(jax.vmap(logp1)), kernel, p,
                log_target_fn=with_no_aux(jax.vmap(log_target1)),
            )
        )(x)
        log_w = jax.vmap(logp1)(x) - jax.vmap(log_target1)(x)
        a = jnp.exp(log_w) / jnp.sum(jnp.exp(log_w))
        np.testing.assert_allclose(info.weights, a, rtol=1e-10)
        expected = jax.jit(_brute_force_direction, static_argnums=(0, 1))(
            logp1, kernel, x, a
        )
        np.testing.assert_allclose(phi, expected, rtol=1e-9, atol=1e-12)
        # With p(Γ(x)) = ρ(x) every weight is 1/n: discrete SVGD is SVGD.
        phi_svgd, _ = jax.jit(lambda p: stein_direction(with_no_aux(jax.vmap(logp1)), kernel,
                                                     p))(x)
        phi_equal, _ = jax.jit(
            lambda p: stein_direction(
                with_no_aux(jax.vmap(logp1)), kernel, p,
                log_target_fn=with_no_aux(jax.vmap(logp1)),
            )
        )(x)
        np.testing.assert_allclose(phi_equal, phi_svgd, rtol=1e-10, atol=1e-12)


def test_importance_log_weights_are_stable_and_normalised():
    """Weights of e^±10⁴ neither overflow nor underflow; bad ones get 0."""
    log_rho = jnp.array([1e4, 1e4 + 1.0, -1e4, 0.0, jnp.nan])
    log_p = jnp.array([0.0, 0.0, 0.0, jnp.inf, 0.0])
    log_w = importance_log_weights(log_rho, log_p)
    w = np.exp(np.asarray(log_w))
    np.testing.assert_allclose(w.sum(), 1.0, rtol=1e-6)
    np.testing.assert_allclose(w[:2], [1 / (1 + np.e), np.e / (1 + np.e)], rtol=1e-5)
    np.testing.assert_array_equal(w[2:], 0.0)  # underflow, -inf and NaN: weight 0
    assert np.all(
        np.asarray(importance_log_weights(jnp.full(3, jnp.nan), jnp.zeros(3)))
        == -np.inf
    )


def test_sgd_step_is_gradient_ascent():
    """With optax.sgd(ε) one SGD step is θ + ε ∇log ρ(θ)."""
    logp1 = _random_target(3, 5)
    x0 = jax.random.normal(jax.random.key(6), (5, 3))
    optimizer = optax.sgd(0.05)
    state, info = jax.jit(build_sgd_step(with_no_aux(jax.vmap(logp1)), optimizer))(
        init(x0, optimizer), KEY
    )
    expected = x0 + 0.05 * jax.vmap(jax.grad(logp1))(x0)
    np.testing.assert_allclose(state.particles, expected, rtol=1e-6, atol=1e-6)
    assert info.bandwidth.shape == (0,)


def test_any_optax_transformation_works_and_reports_its_learning_rate():
    """Chains, clipping and schedules plug in; ε is read back."""
    logp1 = _random_target(2, 7)
    x0 = jax.random.normal(jax.random.key(8), (10, 2))
    schedule = optax.exponential_decay(0.1, transition_steps=1, decay_rate=0.5)
    optimizer = optax.chain(
        optax.clip_by_global_norm(1.0),
        optax.inject_hyperparams(optax.adam)(learning_rate=schedule),
    )
    step = jax.jit(build_svgd_step(with_no_aux(jax.vmap(logp1)), rbf(), optimizer))
    state = init(x0, optimizer)
    rates = []
    for _ in range(3):
        state, info = step(state, KEY)
        rates.append(float(info.learning_rate))
    np.testing.assert_allclose(rates, [0.1, 0.05, 0.025], rtol=1e-6)
    # optax.sgd does not expose its rate: reported as NaN, not guessed.
    plain = jax.jit(build_svgd_step(with_no_aux(jax.vmap(logp1)), rbf(), optax.sgd(0.1)))
    assert np.isnan(float(plain(init(x0, optax.sgd(0.1)), KEY)[1].learning_rate))


def _billiards_like(x):
    """A batched 'rollout': returns log ρ and soft features of the same pass."""
    traj = jnp.cumsum(
        jnp.tanh(x[:, None, :] * jnp.linspace(0.1, 1.0, 8)[None, :, None]), 1
    )
    logp = -jnp.sum((traj[:, -1] - jnp.array([1.0, -0.5])) ** 2, axis=-1)
    feats = jax.nn.sigmoid(
        jnp.stack([traj[:, :, 0].max(1), -traj[:, :, 1].min(1), x[:, 0] * x[:, 1]], 1)
    )
    return logp, feats


@pytest.mark.parametrize("jacobian", ["auto", "fwd", "rev"])
def test_features_from_the_log_density_equal_a_separate_feature_map(jacobian):
    """App. B-C: kernel over [θ, w(θ)] with w from the same batched call as log ρ."""
    x0 = jax.random.normal(jax.random.key(9), (16, 2))
    optimizer = optax.sgd(0.1)
    shared = build_svgd_step(
        _billiards_like, feature_kernel(), optimizer, jacobian=jacobian
    )
    separate = build_svgd_step(
        with_no_aux(lambda p: _billiards_like(p)[0]),
        feature_kernel(feature_fn=lambda p: _billiards_like(p)[1]),
        optimizer,
    )
    s1, i1 = jax.jit(shared)(init(x0, optimizer), KEY)
    s2, i2 = jax.jit(separate)(init(x0, optimizer), KEY)
    np.testing.assert_allclose(s1.particles, s2.particles, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(i1.bandwidth, i2.bandwidth, rtol=1e-5)
    assert i1.bandwidth.shape == (2,)  # one median bandwidth for θ, one for w(θ)


@pytest.mark.parametrize(
    "kernel, fn, jacobian",
    [
        (rbf(), with_no_aux(lambda p: _billiards_like(p)[0]), "auto"),
        (feature_kernel(), _billiards_like, "rev"),
        (feature_kernel(), _billiards_like, "fwd"),
    ],
)
def test_one_batched_log_density_call_per_step(kernel, fn, jacobian):
    """N rollouts per step, not N² (nor 2N): the batch is traced once, at (n, d)."""
    shapes = []

    def counted(p):
        shapes.append(p.shape)
        return fn(p)

    optimizer = optax.sgd(0.1)
    step = build_svgd_step(counted, kernel, optimizer, jacobian=jacobian)
    x0 = jax.random.normal(KEY, (11, 2))
    jax.jit(step).trace(init(x0, optimizer), KEY)
    assert shapes == [(11, 2)]


def test_nonfinite_particles_get_zero_weight_and_do_not_poison_others():
    """A NaN particle gets weight 0 and the others stay finite."""

    def logp(x):
        value = -jnp.sum(x**2, axis=1)
        return jnp.where(x[:, 0] > 2.5, jnp.nan, value)

    x0 = jnp.concatenate([jnp.array([[3.0, 0.0]]), jax.random.normal(KEY, (7, 2))])
    optimizer = optax.sgd(0.1)
    state, info = jax.jit(build_svgd_step(with_no_aux(logp), rbf(), optimizer))(
        init(x0, optimizer), KEY
    )
    assert np.all(np.isfinite(state.particles))
    assert int(info.nonfinite_particles) == 1 and float(info.weights[0]) == 0.0
    np.testing.assert_allclose(
        float(info.logdensity_mean), float(jnp.mean(logp(x0)[1:])), rtol=1e-6
    )


@pytest.mark.parametrize(
    "call, match",
    [
        (
            lambda: init(jnp.zeros(5), optax.sgd(0.1)),
            r"shape \(n, d\); got shape \(5,\)",
        ),
        (
            lambda: jax.jit(
                build_svgd_step(with_no_aux(lambda p: -jnp.sum(p**2, 1)), rbf(),
                                optax.sgd(0.1))
            )(init(jnp.zeros((1, 2)), optax.sgd(0.1)), KEY),
            r"at least 2 particles \(n >= 2\); got n=1",
        ),
        (  # one signature: a bare (n,) array is not one
            lambda: jax.jit(
                build_svgd_step(lambda p: -jnp.sum(p**2, 1), rbf(), optax.sgd(0.1))
            )(init(jnp.zeros((4, 2)), optax.sgd(0.1)), KEY),
            r"logdensity_fn must return \(logp \(n,\), aux \(n, f\)\)",
        ),
        (
            lambda: jax.jit(
                build_svgd_step(lambda p: (-jnp.sum(p**2), jnp.zeros((4, 0))), rbf(),
                                optax.sgd(0.1))
            )(init(jnp.zeros((4, 2)), optax.sgd(0.1)), KEY),
            r"log-densities of shape \(n,\) = \(4,\)",
        ),
        (
            lambda: jax.jit(
                build_svgd_step(
                    with_no_aux(lambda p: -jnp.sum(p**2, 1)), feature_kernel(), optax.sgd(0.1)
                )
            )(init(jnp.zeros((4, 2)), optax.sgd(0.1)), KEY),
            r"must return \(logp \(n,\), features \(n, f\)\) with f >= 1",
        ),
        (
            lambda: jax.jit(
                build_svgd_step(
                    with_no_aux(lambda p: -jnp.sum(p**2, 1)), rbf(groups=[[0]]), optax.sgd(0.1)
                )
            )(init(jnp.zeros((4, 2)), optax.sgd(0.1)), KEY),
            r"RBF groups must cover every coordinate .* \[1\] are in none",
        ),
        (
            lambda: build_svgd_step(lambda p: p, rbf(), "adam"),
            r"optax.GradientTransformation",
        ),
        (
            lambda: build_svgd_step(lambda p: p, "rbf", optax.sgd(0.1)),
            r"Kernel or None",
        ),
        (
            lambda: build_svgd_step(lambda p: p, rbf(), optax.sgd(0.1), jacobian="x"),
            r"jacobian must be one of",
        ),
        (
            lambda: build_dsvgd_step(lambda p: p, None, rbf(), optax.sgd(0.1)),
            r"log_target_fn",
        ),
    ],
)
def test_bad_input_raises_clear_value_error(call, match):
    """Bad arguments raise a ValueError naming them, before compiling."""
    with pytest.raises(ValueError, match=match):
        call()


def test_sgd_step_forward_mode_scores_equal_reverse_mode():
    """`jacobian='fwd'` (d tangents) gives the same SGD step as the pullback."""
    import optax

    from mjstamp.svgd import build_sgd_step, init

    def logp(x):
        return -jnp.sum((x - 1.0) ** 2 * jnp.arange(1, x.shape[1] + 1), axis=1) + jnp.sin(x[:, 0])

    x = jax.random.normal(jax.random.key(0), (5, 3))
    opt = optax.sgd(0.1)
    out = [build_sgd_step(with_no_aux(logp), opt, jacobian=mode)(init(x, opt), jax.random.key(1))
           for mode in ("rev", "fwd")]
    np.testing.assert_allclose(out[0][0].particles, out[1][0].particles, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(out[0][1].logdensity, out[1][1].logdensity)


def test_sgd_step_auto_mode_is_forward_for_d_up_to_2_else_reverse():
    """'auto': forward mode (d tangents) when d <= 2, a pullback otherwise."""
    import optax

    from mjstamp.svgd import build_sgd_step, init

    # N.B. a custom_vjp function has no forward-mode derivative: jvp through it raises.
    @jax.custom_vjp
    def logp(x):
        return -jnp.sum(x**2, axis=1)

    logp.defvjp(lambda x: (logp(x), x), lambda x, g: (-2.0 * x * g[:, None],))
    opt = optax.sgd(0.1)
    x3 = jax.random.normal(jax.random.key(0), (4, 3))
    state, _ = build_sgd_step(with_no_aux(logp), opt)(init(x3, opt), jax.random.key(1))
    np.testing.assert_allclose(state.particles, x3 * 0.8, rtol=1e-12)
    x2 = x3[:, :2]
    with pytest.raises(TypeError, match="custom_vjp"):
        build_sgd_step(with_no_aux(logp), opt)(init(x2, opt), jax.random.key(1))
    state, _ = build_sgd_step(with_no_aux(logp), opt, jacobian="rev")(init(x2, opt),
                                                                       jax.random.key(1))
    np.testing.assert_allclose(state.particles, x2 * 0.8, rtol=1e-12)
