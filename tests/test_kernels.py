"""Tests of mjstamp.svgd.kernels: closed forms against autodiff, invariants, errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from blackjax.vi import svgd as blackjax_svgd
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from jax.test_util import check_grads

from mjstamp.relax import soft_onehot
from mjstamp.svgd import (
    feature_kernel,
    flat_bandwidths,
    median_bandwidth,
    rbf,
    sum_kernels,
    von_mises,
)
from mjstamp.svgd.kernels import median_pairwise_distance

N, D = 9, 5


def _features(t):
    """A nonlinear, particle-separable feature map (n, 5) -> (n, 2)."""
    return jnp.stack([jnp.tanh(t[:, 0] * t[:, 1]), jnp.sin(t[:, 2]) + t[:, 3] ** 2], 1)


KERNELS = {
    "rbf": lambda: rbf(),
    "rbf_fixed": lambda: rbf(bandwidth=1.3),
    "rbf_groups": lambda: rbf(
        groups=[slice(0, 2), [2, 4], [3]], bandwidth=("median", 0.7, "median")
    ),
    "von_mises": lambda: von_mises(groups=[slice(0, 3), slice(3, None)]),
    "von_mises_fixed": lambda: von_mises(bandwidth=0.8),
    "sum": lambda: sum_kernels(
        [(0.5, rbf(), slice(0, 2)), (2.0, von_mises(), [2, 3]), (1.0, rbf(), [1, 4])]
    ),
    "feature": lambda: feature_kernel(feature_fn=_features),
    "feature_fwd": lambda: feature_kernel(feature_fn=_features, jacobian="fwd"),
    "feature_only_softmax": lambda: feature_kernel(
        rbf(bandwidth=0.9),
        feature_fn=lambda t: soft_onehot(t, D),
        include_inputs=False,
    ),
    # App. C-B: RBF on positions, RBF on softmax(s), von Mises on the angle.
    "pushing_like": lambda: sum_kernels(
        [
            (1.0, rbf(), slice(0, 2)),
            (
                0.5,
                feature_kernel(
                    feature_fn=lambda s: soft_onehot(s, 2), include_inputs=False
                ),
                [2, 3],
            ),
            (0.3, von_mises(), [4]),
        ]
    ),
}


def _points(seed=0, n=N, d=D, scale=1.5):
    return jax.random.normal(jax.random.key(seed), (n, d)) * scale


def _reference(kernel, params, x, a):
    """Gram and repulsion by autodiff of the pairwise kernel: O(n²) slow path."""
    k = lambda u, v: kernel.pairwise(params, u, v)  # noqa: E731
    gram = jax.vmap(lambda xj: jax.vmap(lambda xi: k(xj, xi))(x))(x)
    grads = jax.vmap(lambda xj: jax.vmap(lambda xi: jax.grad(k)(xj, xi))(x))(x)
    return gram, jnp.einsum("j,jid->id", a, grads)


@pytest.mark.parametrize("name", sorted(KERNELS))
def test_closed_form_matches_autodiff_and_gram_is_positive_definite(name):
    """Closed-form repulsion equals autodiff (through φ too); K is symmetric and PD.

    R_i = Σ_j a_j ∇_{x_j} k(x_j, x_i); the diagonal k(x, x) is the sum of weights.
    """
    with jax.enable_x64(True):
        kernel = KERNELS[name]()
        x = _points(n=40)
        a = jax.nn.softmax(jax.random.normal(jax.random.key(1), (40,)))
        terms = jax.jit(kernel.evaluate)(x, a)
        gram, repulsion = jax.jit(_reference, static_argnums=0)(
            kernel, terms.params, x, a
        )
        np.testing.assert_allclose(terms.gram, gram, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(terms.repulsion, repulsion, rtol=1e-10, atol=1e-13)
        assert np.all(np.asarray(flat_bandwidths(terms.params)) > 0)

        gram = np.asarray(terms.gram)
        np.testing.assert_allclose(gram, gram.T, atol=1e-14)
        # k(x, x) = Σ of the term weights (1 for a single kernel).
        weights = {"sum": 3.5, "pushing_like": 1.8}.get(name, 1.0)
        np.testing.assert_allclose(np.diag(gram), weights, rtol=1e-12)
        # Eigenvalues of a PD Gram matrix are > 0; 1e-10·n allows for rounding.
        assert np.linalg.eigvalsh(gram).min() > -1e-10 * len(gram)


@pytest.mark.parametrize("name", sorted(KERNELS))
def test_pairwise_gradient_matches_finite_differences(name):
    """The gradient the reference relies on: JVP vs central FD, VJP vs JVP."""
    with jax.enable_x64(True):
        kernel = KERNELS[name]()
        x = _points()
        params = jax.jit(kernel.evaluate)(x).params
        check_grads(
            jax.jit(lambda u: kernel.pairwise(params, u, x[1])),
            (x[0],),
            order=1,
            eps=1e-6,
        )


_RANDOM_POINT_GRAMS = {
    "rbf": jax.jit(rbf(bandwidth=0.5).gram),
    "von_mises": jax.jit(von_mises(bandwidth=0.5).gram),
    "sum": jax.jit(
        sum_kernels([(1.0, rbf(bandwidth=0.5), [0, 1]), (2.0, von_mises(), [2])]).gram
    ),
}


@settings(max_examples=15, deadline=None)
@given(
    hnp.arrays(np.float64, (12, 3), elements=st.floats(-4, 4, allow_nan=False)),
    st.sampled_from(["rbf", "von_mises", "sum"]),
)
def test_gram_is_positive_semidefinite_on_random_points(points, family):
    """Gram matrices of random points have no negative eigenvalue."""
    with jax.enable_x64(True):
        gram = np.asarray(_RANDOM_POINT_GRAMS[family](jnp.asarray(points)))
    assert np.linalg.eigvalsh(gram).min() > -1e-9


_MEDIAN = jax.jit(median_pairwise_distance)


@settings(max_examples=40, deadline=None)
@given(
    hnp.arrays(
        np.float32,
        (13, 2),
        elements=st.sampled_from([0.0, 0.5, 1.0, -2.0])  # many ties
        | st.floats(-3, 3, allow_nan=False, width=32),
    ),
)
def test_bisection_median_equals_sorting_median(points):
    """The exact bisection median equals numpy's, ties and coincident points too."""
    d2 = np.sum((points[:, None] - points[None]) ** 2, axis=-1)
    expected = np.median(np.sqrt(d2[np.triu_indices(13, 1)]))
    got = float(_MEDIAN(jnp.asarray(d2)))
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-7)


