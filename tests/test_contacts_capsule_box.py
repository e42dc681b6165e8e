"""The port of C's capsule-box collider (colliders.capsule_box) against C, and its gradients."""

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco.mjx._src.collision_types import GeomInfo

from mjstamp import colliders
from mjstamp.colliders import capsule_box, compare

CAPSULE = int(mujoco.mjtGeom.mjGEOM_CAPSULE)
BOX = int(mujoco.mjtGeom.mjGEOM_BOX)
TOL = 1e-9
# One batch size for the harness's comparisons: it compiles once per batch shape.
N = 300


@pytest.fixture(scope="module")
def pm():
    colliders.patch_collisions()
    return compare.pair_model(CAPSULE, BOX)


def _check(pm, draws):
    c = compare.c_contacts(pm, draws)
    report = compare.compare(pm, draws, c, compare.mjx_contacts(pm, draws))
    assert report.count_mismatches == 0, report
    assert max(report.dist, report.pos, report.normal, report.frame) <= TOL, report
    return np.bincount([len(a) for a in c], minlength=3)


def test_registered():
    assert colliders.PORTED[(CAPSULE, BOX)] is capsule_box.capsule_box
    # C's routine calls its sphere-box at most twice (mj_maxContact reserves 4).
    assert capsule_box.capsule_box.ncon == 2


def test_random_poses_match_c(pm):
    counts = _check(pm, compare.draw(pm, N, np.random.default_rng(0)))
    assert counts[1] > 0 and counts[2] > 0


def test_aligned_poses_match_c(pm):
    # every draw axis-aligned (multiples of 90 degrees), half of them with a margin
    draws = compare.draw(pm, N, np.random.default_rng(3), aligned_share=1.0, margin_share=0.5)
    assert _check(pm, draws)[2] > 0


@functools.cache
def _batched():
    def one(p1, m1, s1, p2, m2, s2, margin):
        pos, axis = capsule_box.box_frame(p1, m1, p2, m2)
        _, _, secondpos, best = capsule_box.segment_points(pos, axis, s1, s2, margin)
        out = capsule_box.capsule_box.pair_fn(GeomInfo(p1, m1, s1), GeomInfo(p2, m2, s2), margin)
        return best["cltype"], secondpos, out

    return jax.jit(jax.vmap(one))


