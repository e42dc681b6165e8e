"""MuJoCo C's general convex collisions in MJX (colliders.convex) against the C engine.

Each pair is collided by MuJoCo C (mj_collision) and by MJX with the ported
colliders on random poses (`compare.run`), and must give the same contacts:
the same number, and distance, position and frame within 1e-9. Gradients of a
smooth function of the contacts are checked against central differences, and
must stay finite on degenerate poses.

N.B. the GJK/EPA colliders are large programs: a cold compile takes one to two
minutes per pair (three for a gradient) on two cores, so those tests are marked
slow; JAX's persistent compilation cache (conftest) makes later runs fast.
"""

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco.mjx._src.collision_types import GeomInfo

from mjstamp import colliders
from mjstamp.colliders import ccd, compare, convex

GJK_PAIRS = ["capsule-cylinder", "cylinder-cylinder", "cylinder-box", "sphere-ellipsoid",
             "capsule-ellipsoid", "ellipsoid-ellipsoid", "ellipsoid-cylinder", "ellipsoid-box",
             "sphere-mesh", "capsule-mesh", "cylinder-mesh", "ellipsoid-mesh", "box-mesh",
             "mesh-mesh"]
# The default run compares these against C: GJK and EPA on a cylinder with the multi-contact
# rule (cylinder-box), a capsule shrunk to a segment (capsule-cylinder), the ellipsoid support
# (ellipsoid-ellipsoid) and a mesh's polygons (box-mesh). The other pairs, each a 1-2 min cold
# compile on two cores, are the exhaustive tier (`pytest -m exhaustive`).
DEFAULT_PAIRS = ["cylinder-box", "capsule-cylinder", "ellipsoid-ellipsoid", "box-mesh"]
TOL = 1e-9


def _pair_param(pair: str):
    """A parametrize entry: its own xdist group, exhaustive unless in DEFAULT_PAIRS."""
    marks = [pytest.mark.xdist_group(f"convex-vs-c-{pair}")]
    if pair not in DEFAULT_PAIRS:
        marks.append(pytest.mark.exhaustive)
    return pytest.param(pair, marks=marks, id=pair)


def _grouped(pair: str):
    """A parametrize entry grouped per pair under xdist (a pair's compiled program is shared)."""
    return pytest.param(pair, marks=pytest.mark.xdist_group(f"convex-{pair}"), id=pair)


@pytest.fixture(scope="module", autouse=True)
def _patched():
    colliders.patch_collisions()
    colliders.exact_meshes()
    yield
    colliders.exact_meshes(False)


def test_mesh_pairs_mjx_collides_keep_mjx_by_default():
    """sphere-, capsule-, box- and mesh-mesh: MJX's own unless exact_meshes (and reported so)."""
    from mujoco.mjx._src import collision_driver

    table = collision_driver._COLLISION_FUNC  # pylint: disable=protected-access
    opt_in = {(2, 7), (3, 7), (6, 7), (7, 7)}
    colliders.exact_meshes(False)
    try:
        before = colliders.table_version()
        for pair in opt_in:
            assert table[pair] is not colliders.PORTED[pair]
            assert not colliders.is_exact(*pair)
        for pair in ((5, 7), (4, 7), (0, 7), (5, 6)):  # MJX has none, or it is plane-mesh
            assert table[pair] is colliders.PORTED[pair] and colliders.is_exact(*pair)
    finally:
        colliders.exact_meshes()
    assert colliders.table_version() != before
    assert all(table[pair] is colliders.PORTED[pair] and colliders.is_exact(*pair)
               for pair in opt_in)


def _check(pair: str, n: int, seed: int) -> None:
    r = compare.run(*compare.parse_pair(pair), n, seed=seed)
    assert r.count_mismatches == 0, r
    assert max(r.dist, r.pos, r.normal, r.frame) <= TOL, r
    assert r.contacts_c > n // 2, r  # the draws do collide


def test_plane_mesh_matches_c():
    _check("plane-mesh", 300, seed=11)


@pytest.mark.slow
@pytest.mark.parametrize("pair", [_pair_param(p) for p in GJK_PAIRS])
def test_pair_matches_c(pair):
    _check(pair, 300, seed=12)


def test_contact_slots_follow_c():
    """Slots per pair are mj_maxContact's of the 3.17 binary (no margin dependence)."""
    for pair, ncon in {"cylinder-box": 4, "capsule-cylinder": 2, "capsule-mesh": 2,
                       "mesh-mesh": 4, "sphere-ellipsoid": 1, "ellipsoid-box": 1,
                       "plane-mesh": 4}.items():
        t1, t2 = compare.parse_pair(pair)
        m = compare.pair_model(t1, t2).m
        for has_margin in (0, 1):
            assert mujoco.mj_maxContact(m, 0, 1, has_margin) == ncon, pair
        assert colliders.PORTED[(t1, t2)].ncon == ncon, pair
    assert convex.max_contacts(5, 6, int(mujoco.mjtDisableBit.mjDSBL_MULTICCD)) == 1