def test_von_mises_wraps_around():
    """The von Mises kernel is 2π-periodic and sees -3.1 near 3.0."""
    with jax.enable_x64(True):
        kernel = von_mises(bandwidth=0.7)
        s = jnp.array([0.7])
        x, y = jnp.array([0.1, 3.0]), jnp.array([-0.2, -3.1])
        k = kernel.pairwise(s, x, y)
        k_wrapped = kernel.pairwise(s, x + 2 * jnp.pi, y - 4 * jnp.pi)
        np.testing.assert_allclose(k, k_wrapped, rtol=1e-12)
        # 3.0 and -3.1 are 0.18 apart on the circle: close, unlike for an RBF.
        k_angle = kernel.pairwise(s, x[1:], y[1:])
        assert float(k_angle) > 0.8 and float(rbf().pairwise(s, x[1:], y[1:])) < 1e-20


def test_median_bandwidth_matches_definition_and_blackjax():
    """median/√(log n) per group, equal to blackjax's √length_scale."""
    x = _points(seed=3, n=30)
    xn = np.asarray(x, dtype=np.float64)
    iu = np.triu_indices(30, 1)

    def expected(cols):
        dist = np.linalg.norm(xn[:, None, cols] - xn[None, :, cols], axis=-1)[iu]
        return np.median(dist) / np.sqrt(np.log(30))

    np.testing.assert_allclose(median_bandwidth(x), [expected(slice(None))], rtol=1e-5)
    np.testing.assert_allclose(
        median_bandwidth(x, [slice(0, 2), [2, 3, 4]]),
        [expected(slice(0, 2)), expected([2, 3, 4])],
        rtol=1e-5,
    )
    # blackjax's length_scale (k = exp(-‖Δ‖²/ℓ)) is s².
    ell = jax.jit(lambda p: blackjax_svgd.median_heuristic({"length_scale": 1.0}, p))(
        x
    )["length_scale"]
    np.testing.assert_allclose(median_bandwidth(x)[0] ** 2, ell, rtol=1e-5)
    # Coincident particles have median distance 0: fall back to 1, not 0.
    np.testing.assert_array_equal(median_bandwidth(jnp.zeros((5, 2))), [1.0])


