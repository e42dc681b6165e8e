"""Tests of the STAMP loop (run_stamp) and its convergence test."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from mjstamp.svgd import (
    PHASE_SGD,
    PHASE_SVGD,
    StampConfig,
    feature_kernel,
    has_converged,
    rbf,
    run_stamp,
)

MODES = jnp.array([[2.0, 0.0], [-2.0, 0.0]])


def no_aux(x):
    """The aux of a log density without kernel features: an (n, 0) array."""
    return jnp.zeros((x.shape[0], 0), x.dtype)


def two_modes(x):
    """Batched log density with two unit-weight modes at (±2, 0), σ = 0.5; (logp, aux)."""
    logp = jax.nn.logsumexp(-jnp.sum((x[:, None] - MODES[None]) ** 2, -1) / 0.5, axis=1)
    return logp, no_aux(x)


def uniform_init(key):
    """Sixty particles uniform on [-4, 4]²."""
    return jax.random.uniform(key, (60, 2), minval=-4.0, maxval=4.0)


CONFIG = StampConfig(svgd_learning_rate=0.05, sgd_learning_rate=0.05, seed=3)


@pytest.fixture(scope="module")
def result():
    """One full STAMP run on the two-mode target, shared by several tests."""
    return run_stamp(two_modes, uniform_init, rbf(), CONFIG, progress=False)


def test_svgd_covers_both_modes_then_sgd_reaches_the_optima(result):
    """SVGD keeps both modes; SGD then lands on the optima."""
    assert result.svgd_converged and result.sgd_converged
    assert 0 < result.svgd_iters < CONFIG.svgd_max_iters
    assert 0 < result.sgd_iters < CONFIG.sgd_max_iters
    svgd = np.asarray(result.svgd_particles)
    right = svgd[:, 0] > 0
    assert 0.2 < right.mean() < 0.8  # diversity: both modes hold particles
    # After SVGD the particles spread around each mode (σ = 0.5 per axis)...
    assert 0.3 < svgd[right].std(0).min() and svgd[right].std(0).max() < 0.7
    # ...after SGD they sit on the optima. N.B. the mixture's maxima are not
    # exactly at ±2 (the other mode's tail pulls by ~e⁻³²): 1e-2 is ample.
    final = np.asarray(result.particles)
    nearest = np.asarray(MODES)[np.where(final[:, 0] > 0, 0, 1)]
    np.testing.assert_allclose(final, nearest, atol=1e-2)


def test_diagnostics_record_every_iteration_and_phase(result):
    """One diagnostics row per iteration, with its phase."""
    diag = result.diagnostics
    t_svgd, total = result.svgd_iters, result.svgd_iters + result.sgd_iters
    for field in diag:
        assert len(field) == total
    assert np.all(diag.phase[:t_svgd] == PHASE_SVGD)
    assert np.all(diag.phase[t_svgd:] == PHASE_SGD)
    assert diag.bandwidth.shape == (total, 1)
    assert np.all(diag.bandwidth[:t_svgd] > 0) and np.all(
        np.isnan(diag.bandwidth[t_svgd:])
    )
    np.testing.assert_allclose(diag.learning_rate, 0.05, rtol=1e-6)
    assert np.all(diag.logdensity_max >= diag.logdensity_mean)
    assert diag.logdensity_mean[-1] > diag.logdensity_mean[0] + 5
    assert np.all(diag.nonfinite_particles == 0)
    # The switch happened because the test passed on the recorded history.
    assert has_converged(
        diag.logdensity_mean[:t_svgd],
        diag.displacement[:t_svgd],
        window=CONFIG.window,
        rtol=CONFIG.rtol,
        motion_tol=CONFIG.motion_tol,
        min_iters=CONFIG.min_iters,
    )


def test_one_trace_per_phase_and_same_seed_same_run():
    """Each phase is traced once; a seed reproduces a run exactly."""
    traces = []

    def counted(x):
        traces.append(x.shape)
        return two_modes(x)

    config = StampConfig(svgd_max_iters=40, sgd_max_iters=30, seed=5)
    a = run_stamp(counted, uniform_init, None, config, progress=False)
    assert traces == [(60, 2), (60, 2)]  # SVGD step and SGD step, each traced once
    b = run_stamp(counted, uniform_init, None, config, progress=False)
    np.testing.assert_array_equal(a.particles, b.particles)
    np.testing.assert_array_equal(
        a.diagnostics.logdensity_mean, b.diagnostics.logdensity_mean
    )
    c = run_stamp(
        two_modes,
        uniform_init,
        None,
        StampConfig(svgd_max_iters=40, sgd_max_iters=30, seed=6),
        progress=False,
    )
    assert not np.array_equal(a.particles, c.particles)


def test_iteration_cap_is_the_fallback():
    """Unreachable tolerances stop each phase at its cap."""
    config = StampConfig(svgd_max_iters=15, sgd_max_iters=10, rtol=0.0, motion_tol=0.0)
    res = run_stamp(two_modes, uniform_init, None, config, progress=False)
    assert (res.svgd_iters, res.sgd_iters) == (15, 10)
    assert not res.svgd_converged and not res.sgd_converged


def test_deadlines_end_each_phase_at_its_share_of_a_budget():
    """A phase whose deadline has passed ends after the iteration it is in, as at its cap."""
    import time

    config = StampConfig(svgd_max_iters=15, sgd_max_iters=10, rtol=0.0, motion_tol=0.0)
    now = time.perf_counter()
    res = run_stamp(two_modes, uniform_init, None, config, progress=False,
                    deadlines=(now, now + 3600))
    assert (res.svgd_iters, res.sgd_iters) == (1, 10)
    res = run_stamp(two_modes, uniform_init, None, config, progress=False,
                    deadlines=(None, now))
    assert (res.svgd_iters, res.sgd_iters) == (15, 1)


def test_discrete_svgd_and_density_features_plug_in():
    """log_target_fn and density features run through run_stamp."""

    def with_features(x):
        return two_modes(x)[0], jax.nn.sigmoid(4 * x[:, :1])  # "which side" feature

    config = StampConfig(svgd_max_iters=20, sgd_max_iters=5)
    res = run_stamp(
        with_features,
        uniform_init,
        feature_kernel(),
        config,
        log_target_fn=lambda x: two_modes(
            jnp.round(x * 4) / 4
        ),  # a coarse "hard" target
        svgd_optimizer=optax.sgd(0.05),
        progress=False,
    )
    assert res.diagnostics.bandwidth.shape == (25, 2)  # [θ] and [w(θ)] blocks
    assert np.all(np.isfinite(res.particles))
    assert np.all(
        np.isnan(res.diagnostics.learning_rate[:20])
    )  # optax.sgd: not exposed


def test_progress_bar_in_interactive_use(capsys):
    """progress=True draws a tqdm bar on stderr."""
    run_stamp(
        two_modes,
        uniform_init,
        None,
        StampConfig(svgd_max_iters=3, sgd_max_iters=2),
        progress=True,
    )
    assert "STAMP" in capsys.readouterr().err


def test_status_lines_without_a_terminal(capsys):
    """progress=None with stderr not a terminal (a log, a pipe): a line per phase and tenth."""
    run_stamp(
        two_modes, uniform_init, None, StampConfig(svgd_max_iters=20, sgd_max_iters=10),
        progress=None,
    )
    err = capsys.readouterr().err.splitlines()
    assert "[stamp] SVGD: compiling its step (or loading it from the caches)" in err
    assert "[stamp] SGD: compiling its step (or loading it from the caches)" in err
    svgd = [line for line in err if line.startswith("[stamp] SVGD ")]
    assert [line.split()[2] for line in svgd] == [f"{t}/20:" for t in (1, *range(2, 21, 2))]
    assert all("mean log density" in line and "s/it" in line for line in svgd)
    run_stamp(two_modes, uniform_init, None, StampConfig(svgd_max_iters=2, sgd_max_iters=0),
              progress=False)
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize(
    "means, moves, expected",
    [
        ([-5.0] * 30, [1e-4] * 30, True),
        ([-5.0] * 25, [1e-4] * 25, False),  # fewer than W + 1 = 26 iterations
        (list(np.linspace(-10, -5, 30)), [1e-4] * 30, False),  # still improving
        ([-5.0] * 30, [1e-2] * 30, False),  # still moving
        ([0.0] * 29 + [5e-4], [1e-4] * 30, True),  # near 0: absolute change
        ([-5.0] * 29 + [float("nan")], [1e-4] * 30, False),
    ],
)
def test_has_converged(means, moves, expected):
    """The convergence test on hand-made histories."""
    got = has_converged(
        means, moves, window=25, rtol=1e-3, motion_tol=1e-3, min_iters=10
    )
    assert got is expected


@pytest.mark.parametrize(
    "make, match",
    [
        (
            lambda: StampConfig(svgd_learning_rate=0.0),
            r"svgd_learning_rate must be a float > 0",
        ),
        (
            lambda: StampConfig(sgd_learning_rate=-1e-3),
            r"sgd_learning_rate must be a float > 0",
        ),
        (lambda: StampConfig(window=0), r"window must be an integer >= 1"),
        (
            lambda: StampConfig(svgd_max_iters=-1),
            r"svgd_max_iters must be an integer >= 0",
        ),
        (lambda: StampConfig(rtol=-1.0), r"rtol must be a float >= 0"),
        (lambda: StampConfig(jacobian="central"), r"jacobian must be one of"),
        (
            lambda: run_stamp(two_modes, jnp.zeros((5,)), progress=False),
            r"shape \(n, d\)",
        ),
        (
            lambda: run_stamp(two_modes, jnp.zeros((1, 2)), progress=False),
            r"n >= 2\); got n=1",
        ),
        (
            lambda: run_stamp(two_modes, jnp.zeros((4, 2)), config={}, progress=False),
            r"StampConfig",
        ),
        (
            lambda: run_stamp(
                lambda x: (jnp.full(x.shape[0], jnp.nan), no_aux(x)),
                jnp.ones((4, 2)),
                progress=False,
            ),
            r"NaN/inf .* for all 4 initial particles",
        ),
        (
            lambda: run_stamp(
                two_modes, jnp.ones((4, 2)), rbf(groups=[[0]]), progress=False
            ),
            r"RBF groups must cover every coordinate 0..1",
        ),
    ],
)
def test_bad_input_raises_clear_value_error(make, match):
    """Bad arguments raise a ValueError naming them and their range."""
    with pytest.raises(ValueError, match=match):
        make()


def bowl_and_plateau(x):
    """The log density −min(x², 1): a bowl at 0 inside |x| < 1, a flat plateau outside."""
    return -jnp.minimum(jnp.sum(x**2, -1), 1.0), no_aux(x)


def test_stall_rescue_redraws_a_plateau_particle_and_leaves_a_converging_one():
    """A particle on the plateau (no gradient, low log ρ) is re-drawn after R iterations."""
    start = jnp.array([[3.0], [0.5]])  # plateau, bowl
    drawn = []

    def redraw(key, k):
        drawn.append(k)
        return jax.random.uniform(key, (k, 1), minval=-0.5, maxval=0.5)

    config = StampConfig(svgd_learning_rate=0.05, svgd_max_iters=40, sgd_max_iters=0,
                         min_iters=40, rescue_window=5)
    # A narrow kernel: the two particles do not feel each other, only their own score.
    result = run_stamp(bowl_and_plateau, start, rbf(bandwidth=0.05), config, progress=False,
                       redraw=redraw)
    np.testing.assert_array_equal(result.rescued, [1, 0])
    assert drawn == [1]
    rows = result.diagnostics.rescued
    assert rows.sum() == 1 and int(np.flatnonzero(rows)[0]) == 4  # after the 5th iteration
    final = np.asarray(result.particles)[:, 0]
    assert np.all(np.abs(final) < 0.5)  # the re-drawn one descends the bowl too
    # Off by default, and on without a source of particles is an error before tracing.
    plain = run_stamp(bowl_and_plateau, start, rbf(bandwidth=0.05),
                      dataclasses.replace(config, rescue_window=0), progress=False)
    np.testing.assert_array_equal(plain.rescued, [0, 0])
    # Stuck where it began. N.B. not exactly: rounding leaves a repulsion of ~1e-14,
    # which Adam (eps 1e-8) turns into steps of ~1e-7.
    assert abs(float(plain.particles[0, 0]) - 3.0) < 1e-4
    with pytest.raises(ValueError, match="rescue_window > 0 needs redraw"):
        run_stamp(bowl_and_plateau, start, rbf(), config, progress=False)
    with pytest.raises(ValueError, match="rescue_window"):
        StampConfig(rescue_window=-1)


def narrow_valley(x):
    """A valley 0.01 wide at x = 0.3 (log ρ = −(x − 0.3)²/10⁻⁴), steep beside it."""
    return -jnp.sum((x - 0.3) ** 2, -1) / 1e-4, no_aux(x)


def test_backtrack_keeps_a_particle_in_a_valley_narrower_than_the_step():
    """Adam's first step is the learning rate whatever the gradient: out of the valley.

    In SVGD the step is taken back and halved until the particle climbs;
    without backtracking its log density falls by orders of magnitude first.
    In SGD each particle ends at the best point it visited.
    """
    start = jnp.array([[0.3 + 1e-3], [0.3 - 2e-3]])
    start_logp = np.asarray(narrow_valley(start)[0])
    svgd_only = StampConfig(svgd_learning_rate=0.05, svgd_max_iters=30, sgd_max_iters=0,
                            min_iters=30)
    kernel = rbf(bandwidth=1e-4)  # the two particles do not feel each other
    plain = run_stamp(narrow_valley, start, kernel,
                      dataclasses.replace(svgd_only, backtrack=False), progress=False)
    assert plain.diagnostics.logdensity_mean[1] < 100 * start_logp.mean()
    assert plain.diagnostics.backtracked.sum() == 0
    guarded = run_stamp(narrow_valley, start, kernel, svgd_only, progress=False)
    d = guarded.diagnostics
    assert d.backtracked[0] == 0 and d.backtracked[1] == 2  # the first step, taken back
    assert d.step_scale_median.min() < 0.5
    # The displacement the convergence test reads is the step taken (back, here).
    np.testing.assert_allclose(d.displacement[1], 0.05, rtol=1e-6)
    # Back where they began after the take-back, and in the valley at the end.
    np.testing.assert_array_equal(d.logdensity_mean[2], d.logdensity_mean[0])
    assert np.all(np.abs(np.asarray(guarded.particles)[:, 0] - 0.3) < 0.01)  # within 1 nat
    # SGD: Adam runs free, and each particle ends at its best point, here the start.
    sgd_only = StampConfig(sgd_learning_rate=0.05, svgd_max_iters=0, sgd_max_iters=3,
                           min_iters=3)
    free = run_stamp(narrow_valley, start, kernel, dataclasses.replace(sgd_only, backtrack=False),
                     progress=False)
    best = run_stamp(narrow_valley, start, kernel, sgd_only, progress=False)
    assert np.all(np.asarray(narrow_valley(free.particles)[0]) < start_logp - 1)
    np.testing.assert_array_equal(best.particles, start)
    assert best.diagnostics.backtracked.sum() == 0
    with pytest.raises(ValueError, match="backtrack must be True or False"):
        StampConfig(backtrack=1)


def slope(x):
    """Log ρ = −x: every step towards larger x loses 0.1 nat per 0.1 moved."""
    return -x[:, 0], no_aux(x)


def test_backtrack_bounds_small_falls_by_the_peak_not_the_last_point():
    """Steps that each fall less than the margin cannot add up to more than it.

    An optimizer that always moves +0.1 (down the slope, 0.1 nat a step,
    under the 1-nat margin of d = 1): compared with its last accepted point
    every step would pass and the particle would slide 3 nats in 30 steps;
    compared with its peak, it is held within 1 nat of where it began.
    """
    downhill = optax.GradientTransformation(
        lambda params: optax.EmptyState(),
        lambda updates, state, params=None: (jnp.full_like(updates, 0.1), state))
    start = jnp.array([[0.0], [5.0]])
    config = StampConfig(svgd_max_iters=30, sgd_max_iters=0, min_iters=30)
    kernel = rbf(bandwidth=1e-3)  # the two particles do not feel each other
    plain = run_stamp(slope, start, kernel, dataclasses.replace(config, backtrack=False),
                      svgd_optimizer=downhill, progress=False)
    np.testing.assert_allclose(np.asarray(plain.particles)[:, 0] - [0.0, 5.0], 3.0, rtol=1e-9)
    guarded = run_stamp(slope, start, kernel, config, svgd_optimizer=downhill, progress=False)
    fall = np.asarray(guarded.particles)[:, 0] - [0.0, 5.0]
    assert np.all(fall > 0.5) and np.all(fall <= 1.0 + 1e-9)  # moved, but within a nat
    assert guarded.diagnostics.backtracked.sum() > 0


def cliff(x):
    """Log ρ = x up to a cliff at x = 0.35, NaN beyond it (a rollout that blew up)."""
    return jnp.where(x[:, 0] < 0.35, x[:, 0], jnp.nan), no_aux(x)


def test_backtrack_takes_a_step_into_a_non_finite_region_back():
    """The particle returns to its last accepted point instead of freezing beyond the cliff."""
    start = jnp.array([[0.34], [-0.5]])
    drawn = []

    def redraw(key, k):
        drawn.append(k)
        return jnp.full((k, 1), -0.9)

    config = StampConfig(svgd_learning_rate=0.05, svgd_max_iters=12, sgd_max_iters=0,
                         min_iters=12, nonfinite_redraw=2)
    kernel = rbf(bandwidth=1e-3)
    result = run_stamp(cliff, start, kernel, config, progress=False, redraw=redraw)
    d = result.diagnostics
    assert d.nonfinite_particles[1] == 1 and d.backtracked[1] == 1  # over the cliff, back
    assert drawn == [] and result.nonfinite_redrawn.sum() == 0  # never frozen twice in a row
    final = np.asarray(result.particles)[:, 0]
    assert np.all(np.isfinite(np.asarray(cliff(result.particles)[0])))
    assert 0.3 < final[0] < 0.35
    plain = run_stamp(cliff, start, kernel, dataclasses.replace(config, backtrack=False),
                      progress=False, redraw=redraw)
    assert drawn == [1] and plain.nonfinite_redrawn[0] == 1  # frozen there, then re-drawn


def _with_features(x):
    """two_modes with features of the same evaluation: ψ(θ) = (sin θ₁, θ₂²)."""
    return two_modes(x)[0], jnp.stack([jnp.sin(x[:, 0]), x[:, 1] ** 2], axis=1)


def _compiled_names(logdensity_fn, kernel, init, **config):
    """Names run_stamp hands its jit hook, in order, and the run's result."""
    names = []

    def jit(fn, name, *example):
        names.append(name)
        return jax.jit(fn)

    cfg = StampConfig(svgd_learning_rate=0.05, sgd_learning_rate=0.05, seed=3,
                      svgd_max_iters=6, sgd_max_iters=6, **config)
    return names, run_stamp(logdensity_fn, init, kernel, cfg, progress=False, jit=jit)


