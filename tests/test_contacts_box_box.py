"""The port of MuJoCo C's box-box collider (colliders.box_box) against C and its gradients."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco.mjx._src.collision_types import GeomInfo

from mjstamp import colliders
from mjstamp.colliders import box_box, compare

BOX = int(mujoco.mjtGeom.mjGEOM_BOX)
TOL = 1e-9
# One batch size for every comparison below: the harness compiles once per batch shape.
N = 300


@pytest.fixture(scope="module")
def pm():
    colliders.patch_collisions()
    return compare.pair_model(BOX, BOX)


def _check(pm, draws):
    c = compare.c_contacts(pm, draws)
    report = compare.compare(pm, draws, c, compare.mjx_contacts(pm, draws))
    assert report.count_mismatches == 0, report
    assert max(report.dist, report.pos, report.normal, report.frame) <= TOL, report
    return np.bincount([len(a) for a in c], minlength=compare.ROW)


def test_registered():
    assert colliders.PORTED[(BOX, BOX)] is box_box.box_box
    assert box_box.box_box.ncon == 8


def test_random_poses_match_c(pm):
    counts = _check(pm, compare.draw(pm, N, np.random.default_rng(0)))
    # both branches are exercised: single edge contacts and face manifolds
    assert counts[1] > 0 and counts[4] > 0 and counts[5:].sum() > 0


def test_aligned_poses_match_c(pm):
    # every draw face-parallel, half of them with a margin
    draws = compare.draw(pm, N, np.random.default_rng(3), aligned_share=1.0, margin_share=0.5)
    assert _check(pm, draws)[4] > 0


def _quat(axis, angle):
    q = np.zeros(4)
    mujoco.mju_axisAngle2Quat(q, np.asarray(axis, float), angle)
    return q


def _degenerate_draws() -> compare.Draws:
    """Exactly stacked, corner-to-corner, 45-degree and crossed-edge poses, tilted by 0..1e-3."""
    ident = np.array([1.0, 0, 0, 0])
    rows = []

    def add(s1, s2, q1, q2, p2, margin=(0.0, 0.0)):
        qpos = np.concatenate([np.zeros(3), q1, p2, q2])
        size = np.array([s1, s2], float)
        rows.append((size, np.linalg.norm(size, axis=1), np.array(margin), qpos))

    r2 = np.sqrt(2.0)
    for eps in [0.0, 1e-14, 1e-10, 1e-6, 1e-3]:
        for ang in [0.0, np.pi / 4, np.pi / 2, 0.3]:
            turn = _quat([0, 0, 1], ang)
            tilt = _quat([1, 1, 0], eps)
            add([.2, .2, .1], [.2, .2, .1], ident, turn, [0, 0, 0.2 - eps])
            add([.2, .2, .1], [.2, .2, .1], ident, tilt, [0, 0, 0.2 - eps])
            add([.2, .2, .1], [.2, .2, .1], ident, turn, [0.4 - eps, 0.4 - eps, 0.2 - eps])
            add([.2, .3, .1], [.1, .3, .2], ident, turn, [0.3, 0.2, 0.3 - eps], (0.01, 0.0))
            add([.2, .2, .1], [.1, .1, .1], ident, turn, [0.3 - eps, 0.3, 0.2 - eps])
            add([.2, .2, .2], [.2, .2, .2], _quat([0, 1, 0], np.pi / 4),
                _quat([1, 0, 0], np.pi / 4 + eps), [0, 0, 0.4 * r2 - eps])
            add([.2, .2, .2], [.2, .2, .2], _quat([0, 1, 0], np.pi / 4 + eps),
                _quat([0, 1, 0], np.pi / 4), [0.1, 0.0, 0.4 * r2 - eps])
            add([.2, .2, .1], [.2, .2, .1], _quat([0, 0, 1], eps), ident, [0.4, 0.0, 0.2])
            add([.2, .2, .1], [.2, .2, .1], ident, ident, [0, 0, 0.2 + eps], (eps, 0.0))
    rows = (rows * (N // len(rows) + 1))[:N]
    size, rbound, margin, qpos = (np.array(x) for x in zip(*rows, strict=True))
    return compare.Draws(size, rbound, margin, qpos, np.zeros(N))


def test_degenerate_poses_match_c(pm):
    counts = _check(pm, _degenerate_draws())
    assert counts[8] > 0 and counts[1] > 0 and counts[0] > 0


def _rotmat(axis, angle):
    axis = jnp.asarray(axis) / jnp.linalg.norm(jnp.asarray(axis))
    k = jnp.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]],
                   [-axis[1], axis[0], 0.0]])
    return jnp.eye(3) + jnp.sin(angle) * k + (1 - jnp.cos(angle)) * k @ k


_C = jnp.array([0.3, -0.7, 0.5])


def _objective(x, pose):
    """Sum over active contacts of dist + (pos + normal) . c; x = (geom2 pos (3,), angle)."""
    size1, size2, mat1, mat2, axis, margin = pose
    mat2 = _rotmat(axis, x[3]) @ mat2
    dist, pos, frame = box_box.box_box.pair_fn(
        GeomInfo(jnp.zeros(3), mat1, size1), GeomInfo(x[:3], mat2, size2), margin)
    active = dist < margin
    value = jnp.sum(jnp.where(active, dist + (pos + frame[:, 0]) @ _C, 0.0))
    return value, jnp.sum(active)


_value_and_grad = jax.jit(jax.value_and_grad(_objective, has_aux=True))


def _pose(s1, s2, mat1, p2, mat2, axis, margin=0.0):
    x = jnp.concatenate([jnp.asarray(p2, float), jnp.zeros(1)])
    return x, (jnp.asarray(s1, float), jnp.asarray(s2, float), jnp.asarray(mat1, float),
               jnp.asarray(mat2, float), jnp.asarray(axis, float), jnp.asarray(margin, float))


SMOOTH = {
    # box 1's face clips a tilted box 2 (clip intersections move with the pose)
    "face1": ([.3, .25, .1], [.2, .15, .1], jnp.eye(3), [.05, .02, .19],
              _rotmat([1, 2, 0.3], 0.05), [0.2, 1.0, 0.1], 0.0, 3),
    # equal plates turned by 0.7 rad: an 8-contact manifold in the margin band
    "octagon": ([.2, .2, .1], [.2, .2, .1], jnp.eye(3), [0.01, 0.02, .195],
                _rotmat([0, 0, 1], 0.7), [0.1, 0.2, 1.0], 0.01, 8),
    # box 2's face is the reference
    "face2": ([.05, .06, .07], [.4, .3, .2], _rotmat([1, 1, 1], 0.3), [0.02, 0.03, -0.26],
              jnp.eye(3), [1.0, 0.3, 0.2], 0.0, 3),
    # crossed edges
    "edge": ([.2, .2, .2], [.2, .15, .25], _rotmat([0, 1, 0], np.pi / 4 + 0.05),
             [0.03, 0.02, 0.55], _rotmat([1, 0, 0], np.pi / 4 + 0.1), [0.3, 0.2, 1.0], 0.0, 1),
}


@pytest.mark.parametrize("name", list(SMOOTH))
def test_gradient_matches_finite_differences(name):
    *args, count = SMOOTH[name]
    x, pose = _pose(*args)
    (_, active), grad = _value_and_grad(x, pose)
    assert int(active) == count
    eps = 1e-6
    fd = []
    for k in range(4):
        step = jnp.zeros(4).at[k].set(eps)
        (hi, _), _ = _value_and_grad(x + step, pose)
        (lo, _), _ = _value_and_grad(x - step, pose)
        fd.append((hi - lo) / (2 * eps))
    fd = np.array(fd)
    np.testing.assert_allclose(np.array(grad), fd, rtol=1e-5, atol=1e-5 * np.abs(fd).max())


DEGENERATE = {
    "stacked": ([.2, .2, .1], [.2, .2, .1], jnp.eye(3), [0, 0, 0.2], jnp.eye(3), [0, 0, 1]),
    "stacked_turned": ([.2, .2, .1], [.2, .2, .1], jnp.eye(3), [0, 0, 0.19],
                       _rotmat([0, 0, 1], np.pi / 2), [1, 0, 0]),
    "corner_to_corner": ([.2, .2, .1], [.2, .2, .1], jnp.eye(3), [0.4, 0.4, 0.2], jnp.eye(3),
                         [0, 1, 0]),
    "concentric": ([.2, .3, .1], [.1, .2, .3], jnp.eye(3), [0, 0, 0], jnp.eye(3), [1, 1, 1]),
    "parallel_edges": ([.2, .2, .2], [.2, .2, .2], _rotmat([1, 0, 0], np.pi / 4),
                       [0, 0, 0.4 * np.sqrt(2)], _rotmat([1, 0, 0], np.pi / 4), [1, 0, 0]),
    "separated": ([.2, .2, .1], [.2, .2, .1], jnp.eye(3), [0, 0, 0.5], jnp.eye(3), [0, 0, 1]),
}


@pytest.mark.parametrize("name", list(DEGENERATE))
def test_gradient_finite_on_degenerate_poses(name):
    x, pose = _pose(*DEGENERATE[name], margin=0.01)
    (value, _), grad = _value_and_grad(x, pose)
    assert np.isfinite(float(value))
    assert np.all(np.isfinite(np.array(grad))), grad
