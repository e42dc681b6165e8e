"""Batched MJX rollouts against MuJoCo C, and the gradient health of shipped scenes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjstamp.errors import MjstampError
from mjstamp.scenes import replay
from mjstamp.scenes.check import check_scene

# Per-field tolerances of MJX (float64) against MuJoCo C stepping the same
# gradient-safe model: both run one Newton iteration on the same contact
# problem, so they differ only by floating-point reassociation, amplified by
# the bounces over the horizon (about 1e-11 seen on qpos over 200 steps).
TOL = {"qpos": 1e-8, "qvel": 1e-7, "geom_xpos": 1e-8, "geom_xmat": 1e-8, "xpos": 1e-8}


def _billiards_shots(scene, n, seed=0):
    rng = np.random.default_rng(seed)
    qpos0, qvel0 = scene.initial_state()
    qvel = np.tile(qvel0, (n, 1))
    qvel[:, [scene.dof_adr("cue_x"), scene.dof_adr("cue_y")]] = rng.uniform(-3, 3, (n, 2))
    return np.tile(qpos0, (n, 1)), qvel


@pytest.mark.slow
def test_billiards_rollout_matches_mujoco_c(billiards):
    fields = ("qpos", "qvel", "geom_xpos", "geom_xmat", "xpos")
    qpos0, qvel0 = _billiards_shots(billiards, 8)
    out = billiards.rollout_fn(150, fields=fields)(qpos0, qvel0)
    ref = replay(billiards, qpos0, qvel0, horizon=150, fields=fields, solver="grad")
    for f in fields:
        assert out[f].shape == ref[f].shape, f
        np.testing.assert_allclose(np.asarray(out[f]), ref[f], atol=TOL[f], err_msg=f)
    # The shots do hit something: the cue ball's velocity changes direction.
    v = ref["qvel"][:, :, :2]
    assert (np.sign(v[:, -1]) != np.sign(v[:, 0])).any()


@pytest.mark.slow
def test_pushing_rollout_with_controls_matches_mujoco_c(pushing):
    rng = np.random.default_rng(1)
    n, T = 4, 80
    qpos0, qvel0 = pushing.initial_state()
    qpos0, qvel0 = np.tile(qpos0, (n, 1)), np.tile(qvel0, (n, 1))
    # Servo set-points (x, y, z, vx, vy, vz): the pusher starts 0.15 m west of the
    # block and is sent east at table height, so contact happens.
    ctrl = np.zeros((n, 4, 6))
    ctrl[:, :, 0] = rng.uniform(0.1, 0.35, (n, 4))
    ctrl[:, :, 1] = rng.uniform(-0.05, 0.05, (n, 4))
    ctrl = np.repeat(ctrl, T // 4, axis=1)
    out = pushing.rollout_fn(T, fields=("qpos", "qvel"))(qpos0, qvel0, ctrl)
    ref = replay(pushing, qpos0, qvel0, ctrl, solver="grad")
    for f in ("qpos", "qvel"):
        np.testing.assert_allclose(np.asarray(out[f]), ref[f], atol=TOL[f], err_msg=f)
    block = pushing.qpos_adr("block_x")
    assert np.abs(ref["qpos"][:, -1, block]).max() > 1e-2  # the block was pushed


@pytest.mark.slow
def test_checkpointed_rollout_has_the_same_gradient(billiards):
    qpos0, qvel0 = _billiards_shots(billiards, 4, seed=3)
    grads = []
    for checkpoint in (None, "auto"):
        rollout = billiards.rollout_fn(100, fields=("qpos",), checkpoint=checkpoint)
        loss = lambda v, r=rollout: jnp.sum(r(qpos0, v)["qpos"][:, -1] ** 2)  # noqa: E731
        grads.append(np.asarray(jax.jit(jax.grad(loss))(qvel0)))
    assert billiards.rollout_fn(100, fields=("qpos",), checkpoint="auto").chunk == 10
    np.testing.assert_allclose(grads[0], grads[1], rtol=1e-10, atol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize(
    "scene_name,gradient", [("billiards", "unrolled"), ("pushing", "implicit")]
)
def test_shipped_scene_gradients_are_healthy(scene_name, gradient, request):
    """0 non-finite of 256; fidelity to the scene's own physics; AD vs its FD <= 1e-3.

    With the gradient model `solve` calibrates for each: one unrolled iteration is
    exact on the soft, frictionless billiards table; the pusher's frictional
    contact drifts by 1.3 cm with it and needs the converged (implicit) solver.
    """
    scene = request.getfixturevalue(scene_name)
    if gradient == "implicit":
        scene = scene.with_grad_options(gradient="implicit", iterations=scene.m.opt.iterations)
    report = check_scene(scene, particles=256, seed=0, calibrate=False)
    assert report["healthy"], report["problems"]
    assert report["nonfinite"] == 0
    assert report["rel_err_median"] <= 1e-3
    # The gradients are informative, not vanishing or exploding.
    assert 1e-3 < report["grad_norm_median"] < 1e4


def test_rollout_rejects_bad_shapes(billiards):
    rollout = billiards.rollout_fn(10)
    qpos0, qvel0 = _billiards_shots(billiards, 2)
    with pytest.raises(MjstampError, match=r"qpos0 has shape \(2, 3\); valid: \(n, 4\)"):
        rollout(qpos0[:, :3], qvel0)
    with pytest.raises(MjstampError, match=r"qvel0 has shape"):
        rollout(qpos0, qvel0[:1])
    with pytest.raises(MjstampError, match="unknown rollout field 'qfoo'"):
        billiards.rollout_fn(10, fields=("qfoo",))
    with pytest.raises(MjstampError, match="must divide the horizon 10"):
        billiards.rollout_fn(10, checkpoint=3)


def test_controls_required_where_the_scene_has_actuators(pushing):
    qpos0, qvel0 = pushing.initial_state()
    with pytest.raises(MjstampError, match=r"ctrl is missing.*\(1, 10, 6\)"):
        pushing.rollout_fn(10)(qpos0[None], qvel0[None])


def test_replay_needs_controls_or_a_horizon(billiards):
    """One line naming the caller (replay, calibrate and stepjac share the check)."""
    qpos0, qvel0 = _billiards_shots(billiards, 2)
    with pytest.raises(MjstampError, match="^replay needs ctrl or horizon$"):
        replay(billiards, qpos0, qvel0)
    out = replay(billiards, qpos0, qvel0, horizon=3, fields=("qpos",))
    assert out["qpos"].shape == (2, 3, billiards.m.nq)