def _init_dim(d):
    return lambda key: jax.random.uniform(key, (12, d), minval=-4.0, maxval=4.0)


@pytest.mark.parametrize(
    "logdensity_fn, kernel, d, jacobian, shared",
    [
        (_with_features, "feature", 2, "auto", True),  # both forward mode: billiards' case
        (_with_features, "feature", 3, "auto", False),  # SGD takes one pullback
        (_with_features, "feature", 3, "fwd", True),
        (two_modes, None, 3, "auto", True),  # rbf: both one pullback
        (two_modes, None, 2, "auto", False),  # rbf pullback, SGD forward mode
    ],
)
def test_sgd_phase_reuses_the_svgd_evaluation_when_it_differentiates_the_same_way(
        logdensity_fn, kernel, d, jacobian, shared):
    """One compiled rollout serves both phases where their derivatives agree (issue 12)."""
    def logdensity(x):
        return logdensity_fn(x[:, :2]) if d == 2 else logdensity_fn(x[:, :2] + x[:, 2:3])

    k = feature_kernel() if kernel == "feature" else None
    names, shared_run = _compiled_names(logdensity, k, _init_dim(d), jacobian=jacobian)
    expected = ["svgd-evaluate", "svgd-update", "sgd-update"]
    if not shared:
        expected.insert(2, "sgd-evaluate")
    assert names == expected
    # The same run with each phase evaluating on its own (jit=None keeps the halves
    # apart too): the plans do not depend on the sharing.
    cfg = StampConfig(svgd_learning_rate=0.05, sgd_learning_rate=0.05, seed=3,
                      svgd_max_iters=6, sgd_max_iters=6, jacobian=jacobian)
    alone = run_stamp(logdensity, _init_dim(d), k, cfg, progress=False,
                      sgd_logdensity_fn=lambda x: logdensity(x))
    np.testing.assert_allclose(shared_run.particles, alone.particles, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(shared_run.svgd_particles, alone.svgd_particles, rtol=0,
                               atol=0)


def test_a_step_is_its_update_of_its_evaluation():
    """step(state, key) == step.update(state, step.evaluate(θ), key), for every builder."""
    from mjstamp.svgd import build_dsvgd_step, build_sgd_step, build_svgd_step, init

    x = uniform_init(jax.random.key(0))[:8]
    opt = optax.adam(0.1)
    steps = [build_svgd_step(two_modes, None, opt),
             build_svgd_step(_with_features, feature_kernel(), opt),
             build_dsvgd_step(two_modes, lambda t: (two_modes(t)[0] - 1.0, no_aux(t)), None, opt),
             build_sgd_step(two_modes, opt)]
    for step in steps:
        state = init(x, opt)
        whole, info = jax.jit(step)(state, jax.random.key(1))
        halves, info2 = step.update(state, step.evaluate(state.particles), jax.random.key(1))
        np.testing.assert_allclose(whole.particles, halves.particles, rtol=1e-12)
        np.testing.assert_allclose(info.logdensity, info2.logdensity, rtol=1e-12)
        assert not np.allclose(whole.particles, x)  # the step moved them
