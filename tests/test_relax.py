"""Tests of mjstamp.relax: invariants, App. A's even partition, and gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from jax.test_util import check_grads

from mjstamp.relax import (
    block_labels,
    first_contact_mask,
    hard_onehot,
    soft_contact_indicator,
    soft_onehot,
    softmin_aggregate,
    uniform_base_sample,
)

# Fixed shapes keep hypothesis from compiling a new XLA program per example.
M, K = 3, 2
# N.B. no subnormals: XLA on CPU flushes them to zero, so Γ sees 1.6e-42 and 0
# as a tie (found by hypothesis), while numpy's argmax tells them apart.
finite = st.floats(-5.0, 5.0, allow_nan=False, allow_subnormal=False, width=32)
relaxed_x = hnp.arrays(np.float32, (4, M * K), elements=finite)


@settings(max_examples=30, deadline=None)
@given(relaxed_x)
def test_hard_onehot_is_one_hot_argmax_per_block(x):
    """Γ puts a single 1 per block, at the argmax."""
    z = np.asarray(hard_onehot(x, M)).reshape(4, K, M)
    assert set(np.unique(z)) <= {0.0, 1.0}
    np.testing.assert_array_equal(z.sum(-1), 1.0)
    np.testing.assert_array_equal(z.argmax(-1), x.reshape(4, K, M).argmax(-1))
    np.testing.assert_array_equal(block_labels(x, M), x.reshape(4, K, M).argmax(-1))


@settings(max_examples=30, deadline=None)
@given(relaxed_x, st.sampled_from([0.1, 1.0, 10.0]))
def test_soft_onehot_sums_to_one_per_block(x, temperature):
    """Γ̃ is a probability vector per block."""
    z = np.asarray(soft_onehot(x, M, temperature)).reshape(4, K, M)
    assert np.all((z >= 0) & (z <= 1))
    np.testing.assert_allclose(z.sum(-1), 1.0, rtol=1e-6)


def test_soft_onehot_tends_to_hard_onehot_as_temperature_vanishes():
    """Γ̃ → Γ as temperature → 0, at the rate the logit gaps set."""
    x = jax.random.normal(jax.random.key(0), (64, M * K))
    hard = hard_onehot(x, M)
    temperatures = (1.0, 1e-1, 1e-2, 1e-3)
    errors = [
        float(jnp.max(jnp.abs(soft_onehot(x, M, t) - hard))) for t in temperatures
    ]
    assert all(a > b for a, b in zip(errors[:-1], errors[1:], strict=False))
    # Off the argmax, softmax(x/T) ≤ exp(−gap/T) for the smallest gap between
    # the top two logits of a block; the argmax entry is off by their sum.
    top2 = np.sort(np.asarray(x).reshape(-1, M), axis=-1)[:, -2:]
    gap = float(np.min(top2[:, 1] - top2[:, 0]))
    for t, err in zip(temperatures, errors, strict=True):
        assert err <= (M - 1) * np.exp(-gap / t) + 1e-6


def test_gamma_partitions_uniform_base_evenly():
    """App. A: Γ splits unif([-u, u]^{mK}) into m^K parts of mass 1/m^K each."""
    n, u = 90_000, 3.0
    x = uniform_base_sample(jax.random.key(1), n, M * K, u)
    assert float(x.min()) >= -u and float(x.max()) < u
    codes = np.asarray(block_labels(x, M)) @ (M ** np.arange(K))
    counts = np.bincount(codes, minlength=M**K)
    p = 1.0 / M**K
    # Each count is Binomial(n, p); 5 standard deviations bound all 9 cells with
    # a false-alarm probability below 1e-5.
    sd = np.sqrt(n * p * (1 - p))
    np.testing.assert_array_less(np.abs(counts - n * p), 5 * sd)
    assert counts.size == M**K


def test_first_contact_mask():
    """True up to and including the first contact, all True without one."""
    contact = jnp.array(
        [
            [0, 0, 1, 0, 1],
            [1, 0, 0, 0, 0],
            [0, 0, 0, 0, 0],
        ],
        dtype=bool,
    )
    expected = np.array(
        [
            [1, 1, 1, 0, 0],
            [1, 0, 0, 0, 0],
            [1, 1, 1, 1, 1],
        ],
        dtype=bool,
    )
    np.testing.assert_array_equal(first_contact_mask(contact), expected)


def test_soft_contact_indicator_is_near_one_on_hit_and_near_zero_when_far():
    """The indicator is ≈ 1 on a hit, ≈ 0 when far or when the hit is after t_c."""
    t = jnp.linspace(0.0, 1.0, 50)
    far = 0.5 + t  # never closer than 0.5
    hit = jnp.abs(t - 0.5) - 0.01  # penetrates by 0.01 mid-way
    w = soft_contact_indicator(jnp.stack([far, hit]), alpha=100.0, beta=1.0)
    assert float(w[0]) < 1e-3 and float(w[1]) > 0.5
    # Masking the steps after t_c hides a hit that happens later.
    late_mask = t < 0.3
    w_masked = soft_contact_indicator(hit, alpha=100.0, beta=1.0, mask=late_mask)
    assert float(w_masked) < 1e-3


def test_softmin_aggregate_tends_to_masked_min():
    """The softmin tends to the min over the unmasked steps."""
    losses = jnp.array([3.0, 1.0, 2.0, 0.0])
    mask = jnp.array([True, True, True, False])
    assert float(softmin_aggregate(losses, mask=mask, temperature=1e-3)) == 1.0
    assert float(softmin_aggregate(losses, temperature=1e-3)) == 0.0
    # temperature 1 gives a proper weighted mean, above the min.
    assert 1.0 < float(softmin_aggregate(losses, mask=mask)) < 2.0


def test_masked_entries_leak_no_nan_into_value_or_gradient():
    """A NaN on a masked step changes neither value nor gradient."""
    losses = jnp.array([1.0, 2.0, jnp.nan])
    mask = jnp.array([True, True, False])
    value, grad = jax.value_and_grad(lambda v: softmin_aggregate(v, mask=mask))(losses)
    assert np.isfinite(value) and np.all(np.isfinite(grad))
    assert float(grad[2]) == 0.0


@pytest.mark.parametrize(
    "name",
    ["soft_onehot", "soft_contact_indicator", "soft_contact_masked", "softmin"],
)
def test_gradients_match_finite_differences(name):
    """JVP vs central differences and VJP vs JVP, in float64 (optax's check)."""
    with jax.enable_x64(True):
        rng = np.random.default_rng(0)
        x = jnp.asarray(rng.normal(size=(3, M * K)))
        sd = jnp.asarray(rng.normal(size=(3, 4, 20)) * 0.1)
        mask = first_contact_mask(jnp.asarray(rng.random((3, 20)) < 0.1))[:, None, :]
        fns = {
            "soft_onehot": (lambda x: soft_onehot(x, M, 0.7), x),
            "soft_contact_indicator": (
                lambda s: soft_contact_indicator(s, alpha=10.0, beta=0.5),
                sd,
            ),
            "soft_contact_masked": (
                lambda s: soft_contact_indicator(s, alpha=10.0, beta=0.5, mask=mask),
                sd,
            ),
            "softmin": (
                lambda v: softmin_aggregate(v**2, mask=mask, temperature=0.5),
                sd,
            ),
        }
        fn, arg = fns[name]
        check_grads(
            fn, (arg,), order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-7, rtol=1e-6
        )


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: hard_onehot(jnp.zeros((2, 5)), 3), r"m\*K entries with m=3"),
        (lambda: soft_onehot(jnp.zeros((2, 6)), 0), r"m \(entries per block\)"),
        (lambda: soft_onehot(jnp.zeros((2, 6)), 3, 0.0), r"temperature must be > 0"),
        (lambda: uniform_base_sample(jax.random.key(0), 0, 3), r"n must be"),
        (lambda: uniform_base_sample(jax.random.key(0), 4, 3, -1.0), r"u \(half-width"),
        (
            lambda: soft_contact_indicator(jnp.zeros(3), alpha=0.0, beta=0.0),
            r"alpha must be > 0",
        ),
        (lambda: softmin_aggregate(jnp.zeros(3), temperature=-1), r"temperature"),
    ],
)
def test_bad_input_raises_clear_value_error(call, match):
    """Bad arguments raise a ValueError naming them."""
    with pytest.raises(ValueError, match=match):
        call()