def test_unregistered_mesh_is_an_error():
    """A mesh collider without C's polygons must refuse, not guess."""
    m = compare.pair_model(*compare.parse_pair("box-mesh")).m
    convex._MESHES.clear()  # pylint: disable=protected-access
    with pytest.raises(KeyError, match="register_model"):
        convex._mesh_of(m, 0)  # pylint: disable=protected-access
    convex.register_model(m)
    assert convex._mesh_of(m, 0).polynum > 0  # pylint: disable=protected-access


# ----------------------------------------------------------------------------- gradients

C_VEC = jnp.array([0.3, -0.7, 0.5])
AXIS = jnp.array([0.2, 0.9, -0.4]) / jnp.linalg.norm(jnp.array([0.2, 0.9, -0.4]))


def _rot(th):
    k = jnp.array([[0.0, -AXIS[2], AXIS[1]], [AXIS[2], 0.0, -AXIS[0]], [-AXIS[1], AXIS[0], 0.0]])
    return jnp.eye(3) + jnp.sin(th) * k + (1.0 - jnp.cos(th)) * (k @ k)


def _objective(pair_fn, k1, k2):
    """Sum over active contacts of dist + pos . c, as geom 2 moves by x[:3] and turns by x[3]."""

    def f(x, pos, mat, size, margin):
        i1 = GeomInfo(pos[0], mat[0].reshape(9), size[0])
        i2 = GeomInfo(pos[1] + x[:3], (_rot(x[3]) @ mat[1]).reshape(9), size[1])
        dist, cpos, _ = pair_fn(i1, i2, margin, k1=k1, k2=k2)
        active = jax.lax.stop_gradient(dist < margin)
        return jnp.sum(jnp.where(active, dist + cpos @ C_VEC, 0.0))

    return f


def _poses(pair: str, n: int, seed: int):
    pm = compare.pair_model(*compare.parse_pair(pair))
    dr = compare.draw(pm, n, np.random.default_rng(seed), aligned_share=0.0, miss_share=0.0)
    m, d = pm.m, mujoco.MjData(pm.m)
    out = []
    for i in range(n):
        compare._set_sizes(m, dr.size[i], dr.rbound[i], dr.margin[i])  # pylint: disable=protected-access
        d.qpos[:] = dr.qpos[i]
        mujoco.mj_kinematics(m, d)
        out.append((d.geom_xpos.copy(), d.geom_xmat.copy().reshape(2, 3, 3), m.geom_size.copy(),
                    float(dr.margin[i].sum())))
    return pm, out


# Every gradient check of a pair runs one compiled program: `_compiled` jits the vmapped
# value and derivative of `_objective` (or `_parts`) at BATCH poses; the central differences
# read its values at x0 +- eps, the gradient its derivative at x0, and the degenerate poses
# are padded to BATCH (cylinder-box's come from the program its gradient test compiled).
BATCH = 24


@functools.cache
def _compiled(pair: str, parts: bool):
    """jit(vmap(x, pose -> (value, derivative))) of the pair's objective, at any batch."""
    t1, t2 = compare.parse_pair(pair)
    pm = compare.pair_model(t1, t2)
    f = (_parts if parts else _objective)(colliders.PORTED[(t1, t2)].pair_fn,
                                          convex.kind_of(pm.m, 0), convex.kind_of(pm.m, 1))
    if parts:
        def value_and_derivative(*args):
            jac, value = jax.jacrev(lambda *a: (lambda y: (y, y))(f(*a)), has_aux=True)(*args)
            return value, jac
    else:
        value_and_derivative = jax.value_and_grad(f)
    return jax.jit(jax.vmap(value_and_derivative))


def _batch(poses):
    """Poses (pos, mat, size, margin) stacked along a leading axis, padded to BATCH."""
    assert 0 < len(poses) <= BATCH
    poses = list(poses) + [poses[-1]] * (BATCH - len(poses))
    return tuple(jnp.asarray(np.stack([np.asarray(p[i], np.float64) for p in poses]))
                 for i in range(4))


