"""run_stamp continues from any LoopSnapshot exactly as a run never stopped."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjstamp.svgd import LoopSnapshot, StampConfig, rbf, run_stamp


def _logp(x):
    # A Gaussian bump on a plateau: particles out on the flat feel no gradient and sit
    # below the median, so the stall rescue re-draws them (its counters must resume too).
    bump = -0.5 * jnp.sum((x - jnp.array([0.5, -0.2])) ** 2 / jnp.array([0.3, 0.8]), axis=1)
    return jnp.maximum(bump, -8.0), jnp.zeros((x.shape[0], 0), x.dtype)


def _redraw(key, k):
    return jax.random.normal(key, (k, 2))


# Both phases end by a (loose) convergence test before their caps.
CONFIG = StampConfig(svgd_max_iters=30, sgd_max_iters=30, min_iters=3, window=2, rtol=0.5,
                     motion_tol=1.0, seed=4, rescue_window=2)
X0 = jax.random.normal(jax.random.key(1), (6, 2)) * 3


class _Stop(Exception):
    pass


def _run(**kwargs):
    return run_stamp(_logp, X0, rbf(), CONFIG, progress=False, redraw=_redraw, **kwargs)


@pytest.fixture(scope="module")
def straight():
    snaps = []
    result = _run(checkpoint=lambda make: snaps.append(make()))
    return result, snaps


def test_every_iteration_hands_out_a_snapshot(straight):
    result, snaps = straight
    assert len(snaps) == result.svgd_iters + result.sgd_iters
    assert [s.phase for s in snaps] == [0] * result.svgd_iters + [1] * result.sgd_iters
    assert all(isinstance(s, LoopSnapshot) for s in snaps)
    # Not vacuous: the rescue fires and both phases end by their convergence test.
    assert result.rescued.sum() > 0 and result.svgd_converged and result.sgd_converged


@pytest.mark.parametrize("stop_after", ["first", "second", "svgd-1", "svgd-end",
                                        "sgd-first", "sgd-second", "end"])
def test_resumed_runs_end_where_the_straight_run_ends(straight, stop_after):
    """Stopped after an iteration (in SVGD, at the switch, in SGD, at the end), then resumed."""
    result, _ = straight
    kept = []

    k = result.svgd_iters
    stop_at = {"first": 1, "second": 2, "svgd-1": k - 1, "svgd-end": k, "sgd-first": k + 1,
               "sgd-second": k + 2, "end": k + result.sgd_iters}[stop_after]

    def stop(make):
        kept.append(make())
        if len(kept) == stop_at:
            raise _Stop

    with pytest.raises(_Stop):
        _run(checkpoint=stop)
    resumed = _run(resume=kept[-1])
    np.testing.assert_array_equal(resumed.particles, result.particles)
    np.testing.assert_array_equal(resumed.svgd_particles, result.svgd_particles)
    assert (resumed.svgd_iters, resumed.sgd_iters) == (result.svgd_iters, result.sgd_iters)
    np.testing.assert_array_equal(resumed.rescued, result.rescued)
    for name in ("logdensity_mean", "displacement", "rescued", "phase"):
        np.testing.assert_array_equal(getattr(resumed.diagnostics, name),
                                      getattr(result.diagnostics, name))


def test_a_snapshot_of_another_shape_is_refused(straight):
    _, snaps = straight
    bad = snaps[2]._replace(particles=np.zeros((3, 2)))
    with pytest.raises(ValueError, match="cannot continue"):
        _run(resume=bad)


def test_a_run_resumed_right_after_a_nonfinite_redraw_ends_where_the_straight_one_ends():
    """The non-finite count of a particle re-drawn at the snapshot's iteration resumes too."""

    def logp(x):
        value = jnp.where(x[:, 0] > 2.0, jnp.nan, -0.5 * jnp.sum(x**2, axis=1))
        return value, jnp.zeros((x.shape[0], 0), x.dtype)

    def redraw(key, k):  # back into the NaN region, every time
        return 3.0 + jax.random.uniform(key, (k, 2))

    x0 = jnp.array([[3.0, 0.0], [0.5, 0.5], [-0.5, 0.2]])
    config = StampConfig(svgd_max_iters=6, sgd_max_iters=0, min_iters=6, nonfinite_redraw=1)
    snaps = []
    straight = run_stamp(logp, x0, rbf(), config, progress=False, redraw=redraw,
                         checkpoint=lambda make: snaps.append(make()))
    # Re-drawn, then a grace iteration for the fresh particle, and so on.
    np.testing.assert_array_equal(straight.diagnostics.nonfinite_redrawn, [1, 0] * 3)
    resumed = run_stamp(logp, x0, rbf(), config, progress=False, redraw=redraw, resume=snaps[0])
    np.testing.assert_array_equal(resumed.diagnostics.nonfinite_redrawn,
                                  straight.diagnostics.nonfinite_redrawn)
    np.testing.assert_array_equal(resumed.particles, straight.particles)