def _lattice(pm, n, rng):
    """Sizes and offsets on a grid, orientations by 90 (some 45) degrees: exact ties."""
    m = pm.m
    grid = np.array([0.1, 0.2, 0.3])
    size, rbound = np.zeros((n, 2, 3)), np.zeros((n, 2))
    margin, qpos = rng.choice([0.0, 0.05], size=(n, 2)), np.zeros((n, m.nq))
    for i in range(n):
        s1, s2 = np.array([*rng.choice(grid, 2), 0.0]), rng.choice(grid, 3)
        size[i], rbound[i] = [s1, s2], [s1[0] + s1[1], np.linalg.norm(s2)]
        q = compare._aligned_quat(rng, 2)
        if i % 3 == 0:
            half = np.zeros(4)
            half[0], half[1 + i % 9 // 3] = np.cos(np.pi / 8), np.sin(np.pi / 8)
            mujoco.mju_mulQuat(q[0], q[0].copy(), half)
        qpos[i] = compare._qpos(m, q[0], q[1], rng.integers(-8, 9, size=3) * 0.05)
    return size, rbound, margin, qpos


def test_port_matches_c_on_exact_ties(pm):
    """C's own kinematics fed to the port: every contact C returns, in C's order.

    Stricter than the harness: excluded contacts count too and MJX's kinematics
    (which differ from C's in the last bits for non-axis-aligned turns) are out
    of the loop, so the port's ties and thresholds must fall exactly as C's on
    poses built to tie (N.B. this fails if XLA may fuse C's products into FMAs).
    """
    m, d = pm.m, mujoco.MjData(pm.m)
    size, rbound, margin, qpos = _lattice(pm, 600, np.random.default_rng(5))
    inputs, want = [], []
    for i in range(len(qpos)):
        compare._set_sizes(m, size[i], rbound[i], margin[i])
        d.qpos[:] = qpos[i]
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        want.append(np.array([[c.dist, *c.pos, *c.frame] for c in d.contact[: d.ncon]]))
        inputs.append((d.geom_xpos[0].copy(), d.geom_xmat[0].reshape(3, 3).copy(), size[i, 0],
                       d.geom_xpos[1].copy(), d.geom_xmat[1].reshape(3, 3).copy(), size[i, 1],
                       margin[i].sum()))
    args = [jnp.asarray(np.stack(a)) for a in zip(*inputs, strict=True)]
    cltype, secondpos, (dist, pos, frame) = jax.device_get(_batched()(*args))
    for i, c in enumerate(want):
        used = dist[i] < colliders.FAR
        got = np.concatenate([dist[i][:, None], pos[i], frame[i].reshape(-1, 9)], axis=1)[used]
        assert len(got) == len(c), (i, got[:, 0], c[:, :1])
        if len(c):
            np.testing.assert_allclose(got, c, rtol=0, atol=1e-12, err_msg=f"draw {i}")
    # every case of C's second point, taken and skipped: face, box corner, inside of an edge
    kind = np.where(cltype < 0, 0, np.where(cltype // 3 == 1, 1, 2))
    for k in range(3):
        assert (secondpos[kind == k] > -3).any() and (secondpos[kind == k] <= -3).any()


def _rot(axis, angle):
    axis = jnp.asarray(axis, float) / jnp.linalg.norm(jnp.asarray(axis, float))
    k = jnp.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return jnp.eye(3) + jnp.sin(angle) * k + (1 - jnp.cos(angle)) * k @ k


def _quat_mat(q):
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(q, float) / np.linalg.norm(q))
    return mat.reshape(3, 3)


C_POS = jnp.array([0.3, -0.7, 0.5])
C_FRAME = jnp.arange(9.0).reshape(3, 3) / 10


def _contacts(dp, angle, pose):
    """The port's contacts with the box moved by dp and turned by angle."""
    p1, m1, s1, p2, m2, s2, margin = pose
    box = GeomInfo(p2 + dp, _rot([0.2, 0.5, 1.0], angle) @ m2, s2)
    return capsule_box.capsule_box.pair_fn(GeomInfo(p1, m1, s1), box, margin)


def _objective(dp, angle, pose):
    """Sum of the active distances and of every slot's weighted position and frame.

    N.B. the unused slots' positions and frames enter too (with no effect on
    the poses of the finite-difference test, where both slots are active), so
    that their gradients must be finite on the degenerate poses as well.
    """
    dist, pos, frame = _contacts(dp, angle, pose)
    value = jnp.sum(jnp.where(dist < pose[-1], dist, 0.0)) + jnp.sum(pos @ C_POS)
    return value + jnp.sum(frame * C_FRAME), dist


# One compile for every test below: value (with the distances) and gradient.
_value_and_grad = jax.jit(jax.value_and_grad(_objective, argnums=(0, 1), has_aux=True))


S1 = jnp.array([0.05, 0.2, 0.0])
S2 = jnp.array([0.3, 0.2, 0.1])
MARGIN = 0.01


def _pose(p1, m1, p2=(0.0, 0.0, 0.0), m2=None, s1=S1, s2=S2, margin=MARGIN):
    m2 = jnp.eye(3) if m2 is None else m2
    return (jnp.asarray(p1, float), jnp.asarray(m1), s1, jnp.asarray(p2, float), m2, s2,
            jnp.asarray(margin))


# Two active contacts each, from the three kinds of closest feature.
SMOOTH = {
    "face": _pose([-0.27, 0.31, 0.23], _quat_mat([0.3, 0.96, -0.11, 0.42])),
    "edge": _pose([0.3, 0.0, 0.13], _rot([1, 0, 0], np.pi / 2 + 0.05) @ _rot([0, 1, 0], 0.4)),
    "corner": _pose([0.39, -0.19, 0.26], _quat_mat([-0.58, 0.53, 0.09, 1.59])),
}


@pytest.mark.parametrize("name", list(SMOOTH))
def test_gradient_matches_finite_differences(name):
    pose = SMOOTH[name]
    (_, dist), (gp, ga) = _value_and_grad(jnp.zeros(3), 0.0, pose)
    assert (dist < MARGIN).sum() == 2
    grad = np.append(np.asarray(gp), float(ga))
    eps = 1e-6
    fd = []
    for k in range(4):
        step = np.zeros(4)
        step[k] = eps
        (hi, _), _ = _value_and_grad(jnp.asarray(step[:3]), float(step[3]), pose)
        (lo, _), _ = _value_and_grad(jnp.asarray(-step[:3]), float(-step[3]), pose)
        fd.append((hi - lo) / (2 * eps))
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-8)
    assert np.abs(grad).max() > 0.1


def _rot_quat(direction):
    """Quaternion turning z onto `direction` (C's mju_quatZ2Vec)."""
    q = np.zeros(4)
    mujoco.mju_quatZ2Vec(q, np.asarray(direction, float))
    return q


_R90 = _rot([0, 1, 0], np.pi / 2)  # capsule axis along the box's x
DEGENERATE = {
    # lying flat on the top face: both ends tie, edges parallel to the axis (det = 0)
    "flat": _pose([0.0, 0.0, 0.14], _R90),
    # sphere centres exactly on the face (distance 0: normalize at zero)
    "touching": _pose([0.0, 0.0, 0.15], _R90),
    "on_face": _pose([0.0, 0.0, 0.1], _R90),
    # standing on the face's centre, along the box's z
    "upright": _pose([0.0, 0.0, 0.29], jnp.eye(3)),
    # centred in the box: every face ties
    "inside": _pose([0.0, 0.0, 0.0], jnp.eye(3), s2=jnp.array([0.3, 0.3, 0.3])),
    # along an edge of the box, on it
    "on_edge": _pose([0.0, 0.2, 0.1], _R90),
    # across an edge at 45 degrees
    "crossed": _pose([0.3, 0.0, 0.1], _rot([0, 0, 1], np.pi / 4) @ _R90),
    # pointing at a corner along the diagonal
    "at_corner": _pose([0.4, 0.3, 0.2], _quat_mat(_rot_quat([0.3, 0.2, 0.1]))),
    # parallel to a face, over its edge, half the capsule outside
    "overhang": _pose([0.3, 0.0, 0.14], _R90),
}


@pytest.mark.parametrize("name", list(DEGENERATE))
def test_gradients_finite_on_degenerate_poses(name):
    (value, dist), grads = _value_and_grad(jnp.zeros(3), 0.0, DEGENERATE[name])
    assert (dist < MARGIN).any()
    for leaf in jax.tree_util.tree_leaves((value, grads)):
        assert np.isfinite(np.asarray(leaf)).all()