def _check_against_differences(pair: str, parts: bool) -> None:
    """Derivatives at x0 = 0 against central differences (eps 1e-6) on smooth pieces."""
    _, poses = _poses(pair, BATCH, seed=3)
    fn = _compiled(pair, parts)
    args = _batch(poses)
    x0 = jnp.zeros((BATCH, 4))
    _, D = (np.asarray(a) for a in fn(x0, *args))  # (B,) + (4,) or (3, 4)
    fd = []
    for eps in (1e-6, 2e-6):
        cols = []
        for k in range(4):
            e = jnp.zeros(4).at[k].set(eps)
            plus, _ = fn(x0 + e, *args)
            minus, _ = fn(x0 - e, *args)
            cols.append((np.asarray(plus) - np.asarray(minus)) / (2 * eps))
        fd.append(np.stack(cols, axis=-1))  # (B, 4) or (B, 3, 4)
    checked = 0
    for i in range(BATCH):
        assert np.all(np.isfinite(D[i]))
        scale = np.maximum(np.abs(fd[0][i]), 1e-2)
        if np.max(np.abs(fd[0][i] - fd[1][i]) / scale) > 1e-6:
            continue  # a discontinuity within eps (another EPA face, a clipped vertex)
        np.testing.assert_allclose(D[i], fd[0][i], rtol=1e-5, atol=1e-5 * scale.max())
        checked += 1
    assert checked >= 8


@pytest.mark.slow
# N.B. a GJK/EPA gradient takes about three minutes to compile on two cores: cylinder-box
# (GJK, EPA and the multi-contact rule) and capsule-cylinder (shrunk to a segment) cover the
# code paths; the degenerate poses reuse cylinder-box's compiled program (`_compiled`).
@pytest.mark.parametrize("pair", [_grouped("cylinder-box"), _grouped("capsule-cylinder")])
def test_gradients_match_central_differences(pair):
    """Reverse-mode gradients equal central differences (eps 1e-6) on smooth pieces.

    N.B. GJK and EPA stop on a tolerance (1e-6), so their output is piecewise
    smooth with pieces that can be narrower than eps: a pose is used only where
    central differences at eps and 2 eps agree (both within one piece).
    """
    _check_against_differences(pair, parts=False)


def _parts(pair_fn, k1, k2):
    """(distance, position . c, normal . c) summed over active contacts, as `_objective` moves."""

    def f(x, pos, mat, size, margin):
        i1 = GeomInfo(pos[0], mat[0].reshape(9), size[0])
        i2 = GeomInfo(pos[1] + x[:3], (_rot(x[3]) @ mat[1]).reshape(9), size[1])
        dist, cpos, frame = pair_fn(i1, i2, margin, k1=k1, k2=k2)
        active = jax.lax.stop_gradient(dist < margin)
        return jnp.stack([jnp.sum(jnp.where(active, v, 0.0))
                          for v in (dist, cpos @ C_VEC, frame[:, 0] @ C_VEC)])

    return f


@pytest.mark.slow
@pytest.mark.parametrize("pair", [_grouped("box-mesh"), _grouped("capsule-mesh")])
def test_converged_gradients_match_central_differences(pair):
    """`ccd.ccd_converged`'s rebuild: distance, position and normal each as C's differences.

    N.B. the sum `_objective` hides a wrong normal (it reads distances and
    positions only); a rebuild from material points alone missed positions and
    normals on cylinder-box poses by up to 100% (why cylinders keep `ccd.ccd`).
    """
    assert set(compare.parse_pair(pair)) <= ccd.CONVERGED_KINDS
    _check_against_differences(pair, parts=True)


def _aligned(pair):
    """Degenerate poses: parallel faces, coaxial, coincident centers, exactly touching."""
    size = np.array([[0.2, 0.1, 0.15], [0.2, 0.1, 0.15]])
    eye = np.eye(3)
    flip = np.diag([1.0, -1.0, -1.0])
    poses = []
    for p2, mat2 in ((np.array([0.0, 0.0, 0.15]), eye), (np.array([0.0, 0.0, 0.0]), eye),
                     (np.array([0.0, 0.0, 0.25]), flip), (np.array([0.1, 0.0, 0.2]), eye)):
        pos = np.stack([np.zeros(3), p2])
        poses.append((pos, np.stack([eye, mat2]), size, 0.0))
    return poses


@pytest.mark.slow
@pytest.mark.parametrize("pair", [_grouped("cylinder-box"), _grouped("ellipsoid-ellipsoid")])
def test_gradients_finite_on_degenerate_poses(pair):
    poses = _aligned(pair)
    _, grad = _compiled(pair, False)(jnp.zeros((BATCH, 4)), *_batch(poses))
    for i, pose in enumerate(poses):
        assert np.all(np.isfinite(np.asarray(grad[i]))), (pose, grad[i])