def test_feature_kernel_reads_density_features_like_its_own_feature_map():
    """Features and Jacobians handed in from the log density give the same terms."""
    x = _points(seed=4)
    a = jnp.full((N,), 1.0 / N)
    own = jax.jit(feature_kernel(feature_fn=_features).evaluate)(x, a)
    feats = _features(x)
    feats_jac = jax.jit(jax.vmap(jax.jacobian(lambda t: _features(t[None])[0])))(x)
    read = jax.jit(feature_kernel().evaluate)(x, a, features=(feats, feats_jac))
    np.testing.assert_allclose(read.gram, own.gram, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(read.repulsion, own.repulsion, rtol=1e-4, atol=1e-5)
    # ...and the repulsion really goes through φ: dropping ∂φ/∂θ changes it.
    no_chain = jax.jit(feature_kernel().evaluate)(
        x, a, features=(feats, jnp.zeros_like(feats_jac))
    )
    assert float(jnp.max(jnp.abs(no_chain.repulsion - own.repulsion))) > 1e-3


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: rbf(bandwidth=0.0), r"bandwidth must be > 0"),
        (lambda: rbf(bandwidth=-1.0), r"bandwidth must be > 0"),
        (lambda: von_mises(bandwidth="mean"), r"bandwidth must be > 0 or 'median'"),
        (lambda: rbf(groups=[[0], [1]], bandwidth=(1.0,)), r"one per group \(2\)"),
        (lambda: rbf(groups=[[]]), r"at least one coordinate"),
        (lambda: rbf(groups=["ab"]), r"slice or a sequence of ints"),
        (lambda: sum_kernels([]), r"at least one"),
        (lambda: sum_kernels([(0.0, rbf(), [0])]), r"weight must be > 0"),
        (lambda: sum_kernels([(1.0, "rbf", [0])]), r"must be a Kernel"),
        (lambda: sum_kernels([(1.0, feature_kernel(), [0])]), r"outermost kernel"),
        (lambda: feature_kernel(jacobian="central"), r"jacobian must be one of"),
    ],
)
def test_bad_construction_raises_value_error(make, match):
    """Bad kernel arguments fail when the kernel is built."""
    with pytest.raises(ValueError, match=match):
        make()


@pytest.mark.parametrize(
    "kernel, x, match",
    [
        (
            rbf(groups=[[0, 1], [2]]),
            jnp.zeros((4, 4)),
            r"coordinates \[3\] are in none",
        ),
        (
            rbf(groups=[[0, 1], [1, 2]]),
            jnp.zeros((4, 3)),
            r"\[1\] are in more than one",
        ),
        (rbf(groups=[[0, 5]]), jnp.zeros((4, 3)), r"valid range \[0, 3\)"),
        (
            sum_kernels([(1.0, rbf(), [0]), (1.0, rbf(), [2])]),
            jnp.zeros((4, 3)),
            r"sum_kernels terms must cover .* coordinates \[1\]",
        ),
        (rbf(), jnp.zeros((4,)), r"x must be a 2-D array of shape \(n, d\)"),
        (rbf(), jnp.zeros((1, 3)), r"n >= 2"),
        (feature_kernel(), jnp.zeros((4, 3)), r"logdensity_fn must return"),
    ],
)
def test_bad_evaluation_raises_value_error(kernel, x, match):
    """Groups that do not fit the input fail on evaluation, before compiling."""
    with pytest.raises(ValueError, match=match):
        kernel.evaluate(x)
